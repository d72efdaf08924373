// Argument checks of the compiled operators (torch.ops.torchbend.*), shared by the CPU driver
// (cpu_*.cpp) and the CUDA binding (cuda_binding.cpp).  Every argument is checked before any work:
// shapes, dtypes and devices, the values of every index argument (hinge indices, incidence lists, the
// sparsity pattern of `assemble`, face and face-edge indices), the viscous pair.  A bad argument is a
// c10::ValueError (Python ValueError) naming the operator, the argument and its first offending entry, e.g.
//   torchbend.bending_energy: hinges[12, 3] = 100 is out of range [0, 100) (x has V = 100 vertices)
// On the CPU an index check is one branch-free pass over the integers (vectorized, in parallel chunks; a
// second, scalar pass only to locate the first bad entry); on CUDA it is a few tensor operations and one
// synchronization.
#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cstdint>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

namespace torchbend {
namespace checks {

// TORCHBEND_UNCHECKED (benchmarks/bm_checks.py only: a build to time the operators without their value checks)
// turns off every check of index values; the checks of shapes, dtypes and devices stay
#ifdef TORCHBEND_UNCHECKED
constexpr bool kChecked = false;
#else
constexpr bool kChecked = true;
#endif

template <typename... Args> [[noreturn]] inline void fail(const char* op, const Args&... args) {
  std::ostringstream s;
  s << "torchbend." << op << ": ";
  (s << ... << args);
  throw c10::ValueError({__func__, __FILE__, static_cast<uint32_t>(__LINE__)}, s.str());
}

template <typename... Args> inline void require(bool ok, const char* op, const Args&... args) {
  if (!ok) fail(op, args...);
}

// "[i, j]" for the flat position `flat` of t
inline std::string index_str(const torch::Tensor& t, int64_t flat) {
  std::vector<int64_t> idx(t.dim() > 0 ? t.dim() : 1, 0);
  for (int64_t d = t.dim() - 1; d >= 0; --d) {
    int64_t n = t.size(d);
    if (n > 0) { idx[d] = flat % n; flat /= n; }
  }
  std::ostringstream s;
  s << "[";
  for (size_t d = 0; d < idx.size(); ++d) s << (d ? ", " : "") << idx[d];
  s << "]";
  return s.str();
}

inline std::string shape_str(const torch::Tensor& t) {
  std::ostringstream s;
  s << t.sizes();
  return s.str();
}

// 1 if some of the n integers at p lies outside [lo, hi): one branch-free pass (the compiler vectorizes it)
inline int any_outside(const int64_t* p, int64_t n, int64_t lo, int64_t hi) {
  const uint64_t span = uint64_t(hi) - uint64_t(lo), ulo = uint64_t(lo);
  uint64_t bad = 0;
  for (int64_t i = 0; i < n; ++i) bad |= uint64_t(uint64_t(p[i]) - ulo >= span);
  return int(bad);
}

// the first flat position of t (int64, contiguous, CPU or CUDA) whose value lies outside [lo, hi), or -1
inline int64_t first_outside(const torch::Tensor& t, int64_t lo, int64_t hi) {
  const int64_t n = t.numel();
  if (n == 0) return -1;
  if (!t.device().is_cpu()) {
    auto bad = t.reshape(-1).lt(lo).logical_or_(t.reshape(-1).ge(hi));
    if (!bad.any().item<bool>()) return -1;
    return bad.nonzero().select(1, 0)[0].item<int64_t>();
  }
  const int64_t* p = t.data_ptr<int64_t>();
  int bad = n < (int64_t(1) << 16) ? any_outside(p, n, lo, hi)
                                   : at::parallel_reduce(int64_t(0), n, int64_t(1) << 16, 0,
                                                         [&](int64_t b, int64_t e, int acc) {
                                                           return acc | any_outside(p + b, e - b, lo, hi);
                                                         },
                                                         [](int u, int v) { return u | v; });
  if (!bad) return -1;
  const uint64_t span = uint64_t(hi) - uint64_t(lo);
  for (int64_t i = 0; i < n; ++i)
    if (uint64_t(p[i]) - uint64_t(lo) >= span) return i;
  return -1;
}

inline int64_t value_at(const torch::Tensor& t, int64_t flat) {
  return t.device().is_cpu() ? t.data_ptr<int64_t>()[flat] : t.reshape(-1)[flat].item<int64_t>();
}

// t: an int64 tensor on `device` with `cols` columns (cols < 0: any shape), returned contiguous
inline torch::Tensor index_tensor(const char* op, const char* name, const torch::Tensor& t, const c10::Device& device,
                                  int64_t cols = -1) {
  require(t.scalar_type() == torch::kLong, op, name, " must be an int64 tensor, got ", t.scalar_type());
  require(t.device() == device, op, name, " must be on ", device, " (x's device), got ", t.device());
  if (cols >= 0)
    require(t.dim() == 2 && t.size(1) == cols, op, name, " must have shape (n, ", cols, "), got ", shape_str(t));
  return t.contiguous();
}

// every entry of t in [lo, hi); `what` says where the bound comes from
inline void check_range(const char* op, const char* name, const torch::Tensor& t, int64_t lo, int64_t hi,
                        const std::string& what) {
  if (!kChecked) return;
  int64_t i = first_outside(t, lo, hi);
  if (i >= 0)
    fail(op, name, index_str(t, i), " = ", value_at(t, i), " is out of range [", lo, ", ", hi, ") (", what, ")");
}

// the vertex incidence lists of H hinges over V vertices (torchbend.backends.native.incidence), ptr (V + 1,)
// and idx (4 H,): dtypes, devices, sizes, ptr's ends 0 and 4 H.  Their content is checked where a kernel reads
// them, before it does (check_incidence_content: the CPU kernels sum through them only for hinges in no compact
// order; elsewhere they are not read, and a pass over them would cost more than the checks' budget); CUDA
// tensors (never read: the CUDA kernels scatter with atomics) get the range and order checks here
inline void check_incidence(const char* op, const torch::Tensor& ptr, const torch::Tensor& idx, int64_t V, int64_t H) {
  require(ptr.scalar_type() == torch::kLong && idx.scalar_type() == torch::kLong, op,
          "the incidence lists ptr and idx must be int64 tensors, got ", ptr.scalar_type(), " and ", idx.scalar_type());
  require(ptr.device() == idx.device(), op, "the incidence lists ptr and idx must be on one device");
  require(ptr.numel() == V + 1, op, "ptr (incidence lists) must have V + 1 = ", V + 1, " entries, got ", ptr.numel());
  require(idx.numel() == 4 * H, op, "idx (incidence lists) must have 4 H = ", 4 * H, " entries, got ", idx.numel());
  require(ptr.is_contiguous() && idx.is_contiguous(), op, "the incidence lists ptr and idx must be contiguous");
  int64_t first = value_at(ptr, 0), last = value_at(ptr, V);
  require(first == 0 && last == 4 * H, op, "ptr (incidence lists) must run from 0 to 4 H = ", 4 * H, ", got ", first,
          " .. ", last);
  if (!kChecked || V == 0 || ptr.device().is_cpu()) return;  // CPU: the content where a kernel reads them
  check_range(op, "idx", idx, 0, 4 * H, "stencil slots 4 h + s of H = " + std::to_string(H) + " hinges");
  auto p = ptr.reshape(-1);
  int64_t i = first_outside(p.slice(0, 1).sub(p.slice(0, 0, V)), 0, std::numeric_limits<int64_t>::max());
  if (i >= 0) fail(op, "ptr (incidence lists) must be nondecreasing: ptr[", i + 1, "] < ptr[", i, "]");
}

// the content of CPU incidence lists that passed check_incidence, before a kernel sums through them: ptr
// nondecreasing, and ptr[v] .. ptr[v + 1] lists exactly the stencil slots 4 h + s with hinges[h, s] = v (hp: the
// (H, 4) hinges, in range), each once
inline void check_incidence_content(const char* op, const int64_t* pp, const int64_t* qq, const int64_t* hp, int64_t V,
                                    int64_t H) {
  if (!kChecked) return;
  for (int64_t v = 0; v < V; ++v)
    if (pp[v + 1] < pp[v]) fail(op, "ptr (incidence lists) must be nondecreasing: ptr[", v + 1, "] < ptr[", v, "]");
  std::vector<uint8_t> seen(size_t(4 * H), 0);
  for (int64_t v = 0; v < V; ++v)
    for (int64_t j = pp[v]; j < pp[v + 1]; ++j) {
      int64_t i = qq[j];
      if (uint64_t(i) >= uint64_t(4 * H))
        fail(op, "idx[", j, "] = ", i, " is out of range [0, ", 4 * H, ") (stencil slots 4 h + s of H = ", H,
             " hinges)");
      if (hp[i] != v || seen[size_t(i)])
        fail(op, "idx[", j, "] = ", i, " is not an incidence of vertex ", v, " (hinges[", i / 4, ", ", i % 4, "] = ",
             hp[i], seen[size_t(i)] ? ", and slot listed twice" : "", "): not the incidence lists of these hinges");
      seen[size_t(i)] = 1;
    }
}

}  // namespace checks
}  // namespace torchbend
