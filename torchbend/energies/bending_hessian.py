r"""Exact bending Hessians: per-hinge 12x12 blocks, sparse assembly (per hinge or per triangle),
and PSD projections for Newton-type solvers.

Per hinge (paper eq. 3) the energy Hessian is

    H_h = psi'' grad(theta) grad(theta)^T + psi' Hess(theta)                       (12 x 12)

with ``psi' = d psi/d theta``, ``psi''`` its derivative (:mod:`torchbend.ops.psi`) and the closed-form
``Hess(theta)`` of :mod:`torchbend.ops.hinge`.  Flat index ``3*k + j`` (stencil vertex k, axis j).

Per-triangle assembly (paper sec. 4.1, eq. 7): :mod:`torchbend.ops.triangle`.

Compiled (:mod:`torchbend.backends`), both assemblies (unprojected) run as one C++ pass each: the
per-triangle one is about 1.1x faster than the per-hinge one (both are bound by scattering
~200 resp. 144 values per hinge into the CSR array, not by arithmetic; see
``benchmarks/results/hessian_native_cpu_2core.txt``).

Projections (:class:`~torchbend.options.Projection`)
----------------------------------------------------
``clamp``/``abs`` replace the eigenvalues of each 12x12 hinge block by ``max(l, 0)``/``|l|``;
``gauss_newton`` keeps ``max(psi'', 0) g g^T`` and drops ``psi' Hess(theta)``; ``reduced`` is the
structured projection described in :func:`torchbend.ops.projection.project_blocks`.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .. import backends
from ..backends import native
from ..backends import ops as _ops  # registers torch.ops.torchbend
from ..mesh.topology import HingeTopology
from ..ops import hinge as geometry
from ..ops.projection import project_blocks
from ..ops.psi import BendingModel, psi_theta_derivatives
from ..ops.stencil import chunks, gather, scatter
from ..ops.triangle import triangle_hessian_blocks
from ..options import Assembly, Backend, Projection
from .params import HingeParams
from .sparse import HessianPattern

__all__ = ["hinge_hessian_blocks", "hinge_hessians", "projected_hvp", "assemble", "check_out"]


def check_out(out: Tensor, shape: tuple[int, ...], x: Tensor, what: str) -> Tensor:
    """``out``, a caller's buffer for a result of ``shape`` in ``x``'s dtype on ``x``'s device (``out=`` of
    :meth:`~torchbend.BendingEnergy.hinge_hessians` and :meth:`~torchbend.BendingEnergy.hessian`): contiguous,
    recording no gradient, not overlapping ``x``; else a ``ValueError`` saying which of these it is not."""
    if not isinstance(out, Tensor):
        raise ValueError(f"{what}: out must be a tensor, got {type(out).__name__}")
    problem = None
    if tuple(out.shape) != tuple(shape):
        problem = f"must have shape {tuple(shape)}, got {tuple(out.shape)}"
    elif out.dtype != x.dtype:
        problem = f"must have x's dtype ({x.dtype}), got {out.dtype}"
    elif out.device != x.device:
        problem = f"must be on x's device ({x.device}), got {out.device}"
    elif not out.is_contiguous():
        problem = "must be contiguous"
    elif out.requires_grad:
        problem = "must not require grad (it is written in place)"
    elif _overlap(out, x):
        problem = "overlaps x"
    if problem is not None:
        raise ValueError(f"{what}: out {problem}")
    return out


def _overlap(t: Tensor, u: Tensor) -> bool:
    if t.numel() == 0 or u.numel() == 0 or t.untyped_storage().data_ptr() != u.untyped_storage().data_ptr():
        return False
    lo_t, lo_u = t.data_ptr(), u.data_ptr()
    return lo_t < lo_u + u.numel() * u.element_size() and lo_u < lo_t + t.numel() * t.element_size()


def hinge_hessian_blocks(x4: Tensor, d1: Tensor, d2: Tensor) -> tuple[Tensor, Tensor]:
    """Per-hinge energy Hessians ``(..., H, 12, 12)`` and angle gradients ``(..., H, 12)`` (eager).

    ``x4: (..., H, 4, 3)`` stencils, ``d1 = psi'``, ``d2 = psi''``: ``(..., H)``.  Chunked so that
    the intermediates of one chunk stay in the CPU caches."""
    blocks, grads = [], []
    for sl in chunks(x4.shape[-3]):
        Hb, g = geometry.hinge_energy_hessian_soa(geometry.to_soa(x4[..., sl, :, :]), d1[..., sl], d2[..., sl])
        blocks.append(Hb)
        grads.append(g)
    if len(blocks) == 1:
        return blocks[0], grads[0]
    return torch.cat(blocks, -3), torch.cat(grads, -2)


def _blocks(op: str, x: Tensor, hinges: Tensor, p: HingeParams, model: BendingModel, backend,
            projection: Projection = Projection.NONE, out: Tensor | None = None) -> tuple:
    """``(Hb (..., H, 12, 12), g (..., H, 12), psi'' (..., H))`` by the backend chosen for ``op``, ``Hb``
    projected by ``projection``: in C++ where the blocks were (the eigenvalue projections by Jacobi), else by
    :func:`torchbend.ops.projection.project_blocks`.  ``out``: a checked buffer the compiled CPU kernel writes the
    unprojected blocks into (eagerly; the caller copies the other paths' blocks into it)."""
    if backends.select_backend(op, backend, x, *p.tensors()) is Backend.NATIVE:
        if out is not None and projection is Projection.NONE and not x.is_cuda and not torch.compiler.is_compiling():
            return native.bending_hessians(x, hinges, *p.astuple(), model.value, out=(out, None))
        Hb, g, d2 = _ops.run("hinge_hessians", x, hinges, *p.astuple(), model.value)
        if projection in (Projection.CLAMP, Projection.ABS, Projection.REDUCED):
            Hb = _ops.run("project_blocks", Hb, projection.value, True)
        elif projection is not Projection.NONE:
            Hb = project_blocks(Hb, projection, g, d2)
        return Hb, g, d2
    x4 = gather(x, hinges)
    d1, d2 = psi_theta_derivatives(model, geometry.hinge_angle(x4), *p.astuple())
    Hb, g = hinge_hessian_blocks(x4, d1, d2)
    return (Hb if projection is Projection.NONE else project_blocks(Hb, projection, g, d2)), g, d2


def hinge_hessians(x: Tensor, hinges: Tensor, p: HingeParams, model: BendingModel, projection: Projection,
                   backend, out: Tensor | None = None) -> Tensor:
    """Per-hinge energy Hessians ``(..., H, 12, 12)``, projected per block unless ``projection`` is ``none``;
    written into and returned as ``out`` if given (:func:`check_out`)."""
    if out is not None:
        check_out(out, tuple(x.shape[:-2]) + (hinges.shape[0], 12, 12), x, "BendingEnergy.hinge_hessians")
    Hb = _blocks("hinge_hessians", x, hinges, p, model, backend, projection, out)[0]
    if out is None:
        return Hb
    return out if Hb.data_ptr() == out.data_ptr() else out.copy_(Hb)


def projected_hvp(x: Tensor, v: Tensor, hinges: Tensor, p: HingeParams, model: BendingModel,
                  projection: Projection, backend) -> Tensor:
    """``H_proj v: (..., V, 3)``: matrix-free for ``gauss_newton`` (``max(psi'', 0)(g.v) g``), through the
    projected 12x12 hinge blocks otherwise."""
    V = x.shape[-2]
    v4 = gather(v, hinges).flatten(-2)  # (..., H, 12)
    if projection is Projection.GAUSS_NEWTON:
        backends.select_backend("hvp", backend, x, *p.tensors())  # no compiled kernel: eager
        x4 = gather(x, hinges)
        theta, g4 = geometry.hinge_angle_and_gradient(x4)
        _, d2 = psi_theta_derivatives(model, theta, *p.astuple())
        g = g4.flatten(-2)
        out = (d2.clamp_min(0) * (g * v4).sum(-1))[..., None] * g
    else:
        Hb, g, d2 = _blocks("hvp_projected", x, hinges, p, model, backend, projection)
        out = (Hb @ v4[..., None])[..., 0]
    if out.numel() == 0:  # an empty batch or no hinges: nothing to sum
        return out.new_zeros(out.shape[:-2] + (V, 3))
    return scatter(out.unflatten(-1, (4, 3)), hinges, V)


def _native_assembly(x: Tensor, topo: HingeTopology, hinges: Tensor, p: HingeParams, model: BendingModel,
                     pattern: HessianPattern, per_triangle: bool, out: Tensor | None) -> Tensor:
    """The CSR values of the compiled assembly (the operator; eagerly into ``out`` if given)."""
    args = (hinges, *p.astuple(), model.value, pattern.hinge_blocks, topo.faces, topo.face_edge_hinges,
            topo.face_edge_signs, pattern.face_blocks, pattern.row_len, pattern.nnz, per_triangle)
    if out is None:
        return _ops.run("assemble", x, *args)
    if torch.compiler.is_compiling():
        return out.copy_(torch.ops.torchbend.assemble(x, *args))
    return native.assemble_arrays(x, *args, out=out)


def assemble(x: Tensor, topo: HingeTopology, hinges: Tensor, p: HingeParams, model: BendingModel,
             projection: Projection, assembly: Assembly, pattern: HessianPattern, backend,
             out: Tensor | None = None) -> Tensor:
    """The Hessian of one mesh ``x: (V, 3)`` as a sparse CSR tensor ``(3V, 3V)`` (see the module docstring),
    its values written into ``out`` (``(nnz,)``, :func:`check_out`) if given: the matrix's ``values()`` are then
    ``out`` itself.

    The eigenvalue projections act on whole hinge blocks, so they are assembled per hinge whatever
    ``assembly`` says; ``gauss_newton`` has no ``Hess(theta)`` part."""
    if out is not None:
        check_out(out, (pattern.nnz,), x, "BendingEnergy.hessian")
    if hinges.shape[0] == 0:  # no interior edge: the zero matrix
        return pattern.csr(x.new_zeros(pattern.nnz) if out is None else out.zero_())
    per_triangle = assembly is Assembly.TRIANGLE and projection in (Projection.NONE, Projection.GAUSS_NEWTON)
    if per_triangle or projection is Projection.NONE:  # projected per-hinge blocks ask in _blocks
        op = "hessian_triangle" if per_triangle else "hessian_hinge"
        if backends.select_backend(op, backend, x, *p.tensors()) is Backend.NATIVE and projection is Projection.NONE:
            return pattern.csr(_native_assembly(x, topo, hinges, p, model, pattern, per_triangle, out))
    values = x.new_zeros(pattern.nnz) if out is None else out.zero_()

    def positions(sl: slice) -> Tensor:  # the value positions of the entries of the hinges' blocks
        return pattern.element_positions(x.device, sl).reshape(-1)

    if not per_triangle:
        for sl in chunks(hinges.shape[0]):  # chunks: the blocks of one chunk stay in cache
            Hb = _blocks("hessian_hinge", x, hinges[sl], p.sliced(sl), model, backend, projection)[0]
            values.index_add_(0, positions(sl), Hb.reshape(-1))
        return pattern.csr(values)
    x4 = gather(x, hinges)
    theta, g4 = geometry.hinge_angle_and_gradient(x4)
    d1, d2 = psi_theta_derivatives(model, theta, *p.astuple())
    g = g4.flatten(-2)
    w = d2 if projection is Projection.NONE else d2.clamp_min(0)
    for sl in chunks(hinges.shape[0]):
        gg = (w[sl, None] * g[sl])[:, :, None] * g[sl, None, :]
        values.index_add_(0, positions(sl), gg.reshape(-1))
    if projection is Projection.NONE:
        Hf = triangle_hessian_blocks(x, topo, d1)[pattern.on(x.device)["hinged_faces"]]
        values.index_add_(0, pattern.hinged_face_positions(x.device).reshape(-1), Hf.reshape(-1))
    return pattern.csr(values)
