// CPU driver of torchbend's compiled bending operations (built by torchbend/backends/native.py): the
// loops over tiles of hinges (at::parallel_for), the streaming stores of the blocks, the input checks,
// torch tensor handling and the Python bindings.  The per-hinge mathematics is in hinge_math.h and
// hinge_ops.h, shared with the CUDA driver; the tests compare both against the eager reference in
// torchbend/ops.
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <cstdint>
#include <limits>
#include <mutex>
#include <type_traits>
#include <utility>
#include <vector>
#include <sys/mman.h>
#include <unistd.h>
#ifdef __AVX__
#include <immintrin.h>
#endif

#include "checks.h"
#include "hinge_ops.h"

using namespace torchbend;

// Hinges are processed in tiles of W, every quantity stored as [component][lane] so that the
// compiler vectorizes each formula across the hinges of a tile (about 1.5x over one hinge at a time).
constexpr int W = 8;

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

static int64_t finite_status(const torch::Tensor& t, int64_t flag) {
  bool ok = true;
  AT_DISPATCH_FLOATING_TYPES(t.scalar_type(), "finite_status", [&] { ok = all_finite(t.data_ptr<scalar_t>(), t.numel()); });
  return ok ? 0 : flag;
}

// kFolded if a tan hinge (model 1) has |theta| >= pi (pi rounded to theta's dtype, as check_fold compares)
static int64_t fold_status(const torch::Tensor& theta, int64_t model) {
  if (model != 1) return 0;
  int bad = 0;
  AT_DISPATCH_FLOATING_TYPES(theta.scalar_type(), "fold_status", [&] {
    const scalar_t* th = theta.data_ptr<scalar_t>();
    const scalar_t pi = scalar_t(3.14159265358979323846);
    for (int64_t i = 0, n = theta.numel(); i < n; ++i) bad |= std::abs(th[i]) >= pi;
  });
  return bad ? kFolded : 0;
}

// ---- large outputs ---------------------------------------------------------------------------------
// Fresh memory page-faults on first touch: for the per-hinge blocks (1152 bytes a hinge in float64) the
// faults cost several times the kernel itself (benchmarks/results/hessian_native_cpu_2core.txt).  Outputs
// of at least kPoolMin bytes therefore take their memory from a small cache of blocks that earlier outputs
// released: a loop that calls an operation repeatedly (a Newton solver, a benchmark) writes into warm
// pages, as with the caller-provided out= buffers, without having to manage them.  At most kPoolBlocks
// released blocks and `limit` bytes are kept (TORCHBEND_OUTPUT_CACHE_MB; 0: no cache; default: an eighth of the
// physical memory, at least 1 GiB, so that the blocks of a million hinges, 1.15 GB in float64, stay warm on a
// machine of 16 GB or more); torchbend.backends.native.empty_output_cache() frees them.  Blocks are matched by
// exact size.
constexpr size_t kPoolMin = size_t(4) << 20, kPoolAlign = size_t(2) << 20;
constexpr int kPoolBlocks = 4;

struct OutputPool {
  std::mutex mu;
  std::vector<std::pair<void*, size_t>> blocks;  // released, most recent last
  size_t held = 0, limit = 0;
  int64_t hits = 0, misses = 0;
};

static OutputPool& output_pool() {
  static OutputPool* pool = [] {  // never destroyed: tensors may be released at interpreter exit
    auto* p = new OutputPool;
    const char* env = std::getenv("TORCHBEND_OUTPUT_CACHE_MB");
    long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGE_SIZE);
    size_t eighth = pages > 0 && page > 0 ? size_t(pages) * size_t(page) / 8 : 0;
    p->limit = env ? size_t(std::max(0L, std::atol(env))) << 20 : std::max(size_t(1) << 30, eighth);
    return p;
  }();
  return *pool;
}

static void pool_release(void* ptr, size_t bytes) {
  OutputPool& P = output_pool();
  std::vector<void*> drop;
  {
    std::lock_guard<std::mutex> lock(P.mu);
    if (bytes <= P.limit) {
      P.blocks.emplace_back(ptr, bytes);
      P.held += bytes;
      ptr = nullptr;
      while (P.held > P.limit || int(P.blocks.size()) > kPoolBlocks) {  // the oldest go first
        drop.push_back(P.blocks.front().first);
        P.held -= P.blocks.front().second;
        P.blocks.erase(P.blocks.begin());
      }
    }
  }
  if (ptr) drop.push_back(ptr);
  for (void* q : drop) std::free(q);
}

static void* pool_acquire(size_t bytes) {
  OutputPool& P = output_pool();
  {
    std::lock_guard<std::mutex> lock(P.mu);
    for (size_t i = P.blocks.size(); i-- > 0;)
      if (P.blocks[i].second == bytes) {
        void* ptr = P.blocks[i].first;
        P.held -= bytes;
        P.blocks.erase(P.blocks.begin() + int64_t(i));
        ++P.hits;
        return ptr;
      }
    ++P.misses;
  }
  void* ptr = std::aligned_alloc(kPoolAlign, bytes);  // bytes: a multiple of kPoolAlign
  TORCH_CHECK(ptr, "out of memory (", bytes, " bytes)");
#ifdef MADV_HUGEPAGE
  madvise(ptr, bytes, MADV_HUGEPAGE);  // fewer, larger first-touch faults where transparent huge pages are on
#endif
  return ptr;
}

// torch::empty(shape) for small outputs, a pooled block (64-byte aligned) for large ones
static torch::Tensor pooled_empty(const std::vector<int64_t>& shape, const torch::TensorOptions& options) {
  int64_t n = 1;
  for (auto s : shape) n *= s;
  size_t bytes = size_t(n) * options.dtype().itemsize();
  if (bytes < kPoolMin || output_pool().limit == 0) return torch::empty(shape, options);
  size_t rounded = (bytes + kPoolAlign - 1) / kPoolAlign * kPoolAlign;
  void* ptr = pool_acquire(rounded);
  return torch::from_blob(ptr, shape, [rounded](void* q) { pool_release(q, rounded); }, options);
}

// (blocks held, bytes held, hits, misses, limit in bytes) of the output cache
static std::tuple<int64_t, int64_t, int64_t, int64_t, int64_t> output_cache_info() {
  OutputPool& P = output_pool();
  std::lock_guard<std::mutex> lock(P.mu);
  return {int64_t(P.blocks.size()), int64_t(P.held), P.hits, P.misses, int64_t(P.limit)};
}

static void empty_output_cache() {
  OutputPool& P = output_pool();
  std::vector<std::pair<void*, size_t>> drop;
  {
    std::lock_guard<std::mutex> lock(P.mu);
    drop.swap(P.blocks);
    P.held = 0;
  }
  for (auto& b : drop) std::free(b.first);
}

static void set_output_cache_limit(int64_t bytes) {
  OutputPool& P = output_pool();
  {
    std::lock_guard<std::mutex> lock(P.mu);
    P.limit = size_t(std::max<int64_t>(0, bytes));
  }
  if (P.held > P.limit) empty_output_cache();
}

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

static bool disjoint(const torch::Tensor& t, const torch::Tensor& u) {
  auto p = reinterpret_cast<uintptr_t>(t.data_ptr()), q = reinterpret_cast<uintptr_t>(u.data_ptr());
  return p + t.nbytes() <= q || q + u.nbytes() <= p;
}

// A caller-provided output buffer (out=): a contiguous CPU tensor of x's dtype and exactly the output's
// shape, not overlapping x; without one a new tensor (pooled_empty: large ones in warm memory).
static torch::Tensor output(const c10::optional<torch::Tensor>& buf, const std::vector<int64_t>& shape,
                            const torch::Tensor& x, const char* what) {
  if (!buf.has_value()) return pooled_empty(shape, x.options());
  const torch::Tensor& t = *buf;
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == x.scalar_type() && t.is_contiguous(), what,
              " must be a contiguous CPU tensor of x's dtype (", x.scalar_type(), ")");
  TORCH_CHECK(t.sizes() == c10::IntArrayRef(shape), what, " must have shape ", c10::IntArrayRef(shape), ", got ",
              t.sizes());
  TORCH_CHECK(disjoint(t, x), what, " overlaps x");
  return t;
}

struct Prepared {
  torch::Tensor x, hinges, a, k, rest, c, prev;
  std::vector<int64_t> batch;
  int64_t B, V, H;
  bool damped;
};

// every hinge index in [0, V) (a separate pass; the operators that read the indices in a pass of their own check
// them there: gather_tile, scatter_plan)
static void check_hinge_range(const char* op, const torch::Tensor& hinges, int64_t V) {
  torchbend::checks::check_range(op, "hinges", hinges, 0, V, "x has V = " + std::to_string(V) + " vertices");
}

// the arguments shared by the bending operators, checked (torchbend/csrc/checks.h) before any work: x a CPU
// float32/float64 (..., V, 3) tensor, hinges an int64 (H, 4) tensor of vertex indices in [0, V), the per-hinge
// parameters CPU tensors of 1, H or (prev) B*H values, c and prev both given or both absent
static Prepared prepare(const char* op, torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
                        torch::Tensor rest, const c10::optional<torch::Tensor>& c_,
                        const c10::optional<torch::Tensor>& prev_, int64_t model, bool check_hinges,
                        bool batched_params = true) {
  namespace ck = torchbend::checks;
  ck::require(model >= 0 && model <= 2, op, "model code must be 0 (quadratic), 1 (tan) or 2 (sin), got ", model);
  ck::require(x.device().is_cpu() && x.dim() >= 2 && x.size(-1) == 3, op, "x must be a CPU (..., V, 3) tensor, got ",
              ck::shape_str(x), " on ", x.device());
  ck::require(x.scalar_type() == torch::kFloat || x.scalar_type() == torch::kDouble, op,
              "x must be float32 or float64, got ", x.scalar_type());
  ck::require(c_.has_value() == prev_.has_value(), op, "the viscous term needs both c and prev (got ",
              c_.has_value() ? "c without prev" : "prev without c", ")");
  Prepared p;
  p.hinges = ck::index_tensor(op, "hinges", hinges, x.device(), 4);
  p.batch.assign(x.sizes().begin(), x.sizes().end() - 2);
  p.V = x.size(-2); p.H = hinges.size(0); p.B = 1;
  for (auto s : p.batch) p.B *= s;
  if (check_hinges) check_hinge_range(op, p.hinges, p.V);
  p.x = x.contiguous();
  p.damped = c_.has_value();
  auto prep = [&](torch::Tensor t, const char* name, bool batched) {
    ck::require(t.device().is_cpu(), op, name, " must be on the CPU (x's device), got ", t.device());
    ck::require(t.is_floating_point() || t.scalar_type() == torch::kLong || t.scalar_type() == torch::kInt, op, name,
                " must be a real tensor, got ", t.scalar_type());
    int64_t n = t.numel();
    ck::require(n == 1 || n == p.H || (batched && n == p.B * p.H), op, name, " has ", n, " values; expected 1 or H = ",
                p.H, batched ? " or B*H = " + std::to_string(p.B * p.H) : std::string());
    return as_dtype(t, x.scalar_type());
  };
  p.a = prep(a, "a", batched_params); p.k = prep(k, "k", batched_params); p.rest = prep(rest, "rest", batched_params);
  if (p.damped) { p.c = prep(*c_, "c", batched_params); p.prev = prep(*prev_, "prev", batched_params); }
  return p;
}

// ----------------------------------------------------------------------------------------------
// Sparse assembly of the Hessian of one mesh into CSR values, both ways of
// torchbend.energies.bending_hessian.assemble: per hinge (scatter of the 12x12 blocks) and per
// triangle (paper sec. 4.1-4.2: psi'' g g^T per hinge, plus sum_h psi'_h Hess(theta_h) as one 9x9
// block per triangle, eq. 7 with the conditional transpose: face_block).  Serial: the scatter
// targets overlap.

// values += the local (3m x 3m) matrix `loc` of an element with vertices v[0..m): vertex block (a, b) starts at
// CSR position base[m a + b], its row p at base + p row_len[v[a]] (torchbend.energies.sparse.StencilPattern)
template <typename T, int m>
static inline void scatter_blocks(T* values, const int64_t* base, const int64_t* v, const int64_t* row_len,
                                  const T* loc) {
  for (int a = 0; a < m; ++a) {
    const int64_t rl = row_len[v[a]];
    for (int b = 0; b < m; ++b) {
      T* dst = values + base[m * a + b];
      for (int p = 0; p < 3; ++p, dst += rl) {
        const T* src = loc + 3 * m * (3 * a + p) + 3 * b;
        dst[0] += src[0]; dst[1] += src[1]; dst[2] += src[2];
      }
    }
  }
}

// names the first base bp[i] of an element (vertices ev[0 .. m)) outside the first scalar row of its block row
// ev[i / m] with its 3 columns (so that the block's rows base + p row_len (p < 3) would leave that block row)
template <int m>
[[noreturn, gnu::cold, gnu::noinline]] static void report_element_bases(const char* name, int64_t e, const int64_t* bp, const int64_t* ev,
                                              const int64_t* rs, const int64_t* rl) {
  for (int i = 0; i < m * m; ++i) {
    int64_t v = ev[i / m], r0 = rs[v];
    if (bp[i] < r0 || bp[i] > r0 + rl[v] - 3)
      torchbend::checks::fail("assemble", name, "[", e, ", ", i, "] = ", bp[i], " is not a block of row ", v,
                              " of the pattern (its first scalar row spans [", r0, ", ", r0 + rl[v], "))");
  }
  torchbend::checks::fail("assemble", name, "[", e, "]: a block base outside its block row");
}

// the block bases bp[0 .. m m) of an element checked against its block rows (checked by the assembly as it reads
// them, before their scatter; the hinges' check is fused into the assembly's reach loop)
template <int m>
static inline void check_element_bases(const char* name, int64_t e, const int64_t* bp, const int64_t* ev,
                                       const int64_t* rs, const int64_t* rl) {
  if (!torchbend::checks::kChecked) return;
  int bad = 0;
  for (int a = 0; a < m; ++a) {
    const int64_t lo = rs[ev[a]], hi = lo + rl[ev[a]] - 3;
    for (int b = 0; b < m; ++b) bad |= int(bp[m * a + b] < lo) | int(bp[m * a + b] > hi);
  }
  if (bad) report_element_bases<m>(name, e, bp, ev, rs, rl);
}

// the failure paths of assemble_impl's fused index checks, out of line (the hot loop keeps only the tests)
static torch::Tensor index_view(const int64_t* p, int64_t n, int64_t m) {  // the caller's array as a tensor (no copy)
  return torch::from_blob(const_cast<int64_t*>(p), {n, m}, torch::kLong);
}

[[gnu::cold, gnu::noinline]] static void assemble_bad_hinges(const int64_t* hinges, int64_t H, int64_t V) {
  check_hinge_range("assemble", index_view(hinges, H, 4), V);
}

[[gnu::cold, gnu::noinline]] static void assemble_bad_faces(const int64_t* faces, const int64_t* fes, int64_t F, int64_t V) {
  namespace ck = torchbend::checks;
  ck::check_range("assemble", "faces", index_view(faces, F, 3), 0, V, "x has V = " + std::to_string(V) + " vertices");
  for (int64_t i = 0; i < 3 * F; ++i)
    if (fes[i] != 1 && fes[i] != -1)
      ck::fail("assemble", "face_edge_signs[", i / 3, ", ", i % 3, "] = ", fes[i], " must be +1 or -1");
}

template <typename T>
[[gnu::flatten]] static void assemble_impl(const T* x, const int64_t* hinges, int64_t H, Param<T> a, Param<T> k, Param<T> rest,
                          Param<T> c, Param<T> prev, bool damped, int model, const int64_t* hblk,
                          const int64_t* faces, const int64_t* feh, const int64_t* fes, const int64_t* fblk,
                          const int64_t* row_len, const int64_t* rs, int64_t V, int64_t F, bool per_triangle,
                          T* values, int64_t nnz, T* thout) {
  namespace ck = torchbend::checks;
  // the index arguments are checked as the assembly reads them, each before its first use (one pass over them
  // that the assembly makes anyway); the first offending entry in memory order is named
  auto bad_hinge = [&]() { assemble_bad_hinges(hinges, H, V); };
  auto bad_face = [&]() { assemble_bad_faces(faces, fes, F, V); };
  std::vector<T> d1s(per_triangle ? H : 0);
  // per triangle: each face's 9x9 block goes in right after the tile holding the last of its hinges, whose 16
  // vertex blocks include the face's 9, so that its scatter finds them in cache (a separate pass over the faces
  // would stream the whole value array a second time).  first[h] -> next[f] -> ...: the faces whose last hinge is h
  std::vector<int64_t> first(per_triangle ? H : 0, -1), next(per_triangle ? F : 0, -1);
  if (per_triangle && ck::kChecked) {
    int bad = 0;
    for (int64_t i = 0; i < 3 * F; ++i) bad |= int(feh[i] < -1) | int(feh[i] >= H);
    for (int64_t i = 0; bad && i < 3 * F; ++i)
      if (feh[i] < -1 || feh[i] >= H)
        ck::fail("assemble", "face_edge_hinges[", i / 3, ", ", i % 3, "] = ", feh[i], " is out of range [-1, ", H,
                 ") (hinge indices of H = ", H, " hinges, -1 on the boundary)");
  }
  for (int64_t f = per_triangle ? F : 0; f-- > 0;) {
    const int64_t* fh = feh + 3 * f;
    int64_t last = std::max(fh[0], std::max(fh[1], fh[2]));
    if (last >= 0) { next[f] = first[last]; first[last] = f; }
  }
  T blk[81];
  alignas(64) T buf[W][144];
  T gbuf[W][12];
  T X[12][W], D1[W], D2[W], G[12][W];
  Blocks<T, W> tile;
  T* op[W]; T* gp[W];
  for (int l = 0; l < W; ++l) { op[l] = buf[l]; gp[l] = gbuf[l]; }
  // `values` comes uninitialised and is zeroed just ahead of the scatter: before a tile, [0, zeroed) is zeroed up
  // to the last position the tile touches (first touches come after, and in cache, whatever the hinge order)
  int64_t zeroed = 0;
  for (int64_t h0 = 0; h0 < H; h0 += W) {
    int nl = int(std::min<int64_t>(W, H - h0));
    int64_t reach = zeroed;
    for (int l = 0; l < W; ++l) {
      if (l >= nl) { for (int m = 0; m < 12; ++m) X[m][l] = T(0); D1[l] = D2[l] = T(0); continue; }
      int64_t h = h0 + l;
      const int64_t* q = hinges + 4 * h;
      if (ck::kChecked && (uint64_t(q[0]) >= uint64_t(V) || uint64_t(q[1]) >= uint64_t(V) ||
                           uint64_t(q[2]) >= uint64_t(V) || uint64_t(q[3]) >= uint64_t(V)))
        bad_hinge();
      load_hinge<T, W>(x, q, X, l);
      hinge_psi<T, W>(X, l, model, a(0, h), k(0, h), rest(0, h), damped, damped ? c(0, h) : T(0),
                      damped ? prev(0, h) : T(0), thout[h], D1[l], D2[l]);
      // the reach of the hinge's blocks, and (fused, from the same loads) whether every base of block row q[va]
      // lies in that row's first scalar row with its 3 columns (check_element_bases names the first that does not)
      int bad = 0;
      for (int va = 0; va < 4; ++va) {
        const int64_t* base = hblk + 16 * h + 4 * va;
        const int64_t lo = std::min(std::min(base[0], base[1]), std::min(base[2], base[3]));
        const int64_t hi = std::max(std::max(base[0], base[1]), std::max(base[2], base[3]));
        const int64_t rl = row_len[q[va]];
        if (ck::kChecked) bad |= int(lo < rs[q[va]]) | int(hi > rs[q[va]] + rl - 3);
        reach = std::max(reach, hi + 2 * rl + 3);
      }
      if (bad) report_element_bases<4>("hinge_blocks", h, hblk + 16 * h, q, rs, row_len);
    }
    if (reach > zeroed) { std::fill(values + zeroed, values + reach, T(0)); zeroed = reach; }
    if (!per_triangle) {
      block_tile<T, W>(X, D1, D2, tile);
      write_tile<T, false>(tile, nl, op, gp);
      for (int l = 0; l < nl; ++l) scatter_blocks<T, 4>(values, hblk + 16 * (h0 + l), hinges + 4 * (h0 + l), row_len,
                                                       buf[l]);
    } else {
      grad_tile<T, W>(X, G);
      for (int l = 0; l < nl; ++l) {
        d1s[h0 + l] = D1[l];
        T gg[144];
        for (int r = 0; r < 12; ++r) {
          T gr = D2[l] * G[r][l];
          for (int cc = 0; cc < 12; ++cc) gg[12 * r + cc] = gr * G[cc][l];
        }
        scatter_blocks<T, 4>(values, hblk + 16 * (h0 + l), hinges + 4 * (h0 + l), row_len, gg);
      }
      for (int l = 0; l < nl; ++l)
        for (int64_t f = first[h0 + l]; f >= 0; f = next[f]) {
          const int64_t* fh = feh + 3 * f;
          T cf[3] = {fh[0] >= 0 ? d1s[fh[0]] : T(0), fh[1] >= 0 ? d1s[fh[1]] : T(0), fh[2] >= 0 ? d1s[fh[2]] : T(0)};
          const int64_t* fv = faces + 3 * f;
          const int64_t* fs = fes + 3 * f;
          if (ck::kChecked && (uint64_t(fv[0]) >= uint64_t(V) || uint64_t(fv[1]) >= uint64_t(V) ||
                               uint64_t(fv[2]) >= uint64_t(V) || (fs[0] != 1 && fs[0] != -1) ||
                               (fs[1] != 1 && fs[1] != -1) || (fs[2] != 1 && fs[2] != -1)))
            bad_face();
          check_element_bases<3>("face_blocks", f, fblk + 9 * f, fv, rs, row_len);
          face_block(x + 3 * fv[0], x + 3 * fv[1], x + 3 * fv[2], cf, fes + 3 * f, blk);
          scatter_blocks<T, 3>(values, fblk + 9 * f, fv, row_len, blk);
        }
    }
  }
  std::fill(values + zeroed, values + nnz, T(0));  // blocks of no hinge (none in a bending pattern)
}

// the arguments of `assemble` checked before any work (checks.h); returns them prepared (contiguous)
struct AssembleArgs {
  Prepared P;
  torch::Tensor faces, face_edge_hinges, face_edge_signs, face_blocks, hinge_blocks, row_len;
  std::vector<int64_t> rs;  // per vertex v, the CSR position of its block row's first entry (V + 1 values)
};


static AssembleArgs assemble_args(torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
                                  torch::Tensor rest, const c10::optional<torch::Tensor>& c_,
                                  const c10::optional<torch::Tensor>& prev_, int64_t model, torch::Tensor hinge_blocks,
                                  torch::Tensor faces, torch::Tensor face_edge_hinges, torch::Tensor face_edge_signs,
                                  torch::Tensor face_blocks, torch::Tensor row_len, int64_t nnz, bool per_triangle) {
  const char* op = "assemble";
  namespace ck = torchbend::checks;
  ck::require(x.device().is_cpu() && x.dim() == 2 && x.size(1) == 3, op, "x must be a CPU (V, 3) tensor (one mesh), got ",
              ck::shape_str(x), " on ", x.device());
  Prepared P = prepare(op, x, hinges, a, k, rest, c_, prev_, model, false, false);
  hinges = P.hinges;
  const int64_t V = P.V, H = P.H;
  auto dev = x.device();
  faces = ck::index_tensor(op, "faces", faces, dev, 3);
  const int64_t F = faces.size(0);
  auto per_face = [&](torch::Tensor t, const char* name, int64_t cols) {
    t = ck::index_tensor(op, name, t, dev, cols);
    ck::require(t.size(0) == F, op, name, " must have F = ", F, " rows (one per face), got ", t.size(0));
    return t;
  };
  face_edge_hinges = per_face(face_edge_hinges, "face_edge_hinges", 3);
  face_edge_signs = per_face(face_edge_signs, "face_edge_signs", 3);
  face_blocks = per_face(face_blocks, "face_blocks", 9);
  hinge_blocks = ck::index_tensor(op, "hinge_blocks", hinge_blocks, dev, 16);
  ck::require(hinge_blocks.size(0) == H, op, "hinge_blocks must have H = ", H, " rows (one per hinge), got ",
              hinge_blocks.size(0));
  row_len = ck::index_tensor(op, "row_len", row_len, dev);
  ck::require(row_len.dim() == 1 && row_len.size(0) == V, op, "row_len must have shape (V,) = (", V, ",), got ",
              ck::shape_str(row_len));
  // hinges, faces, face-edge hinges and signs: checked by the assembly as it reads them (assemble_impl)
  // the pattern: row_len[v] = 3 x (vertex blocks in block row v), nnz = 3 sum(row_len); each block base of an
  // element's vertex pair (a, b) lies in the first scalar row of block row v_a with its 3 columns, so that the
  // block's rows base + p row_len[v_a] (p < 3) stay inside that block row
  ck::check_range(op, "row_len", row_len, 0, 3 * V + 1, "3 x the vertex blocks of a row of V = " +
                  std::to_string(V) + " vertices");
  const int64_t* rl = row_len.data_ptr<int64_t>();
  std::vector<int64_t> rs(size_t(V) + 1, 0);
  for (int64_t v = 0; v < V; ++v) {
    if (rl[v] % 3) ck::fail(op, "row_len[", v, "] = ", rl[v], " must be a multiple of 3");
    rs[size_t(v) + 1] = rs[size_t(v)] + 3 * rl[v];
  }
  ck::require(nnz == rs[size_t(V)], op, "nnz = ", nnz, " does not match the pattern: 3 sum(row_len) = ", rs[size_t(V)]);
  return AssembleArgs{P, faces, face_edge_hinges, face_edge_signs, face_blocks, hinge_blocks, row_len, std::move(rs)};
}

// (CSR values (nnz,) of the Hessian of one mesh x (V, 3), theta (H,), status); parameters as in
// bending_hessians, the pattern as block bases (torchbend.energies.sparse.StencilPattern: hinge_blocks (H, 16),
// face_blocks (F, 9), row_len (V,)), x finite (the caller checks)
std::tuple<torch::Tensor, torch::Tensor, int64_t> assemble(torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k, torch::Tensor rest,
                       c10::optional<torch::Tensor> c_, c10::optional<torch::Tensor> prev_, int64_t model,
                       torch::Tensor hinge_blocks, torch::Tensor faces, torch::Tensor face_edge_hinges,
                       torch::Tensor face_edge_signs, torch::Tensor face_blocks, torch::Tensor row_len, int64_t nnz,
                       bool per_triangle) {
  AssembleArgs A = assemble_args(x, hinges, a, k, rest, c_, prev_, model, hinge_blocks, faces, face_edge_hinges,
                                 face_edge_signs, face_blocks, row_len, nnz, per_triangle);
  const Prepared& P = A.P;
  x = P.x; hinges = P.hinges;
  const int64_t H = P.H, F = A.faces.size(0);
  faces = A.faces; face_edge_hinges = A.face_edge_hinges; face_edge_signs = A.face_edge_signs;
  face_blocks = A.face_blocks; hinge_blocks = A.hinge_blocks; row_len = A.row_len;
  const bool damped = P.damped;
  a = P.a; k = P.k; rest = P.rest;
  torch::Tensor c = P.c, prev = P.prev;
  auto values = pooled_empty({nnz}, x.options()), theta = torch::empty({H}, x.options());  // zeroed in the pass
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "assemble", [&] {
    Param<scalar_t> none{nullptr, 0, H};
    assemble_impl<scalar_t>(x.data_ptr<scalar_t>(), hinges.data_ptr<int64_t>(), H, param<scalar_t>(a, H),
                            param<scalar_t>(k, H), param<scalar_t>(rest, H), damped ? param<scalar_t>(c, H) : none,
                            damped ? param<scalar_t>(prev, H) : none, damped, int(model),
                            hinge_blocks.data_ptr<int64_t>(), faces.data_ptr<int64_t>(),
                            face_edge_hinges.data_ptr<int64_t>(), face_edge_signs.data_ptr<int64_t>(),
                            face_blocks.data_ptr<int64_t>(), row_len.data_ptr<int64_t>(), A.rs.data(), P.V, F, per_triangle,
                            values.data_ptr<scalar_t>(), nnz,
                            theta.data_ptr<scalar_t>());
  });
  return {values, theta, fold_status(theta, model)};
}

// ----------------------------------------------------------------------------------------------
// Energy, gradient, Hessian-vector product and the general second-order product (the hot paths of
// training and of matrix-free solvers).  Each is one parallel pass over tiles of W hinges (gather, angle,
// psi, closed forms; every lane loop branch-free and vectorized, the model and damping template
// arguments); the gradient and the products sum their per-hinge 12-vectors per vertex in blocks of
// consecutive hinges (scatter_tiles: bit-identical for any number of threads, no two threads writing one
// value), or, for hinges in no compact order, through a per-hinge buffer and the incidence lists (inc_ptr
// (V+1), inc_idx (4H): entries 4 h + slot, sorted by vertex).

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

// The tiles [begin, end) of B samples of H hinges (flattened (sample, hinge) index bh = b H + h), each
// handed to body(bh0, nl, bs, hs) with its first index, lane count and per-lane sample and hinge.
template <typename Body> static void for_tiles(int64_t B, int64_t H, Body&& body) {
  int64_t BH = B * H, tiles = (BH + W - 1) / W;
  at::parallel_for(0, tiles, 64, [&](int64_t begin, int64_t end) {
    int64_t bs[W], hs[W];
    for (int64_t t = begin; t < end; ++t) {
      int64_t bh0 = t * W;
      int nl = int(std::min<int64_t>(W, BH - bh0));
      int64_t b = bh0 / H, h = bh0 - b * H;  // one division per tile
      for (int l = 0; l < nl; ++l) {
        bs[l] = b; hs[l] = h;
        if (++h == H) { h = 0; ++b; }
      }
      body(bh0, nl, bs, hs);
    }
  });
}

// gather the stencils (and, if vp is given, the directions) and the parameters of a tile; lanes past
// nl get zeros (finite: theta = atan2(0, 0) = 0).  The hinge indices are range-checked as they are read (the
// check of the operators that make no other pass over them, bending_energy): a lane with an index outside
// [0, V) reads nothing and gets zeros, and the return value is nonzero, for the caller to raise the ValueError
// (checks::check_range) before returning anything
// (Check = false: the indices were checked before, by the scatter plan of the gradient operators.)
template <typename T, bool Check = false>
static TB_FORCEINLINE int gather_tile(const T* xp, const T* vp, const int64_t* hp, int64_t V, const HingeArgs<T>& args,
                                      const Param<T>* w, int nl, const int64_t* bs, const int64_t* hs, T (*X)[W],
                                      T (*Vd)[W], HingeTile<T, W>& P) {
  const uint64_t uV = uint64_t(V);
  int bad = 0;
  for (int l = 0; l < W; ++l) {
    int64_t b = l < nl ? bs[l] : 0, h = l < nl ? hs[l] : 0;
    const int64_t* q = hp + 4 * h;
    const bool out = Check && torchbend::checks::kChecked && l < nl &&
                     (uint64_t(q[0]) >= uV || uint64_t(q[1]) >= uV || uint64_t(q[2]) >= uV || uint64_t(q[3]) >= uV);
    if (l >= nl || out) {
      bad |= int(out);
      for (int m = 0; m < 12; ++m) X[m][l] = T(0);
      if (vp) for (int m = 0; m < 12; ++m) Vd[m][l] = T(0);
      zero_params<T, W>(l, P);
      continue;
    }
    load_hinge<T, W>(xp + 3 * V * b, q, X, l);
    if (vp) load_hinge<T, W>(vp + 3 * V * b, q, Vd, l);
    load_params<T, W>(args, b, h, l, P);
    P.w[l] = w ? (*w)(b, h) : T(1);
  }
  return bad;
}

// the first nl lanes of a tile's 12-vectors O to the per-hinge buffer rows bh0 ...
template <typename T> static inline void store_rows(const T (*O)[W], int nl, T* dst) {
  for (int l = 0; l < nl; ++l)
    for (int m = 0; m < 12; ++m) dst[12 * l + m] = O[m][l];
}

// out[b, v, :] = sum over the incidences i of v of w[b, i / 4, 3 (i % 4) + :]
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

static Scratch scratch(size_t bytes) {
  thread_local struct Kept {
    void* p = nullptr;
    size_t n = 0;
    ~Kept() { std::free(p); }
  } kept;
  Scratch s;
  if (bytes > kScratchKeep) {
    s.hold = torch::empty({int64_t(bytes)}, torch::kUInt8);
    s.p = s.hold.data_ptr();
    return s;
  }
  if (bytes > kept.n) {
    std::free(kept.p);
    kept.p = std::malloc(std::max<size_t>(bytes, 64));
    kept.n = kept.p ? bytes : 0;
    TORCH_CHECK(kept.p, "out of memory (", bytes, " bytes of scratch)");
  }
  s.p = kept.p;
  return s;
}

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

static ScatterPlan scatter_plan(const int64_t* hp, int64_t H, int64_t V) {
  ScatterPlan P;
  // about 32 blocks for mid-sized meshes (parallel slack), 512 .. 4096 hinges (a multiple of W)
  P.S = std::min<int64_t>(4096, std::max<int64_t>(512, ((H / 32 + W - 1) / W) * W));
  P.nb = (H + P.S - 1) / P.S;
  std::vector<int64_t> hi(P.nb);
  P.lo.assign(P.nb, 0);
  P.off.assign(P.nb + 1, 0);
  at::parallel_for(0, P.nb, 4, [&](int64_t begin, int64_t end) {
    for (int64_t j = begin; j < end; ++j) {
      const int64_t* q = hp + 4 * j * P.S;
      int64_t n = 4 * (std::min(H, (j + 1) * P.S) - j * P.S), mn = q[0], mx = q[0];
      for (int64_t i = 1; i < n; ++i) { mn = std::min(mn, q[i]); mx = std::max(mx, q[i]); }
      P.lo[j] = mn; hi[j] = mx;
    }
  });
  for (int64_t j = 0; j < P.nb; ++j) {
    P.vmin = j ? std::min(P.vmin, P.lo[j]) : P.lo[j];
    P.vmax = std::max(P.vmax, hi[j]);
  }
  if (P.vmin < 0 || P.vmax >= V) return P;  // out of range: the caller raises (no sizes computed from them)
  for (int64_t j = 0; j < P.nb; ++j) P.off[j + 1] = P.off[j] + (hi[j] - P.lo[j] + 1);
  P.total = P.off[P.nb];
  P.blocked = P.total <= 2 * H;  // accumulators (3 values a vertex) at most half a 12-value-a-hinge buffer
  return P;
}

// out (B, V, 3) = per vertex, the sum of the 12-vectors O that body(bh0, nl, bs, hs, O) computes for the
// tiles of hinges (see for_tiles; O[3 s + c][l]: component c of stencil slot s of lane l)
// The plan's pass over the hinge indices is their range check (before any work: checks::check_range names the
// first bad entry); the incidence lists, which only the unblocked path reads, are checked in full there.
template <typename T, typename Body>
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
    for_tiles(B, H, [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs) {
      alignas(64) T O[12][W];
      body(bh0, nl, bs, hs, O);
      store_rows<T>(O, nl, bp + 12 * bh0);
    });
    gather_vertices<T>(bp, inc_ptr, inc_idx, B, V, H, out);
    return;
  }
  Scratch sc = scratch(sizeof(T) * 3 * size_t(B * P.total));
  T* part = static_cast<T*>(sc.p);
  at::parallel_for(0, B * P.nb, 1, [&](int64_t begin, int64_t end) {
    int64_t bs[W], hs[W];
    alignas(64) T O[12][W];
    for (int64_t blk = begin; blk < end; ++blk) {
      int64_t b = blk / P.nb, j = blk - b * P.nb, lo = P.lo[j];
      T* acc = part + 3 * (b * P.total + P.off[j]);
      std::fill(acc, acc + 3 * (P.off[j + 1] - P.off[j]), T(0));
      int64_t h1 = std::min(H, (j + 1) * P.S);
      for (int64_t h0 = j * P.S; h0 < h1; h0 += W) {
        int nl = int(std::min<int64_t>(W, h1 - h0));
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

static std::vector<int64_t> shape_with(const std::vector<int64_t>& batch, std::initializer_list<int64_t> tail) {
  std::vector<int64_t> s = batch;
  s.insert(s.end(), tail);
  return s;
}

static torch::Tensor prepare_weight(const char* op, torch::Tensor weight, const Prepared& P) {
  namespace ck = torchbend::checks;
  ck::require(weight.device().is_cpu() && weight.is_floating_point(), op,
              "weight must be a floating-point CPU tensor, got ", weight.scalar_type(), " on ", weight.device());
  ck::require(weight.numel() == 1 || weight.numel() == P.H || weight.numel() == P.B * P.H, op, "weight has ",
              weight.numel(), " values; expected 1, H = ", P.H, " or B*H = ", P.B * P.H);
  return as_dtype(weight, P.x.scalar_type());
}

// a direction v of x's shape, dtype and device
static void check_direction(const char* op, const torch::Tensor& v, const Prepared& P) {
  torchbend::checks::require(v.sizes() == P.x.sizes() && v.scalar_type() == P.x.scalar_type() && v.device().is_cpu(),
                             op, "v must be a CPU tensor of x's shape ", torchbend::checks::shape_str(P.x),
                             " and dtype ", P.x.scalar_type(), ", got ", torchbend::checks::shape_str(v), " ",
                             v.scalar_type(), " on ", v.device());
}

// (psi (..., H), theta (..., H), status): the per-hinge energies (summed by the caller per mesh or segment);
// check: x's finiteness first (kBadX: no other work)
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
      for_tiles(P.B, P.H, [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs) {
        alignas(64) T X[12][W];
        alignas(64) T TH[W], PS[W];
        HingeTile<T, W> Q;
        if (gather_tile<T, true>(xp, nullptr, hp, V, args, nullptr, nl, bs, hs, X, nullptr, Q))
          bad_index.store(true, std::memory_order_relaxed);
        theta_tile<T, W>(X, TH);
        TB_LANES_AGG(W) {
          T d1, d2;
          psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], PS[l], d1, d2, static_cast<T*>(nullptr));
        }
        for (int l = 0; l < nl; ++l) { po[bh0 + l] = PS[l]; to[bh0 + l] = TH[l]; }
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
      scatter_tiles<T>(op, P.hinges, P.B, V, inc_ptr.data_ptr<int64_t>(), inc_idx.data_ptr<int64_t>(), gx.data_ptr<T>(),
                       [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs, T (*O)[W]) {
        alignas(64) T X[12][W], G[12][W];
        alignas(64) T TH[W], S[W], PS[W], GP[4][W];
        HingeTile<T, W> Q;
        Half<T, W> hA, hB;
        gather_tile<T>(xp, nullptr, hp, V, args, &w, nl, bs, hs, X, nullptr, Q);
        theta_tile<T, W>(X, TH);
        if (gpp) {
          TB_LANES_AGG(W) {
            T d1, d2, g4[4];
            psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], PS[l], d1, d2, g4);
            S[l] = Q.w[l] * d1;
            GP[0][l] = Q.w[l] * g4[0]; GP[1][l] = Q.w[l] * g4[1]; GP[2][l] = Q.w[l] * g4[2]; GP[3][l] = Q.w[l] * g4[3];
          }
          for (int l = 0; l < nl; ++l)
            for (int j = 0; j < 4; ++j) gpp[4 * (bh0 + l) + j] = GP[j][l];
        } else {
          TB_LANES_AGG(W) {
            T d1, d2;
            psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], PS[l], d1, d2, static_cast<T*>(nullptr));
            S[l] = Q.w[l] * d1;
          }
        }
        halves_tile<T, W>(X, hA, hB);
        grad_of_halves<T, W>(hA, hB, G);
        for (int m = 0; m < 12; ++m) TB_LANES(W) O[m][l] = S[l] * G[m][l];
        for (int l = 0; l < nl; ++l) to[bh0 + l] = TH[l];
        if (po)
          for (int l = 0; l < nl; ++l) po[bh0 + l] = PS[l];
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
// w a per-hinge weight as in bending_gradient; status as in bending_energy (check: x, then v)
std::tuple<torch::Tensor, torch::Tensor, int64_t> bending_hvp(torch::Tensor x, torch::Tensor v, torch::Tensor hinges,
                                                              torch::Tensor a, torch::Tensor k, torch::Tensor rest,
                                                              c10::optional<torch::Tensor> c,
                                                              c10::optional<torch::Tensor> prev, int64_t model,
                                                              torch::Tensor weight, torch::Tensor inc_ptr,
                                                              torch::Tensor inc_idx, bool check) {
  const char* op = "bending_hvp";
  Prepared P = prepare(op, x, hinges, a, k, rest, c, prev, model, false);
  check_direction(op, v, P);
  v = v.contiguous();
  weight = prepare_weight(op, weight, P);
  torchbend::checks::check_incidence(op, inc_ptr, inc_idx, P.V, P.H);
  auto hv = torch::empty(shape_with(P.batch, {P.V, 3}), P.x.options());
  auto theta = torch::empty(shape_with(P.batch, {P.H}), P.x.options());
  if (check) {
    int64_t bad = finite_status(P.x, kBadX) | finite_status(v, kBadV);
    if (bad) return {hv, theta, bad};
  }
  AT_DISPATCH_FLOATING_TYPES(P.x.scalar_type(), "bending_hvp", [&] {
    using T = scalar_t;
    HingeArgs<T> args = hinge_args<T>(P.a, P.k, P.rest, P.c, P.prev, P.damped, int(model), P.H);
    Param<T> w{weight.data_ptr<T>(), weight.numel(), P.H};
    const T* xp = P.x.data_ptr<T>(); const T* vp = v.data_ptr<T>();
    const int64_t* hp = P.hinges.data_ptr<int64_t>();
    T* to = theta.data_ptr<T>();
    int64_t V = P.V;
    with_model(int(model), P.damped, [&](auto M_, auto D_) {
      constexpr int M = decltype(M_)::value;
      constexpr bool D = decltype(D_)::value;
      scatter_tiles<T>(op, P.hinges, P.B, V, inc_ptr.data_ptr<int64_t>(), inc_idx.data_ptr<int64_t>(), hv.data_ptr<T>(),
                       [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs, T (*O)[W]) {
        alignas(64) T X[12][W], Vd[12][W], G[12][W];
        alignas(64) T TH[W], D1[W], D2[W], U[W];
        HingeTile<T, W> Q;
        Half<T, W> hA, hB;
        gather_tile<T>(xp, vp, hp, V, args, &w, nl, bs, hs, X, Vd, Q);
        theta_tile<T, W>(X, TH);
        TB_LANES_AGG(W) {
          T psi, d1, d2;
          psi_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], psi, d1, d2, static_cast<T*>(nullptr));
          D1[l] = Q.w[l] * d1; D2[l] = Q.w[l] * d2;
        }
        halves_tile<T, W>(X, hA, hB);
        grad_of_halves<T, W>(hA, hB, G);
        dot_tile<T, W>(G, Vd, U);
        TB_LANES(W) U[l] *= D2[l];
        hvp_of_halves<T, W>(hA, hB, Vd, G, D1, U, true, O);
        for (int l = 0; l < nl; ++l) to[bh0 + l] = TH[l];
      });
    });
  });
  return {hv, theta, fold_status(theta, model)};
}

// The general double backward (torchbend.energies._bending_fn._second_order without a tangent of the
// cotangent): with directions v (..., V, 3) in x (or None) and t (..., H, 4) or (H, 4) in the per-hinge
// (k, rest, c, prev) (or None), per hinge u = g . v and z = Hess_p(psi) (u, t):
// (dx = sum_h w (z_theta g + psi' H_theta v) (..., V, 3), dp = w z_(k, rest, c, prev) (..., H, 4),
//  dg = grad_p(psi) . (u, t) (..., H), theta (..., H)); w the per-hinge weight (the cotangent gE).
// Without damping the c and prev entries of dp are 0 and those of t are ignored.  Last: the status word
// (fold check only: the inputs come from a backward pass).
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor, int64_t> bending_second_order(
    torch::Tensor x, c10::optional<torch::Tensor> v_, c10::optional<torch::Tensor> t_, torch::Tensor hinges,
    torch::Tensor a, torch::Tensor k, torch::Tensor rest, c10::optional<torch::Tensor> c,
    c10::optional<torch::Tensor> prev, int64_t model, torch::Tensor weight, torch::Tensor inc_ptr,
    torch::Tensor inc_idx) {
  const char* op = "bending_second_order";
  namespace ck = torchbend::checks;
  Prepared P = prepare(op, x, hinges, a, k, rest, c, prev, model, false);
  torch::Tensor v, tt;
  if (v_.has_value()) {
    check_direction(op, *v_, P);
    v = v_->contiguous();
  }
  if (t_.has_value()) {
    ck::require(t_->device().is_cpu() && t_->is_floating_point() && t_->dim() >= 2 && t_->size(-1) == 4 &&
                    t_->size(-2) == P.H && (t_->numel() == 4 * P.H || t_->numel() == 4 * P.B * P.H),
                op, "t must be a floating-point CPU (H, 4) or (..., H, 4) tensor of x's batch, H = ", P.H, ", got ",
                ck::shape_str(*t_));
    tt = as_dtype(*t_, P.x.scalar_type());
  }
  weight = prepare_weight(op, weight, P);
  ck::check_incidence(op, inc_ptr, inc_idx, P.V, P.H);
  auto dx = torch::empty(shape_with(P.batch, {P.V, 3}), P.x.options());
  auto dp = torch::empty(shape_with(P.batch, {P.H, 4}), P.x.options());
  auto dg = torch::empty(shape_with(P.batch, {P.H}), P.x.options()), theta = torch::empty_like(dg);
  AT_DISPATCH_FLOATING_TYPES(P.x.scalar_type(), "bending_second_order", [&] {
    using T = scalar_t;
    HingeArgs<T> args = hinge_args<T>(P.a, P.k, P.rest, P.c, P.prev, P.damped, int(model), P.H);
    Param<T> w{weight.data_ptr<T>(), weight.numel(), P.H};
    const T* xp = P.x.data_ptr<T>();
    const T* vp = v.defined() ? v.data_ptr<T>() : nullptr;
    const T* tp = tt.defined() ? tt.data_ptr<T>() : nullptr;
    bool t_batched = tt.defined() && tt.numel() != 4 * P.H;
    const int64_t* hp = P.hinges.data_ptr<int64_t>();
    T* dpp = dp.data_ptr<T>(); T* dgp = dg.data_ptr<T>(); T* to = theta.data_ptr<T>();
    int64_t V = P.V, H = P.H;
    with_model(int(model), P.damped, [&](auto M_, auto D_) {
      constexpr int M = decltype(M_)::value;
      constexpr bool D = decltype(D_)::value;
      scatter_tiles<T>(op, P.hinges, P.B, V, inc_ptr.data_ptr<int64_t>(), inc_idx.data_ptr<int64_t>(), dx.data_ptr<T>(),
                       [&](int64_t bh0, int nl, const int64_t* bs, const int64_t* hs, T (*O)[W]) {
        alignas(64) T X[12][W], Vd[12][W], G[12][W];
        alignas(64) T TH[W], U[W], TG[4][W], S1[W], S2[W], Z[4][W], DG[W];
        HingeTile<T, W> Q;
        Half<T, W> hA, hB;
        gather_tile<T>(xp, vp, hp, V, args, &w, nl, bs, hs, X, Vd, Q);
        for (int l = 0; l < W; ++l) {
          const T* src = (tp && l < nl) ? tp + 4 * (t_batched ? bs[l] * H + hs[l] : hs[l]) : nullptr;
          for (int j = 0; j < 4; ++j) TG[j][l] = src ? src[j] : T(0);
        }
        theta_tile<T, W>(X, TH);
        halves_tile<T, W>(X, hA, hB);
        grad_of_halves<T, W>(hA, hB, G);
        if (vp) dot_tile<T, W>(G, Vd, U); else TB_LANES(W) U[l] = T(0);
        TB_LANES_AGG(W) {
          T d1, zt, z4[4], dgl;
          psi_second_lane<M, D>(TH[l], Q.a[l], Q.k[l], Q.rest[l], Q.c[l], Q.prev[l], U[l], TG[0][l], TG[1][l],
                                TG[2][l], TG[3][l], d1, zt, z4, dgl);
          T wl = Q.w[l];
          S1[l] = wl * d1; S2[l] = wl * zt;
          Z[0][l] = wl * z4[0]; Z[1][l] = wl * z4[1]; Z[2][l] = wl * z4[2]; Z[3][l] = wl * z4[3];
          DG[l] = dgl;
        }
        hvp_of_halves<T, W>(hA, hB, Vd, G, S1, S2, vp != nullptr, O);
        for (int l = 0; l < nl; ++l) {
          for (int j = 0; j < 4; ++j) dpp[4 * (bh0 + l) + j] = Z[j][l];
          dgp[bh0 + l] = DG[l];
          to[bh0 + l] = TH[l];
        }
      });
    });
  });
  return {dx, dp, dg, theta, fold_status(theta, model)};
}

// ----------------------------------------------------------------------------------------------
// Per-hinge 12x12 blocks: gather, angle, psi' and psi'' (psi_lane, vectorized across the lanes of a tile
// like the operations above), the closed-form blocks (block_tile) and their output.  A block is written
// once and not read again here, so it goes out with streaming stores (no read-for-ownership of the output
// lines).  For a full tile with AVX-512 (float64) or AVX (float32), the tile is completed in place across
// its lanes (mirrored lower triangle, B terms: complete_tile) and transposed in registers 8 entries at a
// time, each lane's 8 consecutive entries one aligned streaming store (stream_tile: every block of a
// 64-byte aligned output starts 64-byte aligned, 1152 = 18 x 64 and 576 = 9 x 64 bytes); elsewhere (a
// partial tile, an unaligned out= buffer) block_lane copies lane by lane (write_tile).  Both give the same
// values: the same operations on the same numbers, only the copies differ.

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
#if defined(__AVX512F__)
  if (std::is_same<T, double>::value) return true;
#endif
#if defined(__AVX__)
  if (std::is_same<T, float>::value) return true;
#endif
  return false;
}

// the completed blocks of the 8 lanes of a tile to out + 144 l (64-byte aligned), 8 entries at a time
static inline void stream_tile(const Blocks<double, W>& b, double* out) {
#if defined(__AVX512F__)
  for (int j = 0; j < 18; ++j) {
    const double* src = &b.O[8 * j][0];
    __m512d r0 = _mm512_loadu_pd(src), r1 = _mm512_loadu_pd(src + 8), r2 = _mm512_loadu_pd(src + 16),
            r3 = _mm512_loadu_pd(src + 24), r4 = _mm512_loadu_pd(src + 32), r5 = _mm512_loadu_pd(src + 40),
            r6 = _mm512_loadu_pd(src + 48), r7 = _mm512_loadu_pd(src + 56);
    // 8x8 transpose: pairs within 128-bit lanes, then 128-bit lanes (two steps)
    __m512d t0 = _mm512_unpacklo_pd(r0, r1), t1 = _mm512_unpackhi_pd(r0, r1), t2 = _mm512_unpacklo_pd(r2, r3),
            t3 = _mm512_unpackhi_pd(r2, r3), t4 = _mm512_unpacklo_pd(r4, r5), t5 = _mm512_unpackhi_pd(r4, r5),
            t6 = _mm512_unpacklo_pd(r6, r7), t7 = _mm512_unpackhi_pd(r6, r7);
    __m512d u0 = _mm512_shuffle_f64x2(t0, t2, 0x88), u1 = _mm512_shuffle_f64x2(t1, t3, 0x88),
            u2 = _mm512_shuffle_f64x2(t0, t2, 0xdd), u3 = _mm512_shuffle_f64x2(t1, t3, 0xdd),
            u4 = _mm512_shuffle_f64x2(t4, t6, 0x88), u5 = _mm512_shuffle_f64x2(t5, t7, 0x88),
            u6 = _mm512_shuffle_f64x2(t4, t6, 0xdd), u7 = _mm512_shuffle_f64x2(t5, t7, 0xdd);
    double* dst = out + 8 * j;
    _mm512_stream_pd(dst, _mm512_shuffle_f64x2(u0, u4, 0x88));
    _mm512_stream_pd(dst + 144, _mm512_shuffle_f64x2(u1, u5, 0x88));
    _mm512_stream_pd(dst + 288, _mm512_shuffle_f64x2(u2, u6, 0x88));
    _mm512_stream_pd(dst + 432, _mm512_shuffle_f64x2(u3, u7, 0x88));
    _mm512_stream_pd(dst + 576, _mm512_shuffle_f64x2(u0, u4, 0xdd));
    _mm512_stream_pd(dst + 720, _mm512_shuffle_f64x2(u1, u5, 0xdd));
    _mm512_stream_pd(dst + 864, _mm512_shuffle_f64x2(u2, u6, 0xdd));
    _mm512_stream_pd(dst + 1008, _mm512_shuffle_f64x2(u3, u7, 0xdd));
  }
#else
  (void)b; (void)out;
#endif
}

static inline void stream_tile(const Blocks<float, W>& b, float* out) {
#if defined(__AVX__)
  for (int j = 0; j < 18; ++j) {
    const float* src = &b.O[8 * j][0];
    __m256 r0 = _mm256_loadu_ps(src), r1 = _mm256_loadu_ps(src + 8), r2 = _mm256_loadu_ps(src + 16),
           r3 = _mm256_loadu_ps(src + 24), r4 = _mm256_loadu_ps(src + 32), r5 = _mm256_loadu_ps(src + 40),
           r6 = _mm256_loadu_ps(src + 48), r7 = _mm256_loadu_ps(src + 56);
    __m256 t0 = _mm256_unpacklo_ps(r0, r1), t1 = _mm256_unpackhi_ps(r0, r1), t2 = _mm256_unpacklo_ps(r2, r3),
           t3 = _mm256_unpackhi_ps(r2, r3), t4 = _mm256_unpacklo_ps(r4, r5), t5 = _mm256_unpackhi_ps(r4, r5),
           t6 = _mm256_unpacklo_ps(r6, r7), t7 = _mm256_unpackhi_ps(r6, r7);
    __m256 u0 = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(1, 0, 1, 0)), u1 = _mm256_shuffle_ps(t0, t2, _MM_SHUFFLE(3, 2, 3, 2)),
           u2 = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(1, 0, 1, 0)), u3 = _mm256_shuffle_ps(t1, t3, _MM_SHUFFLE(3, 2, 3, 2)),
           u4 = _mm256_shuffle_ps(t4, t6, _MM_SHUFFLE(1, 0, 1, 0)), u5 = _mm256_shuffle_ps(t4, t6, _MM_SHUFFLE(3, 2, 3, 2)),
           u6 = _mm256_shuffle_ps(t5, t7, _MM_SHUFFLE(1, 0, 1, 0)), u7 = _mm256_shuffle_ps(t5, t7, _MM_SHUFFLE(3, 2, 3, 2));
    float* dst = out + 8 * j;
    _mm256_stream_ps(dst, _mm256_permute2f128_ps(u0, u4, 0x20));
    _mm256_stream_ps(dst + 144, _mm256_permute2f128_ps(u1, u5, 0x20));
    _mm256_stream_ps(dst + 288, _mm256_permute2f128_ps(u2, u6, 0x20));
    _mm256_stream_ps(dst + 432, _mm256_permute2f128_ps(u3, u7, 0x20));
    _mm256_stream_ps(dst + 576, _mm256_permute2f128_ps(u0, u4, 0x31));
    _mm256_stream_ps(dst + 720, _mm256_permute2f128_ps(u1, u5, 0x31));
    _mm256_stream_ps(dst + 864, _mm256_permute2f128_ps(u2, u6, 0x31));
    _mm256_stream_ps(dst + 1008, _mm256_permute2f128_ps(u3, u7, 0x31));
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
      int64_t b = bh0 / H, h = bh0 - b * H;  // one division per tile
      for (int l = 0; l < nl; ++l) {
        bs[l] = b; hs[l] = h;
        if (++h == H) { h = 0; ++b; }
      }
      gather_tile<T>(xp, nullptr, hp, V, args, nullptr, nl, bs, hs, X, nullptr, Q);
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
  auto out = output(out_, shape_with(P.batch, {P.H, 12, 12}), P.x, "out (blocks)");
  auto g = output(gout_, shape_with(P.batch, {P.H, 12}), P.x, "out (gradients)");
  TORCH_CHECK(disjoint(out, g), "the two out buffers overlap");
  auto d2 = torch::empty(shape_with(P.batch, {P.H}), P.x.options()), theta = torch::empty_like(d2);
  if (check && finite_status(P.x, kBadX)) return {out, g, d2, theta, kBadX};
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

// ----------------------------------------------------------------------------------------------
// PSD projection of symmetric blocks (torchbend.ops.projection: clamp Q max(L, 0) Q^T, abs Q |L| Q^T) by cyclic
// Jacobi, W blocks at a time with every rotation vectorized across the lanes.  Each block is symmetrized and
// scaled by its largest entry (no overflow or underflow in the rotations, whatever the units), swept until
// the off-diagonal part is below eps / 100 of the whole in every lane (quadratic convergence: 6-8 sweeps for
// the 12x12 hinge blocks), and rebuilt as sum_k f(l_k) v_k v_k^T.  Jacobi's eigenvalues are accurate to the
// block's norm times eps, as eigh's.

// A (N x N per lane, symmetric) <- its projection, in place
template <typename T, int N>
static void jacobi_project(T (&A)[N][N][W], bool abs_mode) {
  alignas(64) T V[N][N][W];
  T scale[W];
  for (int l = 0; l < W; ++l) {
    T mx = T(0);
    for (int i = 0; i < N; ++i)
      for (int j = 0; j < N; ++j) mx = std::max(mx, std::abs(A[i][j][l]));
    scale[l] = mx > T(0) && std::isfinite(mx) ? mx : T(1);
  }
  for (int i = 0; i < N; ++i)
    for (int j = 0; j < N; ++j)
#pragma omp simd
      for (int l = 0; l < W; ++l) {
        A[i][j][l] /= scale[l];
        V[i][j][l] = i == j ? T(1) : T(0);
      }
  // rotations of |a_pq| <= skip (the blocks are scaled to entries of at most 1, so |A| >= 1) are left out: they
  // change the result by less than eps / 1000 of |A|; the sweeps stop when the off-diagonal part is below
  // eps / 100 of |A| in every lane (the skipped entries together stay below that: N^2 skip^2 < 1e-4 eps^2)
  constexpr T eps = std::numeric_limits<T>::epsilon(), skip = eps * T(1e-3);
  for (int sweep = 0; sweep < 30; ++sweep) {
    bool done = true;
    for (int l = 0; l < W; ++l) {
      T off = T(0), all = T(0);
      for (int i = 0; i < N; ++i) {
        all += A[i][i][l] * A[i][i][l];
        for (int j = i + 1; j < N; ++j) off += A[i][j][l] * A[i][j][l];
      }
      done = done && off <= eps * eps * T(1e-4) * (all + T(2) * off);
    }
    if (done) break;
    for (int p = 0; p < N - 1; ++p)
      for (int q = p + 1; q < N; ++q) {
        T c[W], sn[W], t[W], big = T(0);
        for (int l = 0; l < W; ++l) big = std::max(big, std::abs(A[p][q][l]));
        if (big <= skip) continue;  // below what the result can resolve in every lane
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T apq = A[p][q][l], tau = A[q][q][l] - A[p][p][l];
          T den = std::abs(tau) + std::sqrt(tau * tau + T(4) * apq * apq);
          t[l] = den > T(0) ? T(2) * apq * (tau >= T(0) ? T(1) : T(-1)) / den : T(0);
          c[l] = T(1) / std::sqrt(T(1) + t[l] * t[l]);
          sn[l] = t[l] * c[l];
        }
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T apq = A[p][q][l];
          A[p][p][l] -= t[l] * apq;
          A[q][q][l] += t[l] * apq;
          A[p][q][l] = A[q][p][l] = T(0);
        }
        for (int k = 0; k < N; ++k) {
          if (k == p || k == q) continue;
#pragma omp simd
          for (int l = 0; l < W; ++l) {
            T akp = A[k][p][l], akq = A[k][q][l];
            A[k][p][l] = A[p][k][l] = c[l] * akp - sn[l] * akq;
            A[k][q][l] = A[q][k][l] = sn[l] * akp + c[l] * akq;
          }
        }
        for (int k = 0; k < N; ++k) {
#pragma omp simd
          for (int l = 0; l < W; ++l) {
            T vkp = V[k][p][l], vkq = V[k][q][l];
            V[k][p][l] = c[l] * vkp - sn[l] * vkq;
            V[k][q][l] = sn[l] * vkp + c[l] * vkq;
          }
        }
      }
  }
  T f[N][W];
  for (int k = 0; k < N; ++k)
#pragma omp simd
    for (int l = 0; l < W; ++l) {
      T lk = A[k][k][l];
      f[k][l] = (abs_mode ? std::abs(lk) : std::max(lk, T(0))) * scale[l];
    }
  for (int i = 0; i < N; ++i)
    for (int j = i; j < N; ++j) {
      T acc[W];
#pragma omp simd
      for (int l = 0; l < W; ++l) acc[l] = T(0);
      for (int k = 0; k < N; ++k)
#pragma omp simd
        for (int l = 0; l < W; ++l) acc[l] += V[i][k][l] * f[k][l] * V[j][k][l];
#pragma omp simd
      for (int l = 0; l < W; ++l) A[i][j][l] = A[j][i][l] = acc[l];
    }
}

// (M + M^T) / 2 of the first nl blocks at `in` (N x N each) into A (zeros in the other lanes)
template <typename T, int N>
static void load_symmetric(const T* in, int nl, T (&A)[N][N][W]) {
  for (int l = 0; l < W; ++l)
    for (int i = 0; i < N; ++i)
      for (int j = 0; j < N; ++j)
        A[i][j][l] = l < nl ? T(0.5) * (in[l * N * N + i * N + j] + in[l * N * N + j * N + i]) : T(0);
}

template <typename T, int N>
static void store_blocks(const T (&A)[N][N][W], int nl, T* out) {
  for (int l = 0; l < nl; ++l)
    for (int i = 0; i < N; ++i)
      for (int j = 0; j < N; ++j) out[l * N * N + i * N + j] = A[i][j][l];
}

// Hinge blocks (4 vertices x 3) are invariant under translations (rows and columns of each 3x3 block row sum to
// zero): with U (12 x 9) an orthonormal basis of the translations' complement, H = U (U^T H U) U^T and its
// projection is U proj(U^T H U) U^T, a 9x9 eigenproblem instead of 12x12 (0.42 of the work).  U = h^T (x) I3,
// h the orthonormal (Helmert) rows (1, -1, 0, 0) / sqrt 2, (1, 1, -2, 0) / sqrt 6, (1, 1, 1, -3) / sqrt 12.
template <typename T>
static void project_hinge_tile(const T* in, T* out, int nl, bool abs_mode) {
  const T r2 = T(1) / std::sqrt(T(2)), r6 = T(1) / std::sqrt(T(6)), r12 = T(1) / std::sqrt(T(12));
  const T h[3][4] = {{r2, -r2, T(0), T(0)}, {r6, r6, T(-2) * r6, T(0)}, {r12, r12, r12, T(-3) * r12}};
  alignas(64) T S[12][12][W], T1[12][9][W], A[9][9][W];
  load_symmetric<T, 12>(in, nl, S);
  for (int r = 0; r < 12; ++r)  // T1 = S U
    for (int c = 0; c < 3; ++c)
      for (int j = 0; j < 3; ++j)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int a = 0; a < 4; ++a) acc += S[r][3 * a + j][l] * h[c][a];
          T1[r][3 * c + j][l] = acc;
        }
  for (int b = 0; b < 3; ++b)  // A = U^T T1
    for (int i = 0; i < 3; ++i)
      for (int cc = 0; cc < 9; ++cc)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int a = 0; a < 4; ++a) acc += h[b][a] * T1[3 * a + i][cc][l];
          A[3 * b + i][cc][l] = acc;
        }
  for (int i = 0; i < 9; ++i)  // exactly symmetric before the sweeps
    for (int j = i + 1; j < 9; ++j)
#pragma omp simd
      for (int l = 0; l < W; ++l) A[i][j][l] = A[j][i][l] = T(0.5) * (A[i][j][l] + A[j][i][l]);
  jacobi_project<T, 9>(A, abs_mode);
  for (int r = 0; r < 9; ++r)  // T1^T = P U^T: T1[c'][r] = sum_c P[r][c] U[c'][c]
    for (int a = 0; a < 4; ++a)
      for (int j = 0; j < 3; ++j)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int c = 0; c < 3; ++c) acc += A[r][3 * c + j][l] * h[c][a];
          T1[3 * a + j][r][l] = acc;
        }
  for (int a = 0; a < 4; ++a)  // out = U (P U^T): out[3a+i][col] = sum_b h[b][a] T1[col][3b+i]
    for (int i = 0; i < 3; ++i)
      for (int col = 0; col < 12; ++col)
#pragma omp simd
        for (int l = 0; l < W; ++l) {
          T acc = T(0);
          for (int b = 0; b < 3; ++b) acc += h[b][a] * T1[col][3 * b + i][l];
          S[3 * a + i][col][l] = acc;
        }
  for (int i = 0; i < 12; ++i)
    for (int j = i + 1; j < 12; ++j)
#pragma omp simd
      for (int l = 0; l < W; ++l) S[i][j][l] = S[j][i][l] = T(0.5) * (S[i][j][l] + S[j][i][l]);
  store_blocks<T, 12>(S, nl, out);
}

// The `reduced` projection of hinge blocks (torchbend.ops.projection): the lower-right 9x9 block (the Hessian in
// y_k = x_k - x_0) clamped, then D^T P D back to 12x12 (block row and column 0: minus the sums of the others)
template <typename T>
static void project_reduced_tile(const T* in, T* out, int nl) {
  alignas(64) T A[9][9][W];
  for (int l = 0; l < W; ++l)
    for (int i = 0; i < 9; ++i)
      for (int j = 0; j < 9; ++j)
        A[i][j][l] = l < nl ? T(0.5) * (in[l * 144 + (i + 3) * 12 + j + 3] + in[l * 144 + (j + 3) * 12 + i + 3]) : T(0);
  jacobi_project<T, 9>(A, false);
  for (int l = 0; l < nl; ++l) {
    T* o = out + l * 144;
    for (int i = 0; i < 9; ++i)
      for (int j = 0; j < 9; ++j) o[(i + 3) * 12 + j + 3] = A[i][j][l];
    for (int p = 0; p < 3; ++p)
      for (int c = 3; c < 12; ++c) {  // row p of block row 0 and, by symmetry, column p
        T s = T(0);
        for (int k = 0; k < 3; ++k) s += o[(3 * (k + 1) + p) * 12 + c];
        o[p * 12 + c] = o[c * 12 + p] = -s;
      }
    for (int p = 0; p < 3; ++p)
      for (int q = 0; q < 3; ++q) {
        T s = T(0);
        for (int k = 0; k < 3; ++k) s += o[p * 12 + 3 * (k + 1) + q];
        o[p * 12 + q] = -s;
      }
  }
}

template <typename T, int N>
static void project_tile(const T* in, T* out, int nl, bool abs_mode) {
  alignas(64) T A[N][N][W];
  load_symmetric<T, N>(in, nl, A);
  jacobi_project<T, N>(A, abs_mode);
  store_blocks<T, N>(A, nl, out);
}

// the PSD projection (mode 0: clamp, 1: abs) of symmetric blocks M (..., n, n), n = 9 or 12; with `hinge`, 12x12
// blocks invariant under translations of their 4 vertices, projected in the translations' complement, or by
// mode 2 (reduced, hinge blocks only): a new tensor
torch::Tensor project_blocks(torch::Tensor M, int64_t mode, bool hinge) {
  const char* op = "project_blocks";
  namespace ck = torchbend::checks;
  ck::require(M.device().is_cpu() && M.dim() >= 2 && M.size(-1) == M.size(-2) && (M.size(-1) == 9 || M.size(-1) == 12),
              op, "M must be a CPU (..., n, n) tensor with n 9 or 12, got ", ck::shape_str(M), " on ", M.device());
  ck::require(M.scalar_type() == torch::kFloat || M.scalar_type() == torch::kDouble, op,
              "M must be float32 or float64, got ", M.scalar_type());
  ck::require(mode >= 0 && mode <= 2 && (mode < 2 || (hinge && M.size(-1) == 12)), op,
              "mode must be 0 (clamp), 1 (abs) or, for 12x12 hinge blocks, 2 (reduced), got ", mode);
  if (finite_status(M.contiguous(), 1)) {
    auto bad = M.isfinite().logical_not().reshape({-1, M.size(-1) * M.size(-1)}).any(1).nonzero();
    ck::fail(op, "M holds non-finite values (first in block ", bad[0][0].item<int64_t>(), " of the flattened batch)");
  }
  const bool abs_mode = mode == 1;
  M = M.contiguous();
  const int64_t n = M.size(-1), count = n ? M.numel() / (n * n) : 0;
  auto out = pooled_empty(M.sizes().vec(), M.options());
  AT_DISPATCH_FLOATING_TYPES(M.scalar_type(), "project_blocks", [&] {
    const scalar_t* in = M.data_ptr<scalar_t>();
    scalar_t* o = out.data_ptr<scalar_t>();
    const int64_t tiles = (count + W - 1) / W;
    at::parallel_for(0, tiles, 16, [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t) {
        int nl = int(std::min<int64_t>(W, count - t * W));
        if (mode == 2) project_reduced_tile<scalar_t>(in + t * W * 144, o + t * W * 144, nl);
        else if (n == 12 && hinge) project_hinge_tile<scalar_t>(in + t * W * 144, o + t * W * 144, nl, abs_mode);
        else if (n == 12) project_tile<scalar_t, 12>(in + t * W * 144, o + t * W * 144, nl, abs_mode);
        else project_tile<scalar_t, 9>(in + t * W * 81, o + t * W * 81, nl, abs_mode);
      }
    });
  });
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("bending_hessians", &bending_hessians, "fused gather, angle, psi and per-hinge blocks");
  m.def("assemble", &assemble, "CSR values of the bending Hessian of one mesh, per hinge or per triangle");
  m.def("bending_energy", &bending_energy, "per-hinge energies and angles");
  m.def("bending_gradient", &bending_gradient, "weighted gradient in positions and per-hinge parameter gradients");
  m.def("bending_energy_gradient", &bending_energy_gradient,
        "per-hinge energies with the gradient in positions and the per-hinge parameter gradients, one pass");
  m.def("bending_hvp", &bending_hvp, "weighted Hessian-vector product in positions");
  m.def("bending_second_order", &bending_second_order,
        "the general double backward: position and parameter directions, per-hinge weight");
  m.def("output_cache_info", &output_cache_info, "(blocks, bytes, hits, misses, limit) of the cache of large outputs");
  m.def("empty_output_cache", &empty_output_cache, "free the memory the cache of large outputs holds");
  m.def("project_blocks", &project_blocks, "PSD projection (clamp, abs; reduced for hinge blocks) of symmetric 9x9 or 12x12 blocks, Jacobi");
  m.def("set_output_cache_limit", &set_output_cache_limit, "the most bytes the cache of large outputs keeps");
}
