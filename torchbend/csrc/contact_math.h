// Per-stencil mathematics of torchbend's compiled contact kernels: the distance types of a point-triangle or
// edge-edge stencil, the squared distance of each type with its closed-form gradient and Hessian, IPC's barrier
// on squared distances, the edge-edge mollifier, and a pair's energy, gradient and Hessian in reduced coordinates.
// It mirrors the eager reference torchbend/ops/distance.py (types, formulas) and torchbend/sim/self_contact.py
// (the pair energy), which the tests compare against, with the IPC toolkit as the independent oracle.
//
// Written as hinge_math.h is (TB_HD functions, the C math functions, no std::, no torch) so that a CUDA driver
// can compile it with nvcc, one stencil per thread; the CPU driver is cpu_contact.cpp.
//
// Reduced coordinates.  Each type's squared distance D is a function of k = 3 r (r = 1, 2, 3) coordinates
// y = (C (x) I3) x, differences of the stencil's four corners x (12) with a row pattern C (r x 4) of -1, 0, 1:
//     point-point   y = (p - q)                    D = |y|^2
//     point-line    y = (e, a) = (p - e0, e1 - e0)  D = |e|^2 - (e.a)^2 / |a|^2
//     point-plane   y = (e, a, b) = (p - t0, t1 - t0, t2 - t0),   D = s^2 / q,  s = e.(a x b), q = |a x b|^2
//     line-line     y = (e, a, b) = (b0 - a0, a1 - a0, b1 - b0),  the same formula.
// An edge-edge pair below the mollifier's threshold depends on all four corners (the mollifier takes a and b of
// the two edges): it is written in the line-line coordinates whatever its type (the type's own y are T y_lines).
// The gradient and Hessian in x are L^T g and L^T H L, L = C (x) I3; the PSD projection of L^T H L is
// L^T R^-T proj(R^T H R) R^-1 L with R R^T = C C^T (Cholesky; Q = L^T R^-T has orthonormal columns), a k x k
// eigenproblem (k = 3, 6 or 9) instead of 12 x 12 (cpu_symeig.h on the CPU).
#pragma once

#include "vector_math.h"

namespace torchbend {
namespace contact {

// the distance types (torchbend.ops.distance: PT_* then EE_*)
enum : int {
  PT_P0 = 0, PT_P1, PT_P2, PT_E01, PT_E12, PT_E20, PT_FACE,
  EE_A0B0, EE_A0B1, EE_A1B0, EE_A1B1, EE_AB0, EE_AB1, EE_A0B, EE_A1B, EE_LINES, NUM_TYPES
};
enum : int { F_PP = 0, F_PE = 1, F_PLANE = 2 };  // formulas; F_PLANE: point-plane and line-line

// A type's formula and row pattern C (r rows over the stencil's 4 corners); returns r
TB_HD static inline int type_rows(int type, int* formula, signed char C[3][4]) {
  // rows: {formula, r, C row 0, C row 1, C row 2}
  const signed char tab[NUM_TYPES][14] = {
      {F_PP, 1, 1, -1, 0, 0},                                    // PT_P0    p - t0
      {F_PP, 1, 1, 0, -1, 0},                                    // PT_P1
      {F_PP, 1, 1, 0, 0, -1},                                    // PT_P2
      {F_PE, 2, 1, -1, 0, 0, 0, -1, 1, 0},                       // PT_E01   p - t0, t1 - t0
      {F_PE, 2, 1, 0, -1, 0, 0, 0, -1, 1},                       // PT_E12   p - t1, t2 - t1
      {F_PE, 2, 1, 0, 0, -1, 0, 1, 0, -1},                       // PT_E20   p - t2, t0 - t2
      {F_PLANE, 3, 1, -1, 0, 0, 0, -1, 1, 0, 0, -1, 0, 1},      // PT_FACE  p - t0, t1 - t0, t2 - t0
      {F_PP, 1, 1, 0, -1, 0},                                    // EE_A0B0  a0 - b0
      {F_PP, 1, 1, 0, 0, -1},                                    // EE_A0B1
      {F_PP, 1, 0, 1, -1, 0},                                    // EE_A1B0
      {F_PP, 1, 0, 1, 0, -1},                                    // EE_A1B1
      {F_PE, 2, -1, 0, 1, 0, -1, 1, 0, 0},                       // EE_AB0   b0 - a0, a1 - a0
      {F_PE, 2, -1, 0, 0, 1, -1, 1, 0, 0},                       // EE_AB1   b1 - a0, a1 - a0
      {F_PE, 2, 1, 0, -1, 0, 0, 0, -1, 1},                       // EE_A0B   a0 - b0, b1 - b0
      {F_PE, 2, 0, 1, -1, 0, 0, 0, -1, 1},                       // EE_A1B   a1 - b0, b1 - b0
      {F_PLANE, 3, -1, 0, 1, 0, -1, 1, 0, 0, 0, 0, -1, 1},      // EE_LINES b0 - a0, a1 - a0, b1 - b0
  };
  const signed char* t = tab[type];
  *formula = t[0];
  for (int r = 0; r < 3; ++r)
    for (int v = 0; v < 4; ++v) C[r][v] = r < t[1] ? t[2 + 4 * r + v] : 0;
  return t[1];
}

template <typename T> TB_HD static inline T dot3p(const T* u, const T* v) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }
template <typename T> TB_HD static inline void cross3p(const T* u, const T* v, T* o) {
  o[0] = u[1] * v[2] - u[2] * v[1]; o[1] = u[2] * v[0] - u[0] * v[2]; o[2] = u[0] * v[1] - u[1] * v[0];
}

// ---- distance types (Ericson's tests, as torchbend.ops.distance classifies them) ----------------
// Compiled without contracting a * b + c into a fused multiply-add, so that each product and sum is rounded as
// torch rounds the eager reference's: a stencil on a boundary between two types (a vertex exactly above an edge)
// gets the same type both ways (the distances agree there, the Hessians do not).
#if defined(__GNUC__) && !defined(__clang__) && !defined(__CUDACC__)
#pragma GCC push_options
#pragma GCC optimize("fp-contract=off")
#define TB_CONTACT_NO_CONTRACT 1
#endif
template <typename T> TB_HD static inline int point_triangle_type(const T* p, const T* a, const T* b, const T* c) {
  T ab[3], ac[3], ap[3], bp[3], cp[3];
  for (int i = 0; i < 3; ++i) { ab[i] = b[i] - a[i]; ac[i] = c[i] - a[i]; ap[i] = p[i] - a[i]; bp[i] = p[i] - b[i]; cp[i] = p[i] - c[i]; }
  T d1 = dot3p(ab, ap), d2 = dot3p(ac, ap), d3 = dot3p(ab, bp), d4 = dot3p(ac, bp), d5 = dot3p(ab, cp), d6 = dot3p(ac, cp);
  T va = d3 * d6 - d5 * d4, vb = d5 * d2 - d1 * d6, vc = d1 * d4 - d3 * d2;
  if (d1 <= 0 && d2 <= 0) return PT_P0;
  if (d3 >= 0 && d4 <= d3) return PT_P1;
  if (d6 >= 0 && d5 <= d6) return PT_P2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return PT_E01;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return PT_E20;
  if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) return PT_E12;
  return PT_FACE;
}

// squared distance of p to the segment e0 e1 and where the closest point is (0: e0, 1: e1, 2: inside)
template <typename T> TB_HD static inline T point_segment(const T* p, const T* e0, const T* e1, int* where) {
  T e[3], w[3];
  for (int i = 0; i < 3; ++i) { e[i] = e1[i] - e0[i]; w[i] = p[i] - e0[i]; }
  T ee = dot3p(e, e);
  T tiny = sizeof(T) == 4 ? T(FLT_MIN) : T(DBL_MIN);
  T t = dot3p(w, e) / (ee > tiny ? ee : tiny);
  t = t < 0 ? T(0) : (t > 1 ? T(1) : t);
  *where = t <= 0 ? 0 : (t >= 1 ? 1 : 2);
  T d = 0;
  for (int i = 0; i < 3; ++i) { T q = p[i] - (e0[i] + t * e[i]); d += q * q; }
  return d;
}

template <typename T> TB_HD static inline int edge_edge_type(const T* a0, const T* a1, const T* b0, const T* b1,
                                                             T parallel) {
  T u[3], v[3], w[3];
  for (int i = 0; i < 3; ++i) { u[i] = a1[i] - a0[i]; v[i] = b1[i] - b0[i]; w[i] = a0[i] - b0[i]; }
  T a = dot3p(u, u), b = dot3p(u, v), c = dot3p(v, v), d = dot3p(u, w), e = dot3p(v, w);
  T den = a * c - b * b;
  if (den <= parallel * a * c) {  // parallel: the nearest of the four corner-segment pairs
    int wh[4];
    T D[4] = {point_segment(a0, b0, b1, &wh[0]), point_segment(a1, b0, b1, &wh[1]),
              point_segment(b0, a0, a1, &wh[2]), point_segment(b1, a0, a1, &wh[3])};
    int k = 0;
    for (int j = 1; j < 4; ++j) if (D[j] < D[k]) k = j;  // the first of equal minima, as argmin
    const int tab[4][3] = {{EE_A0B0, EE_A0B1, EE_A0B}, {EE_A1B0, EE_A1B1, EE_A1B},
                           {EE_A0B0, EE_A1B0, EE_AB0}, {EE_A0B1, EE_A1B1, EE_AB1}};
    return tab[k][wh[k]];
  }
  T s = (b * e - c * d) / den;
  s = s < 0 ? T(0) : (s > 1 ? T(1) : s);
  T t = (b * s + e) / c;
  if (t < 0) { t = 0; s = -d / a; s = s < 0 ? T(0) : (s > 1 ? T(1) : s); }
  else if (t > 1) { t = 1; s = (b - d) / a; s = s < 0 ? T(0) : (s > 1 ? T(1) : s); }
  int si = s <= 0 ? 0 : (s >= 1 ? 1 : 2), ti = t <= 0 ? 0 : (t >= 1 ? 1 : 2);
  const int table[3][3] = {{EE_A0B0, EE_A0B1, EE_A0B}, {EE_A1B0, EE_A1B1, EE_A1B}, {EE_AB0, EE_AB1, EE_LINES}};
  return table[si][ti];
}

// The squared distance of a formula from its reduced coordinates y (the value typed_derivs returns, its
// expressions written out) and the squared cross product c = |a x b|^2 of a stencil's two edges (the mollifier's
// argument), both without contraction: every energy of the compiled kernels (pair_terms, and the energy lanes of
// cpu_contact.cpp, which spell the same expressions) comes out bit for bit the same.
template <typename T> TB_HD static inline T typed_distance(int formula, const T* y) {
  if (formula == F_PP) return y[0] * y[0] + y[1] * y[1] + y[2] * y[2];
  if (formula == F_PE) {
    const T x0 = y[1] * y[5] - y[2] * y[4], x1 = y[2] * y[3] - y[0] * y[5], x2 = y[0] * y[4] - y[1] * y[3];
    return (x0 * x0 + x1 * x1 + x2 * x2) / (y[3] * y[3] + y[4] * y[4] + y[5] * y[5]);
  }
  const T n0 = y[4] * y[8] - y[5] * y[7], n1 = y[5] * y[6] - y[3] * y[8], n2 = y[3] * y[7] - y[4] * y[6];
  const T sn = y[0] * n0 + y[1] * n1 + y[2] * n2;
  return sn * sn / (n0 * n0 + n1 * n1 + n2 * n2);
}

template <typename T> TB_HD static inline T edge_cross_sq(const T x[4][3]) {
  const T a0 = x[1][0] - x[0][0], a1 = x[1][1] - x[0][1], a2 = x[1][2] - x[0][2];
  const T b0 = x[3][0] - x[2][0], b1 = x[3][1] - x[2][1], b2 = x[3][2] - x[2][2];
  const T c0 = a1 * b2 - a2 * b1, c1 = a2 * b0 - a0 * b2, c2 = a0 * b1 - a1 * b0;
  return c0 * c0 + c1 * c1 + c2 * c2;
}

#ifdef TB_CONTACT_NO_CONTRACT
#pragma GCC pop_options
#undef TB_CONTACT_NO_CONTRACT
#endif

// the reduced coordinates y (3 r; 9 written, zeros beyond) of a stencil x (4 x 3) for the row pattern C
template <typename T> TB_HD static inline void reduce(const signed char C[3][4], int r, const T x[4][3], T* y) {
  (void)r;
  for (int row = 0; row < 3; ++row)
    for (int i = 0; i < 3; ++i) {
      T s = 0;
      for (int v = 0; v < 4; ++v) s += C[row][v] == 0 ? T(0) : T(C[row][v]) * x[v][i];
      y[3 * row + i] = s;
    }
}

// ---- squared distances with gradient g (k) and Hessian H (k x k, row-major; if H) in y ---------------
template <typename T> TB_HD static inline T pp_derivs(const T* y, T* g, T* H) {
  if (g) for (int i = 0; i < 3; ++i) g[i] = 2 * y[i];
  if (H) for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) H[3 * i + j] = i == j ? T(2) : T(0);
  return dot3p(y, y);
}

// D = |e|^2 - (e.a)^2 / |a|^2 = |e x a|^2 / |a|^2
template <typename T> TB_HD static inline T pe_derivs(const T* y, T* g, T* H) {
  const T* e = y; const T* a = y + 3;
  T r = dot3p(a, a), t = dot3p(e, a), u = t / r, cr[3];
  cross3p(e, a, cr);
  T D = dot3p(cr, cr) / r;
  if (g)
    for (int i = 0; i < 3; ++i) { g[i] = 2 * (e[i] - u * a[i]); g[3 + i] = 2 * u * (u * a[i] - e[i]); }
  if (H) {
    T w[3];
    for (int i = 0; i < 3; ++i) w[i] = e[i] - 2 * u * a[i];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        T id = i == j ? T(1) : T(0);
        H[6 * i + j] = 2 * id - 2 * a[i] * a[j] / r;                  // ee
        T ea = -2 * u * id - 2 * a[i] * w[j] / r;                     // d g_e_i / d a_j
        H[6 * i + 3 + j] = ea;
        H[6 * (3 + j) + i] = ea;
        H[6 * (3 + i) + 3 + j] = 2 * u * u * id - 2 * w[i] * w[j] / r;  // aa
      }
  }
  return D;
}

// the 3x3 cross-product matrix [v]_x (row-major): [v]_x u = v x u
template <typename T> TB_HD static inline void skew(const T* v, T* S) {
  S[0] = 0; S[1] = -v[2]; S[2] = v[1];
  S[3] = v[2]; S[4] = 0; S[5] = -v[0];
  S[6] = -v[1]; S[7] = v[0]; S[8] = 0;
}

// D = s^2 / q, s = e.(a x b), q = |a x b|^2 (point-plane and line-line)
template <typename T> TB_HD static inline T plane_derivs(const T* y, T* g, T* H) {
  const T* e = y; const T* a = y + 3; const T* b = y + 6;
  T n[3];
  cross3p(a, b, n);
  T s = dot3p(e, n), q = dot3p(n, n);
  T D = s * s / q;
  if (!g && !H) return D;
  T gs[9], gq[9];
  for (int i = 0; i < 3; ++i) { gs[i] = n[i]; gq[i] = 0; }
  cross3p(b, e, gs + 3);
  cross3p(e, a, gs + 6);
  T bn[3], na[3];
  cross3p(b, n, bn);
  cross3p(n, a, na);
  for (int i = 0; i < 3; ++i) { gq[3 + i] = 2 * bn[i]; gq[6 + i] = 2 * na[i]; }
  const T c1 = 2 * s / q, c2 = s * s / (q * q);
  if (g) for (int i = 0; i < 9; ++i) g[i] = c1 * gs[i] - c2 * gq[i];
  if (H) {
    for (int i = 0; i < 81; ++i) H[i] = 0;
    // (2 s / q) Hs: ea = -[b]x, eb = [a]x, ab = -[e]x and their transposes
    T Sb[9], Sa[9], Se[9];
    skew(b, Sb); skew(a, Sa); skew(e, Se);
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        T ea = -c1 * Sb[3 * i + j], eb = c1 * Sa[3 * i + j], ab = -c1 * Se[3 * i + j];
        H[9 * i + 3 + j] += ea; H[9 * (3 + j) + i] += ea;
        H[9 * i + 6 + j] += eb; H[9 * (6 + j) + i] += eb;
        H[9 * (3 + i) + 6 + j] += ab; H[9 * (6 + j) + 3 + i] += ab;
      }
    // -(s^2 / q^2) Hq: aa = 2 (|b|^2 I - b b^T), bb = 2 (|a|^2 I - a a^T), ab = 2 (2 a b^T - b a^T - (a.b) I)
    T aa = dot3p(a, a), bb = dot3p(b, b), ab = dot3p(a, b);
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        T id = i == j ? T(1) : T(0);
        H[9 * (3 + i) + 3 + j] -= c2 * 2 * (bb * id - b[i] * b[j]);
        H[9 * (6 + i) + 6 + j] -= c2 * 2 * (aa * id - a[i] * a[j]);
        T m = c2 * 2 * (2 * a[i] * b[j] - b[i] * a[j] - ab * id);
        H[9 * (3 + i) + 6 + j] -= m; H[9 * (6 + j) + 3 + i] -= m;
      }
    // (2 / q) gs gs^T - (2 s / q^2) (gs gq^T + gq gs^T) + (2 s^2 / q^3) gq gq^T
    const T k1 = 2 / q, k2 = c1 / q, k3 = 2 * c2 / q;
    for (int i = 0; i < 9; ++i)
      for (int j = 0; j < 9; ++j)
        H[9 * i + j] += k1 * gs[i] * gs[j] - k2 * (gs[i] * gq[j] + gq[i] * gs[j]) + k3 * gq[i] * gq[j];
  }
  return D;
}

template <typename T> TB_HD static inline T typed_derivs(int formula, const T* y, T* g, T* H) {
  return formula == F_PP ? pp_derivs(y, g, H) : (formula == F_PE ? pe_derivs(y, g, H) : plane_derivs(y, g, H));
}

// ---- IPC's barrier on squared distances and the edge-edge mollifier --------------------------------
// The barrier's log: vector_math.h's tb_logv (within 1 ulp), not the C library's.  A library call from code that
// has used 512-bit registers stalls on the library's SSE-encoded first instructions where the compiler leaves out
// the vzeroupper before it (GCC 12 does in pair_terms): about 100 ns a pair.  On the host one compiled copy
// (noinline) serves every caller, so that no inlining context contracts its products differently: the energies of
// the lanes (cpu_contact_scan.h) and of pair_terms stay equal bit for bit.  On the device (no stall there) the
// CUDA library's log and logf, as before.
#if defined(__CUDA_ARCH__)
TB_HD static inline double barrier_log(double v) { return log(v); }
TB_HD static inline float barrier_log(float v) { return logf(v); }
#else
__attribute__((noinline)) static double barrier_log(double v) { return tb_logv(v); }
static inline float barrier_log(float v) { return float(barrier_log(double(v))); }
#endif

// b(D) = -kappa (D - Dh)^2 log(D / Dh) for 0 < D < Dh (0 beyond); b1 = b', b2 = b''
template <typename T> TB_HD static inline T barrier(T D, T dh2, T kappa, T* b1, T* b2) {
  if (D >= dh2) { *b1 = 0; *b2 = 0; return 0; }
  T L = barrier_log(D / dh2), r = D - dh2;
  *b1 = -kappa * (2 * r * L + r * r / D);
  *b2 = -kappa * (2 * L + 4 * r / D - r * r / (D * D));
  return -kappa * r * r * L;
}

// m(c) = (2 - c / eps) c / eps for c < eps (1 beyond), c = |a x b|^2 of the edges a, b; m1 = m', m2 = m''
template <typename T> TB_HD static inline T mollifier(T c, T eps, T* m1, T* m2) {
  if (!(c < eps)) { *m1 = 0; *m2 = 0; return 1; }
  T r = c / eps;
  *m1 = (2 - 2 * r) / eps;
  *m2 = -2 / (eps * eps);
  return (2 - r) * r;
}

// ---- a pair: energy with gradient and Hessian in its reduced coordinates ----------------------------
// A pair's result: energy E, its reduced coordinates' pattern C (r rows), gradient g (3 r), Hessian H (3 r x 3 r)
template <typename T> struct PairTerms {
  signed char C[3][4];
  int r;
  bool mollified;  // an edge-edge pair below its mollifier's threshold (written in line-line coordinates)
  T E, D;
  T g[9], H[81];
};

// the line-line coordinates' map to a type's own: y_t = T y_lines with y_lines = (b0 - a0, a1 - a0, b1 - b0);
// corner v relative to a0 is Z_v y_lines: a0 -> 0, a1 -> a, b0 -> e, b1 -> e + b, so T = C_t Z (r x 3 blocks)
TB_HD static inline void lines_map(const signed char C[3][4], int r, signed char Tm[3][3]) {
  const signed char Z[4][3] = {{0, 0, 0}, {0, 1, 0}, {1, 0, 0}, {1, 0, 1}};
  (void)r;  // rows beyond r are zero in C, and so in Tm
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      int s = 0;
      for (int v = 0; v < 4; ++v) s += C[i][v] * Z[v][j];
      Tm[i][j] = (signed char)s;
    }
}

// The barrier energy of a stencil x (4 x 3) of distance type `type` (eps > 0: an edge-edge pair's mollifier
// threshold; 0 for point-triangle pairs); gradient (want >= 1) and Hessian (want >= 2) in reduced coordinates.
// D <= 0 (touching or crossed): E = +inf, g = H = 0.
template <typename T> TB_HD static inline void pair_terms(const T x[4][3], int type, T eps, T dh2, T kappa, int want,
                                                         PairTerms<T>* out) {
  int formula;
  signed char C[3][4] = {};
  int r = type_rows(type, &formula, C);
  T y[9], gD[9], HD[81];
  reduce(C, r, x, y);
  if (want >= 1) typed_derivs(formula, y, gD, want >= 2 ? HD : (T*)0);
  const T D = typed_distance(formula, y);
  out->D = D;
  out->mollified = false;
  const int k = 3 * r;
  if (!(D > 0)) {
    out->E = T(1) / T(0);
    out->r = r;
    for (int a = 0; a < 3; ++a) for (int v = 0; v < 4; ++v) out->C[a][v] = C[a][v];
    for (int i = 0; i < k; ++i) out->g[i] = 0;
    for (int i = 0; i < k * k; ++i) out->H[i] = 0;
    return;
  }
  T b1, b2, bE = barrier(D, dh2, kappa, &b1, &b2);
  // the mollifier (edge-edge pairs): c = |a x b|^2 of a = a1 - a0, b = b1 - b0
  T m = 1, m1 = 0, m2 = 0, ea[3], eb[3];
  if (eps > 0) {
    for (int i = 0; i < 3; ++i) { ea[i] = x[1][i] - x[0][i]; eb[i] = x[3][i] - x[2][i]; }
    m = mollifier(edge_cross_sq(x), eps, &m1, &m2);
  }
  if (m1 == 0 && m2 == 0) {  // no mollifier term: the type's own coordinates
    out->E = m * bE;
    out->r = r;
    for (int a = 0; a < 3; ++a) for (int v = 0; v < 4; ++v) out->C[a][v] = C[a][v];
    if (want >= 1) for (int i = 0; i < k; ++i) out->g[i] = m * b1 * gD[i];
    if (want >= 2)
      for (int i = 0; i < k; ++i)
        for (int j = 0; j < k; ++j) out->H[k * i + j] = m * (b2 * gD[i] * gD[j] + b1 * HD[k * i + j]);
    return;
  }
  // mollified: everything in the line-line coordinates (9)
  out->mollified = true;
  out->E = m * bE;
  out->r = 3;
  int fl;
  type_rows(EE_LINES, &fl, out->C);
  if (want < 1) return;
  signed char Tm[3][3];
  lines_map(C, r, Tm);
  T g9[9];  // T^T gD
  for (int j = 0; j < 3; ++j)
    for (int c = 0; c < 3; ++c) {
      T s = 0;
      for (int i = 0; i < r; ++i) s += Tm[i][j] == 0 ? T(0) : T(Tm[i][j]) * gD[3 * i + c];
      g9[3 * j + c] = s;
    }
  // c's gradient in (e, a, b): (0, 2 (|b|^2 a - (a.b) b), 2 (|a|^2 b - (a.b) a))
  T aa = dot3p(ea, ea), bb = dot3p(eb, eb), ab = dot3p(ea, eb), gc[9];
  for (int c = 0; c < 3; ++c) {
    gc[c] = 0;
    gc[3 + c] = 2 * (bb * ea[c] - ab * eb[c]);
    gc[6 + c] = 2 * (aa * eb[c] - ab * ea[c]);
  }
  for (int i = 0; i < 9; ++i) out->g[i] = m * b1 * g9[i] + bE * m1 * gc[i];
  if (want < 2) return;
  T* H = out->H;
  for (int i = 0; i < 81; ++i) H[i] = 0;
  // m b1 T^T HD T
  for (int I = 0; I < 3; ++I)
    for (int J = 0; J < 3; ++J)
      for (int i = 0; i < r; ++i)
        for (int j = 0; j < r; ++j) {
          int t = Tm[i][I] * Tm[j][J];
          if (t == 0) continue;
          for (int p = 0; p < 3; ++p)
            for (int q = 0; q < 3; ++q) H[9 * (3 * I + p) + 3 * J + q] += T(t) * m * b1 * HD[k * (3 * i + p) + 3 * j + q];
        }
  // bE m1 Hc: aa = 2 (|b|^2 I - b b^T), bb = 2 (|a|^2 I - a a^T), ab = 2 (2 a b^T - b a^T - (a.b) I)
  const T w = bE * m1;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      T id = i == j ? T(1) : T(0);
      H[9 * (3 + i) + 3 + j] += w * 2 * (bb * id - eb[i] * eb[j]);
      H[9 * (6 + i) + 6 + j] += w * 2 * (aa * id - ea[i] * ea[j]);
      T c = w * 2 * (2 * ea[i] * eb[j] - eb[i] * ea[j] - ab * id);
      H[9 * (3 + i) + 6 + j] += c; H[9 * (6 + j) + 3 + i] += c;
    }
  // m b2 g g^T + bE m2 gc gc^T + m1 b1 (gc g^T + g gc^T)
  for (int i = 0; i < 9; ++i)
    for (int j = 0; j < 9; ++j)
      H[9 * i + j] += m * b2 * g9[i] * g9[j] + bE * m2 * gc[i] * gc[j] + m1 * b1 * (gc[i] * g9[j] + g9[i] * gc[j]);
}

// ---- back to the stencil's 12 coordinates ----------------------------------------------------------
// g12 = L^T g
template <typename T> TB_HD static inline void expand_gradient(const signed char C[3][4], int r, const T* g, T* g12) {
  for (int v = 0; v < 4; ++v)
    for (int i = 0; i < 3; ++i) {
      T s = 0;
      for (int a = 0; a < r; ++a) s += C[a][v] == 0 ? T(0) : T(C[a][v]) * g[3 * a + i];
      g12[3 * v + i] = s;
    }
}

// H12 = L^T H L (H: 3 r x 3 r, row-major; H12: 12 x 12, row-major), as (L^T H) L: rows first, then columns; the
// row count r a template argument (the loops unrolled, no branch on the pattern), expand_hessian dispatching on it
template <typename T, int r> TB_HD static inline void expand_hessian_rows(const signed char C[3][4], const T* H,
                                                                         T* H12) {
  constexpr int k = 3 * r;
  T c[r][4];
  for (int a = 0; a < r; ++a) for (int v = 0; v < 4; ++v) c[a][v] = T(C[a][v]);
  T A[12][k];  // L^T H
  for (int v = 0; v < 4; ++v)
    for (int i = 0; i < 3; ++i)
      for (int col = 0; col < k; ++col) {
        T s = 0;
        for (int a = 0; a < r; ++a) s += c[a][v] * H[k * (3 * a + i) + col];
        A[3 * v + i][col] = s;
      }
  for (int row = 0; row < 12; ++row)
    for (int w = 0; w < 4; ++w)
      for (int j = 0; j < 3; ++j) {
        T s = 0;
        for (int b = 0; b < r; ++b) s += A[row][3 * b + j] * c[b][w];
        H12[12 * row + 3 * w + j] = s;
      }
}

template <typename T> TB_HD static inline void expand_hessian(const signed char C[3][4], int r, const T* H, T* H12) {
  if (r == 1) expand_hessian_rows<T, 1>(C, H, H12);
  else if (r == 2) expand_hessian_rows<T, 2>(C, H, H12);
  else expand_hessian_rows<T, 3>(C, H, H12);
}

// R (r x r, lower) with R R^T = C C^T, and its inverse
template <typename T> TB_HD static inline void gram_cholesky(const signed char C[3][4], int r, T R[3][3], T Ri[3][3]) {
  T G[3][3];
  for (int a = 0; a < r; ++a)
    for (int b = 0; b < r; ++b) {
      int s = 0;
      for (int v = 0; v < 4; ++v) s += C[a][v] * C[b][v];
      G[a][b] = T(s);
    }
  for (int a = 0; a < 3; ++a) for (int b = 0; b < 3; ++b) { R[a][b] = 0; Ri[a][b] = 0; }
  for (int j = 0; j < r; ++j) {
    T d = G[j][j];
    for (int k = 0; k < j; ++k) d -= R[j][k] * R[j][k];
    R[j][j] = sqrt(d);
    for (int i = j + 1; i < r; ++i) {
      T s = G[i][j];
      for (int k = 0; k < j; ++k) s -= R[i][k] * R[j][k];
      R[i][j] = s / R[j][j];
    }
  }
  for (int j = 0; j < r; ++j) {  // forward substitution of R Ri = I, column by column
    for (int i = 0; i < r; ++i) {
      T s = i == j ? T(1) : T(0);
      for (int k = 0; k < i; ++k) s -= R[i][k] * Ri[k][j];
      Ri[i][j] = s / R[i][i];
    }
  }
}

// M = (R (x) I3)^T H (R (x) I3) (k x k) for the projection; and back: P = (Ri (x) I3)^T M (Ri (x) I3)
template <typename T> TB_HD static inline void congruence(const T A[3][3], int r, const T* H, T* M) {
  const int k = 3 * r;
  T tmp[81];
  for (int a = 0; a < r; ++a)  // tmp = H (A (x) I3): column block b = sum_c H[:, c] A[c][b]
    for (int i = 0; i < k; ++i)
      for (int p = 0; p < 3; ++p) {
        T s = 0;
        for (int c = 0; c < r; ++c) s += H[k * i + 3 * c + p] * A[c][a];
        tmp[k * i + 3 * a + p] = s;
      }
  for (int a = 0; a < r; ++a)
    for (int p = 0; p < 3; ++p)
      for (int j = 0; j < k; ++j) {
        T s = 0;
        for (int c = 0; c < r; ++c) s += A[c][a] * tmp[k * (3 * c + p) + j];
        M[k * (3 * a + p) + j] = s;
      }
}

}  // namespace contact
}  // namespace torchbend
