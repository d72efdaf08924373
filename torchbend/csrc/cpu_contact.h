// The compiled contact operators of the CPU extension (cpu_contact.cpp; bound to Python in bending_cpu.cpp).
#pragma once
#include <torch/extension.h>

#include <tuple>

namespace torchbend {
namespace cpu {

// (K, 2) index pairs (a, b) of boxes of A and B that overlap when each is padded by `pad`, without pairs whose
// rows of ids_a and ids_b (int64, one row per box; empty: none) share a value; upper: A = B, pairs a < b only
torch::Tensor contact_box_pairs(torch::Tensor lo_a, torch::Tensor hi_a, torch::Tensor lo_b, torch::Tensor hi_b,
                                double pad, bool upper, torch::Tensor ids_a, torch::Tensor ids_b);
// (point-triangle stencils (P, 4), edge-edge stencils (Q, 4), their edges' indices (Q, 2)) of a mesh over its vertices'
// boxes lo, hi (V, 3): each vertex against each face without it, each edge against each later edge sharing no vertex,
// whose boxes (a primitive's holds its vertices') come within radius
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> contact_candidates(torch::Tensor lo, torch::Tensor hi,
                                                                           torch::Tensor faces, torch::Tensor edges,
                                                                           double radius);
// (types (N,) int64, squared distances (N,)) of point-triangle (edge_edge false) or edge-edge stencils (N, 4)
// over the points x (n, 3)
std::tuple<torch::Tensor, torch::Tensor> contact_distances(torch::Tensor x, torch::Tensor stencils, bool edge_edge);
// (indices into stencils (K,), types (K,)) of the stencils closer than sqrt(dhat_sq), in order
std::tuple<torch::Tensor, torch::Tensor> contact_close(torch::Tensor x, torch::Tensor stencils, bool edge_edge,
                                                       double dhat_sq);
// the largest fraction (<= 1) of a step along which the stencils' vertices, moving at most move[v] (n,), stay
// apart: 0.9 d / (m_A + m_B) over the stencils (d the distance, m_A, m_B the sides' largest moves); with
// displacements move (n, 3) and dhat > 0, each stencil whose first advance binds advances on from the distance it
// reached while that stays above a tenth of min(d, dhat) (conservative advancement, torchbend.sim.self_contact)
double contact_step_bound(torch::Tensor x, torch::Tensor stencils, bool edge_edge, torch::Tensor move, double dhat);
// (energies (N,), gradients (N, 12) if want >= 1, Hessians (N, 12, 12) if want >= 2: unprojected (mode -1),
// clamped (0) or abs (1)) of the barrier of stencils (N, 4) of the given types; eps: the edge-edge pairs'
// mollifier thresholds (N,) or empty (point-triangle pairs)
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> contact_barrier(torch::Tensor x, torch::Tensor stencils,
                                                                        torch::Tensor types, torch::Tensor eps,
                                                                        double dhat_sq, double kappa, int64_t want,
                                                                        int64_t mode);
// the PSD projection (mode 0: clamp, 1: abs) of symmetric blocks (..., n, n), n 3, 6 or 9, by the eigensolver of
// the contact kernels (cpu_symeig.h)
torch::Tensor contact_project_blocks(torch::Tensor M, int64_t mode);
// (indices (2, nnz), values (nnz,)): the (3V, 3V) sum, row-major (a coalesced COO matrix), of blocks H (M, 12, 12)
// of stencils (M, 4); vertices >= V are left out; the blocks of one vertex pair added in stencil order
std::tuple<torch::Tensor, torch::Tensor> contact_stencil_sum(torch::Tensor stencils, torch::Tensor H, int64_t V);
// the sum (n, 3) over the points of x of the barrier gradients of contact_barrier (want 1), a contact found by
// several stencils computed once and counted as many times
torch::Tensor contact_gradient_sum(torch::Tensor x, torch::Tensor stencils, torch::Tensor types, torch::Tensor eps,
                                   double dhat_sq, double kappa);
// the same sum of the barrier Hessians of contact_barrier (want 2, mode) without forming the 12x12 blocks, and of
// friction pairs f_stencils (M, 4) (M = 0: none), whose 12x12 block is w w^T (x) H for their weights f_w (M, 4) and
// point blocks f_H (M, 3, 3), added after the barrier's
std::tuple<torch::Tensor, torch::Tensor> contact_hessian_sum(torch::Tensor x, torch::Tensor stencils,
                                                             torch::Tensor types, torch::Tensor eps, double dhat_sq,
                                                             double kappa, int64_t mode, int64_t V,
                                                             torch::Tensor f_stencils, torch::Tensor f_w,
                                                             torch::Tensor f_H);

}  // namespace cpu
}  // namespace torchbend
