// Vector math shared by the native kernels: sin and cos together, and tanh, on a block of
// rollouts (Simd<T>::V below), without branches where the lanes disagree. No XLA header: the printed
// steps' files include it alone.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

namespace fosmc {

// One block: the CPU's SIMD register (AVX-512: 64 bytes, 8 double or 16 float rollouts; AVX: 32;
// else 16). A block wider than the register takes two registers per value, and the long
// straight-line step then spills what it cannot hold (BENCHMARKS.md: "the block's width").
// -DFOSMC_SIMD_BYTES=N sets another width (an ablation: FOSMC_JAX_KERNEL_FLAGS).
#if defined(FOSMC_SIMD_BYTES)
constexpr int kBytes = FOSMC_SIMD_BYTES;
#elif defined(__AVX512F__)
constexpr int kBytes = 64;
#elif defined(__AVX__)
constexpr int kBytes = 32;
#else
constexpr int kBytes = 16;
#endif

// A block's rollouts as one GCC vector: each variable below holds one quantity of every
// rollout of the block, each operator acts lane by lane, and a comparison gives a lane mask.
template <typename T>
struct Simd {
  typedef T V __attribute__((vector_size(kBytes)));
  static constexpr int W = kBytes / sizeof(T);
  static V Load(const T* p) { V v; std::memcpy(&v, p, sizeof v); return v; }
  static void Store(T* p, V v) { std::memcpy(p, &v, sizeof v); }
  template <typename F>
  static V Map(V x, F f) {
    V r;
    for (int l = 0; l < W; l++) r[l] = f(x[l]);
    return r;
  }
  static V Abs(V x) { return Map(x, [](T a) { return std::fabs(a); }); }
  static V Sqrt(V x) { return Map(x, [](T a) { return std::sqrt(a); }); }
  static V Max(V a, V b) { return a < b ? b : a; }  // jnp.maximum on finite values (NaN in a stays)
  static V Min(V a, V b) { return b < a ? b : a; }
};

template <typename T>
using V = typename Simd<T>::V;

// sin and cos of x (|x| < 2^20), both at once, no branches: Cody-Waite reduction by pi/2, then
// the fdlibm (double) or Cephes (float) kernels, as ../shared/anchors/arm_kernel/kernel.c.
template <typename T>
inline void SinCos(V<T> x, V<T>* s, V<T>* c) {
#ifdef FOSMC_LIBM_SINCOS  // an ablation (benchmarks/arm_levers.py): libm's, lane by lane
  *s = Simd<T>::Map(x, [](T a) { return std::sin(a); });
  *c = Simd<T>::Map(x, [](T a) { return std::cos(a); });
  return;
#endif
  using I = std::conditional_t<sizeof(T) == 8, int64_t, int32_t>;
  typedef I M __attribute__((vector_size(fosmc::kBytes)));
  constexpr int shift = sizeof(T) * 8 - 2;
  T magic, two_pi, p1, p2, p3;  // 1.5 2^(mantissa bits), 2 / pi, pi / 2 in three parts
  if constexpr (sizeof(T) == 8) {
    magic = 0x1.8p52, two_pi = 0x1.45f306dc9c883p-1;
    p1 = 1.57079632673412561417e+00, p2 = 6.07710050630396597660e-11, p3 = 2.02226624871116645580e-21;
  } else {
    magic = 0x1.8p23f, two_pi = 0x1.45f306p-1f;
    p1 = 1.5703125f, p2 = 4.837512969970703125e-4f, p3 = 7.54978995489188216e-8f;
  }
  V<T> jf = x * two_pi + magic;  // j = round(x 2 / pi) in the low mantissa bits
  const M j = (M)jf;
  jf -= magic;
  V<T> r = x - jf * p1;
  r -= jf * p2;
  r -= jf * p3;
  const V<T> z = r * r;
  V<T> ps, pc;  // sin r and cos r, |r| <= pi / 4
  if constexpr (sizeof(T) == 8) {  // fdlibm's __kernel_sin, __kernel_cos
    ps = r + z * r * (-1.66666666666666324348e-01 + z * (8.33333333332248946124e-03 + z * (-1.98412698298579493134e-04 +
         z * (2.75573137070700676789e-06 + z * (-2.50507602534068634195e-08 + z * 1.58969099521155010221e-10)))));
    const V<T> qq = z * (4.16666666666666019037e-02 + z * (-1.38888888888741095749e-03 + z * (2.48015872894767294178e-05 +
                    z * (-2.75573143513906633035e-07 + z * (2.08757232129817482790e-09 + z * -1.13596475577881948265e-11)))));
    const V<T> hz = 0.5 * z, w = 1.0 - hz;
    pc = w + (((1.0 - w) - hz) + z * qq);
  } else {  // Cephes' sinf, cosf
    ps = ((-1.9515295891e-4f * z + 8.3321608736e-3f) * z - 1.6666654611e-1f) * z * r + r;
    pc = ((2.443315711809948e-5f * z - 1.388731625493765e-3f) * z + 4.166664568298827e-2f) * z * z - 0.5f * z + 1.0f;
  }
  const M swap = -(j & 1);  // odd quadrant: sin <-> cos; then the quadrant's signs
  const V<T> sn = swap ? pc : ps, cn = swap ? ps : pc;
  *s = (V<T>)((M)sn ^ ((j & 2) << shift));
  *c = (V<T>)((M)cn ^ (((j + 1) & 2) << shift));
}

// Whether every lane of a comparison's mask is set: lane by lane for 8 doubles, by 64-bit words for
// 16 floats (what ran faster for each, by a micro-benchmark of Tanh).
template <typename T, typename M>
inline bool All(M mask) {
  if constexpr (sizeof(T) == 8) {
    bool all = true;
    for (int l = 0; l < Simd<T>::W; l++) all &= mask[l] != 0;
    return all;
  } else {
    uint64_t words[sizeof(M) / 8], all = ~uint64_t(0);
    std::memcpy(words, &mask, sizeof mask);
    for (uint64_t w : words) all &= w;
    return all == ~uint64_t(0);
  }
}

// tanh x (the Coulomb term), within a few ulps of std::tanh: Cephes' tanh and tanhf. Below
// |x| = 0.625 x + x z P(z)/Q(z) (double; float: x + x z P(z)), z = x^2; above it (e - 1)/(e + 1)
// with e = exp(2 |x|) = 2^n (q + p)/(q - p), Cephes' exp in its Pade form (double; float:
// 1 - 2/(e + 1), expf's polynomial): one division in all, the two parts selected lane by lane.
// |x| is clamped to 20, where tanh is 1 to the last bit (from 19.1 in double, 9.1 in float). A
// vector whose lanes all lie in one part computes that part only (joints in motion, |q'| > 20 v_c:
// the formula's +-1 at once; at rest: the small part), with the same results. NaN stays NaN.
template <typename T>
inline V<T> Tanh(V<T> x) {
  using W = V<T>;
  using I = std::conditional_t<sizeof(T) == 8, int64_t, int32_t>;
  typedef I M __attribute__((vector_size(fosmc::kBytes)));
  constexpr I top = I(1) << (sizeof(T) * 8 - 1), bias = sizeof(T) == 8 ? 1023 : 127;
  constexpr int mant = sizeof(T) == 8 ? 52 : 23;
  const T magic = sizeof(T) == 8 ? 0x1.8p52 : 0x1.8p23f;
  const W zero = {}, ax = (W)((M)x & ~top), z = x * x;
  const M far = ax >= T(20), small = ax < T(0.625);
  const bool all_far = All<T>(far), all_small = All<T>(small);
  if (all_far) return (W)((M)(zero + 1) | ((M)x & top));
  W sn, sd;  // the small part: x + sn / sd (double), x + sn (float)
  if constexpr (sizeof(T) == 8) {
    sn = x * z * ((-9.64399179425052238628E-1 * z - 9.92877231001918586564E1) * z - 1.61468768441708447952E3);
    sd = ((z + 1.12811678491632931402E2) * z + 2.23548839060100448583E3) * z + 4.84406305325125486048E3;
    if (all_small) return x + sn / sd;
  } else {
    sn = ((((-5.70498872745E-3f * z + 2.06390887954E-2f) * z - 5.37397155531E-2f) * z + 1.33314422036E-1f) * z -
          3.33332819422E-1f) * z * x;
    if (all_small) return sn + x;
  }
  const W y = 2 * Simd<T>::Min(ax, zero + 20);  // 2 |x|, then e^y = 2^n e^r, |r| <= ln(2) / 2
  W nf = y * T(1.4426950408889634) + magic;
  const M n = (M)nf - (M)(zero + magic);
  nf -= magic;
  const W scale = (W)((n + bias) << mant);
  if constexpr (sizeof(T) == 8) {
    W r = y - nf * 6.93145751953125E-1;
    r -= nf * 1.42860682030941723212E-6;
    const W rr = r * r;
    const W p = r * ((1.26177193074810590878E-4 * rr + 3.02994407707441961300E-2) * rr + 9.99999999999999999910E-1);
    const W q = ((3.00198505138664455042E-6 * rr + 2.52448340349684104192E-3) * rr + 2.27265548208155028766E-1) * rr +
                2.00000000000000000009E0;
    const W num = (q + p) * scale - (q - p), den = (q + p) * scale + (q - p);  // e - 1, e + 1 over (q - p)
    const W ratio = (small ? sn : num) / (small ? sd : den);
    return small ? x + ratio : (W)((M)ratio | ((M)x & top));
  } else {
    W r = y - nf * 0.693359375f;
    r -= nf * -2.12194440e-4f;
    const W e = (((((1.9875691500E-4f * r + 1.3981999507E-3f) * r + 8.3334519073E-3f) * r + 4.1665795894E-2f) * r +
                  1.6666665459E-1f) * r + 5.0000001201E-1f) * (r * r) + r + 1.0f;
    const W big = 1.0f - 2.0f / (e * scale + 1.0f);
    return small ? sn + x : (W)((M)big | ((M)x & top));
  }
}

}  // namespace fosmc
