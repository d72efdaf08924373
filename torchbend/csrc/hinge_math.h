// Per-hinge mathematics of torchbend's compiled kernels: the bend angle, psi' and psi'' of the three
// models, the half-hinge quantities, the closed-form 12x12 blocks and angle gradients, and the 9x9
// per-triangle blocks of the triangle assembly.  It mirrors the eager reference in torchbend/ops
// (hinge.py, psi.py, triangle.py), which the tests compare against.
//
// No torch, no std:: containers, no std:: math (the C functions, which nvcc also has on the device)
// and no pragmas outside the TB_SIMD / TB_IVDEP macros: every function is `TB_HD static inline` (or a
// template), so that a CUDA driver can compile this header with nvcc (TB_HD = __host__ __device__
// there, the loop pragmas empty) as the CPU driver (cpu_*.cpp) does with g++.
//
// Hinges are handled in tiles of W lanes with every quantity stored as [component][lane]: on the CPU,
// W = 16 or 8 and each formula is vectorized across the lanes of a tile; a GPU driver takes W = 1 (one
// hinge per thread).  The CPU build passes -fno-math-errno, without which no loop that takes a square
// root vectorizes (see TB_LANES_AGG).
#pragma once

#include "vector_math.h"

namespace torchbend {

template <typename T> TB_HD static inline void cross(const T* u, const T* v, T* o) {
  o[0] = u[1] * v[2] - u[2] * v[1]; o[1] = u[2] * v[0] - u[0] * v[2]; o[2] = u[0] * v[1] - u[1] * v[0];
}
template <typename T> TB_HD static inline T dot(const T* u, const T* v) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }

// ---- one triangle ----------------------------------------------------------------------------
// 3-vectors by value: in the lane loops they become one register per component (see TB_LANES_AGG)
template <typename T> struct V3 { T x, y, z; };
template <typename T> TB_HD static TB_FORCEINLINE V3<T> sub3(V3<T> u, V3<T> v) { return {u.x - v.x, u.y - v.y, u.z - v.z}; }
template <typename T> TB_HD static TB_FORCEINLINE V3<T> scale3(V3<T> u, T s) { return {u.x * s, u.y * s, u.z * s}; }
template <typename T> TB_HD static TB_FORCEINLINE T dot3(V3<T> u, V3<T> v) { return u.x * v.x + u.y * v.y + u.z * v.z; }
template <typename T> TB_HD static TB_FORCEINLINE V3<T> cross3(V3<T> u, V3<T> v) {
  return {u.y * v.z - u.z * v.y, u.z * v.x - u.x * v.z, u.x * v.y - u.y * v.x};
}

// The quantities of a triangle p0 p1 p2 that both the half-hinge tiles and the per-triangle blocks
// need, from its cyclic edge vectors e_k = p_{k+2} - p_{k+1} (edge k is opposite p_k), written with the
// unnormalized normal N (twice the area times the unit normal; torchbend.ops.hinge, "Accuracy"):
// N = e_{m+1} x e_{m+2} from the two shortest edges (m the longest: the cross product at the largest angle
// keeps N's relative error near eps, where the others lose eps / sin(smallest angle)),
// valid = |N| > eps max_k |e_k|^2 (degenerate, collinear triangles give zeros: torchbend.ops.hinge's
// policy), nn = |N|^2 (1 if not valid), inn = 1/|N|^2 (0 if not valid) and mh_k = (e_k x N) inn = m_k / h_k
// (the outward edge normal over the height on edge k).
template <typename T> struct Tri {
  T ee0, ee1, ee2;            // |e_k|^2
  T valid;                    // 1 if valid, else 0 (a number, not a bool: it stays in a vector lane)
  T nn, inn;                  // |N|^2 and 1/|N|^2 (1 and 0 if not valid)
  V3<T> N, mh0, mh1, mh2;     // normal, (e_k x N) / |N|^2
};

template <typename T> TB_HD static TB_FORCEINLINE V3<T> pick3(bool c, V3<T> a, V3<T> b) {
  return {c ? a.x : b.x, c ? a.y : b.y, c ? a.z : b.z};
}

// (tri_normal: all but the mh_k, which tri_frame adds)
template <typename T> TB_HD static TB_FORCEINLINE Tri<T> tri_normal(V3<T> e0, V3<T> e1, V3<T> e2) {
  Tri<T> t;
  t.ee0 = dot3(e0, e0); t.ee1 = dot3(e1, e1); t.ee2 = dot3(e2, e2);
  // the longest edge m: 2 if e2 is (ties included), else 0 if e0 is at least as long as e1, else 1
  bool m2 = t.ee2 >= t.ee1 && t.ee2 >= t.ee0, m0 = !m2 && t.ee0 >= t.ee1;
  // m = 2: e0 x e1, m = 0: e1 x e2, m = 1: e2 x e0
  t.N = cross3(pick3(m2, e0, pick3(m0, e1, e2)), pick3(m2, e1, pick3(m0, e2, e0)));
  T nn = dot3(t.N, t.N);
  bool valid = tb_sqrt(nn) > tb_eps(T(0)) * tb_max(tb_max(t.ee2, t.ee1), t.ee0);
  t.valid = valid ? T(1) : T(0);
  t.nn = valid ? nn : T(1);
  t.inn = t.valid / t.nn;
  return t;
}
template <typename T> TB_HD static TB_FORCEINLINE Tri<T> tri_frame(V3<T> e0, V3<T> e1, V3<T> e2) {
  Tri<T> t = tri_normal(e0, e1, e2);
  t.mh0 = scale3(cross3(e0, t.N), t.inn); t.mh1 = scale3(cross3(e1, t.N), t.inn); t.mh2 = scale3(cross3(e2, t.N), t.inn);
  return t;
}

// ---- half-hinges -----------------------------------------------------------------------------
// One half-hinge (a, b, c) = (x0, x1, wing) of W hinges: t_k = rho_k / |N| (the angle gradient of vertex
// k is t_k N; k = 0: vertex a, 1: b, 2: the wing c), the normal N, mh[k] = m_k / h_k and bl = N / |e|^3
// (the B term is bl mh[2]^T); zeros where degenerate.
template <typename T, int W> struct Half { T t[3][W], N[3][W], mh[3][3][W], bl[3][W]; };

// EL and IE: |e| and 1 / |e| of the shared edge e = b - a (both halves take them: one square root and one division
// a hinge instead of two each; 1 and 1 where the triangle is degenerate, as ee = 1 gave).
// Full = false: t and N only (what the angle gradient takes): mh and bl are left unwritten and the compiler drops
// their cross products (the same t and N bits; with GCC 12 on AVX-512 the gradient's half-hinge tile became one
// unrolled pass of 315 instructions and 12 square roots and divisions per 16 hinges, from two loops executing about
// 600 instructions and 16 square roots and divisions)
// the t_k of lane l of a half-hinge (both forms of half_tile) from its edges e = b - a, e0 = c - b, e1 = a - c, its
// validity and inn = 1 / |N|^2; returns 1 / |e| (1 where degenerate), which the full form's bl takes
template <typename T, int W>
TB_HD static TB_FORCEINLINE T half_t_lane(V3<T> e, V3<T> e0, V3<T> e1, T valid, T inn, const T* EL, const T* IE,
                                          Half<T, W>& o, int l) {
  T elen = valid != T(0) ? EL[l] : T(1);
  T ie = valid != T(0) ? IE[l] : T(1);  // reciprocals: divisions here cost the blocks ~10%
  o.t[0][l] = -dot3(e, e0) * ie * inn;  // -(e . (c - b)) / (|e| |N|^2)
  o.t[1][l] = -dot3(e, e1) * ie * inn;  //  (e . (c - a)) / (|e| |N|^2)
  o.t[2][l] = -elen * inn;
  return ie;
}

// Full: two lane loops (the normal, then what it takes: the same operations), for the reason theta_tile gives
// (hinge_ops.h): the HVP on a Zen 4 EPYC 44.4 -> 42.9 ns a hinge (x86-64-v3, against the split angle alone).  The
// angle gradient's short form (Full = false) measured slower split (31.7 -> 32.3): it is the first loop alone, with
// the t_k written there.
template <typename T, int W, bool Full = true>
TB_HD static inline void half_tile(const T (*A)[W], const T (*Bv)[W], const T (*C)[W], const T (*E)[W], const T* EL,
                                   const T* IE, Half<T, W>& o) {
  [[maybe_unused]] T INN[W], VAL[W];  // the full form's, for its second loop
  TB_LANES_AGG(W) {
    V3<T> a{A[0][l], A[1][l], A[2][l]}, b{Bv[0][l], Bv[1][l], Bv[2][l]}, c{C[0][l], C[1][l], C[2][l]};
    V3<T> e{E[0][l], E[1][l], E[2][l]};
    // the triangle's cyclic edges: e_0 = c - b (opposite a), e_1 = a - c (opposite b), e_2 = e = b - a
    V3<T> e0 = sub3(c, b), e1 = sub3(a, c);
    Tri<T> t = tri_normal(e0, e1, e);
    o.N[0][l] = t.N.x; o.N[1][l] = t.N.y; o.N[2][l] = t.N.z;
    if constexpr (Full) {
      INN[l] = t.inn; VAL[l] = t.valid;
    } else {
      half_t_lane<T, W>(e, e0, e1, t.valid, t.inn, EL, IE, o, l);
    }
  }
  if constexpr (Full) {
    TB_LANES_AGG(W) {
      V3<T> a{A[0][l], A[1][l], A[2][l]}, b{Bv[0][l], Bv[1][l], Bv[2][l]}, c{C[0][l], C[1][l], C[2][l]};
      V3<T> e{E[0][l], E[1][l], E[2][l]};
      V3<T> e0 = sub3(c, b), e1 = sub3(a, c);
      V3<T> N{o.N[0][l], o.N[1][l], o.N[2][l]};
      T inn = INN[l];
      T ie = half_t_lane<T, W>(e, e0, e1, VAL[l], inn, EL, IE, o, l);
      T r = ie * ie * ie;
      V3<T> mh0 = scale3(cross3(e0, N), inn), mh1 = scale3(cross3(e1, N), inn), mh2 = scale3(cross3(e, N), inn);
      o.mh[0][0][l] = mh0.x; o.mh[0][1][l] = mh0.y; o.mh[0][2][l] = mh0.z;
      o.mh[1][0][l] = mh1.x; o.mh[1][1][l] = mh1.y; o.mh[1][2][l] = mh1.z;
      o.mh[2][0][l] = mh2.x; o.mh[2][1][l] = mh2.y; o.mh[2][2][l] = mh2.z;
      o.bl[0][l] = N.x * r; o.bl[1][l] = N.y * r; o.bl[2][l] = N.z * r;
    }
  }
}

// both half-hinges (triangles A = x0 x1 x2, B = x0 x1 x3) of W stencils X[3 * vertex + axis][lane]; Full = false:
// t and N only (half_tile), for the angle gradient alone
template <typename T, int W, bool Full = true>
TB_HD static inline void halves_tile(const T (*X)[W], Half<T, W>& hA, Half<T, W>& hB) {
  T E[3][W], EL[W], IE[W];
  for (int p = 0; p < 3; ++p) TB_LANES(W) E[p][l] = X[3 + p][l] - X[p][l];
  TB_LANES_AGG(W) {
    V3<T> e{E[0][l], E[1][l], E[2][l]};
    EL[l] = tb_sqrt(dot3(e, e));
    IE[l] = T(1) / EL[l];
  }
  half_tile<T, W, Full>(X, X + 3, X + 6, E, EL, IE, hA);
  half_tile<T, W, Full>(X, X + 3, X + 9, E, EL, IE, hB);
}

// ---- bend angle and psi --------------------------------------------------------------------------

// phi(theta') - phi(ref) and phi', phi'' at theta' (torchbend.ops.psi.phi_difference): model 0 quadratic,
// 1 tan, 2 sin.  theta' = ref + wrap(theta - ref) (wrap into (-pi, pi]) for quadratic and sin, theta for tan;
// the difference is written without cancellation (tan: 2 sin((t-r)/2) / (cos(t/2) cos(r/2)) where t and r
// have the same sign, 2 (sin(t/2) cos(r/2) - sin(r/2) cos(t/2)) / (cos(t/2) cos(r/2)) where they differ,
// two terms of one sign, the half angles from tb_half_sincos (r) and tb_half_sincos_tan (t, with tan(t/2));
// sin: 4 cos((t+r)/4) sin((t-r)/4)).
// Branch-free (tb_sincos, tb_ceilv): it vectorizes in the lane loops.  tb_sincos (not tb_sincos_accurate)
// suffices: the half angles are in [-pi/4, pi/4] (no reduction), sin((t - r)/2) is used where t and r have the
// same sign (|t - r| / 2 < pi/2: tiny only near 0, unreduced), and the sin model's cos((t + r)/4) is tiny only
// for |t|, |r| both at pi, where its difference term d vanishes with it.
template <int M, typename T> TB_HD static TB_FORCEINLINE void phi_diff(T t, T ref, T& d, T& f1, T& f2) {
#if !defined(__CUDACC__)
  if constexpr (M == 1 && sizeof(T) == sizeof(float)) {
    // float tan on the CPU: all in double, rounded once (as tb_sincos); with the half-angle selects on floats
    // converted back and forth GCC no longer vectorizes the lane loops (the float energy ran 2.2x slower)
    double dd, g1, g2;
    phi_diff<1, double>(double(t), double(ref), dd, g1, g2);
    d = T(dd); f1 = T(g1); f2 = T(g2);
    return;
  }
#endif
  const T pi = T(3.14159265358979323846), two_pi = T(6.28318530717958647692);
  T delta = t - ref;
  if (M == 1) {
    T sh, ch, u, sd, cd, sr, cr;
    tb_half_sincos_tan(t, sh, ch, u);  // t: a bend angle (|t| <= pi); ref may be any finite value
    tb_half_sincos(ref, sr, cr);
    tb_sincos(T(0.5) * delta, sd, cd);
    bool opposite = (t < T(0)) != (ref < T(0));
    T num = opposite ? sh * cr - sr * ch : sd;
    T s2 = T(1) + u * u;  // u = tan(t/2) to 1 ulp (the rounded sh / ch: 2.2)
    d = T(2) * num / (ch * cr); f1 = s2; f2 = s2 * u;
    return;
  }
  T turns = tb_ceilv((delta - pi) / two_pi);  // theta' = theta - 2 pi turns
  T dw = turns != T(0) ? delta - two_pi * turns : delta;
  if (M == 0) { d = dw; f1 = T(1); f2 = T(0); return; }
  T sign = T(1) - T(2) * (turns - T(2) * tb_floorv(T(0.5) * turns));  // (-1)^turns
  T q = T(0.25) * dw, sq, cq, sa, ca, sh, ch;
  tb_sincos(q, sq, cq);
  tb_sincos(T(0.5) * ref + q, sa, ca);
  tb_sincos(T(0.5) * t, sh, ch);
  d = T(4) * ca * sq; f1 = sign * ch; f2 = T(-0.5) * sign * sh;
}

// ---- the bend angle of a stencil -------------------------------------------------------------------
// A power of two p with m p in [1, 2) (m clamped to [2^-1000, 2^1000] for double, [2^-120, 2^120] for
// float first: finite, nonzero scales for every finite m >= 0).  Exponent arithmetic on the bits (a
// bit copy by __builtin_memcpy, host and device): it vectorizes.
TB_HD static TB_FORCEINLINE double tb_pow2_recip(double m) {
  m = m < 0x1p-1000 ? 0x1p-1000 : (m > 0x1p1000 ? 0x1p1000 : m);
  uint64_t b;
  __builtin_memcpy(&b, &m, sizeof b);
  b = 0x7fe0000000000000ull - (b & 0x7ff0000000000000ull);  // exponent 1023 - (E - 1023)
  double r;
  __builtin_memcpy(&r, &b, sizeof r);
  return r;
}
TB_HD static TB_FORCEINLINE float tb_pow2_recip(float m) {
  m = m < 0x1p-120f ? 0x1p-120f : (m > 0x1p120f ? 0x1p120f : m);
  uint32_t b;
  __builtin_memcpy(&b, &m, sizeof b);
  b = 0x7f000000u - (b & 0x7f800000u);
  float r;
  __builtin_memcpy(&r, &b, sizeof r);
  return r;
}
// |v| by its sign bit (one AND; a compare-and-select costs a blend per value on AVX2): -0 gives +0, which changes
// nothing where it is used (the largest magnitude, clamped to a normal scale)
template <typename T> TB_HD static TB_FORCEINLINE T tb_absv(T v) { return fabs(v); }

// The type the bend angle is computed in: double for float stencils on the CPU (the products below span
// up to five lengths; in double every finite float stencil fits, and the angle is rounded once), the
// stencil's own type on the GPU (where double is slow on many devices; the scaling below still keeps
// every product in range, at float accuracy).
template <typename T> struct ThetaType { using type = double; };
#if defined(__CUDACC__) || defined(TORCHBEND_FLOAT32_THETA)
template <> struct ThetaType<float> { using type = float; };
#endif

// theta = atan2(e_hat . (nA x nB), nA . nB), nA = e x (x2 - x0), nB = (x3 - x0) x e (the SPEC formula), of lane
// l of the stencils X (torchbend.ops.hinge._stencil_theta): the edges x_k - x0 are scaled by the power of two
// that brings their largest component into [1, 2) (exact; the angle is the unscaled one bit for bit wherever
// that did not over- or underflow), so that no scale of the input overflows or underflows the products of
// five lengths.  The one formula of every kernel, so that angles at the rest state vanish bit for bit.
// (stencil_theta_args: the two arguments of that atan2, for theta_tile's separate lane loops)
template <typename T, int W, typename C = typename ThetaType<T>::type>
TB_HD static TB_FORCEINLINE void stencil_theta_args(const T (*X)[W], int l, C& y, C& x) {
  C e[3], u[3], w[3];
  for (int m = 0; m < 3; ++m) {
    C x0 = C(X[m][l]);
    e[m] = C(X[3 + m][l]) - x0; u[m] = C(X[6 + m][l]) - x0; w[m] = C(X[9 + m][l]) - x0;
  }
  C mx = tb_absv(e[0]);
  for (int m = 1; m < 3; ++m) mx = tb_max(mx, tb_absv(e[m]));
  for (int m = 0; m < 3; ++m) mx = tb_max(tb_max(mx, tb_absv(u[m])), tb_absv(w[m]));
  C p = tb_pow2_recip(mx);
  for (int m = 0; m < 3; ++m) { e[m] *= p; u[m] *= p; w[m] *= p; }
  C NA[3], NB[3], NN[3];
  cross(e, u, NA); cross(w, e, NB); cross(NA, NB, NN);
  // atan2(e . (nA x nB), |e| nA . nB): the same angle without a division on the way to atan2's (a collapsed edge
  // gives atan2(0, 0) = 0, as 0 * (1 / |e|) did)
  C elen = tb_sqrt(dot(e, e));
  y = dot(e, NN); x = elen * dot(NA, NB);
}
template <typename T, int W> TB_HD static TB_FORCEINLINE T stencil_theta(const T (*X)[W], int l) {
  typename ThetaType<T>::type y, x;
  stencil_theta_args<T, W>(X, l, y, x);
  return T(tb_atan2v(y, x));
}

template <typename T> TB_HD static inline void phi_difference(int model, T t, T ref, T& d, T& f1, T& f2) {
  if (model == 0) phi_diff<0>(t, ref, d, f1, f2);
  else if (model == 1) phi_diff<1>(t, ref, d, f1, f2);
  else phi_diff<2>(t, ref, d, f1, f2);
}

// phi' and phi'' of the model at a reference angle r (the parameter derivatives need them)
template <int M, typename T> TB_HD static TB_FORCEINLINE void phi_ref(T r, T& p1, T& p2) {
  if (M == 0) { p1 = T(1); p2 = T(0); return; }
  T s, c;
  if (M == 1) { tb_half_sincos(r, s, c); T u = s / c; p1 = T(1) + u * u; p2 = p1 * u; return; }
  tb_sincos(T(0.5) * r, s, c);
  p1 = c; p2 = T(-0.5) * s;
}

// a per-hinge parameter given as a scalar (n == 1), one per hinge (n == H) or one per sample and hinge
template <typename T> struct Param {
  const T* p; int64_t n, H;
  TB_HD inline T operator()(int64_t b, int64_t h) const { return n == 1 ? p[0] : (n == H ? p[h] : p[b * H + h]); }
};

// the stencil x0 x1 x2 x3 of one hinge (vertex ids st[0..3]) from positions xb (V, 3) into lane l of X
template <typename T, int W> TB_HD static inline void load_hinge(const T* xb, const int64_t* st, T (*X)[W], int l) {
  for (int v = 0; v < 4; ++v)
    for (int m = 0; m < 3; ++m) X[3 * v + m][l] = xb[3 * st[v] + m];
}

// theta, psi' (d1) and psi'' (d2) of lane l of the stencils X at its bend angle
// theta by stencil_theta; psi = a (k (phi - phi(rest))^2 + c (phi - phi(prev))^2) as torchbend.ops.psi, each
// term on the branch of its reference angle, the viscous term only if damped.  The caller checks theta
// for folded tan hinges (|theta| >= pi), where psi' and psi'' are meaningless.
template <typename T, int W>
TB_HD static inline void hinge_psi(const T (*X)[W], int l, int model, T a, T k, T rest, bool damped, T c, T prev,
                                   T& theta, T& d1, T& d2) {
  theta = stencil_theta<T, W>(X, l);
  T dr, f1, f2;
  phi_difference(model, theta, rest, dr, f1, f2);
  T kd = k * dr, s = kd, h2 = k * f1 * f1 + kd * f2;
  if (damped) {
    T dp, g1, g2;
    phi_difference(model, theta, prev, dp, g1, g2);
    T cd = c * dp;
    s = kd * f1 + cd * g1;
    h2 += c * g1 * g1 + cd * g2;
  } else {
    s = kd * f1;
  }
  T two_a = T(2) * a;
  d1 = two_a * s;
  d2 = two_a * h2;
}

// ---- 12x12 blocks and angle gradients ------------------------------------------------------------
// The blocks of W hinges before their output: the upper triangle (r <= c) of
// H[(i,p),(j,q)] = psi' (tA_i mhA_j[p] NA_q + tA_j mhA_i[q] NA_p - (same for B)) + psi'' g_r g_c,
// the B term B = psi' (blA mhA_2^T - blB mhB_2^T) of the (x0, x1) blocks, and the angle gradients g.
template <typename T, int W> struct Blocks { T O[144][W], Bm[3][3][W], G[12][W]; };

template <typename T, int W>
TB_HD static inline void block_tile(const T (*X)[W], const T* d1, const T* d2, Blocks<T, W>& b) {
  Half<T, W> hA, hB;
  halves_tile<T, W>(X, hA, hB);
  // coefficients per stencil vertex: t (times psi'), mh; vertex 3 is not in triangle A, 2 not in B
  T RA[4][W], RB[4][W], MA[4][3][W], MB[4][3][W];
  const int ia_[4] = {0, 1, 2, -1}, ib_[4] = {0, 1, -1, 2};
  for (int i = 0; i < 4; ++i) {
    int sa = ia_[i], sb = ib_[i];
    TB_LANES(W) {
      RA[i][l] = sa < 0 ? T(0) : d1[l] * hA.t[sa][l];
      RB[i][l] = sb < 0 ? T(0) : d1[l] * hB.t[sb][l];
    }
    for (int p = 0; p < 3; ++p) TB_LANES(W) {
      MA[i][p][l] = sa < 0 ? T(0) : hA.mh[sa][p][l];
      MB[i][p][l] = sb < 0 ? T(0) : hB.mh[sb][p][l];
      b.G[3 * i + p][l] = (sa < 0 ? T(0) : hA.t[sa][l] * hA.N[p][l]) - (sb < 0 ? T(0) : hB.t[sb][l] * hB.N[p][l]);
    }
  }
#if defined(__CUDACC__)
  for (int r = 0; r < 12; ++r) {
    int i = r / 3, p = r % 3;
    for (int c = r; c < 12; ++c) {
      int j = c / 3, q = c % 3;
      TB_LANES(W) b.O[12 * r + c][l] = RA[i][l] * MA[j][p][l] * hA.N[q][l] + RA[j][l] * MA[i][q][l] * hA.N[p][l]
                                     - RB[i][l] * MB[j][p][l] * hB.N[q][l] - RB[j][l] * MB[i][q][l] * hB.N[p][l]
                                     + d2[l] * b.G[r][l] * b.G[c][l];
    }
  }
#else
  // the same expression with its repeated first factors RA_i mhA_j[p] (and B's) and psi'' g_r taken once per
  // tile (the same operations on the same numbers: the same bits); on the GPU (one hinge a thread) the
  // tables would not fit in registers
  T PA[4][4][3][W], PB[4][4][3][W], S[W];
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j)
      for (int p = 0; p < 3; ++p) TB_LANES(W) {
        PA[i][j][p][l] = RA[i][l] * MA[j][p][l];
        PB[i][j][p][l] = RB[i][l] * MB[j][p][l];
      }
  for (int r = 0; r < 12; ++r) {
    int i = r / 3, p = r % 3;
    TB_LANES(W) S[l] = d2[l] * b.G[r][l];
    for (int c = r; c < 12; ++c) {
      int j = c / 3, q = c % 3;
      TB_LANES(W) b.O[12 * r + c][l] = PA[i][j][p][l] * hA.N[q][l] + PA[j][i][q][l] * hA.N[p][l]
                                     - PB[i][j][p][l] * hB.N[q][l] - PB[j][i][q][l] * hB.N[p][l]
                                     + S[l] * b.G[c][l];
    }
  }
#endif
  // B is symmetric only when both halves are valid, so it is applied as is (as torchbend.ops.hinge
  // does) rather than mirrored
  for (int p = 0; p < 3; ++p)
    for (int q = 0; q < 3; ++q)
      TB_LANES(W) b.Bm[p][q][l] = d1[l] * (hA.bl[p][l] * hA.mh[2][q][l] - hB.bl[p][l] * hB.mh[2][q][l]);
}

// the row-major 12x12 block of lane l (144 values into o): the mirrored upper triangle plus the B
// terms [[-B, B], [B^T, -B]] on the (x0, x1) blocks
template <typename T, int W> TB_HD static inline void block_lane(const Blocks<T, W>& b, int l, T* o) {
  for (int r = 0; r < 12; ++r) {
    for (int c = 0; c < r; ++c) o[12 * r + c] = b.O[12 * c + r][l];
    for (int c = r; c < 12; ++c) o[12 * r + c] = b.O[12 * r + c][l];
  }
  for (int p = 0; p < 3; ++p)
    for (int q = 0; q < 3; ++q) {
      T B = b.Bm[p][q][l];
      o[12 * p + q] -= B;
      o[12 * p + 3 + q] += B;
      o[12 * (3 + q) + p] += B;
      o[12 * (3 + p) + 3 + q] -= B;
    }
}

// angle gradients G[3 * vertex + axis][lane] from the two half-hinges: T'_A - T'_B (g_k = t_k N per half)
template <typename T, int W>
TB_HD static inline void grad_of_halves(const Half<T, W>& hA, const Half<T, W>& hB, T (*G)[W]) {
  for (int p = 0; p < 3; ++p) TB_LANES(W) {
    G[p][l] = hA.t[0][l] * hA.N[p][l] - hB.t[0][l] * hB.N[p][l];
    G[3 + p][l] = hA.t[1][l] * hA.N[p][l] - hB.t[1][l] * hB.N[p][l];
    G[6 + p][l] = hA.t[2][l] * hA.N[p][l];
    G[9 + p][l] = -hB.t[2][l] * hB.N[p][l];
  }
}

// angle gradients of W hinges (G[3 * vertex + axis][lane])
template <typename T, int W> TB_HD static inline void grad_tile(const T (*X)[W], T (*G)[W]) {
  Half<T, W> hA, hB;
  halves_tile<T, W, false>(X, hA, hB);
  grad_of_halves<T, W>(hA, hB, G);
}

// ---- per-triangle blocks (triangle assembly) -----------------------------------------------------
// 9x9 blocks (flat (3 i + p) * 9 + 3 j + q) of sum_h psi'_h Hess(theta_h) over the hinges of W triangles
// p0 p1 p2 (paper eq. 7, torchbend.ops.triangle), vectorized across them: corners P[3 k + axis][lane], psi' of the
// hinge on edge k (opposite p_k; 0 on the boundary) C[k][lane], SG[k][lane] > 0 where the triangle runs edge k in
// its global direction (+1 / -1), the blocks into O[(3 i + p) * 9 + 3 j + q][lane]; a degenerate triangle: zeros.
template <typename T, int W>
TB_HD static inline void face_block_tile(const T (*P)[W], const T (*C)[W], const T (*SG)[W], T (*O)[W]) {
  T N[3][W], MH[3][3][W], G[3][3][W], R[3][W], OK[W];
  TB_LANES_AGG(W) {
    V3<T> p0{P[0][l], P[1][l], P[2][l]}, p1{P[3][l], P[4][l], P[5][l]}, p2{P[6][l], P[7][l], P[8][l]};
    V3<T> ev[3] = {sub3(p2, p1), sub3(p0, p2), sub3(p1, p0)};
    Tri<T> t = tri_frame(ev[0], ev[1], ev[2]);
    const bool valid = t.valid != T(0);
    const T ee[3] = {valid ? t.ee0 : T(1), valid ? t.ee1 : T(1), valid ? t.ee2 : T(1)};
    N[0][l] = t.N.x; N[1][l] = t.N.y; N[2][l] = t.N.z;
    MH[0][0][l] = t.mh0.x; MH[0][1][l] = t.mh0.y; MH[0][2][l] = t.mh0.z;
    MH[1][0][l] = t.mh1.x; MH[1][1][l] = t.mh1.y; MH[1][2][l] = t.mh1.z;
    MH[2][0][l] = t.mh2.x; MH[2][1][l] = t.mh2.y; MH[2][2][l] = t.mh2.z;
    T s[3];
    for (int k = 0; k < 3; ++k) {
      T elen = tb_sqrt(ee[k]);
      s[k] = C[k][l] / elen;
      R[k][l] = C[k][l] / (ee[k] * elen);
    }
    for (int i = 0; i < 3; ++i) {
      T D = -((dot3(ev[i], ev[0]) * s[0] + dot3(ev[i], ev[1]) * s[1]) + dot3(ev[i], ev[2]) * s[2]) / t.nn;
      G[i][0][l] = D * t.N.x; G[i][1][l] = D * t.N.y; G[i][2][l] = D * t.N.z;
    }
    OK[l] = t.valid;
  }
  // R_k = (c_k / |e_k|^3) N mh_k^T (RN) and R_k or R_k^T as the triangle runs edge k along or against its global
  // direction (RF; RT its transpose)
  T RN[3][3][3][W], RF[3][3][3][W], RT[3][3][3][W];
  for (int k = 0; k < 3; ++k)
    for (int p = 0; p < 3; ++p)
      for (int q = 0; q < 3; ++q) TB_LANES(W) {
        T a = R[k][l] * N[p][l] * MH[k][q][l], b = R[k][l] * N[q][l] * MH[k][p][l];
        bool along = SG[k][l] > T(0);
        RN[k][p][q][l] = a;
        RF[k][p][q][l] = along ? a : b;
        RT[k][p][q][l] = along ? b : a;
      }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      // j = i + 1: edge k = i + 2 runs p_i -> p_{i+1} (RF); j = i - 1: edge k = i + 1, the transpose of block (j, i)
      // (RT); j = i: minus R of the two other edges
      const int k1 = (i + 1) % 3, k2 = (i + 2) % 3;
      for (int p = 0; p < 3; ++p)
        for (int q = 0; q < 3; ++q) {
          const T(*E)[W] = i == j ? nullptr : (j == k1 ? RF[k2][p] : RT[k1][p]);
          TB_LANES(W) {
            T v = MH[j][p][l] * G[i][q][l] + G[j][p][l] * MH[i][q][l];
            v = E ? v + E[q][l] : v - (RN[k1][p][q][l] + RN[k2][p][q][l]);
            O[(3 * i + p) * 9 + 3 * j + q][l] = OK[l] != T(0) ? v : T(0);
          }
        }
    }
}

}  // namespace torchbend
