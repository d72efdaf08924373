"""The names of the compiled operations, in one table: the entry points of the energies that have a compiled
kernel (and on which devices), the operators ``torch.ops.torchbend.*`` with the kernel of the CUDA driver behind
each, and the codes the kernels take for the bending models and the projections."""
from __future__ import annotations

ENTRY_POINTS: dict[str, tuple[str, ...]] = {
    "energy": ("cpu", "cuda"),
    "gradient": ("cpu", "cuda"),
    "hvp": ("cpu", "cuda"),
    "hinge_hessians": ("cpu", "cuda"),
    "hvp_projected": ("cpu", "cuda"),
    "hessian_hinge": ("cpu",),
    "hessian_triangle": ("cpu",),
    "membrane_element_hessians": ("cpu", "cuda"),
    "membrane_energy": ("cpu", "cuda"),
    "membrane_gradient": ("cpu", "cuda"),
    "membrane_hvp": ("cpu", "cuda"),
}
"""Operation of the energies (the ``op`` of :func:`torchbend.backends.select_backend`) -> the devices with a
compiled kernel for it: the energy, its gradient and Hessian-vector product (inside the analytic autograd
Functions), the per-hinge 12x12 blocks (also behind the eigenvalue-projected hvp and assembly) and the
unprojected sparse assembly per hinge or per triangle (one mesh, CPU only); of the membrane (every model), the
element Hessians (projected or not), the energy and gradient (inside the membrane's autograd Functions) and the
Hessian-vector product (projected or not)."""

ONE_MESH = frozenset({"hessian_hinge", "hessian_triangle"})
"""Entry points whose kernel takes one mesh (no batch)."""
DIFFERENTIABLE = frozenset({"energy", "gradient", "membrane_energy", "membrane_gradient"})
"""Kernels called inside torchbend's autograd Functions: differentiable (analytically), so a recorded graph does
not keep them from running."""

OPERATORS: dict[str, str | None] = {
    "bending_energy": "energy",
    "bending_gradient": "gradient",
    "bending_energy_gradient": "gradient",
    "bending_hvp": "hvp",
    "bending_second_order": "second_order",
    "hinge_hessians": "hinge_hessians",
    "assemble": None,
    "project_blocks": None,
    "membrane_energy_gradient": None,
    "membrane_hvp": None,
    "sum_last": None,
}
"""``torch.ops.torchbend.<name>`` (:mod:`torchbend.backends.ops`) -> the kernel of the CUDA driver that runs it
(``None``: no CUDA kernel; ``project_blocks`` and the membrane operators run their eager formulas on CUDA tensors)."""

SCHEMAS: dict[str, str] = {
    "bending_energy": "(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, str model, "
                      "bool check) -> Tensor",
    "bending_gradient": "(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, "
                        "str model, Tensor weight, Tensor ptr, Tensor idx, bool params, bool check) -> (Tensor, Tensor)",
    "bending_energy_gradient": "(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, "
                               "str model, Tensor ptr, Tensor idx, bool params, bool check) -> (Tensor, Tensor, Tensor)",
    "bending_hvp": "(Tensor x, Tensor v, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, "
                   "str model, Tensor weight, Tensor ptr, Tensor idx, bool check=False) -> Tensor",
    "bending_second_order": "(Tensor x, Tensor? v, Tensor? t, Tensor hinges, Tensor a, Tensor k, Tensor rest, "
                            "Tensor? c, Tensor? prev, str model, Tensor weight, Tensor ptr, Tensor idx) "
                            "-> (Tensor, Tensor, Tensor)",
    "hinge_hessians": "(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, str model, "
                      "bool check=False) -> (Tensor, Tensor, Tensor)",
    "assemble": "(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, str model, "
                "Tensor hinge_blocks, Tensor faces, Tensor face_edge_hinges, Tensor face_edge_signs, "
                "Tensor face_blocks, Tensor row_len, SymInt nnz, bool per_triangle) -> Tensor",
    "project_blocks": "(Tensor M, str mode, bool hinge=False) -> Tensor",
    "membrane_energy_gradient": "(Tensor x, Tensor faces, Tensor D, Tensor coef, Tensor mu, Tensor lam, Tensor weight, "
                                "bool gradient, str model) -> (Tensor, Tensor)",
    "membrane_hvp": "(Tensor x, Tensor v, Tensor faces, Tensor D, Tensor coef, Tensor mu, Tensor lam, Tensor weight, "
                    "str model, str projection) -> (Tensor, Tensor)",
    "sum_last": "(Tensor values) -> Tensor",
}
"""The schema of every operator (``torch.ops.torchbend.<name>``): registered in C++ by the CPU extension
(``csrc/op_registration.h``, the same strings: a test compares them), defined from Python where it cannot be
built (:mod:`torchbend.backends.ops`)."""

MEMBRANE_CUDA_KERNELS: tuple[str, ...] = ("membrane_energy_gradient", "membrane_hvp", "membrane_blocks")
"""The membrane's kernels of the CUDA driver (called by the membrane's Python paths, not registered as operators)."""
CONTACT_CUDA_KERNELS: tuple[str, ...] = ("contact_barrier",)
"""The contact kernels of the CUDA driver (:func:`torchbend.backends.cuda.contact_barrier`)."""
CUDA_KERNELS: tuple[str, ...] = (tuple(dict.fromkeys(k for k in OPERATORS.values() if k is not None))
                                 + MEMBRANE_CUDA_KERNELS + CONTACT_CUDA_KERNELS)
"""The kernels of the CUDA driver (``csrc/bending_cuda.cu``), each compiled for float32 and float64."""

MODEL_CODE = {"quadratic": 0, "tan": 1, "sin": 2}
"""The bending models as the kernels take them."""

PROJECTION_CODE = {"clamp": 0, "abs": 1, "reduced": 2}
"""The projections of the compiled ``project_blocks``."""

MEMBRANE_MODEL_CODE = {"stvk": 0, "arap": 1, "symmetric_dirichlet": 2, "neohookean": 3}
"""The codes of the membrane models in the kernels (csrc/membrane_math.h)."""
MEMBRANE_PROJECTION_CODE = {"none": 0, "clamp": 1, "abs": 2}
"""The codes of the membrane's eigenvalue projections in the kernels (csrc/membrane_math.h)."""


def model_code(model) -> int:
    """The kernels' code of ``model`` (a name or a :class:`torchbend.ops.psi.BendingModel`)."""
    return MODEL_CODE[getattr(model, "value", model)]
