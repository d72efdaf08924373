// The operators of the CPU extension (defined in cpu_*.cpp, bound to Python in bending_cpu.cpp).  Each returns its
// results with a status word (cpu_tiles.h: kBadX, kBadV, kFolded) that the Python wrappers
// (torchbend.backends._status) turn into the ValueErrors of torchbend._checks and torchbend.ops.psi.check_fold.
#pragma once
#include <torch/extension.h>

#include <cstdint>
#include <tuple>

namespace torchbend {
namespace cpu {

using Tensor = torch::Tensor;
using OptTensor = c10::optional<torch::Tensor>;

// (psi (..., H), theta (..., H), status): per-hinge energies of positions x (..., V, 3) (cpu_first_order.cpp)
std::tuple<Tensor, Tensor, int64_t> bending_energy(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest,
                                                   OptTensor c, OptTensor prev, int64_t model, bool check);
// (w dE/dx, w dpsi/d(k, rest, c, prev) or empty, theta, status) (cpu_first_order.cpp)
std::tuple<Tensor, Tensor, Tensor, int64_t> bending_gradient(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest,
                                                             OptTensor c, OptTensor prev, int64_t model, Tensor weight,
                                                             Tensor inc_ptr, Tensor inc_idx, bool params, bool check);
// (psi, dE/dx, dpsi/d(k, rest, c, prev) or empty, theta, status) in one pass (cpu_first_order.cpp)
std::tuple<Tensor, Tensor, Tensor, Tensor, int64_t> bending_energy_gradient(
    Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, OptTensor c, OptTensor prev, int64_t model,
    Tensor inc_ptr, Tensor inc_idx, bool params, bool check);
// (w H v, theta, status) (cpu_second_order.cpp)
std::tuple<Tensor, Tensor, int64_t> bending_hvp(Tensor x, Tensor v, Tensor hinges, Tensor a, Tensor k, Tensor rest,
                                                OptTensor c, OptTensor prev, int64_t model, Tensor weight,
                                                Tensor inc_ptr, Tensor inc_idx, bool check);
// (dx, dp, dg, theta, status): the general double backward (cpu_second_order.cpp)
std::tuple<Tensor, Tensor, Tensor, Tensor, int64_t> bending_second_order(
    Tensor x, OptTensor v, OptTensor t, Tensor hinges, Tensor a, Tensor k, Tensor rest, OptTensor c, OptTensor prev,
    int64_t model, Tensor weight, Tensor inc_ptr, Tensor inc_idx);
// (blocks (..., H, 12, 12), angle gradients (..., H, 12), psi'' (..., H), theta, status); out, gout: optional
// caller-owned buffers of the first two (cpu_blocks.cpp)
std::tuple<Tensor, Tensor, Tensor, Tensor, int64_t> bending_hessians(Tensor x, Tensor hinges, Tensor a, Tensor k,
                                                                     Tensor rest, OptTensor c, OptTensor prev,
                                                                     int64_t model, OptTensor out, OptTensor gout,
                                                                     bool check);
// (CSR values (nnz,), theta (H,), status) of the Hessian of one mesh (cpu_assembly.cpp); out: an optional
// caller-owned buffer of the values
std::tuple<Tensor, Tensor, int64_t> assemble(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, OptTensor c,
                                             OptTensor prev, int64_t model, Tensor hinge_blocks, Tensor faces,
                                             Tensor face_edge_hinges, Tensor face_edge_signs, Tensor face_blocks,
                                             Tensor row_len, int64_t nnz, bool per_triangle, OptTensor out);
// the PSD projection of symmetric blocks M (..., n, n), n 9 or 12 (cpu_projection.cpp)
Tensor project_blocks(Tensor M, int64_t mode, bool hinge);

// the membrane operators: cpu_membrane.h

// the opt-in cache of large outputs (cpu_tiles.cpp): (blocks, bytes, hits, misses, limit), free, limit in bytes
std::tuple<int64_t, int64_t, int64_t, int64_t, int64_t> output_cache_info();
void empty_output_cache();
void set_output_cache_limit(int64_t bytes);

}  // namespace cpu
}  // namespace torchbend
