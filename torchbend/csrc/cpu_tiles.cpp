// The CPU driver's shared non-template pieces (cpu_tiles.h, cpu_scatter.h): the status scans, the output
// buffers, the argument checks, the scratch memory and the scatter plan.
#include <algorithm>
#include <cstdlib>
#include <mutex>
#include <sys/mman.h>
#include <unistd.h>

#include <ATen/Parallel.h>

#include "cpu_ops.h"
#include "cpu_scatter.h"

namespace torchbend {
namespace cpu {

int64_t finite_status(const torch::Tensor& t, int64_t flag) {
  bool ok = true;
  AT_DISPATCH_FLOATING_TYPES(t.scalar_type(), "finite_status", [&] { ok = all_finite(t.data_ptr<scalar_t>(), t.numel()); });
  return ok ? 0 : flag;
}

// kFolded if a tan hinge (model 1) has |theta| >= pi (pi rounded to theta's dtype, as check_fold compares)
int64_t fold_status(const torch::Tensor& theta, int64_t model) {
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
// Fresh memory is zeroed by the operating system before its first use: for the per-hinge blocks (1152 bytes a
// hinge in float64) the page faults cost more than the kernel itself (benchmarks/results/backends_registration.txt),
// populating the pages in one pass about as much as the kernel.  By default a large
// output (kPoolMin bytes or more) is a plain torch::empty tensor (PyTorch's allocator: nothing is kept once it
// is released) whose 2 MiB-aligned interior is advised to transparent huge pages before its first touch
// (fewer, larger faults where the kernel's THP mode is "madvise" or "always") and whose pages are then
// populated in one pass (populate_pages).  Callers that ask for the blocks
// in a loop keep their own buffers (out=, bending_hessians), or opt in to a cache of released outputs:
// TORCHBEND_OUTPUT_CACHE_MB megabytes (unset or 0: no cache) or
// torchbend.backends.native.set_output_cache_limit(megabytes).  The cache keeps at most kPoolBlocks released
// blocks and `limit` bytes, matched by exact size; torchbend.backends.native.empty_output_cache() frees them.
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
    const char* env = std::getenv("TORCHBEND_OUTPUT_CACHE_MB");  // opt-in: unset, no cache
    p->limit = env ? size_t(std::max(0L, std::atol(env))) << 20 : 0;
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

// The whole pages inside [p, p + bytes) faulted in now, writable, by madvise(MADV_POPULATE_WRITE) (Linux 5.14+;
// an older kernel answers EINVAL and the pages fault on first touch as before; other systems: a no-op): one system
// call a chunk instead of a fault a page, which halves the cost of fresh memory (on a 2-core Xeon VM, 115 MB:
// 27-30 ms of faults against 13 ms populated; benchmarks/results/populate_outputs_intel_2026-12-06.txt).  The
// 8 MiB chunks (on 2 MiB boundaries: a huge page is never split between threads) are shared out over the threads.
#if defined(__linux__) && !defined(MADV_POPULATE_WRITE)
#define MADV_POPULATE_WRITE 23  // the kernel's value; headers older than Linux 5.14 lack the name
#endif
static void populate_pages(void* p, size_t bytes) {
#ifdef MADV_POPULATE_WRITE
  static const size_t page = size_t(sysconf(_SC_PAGESIZE));
  constexpr size_t chunk = size_t(8) << 20;
  uintptr_t lo = (reinterpret_cast<uintptr_t>(p) + page - 1) / page * page;
  uintptr_t hi = (reinterpret_cast<uintptr_t>(p) + bytes) / page * page;
  if (hi <= lo) return;
  uintptr_t base = lo / chunk * chunk;
  int64_t chunks = int64_t((hi - base + chunk - 1) / chunk);
  at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      uintptr_t a = std::max<uintptr_t>(lo, base + uintptr_t(c) * chunk);
      uintptr_t b = std::min<uintptr_t>(hi, base + uintptr_t(c + 1) * chunk);
      madvise(reinterpret_cast<void*>(a), b - a, MADV_POPULATE_WRITE);  // failure: the pages fault on first touch
    }
  });
#else
  (void)p; (void)bytes;
#endif
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
  populate_pages(ptr, bytes);
  return ptr;
}

// the whole 2 MiB pages inside [p, p + bytes) advised to transparent huge pages (before their first touch)
static void advise_huge_pages(void* p, size_t bytes) {
#ifdef MADV_HUGEPAGE
  uintptr_t lo = (reinterpret_cast<uintptr_t>(p) + kPoolAlign - 1) / kPoolAlign * kPoolAlign;
  uintptr_t hi = (reinterpret_cast<uintptr_t>(p) + bytes) / kPoolAlign * kPoolAlign;
  if (hi > lo) madvise(reinterpret_cast<void*>(lo), hi - lo, MADV_HUGEPAGE);
#else
  (void)p; (void)bytes;
#endif
}

// torch::empty(shape); for large outputs with huge pages advised and the pages populated, or with the opt-in
// cache a block of it
torch::Tensor pooled_empty(const std::vector<int64_t>& shape, const torch::TensorOptions& options) {
  int64_t n = 1;
  for (auto s : shape) n *= s;
  size_t bytes = size_t(n) * options.dtype().itemsize();
  if (bytes < kPoolMin) return torch::empty(shape, options);
  if (output_pool().limit == 0) {
    torch::Tensor t = torch::empty(shape, options);
    advise_huge_pages(t.data_ptr(), bytes);
    populate_pages(t.data_ptr(), bytes);
    return t;
  }
  size_t rounded = (bytes + kPoolAlign - 1) / kPoolAlign * kPoolAlign;
  void* ptr = pool_acquire(rounded);
  return torch::from_blob(ptr, shape, [rounded](void* q) { pool_release(q, rounded); }, options);
}

// (blocks held, bytes held, hits, misses, limit in bytes) of the output cache
std::tuple<int64_t, int64_t, int64_t, int64_t, int64_t> output_cache_info() {
  OutputPool& P = output_pool();
  std::lock_guard<std::mutex> lock(P.mu);
  return {int64_t(P.blocks.size()), int64_t(P.held), P.hits, P.misses, int64_t(P.limit)};
}

void empty_output_cache() {
  OutputPool& P = output_pool();
  std::vector<std::pair<void*, size_t>> drop;
  {
    std::lock_guard<std::mutex> lock(P.mu);
    drop.swap(P.blocks);
    P.held = 0;
  }
  for (auto& b : drop) std::free(b.first);
}

void set_output_cache_limit(int64_t bytes) {
  OutputPool& P = output_pool();
  {
    std::lock_guard<std::mutex> lock(P.mu);
    P.limit = size_t(std::max<int64_t>(0, bytes));
  }
  if (P.held > P.limit) empty_output_cache();
}

bool disjoint(const torch::Tensor& t, const torch::Tensor& u) {
  auto p = reinterpret_cast<uintptr_t>(t.data_ptr()), q = reinterpret_cast<uintptr_t>(u.data_ptr());
  return p + t.nbytes() <= q || q + u.nbytes() <= p;
}

// A caller-provided output buffer (out=): a contiguous CPU tensor of x's dtype and exactly the output's
// shape, not overlapping x; without one a new tensor (pooled_empty).
torch::Tensor output(const c10::optional<torch::Tensor>& buf, const std::vector<int64_t>& shape,
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

void check_hinge_range(const char* op, const torch::Tensor& hinges, int64_t V) {
  torchbend::checks::check_range(op, "hinges", hinges, 0, V, "x has V = " + std::to_string(V) + " vertices");
}

// the arguments shared by the bending operators, checked (torchbend/csrc/checks.h) before any work: x a CPU
// float32/float64 (..., V, 3) tensor, hinges an int64 (H, 4) tensor of vertex indices in [0, V), the per-hinge
// parameters CPU tensors of 1, H or (prev) B*H values, c and prev both given or both absent
Prepared prepare(const char* op, torch::Tensor x, torch::Tensor hinges, torch::Tensor a, torch::Tensor k,
                        torch::Tensor rest, const c10::optional<torch::Tensor>& c_,
                        const c10::optional<torch::Tensor>& prev_, int64_t model, bool check_hinges,
                        bool batched_params) {
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


Scratch scratch(size_t bytes) {
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

ScatterPlan scatter_plan(const int64_t* hp, int64_t H, int64_t V) {
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

torch::Tensor prepare_weight(const char* op, torch::Tensor weight, const Prepared& P) {
  namespace ck = torchbend::checks;
  ck::require(weight.device().is_cpu() && weight.is_floating_point(), op,
              "weight must be a floating-point CPU tensor, got ", weight.scalar_type(), " on ", weight.device());
  ck::require(weight.numel() == 1 || weight.numel() == P.H || weight.numel() == P.B * P.H, op, "weight has ",
              weight.numel(), " values; expected 1, H = ", P.H, " or B*H = ", P.B * P.H);
  return as_dtype(weight, P.x.scalar_type());
}

// a direction v of x's shape, dtype and device
void check_direction(const char* op, const torch::Tensor& v, const Prepared& P) {
  torchbend::checks::require(v.sizes() == P.x.sizes() && v.scalar_type() == P.x.scalar_type() && v.device().is_cpu(),
                             op, "v must be a CPU tensor of x's shape ", torchbend::checks::shape_str(P.x),
                             " and dtype ", P.x.scalar_type(), ", got ", torchbend::checks::shape_str(v), " ",
                             v.scalar_type(), " on ", v.device());
}

// (psi (..., H), theta (..., H), status): the per-hinge energies (summed by the caller per mesh or segment);

}  // namespace cpu
}  // namespace torchbend
