r"""Rigid colliders with a smooth one-sided penalty (analytic gradient and Hessian).

Each collider has a signed distance ``s(x)`` (positive outside) and penalises every vertex closer
than ``margin``::

    E = sum_i  k/2 * max(0, margin - s(x_i))^2          [J],  k = stiffness [N/m]

    grad_i = -k d_i grad s,          Hess_i = k grad s grad s^T  -  k d_i Hess s        (d_i = margin - s > 0)

``grad s`` is the unit contact normal.  For convex colliders ``Hess s`` is PSD, so the curvature
term ``-k d Hess s`` is negative semi-definite; every projection but ``none``
(:class:`~torchbend.options.Projection`) drops it.  Units: positions [m].
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._checks import nonnegative, positive, vec3
from ..options import Projection

__all__ = ["Sphere", "Plane", "Capsule", "Collider"]


@dataclass(frozen=True, kw_only=True)
class Collider:
    """Base of the rigid colliders: a signed distance and the one-sided penalty on it, with
    ``stiffness`` [N/m] (> 0) and ``margin`` [m] (>= 0) as keyword arguments of every collider."""

    stiffness: float = 1e4
    margin: float = 0.0

    def _check_penalty(self) -> None:
        """Validate (and store as floats) the penalty ``stiffness`` (> 0) and ``margin`` (>= 0)."""
        name = type(self).__name__
        object.__setattr__(self, "stiffness", positive(self.stiffness, f"{name}.stiffness"))
        object.__setattr__(self, "margin", nonnegative(self.margin, f"{name}.margin"))

    def _sd(self, x: Tensor):  # pragma: no cover - abstract
        """``(s, n, curv)``: signed distance ``(V,)``, unit normal ``(V, 3)``, ``Hess s`` ``(V, 3, 3)`` or None."""
        raise NotImplementedError

    def depth(self, x: Tensor) -> Tensor:
        """Penetration depth ``margin - s(x)`` ``(V,)`` [m] (positive = inside the margin)."""
        return self.margin - self._sd(x)[0]

    def energy(self, x: Tensor) -> Tensor:
        d = (self.margin - self._sd(x)[0]).clamp_min(0)
        return 0.5 * self.stiffness * (d * d).sum()

    def gradient(self, x: Tensor) -> Tensor:
        s, n, _ = self._sd(x)
        d = (self.margin - s).clamp_min(0)
        return -self.stiffness * d[:, None] * n

    def hessian_blocks(self, x: Tensor, project=None) -> Tensor:
        """Per-vertex 3x3 Hessian blocks ``(V, 3, 3)`` [N/m]; any ``project`` but ``None``/``"none"``
        drops the curvature term (PSD for convex colliders)."""
        exact = Projection.parse(project, what="collider projection") is Projection.NONE
        s, n, curv = self._sd(x)
        d = (self.margin - s).clamp_min(0)
        active = (d > 0).to(x.dtype)
        H = self.stiffness * active[:, None, None] * n[:, :, None] * n[:, None, :]
        if curv is not None and exact:
            H = H - self.stiffness * d[:, None, None] * curv
        return H


def _radial(p: Tensor, radius: float):
    """Distance to a point (``p`` relative to it) minus ``radius``: ``(s, n, Hess s)``."""
    r = p.norm(dim=-1)
    safe = torch.where(r > 0, r, torch.ones_like(r))
    n = torch.where((r > 0)[:, None], p / safe[:, None], torch.zeros_like(p))
    eye = torch.eye(3, dtype=p.dtype, device=p.device)
    curv = (eye - n[:, :, None] * n[:, None, :]) / safe[:, None, None]
    return r - radius, n, curv


@dataclass(frozen=True)
class Sphere(Collider):
    """Solid sphere ``|x - center| <= radius`` [m]."""

    center: tuple = (0.0, 0.0, 0.0)
    radius: float = 1.0
    def __post_init__(self):
        object.__setattr__(self, "center", vec3(self.center, "Sphere.center"))
        object.__setattr__(self, "radius", positive(self.radius, "Sphere.radius"))
        self._check_penalty()

    def _sd(self, x: Tensor):
        return _radial(x - x.new_tensor(self.center), self.radius)


@dataclass(frozen=True)
class Plane(Collider):
    """Half-space below the plane through ``point`` with outward ``normal`` (normalised)."""

    point: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, 1.0)
    def __post_init__(self):
        object.__setattr__(self, "point", vec3(self.point, "Plane.point"))
        n = vec3(self.normal, "Plane.normal")
        norm = math.sqrt(sum(v * v for v in n))
        if norm == 0:
            raise ValueError("Plane.normal must be non-zero")
        object.__setattr__(self, "normal", tuple(v / norm for v in n))
        self._check_penalty()

    def _sd(self, x: Tensor):
        n = x.new_tensor(self.normal)
        s = (x - x.new_tensor(self.point)) @ n
        return s, n.expand_as(x), None


@dataclass(frozen=True)
class Capsule(Collider):
    """Solid capsule: points within ``radius`` [m] of the segment ``a -> b`` [m]."""

    a: tuple = (0.0, 0.0, 0.0)
    b: tuple = (1.0, 0.0, 0.0)
    radius: float = 0.1
    def __post_init__(self):
        a, b = vec3(self.a, "Capsule.a"), vec3(self.b, "Capsule.b")
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "b", b)
        length = math.dist(a, b)
        if length == 0:
            raise ValueError("Capsule.a and Capsule.b must differ (use a Sphere for a point)")
        object.__setattr__(self, "radius", positive(self.radius, "Capsule.radius"))
        self._check_penalty()

    def transformed(self, a, b) -> Capsule:
        """The same capsule with new end points ``a``, ``b`` [m] (e.g. attached to a moving link).

        Tensor end points are kept as tensors: the collider's energy and gradient are then
        differentiable with respect to them (used to differentiate through contacts with robot links)."""
        if isinstance(a, Tensor) or isinstance(b, Tensor):
            return _TensorCapsule(a, b, radius=self.radius, stiffness=self.stiffness, margin=self.margin)
        return Capsule(a=a, b=b, radius=self.radius, stiffness=self.stiffness, margin=self.margin)

    def _ends(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return x.new_tensor(self.a), x.new_tensor(self.b)

    def _sd(self, x: Tensor):
        a, b = self._ends(x)
        return _capsule_sd(x, a, b, self.radius)


class _TensorCapsule(Capsule):
    """A :class:`Capsule` whose end points are tensors ``(3,)`` (possibly requiring grad)."""

    ends: tuple[Tensor, Tensor]

    def __init__(self, a: Tensor, b: Tensor, *, radius: float, stiffness: float, margin: float):
        a, b = torch.as_tensor(a), torch.as_tensor(b)
        super().__init__(a=tuple(a.detach().tolist()), b=tuple(b.detach().tolist()), radius=radius, stiffness=stiffness,
                         margin=margin)
        object.__setattr__(self, "ends", (a, b))

    def _ends(self, x: Tensor) -> tuple[Tensor, Tensor]:
        a, b = self.ends
        return a.to(dtype=x.dtype, device=x.device), b.to(dtype=x.dtype, device=x.device)


def _capsule_sd(x: Tensor, a: Tensor, b: Tensor, radius: float):
    """Signed distance of ``x (V, 3)`` to the capsule ``a -> b`` (tensors ``(3,)``): ``(s, n, Hess s)``."""
    length = (b - a).norm()
    t_hat = (b - a) / length
    tau = torch.minimum(((x - a) @ t_hat).clamp_min(0.0), length)
    s, n, curv = _radial(x - (a + tau[:, None] * t_hat), radius)
    interior = ((tau > 0) & (tau < length)).to(x.dtype)
    # along the segment's interior the distance is constant in the axis direction
    tt = t_hat[:, None] * t_hat[None, :]
    r = (s + radius).clamp_min(torch.finfo(x.dtype).tiny)
    curv = curv - interior[:, None, None] * tt / r[:, None, None]
    return s, n, curv
