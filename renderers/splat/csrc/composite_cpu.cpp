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
// One visitor (walk) holds the pixel loop of both: it hands the ellipse's pixels in the tile as
// blocks of one vector (8 floats or 4 doubles of a row; simd.h), with their powers and
// exponentials computed four blocks at a time, to a block kernel, branch-free vector code in
// both passes. The backward sums gradients per Gaussian in per-lane partial sums, then in one
// buffer per chunk of tiles, and adds the chunks in order: deterministic for a thread count,
// and the same on one thread as on two (max(2, threads) chunks).
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include "simd.h"
#include "splat_cpu.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <type_traits>
#include <vector>

namespace {

// Work counters for benchmarks (work_counters()): tile-Gaussian pairs the forward visited, the
// pixel blocks it evaluated, and the same two for the backward, summed over calls. Each thread
// counts in locals and adds once per call, so the kernels pay nothing measurable.
std::atomic<int64_t> g_work[4] = {};

struct Grid {
  int64_t tiles_x, tiles_y, ts;
};

// Per Gaussian, once per call (not once per tile pair): the opacity cut, its pixel box and the
// row-span terms. alpha >= alpha_min  <=>  power >= ln(alpha_min / o). The reject threshold
// keeps a margin of 1e-3 in power, and the box holds the pixels whose centre lies in the exact
// box of {q(d) <= 2 ln(o/alpha_min) + 2e-3} (q = d^T conic d) widened by a relative 1e-6 and
// 1e-4 px, so every pixel the exact test could accept is visited. Empty box (x0 > x1): nothing
// to visit; a degenerate conic: every pixel.
template <typename scalar_t>
struct Shapes {
  struct Shape {  // one record per Gaussian: a tile pair's set-up reads one cache line
    double ALs, det, invA, BinvA;
    int32_t x0, x1, y0, y1;  // image pixels, inclusive (clamped to +-2^30)
    scalar_t cut;
  };
  std::vector<Shape> of;

  Shapes(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac, int64_t G, double amin) : of(G) {
    const double floor_o = amin * std::exp(-1e-3);
    constexpr double kBig = double(1 << 30);
    auto to_int = [](double v) { return int32_t(v >= -kBig ? (v <= kBig ? v : kBig) : -kBig); };  // NaN: -2^30
    at::parallel_for(0, G, 512, [&](int64_t g0, int64_t g1) {  // both threads above 512 Gaussians
      for (int64_t g = g0; g < g1; ++g) {
        Shape& r = of[g];
        const double o = opac[g];
        r = Shape{0, 0, 0, 0, 1, 0, 1, 0, scalar_t(0)};
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
          r.x0 = r.y0 = -int32_t(kBig); r.x1 = r.y1 = int32_t(kBig);
          continue;
        }
        const double ex = std::sqrt(L * c / dt) * (1 + 1e-6) + 1e-4;
        const double ey = std::sqrt(L * a / dt) * (1 + 1e-6) + 1e-4;
        // pixel centre i + 0.5 within [m - e, m + e]
        const double cx = double(means2d[2 * g]) - 0.5, cy = double(means2d[2 * g + 1]) - 0.5;
        r.x0 = to_int(std::ceil(cx - ex)); r.x1 = to_int(std::floor(cx + ex));
        r.y0 = to_int(std::ceil(cy - ey)); r.y1 = to_int(std::floor(cy + ey));
      }
    });
  }
};

constexpr int64_t kAhead = 8;  // list entries the gathers prefetch ahead

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
      if (k + kAhead < n) {  // the list is in depth order, so g jumps: fetch ahead of the gathers
        const int64_t h = gids[s + k + kAhead];
        __builtin_prefetch(means2d + 2 * h);
        __builtin_prefetch(conics + 3 * h);
        __builtin_prefetch(opac + h);
        __builtin_prefetch(depths + h);
        __builtin_prefetch(feats + h * D);
        __builtin_prefetch(&sh.of[h]);
      }
      const int64_t g = gids[s + k];
      mx[k] = means2d[2 * g]; my[k] = means2d[2 * g + 1];
      A[k] = conics[3 * g]; B[k] = conics[3 * g + 1]; C[k] = conics[3 * g + 2];
      o[k] = opac[g]; z[k] = depths[g];
      for (int64_t d = 0; d < D; ++d) f[k * D + d] = feats[g * D + d];
      const auto& r = sh.of[g];
      cut[k] = r.cut; ALs[k] = r.ALs; det[k] = r.det; invA[k] = r.invA; BinvA[k] = r.BinvA;
      // the box in tile-local pixels; tile origins are whole pixels
      x0[k] = int32_t(std::max<int64_t>(0, r.x0 - int64_t(ox)));
      x1[k] = int32_t(std::min<int64_t>(last, r.x1 - int64_t(ox)));
      y0[k] = int32_t(std::max<int64_t>(0, r.y0 - int64_t(oy)));
      y1[k] = int32_t(std::min<int64_t>(last, r.y1 - int64_t(oy)));
    }
  }
};

// The pixels of Gaussian k's box in the tile, handed to seg one block of L pixels of a row at a
// time (Simd<scalar_t>::L: 8 floats or 4 doubles): first the row spans of the whole box in one
// vectorised pass (the exact span of q(d) <= Ls per row, within the box; empty where the row
// misses the ellipse), then for each row where row_live(iy) (some pixel of the row is still
// compositing, or lies in front of k's stop) and each block from the span's start, the vectors
// dx, power and G = exp(power) of its lanes, and seg(iy, c0, m, dx, dy, power, G) with c0 the
// block's first tile-local column and m <= L the lanes inside the span. Lanes past m hold
// pixels beyond the span (or beyond the tile's row, in the buffers' row padding): seg masks
// them. Which pixels count is seg's test power >= cut, so the spans only need to cover them.
constexpr int64_t kLoad = 64;  // the forward loads a tile's pairs in blocks of this many

template <typename scalar_t>
struct Spans {
  std::vector<int32_t> x0, x1;  // per row of the tile
  std::vector<int32_t> by, bx, bm;  // per block: row, first column, lanes inside the span
  explicit Spans(int64_t ts)
      : x0(ts), x1(ts), by(ts * (ts / Simd<scalar_t>::L + 1)), bx(by.size()), bm(by.size()) {}

  void fill(const TileData<scalar_t>& td, int64_t k, double ox, double oy, int64_t ts) {
    const int32_t y0 = td.y0[k], y1 = td.y1[k], bx0 = td.x0[k], bx1 = td.x1[k];
    const double ALs = td.ALs[k], det = td.det[k], ia = td.invA[k], ba = td.BinvA[k];
    const double my = double(td.my[k]), cx = double(td.mx[k]) - ox - 0.5, tsd = double(ts);
    int32_t* px0 = x0.data();
    int32_t* px1 = x1.data();
    if (!(ALs > 0)) {  // no span: the box's full rows
      for (int32_t iy = y0; iy <= y1; ++iy) { px0[iy] = bx0; px1[iy] = bx1; }
      return;
    }
#pragma omp simd
    for (int32_t iy = y0; iy <= y1; ++iy) {  // A dx^2 + 2 B dy dx + C dy^2 - Ls <= 0 in dx
      const double dyd = oy + iy + 0.5 - my, disc = ALs - det * dyd * dyd;
      const double r = std::sqrt(disc < 0 ? 0.0 : disc) * ia, mid = cx - ba * dyd;
      const double lo = std::ceil(mid - r), hi = std::floor(mid + r);
      const int32_t a = int32_t(lo > -1.0 ? lo : -1.0), b = int32_t(hi < tsd ? hi : tsd);
      px0[iy] = disc < 0 ? 1 : (a > bx0 ? a : bx0);
      px1[iy] = disc < 0 ? 0 : (b < bx1 ? b : bx1);
    }
  }
};

// Blocks are computed kGroup at a time: their exps are independent chains of ~25 dependent
// vector operations each, which a core runs side by side; one at a time, the exp's latency set
// the pace.
constexpr int kGroup = 4;  // 2 and 8 measured the same or slower

template <typename scalar_t, typename R, typename F>
inline int32_t walk(const TileData<scalar_t>& td, Spans<scalar_t>& sp, int64_t k, double ox, double oy, int64_t ts,
                 R&& row_live, F&& seg) {
  using V = typename Simd<scalar_t>::V;
  constexpr int L = Simd<scalar_t>::L;
  const scalar_t A = td.A[k], B = td.B[k], C = td.C[k], mx = td.mx[k], my = td.my[k];
  // a box at most one block wide is one block per row whatever the spans: skip solving them
  // (the small Gaussians of a 64 px render); seg's cut test picks the same pixels either way
  const bool narrow = td.x1[k] - td.x0[k] < L;
  if (!narrow) sp.fill(td, k, ox, oy, ts);
  // the blocks of each live row, written branch-free: a row's span (at most ts pixels) is
  // ceil(ts / L) block slots, a slot kept (nb advances) where the span reaches it
  const int32_t slots = int32_t((ts + L - 1) / L);
  int32_t nb = 0;
  for (int32_t iy = td.y0[k]; iy <= td.y1[k]; ++iy) {
    const int32_t x0 = narrow ? td.x0[k] : sp.x0[iy], x1 = narrow ? td.x1[k] : sp.x1[iy];
    const int32_t w = row_live(iy) ? x1 - x0 + 1 : 0;  // <= 0: nothing to visit
    for (int32_t j = 0; j < slots; ++j) {
      const int32_t rest = w - j * L;
      sp.by[nb] = iy;
      sp.bx[nb] = x0 + j * L;
      sp.bm[nb] = rest < L ? rest : L;
      nb += rest > 0;
    }
  }
  const V lanes = iota<V>() + scalar_t(0.5);
  auto group = [&](auto size, int32_t b0) {  // blocks b0 .. b0 + size - 1, size a compile-time constant
    constexpr int n = decltype(size)::value;
    V dx[n], pw[n], G[n];
    scalar_t dy[n];
    for (int g = 0; g < n; ++g) {
      const int32_t b = b0 + g;
      dy[g] = scalar_t(oy + sp.by[b]) + scalar_t(0.5) - my;
      // scalar_t(ox + c0 + j) + 0.5 - mx: integers and halves below 2^24 are exact in float
      dx[g] = (splat<V>(scalar_t(ox + sp.bx[b])) + lanes) - mx;
      // -1/2 (A dx^2 + C dy^2) - B dx dy, two of its steps fused (the same code in both passes)
      const V q = fmadd(A * dx[g], dx[g], splat<V>(C * dy[g] * dy[g]));
      pw[g] = fmadd(splat<V>(scalar_t(-0.5)), q, -(B * dx[g] * dy[g]));
      G[g] = vexp(pw[g]);
    }
    for (int g = 0; g < n; ++g) seg(sp.by[b0 + g], sp.bx[b0 + g], sp.bm[b0 + g], dx[g], dy[g], pw[g], G[g]);
  };
  int32_t b0 = 0;
  for (; b0 + kGroup <= nb; b0 += kGroup) group(std::integral_constant<int, kGroup>{}, b0);
  static_assert(kGroup == 4, "the rest below is written for groups of 4");
  switch (nb - b0) {  // the rest, without computing blocks that are not handed on
    case 3: group(std::integral_constant<int, 3>{}, b0); break;
    case 2: group(std::integral_constant<int, 2>{}, b0); break;
    case 1: group(std::integral_constant<int, 1>{}, b0); break;
    default: break;
  }
  return nb;  // the blocks handed to seg
}

// Tiles in order of decreasing list length, taken one at a time by whichever thread is free:
// a tile's output depends only on the tile, so the schedule cannot change a bit of it, and the
// longest tiles start first, so that no thread waits on a long tile at the end (a static split
// in halves serves a scene whose object sits in one half badly).
inline std::vector<int64_t> longest_first(const int64_t* pt, int64_t n_tiles) {
  std::vector<int64_t> order(n_tiles);
  for (int64_t t = 0; t < n_tiles; ++t) order[t] = t;
  std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return pt[a + 1] - pt[a] > pt[b + 1] - pt[b]; });
  return order;
}

// The backward's chunks of consecutive tiles (one gradient buffer each, added in order), cut
// where the work so far (the pairs each pixel visits: its stop index, plus one per pixel)
// reaches an equal share: a function of the inputs and the thread count only, so the sums stay
// deterministic.
inline std::vector<int64_t> balanced_chunks(const int32_t* last, int64_t n_tiles, int64_t area, int64_t n_chunks) {
  std::vector<double> cum(n_tiles + 1, 0.0);
  at::parallel_for(0, n_tiles, 64, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      int64_t c = area;
      for (int64_t p = 0; p < area; ++p) c += last[t * area + p];
      cum[t + 1] = double(c);
    }
  });
  for (int64_t t = 0; t < n_tiles; ++t) cum[t + 1] += cum[t];
  std::vector<int64_t> bounds(n_chunks + 1, n_tiles);
  bounds[0] = 0;
  for (int64_t c = 1; c < n_chunks; ++c) {
    const double share = cum[n_tiles] * double(c) / double(n_chunks);
    bounds[c] = std::max(bounds[c - 1], int64_t(std::lower_bound(cum.begin(), cum.end(), share) - cum.begin()));
    bounds[c] = std::min(bounds[c], n_tiles);
  }
  return bounds;
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

  const Shapes<scalar_t> shapes(pm, pc, po, means2d.size(0), amin_);
  const std::vector<int64_t> order = longest_first(pt, n_tiles);
  std::atomic<int64_t> next{0};
  at::parallel_for(0, std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), n_tiles)), 1, [&](int64_t, int64_t) {
    using V = typename Simd<scalar_t>::V;
    using M = typename Simd<scalar_t>::M;
    using I = typename Simd<scalar_t>::I;
    constexpr int L = Simd<scalar_t>::L;
    TileData<scalar_t> td;
    Spans<scalar_t> spans(ts);
    // per-tile buffers with rows of ts + L entries (a block's lanes past the row's end land in the
    // padding, never in the next row), features channel-major ([D][sa]) so that a block is
    // contiguous
    const int64_t rs = ts + L, sa = ts * rs;
    std::vector<scalar_t> T(sa), acc(sa * D), dep(sa), wsq(sa);
    std::vector<int32_t> last(sa), live(ts);
    const V lane = iota<V>();
    int64_t n_pairs = 0, n_blocks = 0;
    for (int64_t i = next++; i < n_tiles; i = next++) {
      const int64_t t = order[i];
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
        ++n_pairs;
        n_blocks += walk(td, spans, k, ti.ox, ti.oy, ts, row_live, [&](int32_t iy, int32_t c0, int32_t m, V, scalar_t, V pw, V G) {
          // branch-free over the block: a pixel outside the span or the ellipse, one that has
          // stopped, or one where alpha < alpha_min gets w = 0 and keeps its state; one where T
          // would fall below t_min stops there without adding
          const int64_t p0 = int64_t(iy) * rs + c0;
          V alpha = o * G;
          alpha = alpha < amax ? alpha : splat<V>(amax);
          const V Tj = loadu<V>(T.data() + p0), nT = Tj * (1 - alpha);
          const I lj = loadu<I>(last.data() + p0);
          const M live_lane = __builtin_convertvector(lj == nn, M);
          const M ok = (lane < scalar_t(m)) & (pw >= cut) & (alpha >= amin) & live_lane;
          const M stop = ok & (nT < tmin), add = ok & ~stop;
          const V w = add ? alpha * Tj : splat<V>(0);
          storeu(T.data() + p0, add ? nT : Tj);
          if (const uint32_t stops = bits(stop)) {
            storeu(last.data() + p0, __builtin_convertvector(stop, I) ? splat<I>(kk) : lj);
            const int c = __builtin_popcount(stops);
            n_done += c;
            live[iy] -= c;
          }
          // w > 0 wherever a pixel adds (alpha >= alpha_min, T >= t_min), so w != 0 marks them
          const M adds = w != 0;
          for (int64_t d = 0; want_feat && d < D; ++d) {
            scalar_t* ap = acc.data() + d * sa + p0;
            const V a = loadu<V>(ap);
            storeu(ap, adds ? fmadd(w, splat<V>(td.f[k * D + d]), a) : a);
          }
          if (want_depth) {
            const V a = loadu<V>(dep.data() + p0);
            storeu(dep.data() + p0, adds ? fmadd(w, splat<V>(z), a) : a);
          }
          if (want_wsq) storeu(wsq.data() + p0, fmadd(w, w, loadu<V>(wsq.data() + p0)));
        });
      }
      for (int64_t py = 0; py < ts; ++py) {  // rows and columns: no integer division per pixel
        for (int64_t px = 0; px < ts; ++px) {
          const int64_t q = t * area + py * ts + px, b = py * rs + px;
          oT[q] = T[b];
          oL[q] = last[b];
          if (oF) for (int64_t d = 0; d < D; ++d) oF[q * D + d] = acc[d * sa + b];
          if (oD) oD[q] = dep[b];
          if (oW) oW[q] = wsq[b];
        }
      }
    }
    g_work[0] += n_pairs;
    g_work[1] += n_blocks;
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
  // a given thread count, and no per-pair arrays or scatter. At least two chunks, so that one
  // thread sums as two do (a sweep's one-thread workers and a two-thread run agree bit for bit);
  // the second chunk costs one thread a buffer of n_gauss x W and its addition.
  const int64_t n_gauss = means2d.size(0), W = 7 + D;
  const int64_t threads = std::max<int64_t>(at::get_num_threads(), 2);
  const int64_t n_chunks = std::max<int64_t>(1, std::min<int64_t>(threads, n_tiles));
  std::unique_ptr<scalar_t[]> sums(new scalar_t[n_chunks * n_gauss * W]);

  const Shapes<scalar_t> shapes(pm, pc, po, n_gauss, amin_);
  const std::vector<int64_t> bounds = balanced_chunks(pL, n_tiles, area, n_chunks);
  at::parallel_for(0, n_chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      scalar_t* sum = sums.get() + c * n_gauss * W;
      std::fill(sum, sum + n_gauss * W, scalar_t(0));
      const int64_t t0 = bounds[c], t1 = bounds[c + 1];
      using V = typename Simd<scalar_t>::V;
      using M = typename Simd<scalar_t>::M;
      using I = typename Simd<scalar_t>::I;
      constexpr int L = Simd<scalar_t>::L;
      using SV = typename Simd<scalar_t>::D;  // S in double, L lanes
      TileData<scalar_t> td;
      Spans<scalar_t> spans(ts);
      // the tile's per-pixel state and incoming gradients, copied into rows of ts + L entries (a
      // block's lanes past the row's end read the padding: finite, masked out)
      const int64_t rs = ts + L, sa = ts * rs;
      std::vector<scalar_t> T(sa, 1), Tf(sa, 1), bT(sa, 0), bD(sa, 0), bW(sa, 0), bF(sa * D, 0);
      std::vector<double> S(sa, 0.0);
      std::vector<int32_t> last(sa, 0), row_last(ts);
      std::vector<V> gf(D);
      const V lane = iota<V>();
      int64_t n_pairs = 0, n_blocks = 0;
      for (int64_t t = t0; t < t1; ++t) {
        const TileIndex ti = tile_index(pt, t, grid);
        const int64_t n = ti.e - ti.s;
        if (n == 0) continue;
        const int64_t base = t * area;
        int32_t deepest = 0;  // Gaussians at or behind every pixel's stop contribute nothing
        std::fill(row_last.begin(), row_last.end(), int32_t(0));
        for (int64_t py = 0; py < ts; ++py) {  // rows and columns: no integer division per pixel
          for (int64_t px = 0; px < ts; ++px) {
            const int64_t q = base + py * ts + px, b = py * rs + px;
            T[b] = Tf[b] = pTf[q];
            S[b] = 0.0;
            last[b] = pL[q];
            if (gT) bT[b] = gT[q];
            if (gD) bD[b] = gD[q];
            if (gW) bW[b] = gW[q];
            if (gF) for (int64_t d = 0; d < D; ++d) bF[d * sa + b] = gF[q * D + d];
            deepest = std::max(deepest, pL[q]);
            row_last[py] = std::max(row_last[py], pL[q]);
          }
        }
        td.load(pm, pc, po, pf, pz, D, shapes, pg, ti.s, n, 0, std::min<int64_t>(n, deepest), ti.ox, ti.oy, ts);
        for (int64_t k = std::min<int64_t>(n, deepest) - 1; k >= 0; --k) {
          // per-lane partial sums of the Gaussian's gradients, added across lanes at the end
          V go{}, gmx{}, gmy{}, gA{}, gB{}, gC{}, gz{};
          std::fill(gf.begin(), gf.end(), V{});
          const scalar_t o = td.o[k], cut = td.cut[k], z = td.z[k], A = td.A[k], B = td.B[k], C = td.C[k];
          const int32_t kk = int32_t(k);
          auto row_live = [&](int32_t iy) { return k < row_last[iy]; };
          ++n_pairs;
          n_blocks += walk(td, spans, k, ti.ox, ti.oy, ts, row_live, [&](int32_t iy, int32_t c0, int32_t m, V dx, scalar_t dy, V pw, V G) {
            const int64_t b = int64_t(iy) * rs + c0;
            // inside the span and the ellipse, and in front of the pixel's stop
            const M front = __builtin_convertvector(loadu<I>(last.data() + b) > kk, M);
            const V raw = o * G;
            const M unclamped = raw < amax;
            const V alpha = unclamped ? raw : splat<V>(amax);
            const M ok = (lane < scalar_t(m)) & (pw >= cut) & front & (alpha >= amin);
            if (!bits(ok)) return;
            const V Tp = loadu<V>(T.data() + b);
            const V Tb = Tp / (1 - alpha);  // transmittance in front of k
            const V w = alpha * Tb;
            const V zero = splat<V>(0);
            V v = (gD ? loadu<V>(bD.data() + b) * z : zero) + (gW ? 2 * w * loadu<V>(bW.data() + b) : zero);
            for (int64_t d = 0; gF && d < D; ++d) {
              const V gfd = loadu<V>(bF.data() + d * sa + b);
              v += gfd * td.f[k * D + d];
              gf[d] += ok ? w * gfd : zero;
            }
            if (gD) gz += ok ? w * loadu<V>(bD.data() + b) : zero;
            const M um = ok & unclamped;
            const SV Sp = loadu<SV>(S.data() + b);
            const V gt = gT ? loadu<V>(bT.data() + b) : zero;
            const V g_alpha = Tb * v - (__builtin_convertvector(Sp, V) + loadu<V>(Tf.data() + b) * gt) / (1 - alpha);
            const V g_power = g_alpha * alpha;
            go += um ? g_alpha * G : zero;
            gmx += um ? (A * dx + B * dy) * g_power : zero;
            gmy += um ? (B * dx + C * dy) * g_power : zero;
            gA += um ? scalar_t(-0.5) * dx * dx * g_power : zero;
            gB += um ? -dx * dy * g_power : zero;
            gC += um ? scalar_t(-0.5) * dy * dy * g_power : zero;
            const auto okd = __builtin_convertvector(ok, typename Simd<scalar_t>::DM);
            storeu(S.data() + b, okd ? Sp + __builtin_convertvector(w, SV) * __builtin_convertvector(v, SV) : Sp);
            storeu(T.data() + b, ok ? Tb : Tp);
          });
          auto hsum = [](V x) {
            scalar_t r = 0;
            for (int j = 0; j < L; ++j) r += x[j];
            return r;
          };
          scalar_t* r = sum + pg[ti.s + k] * W;
          r[0] += hsum(gmx); r[1] += hsum(gmy); r[2] += hsum(gA); r[3] += hsum(gB); r[4] += hsum(gC);
          r[5] += hsum(go); r[6] += hsum(gz);
          for (int64_t d = 0; d < D; ++d) r[7 + d] += hsum(gf[d]);
        }
      }
      g_work[2] += n_pairs;
      g_work[3] += n_blocks;
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
    using V = typename Simd<scalar_t>::V;
    constexpr int64_t L = Simd<scalar_t>::L;
    for (int64_t i = 0; i < x.numel(); i += L) {  // the kernel's vector code, a partial last block padded
      V v = splat<V>(scalar_t(0));
      std::memcpy(&v, px + i, sizeof(scalar_t) * std::min<int64_t>(L, x.numel() - i));
      const V e = vexp(v);
      std::memcpy(po + i, &e, sizeof(scalar_t) * std::min<int64_t>(L, x.numel() - i));
    }
  });
  return out;
}

std::vector<int64_t> work_counters(bool reset) {
  std::vector<int64_t> r(4);
  for (int i = 0; i < 4; ++i) r[i] = reset ? g_work[i].exchange(0) : g_work[i].load();
  return r;
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
  m.def("zoom_taps", &zoom_taps, "Separable resampling of image stacks by taps (CPU; gdbench.assets.zoom)");
  m.def("sqdist_rows", &sqdist_rows, "Squared distances of one vector to the rows of a matrix, in double (CPU; gdbench.priors.empirical)");
  m.def("work_counters", &work_counters, py::arg("reset") = true,
        "Compositor work since the last reset: [forward tile-Gaussian pairs visited, forward pixel blocks "
        "evaluated, backward pairs, backward blocks] (for benchmarks' work fits)");
  m.def("fast_exp", &fast_exp, "The compositor's exp on [-80, 0] (for tests)");
  m.def("philox_normal", &philox_normal, py::arg("n"), py::arg("seed"),
        "n standard normals (float32) from Philox4x32-10 keyed by seed and Box-Muller (gdbench.rand)");
  m.def("noise_finish", &noise_finish,
        "Structured noise's last pass: tile sums -> feat / sqrt(sum w^2) images, iid where uncovered (CPU)");
  m.def("philox4x32", &philox4x32, "One Philox4x32-10 block: 4 counter words, 2 key words (for tests)");
  m.def("normal_parts", &normal_parts, "philox_normal's log (0), cos (1) and sin (2) of 2 pi u (for tests)");
}
