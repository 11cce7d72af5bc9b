// SH colour of renderers.splat on CPU, forward only (the no-gradient path; with gradients the
// torch eval_sh of sh.py runs): colour = max(0, sum_k Y_k(d) f_k + 0.5) with the basis of sh.py,
// its products in the same order, fused per (camera, Gaussian) instead of ~50 full-size torch
// operations and a [N, K, D] temporary.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>

#include "splat_cpu.h"

namespace {

// C0..C3 of sh.py
constexpr double kC0 = 0.28209479177387814, kC1 = 0.4886025119029199;
constexpr double kC2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                           0.5462742152960396};
constexpr double kC3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                           -0.4570457994644658, 1.445305721320277,  -0.5900435899266435};

template <typename T>
int basis(int degree, T x, T y, T z, T* Y) {
  Y[0] = T(kC0);
  if (degree < 1) return 1;
  Y[1] = T(-kC1) * y; Y[2] = T(kC1) * z; Y[3] = T(-kC1) * x;
  if (degree < 2) return 4;
  const T xx = x * x, yy = y * y, zz = z * z;
  Y[4] = T(kC2[0]) * x * y;
  Y[5] = T(kC2[1]) * y * z;
  Y[6] = T(kC2[2]) * (T(2) * zz - xx - yy);
  Y[7] = T(kC2[3]) * x * z;
  Y[8] = T(kC2[4]) * (xx - yy);
  if (degree < 3) return 9;
  Y[9] = T(kC3[0]) * y * (T(3) * xx - yy);
  Y[10] = T(kC3[1]) * x * y * z;
  Y[11] = T(kC3[2]) * y * (T(4) * zz - xx - yy);
  Y[12] = T(kC3[3]) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  Y[13] = T(kC3[4]) * x * (T(4) * zz - xx - yy);
  Y[14] = T(kC3[5]) * z * (xx - yy);
  Y[15] = T(kC3[6]) * x * (xx - T(3) * yy);
  return 16;
}

}  // namespace

torch::Tensor sh_forward(int64_t degree, const torch::Tensor& coeffs, const torch::Tensor& dirs) {
  TORCH_CHECK(degree >= 0 && degree <= 3, "degree must be 0..3");
  TORCH_CHECK(coeffs.dim() == 4 && dirs.dim() == 4 && dirs.size(3) == 3, "coeffs [B, N, K, D], dirs [B, C, N, 3]");
  TORCH_CHECK(coeffs.device().is_cpu() && dirs.device().is_cpu(), "CPU tensors");
  TORCH_CHECK(coeffs.is_contiguous() && dirs.is_contiguous() && coeffs.dtype() == dirs.dtype(), "contiguous, one dtype");
  const int64_t B = coeffs.size(0), N = coeffs.size(1), K = coeffs.size(2), D = coeffs.size(3), C = dirs.size(1);
  TORCH_CHECK(dirs.size(0) == B && dirs.size(2) == N && K >= (degree + 1) * (degree + 1), "shapes");
  auto out = torch::empty({B, C, N, D}, coeffs.options());
  AT_DISPATCH_FLOATING_TYPES(coeffs.scalar_type(), "sh_forward", [&] {
    const scalar_t* pc = coeffs.data_ptr<scalar_t>();
    const scalar_t* pd = dirs.data_ptr<scalar_t>();
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, B * C * N, 4096, [&](int64_t i0, int64_t i1) {
      scalar_t Y[16];
      for (int64_t i = i0; i < i1; ++i) {
        const int64_t b = i / (C * N), n = i % N;
        const int nk = basis<scalar_t>(int(degree), pd[3 * i], pd[3 * i + 1], pd[3 * i + 2], Y);
        const scalar_t* f = pc + (b * N + n) * K * D;
        for (int64_t d = 0; d < D; ++d) {
          scalar_t acc = 0;
          for (int k = 0; k < nk; ++k) acc += Y[k] * f[k * D + d];
          po[i * D + d] = std::max(acc + scalar_t(0.5), scalar_t(0));
        }
      }
    });
  });
  return out;
}
