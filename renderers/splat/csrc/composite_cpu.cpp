// CPU compositor of renderers.splat: the same image formation as composite.py, one pixel
// at a time with early termination, parallel over tiles (at::parallel_for / OpenMP).
//
// Forward:  per pixel, front to back over its tile's list:
//   alpha = min(alpha_max, o exp(power)); skip if alpha < alpha_min;
//   stop (without adding) if T (1 - alpha) < t_min; else w = alpha T, accumulate, T *= 1 - alpha.
// Backward: per pixel, pass 1 accumulates S = sum_kept w v (double); pass 2 walks the list
//   again and forms dL/dalpha = T v - (S - prefix_incl + T_final dL/dT) / (1 - alpha).
//   Gradients are written per tile-Gaussian pair (each pair belongs to one tile, so no two
//   threads write the same entry); Python scatters them to Gaussians with index_add_.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <vector>

namespace {

struct Grid {
  int64_t tiles_x, tiles_y, ts;
};

template <typename scalar_t>
struct TileData {
  // Gathered per-tile copies (structure of arrays) for locality.
  std::vector<scalar_t> mx, my, A, B, C, o, z, f;
  void load(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac, const scalar_t* feats,
            const scalar_t* depths, int64_t D, const int64_t* gids, int64_t s, int64_t e) {
    const int64_t n = e - s;
    mx.resize(n); my.resize(n); A.resize(n); B.resize(n); C.resize(n); o.resize(n); z.resize(n);
    f.resize(n * D);
    for (int64_t k = 0; k < n; ++k) {
      const int64_t g = gids[s + k];
      mx[k] = means2d[2 * g]; my[k] = means2d[2 * g + 1];
      A[k] = conics[3 * g]; B[k] = conics[3 * g + 1]; C[k] = conics[3 * g + 2];
      o[k] = opac[g]; z[k] = depths[g];
      for (int64_t d = 0; d < D; ++d) f[k * D + d] = feats[g * D + d];
    }
  }
};

template <typename scalar_t>
void forward_impl(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opac,
                  const torch::Tensor& feats, const torch::Tensor& depths, const torch::Tensor& gids,
                  const torch::Tensor& tstart, Grid grid, double amin_, double amax_, double tmin_,
                  torch::Tensor& out_feat, torch::Tensor& out_T, torch::Tensor& out_depth, torch::Tensor& out_wsq,
                  bool want_feat, bool want_depth, bool want_wsq) {
  const scalar_t amin = amin_, amax = amax_, tmin = tmin_;
  const int64_t D = feats.size(1), ts = grid.ts, area = ts * ts;
  const int64_t n_tiles = tstart.numel() - 1;
  const scalar_t* pm = means2d.data_ptr<scalar_t>();
  const scalar_t* pc = conics.data_ptr<scalar_t>();
  const scalar_t* po = opac.data_ptr<scalar_t>();
  const scalar_t* pf = feats.data_ptr<scalar_t>();
  const scalar_t* pz = depths.data_ptr<scalar_t>();
  const int64_t* pg = gids.data_ptr<int64_t>();
  const int64_t* pt = tstart.data_ptr<int64_t>();
  scalar_t* oF = want_feat ? out_feat.data_ptr<scalar_t>() : nullptr;
  scalar_t* oT = out_T.data_ptr<scalar_t>();
  scalar_t* oD = want_depth ? out_depth.data_ptr<scalar_t>() : nullptr;
  scalar_t* oW = want_wsq ? out_wsq.data_ptr<scalar_t>() : nullptr;

  at::parallel_for(0, n_tiles, 1, [&](int64_t t0, int64_t t1) {
    TileData<scalar_t> td;
    std::vector<scalar_t> acc(D);
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t s = pt[t], e = pt[t + 1];
      if (s == e) continue;
      td.load(pm, pc, po, pf, pz, D, pg, s, e);
      const int64_t n = e - s;
      const int64_t local = t % (grid.tiles_x * grid.tiles_y);
      const int64_t ty = local / grid.tiles_x, tx = local % grid.tiles_x;
      for (int64_t p = 0; p < area; ++p) {
        const scalar_t px = scalar_t(tx * ts + p % ts) + scalar_t(0.5);
        const scalar_t py = scalar_t(ty * ts + p / ts) + scalar_t(0.5);
        scalar_t T = 1, dep = 0, wsq = 0;
        std::fill(acc.begin(), acc.end(), scalar_t(0));
        for (int64_t k = 0; k < n; ++k) {
          const scalar_t dx = px - td.mx[k], dy = py - td.my[k];
          const scalar_t power = scalar_t(-0.5) * (td.A[k] * dx * dx + td.C[k] * dy * dy) - td.B[k] * dx * dy;
          scalar_t alpha = td.o[k] * std::exp(power);
          if (!(alpha < amax)) alpha = amax;
          if (alpha < amin) continue;
          const scalar_t nT = T * (1 - alpha);
          if (nT < tmin) break;
          const scalar_t w = alpha * T;
          for (int64_t d = 0; d < D; ++d) acc[d] += w * td.f[k * D + d];
          dep += w * td.z[k];
          wsq += w * w;
          T = nT;
        }
        const int64_t q = t * area + p;
        oT[q] = T;
        if (oF) for (int64_t d = 0; d < D; ++d) oF[q * D + d] = acc[d];
        if (oD) oD[q] = dep;
        if (oW) oW[q] = wsq;
      }
    }
  });
}

template <typename scalar_t>
void backward_impl(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opac,
                   const torch::Tensor& feats, const torch::Tensor& depths, const torch::Tensor& gids,
                   const torch::Tensor& tstart, Grid grid, double amin_, double amax_, double tmin_,
                   const torch::Tensor& g_feat, const torch::Tensor& g_T, const torch::Tensor& g_depth,
                   const torch::Tensor& g_wsq, torch::Tensor& pg_mean, torch::Tensor& pg_conic,
                   torch::Tensor& pg_opac, torch::Tensor& pg_feat, torch::Tensor& pg_depth) {
  const scalar_t amin = amin_, amax = amax_, tmin = tmin_;
  const int64_t D = feats.size(1), ts = grid.ts, area = ts * ts;
  const int64_t n_tiles = tstart.numel() - 1;
  const scalar_t* pm = means2d.data_ptr<scalar_t>();
  const scalar_t* pc = conics.data_ptr<scalar_t>();
  const scalar_t* po = opac.data_ptr<scalar_t>();
  const scalar_t* pf = feats.data_ptr<scalar_t>();
  const scalar_t* pz = depths.data_ptr<scalar_t>();
  const int64_t* pg = gids.data_ptr<int64_t>();
  const int64_t* pt = tstart.data_ptr<int64_t>();
  const scalar_t* gF = g_feat.numel() ? g_feat.data_ptr<scalar_t>() : nullptr;
  const scalar_t* gT = g_T.numel() ? g_T.data_ptr<scalar_t>() : nullptr;
  const scalar_t* gD = g_depth.numel() ? g_depth.data_ptr<scalar_t>() : nullptr;
  const scalar_t* gW = g_wsq.numel() ? g_wsq.data_ptr<scalar_t>() : nullptr;
  scalar_t* qM = pg_mean.data_ptr<scalar_t>();
  scalar_t* qC = pg_conic.data_ptr<scalar_t>();
  scalar_t* qO = pg_opac.data_ptr<scalar_t>();
  scalar_t* qF = pg_feat.data_ptr<scalar_t>();
  scalar_t* qZ = pg_depth.data_ptr<scalar_t>();

  at::parallel_for(0, n_tiles, 1, [&](int64_t t0, int64_t t1) {
    TileData<scalar_t> td;
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t s = pt[t], e = pt[t + 1];
      if (s == e) continue;
      td.load(pm, pc, po, pf, pz, D, pg, s, e);
      const int64_t n = e - s;
      const int64_t local = t % (grid.tiles_x * grid.tiles_y);
      const int64_t ty = local / grid.tiles_x, tx = local % grid.tiles_x;
      for (int64_t p = 0; p < area; ++p) {
        const int64_t q = t * area + p;
        const scalar_t px = scalar_t(tx * ts + p % ts) + scalar_t(0.5);
        const scalar_t py = scalar_t(ty * ts + p / ts) + scalar_t(0.5);
        const scalar_t gt = gT ? gT[q] : scalar_t(0);
        const scalar_t gd = gD ? gD[q] : scalar_t(0);
        const scalar_t gw = gW ? gW[q] : scalar_t(0);
        auto value = [&](int64_t k, scalar_t w) {
          scalar_t v = gd * td.z[k] + 2 * w * gw;
          if (gF) for (int64_t d = 0; d < D; ++d) v += gF[q * D + d] * td.f[k * D + d];
          return v;
        };
        // Pass 1: total of w v over kept Gaussians, final transmittance, end of the list.
        double S = 0;
        scalar_t T = 1;
        int64_t end = n;
        for (int64_t k = 0; k < n; ++k) {
          const scalar_t dx = px - td.mx[k], dy = py - td.my[k];
          const scalar_t power = scalar_t(-0.5) * (td.A[k] * dx * dx + td.C[k] * dy * dy) - td.B[k] * dx * dy;
          scalar_t alpha = td.o[k] * std::exp(power);
          if (!(alpha < amax)) alpha = amax;
          if (alpha < amin) continue;
          const scalar_t nT = T * (1 - alpha);
          if (nT < tmin) { end = k; break; }
          const scalar_t w = alpha * T;
          S += double(w) * double(value(k, w));
          T = nT;
        }
        const scalar_t T_final = T;
        // Pass 2: gradients per pair.
        double prefix = 0;
        T = 1;
        for (int64_t k = 0; k < end; ++k) {
          const scalar_t dx = px - td.mx[k], dy = py - td.my[k];
          const scalar_t power = scalar_t(-0.5) * (td.A[k] * dx * dx + td.C[k] * dy * dy) - td.B[k] * dx * dy;
          const scalar_t G = std::exp(power);
          const scalar_t raw = td.o[k] * G;
          const bool unclamped = raw < amax;
          const scalar_t alpha = unclamped ? raw : amax;
          if (alpha < amin) continue;
          const scalar_t w = alpha * T;
          const scalar_t v = value(k, w);
          prefix += double(w) * double(v);
          const int64_t pair = s + k;
          if (gF) for (int64_t d = 0; d < D; ++d) qF[pair * D + d] += w * gF[q * D + d];
          qZ[pair] += w * gd;
          if (unclamped) {
            const scalar_t behind = scalar_t(S - prefix);
            const scalar_t g_alpha = T * v - (behind + T_final * gt) / (1 - alpha);
            const scalar_t g_power = g_alpha * alpha;
            qO[pair] += g_alpha * G;
            qM[2 * pair] += (td.A[k] * dx + td.B[k] * dy) * g_power;
            qM[2 * pair + 1] += (td.B[k] * dx + td.C[k] * dy) * g_power;
            qC[3 * pair] += scalar_t(-0.5) * dx * dx * g_power;
            qC[3 * pair + 1] += -dx * dy * g_power;
            qC[3 * pair + 2] += scalar_t(-0.5) * dy * dy * g_power;
          }
          T = T * (1 - alpha);
        }
      }
    }
  });
}

void check(const torch::Tensor& x, const char* name) {
  TORCH_CHECK(x.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(x.is_contiguous(), name, " must be contiguous");
}

}  // namespace

std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                             torch::Tensor feats, torch::Tensor depths, torch::Tensor gids,
                                             torch::Tensor tstart, int64_t tiles_x, int64_t tiles_y, int64_t ts,
                                             double amin, double amax, double tmin, bool want_feat, bool want_depth,
                                             bool want_wsq) {
  for (auto* x : {&means2d, &conics, &opac, &feats, &depths, &gids, &tstart}) check(*x, "input");
  const int64_t n_tiles = tstart.numel() - 1, area = ts * ts, D = feats.size(1);
  auto opts = means2d.options();
  auto out_feat = want_feat ? torch::zeros({n_tiles, area, D}, opts) : torch::zeros({0}, opts);
  auto out_T = torch::ones({n_tiles, area}, opts);
  auto out_depth = want_depth ? torch::zeros({n_tiles, area}, opts) : torch::zeros({0}, opts);
  auto out_wsq = want_wsq ? torch::zeros({n_tiles, area}, opts) : torch::zeros({0}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    forward_impl<scalar_t>(means2d, conics, opac, feats, depths, gids, tstart, Grid{tiles_x, tiles_y, ts}, amin,
                           amax, tmin, out_feat, out_T, out_depth, out_wsq, want_feat, want_depth, want_wsq);
  });
  return {out_feat, out_T, out_depth, out_wsq};
}

std::vector<torch::Tensor> composite_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                              torch::Tensor feats, torch::Tensor depths, torch::Tensor gids,
                                              torch::Tensor tstart, int64_t tiles_x, int64_t tiles_y, int64_t ts,
                                              double amin, double amax, double tmin, torch::Tensor g_feat,
                                              torch::Tensor g_T, torch::Tensor g_depth, torch::Tensor g_wsq) {
  for (auto* x : {&means2d, &conics, &opac, &feats, &depths, &gids, &tstart, &g_feat, &g_T, &g_depth, &g_wsq})
    check(*x, "input");
  const int64_t P = gids.numel(), D = feats.size(1);
  auto opts = means2d.options();
  auto pg_mean = torch::zeros({P, 2}, opts);
  auto pg_conic = torch::zeros({P, 3}, opts);
  auto pg_opac = torch::zeros({P}, opts);
  auto pg_feat = torch::zeros({P, D}, opts);
  auto pg_depth = torch::zeros({P}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    backward_impl<scalar_t>(means2d, conics, opac, feats, depths, gids, tstart, Grid{tiles_x, tiles_y, ts}, amin,
                            amax, tmin, g_feat, g_T, g_depth, g_wsq, pg_mean, pg_conic, pg_opac, pg_feat, pg_depth);
  });
  return {pg_mean, pg_conic, pg_opac, pg_feat, pg_depth};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("composite_forward", &composite_forward, "Tiled front-to-back compositing (CPU)");
  m.def("composite_backward", &composite_backward, "Per-pair gradients of the compositor (CPU)");
}
