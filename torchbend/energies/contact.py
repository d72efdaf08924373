r"""Contact laws: the one-sided potential of a penetration depth, shared by the solver's colliders
(:mod:`torchbend.energies.colliders`) and the contact losses (:class:`torchbend.losses.BodyContact`).

A law is a function ``phi(d)`` of the depth ``d = margin - s`` [m] of a point below the contact surface
offset by ``margin`` (``s`` the signed distance, positive outside), zero for ``d <= 0``, with its first and
second derivatives in closed form:

* :class:`Penalty` (``"penalty"``): ``phi = k/2 max(0, d)^2``, ``k`` [N/m]; the force ``k d`` grows linearly
  with the depth (the training losses' usual law; a solver's collider with ``law="penalty"``);
* :class:`PowerBarrier` (``"barrier"``): ``phi = k max(0, d)^p``, ``k`` [J/m^p], ``p > 1`` (default 3): HOOD's
  and SNUG's collision term ``k max(0, eps - s)^3`` with ``margin = eps`` a few millimetres;
* :class:`LogBarrier` (``"ipc"``): the barrier of Incremental Potential Contact on the gap ``s`` with the
  activation distance ``dhat = margin`` [m] (> 0), ``phi = -k (s - dhat)^2 log(s / dhat)`` for ``0 < s < dhat``,
  i.e. ``-k d^2 log(1 - d / dhat)``, ``k`` [J/m^2]: zero with its first two derivatives where a point comes
  within ``dhat`` (C2: the Newton model sees a contact before it is made, where the penalty's curvature jumps
  from 0 to ``k``), convex, and infinite on the surface (``s <= 0``), which a point never reaches: the
  colliders' step bound keeps every step of a solve outside (``bounded``).  The solver's colliders' default.

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

__all__ = ["ContactLaw", "Penalty", "PowerBarrier", "LogBarrier", "contact_law", "LAWS"]


@dataclass(frozen=True)
class ContactLaw:
    """Base of the contact laws: ``phi(d)`` with ``d`` the penetration depth [m] (module docstring)."""

    stiffness: float

    bounded = False
    """Whether the law is infinite on the surface (``s = 0``), which a step must then never reach."""

    @property
    def power(self) -> float | None:  # pragma: no cover - abstract
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


@dataclass(frozen=True)
class LogBarrier(ContactLaw):
    """``phi = -k d^2 log(1 - d / dhat)`` for ``0 < d < dhat`` (``d = dhat - s``; zero for ``d <= 0``, infinite for
    ``d >= dhat``: on or inside the surface) with ``stiffness`` ``k`` [J/m^2] and activation distance ``dhat``
    [m] (> 0; the colliders' ``margin``).  With ``u = 1 - d / dhat``::

        phi'  = -2 k d log u + k d^2 / (dhat u)
        phi'' = -2 k log u + 4 k d / (dhat u) + k (d / (dhat u))^2

    all zero at ``d = 0``; ``phi ~ k d^3 / dhat`` near the activation."""

    dhat: float = 0.0
    bounded = True

    def __post_init__(self):
        object.__setattr__(self, "stiffness", positive(self.stiffness, "LogBarrier: stiffness"))
        object.__setattr__(self, "dhat", positive(self.dhat, "LogBarrier: dhat (the margin)"))

    @property
    def power(self) -> None:  # pyright: ignore[reportIncompatibleVariableOverride]
        return None

    def _parts(self, d: Tensor):
        # (a, r = a / dhat, log u, u, a < dhat) with a = max(d, 0): u = (dhat - a) / dhat is the gap over dhat,
        # formed from the exact difference dhat - a (Sterbenz, a near dhat) and its log without cancellation
        # either way (log1p(-r) for small r)
        a = d.clamp_min(0)
        inside = a < self.dhat
        a_in = torch.where(inside, a, torch.zeros_like(a))  # the log of an infeasible point is never formed
        r = a_in / self.dhat
        u = (self.dhat - a_in) / self.dhat
        lg = torch.where(r < 0.5, torch.log1p(-r), torch.log(u))
        return a, r, lg, u, inside

    def value(self, d: Tensor) -> Tensor:
        a, _, lg, _, inside = self._parts(d)
        return torch.where(inside, -self.stiffness * a * a * lg, torch.full_like(a, math.inf))

    def slope(self, d: Tensor) -> Tensor:
        a, r, lg, u, inside = self._parts(d)
        return torch.where(inside, self.stiffness * a * (r / u - 2 * lg), torch.full_like(a, math.inf))

    def curvature(self, d: Tensor) -> Tensor:
        _, r, lg, u, inside = self._parts(d)
        q = r / u
        return torch.where(inside, self.stiffness * (4 * q + q * q - 2 * lg), torch.full_like(r, math.inf))


LAWS = {"penalty": Penalty, "barrier": PowerBarrier, "ipc": LogBarrier}
"""The contact laws by name (configs' ``law`` key)."""


def contact_law(law: str | ContactLaw, stiffness: float | None = None, power: float | None = None,
                margin: float | None = None) -> ContactLaw:
    """A :class:`ContactLaw`: ``law`` itself, or the law named ``"penalty"`` (``stiffness`` [N/m]; ``power``
    must be None or 2), ``"barrier"`` (``stiffness`` [J/m^p], ``power``, default 3) or ``"ipc"`` (``stiffness``
    [J/m^2], ``margin`` the activation distance ``dhat`` [m] > 0, no ``power``).  A ``ValueError`` names what is
    wrong."""
    if isinstance(law, ContactLaw):
        return law
    try:
        return _named_law(law, stiffness, power, margin)
    except ValueError as e:  # the law's own messages, without the class name (the caller names itself)
        msg = str(e)
        for prefix in ("PowerBarrier: ", "Penalty: ", "LogBarrier: "):
            msg = msg.removeprefix(prefix)
        raise ValueError(msg) from None


def _named_law(law, stiffness, power, margin=None) -> ContactLaw:
    if law not in LAWS:
        raise ValueError(f"contact law must be one of {sorted(LAWS)} or a ContactLaw, got {law!r}")
    if stiffness is None:
        raise ValueError(f"the {law} contact law needs a stiffness")
    if law == "penalty":
        if power is not None and power != 2:
            raise ValueError(f"the penalty contact law has power 2 (k/2 d^2), got power={power!r}: use law='barrier'")
        return Penalty(stiffness)
    if law == "ipc":
        if power is not None:
            raise ValueError(f"the ipc contact law has no power (its activation is C2), got power={power!r}")
        if not margin:
            raise ValueError("the ipc contact law needs margin > 0 (its activation distance dhat) [m], got "
                             f"margin={margin!r}")
        return LogBarrier(stiffness, float(margin))
    return PowerBarrier(stiffness, 3.0 if power is None else power)
