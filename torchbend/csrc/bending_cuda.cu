// CUDA driver of torchbend's compiled bending, membrane and contact operations: one thread per (sample, hinge) or (sample,
// triangle); the membrane's per-triangle mathematics is membrane_math.h, as on the CPU (cpu_membrane.cpp).  The per-hinge
// mathematics of hinge_math.h / hinge_ops.h with W = 1 (the same functions the CPU driver runs in tiles
// of 8 lanes, which the CPU tests compare against the eager reference), atomic scatter of the per-vertex
// results.  No torch headers: the C interface is bending_cuda.h, bound to torch in cuda_binding.cpp.
#include <cuda_runtime.h>

#include "bending_cuda.h"
#include "contact_math.h"
#include "hinge_ops.h"
#include "membrane_math.h"

using namespace torchbend;

namespace {

constexpr int kThreads = 128;

template <typename T> Param<T> param(tb_param p, int64_t H) { return Param<T>{static_cast<const T*>(p.p), p.n, H}; }

template <typename T> HingeArgs<T> hinge_args(const tb_hinge_args& a, int64_t H) {
  return HingeArgs<T>{param<T>(a.a, H), param<T>(a.k, H), param<T>(a.rest, H), param<T>(a.c, H), param<T>(a.prev, H),
                      a.damped != 0, a.model};
}

__device__ inline int64_t thread_index() { return int64_t(blockIdx.x) * blockDim.x + threadIdx.x; }

template <typename T>
__global__ void energy_kernel(const T* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H, HingeArgs<T> args,
                              T* psi, T* theta) {
  int64_t bh = thread_index();
  if (bh >= B * H) return;
  int64_t b = bh / H, h = bh - b * H;
  T X[12][1];
  load_hinge<T, 1>(x + 3 * V * b, hinges + 4 * h, X, 0);
  T th = hinge_theta<T, 1>(X, 0), p, d1;
  psi_first<T>(args, b, h, th, p, d1, nullptr);
  psi[bh] = p;
  theta[bh] = th;
}

template <typename T>
__global__ void gradient_kernel(const T* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H, HingeArgs<T> args,
                                Param<T> w, T* gx, T* gp, T* psi, T* theta) {
  int64_t bh = thread_index();
  if (bh >= B * H) return;
  int64_t b = bh / H, h = bh - b * H;
  const int64_t* st = hinges + 4 * h;
  T X[12][1], G[12][1];
  load_hinge<T, 1>(x + 3 * V * b, st, X, 0);
  T th = hinge_theta<T, 1>(X, 0), p, d1, g4[4];
  psi_first<T>(args, b, h, th, p, d1, gp ? g4 : nullptr);
  T wi = w(b, h), s = wi * d1;
  theta[bh] = th;
  if (psi) psi[bh] = p;  // the energy in the same pass (bending_energy_gradient)
  if (gp) for (int j = 0; j < 4; ++j) gp[4 * bh + j] = wi * g4[j];
  grad_tile<T, 1>(X, G);
  T* out = gx + 3 * V * b;
  for (int v = 0; v < 4; ++v)
    for (int m = 0; m < 3; ++m) atomicAdd(out + 3 * st[v] + m, s * G[3 * v + m][0]);
}

template <typename T>
__global__ void hvp_kernel(const T* x, const T* vd, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                           HingeArgs<T> args, Param<T> w, T* hv, T* theta) {
  int64_t bh = thread_index();
  if (bh >= B * H) return;
  int64_t b = bh / H, h = bh - b * H;
  const int64_t* st = hinges + 4 * h;
  T X[12][1], Vd[12][1], O[12][1], th, d1, d2;
  load_hinge<T, 1>(x + 3 * V * b, st, X, 0);
  load_hinge<T, 1>(vd + 3 * V * b, st, Vd, 0);
  hinge_psi<T, 1>(X, 0, args.model, args.a(b, h), args.k(b, h), args.rest(b, h), args.damped,
                  args.damped ? args.c(b, h) : T(0), args.damped ? args.prev(b, h) : T(0), th, d1, d2);
  T wi = w(b, h);
  d1 *= wi; d2 *= wi;
  theta[bh] = th;
  // psi' H_theta v + psi'' (g . v) g in closed form (torchbend.ops.hinge), no 12x12 block
  Half<T, 1> hA, hB;
  T G[12][1], u;
  halves_tile<T, 1>(X, hA, hB);
  grad_of_halves<T, 1>(hA, hB, G);
  dot_tile<T, 1>(G, Vd, &u);
  u *= d2;
  hvp_of_halves<T, 1>(hA, hB, Vd, G, &d1, &u, true, O);
  T* out = hv + 3 * V * b;
  for (int v = 0; v < 4; ++v)
    for (int m = 0; m < 3; ++m) atomicAdd(out + 3 * st[v] + m, O[3 * v + m][0]);
}

template <typename T>
__global__ void second_order_kernel(const T* x, const T* vd, const T* tg, bool t_batched, const int64_t* hinges,
                                    int64_t B, int64_t V, int64_t H, HingeArgs<T> args, Param<T> w, T* dx, T* dp,
                                    T* dg, T* theta) {
  int64_t bh = thread_index();
  if (bh >= B * H) return;
  int64_t b = bh / H, h = bh - b * H;
  const int64_t* st = hinges + 4 * h;
  T X[12][1], Vd[12][1], G[12][1], O[12][1], t4[4] = {T(0), T(0), T(0), T(0)}, u = T(0);
  load_hinge<T, 1>(x + 3 * V * b, st, X, 0);
  if (tg) {
    const T* src = tg + 4 * (t_batched ? bh : h);
    for (int j = 0; j < 4; ++j) t4[j] = src[j];
  }
  T th = hinge_theta<T, 1>(X, 0);
  Half<T, 1> hA, hB;
  halves_tile<T, 1>(X, hA, hB);
  grad_of_halves<T, 1>(hA, hB, G);
  if (vd) {
    load_hinge<T, 1>(vd + 3 * V * b, st, Vd, 0);
    dot_tile<T, 1>(G, Vd, &u);
  }
  T d1, zt, z4[4], g;
  psi_second<T>(args, b, h, th, u, t4, d1, zt, z4, g);
  T wi = w(b, h), s1 = wi * d1, s2 = wi * zt;
  hvp_of_halves<T, 1>(hA, hB, Vd, G, &s1, &s2, vd != nullptr, O);
  for (int j = 0; j < 4; ++j) dp[4 * bh + j] = wi * z4[j];
  dg[bh] = g;
  theta[bh] = th;
  T* out = dx + 3 * V * b;
  for (int v = 0; v < 4; ++v)
    for (int m = 0; m < 3; ++m) atomicAdd(out + 3 * st[v] + m, O[3 * v + m][0]);
}

template <typename T>
__global__ void blocks_kernel(const T* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H, HingeArgs<T> args,
                              T* blocks, T* grads, T* d2out, T* theta) {
  int64_t bh = thread_index();
  if (bh >= B * H) return;
  int64_t b = bh / H, h = bh - b * H;
  T X[12][1], th, d1, d2;
  load_hinge<T, 1>(x + 3 * V * b, hinges + 4 * h, X, 0);
  hinge_psi<T, 1>(X, 0, args.model, args.a(b, h), args.k(b, h), args.rest(b, h), args.damped,
                  args.damped ? args.c(b, h) : T(0), args.damped ? args.prev(b, h) : T(0), th, d1, d2);
  Blocks<T, 1> blk;
  block_tile<T, 1>(X, &d1, &d2, blk);
  block_lane<T, 1>(blk, 0, blocks + 144 * bh);
  for (int m = 0; m < 12; ++m) grads[12 * bh + m] = blk.G[m][0];
  d2out[bh] = d2;
  theta[bh] = th;
}

unsigned grid(int64_t n) { return unsigned((n + kThreads - 1) / kThreads); }

template <typename T> int energy(const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                                 const tb_hinge_args& a, void* psi, void* theta, cudaStream_t s) {
  if (B * H == 0) return 0;
  energy_kernel<T><<<grid(B * H), kThreads, 0, s>>>(static_cast<const T*>(x), hinges, B, V, H, hinge_args<T>(a, H),
                                                    static_cast<T*>(psi), static_cast<T*>(theta));
  return int(cudaGetLastError());
}

template <typename T> int gradient(const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                                   const tb_hinge_args& a, tb_param w, void* gx, void* gp, void* psi, void* theta,
                                   cudaStream_t s) {
  if (B * H == 0) return 0;
  gradient_kernel<T><<<grid(B * H), kThreads, 0, s>>>(static_cast<const T*>(x), hinges, B, V, H, hinge_args<T>(a, H),
                                                      param<T>(w, H), static_cast<T*>(gx), static_cast<T*>(gp),
                                                      static_cast<T*>(psi), static_cast<T*>(theta));
  return int(cudaGetLastError());
}

template <typename T> int hvp(const void* x, const void* v, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                              const tb_hinge_args& a, tb_param w, void* hv, void* theta, cudaStream_t s) {
  if (B * H == 0) return 0;
  hvp_kernel<T><<<grid(B * H), kThreads, 0, s>>>(static_cast<const T*>(x), static_cast<const T*>(v), hinges, B, V, H,
                                                 hinge_args<T>(a, H), param<T>(w, H), static_cast<T*>(hv),
                                                 static_cast<T*>(theta));
  return int(cudaGetLastError());
}

template <typename T> int second_order(const void* x, const void* v, const void* t, int64_t t_rows,
                                       const int64_t* hinges, int64_t B, int64_t V, int64_t H, const tb_hinge_args& a,
                                       tb_param w, void* dx, void* dp, void* dg, void* theta, cudaStream_t s) {
  if (B * H == 0) return 0;
  second_order_kernel<T><<<grid(B * H), kThreads, 0, s>>>(
      static_cast<const T*>(x), static_cast<const T*>(v), static_cast<const T*>(t), t_rows != H, hinges, B, V, H,
      hinge_args<T>(a, H), param<T>(w, H), static_cast<T*>(dx), static_cast<T*>(dp), static_cast<T*>(dg),
      static_cast<T*>(theta));
  return int(cudaGetLastError());
}

template <typename T> int hessians(const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                                   const tb_hinge_args& a, void* blocks, void* grads, void* d2, void* theta,
                                   cudaStream_t s) {
  if (B * H == 0) return 0;
  blocks_kernel<T><<<grid(B * H), kThreads, 0, s>>>(static_cast<const T*>(x), hinges, B, V, H, hinge_args<T>(a, H),
                                                    static_cast<T*>(blocks), static_cast<T*>(grads),
                                                    static_cast<T*>(d2), static_cast<T*>(theta));
  return int(cudaGetLastError());
}

// ---- the membrane: one thread per (sample, triangle), atomic scatter of the per-vertex results ----------------
template <typename T>
__global__ void membrane_energy_gradient_kernel(const T* x, const int64_t* faces, int64_t B, int64_t V, int64_t Tn,
                                                const T* D, const T* coef, T mu, T lam, int model, const T* w, T* psi,
                                                T* gx) {
  int64_t bt = thread_index();
  if (bt >= B * Tn) return;
  int64_t b = bt / Tn, e = bt - b * Tn;
  const int64_t* t = faces + 3 * e;
  const T* xb = x + 3 * V * b;
  T f[9];
  psi[bt] = membrane_face<T>(model, xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2], D + 6 * e, mu, lam, coef[e],
                             gx ? f : nullptr);
  if (!gx) return;
  T* out = gx + 3 * V * b;
  for (int k = 0; k < 3; ++k)
    for (int i = 0; i < 3; ++i) atomicAdd(out + 3 * t[k] + i, w[b] * f[3 * k + i]);
}

template <typename T>
__global__ void membrane_hvp_kernel(const T* x, const T* v, const int64_t* faces, int64_t B, int64_t V, int64_t Tn,
                                    const T* D, const T* coef, T mu, T lam, int model, int projection, const T* w,
                                    T* hv, T* dots) {
  int64_t bt = thread_index();
  if (bt >= B * Tn) return;
  int64_t b = bt / Tn, e = bt - b * Tn;
  const int64_t* t = faces + 3 * e;
  const T* xb = x + 3 * V * b;
  const T* vb = v + 3 * V * b;
  T h[9];
  dots[bt] = membrane_face_hvp<T>(model, projection, xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2], vb + 3 * t[0],
                                  vb + 3 * t[1], vb + 3 * t[2], D + 6 * e, mu, lam, coef[e], h);
  T* out = hv + 3 * V * b;
  for (int k = 0; k < 3; ++k)
    for (int i = 0; i < 3; ++i) atomicAdd(out + 3 * t[k] + i, w[b] * h[3 * k + i]);
}

template <typename T>
__global__ void membrane_blocks_kernel(const T* x, const int64_t* faces, int64_t B, int64_t V, int64_t Tn, const T* D,
                                       const T* coef, T mu, T lam, int model, int projection, T* blocks) {
  int64_t bt = thread_index();
  if (bt >= B * Tn) return;
  int64_t b = bt / Tn, e = bt - b * Tn;
  const int64_t* t = faces + 3 * e;
  const T* xb = x + 3 * V * b;
  membrane_face_block<T>(model, projection, xb + 3 * t[0], xb + 3 * t[1], xb + 3 * t[2], D + 6 * e, mu, lam, coef[e],
                         blocks + 81 * bt);
}

template <typename T> int membrane_energy_gradient(const void* x, const int64_t* faces, int64_t B, int64_t V,
                                                   int64_t Tn, const tb_membrane_args& a, const void* w, void* psi,
                                                   void* gx, cudaStream_t s) {
  if (B * Tn == 0) return 0;
  membrane_energy_gradient_kernel<T><<<grid(B * Tn), kThreads, 0, s>>>(
      static_cast<const T*>(x), faces, B, V, Tn, static_cast<const T*>(a.D), static_cast<const T*>(a.coef), T(a.mu),
      T(a.lam), a.model, static_cast<const T*>(w), static_cast<T*>(psi), static_cast<T*>(gx));
  return int(cudaGetLastError());
}

template <typename T> int membrane_hvp(const void* x, const void* v, const int64_t* faces, int64_t B, int64_t V,
                                       int64_t Tn, const tb_membrane_args& a, const void* w, void* hv, void* dots,
                                       cudaStream_t s) {
  if (B * Tn == 0) return 0;
  membrane_hvp_kernel<T><<<grid(B * Tn), kThreads, 0, s>>>(
      static_cast<const T*>(x), static_cast<const T*>(v), faces, B, V, Tn, static_cast<const T*>(a.D),
      static_cast<const T*>(a.coef), T(a.mu), T(a.lam), a.model, a.projection, static_cast<const T*>(w),
      static_cast<T*>(hv), static_cast<T*>(dots));
  return int(cudaGetLastError());
}

template <typename T> int membrane_blocks(const void* x, const int64_t* faces, int64_t B, int64_t V, int64_t Tn,
                                          const tb_membrane_args& a, void* blocks, cudaStream_t s) {
  if (B * Tn == 0) return 0;
  membrane_blocks_kernel<T><<<grid(B * Tn), kThreads, 0, s>>>(
      static_cast<const T*>(x), faces, B, V, Tn, static_cast<const T*>(a.D), static_cast<const T*>(a.coef), T(a.mu),
      T(a.lam), a.model, a.projection, static_cast<T*>(blocks));
  return int(cudaGetLastError());
}

// one contact stencil per thread: contact_math.h's pair terms, back to the stencil's 12 coordinates
template <typename T>
__global__ void contact_barrier_kernel(const T* x, const int64_t* stencils, const int64_t* types, const T* eps,
                                       int64_t N, T dh2, T kappa, int want, T* E, T* G, T* H) {
  int64_t n = thread_index();
  if (n >= N) return;
  T X[4][3];
  for (int v = 0; v < 4; ++v)
    for (int i = 0; i < 3; ++i) X[v][i] = x[3 * stencils[4 * n + v] + i];
  contact::PairTerms<T> p;
  contact::pair_terms<T>(X, int(types[n]), eps ? eps[n] : T(0), dh2, kappa, want, &p);
  E[n] = p.E;
  if (want >= 1) contact::expand_gradient(p.C, p.r, p.g, G + 12 * n);
  if (want >= 2) contact::expand_hessian(p.C, p.r, p.H, H + 144 * n);
}

template <typename T> int contact_barrier(const void* x, const int64_t* stencils, const int64_t* types, const void* eps,
                                          int64_t N, double dh2, double kappa, int want, void* E, void* G, void* H,
                                          cudaStream_t s) {
  if (N == 0) return 0;
  contact_barrier_kernel<T><<<grid(N), kThreads, 0, s>>>(
      static_cast<const T*>(x), stencils, types, static_cast<const T*>(eps), N, T(dh2), T(kappa), want,
      static_cast<T*>(E), static_cast<T*>(G), static_cast<T*>(H));
  return int(cudaGetLastError());
}

const char* const kKernels[] = {"energy_f32", "energy_f64", "gradient_f32", "gradient_f64",
                                "hvp_f32", "hvp_f64", "hinge_hessians_f32", "hinge_hessians_f64",
                                "second_order_f32", "second_order_f64",
                                "membrane_energy_gradient_f32", "membrane_energy_gradient_f64",
                                "membrane_hvp_f32", "membrane_hvp_f64", "membrane_blocks_f32", "membrane_blocks_f64",
                                "contact_barrier_f32", "contact_barrier_f64"};

}  // namespace

extern "C" {

int tb_cuda_energy(int dtype, const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                   tb_hinge_args args, void* psi, void* theta, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? energy<double>(x, hinges, B, V, H, args, psi, theta, s)
               : energy<float>(x, hinges, B, V, H, args, psi, theta, s);
}

int tb_cuda_gradient(int dtype, const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                     tb_hinge_args args, tb_param weight, void* gx, void* gp, void* psi, void* theta,
                     void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? gradient<double>(x, hinges, B, V, H, args, weight, gx, gp, psi, theta, s)
               : gradient<float>(x, hinges, B, V, H, args, weight, gx, gp, psi, theta, s);
}

int tb_cuda_hvp(int dtype, const void* x, const void* v, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                tb_hinge_args args, tb_param weight, void* hv, void* theta, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? hvp<double>(x, v, hinges, B, V, H, args, weight, hv, theta, s)
               : hvp<float>(x, v, hinges, B, V, H, args, weight, hv, theta, s);
}

int tb_cuda_second_order(int dtype, const void* x, const void* v, const void* t, int64_t t_rows,
                         const int64_t* hinges, int64_t B, int64_t V, int64_t H, tb_hinge_args args, tb_param weight,
                         void* dx, void* dp, void* dg, void* theta, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? second_order<double>(x, v, t, t_rows, hinges, B, V, H, args, weight, dx, dp, dg, theta, s)
               : second_order<float>(x, v, t, t_rows, hinges, B, V, H, args, weight, dx, dp, dg, theta, s);
}

int tb_cuda_hinge_hessians(int dtype, const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                           tb_hinge_args args, void* blocks, void* grads, void* d2, void* theta, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? hessians<double>(x, hinges, B, V, H, args, blocks, grads, d2, theta, s)
               : hessians<float>(x, hinges, B, V, H, args, blocks, grads, d2, theta, s);
}

int tb_cuda_membrane_energy_gradient(int dtype, const void* x, const int64_t* faces, int64_t B, int64_t V, int64_t T,
                                     tb_membrane_args args, const void* weight, void* psi, void* gx, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? membrane_energy_gradient<double>(x, faces, B, V, T, args, weight, psi, gx, s)
               : membrane_energy_gradient<float>(x, faces, B, V, T, args, weight, psi, gx, s);
}

int tb_cuda_membrane_hvp(int dtype, const void* x, const void* v, const int64_t* faces, int64_t B, int64_t V,
                         int64_t T, tb_membrane_args args, const void* weight, void* hv, void* dots, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? membrane_hvp<double>(x, v, faces, B, V, T, args, weight, hv, dots, s)
               : membrane_hvp<float>(x, v, faces, B, V, T, args, weight, hv, dots, s);
}

int tb_cuda_membrane_blocks(int dtype, const void* x, const int64_t* faces, int64_t B, int64_t V, int64_t T,
                            tb_membrane_args args, void* blocks, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? membrane_blocks<double>(x, faces, B, V, T, args, blocks, s)
               : membrane_blocks<float>(x, faces, B, V, T, args, blocks, s);
}

int tb_cuda_contact_barrier(int dtype, const void* x, const int64_t* stencils, const int64_t* types, const void* eps,
                            int64_t N, double dhat_sq, double kappa, int want, void* E, void* G, void* H, void* stream) {
  auto s = static_cast<cudaStream_t>(stream);
  return dtype ? contact_barrier<double>(x, stencils, types, eps, N, dhat_sq, kappa, want, E, G, H, s)
               : contact_barrier<float>(x, stencils, types, eps, N, dhat_sq, kappa, want, E, G, H, s);
}

const char* tb_cuda_error_string(int code) { return cudaGetErrorString(cudaError_t(code)); }

int tb_cuda_kernel_count() { return int(sizeof(kKernels) / sizeof(kKernels[0])); }

const char* tb_cuda_kernel_name(int i) { return i >= 0 && i < tb_cuda_kernel_count() ? kKernels[i] : nullptr; }
}
