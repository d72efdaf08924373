// The sums of the contact pairs' Hessians into the (3V, 3V) matrix (CPU extension; torchbend.sim.self_contact uses
// them, the eager stencil sum there is the reference):
//   contact_stencil_sum the sum of given 12x12 stencil blocks
//   contact_hessian_sum the pairs' (projected) Hessians summed without the blocks (one pair of each group that is
//                       the same contact, counted as many times), and the friction pairs' (w w^T (x) their point
//                       block); its pattern holds no block of a corner a pair's energy does not depend on (a
//                       point-edge pair's fourth corner, a point-point pair's other two)
#include <algorithm>
#include <cstdint>
#include <limits>
#include <vector>

#include "cpu_contact.h"
#include "cpu_contact_pairs.h"

namespace torchbend {
namespace cpu {

namespace ck = torchbend::checks;
namespace cm = torchbend::contact;

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
  const int64_t* ps = st.data_ptr<int64_t>();
  const int64_t* pfs = f_stencils.data_ptr<int64_t>();
  torch::Tensor indices;
  torch::Tensor val;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "contact", [&] {
    using T = scalar_t;
    const T* px = x.data_ptr<T>();
    const int64_t* pt = ty.data_ptr<int64_t>();
    const T* pe = ep.numel() ? ep.data_ptr<T>() : nullptr;
    // one pair of each group that is the same contact (contact_groups), its Hessian counted as many times; waves of
    // one chunk per thread: the chunks' pairs computed and projected in parallel, then added to the sum in pair
    // order (the same sums for any number of threads)
    std::vector<int64_t> reps, count;
    std::vector<unsigned char> used;
    contact_groups<T>(px, ps, pt, pe, N, x.size(0), reps, count, used);
    const int64_t R = int64_t(reps.size());
    // the pattern's stencils: the groups' (a corner the energy does not depend on left out, as a body's vertex
    // is: index >= V), then the friction pairs'
    const GroupPairs<T> g = group_pairs(ps, pt, pe, reps);
    std::vector<int64_t> sp(4 * (R + M));
    for (int64_t q = 0; q < 4 * R; ++q) sp[q] = used[q] ? g.st[q] : std::numeric_limits<int64_t>::max();
    std::copy(pfs, pfs + 4 * M, sp.begin() + 4 * R);
    BlockPattern P = block_pattern(sp.data(), R + M, V, st.options());
    indices = P.indices;
    val = torch::zeros({9 * P.U}, x.options());
    T* pv = val.data_ptr<T>();
    const int64_t chunks = (R + kPairChunk - 1) / kPairChunk;
    const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), chunks));
    std::vector<std::vector<cm::PairTerms<T>>> terms(threads, std::vector<cm::PairTerms<T>>(kPairChunk));
    for (int64_t wave = 0; wave < chunks; wave += threads) {
      const int64_t nc = std::min(threads, chunks - wave);
      at::parallel_for(0, nc, 1, [&](int64_t c0, int64_t c1) {
        for (int64_t c = c0; c < c1; ++c)
          pair_chunk<T>(px, g.st.data(), g.ty.data(), pe ? g.eps.data() : nullptr, T(dhat_sq), T(kappa), 2, mode,
                        (wave + c) * kPairChunk, std::min<int64_t>(kPairChunk, R - (wave + c) * kPairChunk), terms[c],
                        nullptr, nullptr, nullptr);
      });
      for (int64_t c = 0; c < nc; ++c) {
        const int64_t base = (wave + c) * kPairChunk, n = std::min<int64_t>(kPairChunk, R - base);
        for (int64_t i = 0; i < n; ++i) {
          const auto& q = terms[c][i];
          const int64_t m = base + i;
          const T times = T(count[base + i]);
          alignas(64) T H12[144];  // the pair's 12x12 block, then its 16 3x3 blocks added row by row
          cm::expand_hessian(q.C, q.r, q.H, H12);
          if (count[base + i] > 1)
            for (int e = 0; e < 144; ++e) H12[e] *= times;
          for (int a = 0; a < 4; ++a) {
            const int64_t v = sp[4 * m + a];
            if (v >= V) continue;
            const int64_t len = 3 * P.nb[v];
            for (int b = 0; b < 4; ++b) {
              const int64_t at = P.at[16 * m + 4 * a + b];
              if (at < 0) continue;
              T* dst = pv + at;
              const T* src = H12 + 12 * 3 * a + 3 * b;
              for (int p = 0; p < 3; ++p)
                for (int s = 0; s < 3; ++s) dst[p * len + s] += src[12 * p + s];
            }
          }
        }
      }
    }
    // the friction pairs, in order after the barrier's: block (a, b) of pair m is w_a w_b H_m
    const T* pw = M ? f_w.data_ptr<T>() : nullptr;
    const T* pf = M ? f_H.data_ptr<T>() : nullptr;
    for (int64_t i = 0; i < M; ++i) {
      const int64_t m = R + i;
      const T* w = pw + 4 * i;
      const T* h = pf + 9 * i;
      for (int a = 0; a < 4; ++a)
        for (int b = 0; b < 4; ++b) {
          const int64_t e = 16 * m + 4 * a + b;
          if (P.at[e] < 0) continue;
          const T wab = w[a] * w[b];
          for (int p = 0; p < 3; ++p)
            for (int s = 0; s < 3; ++s) pv[P.value_index(sp[4 * m + a], e, p, s)] += wab * h[3 * p + s];
        }
    }
  });
  return {indices, val};
}


}  // namespace cpu
}  // namespace torchbend
