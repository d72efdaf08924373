// The contact operators' scans over lanes of stencils (cpu_contact.cpp): the close-pair search's distance types
// and squared distances of every candidate (contact_close), and the pairs' energies alone (contact_barrier with
// want = 0, a line search's trial points), kClose stencils at a time with the lanes innermost.
#pragma once
#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <type_traits>

#include "contact_math.h"
#include "vector_math.h"

namespace torchbend {
namespace cpu {
namespace {

namespace cm = torchbend::contact;

// ---- the close-pair search over lanes of stencils ---------------------------------------------------
// contact_close types every candidate: the distance types of kClose stencils at a time, lanes innermost, by the
// classifiers of contact_math.h (point_triangle_type, edge_edge_type) written branch-free: the same operations in
// the same order and, as there, without contracting a * b + c, so that each lane's type is the scalar one
// bit for bit (tests/test_contact_native.py).  The lanes' squared distances are the typed formulas' (point-triangle:
// the same expressions) or those of the closest points the classification finds (edge-edge: equal up to rounding,
// which for nearly parallel edges can reach many ulps): only a pair that close to dhat can be kept by one and not
// the other, where its barrier and the barrier's first two derivatives are about zero.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC push_options
#pragma GCC optimize("fp-contract=off")
#endif

constexpr int kClose = 16;

template <typename A> TB_FORCEINLINE A clamp01(A s) { return s < 0 ? A(0) : (s > 1 ? A(1) : s); }

// the squared distance of p to the segment e0 e1 and where its nearest point is (0: e0, 1: e1, 2: inside): as
// contact::point_segment
template <typename A> TB_FORCEINLINE A segment_lane(A p0, A p1, A p2, A s0, A s1, A s2, A t0, A t1, A t2, int& where) {
  const A e0 = t0 - s0, e1 = t1 - s1, e2 = t2 - s2, w0 = p0 - s0, w1 = p1 - s1, w2 = p2 - s2;
  const A ee = e0 * e0 + e1 * e1 + e2 * e2;
  const A tiny = sizeof(A) == 4 ? A(FLT_MIN) : A(DBL_MIN);
  A t = (w0 * e0 + w1 * e1 + w2 * e2) / (ee > tiny ? ee : tiny);
  t = clamp01(t);
  where = t <= 0 ? 0 : (t >= 1 ? 1 : 2);
  const A q0 = p0 - (s0 + t * e0), q1 = p1 - (s1 + t * e1), q2 = p2 - (s2 + t * e2);
  return q0 * q0 + q1 * q1 + q2 * q2;
}

// edge-edge lanes (corners a0, a1, b0, b1 as P[3 v + i][l], in double): contact::edge_edge_type with
// parallel = 1e-10, and the squared distance
void ee_close_lanes(const double (*P)[kClose], int* type, double* D) {
  TB_LANES(kClose) {
    const double a00 = P[0][l], a01 = P[1][l], a02 = P[2][l], a10 = P[3][l], a11 = P[4][l], a12 = P[5][l];
    const double b00 = P[6][l], b01 = P[7][l], b02 = P[8][l], b10 = P[9][l], b11 = P[10][l], b12 = P[11][l];
    const double u0 = a10 - a00, u1 = a11 - a01, u2 = a12 - a02, v0 = b10 - b00, v1 = b11 - b01, v2 = b12 - b02;
    const double w0 = a00 - b00, w1 = a01 - b01, w2 = a02 - b02;
    const double a = u0 * u0 + u1 * u1 + u2 * u2, b = u0 * v0 + u1 * v1 + u2 * v2, c = v0 * v0 + v1 * v1 + v2 * v2;
    const double d = u0 * w0 + u1 * w1 + u2 * w2, e = v0 * w0 + v1 * w1 + v2 * w2;
    const double den = a * c - b * b;
    const bool parallel = den <= 1e-10 * a * c;
    // not parallel: the clamped parameters of the nearest points
    double s = clamp01((b * e - c * d) / den);
    double t = (b * s + e) / c;
    const bool below = t < 0, above = !below && t > 1;
    const double s_below = clamp01(-d / a), s_above = clamp01((b - d) / a);
    s = below ? s_below : (above ? s_above : s);
    t = below ? 0.0 : (above ? 1.0 : t);
    const int si = s <= 0 ? 0 : (s >= 1 ? 1 : 2), ti = t <= 0 ? 0 : (t >= 1 ? 1 : 2);
    // {{A0B0, A0B1, A0B}, {A1B0, A1B1, A1B}, {AB0, AB1, LINES}}[si][ti]
    const int t_lines = si < 2 ? (ti < 2 ? cm::EE_A0B0 + 2 * si + ti : cm::EE_A0B + si)
                               : (ti < 2 ? cm::EE_AB0 + ti : cm::EE_LINES);
    const double q0 = w0 + s * u0 - t * v0, q1 = w1 + s * u1 - t * v1, q2 = w2 + s * u2 - t * v2;
    const double d_lines = q0 * q0 + q1 * q1 + q2 * q2;
    // parallel: the nearest of the four corner-segment pairs (the first of equal minima)
    int h0, h1, h2, h3;
    const double D0 = segment_lane(a00, a01, a02, b00, b01, b02, b10, b11, b12, h0);
    const double D1 = segment_lane(a10, a11, a12, b00, b01, b02, b10, b11, b12, h1);
    const double D2 = segment_lane(b00, b01, b02, a00, a01, a02, a10, a11, a12, h2);
    const double D3 = segment_lane(b10, b11, b12, a00, a01, a02, a10, a11, a12, h3);
    int k = 0, hk = h0;
    double dk = D0;
    if (D1 < dk) { k = 1; hk = h1; dk = D1; }
    if (D2 < dk) { k = 2; hk = h2; dk = D2; }
    if (D3 < dk) { k = 3; hk = h3; dk = D3; }
    // {{A0B0, A0B1, A0B}, {A1B0, A1B1, A1B}, {A0B0, A1B0, AB0}, {A0B1, A1B1, AB1}}[k][hk]
    const int t_par = k < 2 ? (hk < 2 ? cm::EE_A0B0 + 2 * k + hk : cm::EE_A0B + k)
                            : (hk < 2 ? cm::EE_A0B0 + (k - 2) + 2 * hk : cm::EE_AB0 + (k - 2));
    type[l] = parallel ? t_par : t_lines;
    D[l] = parallel ? dk : d_lines;
  }
}

// point-triangle lanes (p, t0, t1, t2 as P[3 v + i][l], in T): contact::point_triangle_type and the squared
// distance
template <typename T> void pt_close_lanes(const T (*P)[kClose], int* type, T* D) {
  TB_LANES(kClose) {
    const T p0 = P[0][l], p1 = P[1][l], p2 = P[2][l], a0 = P[3][l], a1 = P[4][l], a2 = P[5][l];
    const T b0 = P[6][l], b1 = P[7][l], b2 = P[8][l], c0 = P[9][l], c1 = P[10][l], c2 = P[11][l];
    const T ab0 = b0 - a0, ab1 = b1 - a1, ab2 = b2 - a2, ac0 = c0 - a0, ac1 = c1 - a1, ac2 = c2 - a2;
    const T ap0 = p0 - a0, ap1 = p1 - a1, ap2 = p2 - a2, bp0 = p0 - b0, bp1 = p1 - b1, bp2 = p2 - b2;
    const T cp0 = p0 - c0, cp1 = p1 - c1, cp2 = p2 - c2;
    const T d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2, d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2;
    const T d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2, d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2;
    const T d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2, d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2;
    const T va = d3 * d6 - d5 * d4, vb = d5 * d2 - d1 * d6, vc = d1 * d4 - d3 * d2;
    // the first test that holds, in contact::point_triangle_type's order
    int t = cm::PT_FACE;
    t = va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0 ? int(cm::PT_E12) : t;
    t = vb <= 0 && d2 >= 0 && d6 <= 0 ? int(cm::PT_E20) : t;
    t = vc <= 0 && d1 >= 0 && d3 <= 0 ? int(cm::PT_E01) : t;
    t = d6 >= 0 && d5 <= d6 ? int(cm::PT_P2) : t;
    t = d3 >= 0 && d4 <= d3 ? int(cm::PT_P1) : t;
    t = d1 <= 0 && d2 <= 0 ? int(cm::PT_P0) : t;
    // the distance of the type: to a corner, to an edge's line (e x f / |f|), to the plane
    const T pp = t == cm::PT_P0 ? ap0 * ap0 + ap1 * ap1 + ap2 * ap2
                                : (t == cm::PT_P1 ? bp0 * bp0 + bp1 * bp1 + bp2 * bp2 : cp0 * cp0 + cp1 * cp1 + cp2 * cp2);
    const bool e12 = t == cm::PT_E12, e20 = t == cm::PT_E20;
    const T e0 = e12 ? bp0 : (e20 ? cp0 : ap0), e1 = e12 ? bp1 : (e20 ? cp1 : ap1), e2 = e12 ? bp2 : (e20 ? cp2 : ap2);
    const T f0 = e12 ? c0 - b0 : (e20 ? a0 - c0 : ab0), f1 = e12 ? c1 - b1 : (e20 ? a1 - c1 : ab1);
    const T f2 = e12 ? c2 - b2 : (e20 ? a2 - c2 : ab2);
    const T x0 = e1 * f2 - e2 * f1, x1 = e2 * f0 - e0 * f2, x2 = e0 * f1 - e1 * f0;
    const T pe = (x0 * x0 + x1 * x1 + x2 * x2) / (f0 * f0 + f1 * f1 + f2 * f2);
    const T n0 = ab1 * ac2 - ab2 * ac1, n1 = ab2 * ac0 - ab0 * ac2, n2 = ab0 * ac1 - ab1 * ac0;
    const T sn = ap0 * n0 + ap1 * n1 + ap2 * n2;
    const T pl = sn * sn / (n0 * n0 + n1 * n1 + n2 * n2);
    type[l] = t;
    D[l] = t <= cm::PT_P2 ? pp : (t < cm::PT_FACE ? pe : pl);
  }
}

// The energies alone (contact_barrier with want = 0, a line search's trial points), kClose pairs at a time: each
// lane's reduced coordinates y = C x as contact::reduce forms them (C's entries are -1, 0, 1: one rounded
// difference per coordinate), its formula's squared distance and the edge pairs' mollifier argument spelled as
// contact::typed_distance and contact::edge_cross_sq, without contraction as there: the energies are pair_terms'
// bit for bit.  D and the mollifier M (1 where eps = 0 or c >= eps) per lane; the barrier's log is taken after.
template <typename T> void energy_lanes(const T (*X)[kClose], const T (*C)[4][kClose], const int* form, T* D, T* M) {
  TB_LANES_AGG(kClose) {
    T y[9];
    for (int r = 0; r < 3; ++r)
      for (int i = 0; i < 3; ++i)
        y[3 * r + i] = C[r][0][l] * X[i][l] + C[r][1][l] * X[3 + i][l] + C[r][2][l] * X[6 + i][l] +
                       C[r][3][l] * X[9 + i][l];
    const T pp = y[0] * y[0] + y[1] * y[1] + y[2] * y[2];
    const T x0 = y[1] * y[5] - y[2] * y[4], x1 = y[2] * y[3] - y[0] * y[5], x2 = y[0] * y[4] - y[1] * y[3];
    const T pe = (x0 * x0 + x1 * x1 + x2 * x2) / (y[3] * y[3] + y[4] * y[4] + y[5] * y[5]);
    const T n0 = y[4] * y[8] - y[5] * y[7], n1 = y[5] * y[6] - y[3] * y[8], n2 = y[3] * y[7] - y[4] * y[6];
    const T sn = y[0] * n0 + y[1] * n1 + y[2] * n2;
    const T pl = sn * sn / (n0 * n0 + n1 * n1 + n2 * n2);
    D[l] = form[l] == cm::F_PP ? pp : (form[l] == cm::F_PE ? pe : pl);
    const T a0 = X[3][l] - X[0][l], a1 = X[4][l] - X[1][l], a2 = X[5][l] - X[2][l];
    const T b0 = X[9][l] - X[6][l], b1 = X[10][l] - X[7][l], b2 = X[11][l] - X[8][l];
    const T c0 = a1 * b2 - a2 * b1, c1 = a2 * b0 - a0 * b2, c2 = a0 * b1 - a1 * b0;
    const T cc = c0 * c0 + c1 * c1 + c2 * c2, eps = M[l], rr = cc / eps;
    M[l] = eps > 0 && cc < eps ? (2 - rr) * rr : T(1);
  }
}

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC pop_options
#endif

// the types (-1: not closer than sqrt(dh2)) of the candidate stencils n0 .. n1 - 1
template <typename T> void close_types(const T* px, const int64_t* ps, bool edge_edge, double dh2, int64_t n0,
                                       int64_t n1, int8_t* out) {
  using A = std::conditional_t<std::is_same<T, float>::value, float, double>;
  alignas(64) A P[12][kClose];
  alignas(64) double Pd[12][kClose];
  alignas(64) int type[kClose];
  alignas(64) A DA[kClose];
  alignas(64) double DD[kClose];
  for (int64_t m = n0; m < n1; m += kClose) {
    const int nl = int(std::min<int64_t>(kClose, n1 - m));
    for (int l = 0; l < kClose; ++l) {
      const int64_t* s = ps + 4 * (m + (l < nl ? l : 0));  // the lanes past the end repeat the first
      for (int v = 0; v < 4; ++v)
        for (int i = 0; i < 3; ++i) {
          const T xv = px[3 * s[v] + i];
          if (edge_edge) Pd[3 * v + i][l] = double(xv);
          else P[3 * v + i][l] = A(xv);
        }
    }
    if (edge_edge) {
      ee_close_lanes(Pd, type, DD);
      for (int l = 0; l < nl; ++l) out[m + l] = DD[l] < dh2 ? int8_t(type[l]) : int8_t(-1);
    } else {
      pt_close_lanes<A>(P, type, DA);
      for (int l = 0; l < nl; ++l) out[m + l] = DA[l] < A(dh2) ? int8_t(type[l]) : int8_t(-1);
    }
  }
}

// the energies of the pairs n0 .. n1 - 1 (energy_lanes, then the barrier lane by lane as contact::barrier)
template <typename T> void pair_energies(const T* px, const int64_t* ps, const int64_t* pt, const T* pe, T dh2,
                                         T kappa, int64_t n0, int64_t n1, T* pE) {
  alignas(64) T X[12][kClose], C[3][4][kClose], D[kClose], M[kClose];
  alignas(64) int form[kClose];
  for (int64_t m0 = n0; m0 < n1; m0 += kClose) {
    const int nl = int(std::min<int64_t>(kClose, n1 - m0));
    for (int l = 0; l < kClose; ++l) {
      const int64_t n = m0 + (l < nl ? l : 0);  // the lanes past the end repeat the first
      const int64_t* s = ps + 4 * n;
      for (int v = 0; v < 4; ++v)
        for (int i = 0; i < 3; ++i) X[3 * v + i][l] = px[3 * s[v] + i];
      signed char c[3][4];
      cm::type_rows(int(pt[n]), &form[l], c);
      for (int r = 0; r < 3; ++r)
        for (int v = 0; v < 4; ++v) C[r][v][l] = T(c[r][v]);
      M[l] = pe ? pe[n] : T(0);
    }
    energy_lanes<T>(X, C, form, D, M);
    for (int l = 0; l < nl; ++l) {
      T b1, b2;
      const T d = D[l];
      pE[m0 + l] = d > 0 ? M[l] * cm::barrier(d, dh2, kappa, &b1, &b2) : T(1) / T(0);
    }
  }
}

}  // namespace
}  // namespace cpu
}  // namespace torchbend
