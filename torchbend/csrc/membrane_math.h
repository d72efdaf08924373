// Per-triangle mathematics of torchbend's compiled membrane kernels: StVK's element Hessian, stress and HVP in closed
// form, and for every model (StVK, ARAP, symmetric Dirichlet, neo-Hookean) the closed-form thin SVD and eigensystem
// of Smith, De Goes & Kim with its projections.  It mirrors the eager reference torchbend.ops.membrane (the same
// formulas, the same guards against cancellation and overflow), which the tests compare against; the same
// rules as hinge_math.h (no torch, no std::, every function `TB_HD static inline`), so that a CUDA driver can
// compile it with nvcc as the CPU driver (cpu_membrane.cpp) does with g++.
#pragma once

#include "vector_math.h"

namespace torchbend {

// F (3 x 2, row-major) of a triangle with vertices p0, p1, p2 (or the dF of a direction): e_a = p_a - p0,
// F = e1 W_0^T + e2 W_1^T with W = D's rows 1 and 2 (as torchbend.ops.membrane.deformation_gradient).
template <typename T>
TB_HD static inline void face_deformation(const T* p0, const T* p1, const T* p2, const T* D, T* F) {
  for (int i = 0; i < 3; ++i) {
    const T e1 = p1[i] - p0[i], e2 = p2[i] - p0[i];
    F[2 * i] = e1 * D[2] + e2 * D[4];
    F[2 * i + 1] = e1 * D[3] + e2 * D[5];
  }
}

// StVK's Green strain G = (F^T F - I) / 2 (g: g00, g01, g11) and stress S = 2 mu G + lam tr(G) I (s: s00, s01,
// s11) of F (3 x 2, row-major); returns tr(G).
template <typename T>
TB_HD static inline T stvk_strain_stress(const T* F, T mu, T lam, T* g, T* s) {
  g[0] = T(0.5) * ((F[0] * F[0] + F[2] * F[2] + F[4] * F[4]) - T(1));
  g[1] = T(0.5) * (F[0] * F[1] + F[2] * F[3] + F[4] * F[5]);
  g[2] = T(0.5) * ((F[1] * F[1] + F[3] * F[3] + F[5] * F[5]) - T(1));
  const T tr = g[0] + g[2];
  s[0] = T(2) * mu * g[0] + lam * tr;
  s[1] = T(2) * mu * g[1];
  s[2] = T(2) * mu * g[2] + lam * tr;
  return tr;
}

// The unprojected StVK Hessian of one triangle, coef d^2 Psi / dx^2 (coef = A t), flat (9, 9) over
// (vertex k, axis i) x (vertex l, axis j), index (3 k + i) * 9 + 3 l + j.  F (3 x 2) and D (3 x 2) row-major:
// F = sum_k x_k D_k^T.  With G = (F^T F - I) / 2, S = 2 mu G + lam tr(G) I and t = D F^T:
//   H[k i, l j] = (D S D^T)_kl delta_ij + mu (D D^T)_kl (F F^T)_ij + mu t_kj t_li + lam t_ki t_lj,
// computed on the upper triangle and mirrored (exactly symmetric).
template <typename T>
TB_HD static inline void stvk_block(const T* F, const T* D, T mu, T lam, T coef, T* H) {
  T g[3], S[3];
  stvk_strain_stress(F, mu, lam, g, S);
  const T s00 = S[0], s01 = S[1], s11 = S[2];
  T A[3][3], B[3][3], FF[3][3], t[3][3];
  for (int k = 0; k < 3; ++k) {
    const T dk0 = D[2 * k], dk1 = D[2 * k + 1];
    const T u0 = dk0 * s00 + dk1 * s01, u1 = dk0 * s01 + dk1 * s11;  // (D S)_k
    for (int l = 0; l < 3; ++l) {
      const T dl0 = D[2 * l], dl1 = D[2 * l + 1];
      A[k][l] = coef * (u0 * dl0 + u1 * dl1);
      B[k][l] = coef * mu * (dk0 * dl0 + dk1 * dl1);
      FF[k][l] = F[2 * k] * F[2 * l] + F[2 * k + 1] * F[2 * l + 1];
      t[k][l] = dk0 * F[2 * l] + dk1 * F[2 * l + 1];
    }
  }
  const T cm = coef * mu, cl = coef * lam;
  // the upper triangle (vertex pairs k <= l), mirrored: exactly symmetric blocks (A's upper triangle)
  for (int k = 0; k < 3; ++k)
    for (int l = k; l < 3; ++l) {
      const T a = A[k][l], b = B[k][l];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          if (l == k && j < i) continue;
          const T h = b * FF[i][j] + cm * (t[k][j] * t[l][i]) + cl * (t[k][i] * t[l][j]) + (i == j ? a : T(0));
          H[9 * (3 * k + i) + 3 * l + j] = h;
          H[9 * (3 * l + j) + 3 * k + i] = h;
        }
    }
}

// StVK energy density and forces of one triangle with vertices p0, p1, p2 (F of face_deformation),
// psi = mu |G|^2 + lam tr(G)^2 / 2, and, if
// f is given, f (3 vertices x 3 axes) = coef d psi / dx_k = coef (F S) D_k (the rows of P D^T).
template <typename T>
TB_HD static inline T stvk_face(const T* p0, const T* p1, const T* p2, const T* D, T mu, T lam, T coef, T* f) {
  T F[6], g[3], S[3];
  face_deformation(p0, p1, p2, D, F);
  const T tr = stvk_strain_stress(F, mu, lam, g, S);
  if (f != nullptr) {
    for (int i = 0; i < 3; ++i) {
      const T P0 = coef * (F[2 * i] * S[0] + F[2 * i + 1] * S[1]), P1 = coef * (F[2 * i] * S[1] + F[2 * i + 1] * S[2]);
      for (int k = 0; k < 3; ++k) f[3 * k + i] = P0 * D[2 * k] + P1 * D[2 * k + 1];
    }
  }
  return coef * (mu * (g[0] * g[0] + g[2] * g[2] + T(2) * g[1] * g[1]) + T(0.5) * lam * tr * tr);
}

// The StVK Hessian of one triangle applied to the direction u0, u1, u2 (its vertices'), coef d^2 psi/dx^2 u as
// 3 vertices x 3 axes in h: dP = dF S + F dS, dS = 2 mu sym(F^T dF) + lam tr(F^T dF) I (the eager
// torchbend.ops.membrane.stvk_hvp_stress), h_k = coef dP D_k.  Returns coef P : dF (the directional derivative
// of the face's energy, for the gradient's weight in a double backward).
template <typename T>
TB_HD static inline T stvk_face_hvp(const T* p0, const T* p1, const T* p2, const T* u0, const T* u1, const T* u2,
                                    const T* D, T mu, T lam, T coef, T* h) {
  T F[6], dF[6], g[3], S[3];
  face_deformation(p0, p1, p2, D, F);
  face_deformation(u0, u1, u2, D, dF);
  stvk_strain_stress(F, mu, lam, g, S);
  const T s00 = S[0], s01 = S[1], s11 = S[2];
  // M = F^T dF (2 x 2)
  const T m00 = F[0] * dF[0] + F[2] * dF[2] + F[4] * dF[4], m01 = F[0] * dF[1] + F[2] * dF[3] + F[4] * dF[5];
  const T m10 = F[1] * dF[0] + F[3] * dF[2] + F[5] * dF[4], m11 = F[1] * dF[1] + F[3] * dF[3] + F[5] * dF[5];
  const T trm = lam * (m00 + m11);
  const T d00 = T(2) * mu * m00 + trm, d11 = T(2) * mu * m11 + trm, d01 = mu * (m01 + m10);
  T dot = T(0);
  for (int i = 0; i < 3; ++i) {
    const T f0 = F[2 * i], f1 = F[2 * i + 1], df0 = dF[2 * i], df1 = dF[2 * i + 1];
    const T P0 = f0 * s00 + f1 * s01, P1 = f0 * s01 + f1 * s11;
    dot += P0 * df0 + P1 * df1;
    const T Q0 = coef * (df0 * s00 + df1 * s01 + f0 * d00 + f1 * d01);
    const T Q1 = coef * (df0 * s01 + df1 * s11 + f0 * d01 + f1 * d11);
    for (int k = 0; k < 3; ++k) h[3 * k + i] = Q0 * D[2 * k] + Q1 * D[2 * k + 1];
  }
  return coef * dot;
}


// ---- every model: the closed-form eigensystem of Smith, De Goes & Kim (torchbend.ops.membrane) -----------------
// The models and projections, numbered as the Python wrappers pass them (torchbend.backends.native).
enum MembraneModelId { kStvk = 0, kArap = 1, kSymmetricDirichlet = 2, kNeohookean = 3 };
enum MembraneProjectionId { kProjectNone = 0, kProjectClamp = 1, kProjectAbs = 2 };

TB_HD static inline float tb_hypot(float a, float b) { return hypotf(a, b); }
TB_HD static inline double tb_hypot(double a, double b) { return hypot(a, b); }
TB_HD static inline float tb_copysign(float a, float b) { return copysignf(a, b); }
TB_HD static inline double tb_copysign(double a, double b) { return copysign(a, b); }
TB_UNARY_PAIR(TB_HD static inline, tb_log, logf, log)
TB_HD static inline float tb_tiny(float) { return FLT_MIN; }
TB_HD static inline double tb_tiny(double) { return DBL_MIN; }
// hypot without the library call where no square can overflow or underflow (the largest magnitude within
// 2^-60..2^60 in float, 2^-490..2^490 in double): sqrt of the sum of squares, within an ulp of hypot; the library's
// hypot elsewhere (the call costs more than the rest of a triangle's singular values).
TB_HD static inline bool mem_squares_safe(float big) { return (big > 0x1p-60f) & (big < 0x1p60f); }
TB_HD static inline bool mem_squares_safe(double big) { return (big > 0x1p-490) & (big < 0x1p490); }
template <typename T> TB_HD static inline T tb_abs(T a) { return a < T(0) ? -a : a; }
template <typename T>
TB_HD static inline T mem_hypot(T a, T b) {
  return mem_squares_safe(tb_max(tb_abs(a), tb_abs(b))) ? tb_sqrt(a * a + b * b) : tb_hypot(a, b);
}
template <typename T>
TB_HD static inline T tb_hypot3(const T* v) {
  const T big = tb_max(tb_max(tb_abs(v[0]), tb_abs(v[1])), tb_abs(v[2]));
  return mem_squares_safe(big) ? tb_sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) : tb_hypot(tb_hypot(v[0], v[1]), v[2]);
}

// N = f0 x f1 = det(W) (e1 x e2) of a triangle (exactly zero when it has collapsed); below double the cross product is
// evaluated in double and rounded once (torchbend.ops.membrane.deformation).
template <typename T>
TB_HD static inline void face_normal(const T* p0, const T* p1, const T* p2, const T* D, T* N) {
  double e1[3], e2[3];
  for (int i = 0; i < 3; ++i) {
    e1[i] = double(T(p1[i] - p0[i]));
    e2[i] = double(T(p2[i] - p0[i]));
  }
  const T detW = D[2] * D[5] - D[3] * D[4];
  N[0] = T(e1[1] * e2[2] - e1[2] * e2[1]) * detW;
  N[1] = T(e1[2] * e2[0] - e1[0] * e2[2]) * detW;
  N[2] = T(e1[0] * e2[1] - e1[1] * e2[0]) * detW;
}

// Unit eigenvector (c, s) of [[m + d, h12], [h12, m - d]] for its eigenvalue m + r (r = hypot(d, h12)) from
// components that do not cancel; (1, 0) for a multiple of the identity (ops.membrane._unit_eigvec).
template <typename T>
TB_HD static inline void mem_unit_eigvec(T d, T h12, T r, T* c, T* s) {
  const bool pos = d >= T(0);
  const T x = pos ? d + r : h12, y = pos ? h12 : r - d;
  const T nrm = mem_hypot(x, y);
  if (nrm > T(0)) {
    const T inv = T(1) / nrm;
    *c = x * inv;
    *s = y * inv;
  } else {
    *c = T(1);
    *s = T(0);
  }
}

// Eigenvalues l[0] >= l[1] (up to the sign rule of ops.membrane._eig2) and the eigenvector (c, s) of the first.
template <typename T>
TB_HD static inline void mem_eig2(T h11, T h12, T h22, T* l, T* c, T* s) {
  const T m = T(0.5) * h11 + T(0.5) * h22, d = T(0.5) * h11 - T(0.5) * h22;
  const T r = mem_hypot(d, h12);
  const T big = m + tb_copysign(r, m);
  const T other = big != T(0) ? h11 * (h22 / big) - h12 * (h12 / big) : T(0);
  l[0] = m >= T(0) ? big : other;
  l[1] = m >= T(0) ? other : big;
  mem_unit_eigvec(d, h12, r, c, s);
}

template <typename T>
TB_HD static inline void mem_eig2_diagonal(T h11, T h22, T* l, T* c, T* s) {
  const bool first = h11 >= h22;
  l[0] = first ? h11 : h22;
  l[1] = first ? h22 : h11;
  *c = first ? T(1) : T(0);
  *s = first ? T(0) : T(1);
}

// The singular values s1 >= s2 >= 0 of F (3 x 2, row-major) with N = f0 x f1; d, b, r: the Gram matrix's
// half-difference, off-diagonal and their hypot (ops.membrane._gram).
template <typename T>
TB_HD static inline void mem_gram(const T* F, const T* N, T* s1, T* s2, T* d, T* b, T* r) {
  const T a = F[0] * F[0] + F[2] * F[2] + F[4] * F[4];
  *b = F[0] * F[1] + F[2] * F[3] + F[4] * F[5];
  const T c = F[1] * F[1] + F[3] * F[3] + F[5] * F[5];
  *d = T(0.5) * a - T(0.5) * c;
  *r = mem_hypot(*d, *b);
  *s1 = tb_sqrt((T(0.5) * a + T(0.5) * c) + *r);
  const T J = tb_hypot3(N);
  *s2 = *s1 > T(0) ? J / *s1 : T(0);
}

// The closed-form thin SVD F = U diag(s) V^T (ops.membrane._thin_svd): s, v1 = (cp, sp) (v2 = (-sp, cp)), u1, u2
// and the unit normal n = u1 x u2, with a deterministic orthonormal completion below rank 2.
template <typename T>
TB_HD static inline void mem_thin_svd(const T* F, const T* N, T* s, T* cp, T* sp, T* u1, T* u2, T* n) {
  T d, b, r;
  mem_gram(F, N, &s[0], &s[1], &d, &b, &r);
  mem_unit_eigvec(d, b, r, cp, sp);
  T w[3];
  for (int i = 0; i < 3; ++i) w[i] = F[2 * i] * *cp + F[2 * i + 1] * *sp;
  const T nw = tb_hypot3(w);
  const T iw = nw > T(0) ? T(1) / nw : T(0);  // one division, three products
  for (int i = 0; i < 3; ++i) u1[i] = nw > T(0) ? w[i] * iw : (i == 0 ? T(1) : T(0));
  const T cu = N[0] * u1[0] + N[1] * u1[1] + N[2] * u1[2];
  T m[3];
  for (int i = 0; i < 3; ++i) m[i] = N[i] - cu * u1[i];
  const T nm = tb_hypot3(m);
  if (nm > tb_tiny(T(0)) / tb_eps(T(0))) {
    const T im = T(1) / nm;
    for (int i = 0; i < 3; ++i) n[i] = m[i] * im;
  } else {  // a unit vector perpendicular to u1 (ops.membrane._perp)
    const bool use_y = (u1[0] < T(0) ? -u1[0] : u1[0]) > T(0.9);
    const T alt[3] = {use_y ? T(0) : T(1), use_y ? T(1) : T(0), T(0)};
    T p[3] = {u1[1] * alt[2] - u1[2] * alt[1], u1[2] * alt[0] - u1[0] * alt[2], u1[0] * alt[1] - u1[1] * alt[0]};
    const T np = tb_sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    for (int i = 0; i < 3; ++i) n[i] = p[i] / np;
  }
  u2[0] = n[1] * u1[2] - n[2] * u1[1];
  u2[1] = n[2] * u1[0] - n[0] * u1[2];
  u2[2] = n[0] * u1[1] - n[1] * u1[0];
}

// A model's density in the singular values (ops.membrane._stvk, _arap, _symmetric_dirichlet, _neohookean):
// returns psi; order >= 1: p = (dPsi/ds1, dPsi/ds2); order 2: l = the six eigenvalues (scaling 1, scaling 2, twist,
// flip, normal 1, normal 2) and (c, s) the first scaling eigenvector in (s1, s2).
template <typename T>
TB_HD static inline T mem_density(int model, T s1, T s2, T mu, T lam, int order, T* p, T* l, T* c, T* s) {
  if (model == kStvk) {
    const T q1 = (s1 - T(1)) * (s1 + T(1)), q2 = (s2 - T(1)) * (s2 + T(1));
    const T S = T(0.5) * (q1 + q2);
    const T psi = T(0.25) * mu * (q1 * q1 + q2 * q2) + T(0.5) * lam * S * S;
    if (order == 0) return psi;
    const T c1 = mu * q1 + lam * S, c2 = mu * q2 + lam * S;
    p[0] = c1 * s1;
    p[1] = c2 * s2;
    if (order == 1) return psi;
    const T k = T(2) * mu + lam;
    mem_eig2(c1 + k * s1 * s1, lam * s1 * s2, c2 + k * s2 * s2, l, c, s);
    l[2] = lam * S + mu * (q1 + s2 * (s2 - s1));
    l[3] = lam * S + mu * (q1 + s2 * (s2 + s1));
    l[4] = c1;
    l[5] = c2;
    return psi;
  }
  if (model == kArap) {
    const T d1 = s1 - T(1), d2 = s2 - T(1);
    const T psi = mu * (d1 * d1 + d2 * d2);
    if (order == 0) return psi;
    const T two = T(2) * mu;
    p[0] = two * d1;
    p[1] = two * d2;
    if (order == 1) return psi;
    const T floor = tb_eps(T(0));
    const T t1 = s1 < floor ? floor : s1, t2 = s2 < floor ? floor : s2;
    mem_eig2_diagonal(two, two, l, c, s);
    l[2] = two * (d1 + d2) / (t1 + s2);
    l[3] = two;
    l[4] = two * (t1 - T(1)) / t1;
    l[5] = two * (t2 - T(1)) / t2;
    return psi;
  }
  if (model == kSymmetricDirichlet) {
    const T i1 = T(1) / s1, i2 = T(1) / s2;
    const T d1 = (s1 - T(1)) * (s1 + T(1)) * i1, d2 = (s2 - T(1)) * (s2 + T(1)) * i2;
    const T psi = (mu * d1) * d1 + (mu * d2) * d2;
    if (order == 0) return psi;
    const T two = T(2) * mu;
    p[0] = (two * d1) * (T(1) + i1 * i1);
    p[1] = (two * d2) * (T(1) + i2 * i2);
    if (order == 1) return psi;
    const T six = T(6) * mu;
    mem_eig2_diagonal(two + (((six * i1) * i1) * i1) * i1, two + (((six * i2) * i2) * i2) * i2, l, c, s);
    l[3] = two + ((two * i1) * i2) * (i1 * i1 + i1 * i2 + i2 * i2);
    l[2] = s2 < T(0.5) ? two - ((two * i1) * i2) * (i1 * i1 - i1 * i2 + i2 * i2) : (p[0] + p[1]) / (s1 + s2);
    l[4] = p[0] * i1;
    l[5] = p[1] * i2;
    return psi;
  }
  // neo-Hookean
  const T lj = tb_log(s1) + tb_log(s2);
  const T q1 = (s1 - T(1)) * (s1 + T(1)), q2 = (s2 - T(1)) * (s2 + T(1));
  const T psi = T(0.5) * mu * (q1 + q2) - mu * lj + T(0.5) * lam * lj * lj;
  if (order == 0) return psi;
  const T i1 = T(1) / s1, i2 = T(1) / s2;
  p[0] = (mu * q1 + lam * lj) * i1;
  p[1] = (mu * q2 + lam * lj) * i2;
  if (order == 1) return psi;
  const T A = mu + lam * (T(1) - lj);
  const T rho = s2 * i1;
  const T k11 = A * rho * rho, k12 = lam * rho;
  const T m = T(0.5) * k11 + T(0.5) * A, d = T(0.5) * k11 - T(0.5) * A;
  const T r = mem_hypot(d, k12);
  const T big = m + tb_copysign(r, m);
  const T other = big != T(0) ? ((((mu - lam * lj) * (A + lam)) / big) * i1) * i1 : T(0);
  const T l_big = mu + (big * i2) * i2, l_other = mu + other;
  l[0] = m >= T(0) ? l_big : l_other;
  l[1] = m >= T(0) ? l_other : l_big;
  mem_unit_eigvec(d, k12, r, c, s);
  const T jm1 = (s1 - T(1)) + (s2 - T(1)) + (s1 - T(1)) * (s2 - T(1));
  l[2] = ((mu * jm1 + lam * lj) * i1) * i2;
  l[3] = ((mu * (s1 * s2 + T(1)) - lam * lj) * i1) * i2;
  l[4] = p[0] * i1;
  l[5] = p[1] * i2;
  return psi;
}

// The eigensystem of d^2 Psi / df^2 of F (3 x 2, row-major; N = f0 x f1): eigenvalues l[6] and eigenvectors Q[6][6]
// (mode-major: Q + 6 k is mode k as a row-major 3 x 2), P = dPsi/dF (row-major), returns psi
// (ops.membrane.eigensystem).
template <typename T>
TB_HD static inline T mem_eigensystem(int model, const T* F, const T* N, T mu, T lam, T* l, T* Q, T* P) {
  T s[2], cp, sp, u1[3], u2[3], n[3], p[2], c, sn;
  mem_thin_svd(F, N, s, &cp, &sp, u1, u2, n);
  const T psi = mem_density(model, s[0], s[1], mu, lam, 2, p, l, &c, &sn);
  const T v1[2] = {cp, sp}, v2[2] = {-sp, cp};
  const T h = T(0.70710678118654752440);
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 2; ++b) {
      const int j = 2 * a + b;
      const T o11 = u1[a] * v1[b], o22 = u2[a] * v2[b], o21 = u2[a] * v1[b], o12 = u1[a] * v2[b];
      Q[j] = c * o11 + sn * o22;
      Q[6 + j] = c * o22 - sn * o11;
      Q[12 + j] = h * (o21 - o12);
      Q[18 + j] = h * (o21 + o12);
      Q[24 + j] = n[a] * v1[b];
      Q[30 + j] = n[a] * v2[b];
      P[j] = p[0] * o11 + p[1] * o22;
    }
  return psi;
}

// The eigenvalue after a projection (none, clamp, abs).
template <typename T>
TB_HD static inline T mem_project(int projection, T l) {
  if (projection == kProjectClamp) return l < T(0) ? T(0) : l;
  if (projection == kProjectAbs) return l < T(0) ? -l : l;
  return l;
}

// psi and P = dPsi/dF of any model (StVK in closed form, P = F S; the others through the thin SVD, P = U diag(p) V^T).
template <typename T>
TB_HD static inline T mem_stress(int model, const T* F, const T* N, T mu, T lam, T* P) {
  if (model == kStvk) {
    T g[3], S[3];
    const T tr = stvk_strain_stress(F, mu, lam, g, S);
    for (int i = 0; i < 3; ++i) {
      P[2 * i] = F[2 * i] * S[0] + F[2 * i + 1] * S[1];
      P[2 * i + 1] = F[2 * i] * S[1] + F[2 * i + 1] * S[2];
    }
    return mu * (g[0] * g[0] + g[2] * g[2] + T(2) * g[1] * g[1]) + T(0.5) * lam * tr * tr;
  }
  T s[2], cp, sp, u1[3], u2[3], n[3], p[2], l[6], c, sn;
  mem_thin_svd(F, N, s, &cp, &sp, u1, u2, n);
  const T psi = mem_density(model, s[0], s[1], mu, lam, 1, p, l, &c, &sn);
  for (int a = 0; a < 3; ++a) {
    P[2 * a] = p[0] * u1[a] * cp - p[1] * u2[a] * sp;
    P[2 * a + 1] = p[0] * u1[a] * sp + p[1] * u2[a] * cp;
  }
  return psi;
}

// The density alone of any model (the singular values only).
template <typename T>
TB_HD static inline T mem_energy_density(int model, const T* F, const T* N, T mu, T lam) {
  if (model == kStvk) {
    T g[3], S[3];
    const T tr = stvk_strain_stress(F, mu, lam, g, S);
    return mu * (g[0] * g[0] + g[2] * g[2] + T(2) * g[1] * g[1]) + T(0.5) * lam * tr * tr;
  }
  T s1, s2, d, b, r, p[2], l[6], c, sn;
  mem_gram(F, N, &s1, &s2, &d, &b, &r);
  return mem_density(model, s1, s2, mu, lam, 0, p, l, &c, &sn);
}

// The energy coef psi of one triangle of any model and, if f is given, its forces f (3 vertices x 3 axes) =
// coef P D_k.
template <typename T>
TB_HD static inline T membrane_face(int model, const T* p0, const T* p1, const T* p2, const T* D, T mu, T lam, T coef,
                                    T* f) {
  if (model == kStvk) return stvk_face(p0, p1, p2, D, mu, lam, coef, f);
  T F[6], N[3], P[6];
  face_deformation(p0, p1, p2, D, F);
  face_normal(p0, p1, p2, D, N);
  if (f == nullptr) return coef * mem_energy_density(model, F, N, mu, lam);
  const T psi = mem_stress(model, F, N, mu, lam, P);
  for (int i = 0; i < 3; ++i) {
    const T P0 = coef * P[2 * i], P1 = coef * P[2 * i + 1];
    for (int k = 0; k < 3; ++k) f[3 * k + i] = P0 * D[2 * k] + P1 * D[2 * k + 1];
  }
  return coef * psi;
}

// The (projected) Hessian of one triangle of any model applied to the direction u0, u1, u2: h (3 vertices x 3 axes)
// = coef B^T Q diag(proj(l)) Q^T B u; returns coef P : dF.  StVK unprojected: the closed form (stvk_face_hvp).
template <typename T>
TB_HD static inline T membrane_face_hvp(int model, int projection, const T* p0, const T* p1, const T* p2, const T* u0,
                                        const T* u1, const T* u2, const T* D, T mu, T lam, T coef, T* h) {
  if (model == kStvk && projection == kProjectNone) return stvk_face_hvp(p0, p1, p2, u0, u1, u2, D, mu, lam, coef, h);
  T F[6], N[3], dF[6], l[6], Q[36], P[6], dP[6] = {T(0), T(0), T(0), T(0), T(0), T(0)};
  face_deformation(p0, p1, p2, D, F);
  face_normal(p0, p1, p2, D, N);
  face_deformation(u0, u1, u2, D, dF);
  mem_eigensystem(model, F, N, mu, lam, l, Q, P);
  T dot = T(0);
  for (int j = 0; j < 6; ++j) dot += P[j] * dF[j];
  for (int k = 0; k < 6; ++k) {
    T ck = T(0);
    for (int j = 0; j < 6; ++j) ck += Q[6 * k + j] * dF[j];
    const T w = mem_project(projection, l[k]) * ck;
    for (int j = 0; j < 6; ++j) dP[j] += w * Q[6 * k + j];
  }
  for (int i = 0; i < 3; ++i) {
    const T Q0 = coef * dP[2 * i], Q1 = coef * dP[2 * i + 1];
    for (int k = 0; k < 3; ++k) h[3 * k + i] = Q0 * D[2 * k] + Q1 * D[2 * k + 1];
  }
  return coef * dot;
}

// The (projected) Hessian of one triangle of any model, flat (9, 9) over (vertex, axis): coef sum_k proj(l_k) z_k z_k^T
// with z_k = B^T q_k (z_k[3 m + a] = (Q_k D^T)[a, m]), exactly symmetric.  Each mode is a sum of outer products
// u v^T (u in {u1, u2, n}, v in {v1, v2}), whose z is u[a] (W v)[m] for the vertices m = 1, 2 (W: D's rows 1, 2);
// vertex 0's rows are minus the sum of the others' (D's row 0 is -(W's rows summed): the translations are in the
// null space), so only the 6 x 6 block of vertices 1, 2 is accumulated over the modes.  StVK unprojected: stvk_block.
template <typename T>
TB_HD static inline void membrane_face_block(int model, int projection, const T* p0, const T* p1, const T* p2,
                                             const T* D, T mu, T lam, T coef, T* H) {
  T F[6];
  face_deformation(p0, p1, p2, D, F);
  if (model == kStvk && projection == kProjectNone) {
    stvk_block(F, D, mu, lam, coef, H);
    return;
  }
  T N[3], s[2], cp, sp, u1[3], u2[3], n[3], p[2], l[6], c, sn;
  face_normal(p0, p1, p2, D, N);
  mem_thin_svd(F, N, s, &cp, &sp, u1, u2, n);
  mem_density(model, s[0], s[1], mu, lam, 2, p, l, &c, &sn);
  for (int k = 0; k < 6; ++k) l[k] = coef * mem_project(projection, l[k]);
  // (W v1)[m], (W v2)[m] for m = 1, 2 (v1 = (cp, sp), v2 = (-sp, cp))
  T w1[2], w2[2];
  for (int m = 0; m < 2; ++m) {
    const T d0 = D[2 * (m + 1)], d1 = D[2 * (m + 1) + 1];
    w1[m] = d0 * cp + d1 * sp;
    w2[m] = d1 * cp - d0 * sp;
  }
  const T h = T(0.70710678118654752440);
  T z[6][6];  // the six modes over (vertex m = 1, 2; axis a): index 3 (m - 1) + a
  for (int m = 0; m < 2; ++m)
    for (int a = 0; a < 3; ++a) {
      const T o11 = u1[a] * w1[m], o22 = u2[a] * w2[m], o21 = u2[a] * w1[m], o12 = u1[a] * w2[m];
      const int j = 3 * m + a;
      z[0][j] = c * o11 + sn * o22;
      z[1][j] = c * o22 - sn * o11;
      z[2][j] = h * (o21 - o12);
      z[3][j] = h * (o21 + o12);
      z[4][j] = n[a] * w1[m];
      z[5][j] = n[a] * w2[m];
    }
  T R[6][6];  // vertices 1, 2
  for (int r = 0; r < 6; ++r) {
    T lz[6];
    for (int k = 0; k < 6; ++k) lz[k] = l[k] * z[k][r];
    for (int q = r; q < 6; ++q) {
      T acc = T(0);
      for (int k = 0; k < 6; ++k) acc += lz[k] * z[k][q];
      R[r][q] = acc;
      R[q][r] = acc;
    }
  }
  T C[3][6];  // vertex 0 against vertices 1, 2: minus the column sums over vertices 1, 2
  for (int a = 0; a < 3; ++a)
    for (int q = 0; q < 6; ++q) C[a][q] = -(R[a][q] + R[3 + a][q]);
  for (int a = 0; a < 3; ++a)
    for (int b = a; b < 3; ++b) {
      const T v = -(C[a][b] + C[a][3 + b]);  // vertex 0 against itself
      H[9 * a + b] = v;
      H[9 * b + a] = v;
    }
  for (int a = 0; a < 3; ++a)
    for (int q = 0; q < 6; ++q) {
      H[9 * a + 3 + q] = C[a][q];
      H[9 * (3 + q) + a] = C[a][q];
    }
  for (int r = 0; r < 6; ++r)
    for (int q = 0; q < 6; ++q) H[9 * (3 + r) + 3 + q] = R[r][q];
}

}  // namespace torchbend
