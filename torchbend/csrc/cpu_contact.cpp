// The compiled contact operators of the CPU extension (torchbend.sim.self_contact uses them; the eager code there
// is the reference):
//   contact_box_pairs   the broad phase (cpu_broad_phase.cpp)
//   contact_distances   the distance type and squared distance of point-triangle or edge-edge stencils
//   contact_close       the stencils closer than dhat
//   contact_step_bound  the conservative step bound of candidate stencils
//   contact_barrier     the pairs' barrier energies, gradients and (PSD-projected) Hessians
//   contact_gradient_sum the pairs' barrier gradients summed over the points, a contact found by several stencils
//                       computed once and counted as many times
//   contact_hessian_sum, contact_stencil_sum: the sums of the pairs' Hessians (cpu_contact_sum.cpp)
// The per-stencil mathematics is contact_math.h (shared with the CUDA driver, bending_cuda.cu); the pieces both
// translation units share (the pairs' terms a chunk at a time) are cpu_contact_pairs.h.
#include <algorithm>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

#include "contact_math.h"
#include "cpu_contact.h"
#include "cpu_contact_pairs.h"
#include "cpu_contact_scan.h"

namespace torchbend {
namespace cpu {

namespace ck = torchbend::checks;
namespace cm = torchbend::contact;

// ---- stencils: types, distances -------------------------------------------------------------------
namespace {
// the squared distance of a stencil and (type) its distance type
// (edge-edge stencils typed in double: in float32 |u|^2 |v|^2 - (u . v)^2 of two parallel edges is round-off far
// above the parallel threshold, and the clamped parameters are noise: two parallel edges of a flat float32 grid
// came out as crossing lines at distance 0)
template <typename T> T stencil_distance_sq(const T X[4][3], bool edge_edge, int* type) {
  int t;
  if (edge_edge) {
    double D[4][3];
    for (int v = 0; v < 4; ++v)
      for (int i = 0; i < 3; ++i) D[v][i] = double(X[v][i]);
    t = cm::edge_edge_type(D[0], D[1], D[2], D[3], 1e-10);
  } else {
    t = cm::point_triangle_type(X[0], X[1], X[2], X[3]);
  }
  int formula;
  signed char C[3][4] = {};
  const int r = cm::type_rows(t, &formula, C);
  T y[9];
  cm::reduce(C, r, X, y);
  *type = t;
  return cm::typed_distance<T>(formula, y);
}

// the squared gap (in A arithmetic) between the boxes of a stencil's two sides, corners [0, split) and [split, 4):
// a lower bound of its squared distance
template <typename A, typename T> A box_gap_sq(const T X[4][3], int split) {
  A gap = 0;
  for (int i = 0; i < 3; ++i) {
    T loA = X[0][i], hiA = X[0][i], loB = X[split][i], hiB = X[split][i];
    for (int v = 1; v < split; ++v) { loA = std::min(loA, X[v][i]); hiA = std::max(hiA, X[v][i]); }
    for (int v = split + 1; v < 4; ++v) { loB = std::min(loB, X[v][i]); hiB = std::max(hiB, X[v][i]); }
    A g = std::max(A(loB) - A(hiA), A(loA) - A(hiB));
    if (g > 0) gap += g * g;
  }
  return gap;
}

}  // namespace

std::tuple<torch::Tensor, torch::Tensor> contact_distances(torch::Tensor x, torch::Tensor stencils, bool edge_edge) {
  const char* op = "contact_distances";
  stencils = stencil_tensor(op, x, stencils);
  x = x.contiguous();
  const int64_t N = stencils.size(0);
  auto types = torch::empty({N}, stencils.options());
  auto D = torch::empty({N}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    const scalar_t* px = x.data_ptr<scalar_t>();
    const int64_t* ps = stencils.data_ptr<int64_t>();
    int64_t* pt = types.data_ptr<int64_t>();
    scalar_t* pd = D.data_ptr<scalar_t>();
    at::parallel_for(0, N, 2048, [&](int64_t n0, int64_t n1) {
      for (int64_t n = n0; n < n1; ++n) {
        scalar_t X[4][3];
        gather(px, ps + 4 * n, X);
        int t;
        pd[n] = stencil_distance_sq(X, edge_edge, &t);
        pt[n] = t;
      }
    });
  });
  return {types, D};
}

// the pairs of candidate stencils closer than sqrt(dhat_sq) (every candidate typed and measured over lanes,
// cpu_contact_scan.h), with their types, in order: every pair counts, as the IPC toolkit's collision sets weigh a
// vertex-edge or vertex-vertex contact found by several triangles by their number (its energy stays continuous
// where a point crosses above an edge or a vertex)
std::tuple<torch::Tensor, torch::Tensor> contact_close(torch::Tensor x, torch::Tensor stencils, bool edge_edge,
                                                       double dhat_sq) {
  const char* op = "contact_close";
  stencils = stencil_tensor(op, x, stencils);
  ck::require(dhat_sq > 0 && std::isfinite(dhat_sq), op, "dhat_sq must be finite and > 0, got ", dhat_sq);
  x = x.contiguous();
  const int64_t N = stencils.size(0);
  std::vector<int8_t> type(N, -1);
  const int64_t* ps = stencils.data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* px = x.data_ptr<T>();
    const T dh2 = T(dhat_sq);
    at::parallel_for(0, N, 2048, [&](int64_t n0, int64_t n1) {
      close_types<T>(px, ps, edge_edge, double(dh2), n0, n1, type.data());
    });
  });
  std::vector<int64_t> keep;
  for (int64_t n = 0; n < N; ++n)
    if (type[n] >= 0) keep.push_back(n);
  auto idx = torch::empty({int64_t(keep.size())}, stencils.options());
  auto types = torch::empty({int64_t(keep.size())}, stencils.options());
  for (size_t i = 0; i < keep.size(); ++i) {
    idx.data_ptr<int64_t>()[i] = keep[i];
    types.data_ptr<int64_t>()[i] = type[keep[i]];
  }
  return {idx, types};
}

// The conservative step bound of stencils whose vertices move along a step: 0.9 d / (m_A + m_B), at most 1, the
// smallest over the stencils (torchbend.sim.self_contact).  move (n,): each point's largest move, m_A and m_B the
// largest of each side; move (n, 3): each point's displacement, m_A and m_B the largest of each side's displacements
// less the stencil's mean (a move the four corners share changes no distance: a cloth falling onto itself as a
// whole is not held back), or of the displacements themselves where those give the smaller sum.  A stencil whose primitives' boxes are so far apart that their gap alone bounds it above
// the smallest so far is skipped (its distance is at least the gap).
namespace {
constexpr int kMaxAdvances = 64;  // advances of a pair's conservative advancement at most (torchbend.sim.self_contact)
// a pair advances past its first advance only where a tenth of its start (or of dhat) is at least kResolvable double
// epsilons of its corners' scale (their largest coordinate plus their largest displacement component): the distances
// it measures along the step (in double whatever T) are then within a small part of its floor.  The floor is that
// tenth, and at least kRounding epsilons of T of the scale: the bound keeps every pair at a tenth of its floor at
// least (6.4 epsilons of the scale), and rounding the step's end x + alpha dx to T (two roundings, each coordinate
// within an epsilon of the scale) moves a pair's distance by at most 2 sqrt(3), about 3.5, epsilons of it
// (torchbend.sim.self_contact._advance).  In float64 the first bound is the larger: the floor is the tenth.
constexpr double kResolvable = 1024.0, kRounding = 64.0;
constexpr double measured_floor() { return kResolvable * std::numeric_limits<double>::epsilon(); }
template <typename T> constexpr double rounding_floor() {
  return kRounding * double(std::numeric_limits<T>::epsilon());
}

template <typename T> double corner_scale(const T X[4][3], const T* pm, const int64_t* s) {
  double sx = 0, sp = 0;
  for (int v = 0; v < 4; ++v)
    for (int i = 0; i < 3; ++i) {
      sx = std::max(sx, double(std::abs(X[v][i])));
      sp = std::max(sp, double(std::abs(pm[3 * s[v] + i])));
    }
  return sx + sp;
}

// the distance of the stencil with corners X moved by t times their displacements (pm, rows s), in double whatever
// T (float32's distance formulas misjudge nearly parallel edges by 10-100x near contact: a review's case)
// (pm null: the corners themselves, for moves given as one distance a point)
template <typename T> double distance_at(const T X[4][3], const T* pm, const int64_t* s, double t, bool edge_edge) {
  double Y[4][3];
  for (int v = 0; v < 4; ++v)
    for (int i = 0; i < 3; ++i) Y[v][i] = pm ? double(X[v][i]) + t * double(pm[3 * s[v] + i]) : double(X[v][i]);
  int ty;
  return std::sqrt(std::max(stencil_distance_sq(Y, edge_edge, &ty), 0.0));
}
}  // namespace

double contact_step_bound(torch::Tensor x, torch::Tensor stencils, bool edge_edge, torch::Tensor move, double dhat) {
  const char* op = "contact_step_bound";
  stencils = stencil_tensor(op, x, stencils);
  const bool vectors = move.dim() == 2;
  ck::require(move.device().is_cpu() && (move.dim() == 1 || (vectors && move.size(1) == 3)) &&
              move.size(0) == x.size(0) && move.scalar_type() == x.scalar_type(), op,
              "move must hold one distance (n,) or one displacement (n, 3) per point of x, in x's dtype, got ",
              ck::shape_str(move));
  x = x.contiguous();
  move = move.contiguous();
  const int64_t N = stencils.size(0);
  const int64_t* ps = stencils.data_ptr<int64_t>();
  double alpha = 1.0;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* px = x.data_ptr<T>();
    const T* pm = move.data_ptr<T>();
    const int split = edge_edge ? 2 : 1;
    const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), (N + 4095) / 4096));
    std::vector<double> best(chunks, 1.0);
    at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) {
        double a = 1.0;
        for (int64_t n = N * c / chunks; n < N * (c + 1) / chunks; ++n) {
          const int64_t* s = ps + 4 * n;
          double mA = 0, mB = 0;
          if (vectors) {
            double d[4][3], mean[3] = {0, 0, 0};
            for (int v = 0; v < 4; ++v)
              for (int i = 0; i < 3; ++i) { d[v][i] = double(pm[3 * s[v] + i]); mean[i] += 0.25 * d[v][i]; }
            double lA = 0, lB = 0;  // the uncentred lengths' bound too: the smaller rate holds (both do)
            for (int v = 0; v < 4; ++v) {
              const double e0 = d[v][0] - mean[0], e1 = d[v][1] - mean[1], e2 = d[v][2] - mean[2];
              const double m = std::sqrt(e0 * e0 + e1 * e1 + e2 * e2);
              const double len = std::sqrt(d[v][0] * d[v][0] + d[v][1] * d[v][1] + d[v][2] * d[v][2]);
              (v < split ? mA : mB) = std::max(v < split ? mA : mB, m);
              (v < split ? lA : lB) = std::max(v < split ? lA : lB, len);
            }
            if (lA + lB < mA + mB) { mA = lA; mB = lB; }
          } else {
            for (int v = 0; v < 4; ++v) (v < split ? mA : mB) = std::max(v < split ? mA : mB, double(pm[s[v]]));
          }
          const double rate = mA + mB;
          if (!(rate > 0)) continue;
          T X[4][3];
          gather(px, s, X);
          if (0.9 * std::sqrt(box_gap_sq<double>(X, split)) * (1 - 1e-9) / rate >= a) continue;
          const double dist = distance_at<T>(X, nullptr, s, 0.0, edge_edge);  // in double, as every distance here
          double t = 0.9 * dist / rate;  // the first advance, taken whole
          if (vectors && dhat > 0 && t < a) {
            // conservative advancement from the distance reached while it stays above the floor, to the step's end
            // (1) at most; a pair whose time reached passes a cannot lower a: its advances stop (the result is the
            // smallest pair time whatever the order and the threads)
            // the floor: a tenth of the start or of dhat, at least what rounding the end to T resolves; a pair whose
            // tenth the double measurement does not resolve keeps its first advance
            const double scale = corner_scale(X, pm, s), tenth = 0.1 * std::min(dist, dhat);
            const double floor = std::max(tenth, rounding_floor<T>() * scale);
            double dn = distance_at(X, pm, s, t, edge_edge);
            if (tenth < measured_floor() * scale) dn = -1;
            for (int i = 1; i < kMaxAdvances && dn >= floor && t < a; ++i) {
              const double tn = t + 0.9 * dn / rate;
              if (tn >= 1.0) { t = 1.0; break; }
              dn = distance_at(X, pm, s, tn, edge_edge);
              if (dn >= floor) t = tn;
            }
          }
          a = std::min(a, t);
        }
        best[c] = a;
      }
    });
    for (double b : best) alpha = std::min(alpha, b);
  });
  return std::max(alpha, 0.0);
}

// ---- the pairs' barrier: energies, gradients, Hessians ------------------------------------------------

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> contact_barrier(torch::Tensor x, torch::Tensor stencils,
                                                                        torch::Tensor types, torch::Tensor eps,
                                                                        double dhat_sq, double kappa, int64_t want,
                                                                        int64_t mode) {
  const char* op = "contact_barrier";
  auto [st, ty, ep] = barrier_args(op, x, stencils, types, eps, dhat_sq, kappa, want, mode);
  x = x.contiguous();
  const int64_t N = st.size(0);
  auto E = torch::empty({N}, x.options());
  auto G = torch::empty({want >= 1 ? N : 0, 12}, x.options());
  auto H = torch::empty({want >= 2 ? N : 0, 12, 12}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* px = x.data_ptr<T>();
    const int64_t* ps = st.data_ptr<int64_t>();
    const int64_t* pt = ty.data_ptr<int64_t>();
    const T* pe = ep.numel() ? ep.data_ptr<T>() : nullptr;
    T* pE = E.data_ptr<T>();
    T* pG = want >= 1 ? G.data_ptr<T>() : nullptr;
    T* pH = want >= 2 ? H.data_ptr<T>() : nullptr;
    if (want == 0) {
      at::parallel_for(0, N, 2048, [&](int64_t n0, int64_t n1) {
        pair_energies<T>(px, ps, pt, pe, T(dhat_sq), T(kappa), n0, n1, pE);
      });
      return;
    }
    const int64_t chunks = (N + kPairChunk - 1) / kPairChunk;
    at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
      std::vector<cm::PairTerms<T>> terms(kPairChunk);
      for (int64_t c = c0; c < c1; ++c) {
        const int64_t base = c * kPairChunk;
        pair_chunk<T>(px, ps, pt, pe, T(dhat_sq), T(kappa), int(want), mode, base,
                      std::min<int64_t>(kPairChunk, N - base), terms, pE, pG, pH);
      }
    });
  });
  return {E, G, H};
}

// the pairs' barrier gradients summed over the points (in this translation unit: each pair's gradient is the one
// contact_barrier computes, bit for bit)
torch::Tensor contact_gradient_sum(torch::Tensor x, torch::Tensor stencils, torch::Tensor types, torch::Tensor eps,
                                   double dhat_sq, double kappa) {
  const char* op = "contact_gradient_sum";
  auto [st, ty, ep] = barrier_args(op, x, stencils, types, eps, dhat_sq, kappa, 1, -1);
  x = x.contiguous();
  const int64_t N = st.size(0), n = x.size(0);
  auto out = torch::zeros({n, 3}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* px = x.data_ptr<T>();
    const int64_t* ps = st.data_ptr<int64_t>();
    const int64_t* pt = ty.data_ptr<int64_t>();
    const T* pe = ep.numel() ? ep.data_ptr<T>() : nullptr;
    T* po = out.data_ptr<T>();
    // one pair of each group that is the same contact, its gradient counted as many times (as the Hessian sum);
    // the chunks' pairs in parallel, their gradients added in pair order (the same sums for any number of threads)
    std::vector<int64_t> reps, count;
    std::vector<unsigned char> used;
    contact_groups<T>(px, ps, pt, pe, N, n, reps, count, used);
    const int64_t R = int64_t(reps.size());
    const GroupPairs<T> g = group_pairs(ps, pt, pe, reps);
    std::vector<T> G(size_t(12) * size_t(R));
    const int64_t chunks = (R + kPairChunk - 1) / kPairChunk;
    at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
      std::vector<cm::PairTerms<T>> terms(kPairChunk);
      for (int64_t c = c0; c < c1; ++c) {
        const int64_t base = c * kPairChunk;
        pair_chunk<T>(px, g.st.data(), g.ty.data(), pe ? g.eps.data() : nullptr, T(dhat_sq), T(kappa), 1, -1, base,
                      std::min<int64_t>(kPairChunk, R - base), terms, nullptr, G.data(), nullptr);
      }
    });
    for (int64_t j = 0; j < R; ++j) {
      const T times = T(count[j]);
      for (int v = 0; v < 4; ++v) {
        if (!used[4 * j + v]) continue;
        T* dst = po + 3 * g.st[4 * j + v];
        const T* gj = G.data() + 12 * j + 3 * v;
        for (int i = 0; i < 3; ++i) dst[i] += count[j] > 1 ? times * gj[i] : gj[i];
      }
    }
  });
  return out;
}

// the PSD projection of symmetric blocks M (..., n, n), n 3, 6 or 9, by the contact kernels' eigensolver (mode 0:
// clamp, 1: abs): the tests' access to it
torch::Tensor contact_project_blocks(torch::Tensor M, int64_t mode) {
  const char* op = "contact_project_blocks";
  ck::require(M.device().is_cpu() && M.dim() >= 2 && M.size(-1) == M.size(-2) &&
              (M.size(-1) == 3 || M.size(-1) == 6 || M.size(-1) == 9) && M.is_floating_point(), op,
              "M must be a CPU (..., n, n) float tensor with n 3, 6 or 9, got ", ck::shape_str(M));
  ck::require(mode == 0 || mode == 1, op, "mode must be 0 (clamp) or 1 (abs)");
  M = M.contiguous();
  auto out = torch::empty_like(M);
  const int64_t n = M.size(-1), count = M.numel() / (n * n);
  AT_DISPATCH_FLOATING_TYPES(M.scalar_type(), "contact", [&] {
    using T = scalar_t;
    auto run = [&](auto N_) {
      constexpr int N = decltype(N_)::value;
      const T* in = M.data_ptr<T>();
      T* o = out.data_ptr<T>();
      for (int64_t t = 0; t < count; t += kLanes) {
        const int nl = int(std::min<int64_t>(kLanes, count - t));
        alignas(64) T A[N][N][kLanes];
        for (int l = 0; l < kLanes; ++l)
          for (int i = 0; i < N; ++i)
            for (int j = 0; j < N; ++j)
              A[i][j][l] = l < nl ? T(0.5) * (in[(t + l) * N * N + i * N + j] + in[(t + l) * N * N + j * N + i]) : T(0);
        ql_project<T, N, kLanes>(A, mode == 1);
        for (int l = 0; l < nl; ++l)
          for (int i = 0; i < N; ++i)
            for (int j = 0; j < N; ++j) o[(t + l) * N * N + i * N + j] = A[i][j][l];
      }
    };
    if (n == 3) run(std::integral_constant<int, 3>{});
    else if (n == 6) run(std::integral_constant<int, 6>{});
    else run(std::integral_constant<int, 9>{});
  });
  return out;
}

}  // namespace cpu
}  // namespace torchbend
