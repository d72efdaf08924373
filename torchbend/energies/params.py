"""The per-hinge parameters of the bending energy, validated and expanded in one place.

A :class:`BendingEnergy` stores the stiffness ``k`` [N m], the rest angles [rad] and the optional
damping ``k_d`` [N m s] (validated once by :func:`hinge_parameter`); each call binds them, with the
rest weights ``a`` and the call's ``theta_prev``/``dt``, into one :class:`HingeParams` cast to the
dtype of the positions.  Every path (autograd Functions, Hessian blocks, assembly, compiled
kernels) takes its scalars from that object.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .._checks import check_finite_tensor
from ..mesh.topology import HingeTopology
from ..ops.stencil import nondegenerate, sliced

__all__ = ["HingeParams", "hinge_parameter", "rest_hinge_weights", "module_tensor"]


def rest_hinge_weights(rest_positions: Tensor, topo: HingeTopology) -> Tensor:
    """``a_h = 3 |e0|^2 / (A_A + A_B)`` [dimensionless]: ``(H,)`` from rest positions ``(V, 3)`` [m].

    Raises ``ValueError`` naming the zero-length edges (with their hinge index) and the faces with
    (numerically) zero area: the weight is undefined there.
    """
    X = rest_positions.detach().to(torch.float64)
    tol = torch.finfo(rest_positions.dtype).eps
    F = topo.faces.to(X.device)
    p0, p1, p2 = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    lengths = torch.stack(((p2 - p1).norm(dim=-1), (p0 - p2).norm(dim=-1), (p1 - p0).norm(dim=-1)), 1)  # opposite k
    longest = lengths.amax(-1)
    # an edge is of zero length relative to its own triangles (no absolute threshold: the units and the
    # mesh's scale do not matter), i.e. when it is shorter than eps times the longest edge of its faces
    E = topo.edges.to(X.device)
    elen = (X[E[:, 1]] - X[E[:, 0]]).norm(dim=-1)
    local = X.new_zeros(E.shape[0]).scatter_reduce(0, topo.face_edges.to(X.device).reshape(-1),
                                                   longest.repeat_interleave(3), "amax", include_self=False)
    bad = torch.nonzero(~(elen > tol * local)).reshape(-1)
    if bad.numel():
        pairs = [tuple(p) for p in E[bad[:8]].tolist()]
        hinge_ids = topo.edge_hinges.to(X.device)[bad[:8]].tolist()
        raise ValueError(
            f"rest shape has zero-length edges {pairs} (hinge index or -1 for boundary: {hinge_ids})"
            + (f" ... ({bad.numel()} in all)" if bad.numel() > 8 else "")
        )
    area2 = torch.linalg.cross(p1 - p0, p2 - p0).norm(dim=-1)  # 2 * area
    bad = torch.nonzero(~nondegenerate(area2, longest * longest, eps=tol)).reshape(-1)
    if bad.numel():
        raise ValueError(
            f"rest shape has zero-area (degenerate) triangles: faces {bad[:8].tolist()}"
            + (f" ... ({bad.numel()} in all)" if bad.numel() > 8 else "")
            + "; the bending weights 3|e|^2/(A_A+A_B) are undefined there"
        )
    H = topo.hinges.to(X.device)
    elen2 = ((X[H[:, 1]] - X[H[:, 0]]) ** 2).sum(-1)
    hf = topo.hinge_faces.to(X.device)
    area = 0.5 * area2
    a = 3.0 * elen2 / (area[hf[:, 0]] + area[hf[:, 1]])
    return a.to(rest_positions.dtype)


def hinge_parameter(value, name: str, H: int, dtype, device, *, nonneg: bool = True) -> Tensor:
    """A validated per-hinge parameter: a scalar or ``(H,)`` tensor (an ``nn.Parameter`` is kept as is,
    so it stays learnable).  ``ValueError`` for a wrong shape, non-finite or (with ``nonneg``)
    negative values."""
    if isinstance(value, nn.Parameter):
        t = value
    else:
        t = torch.as_tensor(value, dtype=dtype, device=device)
        if not t.is_floating_point():
            t = t.to(dtype)
    if t.ndim > 1 or (t.ndim == 1 and t.shape[0] != H):
        raise ValueError(f"{name} must be a scalar or have shape ({H},) (one per hinge), got {tuple(t.shape)}")
    d = t.detach()
    if not bool(torch.isfinite(d).all()):
        raise ValueError(f"{name} must be finite")
    if nonneg and bool((d < 0).any()):
        raise ValueError(f"{name} must be non-negative, got min {float(d.min())}")
    return t


def module_tensor(module: nn.Module, name: str):
    """``getattr(module, name)`` for a buffer or parameter, without ``nn.Module.__getattr__`` (its fallback
    lookup costs about half a microsecond, and the hot paths read several tensors a call)."""
    d = module.__dict__  # (torch.compile traces this lookup as well)
    buffers = d["_buffers"]
    if name in buffers:
        return buffers[name]
    params = d["_parameters"]
    if name in params:
        return params[name]
    return getattr(module, name)


def _cast(t: Tensor, dtype: torch.dtype) -> Tensor:
    return t if t.dtype is dtype else t.to(dtype)


@dataclass(frozen=True)
class HingeParams:
    """The scalars of ``psi`` for one evaluation, in the dtype of the positions.

    Attributes:
        a: ``(H,)`` rest weights ``3|e0|^2/(A_A + A_B)`` (constants: no gradient flows to them).
        k: stiffness [N m], scalar or ``(H,)``.
        rest: rest angles [rad], scalar or ``(H,)``.
        c: viscous coefficient ``k_d/dt`` [N m], scalar or ``(H,)``; ``None`` without damping.
        prev: previous angles ``theta_prev`` [rad], ``(..., H)``; ``None`` without damping.
    """

    a: Tensor
    k: Tensor
    rest: Tensor
    c: Tensor | None = None
    prev: Tensor | None = None

    @classmethod
    def bind(cls, module, x: Tensor, theta_prev=None, dt=None) -> HingeParams:
        """The parameters of ``module`` (a :class:`BendingEnergy`) for positions ``x``, with the
        viscous term when ``theta_prev`` and ``dt`` [s] are given (``ValueError`` when only one is, or
        the module has no damping)."""
        dtype = x.dtype
        c = prev = None
        if theta_prev is not None or dt is not None:
            damping = module_tensor(module, "damping")
            if damping is None:
                raise ValueError("theta_prev/dt given but the module has no damping (pass damping=k_d)")
            if theta_prev is None or dt is None:
                raise ValueError("viscous damping needs both theta_prev and dt")
            dt = float(dt)
            if not (dt > 0 and math.isfinite(dt)):
                raise ValueError(f"dt must be positive and finite, got {dt}")
            prev = torch.as_tensor(theta_prev, device=x.device)
            H = module.hinge_count
            if prev.shape[-1:] != (H,):
                raise ValueError(f"theta_prev must have shape (..., {H}) (one angle per hinge), got {tuple(prev.shape)}")
            check_finite_tensor(prev, "theta_prev", module.check_finite)
            prev = prev.to(dtype)
            c = damping.to(dtype) / dt
        return cls(_cast(module_tensor(module, "weights"), dtype), _cast(module_tensor(module, "stiffness"), dtype),
                   _cast(module_tensor(module, "rest_angles"), dtype), c, prev)

    def astuple(self) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None]:
        """``(a, k, rest, c, prev)``."""
        return (self.a, self.k, self.rest, self.c, self.prev)

    def tensors(self) -> tuple[Tensor, ...]:
        """The parameters that are present (for checks such as ``requires_grad``)."""
        return tuple(t for t in self.astuple() if t is not None)

    def sliced(self, sl: slice) -> HingeParams:
        """The parameters of the hinges ``sl`` (scalars stay scalars)."""
        return HingeParams(self.a[sl], self.k if self.k.ndim == 0 else self.k[sl],
                           self.rest if self.rest.ndim == 0 else self.rest[sl], sliced(self.c, sl), sliced(self.prev, sl))

    def expanded(self, batch: tuple) -> list[Tensor]:
        """``[k, rest(, c, prev)]`` as ``(*batch, H)`` views (the autograd Functions return gradients
        of that shape)."""
        shape = tuple(batch) + tuple(self.a.shape)
        out = [self.k.expand(shape), self.rest.expand(shape)]
        if self.c is not None and self.prev is not None:
            out += [self.c.expand(shape), self.prev.expand(shape)]
        return out
