// C interface of torchbend's CUDA driver (bending_cuda.cu): plain pointers, no torch headers, so the
// CUDA part compiles with nvcc alone and links into a binding built against any torch (CPU-only too).
// Every function returns a cudaError_t code (0 = success); tb_cuda_error_string names it.
#pragma once
#include <cstdint>

extern "C" {

// a per-hinge parameter: n == 1 (scalar), H (per hinge) or B * H (per sample and hinge); p points to
// float or double as the call's dtype says
struct tb_param { const void* p; int64_t n; };
struct tb_hinge_args { tb_param a, k, rest, c, prev; int damped, model; };

// dtype: 0 float32, 1 float64; stream: a cudaStream_t (0 = the default stream).  Outputs of the
// scattering operations (gx, hv) must be zeroed by the caller; gp may be null; psi (B, H), the unweighted
// per-hinge energies computed in the same pass, may be null.
int tb_cuda_energy(int dtype, const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                   tb_hinge_args args, void* psi, void* theta, void* stream);
int tb_cuda_gradient(int dtype, const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                     tb_hinge_args args, tb_param weight, void* gx, void* gp, void* psi, void* theta,
                     void* stream);
int tb_cuda_hvp(int dtype, const void* x, const void* v, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                tb_hinge_args args, tb_param weight, void* hv, void* theta, void* stream);
// the general double backward (torchbend.backends.native.bending_second_order): v (B, V, 3) or null, t
// (t_rows, 4) with t_rows H or B * H, or null; dx (zeroed by the caller), dp (B, H, 4), dg (B, H), theta (B, H)
int tb_cuda_second_order(int dtype, const void* x, const void* v, const void* t, int64_t t_rows,
                         const int64_t* hinges, int64_t B, int64_t V, int64_t H, tb_hinge_args args, tb_param weight,
                         void* dx, void* dp, void* dg, void* theta, void* stream);
int tb_cuda_hinge_hessians(int dtype, const void* x, const int64_t* hinges, int64_t B, int64_t V, int64_t H,
                           tb_hinge_args args, void* blocks, void* grads, void* d2, void* theta, void* stream);
// the membrane of one material (membrane_math.h): D (T, 3, 2) and coef (T,) of x's dtype; model 0 stvk, 1 arap,
// 2 symmetric_dirichlet, 3 neohookean; projection 0 none, 1 clamp, 2 abs
struct tb_membrane_args { const void* D; const void* coef; double mu, lam; int model, projection; };
// psi (B, T) the per-triangle energies (times coef); gx (B, V, 3), zeroed by the caller, or null: weight[b] dE/dx
int tb_cuda_membrane_energy_gradient(int dtype, const void* x, const int64_t* faces, int64_t B, int64_t V, int64_t T,
                                     tb_membrane_args args, const void* weight, void* psi, void* gx, void* stream);
// hv (B, V, 3), zeroed by the caller: weight[b] H v; dots (B, T): coef P : dF per triangle
int tb_cuda_membrane_hvp(int dtype, const void* x, const void* v, const int64_t* faces, int64_t B, int64_t V,
                         int64_t T, tb_membrane_args args, const void* weight, void* hv, void* dots, void* stream);
// blocks (B, T, 81): the (projected) Hessian of each triangle
int tb_cuda_membrane_blocks(int dtype, const void* x, const int64_t* faces, int64_t B, int64_t V, int64_t T,
                            tb_membrane_args args, void* blocks, void* stream);
// the barrier of contact stencils (N, 4) of the given distance types (contact_math.h; eps (N,) the edge-edge pairs'
// mollifier thresholds, or null): E (N,), with want >= 1 G (N, 12), with want >= 2 H (N, 12, 12), unprojected
int tb_cuda_contact_barrier(int dtype, const void* x, const int64_t* stencils, const int64_t* types, const void* eps,
                            int64_t N, double dhat_sq, double kappa, int want, void* E, void* G, void* H, void* stream);
const char* tb_cuda_error_string(int code);
// the names of the kernels this build holds (one per operation and dtype), for the registration check
int tb_cuda_kernel_count();
const char* tb_cuda_kernel_name(int i);
}
