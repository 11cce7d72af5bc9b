// Two kernels of the empirical prior (gdbench.priors.empirical), which is not a renderer but
// shares this library.
//
// zoom_taps: separable resampling of image stacks, for gdbench.assets.zoom (the prior zooms its
// 360-view bank to each field of view it serves). out[v, y, x, c] =
// sum_k wx[x, k] sum_j wy[y, j] img[v, iy[y, j], ix[x, k], c]: the product A_y Y A_x^T of
// zoom.py with A's few non-zero entries per row given as taps (index, weight). Per image, rows
// first into a double buffer of w * C, then columns (one vector pass per tap); sums in double,
// one rounding at the end.
// The dense matrix products of the torch path read every source pixel once per target row
// (128 times); this reads each at most a few times.
//
// sqdist_rows: d[v] = sum_p (Y[v, p] - x[p])^2 in one pass over Y, each difference squared in
// the input's precision and summed in double (torch.cdist's direct mode errs by ~5e-6 relative at
// P = 12288; differences then a dot product need a [V, P] temporary, which the training loop
// pays for in page faults).
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <vector>

#include "splat_cpu.h"

namespace {

template <typename scalar_t>
void zoom_impl(const torch::Tensor& images, const torch::Tensor& iy, const torch::Tensor& wy,
               const torch::Tensor& ix, const torch::Tensor& wx, torch::Tensor& out) {
  const int64_t V = images.size(0), h = images.size(1), w = images.size(2), C = images.size(3);
  const int64_t H = iy.size(0), Ky = iy.size(1), W = ix.size(0), Kx = ix.size(1), row = w * C, orow = W * C;
  const scalar_t* src = images.data_ptr<scalar_t>();
  const int64_t* py = iy.data_ptr<int64_t>();
  const int64_t* px = ix.data_ptr<int64_t>();
  const double* qy = wy.data_ptr<double>();
  const double* qx = wx.data_ptr<double>();
  scalar_t* dst = out.data_ptr<scalar_t>();
  // The column taps laid out per output entry o = x C + c, one table per tap k: the source entry
  // (px[x, k] C + c) and its weight. Each output is then 0 + t_0 + t_1 + ... in tap order, the
  // sum the scalar loop formed, but as Kx vector passes over the row (gathers) instead of a loop
  // of Kx dependent steps per entry.
  std::vector<int32_t> gi(Kx * orow);
  std::vector<double> gw(Kx * orow);
  for (int64_t k = 0; k < Kx; ++k)
    for (int64_t x = 0; x < W; ++x)
      for (int64_t c = 0; c < C; ++c) {
        gi[k * orow + x * C + c] = int32_t(px[x * Kx + k] * C + c);
        gw[k * orow + x * C + c] = qx[x * Kx + k];
      }
  at::parallel_for(0, V, 1, [&](int64_t v0, int64_t v1) {
    std::vector<double> acc(row), sum(orow);
    double* pa = acc.data();
    double* ps = sum.data();
    for (int64_t v = v0; v < v1; ++v) {
      for (int64_t y = 0; y < H; ++y) {
        std::fill(acc.begin(), acc.end(), 0.0);
        for (int64_t j = 0; j < Ky; ++j) {
          const double a = qy[y * Ky + j];
          if (a == 0) continue;
          const scalar_t* s = src + (v * h + py[y * Ky + j]) * row;
#pragma omp simd
          for (int64_t i = 0; i < row; ++i) pa[i] += a * double(s[i]);
        }
        std::fill(sum.begin(), sum.end(), 0.0);
        for (int64_t k = 0; k < Kx; ++k) {
          const int32_t* g = gi.data() + k * orow;
          const double* q = gw.data() + k * orow;
#pragma omp simd
          for (int64_t o = 0; o < orow; ++o) ps[o] += q[o] * pa[g[o]];
        }
        scalar_t* o = dst + (v * H + y) * orow;
#pragma omp simd
        for (int64_t i = 0; i < orow; ++i) o[i] = scalar_t(ps[i]);
      }
    }
  });
}

void check_taps(const char* name, const torch::Tensor& idx, const torch::Tensor& wt, int64_t n_in) {
  TORCH_CHECK(idx.dim() == 2 && idx.scalar_type() == torch::kInt64 && idx.is_contiguous(), name,
              ": expected a contiguous int64 [n_out, K] index tensor");
  TORCH_CHECK(wt.sizes() == idx.sizes() && wt.scalar_type() == torch::kFloat64 && wt.is_contiguous(), name,
              ": expected contiguous float64 weights of the indices' shape");
  if (idx.numel()) {
    TORCH_CHECK(idx.min().item<int64_t>() >= 0 && idx.max().item<int64_t>() < n_in, name,
                ": indices must lie in [0, ", n_in, ")");
  }
}

template <typename scalar_t>
void sqdist_impl(const scalar_t* px, const scalar_t* py, int64_t V, int64_t P, int64_t rs, double* o) {
  at::parallel_for(0, V, 4, [&](int64_t v0, int64_t v1) {
    constexpr int64_t kLanes = 16;  // independent partial sums: the loop vectorises without reassociation
    for (int64_t v = v0; v < v1; ++v) {
      const scalar_t* y = py + v * rs;
      double acc[kLanes] = {};
      int64_t p = 0;
      for (; p + kLanes <= P; p += kLanes) {
#pragma omp simd
        for (int64_t j = 0; j < kLanes; ++j) {
          const scalar_t d = y[p + j] - px[p + j];
          acc[j] += double(d * d);
        }
      }
      double s = 0;
      for (int64_t j = 0; j < kLanes; ++j) s += acc[j];
      for (; p < P; ++p) {
        const scalar_t d = y[p] - px[p];
        s += double(d * d);
      }
      o[v] = s;
    }
  });
}

}  // namespace

torch::Tensor zoom_taps(const torch::Tensor& images, const torch::Tensor& iy, const torch::Tensor& wy,
                        const torch::Tensor& ix, const torch::Tensor& wx) {
  TORCH_CHECK(images.dim() == 4 && images.is_contiguous() && images.device().is_cpu(),
              "images: expected a contiguous CPU tensor [V, h, w, C]");
  TORCH_CHECK(images.scalar_type() == torch::kFloat32 || images.scalar_type() == torch::kFloat64,
              "images: expected float32 or float64");
  check_taps("iy", iy, wy, images.size(1));
  check_taps("ix", ix, wx, images.size(2));
  TORCH_CHECK(images.size(2) * images.size(3) <= INT32_MAX, "images: rows of at most 2^31 - 1 values (w * C)");
  auto out = torch::empty({images.size(0), iy.size(0), ix.size(0), images.size(3)}, images.options());
  AT_DISPATCH_FLOATING_TYPES(images.scalar_type(), "zoom_taps", [&] { zoom_impl<scalar_t>(images, iy, wy, ix, wx, out); });
  return out;
}

torch::Tensor sqdist_rows(const torch::Tensor& x, const torch::Tensor& Y) {
  TORCH_CHECK(Y.dim() == 2 && Y.device().is_cpu() && Y.stride(1) == 1,
              "Y: expected a CPU tensor [V, P] with contiguous rows");
  TORCH_CHECK(Y.scalar_type() == torch::kFloat32 || Y.scalar_type() == torch::kFloat64, "Y: expected float32 or float64");
  TORCH_CHECK(x.dim() == 1 && x.is_contiguous() && x.scalar_type() == Y.scalar_type() && x.size(0) == Y.size(1),
              "x: expected a contiguous [P] tensor of Y's dtype");
  auto out = torch::empty({Y.size(0)}, Y.options().dtype(torch::kFloat64));
  AT_DISPATCH_FLOATING_TYPES(Y.scalar_type(), "sqdist_rows", [&] {
    sqdist_impl<scalar_t>(x.data_ptr<scalar_t>(), Y.data_ptr<scalar_t>(), Y.size(0), Y.size(1), Y.stride(0),
                          out.data_ptr<double>());
  });
  return out;
}
