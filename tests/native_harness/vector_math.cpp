// Torch-free harness of the vectorizable math of torchbend/csrc/vector_math.h (tb_atan2v, tb_sincos_accurate
// ("sincos"), tb_sincos ("sincos_fast"), tb_half_sincos, tb_half_sincos_tan ("half_sct"), tb_logv), built as a shared library by tests/test_vector_math_ulp.py with the CPU extension's
// flags and loaded with ctypes.  The *_vec loops are written as the kernels' lane loops are (a plain loop
// with the header's functions inlined, TB_IVDEP), so that GCC vectorizes them; the *_scalar loops call one
// non-inlined scalar evaluation per element (the code a loop that does not vectorize runs).
#include "torchbend/csrc/vector_math.h"

using torchbend::tb_atan2v;
using torchbend::tb_half_sincos;
using torchbend::tb_half_sincos_tan;
using torchbend::tb_logv;
using torchbend::tb_sincos;
using torchbend::tb_sincos_accurate;

namespace {
template <typename T> __attribute__((noinline)) T atan2_one(T y, T x) { return tb_atan2v(y, x); }
template <typename T> __attribute__((noinline)) void sincos_one(T x, T* s, T* c) { tb_sincos_accurate(x, *s, *c); }
template <typename T> __attribute__((noinline)) void sincos_fast_one(T x, T* s, T* c) { tb_sincos(x, *s, *c); }
template <typename T> __attribute__((noinline)) void half_one(T x, T* s, T* c) { tb_half_sincos(x, *s, *c); }
template <typename T> __attribute__((noinline)) void half_sct_one(T x, T* s, T* c, T* u) { tb_half_sincos_tan(x, *s, *c, *u); }
template <typename T> __attribute__((noinline)) T log_one(T x) { return tb_logv(x); }
}  // namespace

#define TB_HARNESS(T, SUFFIX)                                                                              \
  void tb_atan2_vec_##SUFFIX(const T* __restrict y, const T* __restrict x, T* __restrict o, long n) {      \
    TB_IVDEP for (long i = 0; i < n; ++i) o[i] = tb_atan2v(y[i], x[i]);                                    \
  }                                                                                                        \
  void tb_atan2_scalar_##SUFFIX(const T* y, const T* x, T* o, long n) {                                    \
    for (long i = 0; i < n; ++i) o[i] = atan2_one<T>(y[i], x[i]);                                          \
  }                                                                                                        \
  void tb_sincos_vec_##SUFFIX(const T* __restrict x, T* __restrict s, T* __restrict c, long n) {           \
    TB_IVDEP for (long i = 0; i < n; ++i) {                                                                \
      T si, ci;                                                                                            \
      tb_sincos_accurate(x[i], si, ci);                                                                    \
      s[i] = si; c[i] = ci;                                                                                \
    }                                                                                                      \
  }                                                                                                        \
  void tb_sincos_scalar_##SUFFIX(const T* x, T* s, T* c, long n) {                                         \
    for (long i = 0; i < n; ++i) sincos_one<T>(x[i], s + i, c + i);                                        \
  }                                                                                                        \
  void tb_sincos_fast_vec_##SUFFIX(const T* __restrict x, T* __restrict s, T* __restrict c, long n) {      \
    TB_IVDEP for (long i = 0; i < n; ++i) {                                                                \
      T si, ci;                                                                                            \
      tb_sincos(x[i], si, ci);                                                                             \
      s[i] = si; c[i] = ci;                                                                                \
    }                                                                                                      \
  }                                                                                                        \
  void tb_sincos_fast_scalar_##SUFFIX(const T* x, T* s, T* c, long n) {                                    \
    for (long i = 0; i < n; ++i) sincos_fast_one<T>(x[i], s + i, c + i);                                   \
  }                                                                                                        \
  void tb_half_sincos_vec_##SUFFIX(const T* __restrict x, T* __restrict s, T* __restrict c, long n) {      \
    TB_IVDEP for (long i = 0; i < n; ++i) {                                                                \
      T si, ci;                                                                                            \
      tb_half_sincos(x[i], si, ci);                                                                        \
      s[i] = si; c[i] = ci;                                                                                \
    }                                                                                                      \
  }                                                                                                        \
  void tb_half_sincos_scalar_##SUFFIX(const T* x, T* s, T* c, long n) {                                    \
    for (long i = 0; i < n; ++i) half_one<T>(x[i], s + i, c + i);                                          \
  }                                                                                                        \
  void tb_half_sct_vec_##SUFFIX(const T* __restrict x, T* __restrict s, T* __restrict c, T* __restrict u,     \
                                long n) {                                                                  \
    TB_IVDEP for (long i = 0; i < n; ++i) {                                                                \
      T si, ci, ui;                                                                                        \
      tb_half_sincos_tan(x[i], si, ci, ui);                                                                \
      s[i] = si; c[i] = ci; u[i] = ui;                                                                     \
    }                                                                                                      \
  }                                                                                                        \
  void tb_half_sct_scalar_##SUFFIX(const T* x, T* s, T* c, T* u, long n) {                                 \
    for (long i = 0; i < n; ++i) half_sct_one<T>(x[i], s + i, c + i, u + i);                               \
  }                                                                                                        \
  void tb_log_vec_##SUFFIX(const T* __restrict x, T* __restrict o, long n) {                               \
    TB_IVDEP for (long i = 0; i < n; ++i) o[i] = tb_logv(x[i]);                                            \
  }                                                                                                        \
  void tb_log_scalar_##SUFFIX(const T* x, T* o, long n) {                                                  \
    for (long i = 0; i < n; ++i) o[i] = log_one<T>(x[i]);                                                  \
  }

extern "C" {
TB_HARNESS(double, f64)
TB_HARNESS(float, f32)
}
