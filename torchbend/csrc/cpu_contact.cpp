// The compiled contact operators of the CPU extension (torchbend.sim.self_contact uses them; the eager code there
// is the reference):
//   contact_box_pairs   the broad phase (cpu_broad_phase.cpp)
//   contact_distances   the distance type and squared distance of point-triangle or edge-edge stencils
//   contact_close       the stencils closer than dhat
//   contact_step_bound  the conservative step bound of candidate stencils
//   contact_barrier     the pairs' barrier energies, gradients and (PSD-projected) Hessians
//   contact_hessian_sum the pairs' (projected) Hessians summed into the (3V, 3V) matrix, without the blocks, and
//                       the friction pairs' (w w^T (x) their point block)
//   contact_stencil_sum the sum of given 12x12 stencil blocks
// The per-stencil mathematics is contact_math.h (shared with the CUDA driver, bending_cuda.cu).
#include <algorithm>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

#include "contact_frame.h"
#include "contact_math.h"
#include "cpu_contact.h"
#include "cpu_contact_lanes.h"
#include "cpu_contact_scan.h"
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {

namespace ck = torchbend::checks;
namespace cm = torchbend::contact;

// ---- stencils: gather, types, distances -------------------------------------------------------------
namespace {

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
// a pair advances past its first advance only where its floor is at least kResolvable epsilons of its corners' scale
// (their largest coordinate plus their largest displacement component): there the distances it measures along the
// step are within a small part of the floor (torchbend.sim.self_contact._advance)
constexpr double kResolvable = 1024.0;

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
            const double floor = 0.1 * std::min(dist, dhat);
            double dn = distance_at(X, pm, s, t, edge_edge);
            if (floor < kResolvable * double(std::numeric_limits<T>::epsilon()) * corner_scale(X, pm, s)) dn = -1;
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
namespace {

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

// ---- the sum of stencil blocks -------------------------------------------------------------------------
namespace {

// Where each 3x3 block of a set of four-vertex stencils goes in the row-major (3V, 3V) sum: block row v holds
// nb[v] blocks (distinct column vertices, in increasing order) from 9 first[v]; scalar row 3 v + p holds their
// 3 nb[v] entries.  at[16 m + 4 a + b]: the offset 9 first[v] + 3 j of the block of stencil m's vertices a, b
// (v = st[m][a], j its place in the row), -1 when either vertex is >= V (a body's, not an unknown).
struct BlockPattern {
  std::vector<int64_t> first, nb, at;
  int64_t U = 0;
  torch::Tensor indices;  // (2, 9 U): the entries' rows and columns
  int64_t value_index(int64_t v, int64_t e, int p, int s) const { return at[e] + p * 3 * nb[v] + s; }
};

BlockPattern block_pattern(const int64_t* ps, int64_t M, int64_t V, const torch::TensorOptions& index_options) {
  BlockPattern P;
  // each vertex's slots 4 m + a (stencil m's corner a is the vertex), in stencil order
  std::vector<int64_t> start(V + 1, 0);
  for (int64_t q = 0; q < 4 * M; ++q)
    if (ps[q] < V) ++start[ps[q] + 1];
  for (int64_t v = 0; v < V; ++v) start[v + 1] += start[v];
  std::vector<int64_t> slot(start[V]);
  {
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (int64_t q = 0; q < 4 * M; ++q)
      if (ps[q] < V) slot[fill[ps[q]]++] = q;
  }
  // each row's distinct columns: the vertices < V of its slots' stencils (few per row), by a mark per vertex
  P.nb.assign(V, 0);
  at::parallel_for(0, V, 256, [&](int64_t v0, int64_t v1) {
    std::vector<int64_t> mark(V, -1);
    for (int64_t v = v0; v < v1; ++v) {
      int64_t k = 0;
      for (int64_t i = start[v]; i < start[v + 1]; ++i) {
        const int64_t* s = ps + 4 * (slot[i] / 4);
        for (int b = 0; b < 4; ++b)
          if (s[b] < V && mark[s[b]] != v) { mark[s[b]] = v; ++k; }
      }
      P.nb[v] = k;
    }
  });
  P.first.assign(V + 1, 0);
  for (int64_t v = 0; v < V; ++v) P.first[v + 1] = P.first[v] + P.nb[v];
  P.U = P.first[V];
  P.at.assign(16 * M, -1);
  P.indices = torch::empty({2, 9 * P.U}, index_options);
  int64_t* prow = P.indices.data_ptr<int64_t>();
  int64_t* pcol = prow + 9 * P.U;
  at::parallel_for(0, V, 256, [&](int64_t v0, int64_t v1) {
    std::vector<int64_t> mark(V, -1), pos(V, 0), cols;
    for (int64_t v = v0; v < v1; ++v) {
      cols.clear();
      for (int64_t i = start[v]; i < start[v + 1]; ++i) {
        const int64_t* s = ps + 4 * (slot[i] / 4);
        for (int b = 0; b < 4; ++b)
          if (s[b] < V && mark[s[b]] != v) { mark[s[b]] = v; cols.push_back(s[b]); }
      }
      std::sort(cols.begin(), cols.end());  // row-major: the columns in order
      const int64_t len = 3 * P.nb[v];
      for (size_t j = 0; j < cols.size(); ++j) {
        pos[cols[j]] = int64_t(j);
        for (int p = 0; p < 3; ++p)
          for (int s = 0; s < 3; ++s) {
            const int64_t i = 9 * P.first[v] + 3 * int64_t(j) + p * len + s;
            prow[i] = 3 * v + p; pcol[i] = 3 * cols[j] + s;
          }
      }
      for (int64_t i = start[v]; i < start[v + 1]; ++i) {
        const int64_t q = slot[i], m = q / 4, a = q % 4;
        const int64_t* s = ps + 4 * m;
        for (int b = 0; b < 4; ++b)
          if (s[b] < V) P.at[16 * m + 4 * a + b] = 9 * P.first[v] + 3 * pos[s[b]];
      }
    }
  });
  return P;
}

void check_block_args(const char* op, const torch::Tensor& stencils, int64_t V) {
  ck::require(V >= 0, op, "V must be >= 0, got ", V);
  ck::check_range(op, "stencils", stencils, 0, std::numeric_limits<int64_t>::max(), "vertex indices");
}

}  // namespace

std::tuple<torch::Tensor, torch::Tensor> contact_stencil_sum(torch::Tensor stencils, torch::Tensor H, int64_t V) {
  const char* op = "contact_stencil_sum";
  ck::require(H.device().is_cpu() && H.dim() == 3 && H.size(1) == 12 && H.size(2) == 12 && H.is_floating_point(), op,
              "H must be a CPU (M, 12, 12) float tensor, got ", ck::shape_str(H));
  stencils = ck::index_tensor(op, "stencils", stencils, H.device(), 4);
  ck::require(stencils.size(0) == H.size(0), op, "stencils and H must have one row per stencil");
  check_block_args(op, stencils, V);
  H = H.contiguous();
  const int64_t M = stencils.size(0);
  const int64_t* ps = stencils.data_ptr<int64_t>();
  BlockPattern P = block_pattern(ps, M, V, stencils.options());
  auto val = torch::zeros({9 * P.U}, H.options());
  AT_DISPATCH_FLOATING_TYPES(H.scalar_type(), "contact", [&] {
    const scalar_t* ph = H.data_ptr<scalar_t>();
    scalar_t* pv = val.data_ptr<scalar_t>();
    for (int64_t m = 0; m < M; ++m)  // in stencil order: the same sums for any number of threads
      for (int a = 0; a < 4; ++a)
        for (int b = 0; b < 4; ++b) {
          const int64_t e = 16 * m + 4 * a + b;
          if (P.at[e] < 0) continue;
          for (int p = 0; p < 3; ++p)
            for (int s = 0; s < 3; ++s)
              pv[P.value_index(ps[4 * m + a], e, p, s)] += ph[144 * m + 12 * (3 * a + p) + 3 * b + s];
        }
  });
  return {P.indices, val};
}

std::tuple<torch::Tensor, torch::Tensor> contact_hessian_sum(torch::Tensor x, torch::Tensor stencils,
                                                             torch::Tensor types, torch::Tensor eps, double dhat_sq,
                                                             double kappa, int64_t mode, int64_t V,
                                                             torch::Tensor f_stencils, torch::Tensor f_w,
                                                             torch::Tensor f_H) {
  const char* op = "contact_hessian_sum";
  auto [st, ty, ep] = barrier_args(op, x, stencils, types, eps, dhat_sq, kappa, 2, mode);
  check_block_args(op, st, V);
  x = x.contiguous();
  const int64_t N = st.size(0);
  // the friction pairs (none: zero rows): their stencils follow the barrier's in the pattern and in the sums
  f_stencils = ck::index_tensor(op, "f_stencils", f_stencils, x.device(), 4);
  ck::check_range(op, "f_stencils", f_stencils, 0, x.size(0), "x has n = " + std::to_string(x.size(0)) + " points");
  const int64_t M = f_stencils.size(0);
  ck::require(f_w.dim() == 2 && f_w.size(0) == M && f_w.size(1) == 4 && f_w.device().is_cpu() &&
                  f_w.is_floating_point(), op, "f_w must be a CPU float (M, 4) tensor of the friction stencils' "
              "weights, M = ", M, ", got ", ck::shape_str(f_w));
  ck::require(f_H.dim() == 3 && f_H.size(0) == M && f_H.size(1) == 3 && f_H.size(2) == 3 && f_H.device().is_cpu() &&
                  f_H.is_floating_point(), op, "f_H must be a CPU float (M, 3, 3) tensor of the friction pairs' "
              "point blocks, M = ", M, ", got ", ck::shape_str(f_H));
  f_w = f_w.to(x.scalar_type()).contiguous();
  f_H = f_H.to(x.scalar_type()).contiguous();
  torch::Tensor all = M ? torch::cat({st, f_stencils}) : st;
  const int64_t* ps = all.data_ptr<int64_t>();
  BlockPattern P = block_pattern(ps, N + M, V, st.options());
  auto val = torch::zeros({9 * P.U}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* px = x.data_ptr<T>();
    const int64_t* pt = ty.data_ptr<int64_t>();
    const T* pe = ep.numel() ? ep.data_ptr<T>() : nullptr;
    T* pv = val.data_ptr<T>();
    // waves of one chunk per thread: the chunks' pairs computed and projected in parallel, then added to the sum
    // in pair order (the same sums for any number of threads)
    const int64_t chunks = (N + kPairChunk - 1) / kPairChunk;
    const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), chunks));
    std::vector<std::vector<cm::PairTerms<T>>> terms(threads, std::vector<cm::PairTerms<T>>(kPairChunk));
    for (int64_t wave = 0; wave < chunks; wave += threads) {
      const int64_t nc = std::min(threads, chunks - wave);
      at::parallel_for(0, nc, 1, [&](int64_t c0, int64_t c1) {
        for (int64_t c = c0; c < c1; ++c)
          pair_chunk<T>(px, ps, pt, pe, T(dhat_sq), T(kappa), 2, mode, (wave + c) * kPairChunk,
                        std::min<int64_t>(kPairChunk, N - (wave + c) * kPairChunk), terms[c], nullptr, nullptr,
                        nullptr);
      });
      for (int64_t c = 0; c < nc; ++c) {
        const int64_t base = (wave + c) * kPairChunk, n = std::min<int64_t>(kPairChunk, N - base);
        for (int64_t i = 0; i < n; ++i) {
          const auto& q = terms[c][i];
          const int64_t m = base + i, k = 3 * q.r;
          for (int a = 0; a < 4; ++a)
            for (int b = 0; b < 4; ++b) {
              const int64_t e = 16 * m + 4 * a + b;
              if (P.at[e] < 0) continue;
              T blk[3][3] = {};
              for (int ra = 0; ra < q.r; ++ra) {
                if (q.C[ra][a] == 0) continue;
                for (int rb = 0; rb < q.r; ++rb) {
                  if (q.C[rb][b] == 0) continue;
                  const T w = T(q.C[ra][a] * q.C[rb][b]);
                  for (int p = 0; p < 3; ++p)
                    for (int s = 0; s < 3; ++s) blk[p][s] += w * q.H[k * (3 * ra + p) + 3 * rb + s];
                }
              }
              for (int p = 0; p < 3; ++p)
                for (int s = 0; s < 3; ++s) pv[P.value_index(ps[4 * m + a], e, p, s)] += blk[p][s];
            }
        }
      }
    }
    // the friction pairs, in order after the barrier's: block (a, b) of pair m is w_a w_b H_m
    const T* pw = M ? f_w.data_ptr<T>() : nullptr;
    const T* pf = M ? f_H.data_ptr<T>() : nullptr;
    for (int64_t i = 0; i < M; ++i) {
      const int64_t m = N + i;
      const T* w = pw + 4 * i;
      const T* h = pf + 9 * i;
      for (int a = 0; a < 4; ++a)
        for (int b = 0; b < 4; ++b) {
          const int64_t e = 16 * m + 4 * a + b;
          if (P.at[e] < 0) continue;
          const T wab = w[a] * w[b];
          for (int p = 0; p < 3; ++p)
            for (int s = 0; s < 3; ++s) pv[P.value_index(ps[4 * m + a], e, p, s)] += wab * h[3 * p + s];
        }
    }
  });
  return {P.indices, val};
}

}  // namespace cpu
}  // namespace torchbend
