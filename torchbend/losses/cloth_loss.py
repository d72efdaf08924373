r"""``ClothLoss``: named loss terms summed with weights, per-term values for logging.

Loss scaling
------------
Every term of :mod:`torchbend.losses` is an energy in joules of the same system (the incremental
potential of one backward-Euler step: inertia + gravity + stretch + bending + contact + pinning).
Summed with unit weights, their sum's minimiser is the physical state, so physics needs no weights:
HOOD and SNUG sum their criteria unweighted apart from the contact penalty (a numerical device, not a
physical energy; a weight ramp on it is common).  The *size* of the loss follows the mesh and the
material (a 1 m^2 cloth of 0.2 kg/m^2 falling 0.3 m loses about 0.6 J; a 1 cm^2 patch a million times
less), which changes the effective learning rate of plain SGD (Adam is invariant to a constant
scale).  To make the loss dimensionless and O(1) across meshes, divide by a reference energy, e.g.
:func:`energy_scale` ``= M g L`` (total mass, gravity, the rest shape's size): pass
``weights={name: 1 / E_ref for name in terms}`` or divide the total.  Reweight a physical term only
deliberately (that changes the equilibrium).
"""
from __future__ import annotations

import math
from collections.abc import Mapping

from torch import Tensor, nn

from .._checks import positive
from ..mesh.topology import lumped_areas, mesh_and_rest

__all__ = ["ClothLoss", "energy_scale"]

_REDUCTIONS = ("mean", "sum", "none")


def energy_scale(faces, rest: Tensor, density: float, gravity: float = 9.81) -> float:
    """Reference energy ``M g L`` [J] of a cloth: total mass ``M = density * area`` [kg] (``density`` in
    kg/m^2), gravity ``g`` [m/s^2] and ``L`` the diagonal of the rest shape's bounding box [m]; divide
    the loss by it to make it dimensionless (module docstring)."""
    topo, rest = mesh_and_rest(faces, rest)
    mass = positive(density, "density") * float(lumped_areas(topo.faces.to(rest.device), rest).sum())
    size = float((rest.detach().amax(0) - rest.detach().amin(0)).norm())
    return mass * positive(gravity, "gravity") * size


def _weight(name: str, value) -> float:
    """A term's weight as a finite float; ``ValueError`` naming the term otherwise."""
    try:
        w = float(value)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"ClothLoss: the weight of term '{name}' must be a number, got {value!r}") from None
    if not math.isfinite(w):
        raise ValueError(f"ClothLoss: the weight of term '{name}' must be finite, got {value!r}")
    return w


class ClothLoss(nn.Module):
    """Weighted sum of named loss terms, with the per-term values for logging (HOOD's "criterions
    summed by name").

    Args:
        terms: ``{name: module}``; each module maps positions ``x (B, V, 3)`` (or ``(V, 3)``) and keyword
            inputs to per-sample values ``(B,)`` (or ``()``) [J]: the terms of :mod:`torchbend.losses`
            (:class:`Stretch`, :class:`Bending`, :class:`Gravity`, :class:`Inertia`, :class:`Pinning`,
            :class:`BodyContact`) or any ``nn.Module`` such as :class:`~torchbend.BendingEnergy`.
        weights: ``{name: weight}`` (missing names weigh 1), finite numbers (a NaN or infinite weight is a
            ``ValueError``, here and at every call).  A term of weight 0 is not evaluated (it costs nothing)
            and is left out of the values.  ``loss.weights`` may be changed between calls (e.g. a ramp on
            the contact weight).
        reduction: ``"mean"`` over the batch (default), ``"sum"`` or ``"none"`` (per sample ``(B,)``).
            An empty batch (``x (0, V, 3)``) gives ``0`` for ``"mean"`` and ``"sum"`` (no sample adds to the
            loss; torch's mean of an empty tensor would be NaN) and a ``(0,)`` tensor for ``"none"``; the
            gradient is then the empty ``(0, V, 3)``.

    ``forward(x, **inputs) -> (total, values)``: ``total`` the weighted sum, reduced; ``values``
    ``{name: value}`` the *unweighted* reduced value of every evaluated term, detached (for logging;
    ``total = sum_name weight_name * values[name]``).

    Routing: each term declares the keyword inputs it takes in its ``inputs`` attribute (e.g.
    :class:`Inertia`: ``x_prev``, ``v_prev``, ``x_hat``, ``dt``, ``density``); ``ClothLoss`` passes each
    term the given inputs it declares, so one namespace serves all terms (``density`` reaches both
    :class:`Gravity` and :class:`Inertia`; per-sample materials are ``young``, ``poisson``, ``thickness``,
    ``bending_stiffness``).  Inputs for one term only go in a mapping under the term's name
    (``loss(x, contact={"body": b})``: needed when two terms of one class are in the loss).  A module
    without ``inputs`` gets ``x`` alone.  A keyword no term takes, or a term's bad input, is a
    ``ValueError`` naming it (and the term).  ``None`` inputs count as absent.

    Units: every term is an energy [J]; see the module docstring on loss scaling and weights.
    """

    def __init__(self, terms: Mapping[str, nn.Module], weights: Mapping[str, float] | None = None, *,
                 reduction: str = "mean"):
        super().__init__()
        if not isinstance(terms, Mapping) or not terms:
            raise ValueError("ClothLoss: terms must be a non-empty mapping {name: module}")
        for name, term in terms.items():
            if not isinstance(name, str) or not name or "." in name:
                raise ValueError(f"ClothLoss: term names must be non-empty strings without '.', got {name!r}")
            if not isinstance(term, nn.Module):
                raise ValueError(f"ClothLoss: term '{name}' must be an nn.Module, got {type(term).__name__}")
        self.terms = nn.ModuleDict(dict(terms))
        clash = sorted(set(terms) & self.input_names)
        if clash:
            raise ValueError(f"ClothLoss: term names {clash} are also input names; rename the terms")
        weights = dict(weights or {})
        unknown = sorted(set(weights) - set(terms))
        if unknown:
            raise ValueError(f"ClothLoss: weights for unknown terms {unknown}; terms: {sorted(terms)}")
        self.weights = {name: _weight(name, weights.get(name, 1.0)) for name in terms}
        if reduction not in _REDUCTIONS:
            raise ValueError(f"ClothLoss: reduction must be one of {_REDUCTIONS}, got {reduction!r}")
        self.reduction = reduction

    @property
    def input_names(self) -> frozenset[str]:
        """The keyword inputs the terms take."""
        return frozenset(k for t in self.terms.values() for k in getattr(t, "inputs", ()))

    def energies(self, x: Tensor, **inputs) -> dict[str, Tensor]:
        """Unweighted per-sample values ``{name: (B,) or ()}`` [J] of the terms of non-zero weight, with
        their graphs (not reduced, not detached).  Inputs as :meth:`forward`."""
        own = {k: v for k, v in inputs.items() if k in self.terms}
        shared = {k: v for k, v in inputs.items() if k not in self.terms}
        unknown = sorted(set(shared) - self.input_names)
        if unknown:
            raise ValueError(f"ClothLoss: no term takes the inputs {unknown}; the terms take {sorted(self.input_names)} "
                             f"(or give one term's inputs as {{term name}}={{...}})")
        for name, given in own.items():
            takes = set(getattr(self.terms[name], "inputs", ()))
            if not isinstance(given, Mapping) or set(given) - takes:
                raise ValueError(f"ClothLoss: the inputs of term '{name}' must be a mapping of the names it takes "
                                 f"{sorted(takes)}, got {sorted(given) if isinstance(given, Mapping) else given!r}")
        out = {}
        for name, w in self.weights.items():
            _weight(name, w)  # the weights may have been changed since the construction
        for name, term in self.terms.items():
            if self.weights[name] == 0:
                continue
            kw = {k: shared[k] for k in getattr(term, "inputs", ()) if shared.get(k) is not None}
            kw.update({k: v for k, v in own.get(name, {}).items() if v is not None})
            try:
                out[name] = term(x, **kw)
            except ValueError as e:
                raise ValueError(f"ClothLoss term '{name}': {e}") from None
        return out

    def _reduce(self, v: Tensor) -> Tensor:
        if self.reduction == "mean":
            return v.mean() if v.numel() else v.sum()  # an empty batch: 0, not NaN (class docstring)
        return v.sum() if self.reduction == "sum" else v

    def forward(self, x: Tensor, **inputs) -> tuple[Tensor, dict[str, Tensor]]:
        values = {name: self._reduce(v) for name, v in self.energies(x, **inputs).items()}
        total = None
        for name, v in values.items():
            w = self.weights[name]
            term = v if w == 1 else w * v
            total = term if total is None else total + term
        if total is None:
            total = self._reduce(x.new_zeros(x.shape[:-2]))
        return total, {name: v.detach() for name, v in values.items()}

    def extra_repr(self) -> str:
        return f"weights={self.weights}, reduction={self.reduction!r}"
