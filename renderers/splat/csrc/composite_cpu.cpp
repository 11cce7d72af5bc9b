// CPU compositor of renderers.splat: the same image formation as composite.py, parallel over
// tiles (at::parallel_for / OpenMP). Within a tile the loop runs Gaussian-outer, pixel-inner:
// each Gaussian visits only the pixels of its own box (the exact bounding box of the ellipse
// where o exp(power) >= alpha_min, plus a margin), and each pixel keeps its own transmittance
// and the index where it stopped, so every pixel still sees its Gaussians front to back and stops
// exactly where the sequential kernel would:
//   alpha = min(alpha_max, o exp(power)); skip if alpha < alpha_min;
//   stop (without adding) if T (1 - alpha) < t_min; else w = alpha T, accumulate, T *= 1 - alpha.
// The forward records, per pixel, the list index where it stopped ("last"). The backward is one
// pass back to front from T_final and "last": T before Gaussian i is T after it / (1 - alpha_i),
// S (the sum of w v behind i, double) grows as it goes, and
//   dL/dalpha_i = T_i v_i - (S + T_final dL/dT_final) / (1 - alpha_i).
// One visitor (walk) holds the pixel loop of both. Gradients are written per tile-Gaussian pair
// (each pair belongs to one tile, so no two threads write the same entry); Python scatters them
// to Gaussians with index_add_.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "splat_cpu.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
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

// exp(x) for the kernel's range (x in [-80, 0]: power >= cut > -10 where it is used; lower
// inputs are clamped, their results unused), written so the compiler vectorises it over a row:
// x = n ln2 + r with n = round(x / ln2) (the 1.5 * 2^m rounding trick), |r| <= ln2/2, exp(r) by
// its Taylor series to the precision of the type (degree 7 for float: 2e-8 relative; degree 13
// for double: 4e-18), times 2^n by building the exponent bits. Checked against std::exp to 2
// ulp in float and 4 ulp in double over the range (tests/test_composite.py, through fast_exp).
template <typename T>
struct Exp;

template <>
struct Exp<float> {
  static inline float eval(float x) {
    x = x < -80.0f ? -80.0f : x;
    const float shift = 12582912.0f;  // 1.5 * 2^23
    const float t = x * 1.44269504088896341f + shift;
    const float n = t - shift;
    const float r = (x - n * 0.693145751953125f) - n * 1.42860682030941723e-06f;
    float p = 1.0f / 5040.0f;
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    const int32_t bits = (int32_t(n) + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
  }
};

template <>
struct Exp<double> {
  static inline double eval(double x) {
    x = x < -700.0 ? -700.0 : x;
    const double shift = 6755399441055744.0;  // 1.5 * 2^52
    const double t = x * 1.4426950408889634 + shift;
    const double n = t - shift;
    const double r = (x - n * 0.6931471803691238) - n * 1.9082149292705877e-10;
    double p = 1.0 / 6227020800.0;
    const double c[] = {1.0 / 479001600.0, 1.0 / 39916800.0, 1.0 / 3628800.0, 1.0 / 362880.0, 1.0 / 40320.0,
                        1.0 / 5040.0,      1.0 / 720.0,      1.0 / 120.0,     1.0 / 24.0,     1.0 / 6.0,
                        0.5,               1.0,              1.0};
    for (double ci : c) p = p * r + ci;
    const int64_t bits = (int64_t(n) + 1023) << 52;
    double scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
  }
};

// The pixels of Gaussian k's box in the tile whose power clears the Gaussian's cut, with
// f(p, dx, dy, power, G = exp(power)) called for each (p: tile-local pixel index). Rows where
// row_live(iy) is false (every pixel of the row has stopped, or lies in front of k's turn) are
// skipped; each other row's powers and exponentials are computed in one vectorisable loop first.
template <typename scalar_t, typename R, typename F>
inline void walk(const TileData<scalar_t>& td, int64_t k, double ox, double oy, int64_t ts, R&& row_live, F&& f) {
  constexpr int64_t kRow = 64;
  scalar_t pw[kRow], G[kRow];
  const int32_t x0 = td.x0[k], x1 = td.x1[k];
  const scalar_t A = td.A[k], B = td.B[k], C = td.C[k], mx = td.mx[k], cut = td.cut[k];
  for (int32_t iy = td.y0[k]; iy <= td.y1[k]; ++iy) {
    if (!row_live(iy)) continue;
    const scalar_t dy = scalar_t(oy + iy) + scalar_t(0.5) - td.my[k];
    for (int32_t c0 = x0; c0 <= x1; c0 += int32_t(kRow)) {
      const int32_t c1 = std::min<int32_t>(x1, c0 + int32_t(kRow) - 1);
      const int32_t m = c1 - c0 + 1;
      for (int32_t j = 0; j < m; ++j) {
        const scalar_t dx = scalar_t(ox + (c0 + j)) + scalar_t(0.5) - mx;
        pw[j] = scalar_t(-0.5) * (A * dx * dx + C * dy * dy) - B * dx * dy;
        G[j] = Exp<scalar_t>::eval(pw[j]);
      }
      for (int32_t j = 0; j < m; ++j) {
        if (pw[j] < cut) continue;
        const int32_t ix = c0 + j;
        f(int64_t(iy) * ts + ix, scalar_t(ox + ix) + scalar_t(0.5) - mx, dy, pw[j], G[j]);
      }
    }
  }
}

struct TileIndex {
  int64_t s, e;
  double ox, oy;
};

inline TileIndex tile_index(const int64_t* pt, int64_t t, const Grid& grid) {
  const int64_t local = t % (grid.tiles_x * grid.tiles_y);
  const int64_t ty = local / grid.tiles_x, tx = local % grid.tiles_x;
  return {pt[t], pt[t + 1], double(tx * grid.ts), double(ty * grid.ts)};
}

template <typename scalar_t>
void forward_impl(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opac,
                  const torch::Tensor& feats, const torch::Tensor& depths, const torch::Tensor& gids,
                  const torch::Tensor& tstart, Grid grid, double amin_, double amax_, double tmin_,
                  torch::Tensor& out_feat, torch::Tensor& out_T, torch::Tensor& out_depth, torch::Tensor& out_wsq,
                  torch::Tensor& out_last, bool want_feat, bool want_depth, bool want_wsq) {
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
  int32_t* oL = out_last.data_ptr<int32_t>();

  at::parallel_for(0, n_tiles, 1, [&](int64_t t0, int64_t t1) {
    TileData<scalar_t> td;
    std::vector<scalar_t> T(area), acc(area * D), dep(area), wsq(area);
    std::vector<int32_t> last(area), live(ts);
    for (int64_t t = t0; t < t1; ++t) {
      const TileIndex ti = tile_index(pt, t, grid);
      const int64_t n = ti.e - ti.s;
      if (n == 0) continue;
      td.load(pm, pc, po, pf, pz, D, pg, ti.s, ti.e, amin_, ti.ox, ti.oy, ts);
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(acc.begin(), acc.end(), scalar_t(0));
      std::fill(dep.begin(), dep.end(), scalar_t(0));
      std::fill(wsq.begin(), wsq.end(), scalar_t(0));
      std::fill(last.begin(), last.end(), int32_t(n));
      std::fill(live.begin(), live.end(), int32_t(ts));  // pixels of each row still compositing
      int64_t n_done = 0;
      auto row_live = [&](int32_t iy) { return live[iy] > 0; };
      for (int64_t k = 0; k < n && n_done < area; ++k) {
        walk(td, k, ti.ox, ti.oy, ts, row_live, [&](int64_t p, scalar_t, scalar_t, scalar_t, scalar_t G) {
          if (last[p] < n) return;  // stopped
          scalar_t alpha = td.o[k] * G;
          if (!(alpha < amax)) alpha = amax;
          if (alpha < amin) return;
          const scalar_t nT = T[p] * (1 - alpha);
          if (nT < tmin) { last[p] = int32_t(k); ++n_done; --live[p / ts]; return; }
          const scalar_t w = alpha * T[p];
          for (int64_t d = 0; d < D; ++d) acc[p * D + d] += w * td.f[k * D + d];
          dep[p] += w * td.z[k];
          wsq[p] += w * w;
          T[p] = nT;
        });
      }
      for (int64_t p = 0; p < area; ++p) {
        const int64_t q = t * area + p;
        oT[q] = T[p];
        oL[q] = last[p];
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
                   const torch::Tensor& T_final, const torch::Tensor& last_idx, const torch::Tensor& g_feat,
                   const torch::Tensor& g_T, const torch::Tensor& g_depth, const torch::Tensor& g_wsq,
                   torch::Tensor& pg_mean, torch::Tensor& pg_conic, torch::Tensor& pg_opac, torch::Tensor& pg_feat,
                   torch::Tensor& pg_depth) {
  const scalar_t amin = amin_, amax = amax_;
  (void)tmin_;
  const int64_t D = feats.size(1), ts = grid.ts, area = ts * ts;
  const int64_t n_tiles = tstart.numel() - 1;
  const scalar_t* pm = means2d.data_ptr<scalar_t>();
  const scalar_t* pc = conics.data_ptr<scalar_t>();
  const scalar_t* po = opac.data_ptr<scalar_t>();
  const scalar_t* pf = feats.data_ptr<scalar_t>();
  const scalar_t* pz = depths.data_ptr<scalar_t>();
  const int64_t* pg = gids.data_ptr<int64_t>();
  const int64_t* pt = tstart.data_ptr<int64_t>();
  const scalar_t* pTf = T_final.data_ptr<scalar_t>();
  const int32_t* pL = last_idx.data_ptr<int32_t>();
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
    std::vector<scalar_t> T(area);
    std::vector<double> S(area);
    std::vector<scalar_t> gf_sum(D);
    std::vector<int32_t> row_last(ts);
    for (int64_t t = t0; t < t1; ++t) {
      const TileIndex ti = tile_index(pt, t, grid);
      const int64_t n = ti.e - ti.s;
      if (n == 0) continue;
      td.load(pm, pc, po, pf, pz, D, pg, ti.s, ti.e, amin_, ti.ox, ti.oy, ts);
      const int64_t base = t * area;
      int32_t deepest = 0;  // Gaussians at or behind every pixel's stop contribute nothing
      std::fill(row_last.begin(), row_last.end(), int32_t(0));
      for (int64_t p = 0; p < area; ++p) {
        T[p] = pTf[base + p];
        S[p] = 0.0;
        deepest = std::max(deepest, pL[base + p]);
        row_last[p / ts] = std::max(row_last[p / ts], pL[base + p]);
      }
      for (int64_t k = std::min<int64_t>(n, deepest) - 1; k >= 0; --k) {
        scalar_t go = 0, gmx = 0, gmy = 0, gA = 0, gB = 0, gC = 0, gz = 0;
        std::fill(gf_sum.begin(), gf_sum.end(), scalar_t(0));
        auto row_live = [&](int32_t iy) { return k < row_last[iy]; };
        walk(td, k, ti.ox, ti.oy, ts, row_live, [&](int64_t p, scalar_t dx, scalar_t dy, scalar_t, scalar_t G) {
          if (k >= pL[base + p]) return;  // behind this pixel's stop
          const scalar_t raw = td.o[k] * G;
          const bool unclamped = raw < amax;
          const scalar_t alpha = unclamped ? raw : amax;
          if (alpha < amin) return;
          const int64_t q = base + p;
          const scalar_t Tb = T[p] / (1 - alpha);  // transmittance in front of k
          const scalar_t w = alpha * Tb;
          scalar_t v = (gD ? gD[q] * td.z[k] : scalar_t(0)) + (gW ? 2 * w * gW[q] : scalar_t(0));
          if (gF) for (int64_t d = 0; d < D; ++d) v += gF[q * D + d] * td.f[k * D + d];
          if (gF) for (int64_t d = 0; d < D; ++d) gf_sum[d] += w * gF[q * D + d];
          if (gD) gz += w * gD[q];
          if (unclamped) {
            const scalar_t gt = gT ? gT[q] : scalar_t(0);
            const scalar_t g_alpha = Tb * v - (scalar_t(S[p]) + pTf[q] * gt) / (1 - alpha);
            const scalar_t g_power = g_alpha * alpha;
            go += g_alpha * G;
            gmx += (td.A[k] * dx + td.B[k] * dy) * g_power;
            gmy += (td.B[k] * dx + td.C[k] * dy) * g_power;
            gA += scalar_t(-0.5) * dx * dx * g_power;
            gB += -dx * dy * g_power;
            gC += scalar_t(-0.5) * dy * dy * g_power;
          }
          S[p] += double(w) * double(v);
          T[p] = Tb;
        });
        const int64_t pair = ti.s + k;
        qO[pair] = go;
        qM[2 * pair] = gmx; qM[2 * pair + 1] = gmy;
        qC[3 * pair] = gA; qC[3 * pair + 1] = gB; qC[3 * pair + 2] = gC;
        qZ[pair] = gz;
        for (int64_t d = 0; d < D; ++d) qF[pair * D + d] = gf_sum[d];
      }
    }
  });
}

torch::Tensor fast_exp(torch::Tensor x) {
  x = x.contiguous();
  auto out = torch::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "fast_exp", [&] {
    const scalar_t* px = x.data_ptr<scalar_t>();
    scalar_t* po = out.data_ptr<scalar_t>();
    for (int64_t i = 0; i < x.numel(); ++i) po[i] = Exp<scalar_t>::eval(px[i]);
  });
  return out;
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
  auto out_last = torch::zeros({n_tiles, area}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    forward_impl<scalar_t>(means2d, conics, opac, feats, depths, gids, tstart, Grid{tiles_x, tiles_y, ts}, amin,
                           amax, tmin, out_feat, out_T, out_depth, out_wsq, out_last, want_feat, want_depth,
                           want_wsq);
  });
  return {out_feat, out_T, out_depth, out_wsq, out_last};
}

std::vector<torch::Tensor> composite_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                              torch::Tensor feats, torch::Tensor depths, torch::Tensor gids,
                                              torch::Tensor tstart, int64_t tiles_x, int64_t tiles_y, int64_t ts,
                                              double amin, double amax, double tmin, torch::Tensor T_final,
                                              torch::Tensor last_idx, torch::Tensor g_feat, torch::Tensor g_T,
                                              torch::Tensor g_depth, torch::Tensor g_wsq) {
  for (auto* x : {&means2d, &conics, &opac, &feats, &depths, &gids, &tstart, &T_final, &last_idx, &g_feat, &g_T,
                  &g_depth, &g_wsq})
    check(*x, "input");
  const int64_t P = gids.numel(), D = feats.size(1);
  auto opts = means2d.options();
  // Every pair the backward visits writes its entries; pairs behind every pixel's stop keep zeros.
  auto pg_mean = torch::zeros({P, 2}, opts);
  auto pg_conic = torch::zeros({P, 3}, opts);
  auto pg_opac = torch::zeros({P}, opts);
  auto pg_feat = torch::zeros({P, D}, opts);
  auto pg_depth = torch::zeros({P}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    backward_impl<scalar_t>(means2d, conics, opac, feats, depths, gids, tstart, Grid{tiles_x, tiles_y, ts}, amin,
                            amax, tmin, T_final, last_idx, g_feat, g_T, g_depth, g_wsq, pg_mean, pg_conic, pg_opac,
                            pg_feat, pg_depth);
  });
  return {pg_mean, pg_conic, pg_opac, pg_feat, pg_depth};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("composite_forward", &composite_forward, "Tiled front-to-back compositing (CPU)");
  m.def("composite_backward", &composite_backward, "Per-pair gradients of the compositor, one pass (CPU)");
  m.def("project_forward", &project_forward, "EWA projection, radii and culling (CPU)");
  m.def("project_backward", &project_backward, "Gradients of the projection (CPU)");
  m.def("bin_tiles", &bin_tiles, "Tile lists in depth order (CPU)");
  m.def("fast_exp", &fast_exp, "The compositor's exp on [-80, 0] (for tests)");
}
