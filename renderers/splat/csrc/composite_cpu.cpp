// CPU compositor of renderers.splat: the same image formation as composite.py, parallel over
// tiles (at::parallel_for / OpenMP). Within a tile the loop runs Gaussian-outer, pixel-inner:
// each Gaussian visits only the pixels of its own box (the exact bounding box of the ellipse
// where o exp(power) >= alpha_min, plus a margin), and each pixel keeps its own transmittance
// and a "done" flag, so every pixel still sees its Gaussians front to back and stops exactly
// where the sequential kernel would:
//   alpha = min(alpha_max, o exp(power)); skip if alpha < alpha_min;
//   stop (without adding) if T (1 - alpha) < t_min; else w = alpha T, accumulate, T *= 1 - alpha.
// Backward: pass 1 accumulates S = sum_kept w v per pixel (double); pass 2 walks again and forms
//   dL/dalpha = T v - (S - prefix_incl + T_final dL/dT) / (1 - alpha).
// Gradients are written per tile-Gaussian pair (each pair belongs to one tile, so no two threads
// write the same entry); Python scatters them to Gaussians with index_add_.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "splat_cpu.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

struct Grid {
  int64_t tiles_x, tiles_y, ts;
};

template <typename scalar_t>
struct TileData {
  std::vector<scalar_t> mx, my, A, B, C, o, z, f, cut;
  std::vector<int32_t> x0, x1, y0, y1;  // tile-local pixel box, inclusive; x0 > x1 when empty

  void load(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac, const scalar_t* feats,
            const scalar_t* depths, int64_t D, const int64_t* gids, int64_t s, int64_t e, double amin,
            double ox, double oy, int64_t ts) {
    const int64_t n = e - s;
    for (auto* v : {&mx, &my, &A, &B, &C, &o, &z, &cut}) v->resize(n);
    for (auto* v : {&x0, &x1, &y0, &y1}) v->resize(n);
    f.resize(n * D);
    for (int64_t k = 0; k < n; ++k) {
      const int64_t g = gids[s + k];
      mx[k] = means2d[2 * g]; my[k] = means2d[2 * g + 1];
      A[k] = conics[3 * g]; B[k] = conics[3 * g + 1]; C[k] = conics[3 * g + 2];
      o[k] = opac[g]; z[k] = depths[g];
      for (int64_t d = 0; d < D; ++d) f[k * D + d] = feats[g * D + d];
      // alpha >= alpha_min  <=>  power >= ln(alpha_min / o). The reject threshold keeps a margin
      // of 1e-3 in power, and the box is the exact box of {q(d) <= 2 ln(o/alpha_min) + 2e-3}
      // (q = d^T conic d), so every pixel the exact test could accept is visited.
      const double oo = double(o[k]);
      if (!(oo > 0) || oo < amin * std::exp(-1e-3)) {
        cut[k] = 0; x0[k] = 1; x1[k] = 0; y0[k] = 1; y1[k] = 0;
        continue;
      }
      cut[k] = scalar_t(std::log(amin / oo) - 1e-3);
      const double L = 2.0 * std::log(oo / amin) + 2e-3;
      const double a = A[k], b = B[k], c = C[k];
      const double det = a * c - b * b;
      if (!(det > 0) || !std::isfinite(det)) {
        x0[k] = 0; x1[k] = int32_t(ts - 1); y0[k] = 0; y1[k] = int32_t(ts - 1);
        continue;
      }
      const double ex = std::sqrt(L * c / det) * (1 + 1e-6) + 1e-4;
      const double ey = std::sqrt(L * a / det) * (1 + 1e-6) + 1e-4;
      // pixel centre i + 0.5 (tile-local) within [m - e, m + e]
      const double cx = double(mx[k]) - ox - 0.5, cy = double(my[k]) - oy - 0.5;
      auto clampi = [&](double v) { return int32_t(std::min<double>(std::max<double>(v, -1.0), double(ts))); };
      x0[k] = std::max(0, clampi(std::ceil(cx - ex)));
      x1[k] = std::min(int32_t(ts - 1), clampi(std::floor(cx + ex)));
      y0[k] = std::max(0, clampi(std::ceil(cy - ey)));
      y1[k] = std::min(int32_t(ts - 1), clampi(std::floor(cy + ey)));
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
    std::vector<scalar_t> T(area), acc(area * D), dep(area), wsq(area);
    std::vector<char> done(area);
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t s = pt[t], e = pt[t + 1];
      if (s == e) continue;
      const int64_t local = t % (grid.tiles_x * grid.tiles_y);
      const int64_t ty = local / grid.tiles_x, tx = local % grid.tiles_x;
      const double ox = double(tx * ts), oy = double(ty * ts);
      td.load(pm, pc, po, pf, pz, D, pg, s, e, amin_, ox, oy, ts);
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(acc.begin(), acc.end(), scalar_t(0));
      std::fill(dep.begin(), dep.end(), scalar_t(0));
      std::fill(wsq.begin(), wsq.end(), scalar_t(0));
      std::fill(done.begin(), done.end(), char(0));
      int64_t n_done = 0;
      for (int64_t k = 0; k < e - s && n_done < area; ++k) {
        for (int32_t iy = td.y0[k]; iy <= td.y1[k]; ++iy) {
          const scalar_t dy = scalar_t(oy + iy) + scalar_t(0.5) - td.my[k];
          for (int32_t ix = td.x0[k]; ix <= td.x1[k]; ++ix) {
            const int64_t p = int64_t(iy) * ts + ix;
            if (done[p]) continue;
            const scalar_t dx = scalar_t(ox + ix) + scalar_t(0.5) - td.mx[k];
            const scalar_t power = scalar_t(-0.5) * (td.A[k] * dx * dx + td.C[k] * dy * dy) - td.B[k] * dx * dy;
            if (power < td.cut[k]) continue;
            scalar_t alpha = td.o[k] * std::exp(power);
            if (!(alpha < amax)) alpha = amax;
            if (alpha < amin) continue;
            const scalar_t nT = T[p] * (1 - alpha);
            if (nT < tmin) { done[p] = 1; ++n_done; continue; }
            const scalar_t w = alpha * T[p];
            for (int64_t d = 0; d < D; ++d) acc[p * D + d] += w * td.f[k * D + d];
            dep[p] += w * td.z[k];
            wsq[p] += w * w;
            T[p] = nT;
          }
        }
      }
      for (int64_t p = 0; p < area; ++p) {
        const int64_t q = t * area + p;
        oT[q] = T[p];
        if (oF) for (int64_t d = 0; d < D; ++d) oF[q * D + d] = acc[p * D + d];
        if (oD) oD[q] = dep[p];
        if (oW) oW[q] = wsq[p];
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
    std::vector<scalar_t> T(area), T_final(area);
    std::vector<double> S(area), prefix(area);
    std::vector<char> done(area);
    std::vector<scalar_t> gf_sum(D);
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t s = pt[t], e = pt[t + 1];
      if (s == e) continue;
      const int64_t local = t % (grid.tiles_x * grid.tiles_y);
      const int64_t ty = local / grid.tiles_x, tx = local % grid.tiles_x;
      const double ox = double(tx * ts), oy = double(ty * ts);
      td.load(pm, pc, po, pf, pz, D, pg, s, e, amin_, ox, oy, ts);
      const int64_t n = e - s;
      // v = dL/dfeat . c + dL/ddepth z + 2 w dL/dweight_sq
      auto value = [&](int64_t k, int64_t q, scalar_t w) {
        scalar_t v = (gD ? gD[q] * td.z[k] : scalar_t(0)) + (gW ? 2 * w * gW[q] : scalar_t(0));
        if (gF) for (int64_t d = 0; d < D; ++d) v += gF[q * D + d] * td.f[k * D + d];
        return v;
      };
      // Pass 1: per pixel, total of w v over kept Gaussians and the final transmittance.
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(S.begin(), S.end(), 0.0);
      std::fill(done.begin(), done.end(), char(0));
      int64_t n_done = 0;
      for (int64_t k = 0; k < n && n_done < area; ++k) {
        for (int32_t iy = td.y0[k]; iy <= td.y1[k]; ++iy) {
          const scalar_t dy = scalar_t(oy + iy) + scalar_t(0.5) - td.my[k];
          for (int32_t ix = td.x0[k]; ix <= td.x1[k]; ++ix) {
            const int64_t p = int64_t(iy) * ts + ix;
            if (done[p]) continue;
            const scalar_t dx = scalar_t(ox + ix) + scalar_t(0.5) - td.mx[k];
            const scalar_t power = scalar_t(-0.5) * (td.A[k] * dx * dx + td.C[k] * dy * dy) - td.B[k] * dx * dy;
            if (power < td.cut[k]) continue;
            scalar_t alpha = td.o[k] * std::exp(power);
            if (!(alpha < amax)) alpha = amax;
            if (alpha < amin) continue;
            const scalar_t nT = T[p] * (1 - alpha);
            if (nT < tmin) { done[p] = 1; ++n_done; continue; }
            const scalar_t w = alpha * T[p];
            S[p] += double(w) * double(value(k, t * area + p, w));
            T[p] = nT;
          }
        }
      }
      std::copy(T.begin(), T.end(), T_final.begin());
      // Pass 2: gradients per pair, summed over the Gaussian's pixels.
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(prefix.begin(), prefix.end(), 0.0);
      std::fill(done.begin(), done.end(), char(0));
      n_done = 0;
      for (int64_t k = 0; k < n && n_done < area; ++k) {
        scalar_t go = 0, gmx = 0, gmy = 0, gA = 0, gB = 0, gC = 0, gz = 0;
        std::fill(gf_sum.begin(), gf_sum.end(), scalar_t(0));
        for (int32_t iy = td.y0[k]; iy <= td.y1[k]; ++iy) {
          const scalar_t dy = scalar_t(oy + iy) + scalar_t(0.5) - td.my[k];
          for (int32_t ix = td.x0[k]; ix <= td.x1[k]; ++ix) {
            const int64_t p = int64_t(iy) * ts + ix;
            if (done[p]) continue;
            const scalar_t dx = scalar_t(ox + ix) + scalar_t(0.5) - td.mx[k];
            const scalar_t power = scalar_t(-0.5) * (td.A[k] * dx * dx + td.C[k] * dy * dy) - td.B[k] * dx * dy;
            if (power < td.cut[k]) continue;
            const scalar_t G = std::exp(power);
            const scalar_t raw = td.o[k] * G;
            const bool unclamped = raw < amax;
            const scalar_t alpha = unclamped ? raw : amax;
            if (alpha < amin) continue;
            const scalar_t nT = T[p] * (1 - alpha);
            if (nT < tmin) { done[p] = 1; ++n_done; continue; }
            const int64_t q = t * area + p;
            const scalar_t w = alpha * T[p];
            const scalar_t v = value(k, q, w);
            prefix[p] += double(w) * double(v);
            if (gF) for (int64_t d = 0; d < D; ++d) gf_sum[d] += w * gF[q * D + d];
            if (gD) gz += w * gD[q];
            if (unclamped) {
              const scalar_t behind = scalar_t(S[p] - prefix[p]);
              const scalar_t gt = gT ? gT[q] : scalar_t(0);
              const scalar_t g_alpha = T[p] * v - (behind + T_final[p] * gt) / (1 - alpha);
              const scalar_t g_power = g_alpha * alpha;
              go += g_alpha * G;
              gmx += (td.A[k] * dx + td.B[k] * dy) * g_power;
              gmy += (td.B[k] * dx + td.C[k] * dy) * g_power;
              gA += scalar_t(-0.5) * dx * dx * g_power;
              gB += -dx * dy * g_power;
              gC += scalar_t(-0.5) * dy * dy * g_power;
            }
            T[p] = nT;
          }
        }
        const int64_t pair = s + k;
        qO[pair] = go;
        qM[2 * pair] = gmx; qM[2 * pair + 1] = gmy;
        qC[3 * pair] = gA; qC[3 * pair + 1] = gB; qC[3 * pair + 2] = gC;
        qZ[pair] = gz;
        for (int64_t d = 0; d < D; ++d) qF[pair * D + d] = gf_sum[d];
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
  // Every pair visited by pass 2 writes its entries; pairs never reached (after all pixels of
  // the tile stopped) keep zeros.
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
  m.def("project_forward", &project_forward, "EWA projection, radii and culling (CPU)");
  m.def("project_backward", &project_backward, "Gradients of the projection (CPU)");
  m.def("bin_tiles", &bin_tiles, "Tile lists in depth order (CPU)");
}
