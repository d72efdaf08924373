// The Python bindings of the CPU extension (built by torchbend/backends/native.py and setup.py from
// _build_config.NATIVE_SOURCES).  The driver is split by role: cpu_tiles.h / cpu_tiles.cpp (tiles of hinges,
// argument checks, status words, output buffers), cpu_scatter.h (per-vertex sums), cpu_first_order.cpp (energy,
// gradient), cpu_second_order.cpp (Hessian-vector and second-order products), cpu_blocks.cpp (per-hinge 12x12
// blocks), cpu_assembly.cpp (sparse assembly), cpu_projection.cpp (PSD projection of blocks),
// cpu_contact.cpp, cpu_broad_phase.cpp (contact: broad phase, distances, barrier, block sums); the per-hinge
// mathematics is in hinge_math.h and hinge_ops.h, shared with the CUDA driver.  The same operators are registered
// with the dispatcher as torch.ops.torchbend.* in cpu_registration.cpp.
#include <torch/extension.h>

#include "cpu_contact.h"
#include "cpu_membrane.h"
#include "cpu_ops.h"
#include "op_registration.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  namespace op = torchbend::cpu;
  m.def("bending_hessians", &op::bending_hessians, "fused gather, angle, psi and per-hinge blocks");
  m.def("assemble", &op::assemble, "CSR values of the bending Hessian of one mesh, per hinge or per triangle");
  m.def("bending_energy", &op::bending_energy, "per-hinge energies and angles");
  m.def("bending_gradient", &op::bending_gradient, "weighted gradient in positions and per-hinge parameter gradients");
  m.def("bending_energy_gradient", &op::bending_energy_gradient,
        "per-hinge energies with the gradient in positions and the per-hinge parameter gradients, one pass");
  m.def("bending_hvp", &op::bending_hvp, "weighted Hessian-vector product in positions");
  m.def("bending_second_order", &op::bending_second_order,
        "the general double backward: position and parameter directions, per-hinge weight");
  m.def("project_blocks", &op::project_blocks,
        "PSD projection (clamp, abs; reduced for hinge blocks) of symmetric 9x9 or 12x12 blocks, Jacobi");
  m.def("membrane_blocks", &op::membrane_blocks,
        "the (projected) Hessian of each triangle (..., T, 9, 9) of any membrane model, closed-form eigensystem");
  m.def("membrane_assemble", &op::membrane_assemble,
        "the CSR values of the (projected) membrane Hessian of one mesh, blocks added in face order");
  m.def("membrane_energy_gradient", &op::membrane_energy_gradient,
        "the energy of each sample and, optionally, its weighted gradient, of any membrane model");
  m.def("membrane_hvp", &op::membrane_hvp,
        "the (projected) Hessian-vector product of each sample of any membrane model, weighted, and the directional "
        "derivative of its energy");
  m.def("contact_box_pairs", &op::contact_box_pairs,
        "pairs of overlapping padded boxes (a uniform grid, hashed where sparse), without pairs that share an id");
  m.def("contact_candidates", &op::contact_candidates,
        "the candidate point-triangle and edge-edge stencils of a mesh over its vertices' boxes");
  m.def("contact_distances", &op::contact_distances, "distance types and squared distances of contact stencils");
  m.def("contact_close", &op::contact_close,
        "the contact stencils closer than dhat with their types");
  m.def("contact_step_bound", &op::contact_step_bound,
        "the conservative step bound of contact stencils whose vertices move at most the given distances");
  m.def("contact_barrier", &op::contact_barrier,
        "barrier energies, gradients and (projected) Hessians of contact stencils, closed form");
  m.def("contact_project_blocks", &op::contact_project_blocks,
        "PSD projection of symmetric 3x3, 6x6 or 9x9 blocks by the contact kernels' eigensolver (tridiagonal QL)");
  m.def("contact_stencil_sum", &op::contact_stencil_sum, "the row-major sum of 12x12 stencil blocks");
  m.def("contact_gradient_sum", &op::contact_gradient_sum,
        "the sum over the points of the contact pairs' barrier gradients, a contact found by several stencils once");
  m.def("contact_hessian_sum", &op::contact_hessian_sum,
        "the row-major sum of the contact pairs' (projected) barrier Hessians, without forming the blocks, and of "
        "friction pairs' blocks");
  m.def("output_cache_info", &op::output_cache_info, "(blocks, bytes, hits, misses, limit) of the cache of large outputs");
  m.def("empty_output_cache", &op::empty_output_cache, "free the memory the cache of large outputs holds");
  m.def("set_output_cache_limit", &op::set_output_cache_limit, "the most bytes the cache of large outputs keeps");
  m.def("set_status_handler", &torchbend::reg::set_status_handler,
        "the Python function raising the ValueError of a status word in the registered operators");
  m.def("register_operators", &torchbend::reg::register_operators,
        "register torch.ops.torchbend.* (the schemas and the CPU kernels), once per process");
}
