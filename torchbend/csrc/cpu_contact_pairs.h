// The pairs' shared pieces of the CPU contact operators (cpu_contact.cpp: distances, close pairs, step bound,
// barrier, the gradients' sum; cpu_contact_sum.cpp: the sums of the pairs' Hessians): the checked stencils, a
// stencil's corners, the pairs' terms computed and projected a chunk at a time, the groups of pairs that are one
// contact, and the barrier operators' checked arguments.
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

// The pairs that are one point-point or point-edge contact found by several stencils (a vertex near an edge is
// found by the triangles at the edge and by the edges at the vertex: 2,500 contacts for 9,208 point-edge pairs on
// the 50x50 half fold of benchmarks/bm_contact.py): their energies are one function of the same corners, so one of
// them, counted as many times, gives their Hessians' sum.  Returns the pairs to compute (each group's first, in pair
// order) and their counts.  A pair under its mollifier's threshold (an edge-edge pair; pair_terms mollifies any pair
// given eps > 0) depends on all four corners and is its own group, as is every point-plane and line-line pair.
// used[4 j + v]: whether the energy of reps[j] depends on its corner v (a point-edge pair's three, a point-point
// pair's two; every corner of a mollified, point-plane or line-line pair): the other corners' Hessian blocks are
// zero and stay out of the sum's pattern.
template <typename T>
void contact_groups(const T* px, const int64_t* ps, const int64_t* pt, const T* pe, int64_t N, int64_t n,
                    std::vector<int64_t>& reps, std::vector<int64_t>& count, std::vector<unsigned char>& used) {
  // per type: the contact's corners (point, then the edge's or the other point's; -1: no group)
  static const signed char corner[cm::NUM_TYPES][3] = {
      {0, 1, -1}, {0, 2, -1}, {0, 3, -1}, {0, 1, 2}, {0, 2, 3}, {0, 3, 1}, {-1, -1, -1},  // PT_*
      {0, 2, -1}, {0, 3, -1}, {1, 2, -1}, {1, 3, -1}, {2, 0, 1}, {3, 0, 1}, {0, 2, 3}, {1, 2, 3},  // EE_* (points)
      {-1, -1, -1}};
  // key (a, b, c): point-edge (point, smaller edge end, larger), point-point (smaller, larger, -1); grouped by a
  std::vector<int64_t> key_b(N, -2), key_c(N, -2), start(n + 1, 0);
  std::vector<int64_t> a_of(N, -1);
  std::vector<unsigned char> all4(N, 1);
  for (int64_t i = 0; i < N; ++i) {
    const signed char* c = corner[pt[i]];
    if (c[0] < 0) continue;
    const int64_t* s = ps + 4 * i;
    if (pe && pe[i] > 0) {  // a pair with a mollifier (edge-edge): grouped only above its threshold, as pair_terms
      T X[4][3];
      gather(px, s, X);
      if (cm::edge_cross_sq(X) < pe[i]) continue;
    }
    all4[i] = 0;
    int64_t a = s[c[0]], b = s[c[1]], cc = c[2] < 0 ? -1 : s[c[2]];
    if (cc < 0) { if (b < a) std::swap(a, b); }
    else if (cc < b) std::swap(b, cc);
    a_of[i] = a; key_b[i] = b; key_c[i] = cc;
    ++start[a + 1];
  }
  for (int64_t v = 0; v < n; ++v) start[v + 1] += start[v];
  std::vector<int64_t> slot(start[n]), fill(start.begin(), start.end() - 1), rep(N);
  for (int64_t i = 0; i < N; ++i)
    if (a_of[i] >= 0) slot[fill[a_of[i]]++] = i;
  for (int64_t i = 0; i < N; ++i) rep[i] = i;
  for (int64_t v = 0; v < n; ++v) {  // within a point's pairs (in pair order), the same (b, c): the first one's
    const int64_t lo = start[v], hi = start[v + 1];
    if (hi - lo < 2) continue;
    std::stable_sort(slot.begin() + lo, slot.begin() + hi, [&](int64_t i, int64_t j) {
      return key_b[i] != key_b[j] ? key_b[i] < key_b[j] : key_c[i] < key_c[j];
    });
    for (int64_t q = lo + 1; q < hi; ++q) {
      const int64_t i = slot[q], j = slot[q - 1];
      if (key_b[i] == key_b[j] && key_c[i] == key_c[j]) rep[i] = rep[j];
    }
  }
  std::vector<int64_t> cnt(N, 0);
  for (int64_t i = 0; i < N; ++i) ++cnt[rep[i]];
  reps.clear(); count.clear(); used.clear();
  for (int64_t i = 0; i < N; ++i)
    if (rep[i] == i) {
      reps.push_back(i); count.push_back(cnt[i]);
      signed char C[3][4];
      int formula;
      cm::type_rows(int(pt[i]), &formula, C);
      for (int v = 0; v < 4; ++v) used.push_back(all4[i] || C[0][v] || C[1][v] || C[2][v] ? 1 : 0);
    }
}

// the groups' pairs (contact_groups' reps): their stencils (4 R), types and thresholds (empty where pe is null), the
// arguments of pair_chunk over them
template <typename T> struct GroupPairs {
  std::vector<int64_t> st, ty;
  std::vector<T> eps;
};

template <typename T>
GroupPairs<T> group_pairs(const int64_t* ps, const int64_t* pt, const T* pe, const std::vector<int64_t>& reps) {
  const int64_t R = int64_t(reps.size());
  GroupPairs<T> g{std::vector<int64_t>(4 * R), std::vector<int64_t>(R), std::vector<T>(pe ? R : 0)};
  for (int64_t j = 0; j < R; ++j) {
    for (int v = 0; v < 4; ++v) g.st[4 * j + v] = ps[4 * reps[j] + v];
    g.ty[j] = pt[reps[j]];
    if (pe) g.eps[j] = pe[reps[j]];
  }
  return g;
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
