// Fixed-width vectors for the compositor (GCC/Clang vector extensions, 32 bytes: 8 floats or 4
// doubles, one AVX register; other targets get the same code lowered by the compiler) and its
// exp. The compositor writes each pixel block as straight-line vector code: no loop over lanes
// whose trip count the compiler cannot see, so no prologue, epilogue or per-lane branches.
// Every lane runs the same operations in the same order (the build contracts no multiply-add;
// fmadd below fuses where the code says so), so a lane's result does not depend on its lane.
#pragma once
// 64-byte vectors (8 doubles) pass through inline helpers only; their call ABI does not matter
#pragma GCC diagnostic ignored "-Wpsabi"

#include <cstdint>
#include <cstring>
#include <type_traits>
#if defined(__AVX__)
#include <immintrin.h>
#endif

template <typename T>
struct Simd;

template <>
struct Simd<float> {
  static constexpr int L = 8;
  typedef float V __attribute__((vector_size(32)));
  typedef int32_t M __attribute__((vector_size(32)));  // comparison results (-1 / 0 per lane)
  typedef int32_t I __attribute__((vector_size(32)));  // int32 lanes (the stop indices)
  typedef double D __attribute__((vector_size(64)));  // double lanes (the backward's sums)
  typedef int64_t DM __attribute__((vector_size(64)));
};

template <>
struct Simd<double> {
  static constexpr int L = 4;
  typedef double V __attribute__((vector_size(32)));
  typedef int64_t M __attribute__((vector_size(32)));
  typedef int32_t I __attribute__((vector_size(16)));
  typedef double D __attribute__((vector_size(32)));
  typedef int64_t DM __attribute__((vector_size(32)));
};

template <typename V, typename S>
inline V splat(S s) {
  using E = std::remove_cv_t<std::remove_reference_t<decltype(V{}[0])>>;
  return V{} + E(s);  // 0 + s == s for every s the kernel broadcasts (no -0 or NaN)
}

template <typename V, typename S>
inline V loadu(const S* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}

template <typename V, typename S>
inline void storeu(S* p, V v) {
  std::memcpy(p, &v, sizeof(V));
}

// lanes 0, 1, ..., L - 1
template <typename V>
inline V iota() {
  V v;
  for (int j = 0; j < int(sizeof(V) / sizeof(v[0])); ++j) v[j] = j;
  return v;
}

// one bit per lane of a comparison result (lane j: bit j)
template <typename M>
inline uint32_t bits(M m) {
#if defined(__AVX__)
  if constexpr (sizeof(m[0]) == 4) return uint32_t(_mm256_movemask_ps((__m256)m));
  else return uint32_t(_mm256_movemask_pd((__m256d)m));
#else
  uint32_t r = 0;
  for (int j = 0; j < int(sizeof(M) / sizeof(m[0])); ++j) r |= uint32_t(m[j] != 0) << j;
  return r;
#endif
}

// a * b + c with one rounding: the FMA instruction where the CPU has one (the build targets the
// CPU it runs on), else the two operations. Used explicitly, in code both compositor passes run
// alike (the exp, the power) or that one pass alone runs (the forward's blends); the build
// contracts nothing by itself, so the two passes cannot round one expression differently.
template <typename V>
inline V fmadd(V a, V b, V c) {
#if defined(__FMA__)
  if constexpr (sizeof(V) == 32 && sizeof(a[0]) == 4) return (V)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
  else if constexpr (sizeof(V) == 32 && sizeof(a[0]) == 8) return (V)_mm256_fmadd_pd((__m256d)a, (__m256d)b, (__m256d)c);
  else return a * b + c;
#else
  return a * b + c;
#endif
}

// exp(x) for the kernel's range (x in [-80, 0]: power >= cut > -10 where it is used; lower
// inputs are clamped, their results unused): x = n ln2 + r with n = round(x / ln2) (the
// 1.5 * 2^m rounding trick), |r| <= ln2/2, exp(r) by its Taylor series to the precision of the
// type (degree 7 for float: 2e-8 relative; degree 13 for double: 4e-18; Horner's steps as fused
// multiply-adds, 0.95x the compositor's forward time), times 2^n built in the
// exponent bits. Checked against std::exp to 2 ulp in float and 4 ulp in double over the range
// (tests/test_composite.py, through the module's fast_exp).
inline Simd<float>::V vexp(Simd<float>::V x) {
  using V = Simd<float>::V;
  using M = Simd<float>::M;
  x = x < -80.0f ? splat<V>(-80.0f) : x;
  const float shift = 12582912.0f;  // 1.5 * 2^23
  const V t = x * 1.44269504088896341f + shift;
  const V n = t - shift;
  const V r = (x - n * 0.693145751953125f) - n * 1.42860682030941723e-06f;
  V p = splat<V>(1.0f / 5040.0f);
  for (float ci : {1.0f / 720.0f, 1.0f / 120.0f, 1.0f / 24.0f, 1.0f / 6.0f, 0.5f, 1.0f, 1.0f})
    p = fmadd(p, r, splat<V>(ci));
  const M bits = (__builtin_convertvector(n, M) + 127) << 23;
  return p * (V)bits;
}

inline Simd<double>::V vexp(Simd<double>::V x) {
  using V = Simd<double>::V;
  using M = Simd<double>::M;
  x = x < -700.0 ? splat<V>(-700.0) : x;
  const double shift = 6755399441055744.0;  // 1.5 * 2^52
  const V t = x * 1.4426950408889634 + shift;
  const V n = t - shift;
  const V r = (x - n * 0.6931471803691238) - n * 1.9082149292705877e-10;
  V p = splat<V>(1.0 / 6227020800.0);
  const double c[] = {1.0 / 479001600.0, 1.0 / 39916800.0, 1.0 / 3628800.0, 1.0 / 362880.0, 1.0 / 40320.0,
                      1.0 / 5040.0,      1.0 / 720.0,      1.0 / 120.0,     1.0 / 24.0,     1.0 / 6.0,
                      0.5,               1.0,              1.0};
  for (double ci : c) p = fmadd(p, r, splat<V>(ci));
  // n is an integer below 2^51 in magnitude: t's low mantissa bits hold it (AVX2 has no
  // double -> int64 conversion), the same value as int64(n)
  const M nb = (M)t - int64_t(0x4338000000000000);  // the bits of shift
  const M bits = (nb + 1023) << 52;
  return p * (V)bits;
}
