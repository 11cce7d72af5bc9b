// CPU compositor of renderers.splat: the same image formation as composite.py, parallel over
// tiles (at::parallel_for / OpenMP). Within a tile the loop runs Gaussian-outer, pixel-inner:
// each Gaussian visits only the pixels of its own ellipse where o exp(power) >= alpha_min (per
// row its exact span, plus a margin, within the ellipse's box), and each pixel keeps its own transmittance
// and the index where it stopped, so every pixel still sees its Gaussians front to back and stops
// exactly where the sequential kernel would:
//   alpha = min(alpha_max, o exp(power)); skip if alpha < alpha_min;
//   stop (without adding) if T (1 - alpha) < t_min; else w = alpha T, accumulate, T *= 1 - alpha.
// The forward records, per pixel, the list index where it stopped ("last"). The backward is one
// pass back to front from T_final and "last": T before Gaussian i is T after it / (1 - alpha_i),
// S (the sum of w v behind i, double) grows as it goes, and
//   dL/dalpha_i = T_i v_i - (S + T_final dL/dT_final) / (1 - alpha_i).
// One visitor (walk) holds the pixel loop of both: it hands the row segments of a Gaussian's
// ellipse in the tile, with their powers and exponentials, to a segment kernel (branch-free and
// vectorised for runs of 8 pixels or more in the forward). The backward sums gradients per
// Gaussian in one buffer per chunk of tiles and adds the chunks in order.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "fast_exp.h"
#include "splat_cpu.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

namespace {

struct Grid {
  int64_t tiles_x, tiles_y, ts;
};

// Per Gaussian, once per call (not once per tile pair): the opacity cut, the half-extents of its
// box and the row-span terms. alpha >= alpha_min  <=>  power >= ln(alpha_min / o). The reject
// threshold keeps a margin of 1e-3 in power, and the box is the exact box of
// {q(d) <= 2 ln(o/alpha_min) + 2e-3} (q = d^T conic d), so every pixel the exact test could
// accept is visited. ex < 0: nothing to visit; ex = inf (degenerate conic): the whole tile.
template <typename scalar_t>
struct Shapes {
  struct Shape {  // one record per Gaussian: a tile pair's set-up reads one cache line
    double ex, ey, ALs, det, invA, BinvA;
    scalar_t cut;
  };
  std::vector<Shape> of;

  Shapes(const scalar_t* conics, const scalar_t* opac, int64_t G, double amin) : of(G) {
    const double floor_o = amin * std::exp(-1e-3);
    at::parallel_for(0, G, 4096, [&](int64_t g0, int64_t g1) {
      for (int64_t g = g0; g < g1; ++g) {
        Shape& r = of[g];
        const double o = opac[g];
        r = Shape{-1, 0, 0, 0, 0, 0, scalar_t(0)};
        if (!(o > 0) || o < floor_o) continue;
        const double lg = std::log(amin / o);
        r.cut = scalar_t(lg - 1e-3);
        const double L = -2.0 * lg + 2e-3;  // 2 ln(o / alpha_min) + 2e-3, to an ulp (the box has margins)
        const double a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
        const double dt = a * c - b * b;
        // Row spans (walk) solve q(d) <= Ls per row. Float rounding of the power is at most a few
        // ulp of |A dx^2| + |C dy^2| + |2 B dx dy| <= 2 q / (1 - |b| / sqrt(ac)); where that factor
        // is below 2000 (det / ac >= 1e-3) the error is under 1e-3 q, and Ls = 1.01 L covers it
        // ten times over. Needle-thin ellipses keep the box's full rows.
        const bool span = dt > 0 && a > 0 && dt >= 1e-3 * a * c && std::isfinite(dt);
        r.ALs = span ? a * 1.01 * L : 0.0;
        r.det = dt; r.invA = span ? 1.0 / a : 0.0; r.BinvA = span ? b / a : 0.0;
        if (!(dt > 0) || !std::isfinite(dt)) {
          r.ex = std::numeric_limits<double>::infinity();
          continue;
        }
        r.ex = std::sqrt(L * c / dt) * (1 + 1e-6) + 1e-4;
        r.ey = std::sqrt(L * a / dt) * (1 + 1e-6) + 1e-4;
      }
    });
  }
};

template <typename scalar_t>
struct TileData {
  std::vector<scalar_t> mx, my, A, B, C, o, z, f, cut;
  std::vector<int32_t> x0, x1, y0, y1;  // tile-local pixel box, inclusive; x0 > x1 when empty
  std::vector<double> ALs, det, invA, BinvA;  // row spans (walk); ALs = 0: none, full box rows

  // Entries [k0, k1) of the tile's n pairs (list entries s + k); k0 = 0 sizes the arrays. The
  // callers load only what they reach: the forward in blocks until every pixel has stopped, the
  // backward up to the deepest stop.
  void load(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac, const scalar_t* feats,
            const scalar_t* depths, int64_t D, const Shapes<scalar_t>& sh, const int64_t* gids, int64_t s,
            int64_t n, int64_t k0, int64_t k1, double ox, double oy, int64_t ts) {
    if (k0 == 0) {
      for (auto* v : {&mx, &my, &A, &B, &C, &o, &z, &cut}) v->resize(n);
      for (auto* v : {&x0, &x1, &y0, &y1}) v->resize(n);
      for (auto* v : {&ALs, &det, &invA, &BinvA}) v->resize(n);
      f.resize(n * D);
    }
    const int32_t last = int32_t(ts - 1);
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t g = gids[s + k];
      mx[k] = means2d[2 * g]; my[k] = means2d[2 * g + 1];
      A[k] = conics[3 * g]; B[k] = conics[3 * g + 1]; C[k] = conics[3 * g + 2];
      o[k] = opac[g]; z[k] = depths[g];
      for (int64_t d = 0; d < D; ++d) f[k * D + d] = feats[g * D + d];
      const auto& r = sh.of[g];
      cut[k] = r.cut; ALs[k] = r.ALs; det[k] = r.det; invA[k] = r.invA; BinvA[k] = r.BinvA;
      const double ex = r.ex, ey = r.ey;
      if (ex < 0) {
        x0[k] = 1; x1[k] = 0; y0[k] = 1; y1[k] = 0;
        continue;
      }
      if (std::isinf(ex)) {
        x0[k] = 0; x1[k] = last; y0[k] = 0; y1[k] = last;
        continue;
      }
      // pixel centre i + 0.5 (tile-local) within [m - e, m + e]
      const double cx = double(mx[k]) - ox - 0.5, cy = double(my[k]) - oy - 0.5;
      auto clampi = [&](double v) { return int32_t(std::min<double>(std::max<double>(v, -1.0), double(ts))); };
      x0[k] = std::max(0, clampi(std::ceil(cx - ex)));
      x1[k] = std::min(last, clampi(std::floor(cx + ex)));
      y0[k] = std::max(0, clampi(std::ceil(cy - ey)));
      y1[k] = std::min(last, clampi(std::floor(cy + ey)));
    }
  }
};

// The pixels of Gaussian k's box in the tile, handed to seg row segment by row segment: for
// each row where row_live(iy) (some pixel of the row is still compositing, or lies in front of
// k's stop) and each run of at most kRow pixels, the arrays dx, power and G = exp(power) are
// computed in one vectorisable loop, then seg(p0, m, dx, dy, power, G, iy) (p0: tile-local index
// of the run's first pixel) decides, per pixel, whether power clears the Gaussian's cut.
constexpr int32_t kRow = 64;
constexpr int64_t kLoad = 64;  // the forward loads a tile's pairs in blocks of this many
constexpr int32_t kVec = 8;  // runs at least this long take the compositor's vectorised path

template <typename scalar_t, typename R, typename F>
inline void walk(const TileData<scalar_t>& td, int64_t k, double ox, double oy, int64_t ts, R&& row_live, F&& seg) {
  alignas(64) scalar_t dxs[kRow], pw[kRow], G[kRow];
  const scalar_t A = td.A[k], B = td.B[k], C = td.C[k], mx = td.mx[k];
  const double ALs = td.ALs[k], det = td.det[k], ia = td.invA[k], ba = td.BinvA[k], cx = double(mx) - ox - 0.5;
  for (int32_t iy = td.y0[k]; iy <= td.y1[k]; ++iy) {
    if (!row_live(iy)) continue;
    const scalar_t dy = scalar_t(oy + iy) + scalar_t(0.5) - td.my[k];
    int32_t x0 = td.x0[k], x1 = td.x1[k];
    if (ALs > 0) {  // the row's exact span of q(d) <= Ls: A dx^2 + 2 B dy dx + C dy^2 - Ls <= 0
      const double dyd = oy + iy + 0.5 - double(td.my[k]), disc = ALs - det * dyd * dyd;
      if (disc < 0) continue;
      const double r = std::sqrt(disc) * ia, mid = cx - ba * dyd;
      x0 = std::max<int32_t>(x0, int32_t(std::max(-1.0, std::ceil(mid - r))));
      x1 = std::min<int32_t>(x1, int32_t(std::min(double(ts), std::floor(mid + r))));
    }
    for (int32_t c0 = x0; c0 <= x1; c0 += kRow) {
      const int32_t m = std::min<int32_t>(x1, c0 + kRow - 1) - c0 + 1;
      // whole vectors of 8: the entries past m are computed and never read (no scalar tail)
      for (int32_t jb = 0; jb < m; jb += 8) {
#pragma omp simd
        for (int32_t j = jb; j < jb + 8; ++j) {
          const scalar_t dx = scalar_t(ox + (c0 + j)) + scalar_t(0.5) - mx;
          dxs[j] = dx;
          pw[j] = scalar_t(-0.5) * (A * dx * dx + C * dy * dy) - B * dx * dy;
          G[j] = Exp<scalar_t>::eval(pw[j]);
        }
      }
      seg(int64_t(iy) * ts + c0, m, dxs, dy, pw, G, iy);
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

  const Shapes<scalar_t> shapes(pc, po, means2d.size(0), amin_);
  at::parallel_for(0, n_tiles, 1, [&](int64_t t0, int64_t t1) {
    TileData<scalar_t> td;
    // per-tile buffers, features channel-major ([D][area]) so that a row segment is contiguous
    // padded by one vector: the vectorised path runs whole vectors of 8 past a run's end, where
    // it writes back what it read (features: channel stride sa)
    const int64_t sa = area + 8;
    std::vector<scalar_t> T(sa), acc(sa * D), dep(sa), wsq(sa);
    std::vector<int32_t> last(sa), live(ts);
    alignas(64) scalar_t wv[kRow];
    for (int64_t t = t0; t < t1; ++t) {
      const TileIndex ti = tile_index(pt, t, grid);
      const int64_t n = ti.e - ti.s;  // empty tiles too: every output entry is written here
      int64_t loaded = 0;
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(acc.begin(), acc.end(), scalar_t(0));
      std::fill(dep.begin(), dep.end(), scalar_t(0));
      std::fill(wsq.begin(), wsq.end(), scalar_t(0));
      std::fill(last.begin(), last.end(), int32_t(n));
      std::fill(live.begin(), live.end(), int32_t(ts));  // pixels of each row still compositing
      int64_t n_done = 0;
      auto row_live = [&](int32_t iy) { return live[iy] > 0; };
      for (int64_t k = 0; k < n && n_done < area; ++k) {
        if (k == loaded) {
          loaded = std::min<int64_t>(n, loaded + kLoad);
          td.load(pm, pc, po, pf, pz, D, shapes, pg, ti.s, n, k, loaded, ti.ox, ti.oy, ts);
        }
        const scalar_t o = td.o[k], cut = td.cut[k], z = td.z[k];
        const int32_t kk = int32_t(k), nn = int32_t(n);
        walk(td, k, ti.ox, ti.oy, ts, row_live,
             [&](int64_t p0, int32_t m, const scalar_t*, scalar_t, const scalar_t* pw, const scalar_t* G, int32_t iy) {
          // branch-free over the segment (the compiler vectorises it): a pixel that has stopped,
          // or where alpha < alpha_min, gets w = 0 and keeps its state; one where T would fall
          // below t_min stops there without adding
          scalar_t* Tp = T.data() + p0;
          int32_t* lp = last.data() + p0;
          if (m < kVec) {  // short runs: per pixel, with early outs (vectors would run empty)
            for (int32_t j = 0; j < m; ++j) {
              if (pw[j] < cut || lp[j] < nn) continue;
              scalar_t alpha = o * G[j];
              alpha = alpha < amax ? alpha : amax;
              if (alpha < amin) continue;
              const scalar_t nT = Tp[j] * (1 - alpha);
              if (nT < tmin) { lp[j] = kk; ++n_done; --live[iy]; continue; }
              const scalar_t w = alpha * Tp[j];
              const int64_t p = p0 + j;
              if (want_feat) for (int64_t d = 0; d < D; ++d) acc[d * sa + p] += w * td.f[k * D + d];
              if (want_depth) dep[p] += w * z;
              if (want_wsq) wsq[p] += w * w;
              Tp[j] = nT;
            }
            return;
          }
          int32_t stops = 0;
          const int32_t mp = (m + 7) & ~7;
#pragma omp simd reduction(+ : stops)
          for (int32_t j = 0; j < mp; ++j) {
            scalar_t alpha = o * G[j];
            alpha = alpha < amax ? alpha : amax;
            const scalar_t Tj = Tp[j], nT = Tj * (1 - alpha);
            const bool ok = (j < m) & (pw[j] >= cut) & (alpha >= amin) & (lp[j] == nn);
            const bool stop = ok & (nT < tmin), add = ok & !stop;
            wv[j] = add ? alpha * Tj : scalar_t(0);
            Tp[j] = add ? nT : Tj;
            lp[j] = stop ? kk : lp[j];
            stops += stop;
          }
          if (stops) { n_done += stops; live[iy] -= stops; }
          // w > 0 wherever a pixel adds (alpha >= alpha_min, T >= t_min), so w != 0 marks them
          for (int64_t d = 0; want_feat && d < D; ++d) {
            const scalar_t fd = td.f[k * D + d];
            scalar_t* ap = acc.data() + d * sa + p0;
#pragma omp simd
            for (int32_t j = 0; j < mp; ++j) ap[j] = wv[j] != 0 ? ap[j] + wv[j] * fd : ap[j];
          }
          if (want_depth) {
            scalar_t* dp = dep.data() + p0;
#pragma omp simd
            for (int32_t j = 0; j < mp; ++j) dp[j] = wv[j] != 0 ? dp[j] + wv[j] * z : dp[j];
          }
          if (want_wsq) {
            scalar_t* wp = wsq.data() + p0;
#pragma omp simd
            for (int32_t j = 0; j < mp; ++j) wp[j] += wv[j] * wv[j];
          }
        });
      }
      for (int64_t p = 0; p < area; ++p) {
        const int64_t q = t * area + p;
        oT[q] = T[p];
        oL[q] = last[p];
        if (oF) for (int64_t d = 0; d < D; ++d) oF[q * D + d] = acc[d * sa + p];
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
  // Gradients are summed per Gaussian in one buffer per chunk of tiles (rows of W: mean 2,
  // conic 3, opacity, depth, features D), then the chunks are added in order: deterministic for
  // a given thread count, and no per-pair arrays or scatter.
  const int64_t n_gauss = means2d.size(0), W = 7 + D;
  const int64_t n_chunks = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), n_tiles));
  std::unique_ptr<scalar_t[]> sums(new scalar_t[n_chunks * n_gauss * W]);

  const Shapes<scalar_t> shapes(pc, po, n_gauss, amin_);
  at::parallel_for(0, n_chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      scalar_t* sum = sums.get() + c * n_gauss * W;
      std::fill(sum, sum + n_gauss * W, scalar_t(0));
      const int64_t t0 = n_tiles * c / n_chunks, t1 = n_tiles * (c + 1) / n_chunks;
      TileData<scalar_t> td;
      std::vector<scalar_t> T(area);
      std::vector<double> S(area);
      std::vector<scalar_t> gf_sum(D);
      std::vector<int32_t> row_last(ts);
      for (int64_t t = t0; t < t1; ++t) {
        const TileIndex ti = tile_index(pt, t, grid);
        const int64_t n = ti.e - ti.s;
        if (n == 0) continue;
        const int64_t base = t * area;
        int32_t deepest = 0;  // Gaussians at or behind every pixel's stop contribute nothing
        std::fill(row_last.begin(), row_last.end(), int32_t(0));
        for (int64_t p = 0; p < area; ++p) {
          T[p] = pTf[base + p];
          S[p] = 0.0;
          deepest = std::max(deepest, pL[base + p]);
          row_last[p / ts] = std::max(row_last[p / ts], pL[base + p]);
        }
        td.load(pm, pc, po, pf, pz, D, shapes, pg, ti.s, n, 0, std::min<int64_t>(n, deepest), ti.ox, ti.oy, ts);
        for (int64_t k = std::min<int64_t>(n, deepest) - 1; k >= 0; --k) {
          scalar_t go = 0, gmx = 0, gmy = 0, gA = 0, gB = 0, gC = 0, gz = 0;
          std::fill(gf_sum.begin(), gf_sum.end(), scalar_t(0));
          const scalar_t o = td.o[k], cut = td.cut[k], z = td.z[k], A = td.A[k], B = td.B[k], C = td.C[k];
          const int32_t kk = int32_t(k);
          auto row_live = [&](int32_t iy) { return k < row_last[iy]; };
          walk(td, k, ti.ox, ti.oy, ts, row_live,
               [&](int64_t p0, int32_t m, const scalar_t* dxs, scalar_t dy, const scalar_t* pw, const scalar_t* G, int32_t) {
            // per pixel: backward runs are mostly short, and the vectorised form measured slower
            for (int32_t j = 0; j < m; ++j) {
              const int64_t p = p0 + j, q = base + p;
              if (pw[j] < cut || kk >= pL[q]) continue;  // outside the ellipse, or behind the stop
              const scalar_t raw = o * G[j];
              const bool unclamped = raw < amax;
              const scalar_t alpha = unclamped ? raw : amax;
              if (alpha < amin) continue;
              const scalar_t Tb = T[p] / (1 - alpha);  // transmittance in front of k
              const scalar_t w = alpha * Tb;
              scalar_t v = (gD ? gD[q] * z : scalar_t(0)) + (gW ? 2 * w * gW[q] : scalar_t(0));
              if (gF) for (int64_t d = 0; d < D; ++d) v += gF[q * D + d] * td.f[k * D + d];
              if (gF) for (int64_t d = 0; d < D; ++d) gf_sum[d] += w * gF[q * D + d];
              if (gD) gz += w * gD[q];
              if (unclamped) {
                const scalar_t gt = gT ? gT[q] : scalar_t(0);
                const scalar_t g_alpha = Tb * v - (scalar_t(S[p]) + pTf[q] * gt) / (1 - alpha);
                const scalar_t g_power = g_alpha * alpha, dx = dxs[j];
                go += g_alpha * G[j];
                gmx += (A * dx + B * dy) * g_power;
                gmy += (B * dx + C * dy) * g_power;
                gA += scalar_t(-0.5) * dx * dx * g_power;
                gB += -dx * dy * g_power;
                gC += scalar_t(-0.5) * dy * dy * g_power;
              }
              S[p] += double(w) * double(v);
              T[p] = Tb;
            }
          });
          scalar_t* r = sum + pg[ti.s + k] * W;
          r[0] += gmx; r[1] += gmy; r[2] += gA; r[3] += gB; r[4] += gC; r[5] += go; r[6] += gz;
          for (int64_t d = 0; d < D; ++d) r[7 + d] += gf_sum[d];
        }
      }
    }
  });
  scalar_t* qM = pg_mean.data_ptr<scalar_t>();
  scalar_t* qC = pg_conic.data_ptr<scalar_t>();
  scalar_t* qO = pg_opac.data_ptr<scalar_t>();
  scalar_t* qF = pg_feat.data_ptr<scalar_t>();
  scalar_t* qZ = pg_depth.data_ptr<scalar_t>();
  at::parallel_for(0, n_gauss, 2048, [&](int64_t g0, int64_t g1) {
    std::vector<scalar_t> r(W);
    for (int64_t g = g0; g < g1; ++g) {
      std::fill(r.begin(), r.end(), scalar_t(0));
      for (int64_t c = 0; c < n_chunks; ++c) {
        const scalar_t* x = sums.get() + (c * n_gauss + g) * W;
        for (int64_t w = 0; w < W; ++w) r[w] += x[w];
      }
      qM[2 * g] = r[0]; qM[2 * g + 1] = r[1];
      qC[3 * g] = r[2]; qC[3 * g + 1] = r[3]; qC[3 * g + 2] = r[4];
      qO[g] = r[5]; qZ[g] = r[6];
      for (int64_t d = 0; d < D; ++d) qF[g * D + d] = r[7 + d];
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
  // uninitialised: the kernel writes every entry of every tile (empty tiles included)
  auto out_feat = want_feat ? torch::empty({n_tiles, area, D}, opts) : torch::empty({0}, opts);
  auto out_T = torch::empty({n_tiles, area}, opts);
  auto out_depth = want_depth ? torch::empty({n_tiles, area}, opts) : torch::empty({0}, opts);
  auto out_wsq = want_wsq ? torch::empty({n_tiles, area}, opts) : torch::empty({0}, opts);
  auto out_last = torch::empty({n_tiles, area}, opts.dtype(torch::kInt32));
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
  const int64_t G = means2d.size(0), D = feats.size(1);
  auto opts = means2d.options();
  auto pg_mean = torch::empty({G, 2}, opts);
  auto pg_conic = torch::empty({G, 3}, opts);
  auto pg_opac = torch::empty({G}, opts);
  auto pg_feat = torch::empty({G, D}, opts);
  auto pg_depth = torch::empty({G}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    backward_impl<scalar_t>(means2d, conics, opac, feats, depths, gids, tstart, Grid{tiles_x, tiles_y, ts}, amin,
                            amax, tmin, T_final, last_idx, g_feat, g_T, g_depth, g_wsq, pg_mean, pg_conic, pg_opac,
                            pg_feat, pg_depth);
  });
  return {pg_mean, pg_conic, pg_opac, pg_feat, pg_depth};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("composite_forward", &composite_forward, "Tiled front-to-back compositing (CPU)");
  m.def("composite_backward", &composite_backward, "Per-Gaussian gradients of the compositor, one pass (CPU)");
  m.def("project_forward", &project_forward, "EWA projection, radii and culling (CPU)");
  m.def("project_backward", &project_backward, "Gradients of the projection (CPU)");
  m.def("bin_tiles", &bin_tiles, "Tile lists in depth order (CPU)");
  m.def("sh_forward", &sh_forward, "SH colour, forward only (CPU)");
  m.def("fast_exp", &fast_exp, "The compositor's exp on [-80, 0] (for tests)");
}
