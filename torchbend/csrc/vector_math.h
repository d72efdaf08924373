// The vectorizable elementary functions of torchbend's compiled kernels (included by hinge_math.h): the
// host/device spellings of the C functions, branch-free sincos, atan2, floor, ceil, and the half-angle sin, cos
// and tan of the bend angle, one definition for the CPU lane loops (g++, vectorized across the lanes of a tile)
// and the GPU (nvcc).  Their accuracy against a 40-digit reference: tests/test_vector_math_ulp.py.  The platform
// macros (TB_HD, TB_FORCEINLINE, the lane loops) are defined here.
#pragma once

#include <cfloat>
#include <cmath>
#include <cstdint>

#if defined(__CUDACC__)
#define TB_HD __host__ __device__
#define TB_FORCEINLINE __forceinline__
#define TB_SIMD
#define TB_IVDEP
#else
#define TB_HD
#define TB_FORCEINLINE inline __attribute__((always_inline))
#define TB_SIMD _Pragma("omp simd")
#if defined(__clang__)
#define TB_IVDEP _Pragma("clang loop vectorize(assume_safety)")
#else
#define TB_IVDEP _Pragma("GCC ivdep")
#endif
#endif
// A loop over the W lanes of a tile, vectorized across hinges on the CPU.  TB_LANES (`omp simd`) is for
// bodies of scalar locals only: GCC turns every aggregate or address-taken local of an `omp simd` body
// into a per-lane array in memory, which defeats vectorization.  Bodies that use the V3 / Tri values of
// tri_frame take TB_LANES_AGG (`ivdep`: no loop-carried dependences, no privatization), whose locals
// become registers; it vectorizes when the cost model agrees, which with -fno-math-errno (sqrt without
// its errno branch) it does.
#define TB_LANES(W) TB_SIMD for (int l = 0; l < (W); ++l)
#define TB_LANES_AGG(W) TB_IVDEP for (int l = 0; l < (W); ++l)

namespace torchbend {


// ---- scalar helpers (host and device spellings of the same C functions) ----------------------
// the float and the double overload of a unary C function (fname, dname: its float and double spellings)
#define TB_UNARY_PAIR(QUAL, name, fname, dname) \
  QUAL float name(float v) { return fname(v); } \
  QUAL double name(double v) { return dname(v); }
TB_UNARY_PAIR(TB_HD static inline, tb_sqrt, sqrtf, sqrt)
TB_UNARY_PAIR(TB_HD static inline, tb_tan, tanf, tan)
TB_UNARY_PAIR(TB_HD static inline, tb_sin, sinf, sin)
TB_UNARY_PAIR(TB_HD static inline, tb_cos, cosf, cos)
TB_UNARY_PAIR(TB_HD static inline, tb_ceil, ceilf, ceil)
TB_UNARY_PAIR(TB_HD static inline, tb_floor, floorf, floor)
TB_HD static inline float tb_atan2(float y, float x) { return atan2f(y, x); }
TB_HD static inline double tb_atan2(double y, double x) { return atan2(y, x); }
TB_HD static inline float tb_eps(float) { return FLT_EPSILON; }
TB_HD static inline double tb_eps(double) { return DBL_EPSILON; }
template <typename T> TB_HD static inline T tb_max(T a, T b) { return a < b ? b : a; }  // as std::max

// fdlibm's __kernel_sin and __kernel_cos of x = y0 + y1, |x| <= pi/4 (y1: the tail of a reduced argument), each
// result as an unevaluated sum: sin(y0 + y1) ~ ks + ksl and cos(y0 + y1) ~ kc + kcl, the last addition of each
// kernel carried exactly by Fast2Sum (|y0| and |w1| exceed the terms added to them; no product in either chain, so
// that contraction cannot break it).  What is left (a review's scan against a 40-digit
// reference, 2026-12-06): the sum within 0.18 ulp of sin and 0.28 ulp of cos, mostly the rounding of z = y0^2, which
// reaches w1 = 1 - z/2 itself near |y0| = pi/4.  ks and kc alone are fdlibm's values (tb_sincos_kernel; the tails
// are then dead code); where the compiler fuses a product into an fma differently (e.g. with a literal y1 = 0 it
// drops the y1 terms), they may differ in the last bit between inlining contexts.
TB_HD static TB_FORCEINLINE void tb_sincos_kernel_pair(double y0, double y1, double& ks, double& ksl, double& kc,
                                                       double& kcl) {
  double z = y0 * y0, v = z * y0;
  double rs = 8.33333333332248946124e-03 + z * (-1.98412698298579493134e-04 + z * (2.75573137070700676789e-06 +
              z * (-2.50507602534068634195e-08 + z * 1.58969099521155010221e-10)));
  double ps = (z * (0.5 * y1 - v * rs) - y1) - v * -1.66666666666666324348e-01;
  ks = y0 - ps;
  ksl = (y0 - ks) - ps;
  double zz = z * z;
  double rc = z * (4.16666666666666019037e-02 + z * (-1.38888888888741095749e-03 + z * 2.48015872894767294178e-05)) +
              zz * zz * (-2.75573143513906633035e-07 + z * (2.08757232129817482790e-09 + z * -1.13596475577881948265e-11));
  double hz = 0.5 * z, w1 = 1.0 - hz;
  double pc = ((1.0 - w1) - hz) + (z * rc - y0 * y1);
  kc = w1 + pc;
  kcl = (w1 - kc) + pc;
}

// ks and kc alone (the kernels of tb_sincos)
TB_HD static TB_FORCEINLINE void tb_sincos_kernel(double y0, double y1, double& ks, double& kc) {
  double ksl, kcl;
  tb_sincos_kernel_pair(y0, y1, ks, ksl, kc, kcl);
}

// ---- vectorizable sin/cos and atan2 (the CPU lane loops; the same code on the GPU) --------------
// The C library's sin, cos and atan2 are calls that no lane loop vectorizes, and in the energy and
// gradient kernels they cost more than all the geometry.  tb_sincos and tb_atan2v are branch-free
// (selects only, no library calls), so that GCC vectorizes them across the lanes of a tile; the CUDA
// driver compiles the same definitions (TB_HD; rint, fabs, copysign and fma are the C functions, builtins
// of both compilers), so that both devices compute the same values.  Double: fdlibm's kernels
// (__kernel_sin / __kernel_cos on [-pi/4, pi/4] with a two-part Cody-Waite reduction by pi/2, and
// __ieee754_rem_pio2's second and third steps near a multiple of pi/2; atan's polynomial on |t| < 7/16 with
// the reductions about 1/2 and 1, the division's rounding error carried, hi/lo constants per octant, huge
// and tiny arguments scaled by a power of two).  Float: the double evaluation rounded once (correctly
// rounded but for the double rounding).  Both within 0.8 ulp of the exact value (tests/test_vector_math_ulp.py:
// a 40-digit reference, -march=native and x86-64-v3, signed zeros, +-pi, subnormal and huge arguments).
// tb_sincos: |x| < 2^19 (the kernels take half-angles; beyond it the reduction loses accuracy, and inf
// or NaN give NaN), sin(-0) = -0.  tb_atan2v: every finite argument, IEEE's signed zeros and quadrants
// (atan2(+-0, -0) = +-pi), NaN in -> NaN out; infinite arguments are not supported (the kernels' are finite).
// tb_sincos: fdlibm's first reduction step (pi/2 in 33 + 53 bits): within 1 ulp wherever the reduced
// argument keeps its digits, which is all of [-pi/4, pi/4] (no reduction: the kernels' half angles) and every
// |x| < 2^19 but within about |q| 2^-22 of a nonzero multiple q pi/2 (there sin or cos is tiny and loses
// digits: cos(pi/2) by 1e6 ulps).  The kernels take it where such a value is never the one they use (see
// phi_diff).  tb_sincos_accurate adds fdlibm's second and third steps (pi/2 to 152 bits), computed for every
// lane and selected near those multiples: within 1 ulp over all of |x| < 2^19, at about 20% of an energy.
template <bool Accurate>
TB_HD static TB_FORCEINLINE void tb_sincos_impl(double x, double& s, double& c) {
  const double two_over_pi = 6.36619772367581382433e-01;
  const double pio2_1 = 1.57079632673412561417e+00;   // first 33 bits of pi/2 (q * pio2_1 exact)
  const double pio2_1t = 6.07710050650619224932e-11;  // pi/2 - pio2_1
  const double pio2_2 = 6.07710050630396597660e-11;   // second 33 bits of pi/2
  const double pio2_2t = 2.02226624879595063154e-21;  // pi/2 - pio2_1 - pio2_2
  const double pio2_3 = 2.02226624871116645580e-21;   // third 33 bits of pi/2
  const double pio2_3t = 8.47842766036889956997e-32;  // pi/2 - pio2_1 - pio2_2 - pio2_3
  // + 0.0: q = +0 for x = -0, so that r = -0 and sin(-0) = -0 (the same q, r for every other x)
  double q = rint(x * two_over_pi) + 0.0;
  double r = x - q * pio2_1, w = q * pio2_1t;
  double y0 = r - w, y1 = (r - y0) - w;  // x - q pi/2 = y0 + y1, to about |q| 1.3e-26
  // Near a multiple of pi/2 (|y0| < |q| 2^-22) that is too few digits of pi: fdlibm's second and third
  // steps (__ieee754_rem_pio2: pi/2 to 152 bits), computed for every lane and selected
  if constexpr (Accurate) {
    double t2 = r, w2 = q * pio2_2, r2 = t2 - w2;
    w2 = q * pio2_2t - ((t2 - r2) - w2);
    double t3 = r2, w3 = q * pio2_3, r3 = t3 - w3;
    w3 = q * pio2_3t - ((t3 - r3) - w3);
    double y0c = r3 - w3, y1c = (r3 - y0c) - w3;
    bool cancel = fabs(y0) < fabs(q) * 0x1p-22;
    y0 = cancel ? y0c : y0;
    y1 = cancel ? y1c : y1;
  }
  double ks, kc;
  tb_sincos_kernel(y0, y1, ks, kc);
  // quadrant n = q mod 4: (sin, cos) = (ks, kc), (kc, -ks), (-ks, -kc), (-kc, ks)
  int n = int(q) & 3;
  bool odd = (n & 1) != 0;
  double ss = odd ? kc : ks, cc = odd ? ks : kc;
  s = ss * double(1 - (n & 2));  // -ss for n = 2, 3 (a product by +-1, not a blend)
  c = cc * double(1 - ((n + 1) & 2));  // -cc for n = 1, 2
}
TB_HD static TB_FORCEINLINE void tb_sincos(double x, double& s, double& c) { tb_sincos_impl<false>(x, s, c); }
TB_HD static TB_FORCEINLINE void tb_sincos_accurate(double x, double& s, double& c) { tb_sincos_impl<true>(x, s, c); }

// 1 where v's sign bit is set (v < 0 or v = -0), else 0, by arithmetic on the sign: the selects below are
// written as such 0/1 weights because GCC turns arithmetic on selects of constants into blends, which cost 3
// uops each on recent Intel cores without AVX-512 masks (and 2 on older ones)
TB_HD static TB_FORCEINLINE double tb_neg01(double v) { return 0.5 - copysign(0.5, v); }

// tb_atan2v in two stages (tb_atan2v_reduce, then tb_atan2v_finish; tb_atan2v is the two in a row): a lane loop of
// the reduction and one of the polynomial each keep a shorter chain of dependent operations than the whole, so
// that the out-of-order window holds more of the tile's independent lanes (theta_tile, hinge_ops.h)
TB_HD static TB_FORCEINLINE void tb_atan2v_reduce(double y, double x, double& t_, double& tl_, double& sg_,
                                                  double& khi_, double& klo_) {
  double ax = fabs(x), ay = fabs(y);
  // swapped (ay > ax: atan2 = pi/2 - atan(ax / ay)): num = min, den = max (a NaN y makes both NaN)
  double num = ay > ax ? ax : ay, den = ay > ax ? ay : ax;
  double sw = tb_neg01(ax - ay);  // 1 if swapped (a tie gives +0: not swapped)
  // huge or tiny arguments scaled by a power of two (exact, and t, tl are scale-invariant): 16 num, 7 den and
  // 2 den + num stay finite near DBL_MAX, and the quotient's residual stays normal where num is tiny (below 2^-900,
  // with den below 2^880, so that 2^120 den stays finite: a tiny num over a moderate den left the residual
  // subnormal, and t = tn (1/td) uncorrected up to 1.4 ulps)
  double big = tb_neg01(0x1p1000 - den), tiny = tb_neg01(num - 0x1p-900) * tb_neg01(den - 0x1p880);
  double sc = ((1.0 - big) + big * 0x1p-60) * ((1.0 - tiny) + tiny * 0x1p120);
  num *= sc; den *= sc;
  // atan2(+-0, +-0): t = 0 (every other den is at least 2^-954 here; a normal floor, so that it holds with
  // denormals flushed to zero too)
  den = den < 0x1p-1000 ? 0x1p-1000 : den;
  // z = num / den in [0, 1], reduced to |t| < 7/16 with one division: t = z (m0: z < 7/16),
  // (2z - 1) / (2 + z) about A = atan(1/2) (m1: z < 11/16), (z - 1) / (z + 1) about A = atan(1) (m2: else);
  // ties give +0 (not below).  The sign of 16 num - RN(7 den), as the comparison 16 num < 7 den: an explicit fma
  // with the exact 16 num, so that no contraction (nvcc's default, GCC's -ffp-contract=fast) forms it from the
  // exact 7 den instead
  double m0 = tb_neg01(fma(16.0, num, -(7.0 * den))), m01 = tb_neg01(fma(16.0, num, -(11.0 * den)));
  double m1 = m01 - m0, m2 = 1.0 - m01;
  double f = 1.0 + m1, g = 1.0 - m0;  // every product below exact: one rounding per sum, as the three forms
  double tn = f * num - g * den, td = f * den + g * num;
  // one division: t = tn (1 / td) is within about 1.5 ulps of the quotient, and its residual tn - t td by an fma
  // (exact where t is within an ulp of the quotient, rounded in the few lanes where it is not) times 1 / td corrects
  // it: t + tl = tn / td to about 2^-104 relative, as with a second division (a 512-bit division issues once in
  // about 9 cycles on an AVX-512 Xeon, a square root once in 12).  t itself may differ from the correctly rounded
  // quotient: the result's last bit differs from the two-division form for about 0.1% of arguments, within the
  // same 1-ulp bound
  double rd = 1.0 / td;
  double t = tn * rd;
  double tl = fma(-t, td, tn) * rd;  // the rounding error of t: t + tl = tn / td
  t_ = t; tl_ = tl;
  // atan2(|y|, x) = K + sg atan(t + tl) with K = Q pi/2 + sg A: A (Q = 0, sg = 1), pi/2 - A (swapped: Q = 1,
  // sg = -1), pi - A (x < 0: Q = 2, sg = -1), pi/2 + A (both: Q = 1, sg = 1); x < 0 by its sign bit (atan2(+-0, -0)
  // = +-pi) (x = -0, y != 0: swapped with t = 0, pi/2 either way).  A (0, atan(1/2) or pi/4) as an exact blend (0/1
  // weights times constants with at most one weight 1) in hi + lo; K's head Q pi/2 + sg A_hi (both products exact,
  // the sum rounded once, its error by Fast2Sum: |Q pi/2| >= pi/2 > |A| wherever Q is not 0), its tail the error plus
  // Q (pi/2)_lo + sg A_lo: K to about 2^-104 relative, as from the four precomputed pairs, in half the operations
  double xn = tb_neg01(x);
  double ah = m1 * 0.4636476090008061 + m2 * 0.7853981633974483;  // A
  double al = m1 * 2.2698777452961687e-17 + m2 * 3.061616997868383e-17;
  double sg = (1.0 - 2.0 * sw) * (1.0 - 2.0 * xn);
  double Q = sw + 2.0 * xn * (1.0 - sw);
  double qh = Q * 1.5707963267948966, sa = sg * ah;
  double khi = qh + sa;
  double klo = (sa - (khi - qh)) + (Q * 6.123233995736766e-17 + sg * al);
  sg_ = sg; khi_ = khi; klo_ = klo;
}
TB_HD static TB_FORCEINLINE double tb_atan2v_finish(double y, double x, double t, double tl, double sg, double khi,
                                                    double klo) {
  double z = t * t, w = z * z;
  double s1 = z * (3.33333333333329318027e-01 + w * (1.42857142725034663711e-01 + w * (9.09088713343650656196e-02 +
              w * (6.66107313738753120669e-02 + w * (4.97687799461593236017e-02 + w * 1.62858201153657823623e-02)))));
  double s2 = w * (-1.99999999998764832476e-01 + w * (-1.11111104054623557880e-01 + w * (-7.69187620504482999495e-02 +
              w * (-5.83357013379057348645e-02 + w * -3.65315727442169155270e-02))));
  double corr = (tl - tl * z) - t * (s1 + s2);  // atan(t + tl) = t + corr
  double res = khi + (sg * t + (sg * corr + klo));
  res += x - x;  // a NaN x gives NaN (num and den are y's there)
  return copysign(res, y);
}
TB_HD static TB_FORCEINLINE double tb_atan2v(double y, double x) {
  double t, tl, sg, khi, klo;
  tb_atan2v_reduce(y, x, t, tl, sg, khi, klo);
  return tb_atan2v_finish(y, x, t, tl, sg, khi, klo);
}

// log(x) within 1 ulp for every x >= 0 (subnormals too; 0: -inf, +inf: +inf, negative or NaN: NaN): fdlibm's
// __ieee754_log (x = 2^k m, m in [sqrt(2)/2, sqrt(2)), f = m - 1, s = f / (2 + f), log(1 + f) = 2s + s R(s^2) with
// its Lg1..Lg7 and ln2 in two parts), branch-free: both of its final forms computed and selected, subnormals
// scaled by 2^54 first, so that a lane loop vectorizes it (the C library's log is a call).  Float: the double
// evaluation rounded once.  Tests: tests/test_vector_math_ulp.py (a 40-digit reference).
TB_HD static TB_FORCEINLINE double tb_logv(double x) {
  const double Lg1 = 6.666666666666735130e-01, Lg2 = 3.999999999940941908e-01, Lg3 = 2.857142874366239149e-01,
               Lg4 = 2.222219843214978396e-01, Lg5 = 1.818357216161805012e-01, Lg6 = 1.531383769920937332e-01,
               Lg7 = 1.479819860511658591e-01;
  const double ln2_hi = 6.93147180369123816490e-01, ln2_lo = 1.90821492927058770002e-10;
  const bool sub = x < 2.2250738585072014e-308;
  const double xs = sub ? x * 18014398509481984.0 : x;  // 2^54
  // in 64-bit integer lanes only (no int32 <-> int64 or int -> double conversions, which AVX2 lacks): the
  // exponent becomes a double through the 2^52 bias
  uint64_t b;
  __builtin_memcpy(&b, &xs, sizeof b);
  const int64_t hx = int64_t((b >> 32) & 0x000fffffull), e = int64_t((b >> 52) & 0x7ffull);
  const int64_t i = (hx + 0x95f64) & 0x100000;
  const uint64_t nb = (uint64_t(hx | (i ^ 0x3ff00000)) << 32) | (b & 0xffffffffull);
  double m;
  __builtin_memcpy(&m, &nb, sizeof m);  // x or x / 2 normalized into [sqrt(2)/2, sqrt(2))
  const uint64_t kb = 0x4330000000000000ull | uint64_t(e + (i >> 20));  // 2^52 + biased exponent
  double kd;
  __builtin_memcpy(&kd, &kb, sizeof kd);
  const double dk = (kd - 4503599627370496.0) - (sub ? 1077.0 : 1023.0);  // exact
  const double f = m - 1.0;
  const double s = f / (2.0 + f), z = s * s, w = z * z;
  const double t1 = w * (Lg2 + w * (Lg4 + w * Lg6)), t2 = z * (Lg1 + w * (Lg3 + w * (Lg5 + w * Lg7)));
  const double R = t2 + t1, hfsq = 0.5 * f * f;
  const double wide = dk * ln2_hi - ((hfsq - (s * (hfsq + R) + dk * ln2_lo)) - f);
  const double narrow = dk * ln2_hi - ((s * (f - R) - dk * ln2_lo) - f);
  double r = (hx >= 0x6147a) & (hx <= 0x6b851) ? wide : narrow;
  r = x == 0.0 ? -HUGE_VAL : r;
  r = x > 1.7976931348623157e308 ? x : r;  // +inf
  return x >= 0.0 ? r : NAN;  // one comparison: false for negatives and NaN
}
TB_HD static TB_FORCEINLINE float tb_logv(float x) { return float(tb_logv(double(x))); }

// floor and ceil from rint (exact for finite values): GCC vectorizes rint but not floor/ceil here
TB_HD static TB_FORCEINLINE double tb_floorv(double v) { double r = rint(v); return r > v ? r - 1.0 : r; }
TB_HD static TB_FORCEINLINE double tb_ceilv(double v) { double r = rint(v); return r < v ? r + 1.0 : r; }
TB_HD static TB_FORCEINLINE float tb_floorv(float v) { float r = rintf(v); return r > v ? r - 1.0f : r; }
TB_HD static TB_FORCEINLINE float tb_ceilv(float v) { float r = rintf(v); return r < v ? r + 1.0f : r; }

TB_HD static TB_FORCEINLINE void tb_sincos(float x, float& s, float& c) {
  double sd, cd;
  tb_sincos(double(x), sd, cd);
  s = float(sd); c = float(cd);
}
TB_HD static TB_FORCEINLINE void tb_sincos_accurate(float x, float& s, float& c) {
  double sd, cd;
  tb_sincos_accurate(double(x), sd, cd);
  s = float(sd); c = float(cd);
}
TB_HD static TB_FORCEINLINE float tb_atan2v(float y, float x) { return float(tb_atan2v(double(y), double(x))); }

// sin(t/2) and cos(t/2) to a few ulps for t in [-pi, pi], near +-pi too (torchbend.ops.psi.half_angle_sincos):
// for |t| > pi/2 from the complement w = (pi - |t|)/2, formed exactly (pi_hi - |t| by Sterbenz, then the
// tail pi_lo), sin(t/2) = sign(t) cos(w), cos(t/2) = sin(w): t/2 rounded (and a reduction by pi/2 that keeps
// too few digits of pi) would make the tiny cosine near +-pi wrong in most of its digits.  One tb_sincos of
// an argument in [-pi/4, pi/4] (for |t| <= 3 pi / 2; any |t| < 2^19 is reduced); branch-free.  (The reference
// angles take it; a bend angle takes tb_half_sincos_tan below.)
template <typename T> TB_HD static TB_FORCEINLINE void tb_half_sincos(T t, T& s, T& c) {
  const T pi_hi = T(3.14159265358979323846);
  const T pi_lo = sizeof(T) == sizeof(float) ? T(-8.742278000372485e-08) : T(1.2246467991473532e-16);
  T a = fabs(t);  // (+0 for -0, where the old select gave -0: the same w, and big is false)
  bool big = a > T(0.5) * pi_hi;
  T w = T(0.5) * ((pi_hi - a) + pi_lo);
  T sn, cs;
  tb_sincos(big ? w : T(0.5) * t, sn, cs);
  s = big ? cs * copysign(T(1), t) : sn;  // -cs for t < 0 (cs < 0 too where |t| > 2 pi: a product, not copysign)
  c = big ? sn : cs;
}

// sin(t/2), cos(t/2) and tan(t/2) of a bend angle t in [-pi, pi] (a little beyond, to the float pi), each within
// 1 ulp (tests/test_vector_math_ulp.py), by one evaluation of the sin/cos kernels and one division: |t| <= pi/2 at
// x = t/2 (exact but for subnormal t); |t| > pi/2 from the complement x + y = ((pi_hi - |t|) + pi_lo) / 2 as a
// normalized pair (pi_hi - |t| exact by Sterbenz, pi's tail carried as the kernels' y: near +-pi the small cosine
// keeps its digits), sin(t/2) = sign(t) cos(x + y), cos(t/2) = sin(x + y).  The kernels' results carry their last
// rounding (tb_sincos_kernel_pair), so that tan = (s + sl) / (c + cl) is formed with one reciprocal and the quotient's
// residual (against 2.2 ulps for the rounded s / c; fdlibm's tan kernel for tan(t/2) alone cost an HVP ~5% more).
// Measured (a review's scan of about 12 million arguments against a 40-digit reference, 2026-12-06): sin 0.78, cos
// 0.75, tan 0.92 ulps with GCC's fused multiply-adds (-march=native and x86-64-v3), tan 0.98 without fusion; the
// worst tan near t = pi/2 (tan(t/2) just below 1).  Float: the double evaluation rounded once (0.5 ulp).  Wrong
// beyond |t| = 3 pi / 2 (no reduction).  Branch-free.
TB_HD static TB_FORCEINLINE void tb_half_sincos_tan(double t, double& s, double& c, double& u) {
  const double pi_hi = 3.14159265358979311600e+00, pi_lo = 1.22464679914735320717e-16;
  double a = fabs(t);
  bool big = a > 0.5 * pi_hi;
  double h = 0.5 * (pi_hi - a), l = 0.5 * pi_lo;
  double hs = h + l, ls = l - (hs - h);  // Fast2Sum: h is 0 or a multiple of ulp(pi) / 4 > l
  double x = big ? hs : 0.5 * t, y = big ? ls : 0.0;
  double ks, ksl, kc, kcl;
  tb_sincos_kernel_pair(x, y, ks, ksl, kc, kcl);
  double sg = copysign(1.0, t);
  s = big ? kc * sg : ks;
  double sl = big ? kcl * sg : ksl;
  c = big ? ks : kc;
  double cl = big ? ksl : kcl;
  double r = 1.0 / c;
  double q = s * r;
  double e = (fma(-q, c, s) + sl) - q * cl;  // (s + sl) - q (c + cl): the fma's residual exact where q is within an ulp
  u = q == 0.0 ? q : fma(e, r, q);  // (tan(-0) = -0: the correction +0 would give +0)
}
TB_HD static TB_FORCEINLINE void tb_half_sincos_tan(float t, float& s, float& c, float& u) {
  double sd, cd, ud;
  tb_half_sincos_tan(double(t), sd, cd, ud);
  s = float(sd); c = float(cd); u = float(ud);
}

}  // namespace torchbend
