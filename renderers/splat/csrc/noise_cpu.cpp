// The last pass of structured noise (gdbench.noise.NoiseRenderer): from the compositor's sums in
// tile layout to the unit-variance noise image in one pass, instead of laying features and
// weights out as images and normalising them in a chain of small torch operations. Per pixel u
// with V(u) = sum_i w_i^2:
//   covered = V >= v_min  (V > 0 when v_min is not positive, NaN included)
//   n(u)    = feat(u) / sqrt(V(u))  where covered, else the iid draw at u
// in the scalar type of the inputs (float: v_min rounded to float, as torch compares a float
// tensor with a Python number). The square roots are at::sqrt's, over the tile layout: torch's
// CPU sqrt is not the correctly rounded one (MKL's vector math, within an ulp) but a function of
// the value alone, so the same call gives the bits torch.sqrt gives on the images; the quotient
// is IEEE's, as torch's. The same bits as the torch chain (tests/test_noise.py holds them to it).
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cstdint>
#include <vector>

#include "splat_cpu.h"

namespace {

template <typename scalar_t>
void finish_impl(const scalar_t* feat, const scalar_t* wsq, const scalar_t* root, const scalar_t* iid, scalar_t* out, scalar_t* cover,
                 int64_t I, int64_t H, int64_t W, int64_t D, int64_t tiles_x, int64_t tiles_y, int64_t ts,
                 scalar_t v_min, bool strict) {
  const int64_t area = ts * ts, per_image = tiles_x * tiles_y;
  at::parallel_for(0, I * H, 32, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {  // one row of one image
      const int64_t img = r / H, y = r % H;
      const int64_t row_tiles = img * per_image + (y / ts) * tiles_x, py = (y % ts) * ts;
      for (int64_t x = 0; x < W; ++x) {
        const int64_t q = (row_tiles + x / ts) * area + py + x % ts, o = r * W + x;
        const scalar_t v = wsq[q];
        const bool covered = strict ? v > scalar_t(0) : v >= v_min;
        const scalar_t s = root[q];
        for (int64_t d = 0; d < D; ++d) out[o * D + d] = covered ? feat[q * D + d] / s : iid[o * D + d];
        cover[o] = covered ? scalar_t(1) : scalar_t(0);
      }
    }
  });
}

}  // namespace

std::vector<torch::Tensor> noise_finish(const torch::Tensor& feat, const torch::Tensor& wsq,
                                        const torch::Tensor& iid, int64_t tiles_x, int64_t tiles_y, int64_t ts,
                                        int64_t height, int64_t width, double v_min) {
  TORCH_CHECK(feat.dim() == 3 && wsq.dim() == 2, "noise_finish: expected feat [T, area, D] and wsq [T, area]");
  const int64_t T = feat.size(0), D = feat.size(2), per_image = tiles_x * tiles_y;
  TORCH_CHECK(per_image > 0 && T % per_image == 0 && feat.size(1) == ts * ts && wsq.size(0) == T &&
                  wsq.size(1) == ts * ts && height <= tiles_y * ts && width <= tiles_x * ts,
              "noise_finish: tile outputs do not match the grid");
  const int64_t I = T / per_image;
  TORCH_CHECK(iid.numel() == I * height * width * D, "noise_finish: iid: expected ", I * height * width * D,
              " values, got ", iid.numel());
  for (const auto* x : {&feat, &wsq, &iid}) {
    TORCH_CHECK(x->device().is_cpu() && x->is_contiguous() && x->scalar_type() == feat.scalar_type(),
                "noise_finish: expected contiguous CPU tensors of one dtype");
  }
  auto out = torch::empty({I, height, width, D}, feat.options());
  auto cover = torch::empty({I, height, width, 1}, feat.options());
  const auto root = at::sqrt(wsq);
  AT_DISPATCH_FLOATING_TYPES(feat.scalar_type(), "noise_finish", [&] {
    finish_impl<scalar_t>(feat.data_ptr<scalar_t>(), wsq.data_ptr<scalar_t>(), root.data_ptr<scalar_t>(),
                          iid.data_ptr<scalar_t>(),
                          out.data_ptr<scalar_t>(), cover.data_ptr<scalar_t>(), I, height, width, D, tiles_x,
                          tiles_y, ts, scalar_t(v_min), !(v_min > 0));
  });
  return {out, cover};
}
