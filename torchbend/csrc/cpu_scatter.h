// Summation of per-hinge 12-vectors per vertex (the gradient and the products of cpu_first_order.cpp and
// cpu_second_order.cpp): blocks of consecutive hinges with dense accumulators, or a per-hinge buffer summed
// through the incidence lists.
#pragma once
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {

template <typename T>
static void gather_vertices(const T* w, const int64_t* ptr, const int64_t* idx, int64_t B, int64_t V, int64_t H, T* out) {
  at::parallel_for(0, B * V, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t bv = begin; bv < end; ++bv) {
      int64_t b = bv / V, v = bv - b * V;
      const T* wb = w + 12 * H * b;
      T s0 = 0, s1 = 0, s2 = 0;
      for (int64_t j = ptr[v]; j < ptr[v + 1]; ++j) {
        int64_t i = idx[j];
        const T* src = wb + 12 * (i >> 2) + 3 * (i & 3);
        s0 += src[0]; s1 += src[1]; s2 += src[2];
      }
      out[3 * bv] = s0; out[3 * bv + 1] = s1; out[3 * bv + 2] = s2;
    }
  });
}

// Scratch memory of the calling thread, kept between calls (up to kScratchKeep bytes): fresh memory
// page-faults on first touch, which costs about as much as the kernels' own work per hinge.
constexpr size_t kScratchKeep = size_t(64) << 20;

struct Scratch {
  torch::Tensor hold;  // a one-off allocation past kScratchKeep
  void* p = nullptr;
};

Scratch scratch(size_t bytes);

// Summation of per-hinge 12-vectors per vertex in blocks of consecutive hinges.  Block j (hinges
// [j S, j S + S) of one sample; S a function of H alone) computes its tiles and adds each hinge's
// four 3-vectors at once into its own dense accumulator over the block's vertex range [lo_j, lo_j + n_j)
// (cache resident: hinges of a mesh built by torchbend.topology are ordered so that a block touches a
// compact range of vertices); a second pass sums, per vertex, the accumulators of the blocks covering it
// in block order.  Every vertex's sum is thus one fixed expression (in hinge order within a block, in
// block order across blocks): bit-identical run to run and for any number of threads.  When the blocks'
// ranges are not compact (hinges in no particular order: the accumulators would outweigh a per-hinge
// buffer), the 12-vectors go to a (B, H, 12) buffer summed through the incidence lists (gather_vertices).
struct ScatterPlan {
  int64_t S = 0, nb = 0, total = 0;   // block size, blocks per sample, sum of the ranges
  std::vector<int64_t> lo, off;       // per block: first vertex, offset of its accumulator (vertices)
  int64_t vmin = 0, vmax = -1;        // the smallest and largest hinge index
  bool blocked = false;
};

ScatterPlan scatter_plan(const int64_t* hp, int64_t H, int64_t V);

// out (B, V, 3) = per vertex, the sum of the 12-vectors O that body(bh0, nl, bs, hs, O) computes for the
// tiles of hinges (see for_tiles; O[3 s + c][l]: component c of stencil slot s of lane l)
// The plan's pass over the hinge indices is their range check (before any work: checks::check_range names the
// first bad entry); the incidence lists, which only the unblocked path reads, are checked in full there.
template <typename T, int L, typename Body>
static void scatter_tiles(const char* op, const torch::Tensor& hinges, int64_t B, int64_t V, const int64_t* inc_ptr,
                          const int64_t* inc_idx, T* out, Body&& body) {
  const int64_t* hp = hinges.data_ptr<int64_t>();
  const int64_t H = hinges.size(0);
  ScatterPlan P = scatter_plan(hp, H, V);
  if (H && (P.vmin < 0 || P.vmax >= V))
    check_hinge_range(op, hinges, V);
  if (!P.blocked) {
    torchbend::checks::check_incidence_content(op, inc_ptr, inc_idx, hp, V, H);  // before any work
    torch::Tensor buf = torch::empty({B, H, 12}, c10::CppTypeToScalarType<T>::value);
    T* bp = buf.data_ptr<T>();
    for_tiles<L>(B, H, [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs) {
      alignas(64) T O[12][L];
      body(bh0, nl, bs, hs, O);
      store_rows<T, L>(O, nl, bp + 12 * bh0);
    });
    gather_vertices<T>(bp, inc_ptr, inc_idx, B, V, H, out);
    return;
  }
  Scratch sc = scratch(sizeof(T) * 3 * size_t(B * P.total));
  T* part = static_cast<T*>(sc.p);
  at::parallel_for(0, B * P.nb, 1, [&](int64_t begin, int64_t end) {
    int64_t bs[L], hs[L];
    alignas(64) T O[12][L];
    for (int64_t blk = begin; blk < end; ++blk) {
      int64_t b = blk / P.nb, j = blk - b * P.nb, lo = P.lo[j];
      T* acc = part + 3 * (b * P.total + P.off[j]);
      std::fill(acc, acc + 3 * (P.off[j + 1] - P.off[j]), T(0));
      int64_t h1 = std::min(H, (j + 1) * P.S);
      for (int64_t h0 = j * P.S; h0 < h1; h0 += L) {
        int nl = int(std::min<int64_t>(L, h1 - h0));
        for (int l = 0; l < nl; ++l) { bs[l] = b; hs[l] = h0 + l; }
        body(b * H + h0, nl, bs, hs, O);
        for (int l = 0; l < nl; ++l) {
          const int64_t* q = hp + 4 * (h0 + l);
          for (int s = 0; s < 4; ++s) {
            T* a = acc + 3 * (q[s] - lo);
            a[0] += O[3 * s][l]; a[1] += O[3 * s + 1][l]; a[2] += O[3 * s + 2][l];
          }
        }
      }
    }
  });
  constexpr int64_t C = 2048;  // vertices per chunk of the second pass
  int64_t nc = (V + C - 1) / C;
  at::parallel_for(0, B * nc, 1, [&](int64_t begin, int64_t end) {
    for (int64_t bc = begin; bc < end; ++bc) {
      int64_t b = bc / nc, c0 = (bc - b * nc) * C, c1 = std::min(V, c0 + C);
      T* o = out + 3 * (b * V + c0);
      std::fill(o, o + 3 * (c1 - c0), T(0));
      for (int64_t j = 0; j < P.nb; ++j) {
        int64_t lo = P.lo[j], v0 = std::max(c0, lo), v1 = std::min(c1, lo + P.off[j + 1] - P.off[j]);
        if (v0 >= v1) continue;
        const T* src = part + 3 * (b * P.total + P.off[j] + (v0 - lo));
        T* dst = out + 3 * (b * V + v0);
        for (int64_t i = 0; i < 3 * (v1 - v0); ++i) dst[i] += src[i];
      }
    }
  });
}

}  // namespace cpu
}  // namespace torchbend
