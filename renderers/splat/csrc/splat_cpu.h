// Entry points of the CPU extension of renderers.splat defined in project_cpu.cpp, sh_cpu.cpp
// bank_cpu.cpp, normal_cpu.cpp and noise_cpu.cpp (composite_cpu.cpp holds the compositor and the Python bindings).
#pragma once
#include <torch/extension.h>

#include <vector>

std::vector<torch::Tensor> project_forward(const torch::Tensor& means, const torch::Tensor& quats,
                                           const torch::Tensor& scales, const torch::Tensor& opac,
                                           const torch::Tensor& viewmats, const torch::Tensor& Ks, int64_t width,
                                           int64_t height, double near_plane, double far_plane, double eps2d,
                                           double alpha_min);

std::vector<torch::Tensor> project_backward(const torch::Tensor& means, const torch::Tensor& quats,
                                            const torch::Tensor& scales, const torch::Tensor& viewmats,
                                            const torch::Tensor& Ks, int64_t width, int64_t height,
                                            double near_plane, double far_plane, double eps2d, double alpha_min,
                                            const torch::Tensor& g_m2d, const torch::Tensor& g_con,
                                            const torch::Tensor& g_dep);

std::vector<torch::Tensor> bin_tiles(const torch::Tensor& m2d, const torch::Tensor& rad, const torch::Tensor& dep,
                                     const torch::Tensor& vis, int64_t I, int64_t N, int64_t width, int64_t height,
                                     int64_t tile_size);

torch::Tensor sh_forward(int64_t degree, const torch::Tensor& coeffs, const torch::Tensor& dirs);

torch::Tensor zoom_taps(const torch::Tensor& images, const torch::Tensor& iy, const torch::Tensor& wy,
                        const torch::Tensor& ix, const torch::Tensor& wx);

torch::Tensor sqdist_rows(const torch::Tensor& x, const torch::Tensor& Y);

torch::Tensor philox_normal(int64_t n, int64_t seed);
std::vector<int64_t> philox4x32(std::vector<int64_t> counter, std::vector<int64_t> key);
torch::Tensor normal_parts(const torch::Tensor& u, int64_t which);

std::vector<torch::Tensor> noise_finish(const torch::Tensor& feat, const torch::Tensor& wsq,
                                        const torch::Tensor& iid, int64_t tiles_x, int64_t tiles_y, int64_t ts,
                                        int64_t height, int64_t width, double v_min);
