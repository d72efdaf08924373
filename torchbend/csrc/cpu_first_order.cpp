// The first-order operators: per-hinge energies (bending_energy) and the gradient pass (bending_gradient,
// bending_energy_gradient).
#include <atomic>

#include "cpu_ops.h"
#include "cpu_scatter.h"

namespace torchbend {
namespace cpu {
// ----------------------------------------------------------------------------------------------
// Energy, gradient, Hessian-vector product and the general second-order product (the hot paths of
// training and of matrix-free solvers).  Each is one parallel pass over tiles of WL hinges (gather, angle,
// psi, closed forms; every lane loop branch-free and vectorized, the model and damping template
// arguments); the gradient and the products sum their per-hinge 12-vectors per vertex in blocks of
// consecutive hinges (scatter_tiles: bit-identical for any number of threads, no two threads writing one
// value), or, for hinges in no compact order, through a per-hinge buffer and the incidence lists (inc_ptr
// (V+1), inc_idx (4H): entries 4 h + slot, sorted by vertex).


std::tuple<torch::Tensor, torch::Tensor, int64_t> bending_energy(torch::Tensor x, torch::Tensor hinges,
                                                                 torch::Tensor a, torch::Tensor k, torch::Tensor rest,
                                                                 c10::optional<torch::Tensor> c,
                                                                 c10::optional<torch::Tensor> prev, int64_t model,
                                                                 bool check) {
  Prepared P = prepare("bending_energy", x, hinges, a, k, rest, c, prev, model, false);
  auto psi = torch::empty(shape_with(P.batch, {P.H}), P.x.options()), theta = torch::empty_like(psi);
  if (check && finite_status(P.x, kBadX)) return {psi, theta, kBadX};
  std::atomic<bool> bad_index{false};  // an index outside [0, V) met in the gather (which then reads nothing)
  if (P.B == 0) check_hinge_range("bending_energy", P.hinges, P.V);  // no gather to check them in
  AT_DISPATCH_FLOATING_TYPES(P.x.scalar_type(), "bending_energy", [&] {
    using T = scalar_t;
    HingeArgs<T> args = hinge_args<T>(P.a, P.k, P.rest, P.c, P.prev, P.damped, int(model), P.H);
    const T* xp = P.x.data_ptr<T>();
    const int64_t* hp = P.hinges.data_ptr<int64_t>();
    T* po = psi.data_ptr<T>(); T* to = theta.data_ptr<T>();
    int64_t V = P.V;
    with_model(int(model), P.damped, [&](auto M_, auto D_) {
      constexpr int M = decltype(M_)::value;
      constexpr bool D = decltype(D_)::value;
      for_tiles<WL>(P.B, P.H, [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs) {
        alignas(64) T X[12][WL];
        alignas(64) T TH[WL], PS[WL];
        HingeTile<T, WL> Q;
        if (gather_tile<T, true, WL>(xp, nullptr, hp, V, args, nullptr, nl, bs, hs, X, nullptr, Q))
          bad_index.store(true, std::memory_order_relaxed);
        theta_tile<T, WL>(X, TH);
        TB_LANES_AGG(WL) {
          T d1, d2;
          psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], PS[l], d1, d2, static_cast<T*>(nullptr));
        }
        store_lanes<T, WL>(PS, nl, po + bh0); store_lanes<T, WL>(TH, nl, to + bh0);
      });
    });
  });
  if (bad_index.load()) check_hinge_range("bending_energy", P.hinges, P.V);  // raises: nothing is returned
  return {psi, theta, fold_status(theta, model)};
}

// (psi (..., H) or an empty tensor, w dE/dx (..., V, 3), w dpsi/d(k, rest, c, prev) (..., H, 4) or an empty
// tensor, theta (..., H), status): the gradient pass, which also writes the (unweighted) per-hinge energies
// when `energies` is set (the forward of a recorded energy: one pass instead of two)
static std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor, int64_t> gradient_pass(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
    const c10::optional<torch::Tensor>& c, const c10::optional<torch::Tensor>& prev, int64_t model,
    torch::Tensor weight, const torch::Tensor& inc_ptr, const torch::Tensor& inc_idx, bool params, bool check,
    bool energies) {
  const char* op = energies ? "bending_energy_gradient" : "bending_gradient";
  Prepared P = prepare(op, x, hinges, a, k, rest, c, prev, model, false);
  weight = prepare_weight(op, weight, P);
  torchbend::checks::check_incidence(op, inc_ptr, inc_idx, P.V, P.H);
  auto gx = torch::empty(shape_with(P.batch, {P.V, 3}), P.x.options());
  auto gp = params ? torch::empty(shape_with(P.batch, {P.H, 4}), P.x.options()) : torch::empty({0}, P.x.options());
  auto theta = torch::empty(shape_with(P.batch, {P.H}), P.x.options());
  auto psi = energies ? torch::empty_like(theta) : torch::empty({0}, P.x.options());
  if (check && finite_status(P.x, kBadX)) return {psi, gx, gp, theta, kBadX};
  AT_DISPATCH_FLOATING_TYPES(P.x.scalar_type(), "bending_gradient", [&] {
    using T = scalar_t;
    HingeArgs<T> args = hinge_args<T>(P.a, P.k, P.rest, P.c, P.prev, P.damped, int(model), P.H);
    Param<T> w{weight.data_ptr<T>(), weight.numel(), P.H};
    const T* xp = P.x.data_ptr<T>();
    const int64_t* hp = P.hinges.data_ptr<int64_t>();
    T* gpp = params ? gp.data_ptr<T>() : nullptr; T* to = theta.data_ptr<T>();
    T* po = energies ? psi.data_ptr<T>() : nullptr;
    int64_t V = P.V;
    with_model(int(model), P.damped, [&](auto M_, auto D_) {
      constexpr int M = decltype(M_)::value;
      constexpr bool D = decltype(D_)::value;
      scatter_tiles<T, WL>(op, P.hinges, P.B, V, inc_ptr.data_ptr<int64_t>(), inc_idx.data_ptr<int64_t>(), gx.data_ptr<T>(),
                       [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs, T (*O)[WL]) {
        alignas(64) T X[12][WL], G[12][WL];
        alignas(64) T TH[WL], S[WL], PS[WL], GP[4][WL];
        HingeTile<T, WL> Q;
        Half<T, WL> hA, hB;
        gather_tile<T, false, WL>(xp, nullptr, hp, V, args, &w, nl, bs, hs, X, nullptr, Q);
        theta_tile<T, WL>(X, TH);
        // the half-hinges right after the angle, on which they do not depend (psi does): nearer in the instruction
        // stream to the angle's long-latency divisions and polynomials (no measurable change on an AVX-512 Xeon)
        halves_tile<T, WL, false>(X, hA, hB);
        if (gpp) {
          TB_LANES_AGG(WL) {
            T d1, d2, g4[4];
            psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], PS[l], d1, d2, g4);
            S[l] = Q.w[l] * d1;
            GP[0][l] = Q.w[l] * g4[0]; GP[1][l] = Q.w[l] * g4[1]; GP[2][l] = Q.w[l] * g4[2]; GP[3][l] = Q.w[l] * g4[3];
          }
          for (int l = 0; l < nl; ++l)
            for (int j = 0; j < 4; ++j) gpp[4 * (bh0 + l) + j] = GP[j][l];
        } else {
          TB_LANES_AGG(WL) {
            T d1, d2;
            psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], PS[l], d1, d2, static_cast<T*>(nullptr));
            S[l] = Q.w[l] * d1;
          }
        }
        grad_of_halves<T, WL>(hA, hB, G);
        for (int m = 0; m < 12; ++m) TB_LANES(WL) O[m][l] = S[l] * G[m][l];
        store_lanes<T, WL>(TH, nl, to + bh0);
        if (po) store_lanes<T, WL>(PS, nl, po + bh0);
      });
    });
  });
  return {psi, gx, gp, theta, fold_status(theta, model)};
}

// (w dE/dx (..., V, 3), w dpsi/d(k, rest, c, prev) (..., H, 4) or an empty tensor, theta (..., H), status); w a
// per-hinge weight (the cotangent of the energy: scalar, (H,) or (B, H)); check as in bending_energy
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, int64_t> bending_gradient(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
    c10::optional<torch::Tensor> c, c10::optional<torch::Tensor> prev, int64_t model, torch::Tensor weight,
    torch::Tensor inc_ptr, torch::Tensor inc_idx, bool params, bool check) {
  auto r = gradient_pass(x, hinges, a, k, rest, c, prev, model, weight, inc_ptr, inc_idx, params, check, false);
  return {std::get<1>(r), std::get<2>(r), std::get<3>(r), std::get<4>(r)};
}

// (psi (..., H), dE/dx (..., V, 3), dpsi/d(k, rest, c, prev) (..., H, 4) or an empty tensor, theta (..., H),
// status): the per-hinge energies and the unweighted gradients in one pass; check as in bending_energy
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor, int64_t> bending_energy_gradient(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
    c10::optional<torch::Tensor> c, c10::optional<torch::Tensor> prev, int64_t model, torch::Tensor inc_ptr,
    torch::Tensor inc_idx, bool params, bool check) {
  return gradient_pass(x, hinges, a, k, rest, c, prev, model, torch::ones({1}, x.options()), inc_ptr, inc_idx,
                       params, check, true);
}

// (w H v (..., V, 3), theta (..., H)): the Hessian of the energy applied to directions v (..., V, 3) of x's
// shape, without forming any matrix (per hinge psi' H_theta v + psi'' (g . v) g, H_theta v in closed form);

}  // namespace cpu
}  // namespace torchbend
