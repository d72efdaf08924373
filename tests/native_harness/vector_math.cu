// Compile-only check (tests/test_vector_math_ulp.py, when nvcc is found) that the vectorizable math of
// torchbend/csrc/vector_math.h (tb_atan2v, tb_sincos, tb_half_sincos, tb_half_sincos_tan, tb_floorv, tb_ceilv)
// compiles as CUDA device code: one definition serves the CPU lane loops and the GPU.
#include "torchbend/csrc/vector_math.h"

template <typename T>
__global__ void tb_vector_math_kernel(const T* y, const T* x, T* out, int n) {
  int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n) return;
  T s, c, hs, hc, ts, tc, tu;
  torchbend::tb_sincos(x[i], s, c);
  torchbend::tb_half_sincos(y[i], hs, hc);
  torchbend::tb_half_sincos_tan(x[i], ts, tc, tu);
  out[i] = torchbend::tb_atan2v(y[i], x[i]) + s + c + hs / hc + torchbend::tb_floorv(x[i]) +
           torchbend::tb_ceilv(y[i]) + ts * tc * tu;
}

template __global__ void tb_vector_math_kernel<float>(const float*, const float*, float*, int);
template __global__ void tb_vector_math_kernel<double>(const double*, const double*, double*, int);
