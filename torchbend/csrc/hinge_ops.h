// Per-hinge bodies of the compiled energy, gradient and Hessian-vector operations, shared by the CPU
// driver (bending_cpu.cpp, tiles of W = 8 lanes) and the CUDA driver (bending_cuda.cu, W = 1: one hinge
// per thread).  Everything here is built from hinge_math.h and mirrors the eager reference
// (torchbend.ops.hinge and torchbend.ops.psi), against which the tests compare every operation.
#pragma once

#include "hinge_math.h"

namespace torchbend {

// phi'(t) of the bending model (the parameter derivatives need it at the reference angles)
template <typename T> TB_HD static inline T phi_prime(int model, T t) {
  if (model == 0) return T(1);
  if (model == 1) { T u = tb_tan(T(0.5) * t); return T(1) + u * u; }
  return tb_cos(T(0.5) * t);
}

// bend angle of lane l of the stencils X: theta = atan2(e_hat . (nA x nB), nA . nB) (the SPEC formula)
template <typename T, int W> TB_HD static inline T hinge_theta(const T (*X)[W], int l) {
  T e[3], u[3], w[3];
  for (int m = 0; m < 3; ++m) {
    e[m] = X[3 + m][l] - X[m][l]; u[m] = X[6 + m][l] - X[m][l]; w[m] = X[9 + m][l] - X[m][l];
  }
  T NA[3], NB[3], NN[3];
  cross(e, u, NA); cross(w, e, NB); cross(NA, NB, NN);
  T elen = tb_sqrt(dot(e, e));
  T inv = elen > T(0) ? T(1) / elen : T(0);
  return tb_atan2(dot(e, NN) * inv, dot(NA, NB));
}

// The per-hinge parameters of one evaluation (a per-hinge parameter is a scalar, (H,) or (B, H)).
template <typename T> struct HingeArgs {
  Param<T> a, k, rest, c, prev;
  bool damped;
  int model;
};

// psi, psi' = d psi / d theta and (when gp is not null) the parameter gradients
// gp = (d psi/dk, d psi/drest, d psi/dc, d psi/dprev) of one hinge at theta
// (torchbend.ops.psi.psi_derivatives with hessian=False; each term on the branch of its reference)
template <typename T>
TB_HD static inline void psi_first(const HingeArgs<T>& p, int64_t b, int64_t h, T theta, T& psi, T& d1, T* gp) {
  T a = p.a(b, h), k = p.k(b, h), rest = p.rest(b, h);
  T dr, f1, f2;
  phi_difference(p.model, theta, rest, dr, f1, f2);
  T kd = k * dr, two_a = T(2) * a;
  psi = a * kd * dr;
  T s = kd * f1;
  if (gp) { gp[0] = a * dr * dr; gp[1] = -two_a * kd * phi_prime(p.model, rest); }
  if (p.damped) {
    T c = p.c(b, h), prev = p.prev(b, h);
    T dp, g1, g2;
    phi_difference(p.model, theta, prev, dp, g1, g2);
    T cd = c * dp;
    psi = psi + a * cd * dp;
    s = kd * f1 + cd * g1;
    if (gp) { gp[2] = a * dp * dp; gp[3] = T(-2) * a * cd * phi_prime(p.model, prev); }
  }
  d1 = two_a * s;
}

// H_h v for the W stencils X and directions Vd (both [3 * vertex + axis][lane]): the 12x12 block of
// block_tile applied to v without storing it; d1, d2 = psi', psi'' per lane.
template <typename T, int W>
TB_HD static inline void hvp_tile(const T (*X)[W], const T (*Vd)[W], const T* d1, const T* d2, Blocks<T, W>& b,
                                  T (*out)[W]) {
  block_tile<T, W>(X, d1, d2, b);
  // upper triangle O (r <= c) mirrored, then the B terms of the (x0, x1) blocks (as block_lane)
  for (int r = 0; r < 12; ++r) TB_LANES(W) out[r][l] = T(0);
  for (int r = 0; r < 12; ++r) {
    TB_LANES(W) out[r][l] += b.O[12 * r + r][l] * Vd[r][l];
    for (int c = r + 1; c < 12; ++c) TB_LANES(W) {
      T o = b.O[12 * r + c][l];
      out[r][l] += o * Vd[c][l];
      out[c][l] += o * Vd[r][l];
    }
  }
  for (int p = 0; p < 3; ++p)
    for (int q = 0; q < 3; ++q) TB_LANES(W) {
      T B = b.Bm[p][q][l];
      // o[p][q] -= B, o[p][3+q] += B, o[3+q][p] += B, o[3+p][3+q] -= B
      out[p][l] += B * (Vd[3 + q][l] - Vd[q][l]);
      out[3 + q][l] += B * Vd[p][l];
      out[3 + p][l] -= B * Vd[3 + q][l];
    }
}

}  // namespace torchbend
