// Per-triangle mathematics of torchbend's compiled membrane kernels: the StVK element Hessian in closed form.
// It mirrors the eager reference torchbend.ops.membrane.stvk_blocks, which the tests compare against; the same
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
  // the upper triangle, mirrored: exactly symmetric blocks (A symmetrized the same way)
  for (int r = 0; r < 9; ++r)
    for (int c = r; c < 9; ++c) {
      const int k = r / 3, i = r % 3, l = c / 3, j = c % 3;
      const T a = k <= l ? A[k][l] : A[l][k];
      const T h = B[k][l] * FF[i][j] + cm * (t[k][j] * t[l][i]) + cl * (t[k][i] * t[l][j]) + (i == j ? a : T(0));
      H[9 * r + c] = h;
      H[9 * c + r] = h;
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

}  // namespace torchbend
