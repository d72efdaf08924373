// The pairs' shared pieces of the CPU contact operators (cpu_contact.cpp: distances, close pairs, step bound,
// barrier; cpu_contact_sum.cpp: the sums of the pairs' Hessians): the checked stencils, a stencil's corners, the
// pairs' terms computed and projected a chunk at a time, and the barrier operators' checked arguments.
#pragma once
#include <algorithm>
#include <cstdint>
#include <vector>

#include "checks.h"
#include "contact_frame.h"
#include "contact_math.h"
#include "cpu_contact_lanes.h"
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {

namespace ck = torchbend::checks;
namespace cm = torchbend::contact;

namespace {

// the stencils (n, 4) checked against x (n points)
torch::Tensor stencil_tensor(const char* op, const torch::Tensor& x, torch::Tensor st) {
  ck::require(x.device().is_cpu() && x.dim() == 2 && x.size(1) == 3 &&
              (x.scalar_type() == torch::kFloat || x.scalar_type() == torch::kDouble), op,
              "x must be a CPU (n, 3) float32 or float64 tensor, got ", ck::shape_str(x), " ", x.scalar_type());
  st = ck::index_tensor(op, "stencils", st, x.device(), 4);
  ck::check_range(op, "stencils", st, 0, x.size(0), "x has n = " + std::to_string(x.size(0)) + " points");
  return st;
}

template <typename T> inline void gather(const T* x, const int64_t* s, T X[4][3]) {
  for (int v = 0; v < 4; ++v)
    for (int i = 0; i < 3; ++i) X[v][i] = x[3 * s[v] + i];
}

constexpr int kPairChunk = 256;

// the pairs base .. base + n - 1: their terms (Hessians in reduced coordinates, projected unless mode < 0) and,
// where given, their energies, 12-gradients and 12x12 Hessians
template <typename T>
void pair_chunk(const T* px, const int64_t* ps, const int64_t* pt, const T* pe, T dh2, T kappa, int want, int64_t mode,
                int64_t base, int64_t n, std::vector<cm::PairTerms<T>>& terms, T* pE, T* pG, T* pH) {
  std::vector<int> by_r[3], framed[2];  // by rows: the full eigenproblem; (r = 2, 3): in the normal frame
  for (int64_t i = 0; i < n; ++i) {
    T X[4][3];
    gather(px, ps + 4 * (base + i), X);
    auto& p = terms[i];
    cm::pair_terms<T>(X, int(pt[base + i]), pe ? pe[base + i] : T(0), dh2, kappa, want, &p);
    if (pE) pE[base + i] = p.E;
    if (pG) cm::expand_gradient(p.C, p.r, p.g, pG + 12 * (base + i));
    if (want >= 2) {
      if (mode >= 0) (p.r >= 2 && !p.mollified && cm::frame_ok(p.g) ? framed[p.r - 2] : by_r[p.r - 1]).push_back(int(i));
      else if (pH) cm::expand_hessian(p.C, p.r, p.H, pH + 144 * (base + i));
    }
  }
  if (want >= 2 && mode >= 0) {
    project_group<T, 3>(terms, by_r[0], base, mode == 1, pH);
    project_group<T, 6>(terms, by_r[1], base, mode == 1, pH);
    project_group<T, 9>(terms, by_r[2], base, mode == 1, pH);
    frame_group<T, 2>(terms, framed[0], base, mode == 1, pH);
    frame_group<T, 3>(terms, framed[1], base, mode == 1, pH);
  }
}

// the checked stencils, types and thresholds (in x's dtype; empty: none) of the barrier operators
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> barrier_args(const char* op, const torch::Tensor& x,
                                                                     torch::Tensor stencils, torch::Tensor types,
                                                                     torch::Tensor eps, double dhat_sq, double kappa,
                                                                     int64_t want, int64_t mode) {
  stencils = stencil_tensor(op, x, stencils);
  const int64_t N = stencils.size(0);
  types = ck::index_tensor(op, "types", types, x.device());
  ck::require(types.dim() == 1 && types.size(0) == N, op, "types must have one entry per stencil, got ",
              ck::shape_str(types));
  ck::check_range(op, "types", types, 0, cm::NUM_TYPES, "the distance types");
  if (eps.numel() > 0) {
    ck::require(eps.dim() == 1 && eps.size(0) == N && eps.device().is_cpu(), op,
                "eps must be empty or hold one threshold per stencil, got ", ck::shape_str(eps));
    eps = eps.to(x.scalar_type()).contiguous();
  }
  ck::require(dhat_sq > 0 && std::isfinite(dhat_sq) && kappa >= 0 && std::isfinite(kappa), op,
              "dhat_sq must be finite and > 0 and kappa finite and >= 0, got ", dhat_sq, " and ", kappa);
  ck::require(want >= 0 && want <= 2 && mode >= -1 && mode <= 1, op,
              "want must be 0 (energy), 1 (+ gradient) or 2 (+ Hessian) and mode -1 (none), 0 (clamp) or 1 (abs)");
  return {stencils, types, eps};
}

}  // namespace
}  // namespace cpu
}  // namespace torchbend
