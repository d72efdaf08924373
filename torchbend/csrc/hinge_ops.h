// Per-hinge bodies of the compiled energy, gradient, Hessian-vector and second-order operations, shared
// by the CPU driver (cpu_*.cpp, tiles of W = 16 or 8 lanes) and the CUDA driver (bending_cuda.cu, W = 1:
// one hinge per thread).  Everything here is built from hinge_math.h and mirrors the eager reference
// (torchbend.ops.hinge and torchbend.ops.psi), against which the tests compare every operation.
//
// A tile goes through the same steps in every operation: the driver gathers the stencils X (and
// directions Vd) and the per-lane parameters (HingeTile), theta_tile takes the bend angles, psi_lane /
// psi_second_lane the scalars of psi (templated on the model M and on damping D, so that each lane loop
// is one branch-free body that vectorizes), halves_tile the half-hinge quantities, and grad_of_halves /
// hvp_of_halves the angle gradient and H_theta v in closed form (no 12x12 matrix).
#pragma once

#include "hinge_math.h"

namespace torchbend {

// phi'(t) of the bending model (the parameter derivatives need it at the reference angles)
template <typename T> TB_HD static inline T phi_prime(int model, T t) {
  T p1, p2;
  if (model == 0) phi_ref<0>(t, p1, p2);
  else if (model == 1) phi_ref<1>(t, p1, p2);
  else phi_ref<2>(t, p1, p2);
  return p1;
}

// bend angle of lane l of the stencils X: theta = atan2(e_hat . (nA x nB), nA . nB) (the SPEC formula, scaled:
// stencil_theta)
template <typename T, int W> TB_HD static TB_FORCEINLINE T hinge_theta(const T (*X)[W], int l) {
  return stencil_theta<T, W>(X, l);
}

// the bend angles of the W lanes of a tile, in three lane loops (atan2's arguments, its reduction, its polynomial;
// the same operations as hinge_theta).  The whole angle in one loop was 223 instructions a 4-lane iteration in GCC
// 12's x86-64-v3 code, on a chain of dependent operations (cross products, square root, division, polynomial)
// estimated at over 100 cycles from their latencies: the out-of-order window could not hold much more than one
// iteration's chain, and a loop of each stage holds several.  Measured on a Zen 4 EPYC (1e5 hinges, float64, one
// thread, min over calls): energy 20.1 -> 17.3 ns a hinge with x86-64-v3 (AVX2, 4 lanes a vector), 15.1 -> 13.7
// with AVX-512 (benchmarks/results/amd_zen4_2026-12-06.txt, section 9).
template <typename T, int W> TB_HD static inline void theta_tile(const T (*X)[W], T* theta) {
  using C = typename ThetaType<T>::type;
  C Y[W], Xa[W];
  double At[W], Al[W], Sg[W], Kh[W], Kl[W];  // the reduction's parts are double whatever C is (tb_atan2v_reduce)
  TB_LANES_AGG(W) stencil_theta_args<T, W>(X, l, Y[l], Xa[l]);
  TB_LANES_AGG(W) tb_atan2v_reduce(Y[l], Xa[l], At[l], Al[l], Sg[l], Kh[l], Kl[l]);
  TB_LANES_AGG(W) theta[l] = T(tb_atan2v_finish(Y[l], Xa[l], At[l], Al[l], Sg[l], Kh[l], Kl[l]));
}

// The per-hinge parameters of one evaluation (a per-hinge parameter is a scalar, (H,) or (B, H)).
template <typename T> struct HingeArgs {
  Param<T> a, k, rest, c, prev;
  bool damped;
  int model;
};

// The parameters of the W lanes of a tile, gathered once per tile (lanes past the end: zeros)
template <typename T, int W> struct HingeTile { T a[W], k[W], rest[W], c[W], prev[W], w[W]; };

template <typename T, int W>
TB_HD static inline void load_params(const HingeArgs<T>& p, int64_t b, int64_t h, int l, HingeTile<T, W>& o) {
  o.a[l] = p.a(b, h); o.k[l] = p.k(b, h); o.rest[l] = p.rest(b, h);
  o.c[l] = p.damped ? p.c(b, h) : T(0);
  o.prev[l] = p.damped ? p.prev(b, h) : T(0);
}

template <typename T, int W> TB_HD static inline void zero_params(int l, HingeTile<T, W>& o) {
  o.a[l] = o.k[l] = o.rest[l] = o.c[l] = o.prev[l] = o.w[l] = T(0);
}

// psi, psi' = d psi / d theta, psi'' and (gp not null) the parameter gradients
// gp = (d psi/dk, d psi/drest, d psi/dc, d psi/dprev) of one hinge at theta: torchbend.ops.psi.psi_derivatives,
// each term on the branch of its reference angle, the viscous term only if damped (D)
template <int M, bool D, typename T>
TB_HD static TB_FORCEINLINE void psi_lane(T theta, T a, T k, T rest, T c, T prev, T& psi, T& d1, T& d2, T* gp) {
  T dr, f1, f2;
  phi_diff<M>(theta, rest, dr, f1, f2);
  T kd = k * dr, two_a = T(2) * a;
  T p = a * kd * dr, s = kd * f1, h2 = k * f1 * f1 + kd * f2;
  if (gp) {
    T r1, r2;
    phi_ref<M>(rest, r1, r2);
    gp[0] = a * dr * dr; gp[1] = -two_a * kd * r1; gp[2] = T(0); gp[3] = T(0);
  }
  if (D) {
    T dp, g1, g2;
    phi_diff<M>(theta, prev, dp, g1, g2);
    T cd = c * dp;
    p = p + a * cd * dp;
    s = kd * f1 + cd * g1;
    h2 += c * g1 * g1 + cd * g2;
    if (gp) {
      T p1, p2;
      phi_ref<M>(prev, p1, p2);
      gp[2] = a * dp * dp; gp[3] = T(-2) * a * cd * p1;
    }
  }
  psi = p;
  d1 = two_a * s;
  d2 = two_a * h2;
}

// The second-order scalars of one hinge (torchbend.energies._bending_fn._second_order): with
// p = (theta, k, rest, c, prev) and the direction q = (u, tk, tr, tc, tp) (u = g . v), d1 = psi',
// z = Hess_p(psi) q (zt its theta entry, z4 the (k, rest, c, prev) entries; c and prev 0 if not damped)
// and dg = grad_p(psi) . q
template <int M, bool D, typename T>
TB_HD static TB_FORCEINLINE void psi_second_lane(T theta, T a, T k, T rest, T c, T prev, T u, T tk, T tr, T tc, T tp,
                                                 T& d1, T& zt, T* z4, T& dg) {
  T dr, f1, f2, r1, r2;
  phi_diff<M>(theta, rest, dr, f1, f2);
  phi_ref<M>(rest, r1, r2);
  T two_a = T(2) * a, kd = k * dr;
  // gradient (theta, k, rest) and Hessian entries (torchbend.ops.psi.psi_derivatives)
  T gk = a * dr * dr, gr = -two_a * kd * r1;
  T htt = k * f1 * f1 + kd * f2, s = kd * f1;  // (times 2a)
  T htk = two_a * dr * f1, htr = -two_a * k * f1 * r1, hkr = -two_a * dr * r1;
  T hrr = two_a * k * (r1 * r1 - dr * r2);
  T zT = htk * tk + htr * tr;
  T zk = htk * u + hkr * tr, zr = htr * u + hkr * tk + hrr * tr, zc = T(0), zp = T(0);
  T dgp = gk * tk + gr * tr;
  if (D) {
    T dp, g1, g2, p1, p2;
    phi_diff<M>(theta, prev, dp, g1, g2);
    phi_ref<M>(prev, p1, p2);
    T cd = c * dp;
    T gc = a * dp * dp, gpv = T(-2) * a * cd * p1;
    s = s + cd * g1;
    htt += c * g1 * g1 + cd * g2;
    T htc = two_a * dp * g1, htp = -two_a * c * g1 * p1, hcp = -two_a * dp * p1;
    T hpp = two_a * c * (p1 * p1 - dp * p2);
    zT += htc * tc + htp * tp;
    zc = htc * u + hcp * tp;
    zp = htp * u + hcp * tc + hpp * tp;
    dgp += gc * tc + gpv * tp;
  }
  d1 = two_a * s;
  zt = two_a * htt * u + zT;
  z4[0] = zk; z4[1] = zr; z4[2] = zc; z4[3] = zp;
  dg = d1 * u + dgp;
}

// psi, psi' and (when gp is not null) the parameter gradients of one hinge at theta, for a runtime
// model (the CUDA driver; the CPU driver calls psi_lane with the model as a template argument)
template <typename T>
TB_HD static inline void psi_first(const HingeArgs<T>& p, int64_t b, int64_t h, T theta, T& psi, T& d1, T* gp) {
  T a = p.a(b, h), k = p.k(b, h), rest = p.rest(b, h);
  T c = p.damped ? p.c(b, h) : T(0), prev = p.damped ? p.prev(b, h) : T(0), d2, g4[4];
  T* g = gp ? g4 : nullptr;
  switch (p.model * 2 + (p.damped ? 1 : 0)) {
    case 0: psi_lane<0, false>(theta, a, k, rest, c, prev, psi, d1, d2, g); break;
    case 1: psi_lane<0, true>(theta, a, k, rest, c, prev, psi, d1, d2, g); break;
    case 2: psi_lane<1, false>(theta, a, k, rest, c, prev, psi, d1, d2, g); break;
    case 3: psi_lane<1, true>(theta, a, k, rest, c, prev, psi, d1, d2, g); break;
    case 4: psi_lane<2, false>(theta, a, k, rest, c, prev, psi, d1, d2, g); break;
    default: psi_lane<2, true>(theta, a, k, rest, c, prev, psi, d1, d2, g); break;
  }
  if (gp) {
    gp[0] = g4[0]; gp[1] = g4[1];
    if (p.damped) { gp[2] = g4[2]; gp[3] = g4[3]; }
  }
}

// psi_second_lane for a runtime model and damping (the CUDA driver): d1 = psi', zt, z4 = Hess_p(psi) q, dg
template <typename T>
TB_HD static inline void psi_second(const HingeArgs<T>& p, int64_t b, int64_t h, T theta, T u, const T* t4, T& d1,
                                    T& zt, T* z4, T& dg) {
  T a = p.a(b, h), k = p.k(b, h), rest = p.rest(b, h);
  T c = p.damped ? p.c(b, h) : T(0), prev = p.damped ? p.prev(b, h) : T(0);
  switch (p.model * 2 + (p.damped ? 1 : 0)) {
    case 0: psi_second_lane<0, false>(theta, a, k, rest, c, prev, u, t4[0], t4[1], t4[2], t4[3], d1, zt, z4, dg); break;
    case 1: psi_second_lane<0, true>(theta, a, k, rest, c, prev, u, t4[0], t4[1], t4[2], t4[3], d1, zt, z4, dg); break;
    case 2: psi_second_lane<1, false>(theta, a, k, rest, c, prev, u, t4[0], t4[1], t4[2], t4[3], d1, zt, z4, dg); break;
    case 3: psi_second_lane<1, true>(theta, a, k, rest, c, prev, u, t4[0], t4[1], t4[2], t4[3], d1, zt, z4, dg); break;
    case 4: psi_second_lane<2, false>(theta, a, k, rest, c, prev, u, t4[0], t4[1], t4[2], t4[3], d1, zt, z4, dg); break;
    default: psi_second_lane<2, true>(theta, a, k, rest, c, prev, u, t4[0], t4[1], t4[2], t4[3], d1, zt, z4, dg); break;
  }
}

// ---- closed-form H_theta v of a tile (torchbend.ops.hinge; the angle gradients: grad_of_halves, hinge_math.h) -

// T'' v of one half-hinge (a, b, c) in lane l (torchbend.ops.hinge._HalfHinge.hvp):
// (H v)_k = t_k mu + (mh_k . nu) N + [B terms],  mu = sum_k mh_k (N . v_k),  nu = sum_k t_k v_k,
// B = bl mh_c^T entering as [[-B, B], [B^T, -B]] on the (a, b) blocks
template <typename T, int W>
TB_HD static TB_FORCEINLINE void half_hvp(const Half<T, W>& h, int l, V3<T> va, V3<T> vb, V3<T> vc, V3<T>& oa,
                                          V3<T>& ob, V3<T>& oc) {
  V3<T> N{h.N[0][l], h.N[1][l], h.N[2][l]};
  V3<T> ma{h.mh[0][0][l], h.mh[0][1][l], h.mh[0][2][l]}, mb{h.mh[1][0][l], h.mh[1][1][l], h.mh[1][2][l]};
  V3<T> mc{h.mh[2][0][l], h.mh[2][1][l], h.mh[2][2][l]}, bl{h.bl[0][l], h.bl[1][l], h.bl[2][l]};
  T ta = h.t[0][l], tb = h.t[1][l], tc = h.t[2][l];
  T wa = dot3(N, va), wb = dot3(N, vb), wc = dot3(N, vc);
  V3<T> mu{ma.x * wa + mb.x * wb + mc.x * wc, ma.y * wa + mb.y * wb + mc.y * wc, ma.z * wa + mb.z * wb + mc.z * wc};
  V3<T> nu{va.x * ta + vb.x * tb + vc.x * tc, va.y * ta + vb.y * tb + vc.y * tc, va.z * ta + vb.z * tb + vc.z * tc};
  T bd = dot3(mc, sub3(vb, va)), sa = dot3(ma, nu), sb = dot3(mb, nu), sc = dot3(mc, nu);
  T bla = dot3(bl, va), mcb = dot3(mc, vb);
  oa = V3<T>{sa * N.x + (bd * bl.x + mu.x * ta), sa * N.y + (bd * bl.y + mu.y * ta), sa * N.z + (bd * bl.z + mu.z * ta)};
  ob = V3<T>{bla * mc.x + (sb * N.x + (-mcb * bl.x + mu.x * tb)), bla * mc.y + (sb * N.y + (-mcb * bl.y + mu.y * tb)),
             bla * mc.z + (sb * N.z + (-mcb * bl.z + mu.z * tb))};
  oc = V3<T>{sc * N.x + mu.x * tc, sc * N.y + mu.y * tc, sc * N.z + mu.z * tc};
}

// out = s1 H_theta v + s2 g for W stencils (directions Vd, angle gradients G; [3 * vertex + axis][lane]);
// with_v false: no direction (out = s2 g)
template <typename T, int W>
TB_HD static inline void hvp_of_halves(const Half<T, W>& hA, const Half<T, W>& hB, const T (*Vd)[W], const T (*G)[W],
                                       const T* s1, const T* s2, bool with_v, T (*out)[W]) {
  if (!with_v) {
    for (int m = 0; m < 12; ++m) TB_LANES(W) out[m][l] = s2[l] * G[m][l];
    return;
  }
  TB_LANES_AGG(W) {
    V3<T> v0{Vd[0][l], Vd[1][l], Vd[2][l]}, v1{Vd[3][l], Vd[4][l], Vd[5][l]};
    V3<T> v2{Vd[6][l], Vd[7][l], Vd[8][l]}, v3{Vd[9][l], Vd[10][l], Vd[11][l]};
    V3<T> a0, a1, a2, b0, b1, b3;
    half_hvp<T, W>(hA, l, v0, v1, v2, a0, a1, a2);
    half_hvp<T, W>(hB, l, v0, v1, v3, b0, b1, b3);
    T p = s1[l], q = s2[l];
    // H_theta v = (a0 - b0, a1 - b1, a2, -b3)
    out[0][l] = p * (a0.x - b0.x) + q * G[0][l];
    out[1][l] = p * (a0.y - b0.y) + q * G[1][l];
    out[2][l] = p * (a0.z - b0.z) + q * G[2][l];
    out[3][l] = p * (a1.x - b1.x) + q * G[3][l];
    out[4][l] = p * (a1.y - b1.y) + q * G[4][l];
    out[5][l] = p * (a1.z - b1.z) + q * G[5][l];
    out[6][l] = p * a2.x + q * G[6][l];
    out[7][l] = p * a2.y + q * G[7][l];
    out[8][l] = p * a2.z + q * G[8][l];
    out[9][l] = -p * b3.x + q * G[9][l];
    out[10][l] = -p * b3.y + q * G[10][l];
    out[11][l] = -p * b3.z + q * G[11][l];
  }
}

// g . v per lane.  The sum is a register of the lane loop: accumulated in u[] over an outer loop on m, GCC's
// x86-64-v3 code (16 lanes = 4 AVX2 vectors, the m loop not unrolled) carried it through memory, twelve
// dependent store-load round trips a tile (about 3 ns a hinge on a Zen 4 EPYC, 1 with AVX-512 registers)
template <typename T, int W> TB_HD static inline void dot_tile(const T (*G)[W], const T (*Vd)[W], T* u) {
  TB_LANES(W) {
    T s = T(0);
    for (int m = 0; m < 12; ++m) s += G[m][l] * Vd[m][l];
    u[l] = s;
  }
}

// H_h v for the W stencils X and directions Vd (both [3 * vertex + axis][lane]) through the 12x12 block of
// block_tile (kept for reference and the block tests; the kernels use hvp_of_halves); d1, d2 = psi', psi''.
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
