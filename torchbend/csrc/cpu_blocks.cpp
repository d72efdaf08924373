// The per-hinge 12x12 Hessian blocks (bending_hessians).
#include "cpu_ops.h"
#include "cpu_tiles.h"

namespace torchbend {
namespace cpu {
// ----------------------------------------------------------------------------------------------
// Per-hinge 12x12 blocks: gather, angle, psi' and psi'' (psi_lane, vectorized across the lanes of a tile
// like the operations above), the closed-form blocks (block_tile) and their output.  A block is written
// once and not read again here, so it goes out with streaming stores (no read-for-ownership of the output
// lines).  For a full tile with AVX (AVX2 and AVX-512 machines alike), the tile is completed in place across
// its lanes (mirrored lower triangle, B terms: complete_tile) and transposed in registers, each lane's
// consecutive entries one aligned streaming store (stream_tile: 8 entries a store with AVX-512 (float64) or
// AVX (float32), 4 with AVX (float64); every block of a 64-byte aligned output starts 64-byte aligned,
// 1152 = 18 x 64 and 576 = 9 x 64 bytes); elsewhere (a partial tile, an unaligned out= buffer) block_lane
// copies lane by lane (write_tile).  Both give the same values: the same operations on the same numbers,
// only the copies differ.  (Until the float64 AVX path, AVX2 machines copied float64 blocks lane by lane: on a
// Zen 3 EPYC, out= buffers, min over calls, 202-215 ns a hinge at 1e4 hinges against 145-164 since;
// benchmarks/results/blocks_avx2_stream_amd_zen3_2026-12-07.txt.)

template <typename T> static inline void complete_tile(Blocks<T, W>& b) {
  for (int r = 1; r < 12; ++r)
    for (int c = 0; c < r; ++c) TB_LANES(W) b.O[12 * r + c][l] = b.O[12 * c + r][l];
  for (int p = 0; p < 3; ++p)
    for (int q = 0; q < 3; ++q) TB_LANES(W) {
      T B = b.Bm[p][q][l];
      b.O[12 * p + q][l] -= B;
      b.O[12 * p + 3 + q][l] += B;
      b.O[12 * (3 + q) + p][l] += B;
      b.O[12 * (3 + p) + 3 + q][l] -= B;
    }
}

// whether stream_tile is compiled for T
template <typename T> constexpr bool tile_streams() {
#if defined(__AVX__)
  return std::is_same<T, double>::value || std::is_same<T, float>::value;
#else
  return false;
#endif
}

// the completed blocks of the 8 lanes of a tile to out + 144 l (64-byte aligned), 8 entries at a time: rows r of 8
// entries (entry e of lane l: src[8 l + e]) transposed in registers, pairs within 128-bit lanes (unpack) and then
// the 128-bit lanes (two steps; their order differs between the two widths), each output row one streaming store
// (AVX-512); with AVX alone, 4 lanes at a time
static inline void stream_tile(const Blocks<double, W>& b, double* out) {
#if defined(__AVX512F__)
  for (int j = 0; j < 18; ++j) {
    const double* src = &b.O[8 * j][0];
    __m512d r[8], t[8], u[8];
    for (int i = 0; i < 8; ++i) r[i] = _mm512_loadu_pd(src + 8 * i);
    for (int i = 0; i < 8; i += 2) { t[i] = _mm512_unpacklo_pd(r[i], r[i + 1]); t[i + 1] = _mm512_unpackhi_pd(r[i], r[i + 1]); }
    for (int h = 0; h < 8; h += 4) {
      u[h] = _mm512_shuffle_f64x2(t[h], t[h + 2], 0x88); u[h + 1] = _mm512_shuffle_f64x2(t[h + 1], t[h + 3], 0x88);
      u[h + 2] = _mm512_shuffle_f64x2(t[h], t[h + 2], 0xdd); u[h + 3] = _mm512_shuffle_f64x2(t[h + 1], t[h + 3], 0xdd);
    }
    double* dst = out + 8 * j;
    for (int i = 0; i < 4; ++i) {
      _mm512_stream_pd(dst + 144 * i, _mm512_shuffle_f64x2(u[i], u[i + 4], 0x88));
      _mm512_stream_pd(dst + 144 * (i + 4), _mm512_shuffle_f64x2(u[i], u[i + 4], 0xdd));
    }
  }
#elif defined(__AVX__)
  // 8 entries by 4 lanes at a time: rows r[i] = entry 8 j + i of lanes h..h+3, transposed as two 4x4 blocks (pairs
  // within the 128-bit halves, then the halves); each lane's 8 entries, one 64-byte line of its block, go out as two
  // 32-byte streaming stores in a row, so that every line is whole in its write-combining buffer before the next
  // (four entries a lane across all the lanes first left 8 lines half-written at a time: fresh 1e5-hinge
  // outputs then took up to 2.4x as long)
  for (int j = 0; j < 18; ++j)
    for (int h = 0; h < W; h += 4) {
      __m256d lo[4], hi[4];
      for (int half = 0; half < 2; ++half) {
        __m256d r[4], t[4];
        for (int i = 0; i < 4; ++i) r[i] = _mm256_load_pd(&b.O[8 * j + 4 * half + i][h]);
        t[0] = _mm256_unpacklo_pd(r[0], r[1]); t[1] = _mm256_unpackhi_pd(r[0], r[1]);
        t[2] = _mm256_unpacklo_pd(r[2], r[3]); t[3] = _mm256_unpackhi_pd(r[2], r[3]);
        __m256d* o = half ? hi : lo;
        o[0] = _mm256_permute2f128_pd(t[0], t[2], 0x20); o[1] = _mm256_permute2f128_pd(t[1], t[3], 0x20);
        o[2] = _mm256_permute2f128_pd(t[0], t[2], 0x31); o[3] = _mm256_permute2f128_pd(t[1], t[3], 0x31);
      }
      for (int i = 0; i < 4; ++i) {
        double* dst = out + 144 * (h + i) + 8 * j;
        _mm256_stream_pd(dst, lo[i]);
        _mm256_stream_pd(dst + 4, hi[i]);
      }
    }
#else
  (void)b; (void)out;
#endif
}

static inline void stream_tile(const Blocks<float, W>& b, float* out) {
#if defined(__AVX__)
  // entries 16 j2 .. 16 j2 + 15 (one 64-byte line of each lane's block), 8 at a time, then each lane's line as
  // two 32-byte streaming stores in a row (as the float64 AVX path: every line whole before the next)
  auto rows8 = [&](int j, __m256* o) {  // o[i]: the 8 entries 8 j .. 8 j + 7 of lane i
    const float* src = &b.O[8 * j][0];
    __m256 r[8], t[8], u[8];
    for (int i = 0; i < 8; ++i) r[i] = _mm256_loadu_ps(src + 8 * i);
    for (int i = 0; i < 8; i += 2) { t[i] = _mm256_unpacklo_ps(r[i], r[i + 1]); t[i + 1] = _mm256_unpackhi_ps(r[i], r[i + 1]); }
    for (int h = 0; h < 8; h += 4) {
      u[h] = _mm256_shuffle_ps(t[h], t[h + 2], _MM_SHUFFLE(1, 0, 1, 0)); u[h + 1] = _mm256_shuffle_ps(t[h], t[h + 2], _MM_SHUFFLE(3, 2, 3, 2));
      u[h + 2] = _mm256_shuffle_ps(t[h + 1], t[h + 3], _MM_SHUFFLE(1, 0, 1, 0)); u[h + 3] = _mm256_shuffle_ps(t[h + 1], t[h + 3], _MM_SHUFFLE(3, 2, 3, 2));
    }
    for (int i = 0; i < 4; ++i) {
      o[i] = _mm256_permute2f128_ps(u[i], u[i + 4], 0x20);
      o[i + 4] = _mm256_permute2f128_ps(u[i], u[i + 4], 0x31);
    }
  };
  for (int j2 = 0; j2 < 9; ++j2) {
    __m256 lo[8], hi[8];
    rows8(2 * j2, lo);
    rows8(2 * j2 + 1, hi);
    for (int i = 0; i < 8; ++i) {
      float* dst = out + 144 * i + 16 * j2;
      _mm256_stream_ps(dst, lo[i]);
      _mm256_stream_ps(dst + 8, hi[i]);
    }
  }
#else
  (void)b; (void)out;
#endif
}

// the blocks, angle gradients, psi'' and theta of B samples of H hinges (tiles over the flattened index)
template <typename T, int M, bool D>
static void hessian_tiles(const T* xp, const int64_t* hp, int64_t B, int64_t V, int64_t H, const HingeArgs<T>& args,
                          T* out, T* gout, T* d2out, T* thout) {
  int64_t BH = B * H, tiles = (BH + W - 1) / W;
  bool aligned = tile_streams<T>() && (reinterpret_cast<uintptr_t>(out) & 63) == 0;
  at::parallel_for(0, tiles, 16, [&](int64_t begin, int64_t end) {
    int64_t bs[W], hs[W];
    alignas(64) T X[12][W];
    alignas(64) T TH[W], D1[W], D2[W];
    HingeTile<T, W> Q;
    alignas(64) Blocks<T, W> tile;
    T* op[W]; T* gp[W];
    for (int64_t t = begin; t < end; ++t) {
      int64_t bh0 = t * W;
      int nl = int(std::min<int64_t>(W, BH - bh0));
      tile_lanes(bh0, nl, H, bs, hs);
      gather_tile<T, false, W>(xp, nullptr, hp, V, args, nullptr, nl, bs, hs, X, nullptr, Q);
      theta_tile<T, W>(X, TH);
      TB_LANES_AGG(W) {
        T psi;
        psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], psi, D1[l], D2[l], static_cast<T*>(nullptr));
      }
      block_tile<T, W>(X, D1, D2, tile);
      if (aligned && nl == W) {
        complete_tile<T>(tile);
        stream_tile(tile, out + 144 * bh0);
        T* g = gout + 12 * bh0;
        for (int l = 0; l < W; ++l)
          for (int m = 0; m < 12; ++m) g[12 * l + m] = tile.G[m][l];
      } else {
        for (int l = 0; l < nl; ++l) { op[l] = out + 144 * (bh0 + l); gp[l] = gout + 12 * (bh0 + l); }
        write_tile<T>(tile, nl, op, gp);
      }
      for (int l = 0; l < nl; ++l) { d2out[bh0 + l] = D2[l]; thout[bh0 + l] = TH[l]; }
    }
    store_fence();  // the streaming stores of this thread
  });
}

// Positions x (..., V, 3); per-hinge parameters as scalars, (H,) or (..., H) like x's batch; c and prev None
// without damping; out and gout optional buffers for the first two results.  Returns (blocks (..., H, 12, 12),
// angle gradients (..., H, 12), psi'' (..., H), theta (..., H), status); check as in bending_energy.
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor, int64_t> bending_hessians(
    torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
    c10::optional<torch::Tensor> c, c10::optional<torch::Tensor> prev, int64_t model,
    c10::optional<torch::Tensor> out_, c10::optional<torch::Tensor> gout_, bool check) {
  Prepared P = prepare("hinge_hessians", x, hinges, a, k, rest, c, prev, model, true);
  // checked before the outputs are made: a non-finite x gets unpopulated tensors (no 1 GB zeroed for an error)
  const bool bad = check && finite_status(P.x, kBadX) != 0;
  auto shape = shape_with(P.batch, {P.H, 12, 12}), gshape = shape_with(P.batch, {P.H, 12});
  auto out = bad && !out_ ? torch::empty(shape, P.x.options()) : output(out_, shape, P.x, "out (blocks)");
  auto g = bad && !gout_ ? torch::empty(gshape, P.x.options()) : output(gout_, gshape, P.x, "out (gradients)");
  TORCH_CHECK(disjoint(out, g), "the two out buffers overlap");
  auto d2 = torch::empty(shape_with(P.batch, {P.H}), P.x.options()), theta = torch::empty_like(d2);
  if (bad) return {out, g, d2, theta, kBadX};
  AT_DISPATCH_FLOATING_TYPES(P.x.scalar_type(), "bending_hessians", [&] {
    using T = scalar_t;
    HingeArgs<T> args = hinge_args<T>(P.a, P.k, P.rest, P.c, P.prev, P.damped, int(model), P.H);
    const T* xp = P.x.data_ptr<T>();
    const int64_t* hp = P.hinges.data_ptr<int64_t>();
    T* op = out.data_ptr<T>(); T* gp = g.data_ptr<T>(); T* dp = d2.data_ptr<T>(); T* tp = theta.data_ptr<T>();
    with_model(int(model), P.damped, [&](auto M_, auto D_) {
      constexpr int M = decltype(M_)::value;
      constexpr bool D = decltype(D_)::value;
      hessian_tiles<T, M, D>(xp, hp, P.B, P.V, P.H, args, op, gp, dp, tp);
    });
  });
  return {out, g, d2, theta, fold_status(theta, model)};
}


}  // namespace cpu
}  // namespace torchbend
