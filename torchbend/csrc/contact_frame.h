// The contact pairs' Hessians in their normal frame: where their nonzero eigenvalues live, so that the PSD
// projection is a 4x4 (point-line) or 5x5 (point-plane, line-line) eigenproblem instead of 6x6 or 9x9.
//
// The barrier of a pair is psi(d) of its distance d, so H = psi'' u u^T + psi' Hess(d) with u = grad d.  In the frame
// of the unit normal z (from the line or plane to the point, or between the lines), u = w (x) z for weights w over
// the corners (sum w = 0), and d's Hessian has three kinds of blocks: corner moves along z against each other (the
// plane's or line's tilt, the normal's turn), along z against moves in the plane z-perp (which change where the
// nearest point sits: only through w (x) z-perp), and in the plane against each other (zero: the stencil then stays in
// its parallel planes and d does not change).  So H is zero outside Z + P, where
//     Z = {c (x) z : c in the span of the pattern's rows}    (r dimensions: the normal moves)
//     P = {w (x) p : p perpendicular to z}                    (2 dimensions)
// and its projection is B proj(B^T H B) B^T over an orthonormal basis B of Z + P (m = r + 2 columns).  A mollified
// edge-edge pair (its energy depends on the edges' cross product too) and a point-point pair (r = 1: m = 3 = k)
// keep the full eigenproblem.
//
// In reduced coordinates (contact_math.h: y = L x, L = C (x) I3, R R^T = C C^T): column j of B is C^T Ri^T e_j (x) z
// for j < r, and C^T om (x) p / |w| for the two p, where om (r) holds u's reduced weights (w = C^T om, |w|^2 =
// om^T C C^T om).  B^T H B = Lb^T H_y Lb with Lb = L B (columns R e_j (x) z and C C^T om (x) p / |w|), and the
// projected Hessian in reduced coordinates is U S U^T with U^T L = B^T (columns Ri^T e_j (x) z, om (x) p / |w|).
#pragma once

#include "contact_math.h"

namespace torchbend {
namespace contact {

// the frame of a pair with r = 2 or 3 rows, unmollified, from its barrier gradient g (3 r, reduced coordinates; a
// multiple of u's): Lb and U (k x m, row-major, k = 3 r, m = r + 2).  False where g's first block is zero or not
// finite (d = 0, or a pair beyond dhat: its Hessian is zero and the full eigenproblem handles it).
// the largest magnitude of g's first block (the frame scales g by it: |g_0|^2 of a pair near dhat underflows in
// float32 where g_0 itself does not)
template <typename T> TB_HD static inline T frame_scale(const T* g) {
  const T a = fabs(g[0]), b = fabs(g[1]), c = fabs(g[2]);
  return a > b ? (a > c ? a : c) : (b > c ? b : c);
}

template <typename T> TB_HD static inline bool frame_ok(const T* g) {
  const T m = frame_scale(g);
  return m > 0 && m < T(1) / T(0);
}

template <typename T> TB_HD static inline bool pair_frame(const signed char C[3][4], int r, const T* g, T* Lb, T* U) {
  if (!frame_ok(g)) return false;
  const T s = T(1) / frame_scale(g);
  T gs[9];
  for (int i = 0; i < 3 * r; ++i) gs[i] = g[i] * s;
  const T g0 = sqrt(dot3p(gs, gs));
  T z[3] = {gs[0] / g0, gs[1] / g0, gs[2] / g0};
  T om[3] = {1, 0, 0};  // u's reduced weights, up to a common factor: g_i . z / |g_0|
  for (int i = 1; i < r; ++i) om[i] = dot3p(gs + 3 * i, z) / g0;
  // an orthonormal basis (p, q) of z-perp (Duff et al. 2017: no division by a small number)
  const T sg = z[2] >= 0 ? T(1) : T(-1), a = T(-1) / (sg + z[2]), b = z[0] * z[1] * a;
  const T p[3] = {1 + sg * z[0] * z[0] * a, sg * b, -sg * z[0]}, q[3] = {b, sg + z[1] * z[1] * a, -z[1]};
  // G = C C^T, its Cholesky factor R and R's inverse; G om and |w|
  T R[3][3], Ri[3][3], Gom[3] = {0, 0, 0}, w2 = 0;
  gram_cholesky(C, r, R, Ri);
  for (int i = 0; i < r; ++i) {
    for (int j = 0; j < r; ++j) {
      int s = 0;
      for (int v = 0; v < 4; ++v) s += C[i][v] * C[j][v];
      Gom[i] += T(s) * om[j];
    }
    w2 += om[i] * Gom[i];
  }
  const T iw = T(1) / sqrt(w2);
  const int m = r + 2;
  for (int i = 0; i < r; ++i)
    for (int c = 0; c < 3; ++c) {
      T* lb = Lb + m * (3 * i + c);
      T* u = U + m * (3 * i + c);
      for (int j = 0; j < r; ++j) { lb[j] = R[i][j] * z[c]; u[j] = Ri[j][i] * z[c]; }
      lb[r] = Gom[i] * iw * p[c]; lb[r + 1] = Gom[i] * iw * q[c];
      u[r] = om[i] * iw * p[c]; u[r + 1] = om[i] * iw * q[c];
    }
  return true;
}

}  // namespace contact
}  // namespace torchbend
