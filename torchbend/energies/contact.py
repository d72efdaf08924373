r"""Contact laws: the one-sided potential of a penetration depth, shared by the solver's colliders
(:mod:`torchbend.energies.colliders`) and the contact losses (:class:`torchbend.losses.BodyContact`).

A law is a function ``phi(d)`` of the depth ``d = margin - s`` [m] of a point below the contact surface
offset by ``margin`` (``s`` the signed distance, positive outside), zero for ``d <= 0``, with its first and
second derivatives in closed form:

* :class:`Penalty` (``"penalty"``): ``phi = k/2 max(0, d)^2``, ``k`` [N/m]; the force ``k d`` grows linearly
  with the depth (the solver's colliders by default);
* :class:`PowerBarrier` (``"barrier"``): ``phi = k max(0, d)^p``, ``k`` [J/m^p], ``p > 1`` (default 3): HOOD's
  and SNUG's collision term ``k max(0, eps - s)^3`` with ``margin = eps`` a few millimetres.

``p = 2`` and ``k_barrier = k_penalty / 2`` is the same potential.  A colliding point's energy, gradient and
Hessian follow by the chain rule from ``s``'s gradient (the unit normal ``n``) and Hessian::

    grad phi = -phi'(d) n,          Hess phi = phi''(d) n n^T - phi'(d) Hess s

(:meth:`ContactLaw.vertex_terms`).  :func:`contact_law` builds a law from a name, a stiffness and a power.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._checks import positive

__all__ = ["ContactLaw", "Penalty", "PowerBarrier", "contact_law", "LAWS"]


@dataclass(frozen=True)
class ContactLaw:
    """Base of the contact laws: ``phi(d)`` with ``d`` the penetration depth [m] (module docstring)."""

    stiffness: float

    @property
    def power(self) -> float:  # pragma: no cover - abstract
        """The exponent ``p`` of ``phi ~ d^p``."""
        raise NotImplementedError

    def value(self, d: Tensor) -> Tensor:  # pragma: no cover - abstract
        """``phi(d)`` [J], elementwise (zero for ``d <= 0``)."""
        raise NotImplementedError

    def slope(self, d: Tensor) -> Tensor:  # pragma: no cover - abstract
        """``phi'(d)`` [N], elementwise (zero for ``d <= 0``)."""
        raise NotImplementedError

    def curvature(self, d: Tensor) -> Tensor:  # pragma: no cover - abstract
        """``phi''(d)`` [N/m], elementwise (zero for ``d < 0``)."""
        raise NotImplementedError

    def vertex_terms(self, d: Tensor, n: Tensor, curv: Tensor | None, exact: bool) -> Tensor:
        """Per-point Hessian blocks ``(V, 3, 3)`` of ``phi(margin - s(x))`` for depths ``d (V,)``, unit normals
        ``n (V, 3)`` and ``Hess s`` ``curv (V, 3, 3)`` (None: a plane); ``exact=False`` drops the curvature
        term ``-phi'(d) Hess s`` (negative semi-definite for a convex surface), leaving a PSD block."""
        H = self.curvature(d)[:, None, None] * n[:, :, None] * n[:, None, :]
        if curv is not None and exact:
            H = H - self.slope(d)[:, None, None] * curv
        return H


@dataclass(frozen=True)
class Penalty(ContactLaw):
    """``phi = k/2 max(0, d)^2`` with ``stiffness`` ``k`` [N/m]."""

    def __post_init__(self):
        object.__setattr__(self, "stiffness", positive(self.stiffness, "Penalty: stiffness"))

    @property
    def power(self) -> float:  # pyright: ignore[reportIncompatibleVariableOverride]
        return 2.0

    def value(self, d: Tensor) -> Tensor:
        a = d.clamp_min(0)
        return 0.5 * self.stiffness * a * a

    def slope(self, d: Tensor) -> Tensor:
        return self.stiffness * d.clamp_min(0)

    def curvature(self, d: Tensor) -> Tensor:
        return self.stiffness * (d > 0).to(d.dtype)


@dataclass(frozen=True)
class PowerBarrier(ContactLaw):
    """``phi = k max(0, d)^p`` with ``stiffness`` ``k`` [J/m^p] and ``power`` ``p`` (finite, > 1)."""

    power: float = 3.0  # pyright: ignore[reportIncompatibleMethodOverride]

    def __post_init__(self):
        object.__setattr__(self, "stiffness", positive(self.stiffness, "PowerBarrier: stiffness"))
        try:
            p = float(self.power)
        except (TypeError, ValueError):
            raise ValueError(f"PowerBarrier: power must be a number > 1, got {self.power!r}") from None
        if not (p > 1 and math.isfinite(p)):
            raise ValueError(f"PowerBarrier: power must be > 1 and finite (a differentiable potential), got {self.power!r}")
        object.__setattr__(self, "power", p)

    def value(self, d: Tensor) -> Tensor:
        return self.stiffness * d.clamp_min(0).pow(self.power)

    def slope(self, d: Tensor) -> Tensor:
        return self.stiffness * self.power * d.clamp_min(0).pow(self.power - 1)

    def curvature(self, d: Tensor) -> Tensor:
        p, active = self.power, d > 0
        a = torch.where(active, d, torch.ones_like(d))  # (d^(p-2) of an inactive point is never formed: p < 2)
        return torch.where(active, self.stiffness * p * (p - 1) * a.pow(p - 2), torch.zeros_like(d))


LAWS = {"penalty": Penalty, "barrier": PowerBarrier}
"""The contact laws by name (configs' ``law`` key)."""


def contact_law(law: str | ContactLaw, stiffness: float | None = None, power: float | None = None) -> ContactLaw:
    """A :class:`ContactLaw`: ``law`` itself, or the law named ``"penalty"`` (``stiffness`` [N/m]; ``power``
    must be None or 2) or ``"barrier"`` (``stiffness`` [J/m^p], ``power``, default 3).  A ``ValueError``
    names what is wrong."""
    if isinstance(law, ContactLaw):
        return law
    try:
        return _named_law(law, stiffness, power)
    except ValueError as e:  # the law's own messages, without the class name (the caller names itself)
        raise ValueError(str(e).removeprefix("PowerBarrier: ").removeprefix("Penalty: ")) from None


def _named_law(law, stiffness, power) -> ContactLaw:
    if law not in LAWS:
        raise ValueError(f"contact law must be one of {sorted(LAWS)} or a ContactLaw, got {law!r}")
    if stiffness is None:
        raise ValueError(f"the {law} contact law needs a stiffness")
    if law == "penalty":
        if power is not None and power != 2:
            raise ValueError(f"the penalty contact law has power 2 (k/2 d^2), got power={power!r}: use law='barrier'")
        return Penalty(stiffness)
    return PowerBarrier(stiffness, 3.0 if power is None else power)
