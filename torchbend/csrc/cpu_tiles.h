// The CPU driver's shared pieces (torchbend/csrc/cpu_*.cpp): tiles of W hinges, their gather and output, the
// status word of the input checks, the checked and prepared arguments of the bending operators.  The
// per-hinge mathematics is in hinge_math.h and hinge_ops.h, shared with the CUDA driver.
#pragma once
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>
#include <utility>
#include <vector>
#ifdef __AVX__
#include <immintrin.h>
#endif

#include "checks.h"
#include "hinge_ops.h"

namespace torchbend {
namespace cpu {

// Hinges are processed in tiles of W, every quantity stored as [component][lane] so that the
// compiler vectorizes each formula across the hinges of a tile (about 1.5x over one hinge at a time).
constexpr int W = 8;
// The energy, gradient and product operators (cpu_first_order.cpp, cpu_second_order.cpp) take tiles of WL = 16
// hinges: with 16 lanes GCC 12.2 with -march=native on an AVX-512 Xeon vectorized their lane loops with 512-bit
// vectors (8 lanes: 256-bit, the tuning's preferred width), and on AVX2 two vectors a loop hide more of the long
// latencies of the angle and psi (the divisions, the polynomials).  Measured with the kernels' own lane bodies
// on that Xeon, 1e5 hinges, float64: gather, angle and tan psi 24-25 ns a hinge with 8 lanes, 16-17 with 16
// (native); 25-26 and 20-23 (x86-64-v3).  Each lane's arithmetic and the scatter's order of summation are the
// same for any tile width: so are the results (the tests compare them with the eager reference).
constexpr int WL = 16;

// Each block is written once and not read again here: streaming (non-temporal) stores skip the
// read-for-ownership of every output cache line, which otherwise doubles the memory traffic of this
// memory-bound kernel.  Callers issue a fence (sfence) after the loop.
template <typename T> static inline void store_block(T* dst, const T* src) {
#ifdef __AVX__
  if ((reinterpret_cast<uintptr_t>(dst) & 31) == 0) {
    constexpr int n = int(144 * sizeof(T) / 32);
    for (int v = 0; v < n; ++v)
      _mm256_stream_si256(reinterpret_cast<__m256i*>(dst) + v, _mm256_load_si256(reinterpret_cast<const __m256i*>(src) + v));
    return;
  }
#endif
  std::memcpy(dst, src, 144 * sizeof(T));
}

static inline void store_fence() {
#ifdef __AVX__
  _mm_sfence();
#endif
}

// ---- input checks ----------------------------------------------------------------------------------
// Every operation returns a status word with its results: kBadX (x holds a non-finite value; checked
// before any work when `check` is set), kBadV (likewise the direction v), kFolded (a tan hinge has folded
// through: |theta| >= pi in x's dtype, where psi' and psi'' are meaningless).  The Python wrappers
// (torchbend.backends.native) raise the ValueErrors of torchbend._checks and torchbend.ops.psi.check_fold
// for a non-zero word (one wording, kept there); the scans cost a few nanoseconds a hinge, against the
// microseconds of separate torch calls at small sizes.
constexpr int64_t kBadX = 1, kBadV = 2, kFolded = 4;

template <typename T> static bool all_finite(const T* p, int64_t n) {
  const T big = std::numeric_limits<T>::max();
  int bad = 0;  // no early exit: the loop vectorizes (NaN fails the comparison)
  for (int64_t i = 0; i < n; ++i) bad |= !(std::abs(p[i]) <= big);
  return bad == 0;
}


// kBadX / kBadV (flag) if t holds a non-finite value
int64_t finite_status(const torch::Tensor& t, int64_t flag);
// kFolded if a tan hinge (model 1) has |theta| >= pi (pi rounded to theta's dtype, as check_fold compares)
int64_t fold_status(const torch::Tensor& theta, int64_t model);

// torch::empty(shape, options), or with the opt-in cache of large outputs (cpu_tiles.cpp) a block of warm memory
torch::Tensor pooled_empty(const std::vector<int64_t>& shape, const torch::TensorOptions& options);

// The blocks of the first nl lanes of a tile to out[l] (144 values, streaming stores unless `stream`
// is false) and their angle gradients to gout[l] (12 values).
template <typename T, bool stream = true>
static inline void write_tile(const Blocks<T, W>& b, int nl, T* const* out, T* const* gout) {
  for (int l = 0; l < nl; ++l) {
    alignas(64) T o[144];
    block_lane(b, l, o);
    if (stream) store_block(out[l], o); else std::memcpy(out[l], o, sizeof(o));
    for (int k = 0; k < 12; ++k) gout[l][k] = b.G[k][l];
  }
}

// t in dtype st, contiguous (no dispatch when it is already: these run on every call)
static torch::Tensor as_dtype(torch::Tensor t, c10::ScalarType st) {
  if (t.scalar_type() != st) t = t.to(st);
  return t.is_contiguous() ? t : t.contiguous();
}

template <typename T> static Param<T> param(const torch::Tensor& t, int64_t H) {
  return Param<T>{t.data_ptr<T>(), t.numel(), H};
}

bool disjoint(const torch::Tensor& t, const torch::Tensor& u);

// A caller-provided output buffer (out=): a contiguous CPU tensor of x's dtype and exactly the output's
// shape, not overlapping x; without one a new tensor (pooled_empty).
torch::Tensor output(const c10::optional<torch::Tensor>& buf, const std::vector<int64_t>& shape,
                     const torch::Tensor& x, const char* what);

struct Prepared {
  torch::Tensor x, hinges, a, k, rest, c, prev;
  std::vector<int64_t> batch;
  int64_t B, V, H;
  bool damped;
};

// every hinge index in [0, V) (a separate pass; the operators that read the indices in a pass of their own check
// them there: gather_tile, scatter_plan)
void check_hinge_range(const char* op, const torch::Tensor& hinges, int64_t V);

// the arguments shared by the bending operators, checked (torchbend/csrc/checks.h) before any work: x a CPU
// float32/float64 (..., V, 3) tensor, hinges an int64 (H, 4) tensor of vertex indices in [0, V), the per-hinge
// parameters CPU tensors of 1, H or (prev) B*H values, c and prev both given or both absent
Prepared prepare(const char* op, torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
                 torch::Tensor rest, const c10::optional<torch::Tensor>& c_, const c10::optional<torch::Tensor>& prev_,
                 int64_t model, bool check_hinges, bool batched_params = true);

// the per-hinge weight (the cotangent of the energy: 1, H or B*H values) in x's dtype
torch::Tensor prepare_weight(const char* op, torch::Tensor weight, const Prepared& P);
// a direction v of x's shape, dtype and device
void check_direction(const char* op, const torch::Tensor& v, const Prepared& P);

template <typename T> static HingeArgs<T> hinge_args(const torch::Tensor& a, const torch::Tensor& k,
                                                     const torch::Tensor& rest, const torch::Tensor& c,
                                                     const torch::Tensor& prev, bool damped, int model, int64_t H) {
  Param<T> none{nullptr, 0, H};
  return HingeArgs<T>{param<T>(a, H), param<T>(k, H), param<T>(rest, H), damped ? param<T>(c, H) : none,
                      damped ? param<T>(prev, H) : none, damped, model};
}

// f(model, damped) with both as compile-time constants (std::integral_constant)
template <typename F> static void with_model(int model, bool damped, F&& f) {
  using std::integral_constant;
  switch (model * 2 + (damped ? 1 : 0)) {
    case 0: f(integral_constant<int, 0>{}, integral_constant<bool, false>{}); break;
    case 1: f(integral_constant<int, 0>{}, integral_constant<bool, true>{}); break;
    case 2: f(integral_constant<int, 1>{}, integral_constant<bool, false>{}); break;
    case 3: f(integral_constant<int, 1>{}, integral_constant<bool, true>{}); break;
    case 4: f(integral_constant<int, 2>{}, integral_constant<bool, false>{}); break;
    case 5: f(integral_constant<int, 2>{}, integral_constant<bool, true>{}); break;
    default: TORCH_CHECK(false, "unknown bending model code ", model);
  }
}

// the sample bs[l] and hinge hs[l] of each of the nl lanes of the tile that starts at the flattened index bh0
static inline void tile_lanes(int64_t bh0, int nl, int64_t H, int64_t* bs, int64_t* hs) {
  int64_t b = bh0 / H, h = bh0 - b * H;  // one division per tile
  for (int l = 0; l < nl; ++l) {
    bs[l] = b; hs[l] = h;
    if (++h == H) { h = 0; ++b; }
  }
}

// The tiles [begin, end) of B samples of H hinges (flattened (sample, hinge) index bh = b H + h), each
// handed to body(bh0, nl, bs, hs) with its first index, lane count and per-lane sample and hinge.
template <int L = W, typename Body> static void for_tiles(int64_t B, int64_t H, Body&& body) {
  int64_t BH = B * H, tiles = (BH + L - 1) / L;
  at::parallel_for(0, tiles, 512 / L, [&](int64_t begin, int64_t end) {
    int64_t bs[L], hs[L];
    for (int64_t t = begin; t < end; ++t) {
      int64_t bh0 = t * L;
      int nl = int(std::min<int64_t>(L, BH - bh0));
      tile_lanes(bh0, nl, H, bs, hs);
      body(bh0, nl, bs, hs);
    }
  });
}

// p[0 .. L) = 0 by 32-byte stores where AVX is on (the lane loop became a memset, which GCC's x86-64-v3 code issues
// as a rep stos: tens of cycles to start, every tile)
template <typename T, int L> static TB_FORCEINLINE void zero_lanes(T* p) {
#if defined(__AVX__)
  if constexpr (sizeof(T) * L % 32 == 0) {
    for (int i = 0; i < int(sizeof(T) * L / 32); ++i) _mm256_storeu_si256(reinterpret_cast<__m256i*>(p) + i, _mm256_setzero_si256());
    return;
  }
#endif
  TB_LANES(L) p[l] = T(0);
}

// gather the stencils (and, if vp is given, the directions) and the parameters of a tile; lanes past
// nl get zeros (finite: theta = atan2(0, 0) = 0).  The hinge indices are range-checked as they are read (the
// check of the operators that make no other pass over them, bending_energy): a lane with an index outside
// [0, V) reads nothing and gets zeros, and the return value is nonzero, for the caller to raise the ValueError
// (checks::check_range) before returning anything
// (Check = false: the indices were checked before, by the scatter plan of the gradient operators.)
// A full tile of L consecutive hinges of one sample (every tile but a sample's last, partial or wrapping one)
// in float64 takes gather_full_tile: the four vertices' offsets are computed across the lanes, the points loaded
// by gather_points (AVX builds; elsewhere each of the 12 components is one loop across the lanes), the
// parameters contiguous loads.  The lane-by-lane path stores each coordinate on its own, which then reaches the
// lane loops' vector loads through the store buffer (a stall per component; on AVX2 the difference was about 15%
// of an energy).  Both paths load the same values.
template <int L, typename T> static TB_FORCEINLINE void param_run(const Param<T>& p, int64_t b, int64_t h0, T* o) {
  if (p.n == 1) {
    const T v = p.p[0];
    TB_LANES(L) o[l] = v;
  } else {
    const T* s = p.p + (p.n == p.H ? h0 : b * p.H + h0);
    TB_LANES(L) o[l] = s[l];
  }
}

#if defined(__AVX__)
// X[3 v + m][l] = p[O[v][l] + m] (m = 0, 1, 2: a point's three coordinates) for the four stencil slots v and the L
// lanes: per point one 32-byte load of its coordinates (masked: the fourth double, past the point, is not read)
// and per four lanes a 4x4 transpose in registers (the fourth row dropped).  The compiler's gather of the same
// values loads every coordinate on its own and inserts it into a vector: three times the loads and more shuffles
// (measured with the lane bodies alone on an AVX-512 Xeon, 1e5 hinges in tiles of 16: 4.3 -> 2.6 ns a hinge
// native, 4.0 -> 2.4 x86-64-v3; a Hessian-vector product gathers x and v).
template <int L> static TB_FORCEINLINE void gather_points(const double* p, const int64_t (*O)[L], double (*X)[L]) {
  const __m256i first3 = _mm256_setr_epi64x(-1, -1, -1, 0);
  for (int v = 0; v < 4; ++v)
    for (int g = 0; g < L; g += 4) {
      const __m256d r0 = _mm256_maskload_pd(p + O[v][g], first3), r1 = _mm256_maskload_pd(p + O[v][g + 1], first3);
      const __m256d r2 = _mm256_maskload_pd(p + O[v][g + 2], first3), r3 = _mm256_maskload_pd(p + O[v][g + 3], first3);
      const __m256d t0 = _mm256_unpacklo_pd(r0, r1), t1 = _mm256_unpackhi_pd(r0, r1);  // x0 x1 z0 z1, y0 y1 0 0
      const __m256d t2 = _mm256_unpacklo_pd(r2, r3), t3 = _mm256_unpackhi_pd(r2, r3);
      _mm256_storeu_pd(&X[3 * v][g], _mm256_permute2f128_pd(t0, t2, 0x20));
      _mm256_storeu_pd(&X[3 * v + 1][g], _mm256_permute2f128_pd(t1, t3, 0x20));
      _mm256_storeu_pd(&X[3 * v + 2][g], _mm256_permute2f128_pd(t0, t2, 0x31));
    }
}
#endif

// the stencils (and directions) of the full tile of hinges h0 .. h0 + L - 1 of sample b; with Check, 1 (and
// nothing loaded) if an index is outside [0, V), for the caller to take the lane-by-lane path
template <typename T, bool Check, int L>
static TB_FORCEINLINE int gather_full_tile(const T* xp, const T* vp, const int64_t* hp, int64_t V, int64_t b,
                                           int64_t h0, T (*X)[L], T (*Vd)[L]) {
  const int64_t* q = hp + 4 * h0;
  if (Check && torchbend::checks::kChecked) {
    const uint64_t uV = uint64_t(V);
    int out = 0;
    TB_SIMD for (int i = 0; i < 4 * L; ++i) out |= int(uint64_t(q[i]) >= uV);
    if (out) return 1;
  }
  const T* xb = xp + 3 * V * b;
  alignas(64) int64_t O[4][L];
  for (int v = 0; v < 4; ++v) TB_LANES(L) O[v][l] = 3 * q[4 * l + v];
#if defined(__AVX__)
  if constexpr (sizeof(T) == sizeof(double) && L % 4 == 0) {
    gather_points<L>(reinterpret_cast<const double*>(xb), O, reinterpret_cast<double (*)[L]>(X));
    if (vp) gather_points<L>(reinterpret_cast<const double*>(vp + 3 * V * b), O, reinterpret_cast<double (*)[L]>(Vd));
    return 0;
  }
#endif
  for (int v = 0; v < 4; ++v)
    for (int m = 0; m < 3; ++m) TB_LANES(L) X[3 * v + m][l] = xb[O[v][l] + m];
  if (vp) {
    const T* vb = vp + 3 * V * b;
    for (int v = 0; v < 4; ++v)
      for (int m = 0; m < 3; ++m) TB_LANES(L) Vd[3 * v + m][l] = vb[O[v][l] + m];
  }
  return 0;
}

template <typename T, bool Check = false, int L = W>
static TB_FORCEINLINE int gather_tile(const T* xp, const T* vp, const int64_t* hp, int64_t V, const HingeArgs<T>& args,
                                      const Param<T>* w, int nl, const int64_t* bs, const int64_t* hs, T (*X)[L],
                                      T (*Vd)[L], HingeTile<T, L>& P) {
  // float64 only: for float32 the gathers over 64-bit offsets measured slower than the lane-by-lane loads (an
  // energy 10%, an HVP 20% slower on an AVX-512 Xeon)
  if (sizeof(T) == sizeof(double) && nl == L && hs[L - 1] == hs[0] + (L - 1) &&
      gather_full_tile<T, Check, L>(xp, vp, hp, V, bs[0], hs[0], X, Vd) == 0) {
    const int64_t b = bs[0], h0 = hs[0];
    param_run<L>(args.a, b, h0, P.a); param_run<L>(args.k, b, h0, P.k); param_run<L>(args.rest, b, h0, P.rest);
    if (args.damped) {
      param_run<L>(args.c, b, h0, P.c); param_run<L>(args.prev, b, h0, P.prev);
    } else {
      zero_lanes<T, L>(P.c); zero_lanes<T, L>(P.prev);
    }
    if (w) param_run<L>(*w, b, h0, P.w);
    else TB_LANES(L) P.w[l] = T(1);
    return 0;
  }
  const uint64_t uV = uint64_t(V);
  int bad = 0;
  for (int l = 0; l < L; ++l) {
    int64_t b = l < nl ? bs[l] : 0, h = l < nl ? hs[l] : 0;
    const int64_t* q = hp + 4 * h;
    const bool out = Check && torchbend::checks::kChecked && l < nl &&
                     (uint64_t(q[0]) >= uV || uint64_t(q[1]) >= uV || uint64_t(q[2]) >= uV || uint64_t(q[3]) >= uV);
    if (l >= nl || out) {
      bad |= int(out);
      for (int m = 0; m < 12; ++m) X[m][l] = T(0);
      if (vp) for (int m = 0; m < 12; ++m) Vd[m][l] = T(0);
      zero_params<T, L>(l, P);
      continue;
    }
    load_hinge<T, L>(xp + 3 * V * b, q, X, l);
    if (vp) load_hinge<T, L>(vp + 3 * V * b, q, Vd, l);
    load_params<T, L>(args, b, h, l, P);
    P.w[l] = w ? (*w)(b, h) : T(1);
  }
  return bad;
}

// The first nl of a tile's L per-lane values to dst: a full tile as one copy of a fixed size (inlined vector moves;
// the loop to a variable nl became a call of memcpy every tile).
template <typename T, int L> static TB_FORCEINLINE void store_lanes(const T* src, int nl, T* dst) {
  if (nl == L) std::memcpy(dst, src, sizeof(T) * L);
  else for (int l = 0; l < nl; ++l) dst[l] = src[l];
}

// the first nl lanes of a tile's 12-vectors O to the per-hinge buffer rows bh0 ...
template <typename T, int L> static inline void store_rows(const T (*O)[L], int nl, T* dst) {
  for (int l = 0; l < nl; ++l)
    for (int m = 0; m < 12; ++m) dst[12 * l + m] = O[m][l];
}


static std::vector<int64_t> shape_with(const std::vector<int64_t>& batch, std::initializer_list<int64_t> tail) {
  std::vector<int64_t> s = batch;
  s.insert(s.end(), tail);
  return s;
}

}  // namespace cpu
}  // namespace torchbend
