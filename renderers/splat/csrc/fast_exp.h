// The compositor's exp, vectorisable (see composite_cpu.cpp); header-only.
#pragma once

#include <cstdint>
#include <cstring>

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
