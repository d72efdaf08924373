// The membrane operators of the CPU extension for every model (cpu_membrane.cpp, bound in bending_cpu.cpp).  model:
// 0 stvk, 1 arap, 2 symmetric_dirichlet, 3 neohookean; projection: 0 none, 1 clamp, 2 abs (membrane_math.h).
// Positions x (..., V, 3), faces (T, 3) int64, D (T, 3, 2), coef (T,) = A t, one mu and one lam (0-dim).
#pragma once
#include <torch/extension.h>

#include <cstdint>
#include <tuple>

namespace torchbend {
namespace cpu {

// ((..., T, 9, 9), finite): the (projected) Hessian of each triangle of each sample, coef d^2 psi / dx^2, and whether
// every entry is finite
std::tuple<torch::Tensor, bool> membrane_blocks(torch::Tensor x, torch::Tensor faces, torch::Tensor D,
                                                torch::Tensor coef, torch::Tensor mu, torch::Tensor lam, int64_t model,
                                                int64_t projection);
// the CSR values (nnz,) of the (projected) Hessian of one mesh x (V, 3): each triangle's block added in face order
// (entry (3 k + i, 3 l + j) at blocks[e, 3 k + l] + i row_len[vertex k] + j), without the (T, 9, 9) blocks in
// memory; empty where a value is not finite
torch::Tensor membrane_assemble(torch::Tensor x, torch::Tensor faces, torch::Tensor D, torch::Tensor coef,
                                torch::Tensor mu, torch::Tensor lam, int64_t model, int64_t projection,
                                torch::Tensor blocks, torch::Tensor row_len, int64_t nnz);
// (E (...,), weight dE/dx (..., V, 3) or empty): the energy of each sample and, optionally, its weighted gradient
std::tuple<torch::Tensor, torch::Tensor> membrane_energy_gradient(torch::Tensor x, torch::Tensor faces,
                                                                  torch::Tensor D, torch::Tensor coef,
                                                                  torch::Tensor mu, torch::Tensor lam,
                                                                  torch::Tensor weight, bool gradient, int64_t model);
// (weight H v (..., V, 3), dE/dx . v (...,)): the (projected) Hessian-vector product of each sample
std::tuple<torch::Tensor, torch::Tensor> membrane_hvp(torch::Tensor x, torch::Tensor v, torch::Tensor faces,
                                                      torch::Tensor D, torch::Tensor coef, torch::Tensor mu,
                                                      torch::Tensor lam, torch::Tensor weight, int64_t model,
                                                      int64_t projection);

}  // namespace cpu
}  // namespace torchbend
