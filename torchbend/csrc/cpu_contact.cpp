// The compiled contact operators of the CPU extension (torchbend.sim.self_contact uses them; the eager code there
// is the reference):
//   contact_box_pairs   the broad phase: pairs of overlapping padded boxes by a uniform grid whose cells are
//                       hashed (cost: the boxes and the pairs), without pairs that share a vertex
//   contact_distances   the distance type and squared distance of point-triangle or edge-edge stencils
//   contact_barrier     the pairs' barrier energies, gradients and (PSD-projected) Hessians
//   contact_stencil_csr the sum of 12x12 stencil blocks as a CSR matrix
// The per-stencil mathematics is contact_math.h (shared with a CUDA driver).
#include <algorithm>
#include <cstdint>
#include <vector>

#include "contact_math.h"
#include "cpu_contact.h"
#include "cpu_jacobi.h"
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {

namespace ck = torchbend::checks;
namespace cm = torchbend::contact;

// ---- broad phase ---------------------------------------------------------------------------------
namespace {

// open-addressing map from a cell key to the range [start, end) of the boxes filed under it
struct CellMap {
  std::vector<int64_t> keys;
  std::vector<int64_t> start, end;
  uint64_t mask = 0;
  static uint64_t mix(int64_t k) {
    uint64_t z = uint64_t(k) + 0x9e3779b97f4a7c15ull;
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  void init(int64_t n) {
    uint64_t cap = 16;
    while (cap < uint64_t(2 * n + 1)) cap <<= 1;
    mask = cap - 1;
    keys.assign(cap, INT64_MIN);
    start.assign(cap, 0);
    end.assign(cap, 0);
  }
  int64_t slot(int64_t k) const {
    uint64_t s = mix(k) & mask;
    while (keys[s] != INT64_MIN && keys[s] != k) s = (s + 1) & mask;
    return int64_t(s);
  }
};

template <typename T>
void box_pairs_impl(const T* loA, const T* hiA, int64_t nA, const T* loB, const T* hiB, int64_t nB, T pad, bool upper,
                    const int64_t* idsA, int64_t kA, const int64_t* idsB, int64_t kB, std::vector<int64_t>& out) {
  T ext = 0, org[3];
  for (int i = 0; i < 3; ++i) org[i] = std::numeric_limits<T>::max();
  for (int64_t a = 0; a < nA; ++a)
    for (int i = 0; i < 3; ++i) { ext = std::max(ext, hiA[3 * a + i] - loA[3 * a + i]); org[i] = std::min(org[i], loA[3 * a + i]); }
  for (int64_t b = 0; b < nB; ++b)
    for (int i = 0; i < 3; ++i) { ext = std::max(ext, hiB[3 * b + i] - loB[3 * b + i]); org[i] = std::min(org[i], loB[3 * b + i]); }
  double h = double(ext) + 2 * double(pad);
  if (!(h > 0)) h = 1;
  auto cell = [&](const T* lo, int64_t c[3]) {
    for (int i = 0; i < 3; ++i) c[i] = int64_t(std::floor((double(lo[i]) - double(org[i])) / h));
  };
  // the cells' keys: (c + 1) in [0, 2^21) per axis (a grid of more cells per axis falls back to hashing
  // the wrapped coordinates: equal keys then only mean more candidates, never lost ones)
  auto key = [](int64_t cx, int64_t cy, int64_t cz) {
    return ((cx + 1) & 0x1fffff) << 42 | ((cy + 1) & 0x1fffff) << 21 | ((cz + 1) & 0x1fffff);
  };
  std::vector<int64_t> kb(nB), order(nB);
  for (int64_t b = 0; b < nB; ++b) {
    int64_t c[3];
    cell(loB + 3 * b, c);
    kb[b] = key(c[0], c[1], c[2]);
    order[b] = b;
  }
  std::sort(order.begin(), order.end(), [&](int64_t u, int64_t v) { return kb[u] < kb[v] || (kb[u] == kb[v] && u < v); });
  CellMap map;
  map.init(nB);
  for (int64_t i = 0; i < nB;) {
    int64_t j = i, k = kb[order[i]];
    while (j < nB && kb[order[j]] == k) ++j;
    int64_t s = map.slot(k);
    map.keys[s] = k; map.start[s] = i; map.end[s] = j;
    i = j;
  }
  const T two_pad = 2 * pad;
  const int nt = std::max(1, std::min<int>(at::get_num_threads(), int((nA + 1023) / 1024)));
  std::vector<std::vector<int64_t>> parts(nt);
  at::parallel_for(0, nt, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      auto& o = parts[t];
      int64_t a0 = nA * t / nt, a1 = nA * (t + 1) / nt;
      std::vector<int64_t> hits;
      for (int64_t a = a0; a < a1; ++a) {
        int64_t c[3];
        cell(loA + 3 * a, c);
        hits.clear();
        for (int dx = -1; dx <= 1; ++dx)
          for (int dy = -1; dy <= 1; ++dy)
            for (int dz = -1; dz <= 1; ++dz) {
              int64_t s = map.slot(key(c[0] + dx, c[1] + dy, c[2] + dz));
              if (map.keys[s] == INT64_MIN) continue;
              for (int64_t q = map.start[s]; q < map.end[s]; ++q) {
                int64_t b = order[q];
                if (upper && b <= a) continue;
                const T *la = loA + 3 * a, *ha = hiA + 3 * a, *lb = loB + 3 * b, *hb = hiB + 3 * b;
                if (!(la[0] <= hb[0] + two_pad && ha[0] + two_pad >= lb[0] && la[1] <= hb[1] + two_pad &&
                      ha[1] + two_pad >= lb[1] && la[2] <= hb[2] + two_pad && ha[2] + two_pad >= lb[2]))
                  continue;
                bool shared = false;
                for (int64_t i = 0; i < kA && !shared; ++i)
                  for (int64_t j = 0; j < kB; ++j)
                    if (idsA[kA * a + i] == idsB[kB * b + j]) { shared = true; break; }
                if (!shared) hits.push_back(b);
              }
            }
        std::sort(hits.begin(), hits.end());  // a box's partners in order (the same list for any grid)
        for (int64_t b : hits) { o.push_back(a); o.push_back(b); }
      }
    }
  });
  size_t total = 0;
  for (auto& p : parts) total += p.size();
  out.reserve(total);
  for (auto& p : parts) out.insert(out.end(), p.begin(), p.end());
}

}  // namespace

torch::Tensor contact_box_pairs(torch::Tensor lo_a, torch::Tensor hi_a, torch::Tensor lo_b, torch::Tensor hi_b,
                                double pad, bool upper, torch::Tensor ids_a, torch::Tensor ids_b) {
  const char* op = "contact_box_pairs";
  for (const auto* t : {&lo_a, &hi_a, &lo_b, &hi_b})
    ck::require(t->device().is_cpu() && t->dim() == 2 && t->size(1) == 3 && t->is_floating_point(), op,
                "the boxes' corners must be CPU (n, 3) float tensors, got ", ck::shape_str(*t));
  ck::require(lo_a.sizes() == hi_a.sizes() && lo_b.sizes() == hi_b.sizes(), op, "lower and upper corners differ in shape");
  ck::require(lo_a.scalar_type() == lo_b.scalar_type() && hi_a.scalar_type() == lo_a.scalar_type() &&
              hi_b.scalar_type() == lo_a.scalar_type(), op, "the boxes' corners must share one dtype");
  ck::require(pad >= 0 && std::isfinite(pad), op, "pad must be finite and >= 0, got ", pad);
  const int64_t nA = lo_a.size(0), nB = lo_b.size(0);
  const bool ids = ids_a.numel() > 0 || ids_b.numel() > 0;
  if (ids) {
    ids_a = ck::index_tensor(op, "ids_a", ids_a, lo_a.device());
    ids_b = ck::index_tensor(op, "ids_b", ids_b, lo_a.device());
    ck::require(ids_a.dim() == 2 && ids_a.size(0) == nA && ids_b.dim() == 2 && ids_b.size(0) == nB, op,
                "ids_a and ids_b must have one row per box, got ", ck::shape_str(ids_a), " and ", ck::shape_str(ids_b));
  }
  ck::require(!upper || nA == nB, op, "upper pairs need one set of boxes (A = B)");
  lo_a = lo_a.contiguous(); hi_a = hi_a.contiguous(); lo_b = lo_b.contiguous(); hi_b = hi_b.contiguous();
  ck::require(finite_status(lo_a, 1) == 0 && finite_status(hi_a, 1) == 0 && finite_status(lo_b, 1) == 0 &&
              finite_status(hi_b, 1) == 0, op, "the boxes' corners must be finite");
  std::vector<int64_t> pairs;
  if (nA > 0 && nB > 0) {
    AT_DISPATCH_FLOATING_TYPES(lo_a.scalar_type(), "contact", [&] {
      box_pairs_impl<scalar_t>(lo_a.data_ptr<scalar_t>(), hi_a.data_ptr<scalar_t>(), nA, lo_b.data_ptr<scalar_t>(),
                               hi_b.data_ptr<scalar_t>(), nB, scalar_t(pad), upper,
                               ids ? ids_a.data_ptr<int64_t>() : nullptr, ids ? ids_a.size(1) : 0,
                               ids ? ids_b.data_ptr<int64_t>() : nullptr, ids ? ids_b.size(1) : 0, pairs);
    });
  }
  auto out = torch::empty({int64_t(pairs.size() / 2), 2}, lo_a.options().dtype(torch::kLong));
  std::copy(pairs.begin(), pairs.end(), out.data_ptr<int64_t>());
  return out;
}

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
        int t = edge_edge ? cm::edge_edge_type(X[0], X[1], X[2], X[3], scalar_t(1e-10))
                          : cm::point_triangle_type(X[0], X[1], X[2], X[3]);
        int formula;
        signed char C[3][4];
        int r = cm::type_rows(t, &formula, C);
        scalar_t y[9];
        cm::reduce(C, r, X, y);
        pt[n] = t;
        pd[n] = cm::typed_derivs<scalar_t>(formula, y, nullptr, nullptr);
      }
    });
  });
  return {types, D};
}

// ---- the pairs' barrier: energies, gradients, Hessians ------------------------------------------------
namespace {

constexpr int kPairChunk = 256;

// project the pairs `idx` (all with 3 r reduced coordinates) of a chunk, W at a time, and write their 12x12 blocks
template <typename T, int N>
void project_group(const std::vector<cm::PairTerms<T>>& terms, const std::vector<int>& idx, int64_t base, bool abs_mode,
                   T* H) {
  constexpr int r = N / 3;
  for (size_t t0 = 0; t0 < idx.size(); t0 += W) {
    const int nl = int(std::min<size_t>(W, idx.size() - t0));
    alignas(64) T A[N][N][W];
    T Ri[W][3][3];
    for (int l = 0; l < W; ++l) {
      if (l >= nl) {
        for (int i = 0; i < N; ++i) for (int j = 0; j < N; ++j) A[i][j][l] = 0;
        continue;
      }
      const auto& p = terms[idx[t0 + l]];
      T R[3][3], M[81];
      cm::gram_cholesky(p.C, r, R, Ri[l]);
      cm::congruence(R, r, p.H, M);
      for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) A[i][j][l] = T(0.5) * (M[N * i + j] + M[N * j + i]);
    }
    jacobi_project<T, N>(A, abs_mode);
    for (int l = 0; l < nl; ++l) {
      const auto& p = terms[idx[t0 + l]];
      T M[81], P[81];
      for (int i = 0; i < N; ++i) for (int j = 0; j < N; ++j) M[N * i + j] = A[i][j][l];
      cm::congruence(Ri[l], r, M, P);
      cm::expand_hessian(p.C, r, P, H + 144 * (base + idx[t0 + l]));
    }
  }
}

}  // namespace

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> contact_barrier(torch::Tensor x, torch::Tensor stencils,
                                                                        torch::Tensor types, torch::Tensor eps,
                                                                        double dhat_sq, double kappa, int64_t want,
                                                                        int64_t mode) {
  const char* op = "contact_barrier";
  stencils = stencil_tensor(op, x, stencils);
  const int64_t N = stencils.size(0);
  types = ck::index_tensor(op, "types", types, x.device());
  ck::require(types.dim() == 1 && types.size(0) == N, op, "types must have one entry per stencil, got ",
              ck::shape_str(types));
  ck::check_range(op, "types", types, 0, cm::NUM_TYPES, "the distance types");
  const bool mollified = eps.numel() > 0;
  if (mollified) {
    ck::require(eps.dim() == 1 && eps.size(0) == N && eps.device().is_cpu(), op,
                "eps must be empty or hold one threshold per stencil, got ", ck::shape_str(eps));
    eps = eps.to(x.scalar_type()).contiguous();
  }
  ck::require(dhat_sq > 0 && std::isfinite(dhat_sq) && kappa >= 0 && std::isfinite(kappa), op,
              "dhat_sq must be finite and > 0 and kappa finite and >= 0, got ", dhat_sq, " and ", kappa);
  ck::require(want >= 0 && want <= 2 && mode >= -1 && mode <= 1, op,
              "want must be 0 (energy), 1 (+ gradient) or 2 (+ Hessian) and mode -1 (none), 0 (clamp) or 1 (abs)");
  x = x.contiguous();
  auto E = torch::empty({N}, x.options());
  auto G = torch::empty({want >= 1 ? N : 0, 12}, x.options());
  auto H = torch::empty({want >= 2 ? N : 0, 12, 12}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* px = x.data_ptr<T>();
    const int64_t* ps = stencils.data_ptr<int64_t>();
    const int64_t* pt = types.data_ptr<int64_t>();
    const T* pe = mollified ? eps.data_ptr<T>() : nullptr;
    T* pE = E.data_ptr<T>();
    T* pG = want >= 1 ? G.data_ptr<T>() : nullptr;
    T* pH = want >= 2 ? H.data_ptr<T>() : nullptr;
    const int64_t chunks = (N + kPairChunk - 1) / kPairChunk;
    at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
      std::vector<cm::PairTerms<T>> terms(kPairChunk);
      std::vector<int> by_r[3];
      for (int64_t c = c0; c < c1; ++c) {
        const int64_t base = c * kPairChunk, n = std::min<int64_t>(kPairChunk, N - base);
        for (auto& v : by_r) v.clear();
        for (int64_t i = 0; i < n; ++i) {
          T X[4][3];
          gather(px, ps + 4 * (base + i), X);
          auto& p = terms[i];
          cm::pair_terms<T>(X, int(pt[base + i]), pe ? pe[base + i] : T(0), T(dhat_sq), T(kappa), int(want), &p);
          pE[base + i] = p.E;
          if (want >= 1) cm::expand_gradient(p.C, p.r, p.g, pG + 12 * (base + i));
          if (want >= 2) {
            if (mode < 0) cm::expand_hessian(p.C, p.r, p.H, pH + 144 * (base + i));
            else by_r[p.r - 1].push_back(int(i));
          }
        }
        if (want >= 2 && mode >= 0) {
          project_group<T, 3>(terms, by_r[0], base, mode == 1, pH);
          project_group<T, 6>(terms, by_r[1], base, mode == 1, pH);
          project_group<T, 9>(terms, by_r[2], base, mode == 1, pH);
        }
      }
    });
  });
  return {E, G, H};
}

// ---- the sum of stencil blocks -------------------------------------------------------------------------
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor> contact_stencil_csr(torch::Tensor stencils,
                                                                                           torch::Tensor H, int64_t V) {
  const char* op = "contact_stencil_csr";
  ck::require(H.device().is_cpu() && H.dim() == 3 && H.size(1) == 12 && H.size(2) == 12 && H.is_floating_point(), op,
              "H must be a CPU (M, 12, 12) float tensor, got ", ck::shape_str(H));
  stencils = ck::index_tensor(op, "stencils", stencils, H.device(), 4);
  ck::require(stencils.size(0) == H.size(0), op, "stencils and H must have one row per stencil");
  ck::require(V >= 0, op, "V must be >= 0");
  ck::check_range(op, "stencils", stencils, 0, std::numeric_limits<int64_t>::max(), "vertex indices");
  H = H.contiguous();
  const int64_t M = stencils.size(0);
  const int64_t* ps = stencils.data_ptr<int64_t>();
  // the entries (column vertex, 16 m + 4 a + b) of each block row vi < V (counting sort by vi)
  std::vector<int64_t> count(V + 1, 0);
  for (int64_t m = 0; m < M; ++m)
    for (int a = 0; a < 4; ++a)
      if (ps[4 * m + a] < V)
        for (int b = 0; b < 4; ++b) count[ps[4 * m + a] + 1] += ps[4 * m + b] < V;
  for (int64_t v = 0; v < V; ++v) count[v + 1] += count[v];
  std::vector<int64_t> fill(count.begin(), count.end() - 1);
  std::vector<std::pair<int64_t, int64_t>> entry(count[V]);
  for (int64_t m = 0; m < M; ++m)
    for (int a = 0; a < 4; ++a)
      if (ps[4 * m + a] < V)
        for (int b = 0; b < 4; ++b)
          if (ps[4 * m + b] < V) entry[fill[ps[4 * m + a]]++] = {ps[4 * m + b], 16 * m + 4 * a + b};
  // per block row: the entries sorted by (column vertex, stencil): the blocks of one vertex pair in stencil order
  std::vector<int64_t> nb(V, 0);
  at::parallel_for(0, V, 256, [&](int64_t v0, int64_t v1) {
    for (int64_t v = v0; v < v1; ++v) {
      auto b = entry.begin() + count[v], e = entry.begin() + count[v + 1];
      std::sort(b, e);
      int64_t k = 0, last = -1;
      for (auto it = b; it != e; ++it)
        if (it->first != last) { last = it->first; ++k; }
      nb[v] = k;
    }
  });
  std::vector<int64_t> first(V + 1, 0);  // the first block of each block row
  for (int64_t v = 0; v < V; ++v) first[v + 1] = first[v] + nb[v];
  const int64_t U = first[V];
  auto crow = torch::empty({3 * V + 1}, stencils.options());
  auto col = torch::empty({9 * U}, stencils.options());
  auto rows = torch::empty({9 * U}, stencils.options());
  auto val = torch::empty({9 * U}, H.options());
  int64_t* pc = crow.data_ptr<int64_t>();
  int64_t* pcol = col.data_ptr<int64_t>();
  int64_t* prow = rows.data_ptr<int64_t>();
  for (int64_t v = 0; v < V; ++v)
    for (int p = 0; p < 3; ++p) pc[3 * v + p] = 9 * first[v] + 3 * p * nb[v];
  pc[3 * V] = 9 * U;
  AT_DISPATCH_FLOATING_TYPES(H.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* ph = H.data_ptr<T>();
    T* pv = val.data_ptr<T>();
    at::parallel_for(0, V, 256, [&](int64_t v0, int64_t v1) {
      for (int64_t v = v0; v < v1; ++v) {
        int64_t j = -1, last = -1;
        const int64_t row = 9 * first[v], len = 3 * nb[v];
        for (int64_t q = count[v]; q < count[v + 1]; ++q) {
          const int64_t w = entry[q].first, e = entry[q].second;
          if (w != last) {
            last = w; ++j;
            for (int p = 0; p < 3; ++p)
              for (int s = 0; s < 3; ++s) {
                const int64_t at = row + p * len + 3 * j + s;
                pv[at] = 0; pcol[at] = 3 * w + s; prow[at] = 3 * v + p;
              }
          }
          const int64_t m = e >> 4, a = (e >> 2) & 3, b = e & 3;
          for (int p = 0; p < 3; ++p)
            for (int s = 0; s < 3; ++s) pv[row + p * len + 3 * j + s] += ph[144 * m + 12 * (3 * a + p) + 3 * b + s];
        }
      }
    });
  });
  return {crow, rows, col, val};
}

}  // namespace cpu
}  // namespace torchbend
