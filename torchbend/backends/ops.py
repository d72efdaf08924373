r"""The compiled bending kernels as PyTorch operators: ``torch.ops.torchbend.*``.

Each operator wraps one kernel of :mod:`torchbend.backends.native` (CPU) or :mod:`torchbend.backends.cuda`
(by the device of ``x``) with :func:`torch.library.custom_op` and a fake implementation (output shapes and
dtypes from the input shapes alone), so that ``torch.compile`` (also ``fullgraph=True``) and ``torch.export``
trace through them without a graph break, and ``torch.library.opcheck`` can check them.

The operators are not differentiable themselves: derivatives come from torchbend's autograd Functions
(:mod:`torchbend.energies._bending_fn`), which call ``bending_energy`` in the forward, ``bending_gradient``
in its backward and ``bending_hvp``/``bending_second_order`` in the double backward.  The checks stay on in
compiled code because they run inside the operators: a folded ``tan`` hinge is the ``ValueError`` of
:func:`torchbend.ops.psi.check_fold`; with ``check=True`` non-finite positions are the ``ValueError`` of
:func:`torchbend._checks.check_positions` (the modules pass ``check=True`` only under ``torch.compile``/
``torch.export``, where their own Python-level check cannot run; eagerly they check before the call).

Arguments shared by all: ``x (..., V, 3)``; ``hinges (H, 4)`` int64; ``a (H,)``; ``k``, ``rest``, ``c``,
``prev`` one value or ``(H,)`` (``prev`` also ``(..., H)``, x's batch shape); ``c``/``prev`` both given
(viscous term) or both ``None``; ``model`` ``"quadratic" | "tan" | "sin"``; ``weight`` the per-hinge
cotangent of the energy (one value, ``(H,)`` or ``(..., H)``); ``ptr``, ``idx`` the vertex incidence lists
(:func:`torchbend.backends.native.incidence`).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .._checks import check_positions
from . import kernels

__all__ = ["bending_energy", "bending_gradient", "bending_hvp", "bending_second_order", "hinge_hessians", "assemble", "OPS"]


def _check(x: Tensor, check: bool) -> None:
    if check:
        check_positions(x, x.shape[-2])


def _batch(x: Tensor) -> tuple[int, ...]:
    return tuple(x.shape[:-2])


@torch.library.custom_op("torchbend::bending_energy", mutates_args=())
def bending_energy(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                   prev: Optional[Tensor], model: str, check: bool) -> Tensor:
    """Per-hinge energies ``psi (..., H)``."""
    _check(x, check)
    return kernels.module(x).bending_energy(x, hinges, a, k, rest, c, prev, model)


@bending_energy.register_fake
def _(x, hinges, a, k, rest, c, prev, model, check):
    return x.new_empty(_batch(x) + (hinges.shape[0],))


@torch.library.custom_op("torchbend::bending_gradient", mutates_args=())
def bending_gradient(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                     prev: Optional[Tensor], model: str, weight: Tensor, ptr: Tensor, idx: Tensor, params: bool,
                     check: bool) -> tuple[Tensor, Tensor]:
    """``(w dE/dx (..., V, 3), w dpsi/d(k, rest, c, prev) (..., H, 4))``; the second is empty (``(0,)``)
    without ``params``."""
    _check(x, check)
    gx, gp = kernels.module(x).bending_gradient(x, hinges, a, k, rest, c, prev, model, weight, (ptr, idx), params)
    return gx, (gp if gp is not None else x.new_empty(0))


@bending_gradient.register_fake
def _(x, hinges, a, k, rest, c, prev, model, weight, ptr, idx, params, check):
    gp = x.new_empty(_batch(x) + (hinges.shape[0], 4)) if params else x.new_empty(0)
    return torch.empty_like(x, memory_format=torch.contiguous_format), gp


@torch.library.custom_op("torchbend::bending_hvp", mutates_args=())
def bending_hvp(x: Tensor, v: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                prev: Optional[Tensor], model: str, weight: Tensor, ptr: Tensor, idx: Tensor) -> Tensor:
    """``w H v (..., V, 3)``: the Hessian of the energy in the positions applied to ``v`` (x's shape)."""
    return kernels.module(x).bending_hvp(x, v, hinges, a, k, rest, c, prev, model, weight, (ptr, idx))


@bending_hvp.register_fake
def _(x, v, hinges, a, k, rest, c, prev, model, weight, ptr, idx):
    return torch.empty_like(x, memory_format=torch.contiguous_format)


@torch.library.custom_op("torchbend::bending_second_order", mutates_args=())
def bending_second_order(x: Tensor, v: Optional[Tensor], t: Optional[Tensor], hinges: Tensor, a: Tensor, k: Tensor,
                         rest: Tensor, c: Optional[Tensor], prev: Optional[Tensor], model: str, weight: Tensor,
                         ptr: Tensor, idx: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The general double backward: ``(dx (..., V, 3), dp (..., H, 4), dg (..., H))`` for directions ``v`` in the
    positions and ``t (..., H, 4)`` in the per-hinge ``(k, rest, c, prev)`` (either may be ``None``); see
    :func:`torchbend.backends.native.bending_second_order`."""
    return tuple(kernels.module(x).bending_second_order(x, v, t, hinges, a, k, rest, c, prev, model, weight,
                                                        (ptr, idx)))  # type: ignore[return-value]


@bending_second_order.register_fake
def _(x, v, t, hinges, a, k, rest, c, prev, model, weight, ptr, idx):
    H = hinges.shape[0]
    return (torch.empty_like(x, memory_format=torch.contiguous_format), x.new_empty(_batch(x) + (H, 4)),
            x.new_empty(_batch(x) + (H,)))


@torch.library.custom_op("torchbend::hinge_hessians", mutates_args=())
def hinge_hessians(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                   prev: Optional[Tensor], model: str) -> tuple[Tensor, Tensor, Tensor]:
    """``(blocks (..., H, 12, 12), angle gradients g (..., H, 12), psi'' (..., H))`` (unprojected)."""
    return tuple(kernels.module(x).bending_hessians(x, hinges, a, k, rest, c, prev, model)[:3])  # type: ignore[return-value]


@hinge_hessians.register_fake
def _(x, hinges, a, k, rest, c, prev, model):
    H = hinges.shape[0]
    return x.new_empty(_batch(x) + (H, 12, 12)), x.new_empty(_batch(x) + (H, 12)), x.new_empty(_batch(x) + (H,))


@torch.library.custom_op("torchbend::assemble", mutates_args=())
def assemble(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
             prev: Optional[Tensor], model: str, hinge_pos: Tensor, faces: Tensor, face_edge_hinges: Tensor,
             face_edge_signs: Tensor, face_pos: Tensor, nnz: int, per_triangle: bool) -> Tensor:
    """CSR values ``(nnz,)`` of the unprojected Hessian of one mesh ``x (V, 3)`` (the pattern's arrays from
    :class:`torchbend.energies.sparse.HessianPattern` and the topology)."""
    from . import native

    return native.assemble_arrays(x, hinges, a, k, rest, c, prev, model, hinge_pos, faces, face_edge_hinges,
                                  face_edge_signs, face_pos, nnz, per_triangle)


@assemble.register_fake
def _(x, hinges, a, k, rest, c, prev, model, hinge_pos, faces, face_edge_hinges, face_edge_signs, face_pos, nnz,
      per_triangle):
    return x.new_empty(nnz)


OPS = {
    "bending_energy": bending_energy,
    "bending_gradient": bending_gradient,
    "bending_hvp": bending_hvp,
    "bending_second_order": bending_second_order,
    "hinge_hessians": hinge_hessians,
    "assemble": assemble,
}
"""Every registered operator by name (``torch.ops.torchbend.<name>``)."""
