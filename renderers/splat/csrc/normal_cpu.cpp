// Standard normal draws for the training step (gdbench.rand): counter-based, so a draw is a pure
// function of (seed, index) and any split of the work over threads gives the same numbers.
//
// Philox4x32-10 (Salmon, Moraes, Dror and Shaw, SC 2011; the generator of cuRAND and of torch's
// CUDA RNG) maps the counter (block, 0, 0, 0) and the key (seed low, seed high) to four 32-bit
// words; Box-Muller turns each pair into two normals: r = sqrt(-2 ln u1), t = 2 pi u2, (r cos t,
// r sin t), with u1 = (w >> 8 + 1/2) / 2^24 in (0, 1) and u2 = (w >> 8) / 2^24. Blocks go eight
// to a group, one per vector lane: normal 32 g + 8 j + l is normal j of block 8 g + l (j = 0, 1
// from words 0 and 1, j = 2, 3 from words 2 and 3). The logarithm, sine and cosine are Cephes'
// single-precision polynomials, written for 8 lanes; tests/test_rand.py holds them to float64,
// the words to Random123's known answers and the draws to the normal law. torch's CPU generator
// (mt19937, one word per value) takes ~4 ns a float on this machine's cores.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#if defined(__AVX2__)
#include <immintrin.h>
#endif
#include <vector>

#include "splat_cpu.h"

namespace {

// eight Philox blocks side by side, one per lane
typedef uint32_t U __attribute__((vector_size(32)));
typedef int32_t SI __attribute__((vector_size(32)));
typedef float F __attribute__((vector_size(32)));

// (hi, lo) of the 64-bit products a * m per lane
inline void mulhilo(U a, uint32_t m, U& hi, U& lo) {
#if defined(__AVX2__)
  const __m256i av = (__m256i)a, mv = _mm256_set1_epi32(int32_t(m));
  const __m256i even = _mm256_mul_epu32(av, mv);  // lanes 0, 2, 4, 6 as 64-bit products
  const __m256i odd = _mm256_mul_epu32(_mm256_srli_epi64(av, 32), mv);  // lanes 1, 3, 5, 7
  hi = (U)_mm256_blend_epi32(_mm256_srli_epi64(even, 32), odd, 0xAA);
  lo = (U)_mm256_blend_epi32(even, _mm256_slli_epi64(odd, 32), 0xAA);
#else
  for (int j = 0; j < 8; ++j) {
    const uint64_t p = uint64_t(a[j]) * m;
    hi[j] = uint32_t(p >> 32);
    lo[j] = uint32_t(p);
  }
#endif
}

inline void philox8(U c0, U c1, U c2, U c3, uint32_t k0, uint32_t k1, U out[4]) {
  for (int round = 0; round < 10; ++round) {
    U hi0, lo0, hi1, lo1;
    mulhilo(c0, 0xD2511F53u, hi0, lo0);
    mulhilo(c2, 0xCD9E8D57u, hi1, lo1);
    c0 = hi1 ^ c1 ^ k0;
    c1 = lo1;
    c2 = hi0 ^ c3 ^ k1;
    c3 = lo0;
    k0 += 0x9E3779B9u;
    k1 += 0xBB67AE85u;
  }
  out[0] = c0; out[1] = c1; out[2] = c2; out[3] = c3;
}

template <typename V>
inline V vsel(SI m, V a, V b) { return m ? a : b; }

// ln x for x in (0, 1] (Cephes logf: x = m 2^e with m in [sqrt(1/2), sqrt(2)), a degree-9
// polynomial in m - 1; about 1 ulp)
inline F log01(F x) {
  const SI b = (SI)x;
  SI e = (b >> 23) - 126;  // x = m 2^e with m in [1/2, 1)
  const F m = (F)((b & 0x007FFFFF) | 0x3F000000);
  const SI small = m < 0.707106781186547524f;
  e = small ? e - 1 : e;
  const F f = small ? m + m - 1.0f : m - 1.0f;
  const F z = f * f;
  F p = f * 7.0376836292e-2f - 1.1514610310e-1f;
  p = p * f + 1.1676998740e-1f;
  p = p * f - 1.2420140846e-1f;
  p = p * f + 1.4249322787e-1f;
  p = p * f - 1.6668057665e-1f;
  p = p * f + 2.0000714765e-1f;
  p = p * f - 2.4999993993e-1f;
  p = p * f + 3.3333331174e-1f;
  const F fe = __builtin_convertvector(e, F);
  F y = f * z * p;
  y = y + fe * -2.12194440e-4f;
  y = y - 0.5f * z;
  return (f + y) + fe * 0.693359375f;
}

// (cos 2 pi u, sin 2 pi u) for u in [0, 1): 2 pi u = q pi / 2 + a with q = round(4 u) and
// |a| <= pi / 4, Cephes' sinf and cosf polynomials on a, rotated by q quarter turns
inline void sincos_turn(F u, F& c, F& s) {
  const F v = 4.0f * u;  // exact
  const SI qi = __builtin_convertvector(v + 0.5f, SI);  // v + 0.5 >= 0: truncation rounds
  const F a = (v - __builtin_convertvector(qi, F)) * 1.57079632679489662f;
  const F z = a * a;
  const F sa = a + a * z * ((z * -1.9515295891e-4f + 8.3321608736e-3f) * z - 1.6666654611e-1f);
  const F ca = 1.0f - 0.5f * z + z * z * ((z * 2.443315711809948e-5f - 1.388731625493765e-3f) * z +
                                            4.166664568298827e-2f);
  const SI k = qi & 3;
  const SI swap = (k & 1) != 0, neg_c = (k == 1) | (k == 2), neg_s = k >= 2;
  const F c0 = swap ? sa : ca, s0 = swap ? ca : sa;
  c = neg_c ? -c0 : c0;
  s = neg_s ? -s0 : s0;
}

inline void box_muller(U w1, U w2, F& z0, F& z1) {
  const F u1 = (__builtin_convertvector((SI)(w1 >> 8), F) + 0.5f) * 5.9604644775390625e-8f;  // 2^-24
  const F u2 = __builtin_convertvector((SI)(w2 >> 8), F) * 5.9604644775390625e-8f;
  const F l = -2.0f * log01(u1);
  F r;
  for (int j = 0; j < 8; ++j) r[j] = std::sqrt(l[j]);  // vsqrtps
  F c, s;
  sincos_turn(u2, c, s);
  z0 = r * c;
  z1 = r * s;
}

// the 32 normals of group g: blocks 8 g .. 8 g + 7, one per lane; out[8 j + lane] holds
// normal j of the lane's block (pairs (0, 1) and (2, 3) of its words)
inline void group32(int64_t g, uint32_t k0, uint32_t k1, float* out) {
  U c0, c1;
  for (int j = 0; j < 8; ++j) {
    const uint64_t b = uint64_t(g) * 8 + uint64_t(j);
    c0[j] = uint32_t(b);
    c1[j] = uint32_t(b >> 32);
  }
  U w[4];
  philox8(c0, c1, U{}, U{}, k0, k1, w);
  F z[4];
  box_muller(w[0], w[1], z[0], z[1]);
  box_muller(w[2], w[3], z[2], z[3]);
  std::memcpy(out, z, sizeof(z));
}

}  // namespace

torch::Tensor philox_normal(int64_t n, int64_t seed) {
  TORCH_CHECK(n >= 0, "n: expected a count >= 0, got ", n);
  auto out = torch::empty({n}, torch::kFloat32);
  float* o = out.data_ptr<float>();
  const uint32_t k0 = uint32_t(uint64_t(seed)), k1 = uint32_t(uint64_t(seed) >> 32);
  const int64_t full = n / 32;
  at::parallel_for(0, full, 256, [&](int64_t g0, int64_t g1) {  // threads from 16k values
    for (int64_t g = g0; g < g1; ++g) group32(g, k0, k1, o + 32 * g);
  });
  if (n % 32) {  // the last, partial group
    float z[32];
    group32(full, k0, k1, z);
    std::memcpy(o + 32 * full, z, sizeof(float) * (n % 32));
  }
  return out;
}

std::vector<int64_t> philox4x32(std::vector<int64_t> counter, std::vector<int64_t> key) {
  TORCH_CHECK(counter.size() == 4 && key.size() == 2, "philox4x32: expected 4 counter and 2 key words");
  // the kernel's own eight-lane rounds, every lane on the same block (the tests read lane 0)
  U w[4];
  philox8(U{} + uint32_t(counter[0]), U{} + uint32_t(counter[1]), U{} + uint32_t(counter[2]),
          U{} + uint32_t(counter[3]), uint32_t(key[0]), uint32_t(key[1]), w);
  return {int64_t(w[0][0]), int64_t(w[1][0]), int64_t(w[2][0]), int64_t(w[3][0])};
}

torch::Tensor normal_parts(const torch::Tensor& u, int64_t which) {
  // the kernel's log (which = 0, of u in (0, 1]) or cos / sin of 2 pi u (1 / 2, u in [0, 1)), for tests
  TORCH_CHECK(u.scalar_type() == torch::kFloat32 && u.dim() == 1, "u: expected a 1D float32 tensor");
  auto x = u.contiguous();
  auto out = torch::empty_like(x);
  const float* px = x.data_ptr<float>();
  float* po = out.data_ptr<float>();
  for (int64_t i = 0; i < x.numel(); ++i) {
    const F v = F{} + px[i];
    F c, s;
    if (which == 0) {
      po[i] = log01(v)[0];
    } else {
      sincos_turn(v, c, s);
      po[i] = which == 1 ? c[0] : s[0];
    }
  }
  return out;
}
