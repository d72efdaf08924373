// The second-order products: the Hessian-vector product (bending_hvp) and the general double backward
// (bending_second_order).
#include "cpu_ops.h"
#include "cpu_scatter.h"

namespace torchbend {
namespace cpu {
std::tuple<torch::Tensor, torch::Tensor, int64_t> bending_hvp(torch::Tensor x, torch::Tensor v, torch::Tensor hinges,
                                                              torch::Tensor a, torch::Tensor k, torch::Tensor rest,
                                                              c10::optional<torch::Tensor> c,
                                                              c10::optional<torch::Tensor> prev, int64_t model,
                                                              torch::Tensor weight, torch::Tensor inc_ptr,
                                                              torch::Tensor inc_idx, bool check) {
  const char* op = "bending_hvp";
  Prepared P = prepare(op, x, hinges, a, k, rest, c, prev, model, false);
  check_direction(op, v, P);
  v = v.contiguous();
  weight = prepare_weight(op, weight, P);
  torchbend::checks::check_incidence(op, inc_ptr, inc_idx, P.V, P.H);
  auto hv = torch::empty(shape_with(P.batch, {P.V, 3}), P.x.options());
  auto theta = torch::empty(shape_with(P.batch, {P.H}), P.x.options());
  if (check) {
    int64_t bad = finite_status(P.x, kBadX) | finite_status(v, kBadV);
    if (bad) return {hv, theta, bad};
  }
  AT_DISPATCH_FLOATING_TYPES(P.x.scalar_type(), "bending_hvp", [&] {
    using T = scalar_t;
    HingeArgs<T> args = hinge_args<T>(P.a, P.k, P.rest, P.c, P.prev, P.damped, int(model), P.H);
    Param<T> w{weight.data_ptr<T>(), weight.numel(), P.H};
    const T* xp = P.x.data_ptr<T>(); const T* vp = v.data_ptr<T>();
    const int64_t* hp = P.hinges.data_ptr<int64_t>();
    T* to = theta.data_ptr<T>();
    int64_t V = P.V;
    with_model(int(model), P.damped, [&](auto M_, auto D_) {
      constexpr int M = decltype(M_)::value;
      constexpr bool D = decltype(D_)::value;
      scatter_tiles<T, WL>(op, P.hinges, P.B, V, inc_ptr.data_ptr<int64_t>(), inc_idx.data_ptr<int64_t>(), hv.data_ptr<T>(),
                       [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs, T (*O)[WL]) {
        alignas(64) T X[12][WL], Vd[12][WL], G[12][WL];
        alignas(64) T TH[WL], D1[WL], D2[WL], U[WL];
        HingeTile<T, WL> Q;
        Half<T, WL> hA, hB;
        gather_tile<T, false, WL>(xp, vp, hp, V, args, &w, nl, bs, hs, X, Vd, Q);
        theta_tile<T, WL>(X, TH);
        halves_tile<T, WL>(X, hA, hB);  // before psi, as in gradient_pass
        TB_LANES_AGG(WL) {
          T psi, d1, d2;
          psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], psi, d1, d2, static_cast<T*>(nullptr));
          D1[l] = Q.w[l] * d1; D2[l] = Q.w[l] * d2;
        }
        grad_of_halves<T, WL>(hA, hB, G);
        dot_tile<T, WL>(G, Vd, U);
        TB_LANES(WL) U[l] *= D2[l];
        hvp_of_halves<T, WL>(hA, hB, Vd, G, D1, U, true, O);
        store_lanes<T, WL>(TH, nl, to + bh0);
      });
    });
  });
  return {hv, theta, fold_status(theta, model)};
}

// The general double backward (torchbend.energies._bending_fn._second_order without a tangent of the
// cotangent): with directions v (..., V, 3) in x (or None) and t (..., H, 4) or (H, 4) in the per-hinge
// (k, rest, c, prev) (or None), per hinge u = g . v and z = Hess_p(psi) (u, t):
// (dx = sum_h w (z_theta g + psi' H_theta v) (..., V, 3), dp = w z_(k, rest, c, prev) (..., H, 4),
//  dg = grad_p(psi) . (u, t) (..., H), theta (..., H)); w the per-hinge weight (the cotangent gE).
// Without damping the c and prev entries of dp are 0 and those of t are ignored.  Last: the status word
// (fold check only: the inputs come from a backward pass).
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor, int64_t> bending_second_order(
    torch::Tensor x, c10::optional<torch::Tensor> v_, c10::optional<torch::Tensor> t_, torch::Tensor hinges,
    torch::Tensor a, torch::Tensor k, torch::Tensor rest, c10::optional<torch::Tensor> c,
    c10::optional<torch::Tensor> prev, int64_t model, torch::Tensor weight, torch::Tensor inc_ptr,
    torch::Tensor inc_idx) {
  const char* op = "bending_second_order";
  namespace ck = torchbend::checks;
  Prepared P = prepare(op, x, hinges, a, k, rest, c, prev, model, false);
  torch::Tensor v, tt;
  if (v_.has_value()) {
    check_direction(op, *v_, P);
    v = v_->contiguous();
  }
  if (t_.has_value()) {
    ck::require(t_->device().is_cpu() && t_->is_floating_point() && t_->dim() >= 2 && t_->size(-1) == 4 &&
                    t_->size(-2) == P.H && (t_->numel() == 4 * P.H || t_->numel() == 4 * P.B * P.H),
                op, "t must be a floating-point CPU (H, 4) or (..., H, 4) tensor of x's batch, H = ", P.H, ", got ",
                ck::shape_str(*t_));
    tt = as_dtype(*t_, P.x.scalar_type());
  }
  weight = prepare_weight(op, weight, P);
  ck::check_incidence(op, inc_ptr, inc_idx, P.V, P.H);
  auto dx = torch::empty(shape_with(P.batch, {P.V, 3}), P.x.options());
  auto dp = torch::empty(shape_with(P.batch, {P.H, 4}), P.x.options());
  auto dg = torch::empty(shape_with(P.batch, {P.H}), P.x.options()), theta = torch::empty_like(dg);
  AT_DISPATCH_FLOATING_TYPES(P.x.scalar_type(), "bending_second_order", [&] {
    using T = scalar_t;
    HingeArgs<T> args = hinge_args<T>(P.a, P.k, P.rest, P.c, P.prev, P.damped, int(model), P.H);
    Param<T> w{weight.data_ptr<T>(), weight.numel(), P.H};
    const T* xp = P.x.data_ptr<T>();
    const T* vp = v.defined() ? v.data_ptr<T>() : nullptr;
    const T* tp = tt.defined() ? tt.data_ptr<T>() : nullptr;
    bool t_batched = tt.defined() && tt.numel() != 4 * P.H;
    const int64_t* hp = P.hinges.data_ptr<int64_t>();
    T* dpp = dp.data_ptr<T>(); T* dgp = dg.data_ptr<T>(); T* to = theta.data_ptr<T>();
    int64_t V = P.V, H = P.H;
    with_model(int(model), P.damped, [&](auto M_, auto D_) {
      constexpr int M = decltype(M_)::value;
      constexpr bool D = decltype(D_)::value;
      scatter_tiles<T, WL>(op, P.hinges, P.B, V, inc_ptr.data_ptr<int64_t>(), inc_idx.data_ptr<int64_t>(), dx.data_ptr<T>(),
                       [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs, T (*O)[WL]) {
        alignas(64) T X[12][WL], Vd[12][WL], G[12][WL];
        alignas(64) T TH[WL], U[WL], TG[4][WL], S1[WL], S2[WL], Z[4][WL], DG[WL];
        HingeTile<T, WL> Q;
        Half<T, WL> hA, hB;
        gather_tile<T, false, WL>(xp, vp, hp, V, args, &w, nl, bs, hs, X, Vd, Q);
        for (int l = 0; l < WL; ++l) {
          const T* src = (tp && l < nl) ? tp + 4 * (t_batched ? bs[l] * H + hs[l] : hs[l]) : nullptr;
          for (int j = 0; j < 4; ++j) TG[j][l] = src ? src[j] : T(0);
        }
        theta_tile<T, WL>(X, TH);
        halves_tile<T, WL>(X, hA, hB);
        grad_of_halves<T, WL>(hA, hB, G);
        if (vp) dot_tile<T, WL>(G, Vd, U); else TB_LANES(WL) U[l] = T(0);
        TB_LANES_AGG(WL) {
          T d1, zt, z4[4], dgl;
          psi_second_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], U[l], TG[0][l], TG[1][l],
                                TG[2][l], TG[3][l], d1, zt, z4, dgl);
          T wl = Q.w[l];
          S1[l] = wl * d1; S2[l] = wl * zt;
          Z[0][l] = wl * z4[0]; Z[1][l] = wl * z4[1]; Z[2][l] = wl * z4[2]; Z[3][l] = wl * z4[3];
          DG[l] = dgl;
        }
        hvp_of_halves<T, WL>(hA, hB, Vd, G, S1, S2, vp != nullptr, O);
        for (int l = 0; l < nl; ++l) {
          for (int j = 0; j < 4; ++j) dpp[4 * (bh0 + l) + j] = Z[j][l];
          dgp[bh0 + l] = DG[l];
          to[bh0 + l] = TH[l];
        }
      });
    });
  });
  return {dx, dp, dg, theta, fold_status(theta, model)};
}


}  // namespace cpu
}  // namespace torchbend
