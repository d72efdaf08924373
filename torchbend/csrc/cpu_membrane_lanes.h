// The membrane's per-triangle mathematics over the lanes of a tile (CPU only; cpu_membrane.cpp's tiles run it):
// the thin SVD, the density's eigenvalues, the stress and the HVP in the SVD's frame of every model, and a tile's
// gather, deformation, normal and pull-back to the vertices.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "membrane_math.h"

namespace torchbend {
namespace cpu {

// ---- the thin SVD, stress and eigensystem of every model over the lanes of a tile ---------------------------------
// The scalar membrane_math.h functions call the C library's hypot (and log) and branch.  These lane versions take
// hypot by a power-of-two scaling (lane_scale), select instead of branching, and take neo-Hookean's log J from
// vector_math.h's tb_logv (no library call); the formulas are mem_thin_svd's and mem_density's, so that GCC
// vectorizes the lane loops (tools/check_vectorization.py requires it).  Every energy, gradient, HVP and block but
// unprojected StVK's (which has its own closed form) runs here.
constexpr int kLanes = 8;
constexpr int64_t kFaceChunk = 4096;  // faces per pass of the energy, gradient and HVP (a multiple of kLanes)

// A power of two s (and 1 / s) that brings the largest magnitude `big` into the range where squares neither
// overflow nor underflow (mem_squares_safe); 1 inside it.  Scaling by s is exact, so hypot(a, b) =
// sqrt((s a)^2 + (s b)^2) / s is the fast formula's result wherever that one is safe, without a division.
static TB_FORCEINLINE double lane_scale(double big, double& inv) {
  const bool up = !(big > 0x1p-490), down = big >= 0x1p490;
  inv = up ? 0x1p-600 : (down ? 0x1p600 : 1.0);
  return up ? 0x1p600 : (down ? 0x1p-600 : 1.0);
}
static TB_FORCEINLINE float lane_scale(float big, float& inv) {
  const bool up = !(big > 0x1p-60f), down = big >= 0x1p60f;
  inv = up ? 0x1p-100f : (down ? 0x1p80f : 1.0f);
  return up ? 0x1p100f : (down ? 0x1p-80f : 1.0f);
}

template <typename T>
static TB_FORCEINLINE T lane_hypot(T a, T b) {
  T inv;
  const T sc = lane_scale(std::max(std::abs(a), std::abs(b)), inv);
  const T sa = a * sc, sb = b * sc;
  return std::sqrt(sa * sa + sb * sb) * inv;
}

template <typename T>
static TB_FORCEINLINE T lane_hypot3(T a, T b, T c) {
  T inv;
  const T sc = lane_scale(std::max(std::max(std::abs(a), std::abs(b)), std::abs(c)), inv);
  const T sa = a * sc, sb = b * sc, sd = c * sc;
  return std::sqrt(sa * sa + sb * sb + sd * sd) * inv;
}

// The unit eigenvector (c, s) of [[m + d, h12], [h12, m - d]] for its eigenvalue m + r (mem_unit_eigvec)
template <typename T>
static TB_FORCEINLINE void lane_eigvec(T d, T h12, T r, T& c, T& s) {
  const bool pos = d >= T(0);
  const T ex = pos ? d + r : h12, ey = pos ? h12 : r - d;
  const T nrm = lane_hypot(ex, ey);
  const T inv = T(1) / (nrm > T(0) ? nrm : T(1));
  c = nrm > T(0) ? ex * inv : T(1);
  s = nrm > T(0) ? ey * inv : T(0);
}

// The thin SVD F = U diag(s1, s2) V^T of one triangle (mem_thin_svd): v1 = (cp, sp), u1, u2 and the unit normal n
template <typename T>
struct LaneSvd {
  T s1, s2, cp, sp, u1[3], u2[3], n[3];
};

// The singular values s1 >= s2 >= 0 of F with N = f0 x f1 (mem_gram); d, b, r: the Gram matrix's half-difference,
// off-diagonal and their hypot
template <typename T>
static TB_FORCEINLINE void lane_singular_values(const T (&F)[6], const T (&N)[3], T& s1, T& s2, T& d, T& b, T& r) {
  const T a = F[0] * F[0] + F[2] * F[2] + F[4] * F[4];
  const T c = F[1] * F[1] + F[3] * F[3] + F[5] * F[5];
  b = F[0] * F[1] + F[2] * F[3] + F[4] * F[5];
  d = T(0.5) * a - T(0.5) * c;
  r = lane_hypot(d, b);
  s1 = std::sqrt((T(0.5) * a + T(0.5) * c) + r);
  const T J = lane_hypot3(N[0], N[1], N[2]);
  s2 = s1 > T(0) ? J / (s1 > T(0) ? s1 : T(1)) : T(0);
}

template <typename T>
static TB_FORCEINLINE LaneSvd<T> lane_svd(const T (&F)[6], const T (&N)[3]) {
  LaneSvd<T> o;
  T d, b, r;
  lane_singular_values(F, N, o.s1, o.s2, d, b, r);
  lane_eigvec(d, b, r, o.cp, o.sp);
  // u1 = F v1 / |F v1|
  const T w0 = F[0] * o.cp + F[1] * o.sp, w1 = F[2] * o.cp + F[3] * o.sp, w2 = F[4] * o.cp + F[5] * o.sp;
  const T nw = lane_hypot3(w0, w1, w2);
  const T iw = T(1) / (nw > T(0) ? nw : T(1));
  const T u10 = nw > T(0) ? w0 * iw : T(1), u11 = nw > T(0) ? w1 * iw : T(0), u12 = nw > T(0) ? w2 * iw : T(0);
  // n: N made orthogonal to u1, else a unit vector perpendicular to u1
  const T cu = N[0] * u10 + N[1] * u11 + N[2] * u12;
  const T m0 = N[0] - cu * u10, m1 = N[1] - cu * u11, m2 = N[2] - cu * u12;
  const T nm = lane_hypot3(m0, m1, m2);
  const bool okn = nm > tb_tiny(T(0)) / tb_eps(T(0));
  const T im = T(1) / (okn ? nm : T(1));
  const bool use_y = std::abs(u10) > T(0.9);
  const T al0 = use_y ? T(0) : T(1), al1 = use_y ? T(1) : T(0);
  const T q0 = -u12 * al1, q1 = u12 * al0, q2 = u10 * al1 - u11 * al0;  // u1 x (al0, al1, 0)
  const T iq = T(1) / std::sqrt(q0 * q0 + q1 * q1 + q2 * q2);
  const T n0 = okn ? m0 * im : q0 * iq, n1 = okn ? m1 * im : q1 * iq, n2 = okn ? m2 * im : q2 * iq;
  o.u1[0] = u10, o.u1[1] = u11, o.u1[2] = u12;
  o.n[0] = n0, o.n[1] = n1, o.n[2] = n2;
  o.u2[0] = n1 * u12 - n2 * u11, o.u2[1] = n2 * u10 - n0 * u12, o.u2[2] = n0 * u11 - n1 * u10;
  return o;
}

// A model's density in the singular values (mem_density): psi, p = (dPsi/ds1, dPsi/ds2) and, with Second, the six
// eigenvalues l (scaling 1, scaling 2, twist, flip, normal 1, normal 2) and (c, s) the first scaling eigenvector;
// both sides of every branch computed and selected
template <typename T, int Model, bool Second>
static TB_FORCEINLINE T lane_density(T s1, T s2, T mu, T lam, T (&p)[2], T (&l)[6], T& c, T& s) {
  if (Model == kStvk) {
    const T q1 = (s1 - T(1)) * (s1 + T(1)), q2 = (s2 - T(1)) * (s2 + T(1));
    const T S = T(0.5) * (q1 + q2);
    const T psi = T(0.25) * mu * (q1 * q1 + q2 * q2) + T(0.5) * lam * S * S;
    const T c1 = mu * q1 + lam * S, c2 = mu * q2 + lam * S;
    p[0] = c1 * s1;
    p[1] = c2 * s2;
    if (!Second) return psi;
    const T k = T(2) * mu + lam;
    const T h11 = c1 + k * s1 * s1, h12 = lam * s1 * s2, h22 = c2 + k * s2 * s2;  // mem_eig2
    const T m = T(0.5) * h11 + T(0.5) * h22, d = T(0.5) * h11 - T(0.5) * h22;
    const T r = lane_hypot(d, h12);
    const T big = m + std::copysign(r, m);
    const T sb = big != T(0) ? big : T(1);
    const T other = big != T(0) ? h11 * (h22 / sb) - h12 * (h12 / sb) : T(0);
    l[0] = m >= T(0) ? big : other;
    l[1] = m >= T(0) ? other : big;
    lane_eigvec(d, h12, r, c, s);
    l[2] = lam * S + mu * (q1 + s2 * (s2 - s1));
    l[3] = lam * S + mu * (q1 + s2 * (s2 + s1));
    l[4] = c1;
    l[5] = c2;
    return psi;
  }
  if (Model == kArap) {
    const T d1 = s1 - T(1), d2 = s2 - T(1);
    const T psi = mu * (d1 * d1 + d2 * d2);
    const T two = T(2) * mu;
    p[0] = two * d1;
    p[1] = two * d2;
    if (!Second) return psi;
    const T floor = tb_eps(T(0));
    const T t1 = s1 < floor ? floor : s1, t2 = s2 < floor ? floor : s2;
    l[0] = two, l[1] = two, c = T(1), s = T(0);  // mem_eig2_diagonal(two, two)
    l[2] = two * (d1 + d2) / (t1 + s2);
    l[3] = two;
    l[4] = two * (t1 - T(1)) / t1;
    l[5] = two * (t2 - T(1)) / t2;
    return psi;
  }
  if (Model == kSymmetricDirichlet) {
    const T i1 = T(1) / s1, i2 = T(1) / s2;
    const T d1 = (s1 - T(1)) * (s1 + T(1)) * i1, d2 = (s2 - T(1)) * (s2 + T(1)) * i2;
    const T psi = (mu * d1) * d1 + (mu * d2) * d2;
    const T two = T(2) * mu;
    p[0] = (two * d1) * (T(1) + i1 * i1);
    p[1] = (two * d2) * (T(1) + i2 * i2);
    if (!Second) return psi;
    const T six = T(6) * mu;
    const T h11 = two + (((six * i1) * i1) * i1) * i1, h22 = two + (((six * i2) * i2) * i2) * i2;
    const bool first = h11 >= h22;  // mem_eig2_diagonal
    l[0] = first ? h11 : h22;
    l[1] = first ? h22 : h11;
    c = first ? T(1) : T(0);
    s = first ? T(0) : T(1);
    l[3] = two + ((two * i1) * i2) * (i1 * i1 + i1 * i2 + i2 * i2);
    l[2] = s2 < T(0.5) ? two - ((two * i1) * i2) * (i1 * i1 - i1 * i2 + i2 * i2) : (p[0] + p[1]) / (s1 + s2);
    l[4] = p[0] * i1;
    l[5] = p[1] * i2;
    return psi;
  }
  // neo-Hookean (log J by tb_logv: J = s1 s2 may underflow where s1, s2 do not)
  const T lj = tb_logv(s1) + tb_logv(s2);
  const T q1 = (s1 - T(1)) * (s1 + T(1)), q2 = (s2 - T(1)) * (s2 + T(1));
  const T psi = T(0.5) * mu * (q1 + q2) - mu * lj + T(0.5) * lam * lj * lj;
  const T i1 = T(1) / s1, i2 = T(1) / s2;
  p[0] = (mu * q1 + lam * lj) * i1;
  p[1] = (mu * q2 + lam * lj) * i2;
  if (!Second) return psi;
  const T A = mu + lam * (T(1) - lj);
  const T rho = s2 * i1;
  const T k11 = A * rho * rho, k12 = lam * rho;
  const T m = T(0.5) * k11 + T(0.5) * A, d = T(0.5) * k11 - T(0.5) * A;
  const T r = lane_hypot(d, k12);
  const T big = m + std::copysign(r, m);
  const T sb = big != T(0) ? big : T(1);
  const T other = big != T(0) ? ((((mu - lam * lj) * (A + lam)) / sb) * i1) * i1 : T(0);
  const T l_big = mu + (big * i2) * i2, l_other = mu + other;
  l[0] = m >= T(0) ? l_big : l_other;
  l[1] = m >= T(0) ? l_other : l_big;
  lane_eigvec(d, k12, r, c, s);
  const T jm1 = (s1 - T(1)) + (s2 - T(1)) + (s1 - T(1)) * (s2 - T(1));
  l[2] = ((mu * jm1 + lam * lj) * i1) * i2;
  l[3] = ((mu * (s1 * s2 + T(1)) - lam * lj) * i1) * i2;
  l[4] = p[0] * i1;
  l[5] = p[1] * i2;
  return psi;
}

// psi and P = dPsi/dF (row-major, P[j] for j = 2 a + b) of one triangle of ARAP, symmetric Dirichlet or neo-Hookean
// from F and N: P = U diag(p) V^T
template <typename T, int Model>
static TB_FORCEINLINE T lane_stress(const T (&F)[6], const T (&N)[3], T mu, T lam, T* P) {
  const LaneSvd<T> o = lane_svd(F, N);
  T p[2], l[6], c, s;
  const T psi = lane_density<T, Model, false>(o.s1, o.s2, mu, lam, p, l, c, s);
  for (int a = 0; a < 3; ++a) {
    P[2 * a] = p[0] * o.u1[a] * o.cp - p[1] * o.u2[a] * o.sp;
    P[2 * a + 1] = p[0] * o.u1[a] * o.sp + p[1] * o.u2[a] * o.cp;
  }
  return psi;
}

// The (projected) Hessian of one triangle's density applied to dF, in the SVD's frame (membrane_face_hvp without
// forming the modes): A = U^T dF V (U = [u1 u2 n], V = [v1 v2]), the modes' coordinates of dF from A, scaled by
// the projected eigenvalues, mapped back to dP = U B V^T; returns P : dF = p1 A11 + p2 A22
template <typename T, int Model, int Proj>
static TB_FORCEINLINE T lane_hvp(const T (&F)[6], const T (&N)[3], const T (&dF)[6], T mu, T lam, T* dP) {
  const LaneSvd<T> o = lane_svd(F, N);
  T p[2], l[6], c, s;
  lane_density<T, Model, true>(o.s1, o.s2, mu, lam, p, l, c, s);
  T g1[3], g2[3];  // dF v1, dF v2
  for (int a = 0; a < 3; ++a) {
    g1[a] = dF[2 * a] * o.cp + dF[2 * a + 1] * o.sp;
    g2[a] = dF[2 * a + 1] * o.cp - dF[2 * a] * o.sp;
  }
  const T a11 = o.u1[0] * g1[0] + o.u1[1] * g1[1] + o.u1[2] * g1[2];
  const T a12 = o.u1[0] * g2[0] + o.u1[1] * g2[1] + o.u1[2] * g2[2];
  const T a21 = o.u2[0] * g1[0] + o.u2[1] * g1[1] + o.u2[2] * g1[2];
  const T a22 = o.u2[0] * g2[0] + o.u2[1] * g2[1] + o.u2[2] * g2[2];
  const T a31 = o.n[0] * g1[0] + o.n[1] * g1[1] + o.n[2] * g1[2];
  const T a32 = o.n[0] * g2[0] + o.n[1] * g2[1] + o.n[2] * g2[2];
  const T h = T(0.70710678118654752440);
  const T ck[6] = {c * a11 + s * a22, c * a22 - s * a11, h * (a21 - a12), h * (a21 + a12), a31, a32};
  T w[6];  // the modes' coordinates times the projected eigenvalues
  for (int k = 0; k < 6; ++k)
    w[k] = (Proj == kProjectClamp ? std::max(l[k], T(0)) : Proj == kProjectAbs ? std::abs(l[k]) : l[k]) * ck[k];
  const T b11 = c * w[0] - s * w[1], b22 = s * w[0] + c * w[1];
  const T b21 = h * (w[2] + w[3]), b12 = h * (w[3] - w[2]);
  for (int a = 0; a < 3; ++a) {
    const T r1 = o.u1[a] * b11 + o.u2[a] * b21 + o.n[a] * w[4];  // (U B)[a, 1]
    const T r2 = o.u1[a] * b12 + o.u2[a] * b22 + o.n[a] * w[5];  // (U B)[a, 2]
    dP[2 * a] = r1 * o.cp - r2 * o.sp;
    dP[2 * a + 1] = r1 * o.sp + r2 * o.cp;
  }
  return p[0] * a11 + p[1] * a22;
}

// The inputs of the triangles [e0, e0 + nl) of one sample (nl <= kLanes) over the lanes of a tile: the edge vectors
// e1 = p1 - p0, e2 = p2 - p0 of positions x (and of a direction v), D's six entries and coef; idle lanes a right
// triangle at rest (F = [I; 0]) with no weight.  The gather is scalar, what follows runs over the lanes.
template <typename T>
struct MembraneTile {
  alignas(64) T E[6][kLanes];  // e1 (0..2), e2 (3..5) of x
  alignas(64) T dE[6][kLanes];  // of the direction (HVP only)
  alignas(64) T D[6][kLanes];
  alignas(64) T c[kLanes];
};

template <typename T>
static TB_FORCEINLINE void gather_edges(const T* xb, const int64_t* fc, int64_t e0, int nl, T (&E)[6][kLanes]) {
  for (int l = 0; l < kLanes; ++l) {
    if (l < nl) {
      const int64_t* t = fc + 3 * (e0 + l);
      const T *p0 = xb + 3 * t[0], *p1 = xb + 3 * t[1], *p2 = xb + 3 * t[2];
      for (int i = 0; i < 3; ++i) E[i][l] = p1[i] - p0[i], E[3 + i][l] = p2[i] - p0[i];
    } else {
      for (int i = 0; i < 6; ++i) E[i][l] = (i == 0 || i == 4) ? T(1) : T(0);
    }
  }
}

template <typename T>
static TB_FORCEINLINE void gather_tile(MembraneTile<T>& g, const T* xb, const T* vb, const int64_t* fc, const T* d,
                                       const T* c, int64_t e0, int nl) {
  gather_edges(xb, fc, e0, nl, g.E);
  if (vb != nullptr) gather_edges(vb, fc, e0, nl, g.dE);
  for (int l = 0; l < kLanes; ++l) {
    const T* De = d + 6 * (e0 + l);
    for (int j = 0; j < 6; ++j) g.D[j][l] = l < nl ? De[j] : (j == 2 || j == 5 ? T(1) : T(0));
    g.c[l] = l < nl ? c[e0 + l] : T(0);
  }
}

// F (3 x 2, row-major) from the edges and W = D's rows 1, 2 (face_deformation), in lane l
template <typename T>
static TB_FORCEINLINE void lane_deformation(const T (&E)[6][kLanes], const T (&D)[6][kLanes], int l, T (&F)[6]) {
  for (int i = 0; i < 3; ++i) {
    F[2 * i] = E[i][l] * D[2][l] + E[3 + i][l] * D[4][l];
    F[2 * i + 1] = E[i][l] * D[3][l] + E[3 + i][l] * D[5][l];
  }
}

// N = det(W) (e1 x e2), the cross product in double below double (face_normal), in lane l
template <typename T>
static TB_FORCEINLINE void lane_normal(const T (&E)[6][kLanes], const T (&D)[6][kLanes], int l, T (&N)[3]) {
  const double a0 = E[0][l], a1 = E[1][l], a2 = E[2][l], b0 = E[3][l], b1 = E[4][l], b2 = E[5][l];
  const T detW = D[2][l] * D[5][l] - D[3][l] * D[4][l];
  N[0] = T(a1 * b2 - a2 * b1) * detW;
  N[1] = T(a2 * b0 - a0 * b2) * detW;
  N[2] = T(a0 * b1 - a1 * b0) * detW;
}

// out (3 vertices x 3 axes, as out[3 k + i][l]) = coef G D_k of a (3 x 2) G in lane l: forces from P, HVPs from dP
template <typename T>
static TB_FORCEINLINE void lane_pull_back(const T (&G)[6], const T (&D)[6][kLanes], T ce, int l, T (&out)[9][kLanes]) {
  for (int i = 0; i < 3; ++i) {
    const T G0 = ce * G[2 * i], G1 = ce * G[2 * i + 1];
    for (int k = 0; k < 3; ++k) out[3 * k + i][l] = G0 * D[2 * k][l] + G1 * D[2 * k + 1][l];
  }
}

}  // namespace cpu
}  // namespace torchbend
