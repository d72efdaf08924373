"""Armijo backtracking along a descent direction, with a fallback for round-off-level decreases."""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import torch
from torch import Tensor

__all__ = ["LineSearchResult", "armijo_backtracking"]


class LineSearchResult(NamedTuple):
    """An accepted step: positions ``x (V, 3)`` [m], potential ``energy`` [J] and its ``terms``."""

    x: Tensor
    energy: float
    terms: dict
    alpha: float


def armijo_backtracking(potential: Callable[[Tensor], tuple[float, dict]], x: Tensor, step: Tensor, energy: float,
                        terms: dict, slope: float, residual_decreases: Callable[[Tensor], bool], *,
                        max_steps: int = 30, c: float = 1e-4, shrink: float = 0.5,
                        alpha_max: float = 1.0) -> LineSearchResult | None:
    """Backtrack ``alpha = alpha_max, alpha_max/2, ...`` along ``step (V, 3)`` [m] from ``x (V, 3)`` [m].

    ``potential(y) -> (Phi [J], per-term energies)``; ``energy``, ``terms``: its value at ``x``;
    ``slope``: the directional derivative ``g . step`` [J] (< 0).  A trial ``y = x + alpha step`` is
    accepted when it satisfies the Armijo condition ``Phi(y) <= Phi(x) + c alpha slope``, or, once both
    the change of ``Phi`` and the predicted decrease are below the round-off of ``Phi`` (64 eps times
    the sum of the magnitudes of its terms), when ``residual_decreases(y)``.  A ``ValueError`` raised
    by ``potential`` (e.g. a hinge folded through, for the tan model) counts as an infinite potential.
    ``alpha_max`` in ``(0, 1]``: the largest admissible step fraction, e.g. the continuous collision
    bound :meth:`~torchbend.sim.model.ClothModel.max_step` (no vertex tunnels through a collider).
    Returns the accepted step, or ``None`` after ``max_steps`` rejections."""
    if not 0 < alpha_max <= 1:
        raise ValueError(f"alpha_max must lie in (0, 1], got {alpha_max!r}")
    noise = 64 * torch.finfo(x.dtype).eps * max(abs(energy), sum(abs(v) for v in terms.values()))
    alpha = float(alpha_max)
    for _ in range(max_steps):
        y = x + alpha * step
        try:
            e_new, terms_new = potential(y)
        except ValueError:
            e_new, terms_new = math.inf, {}
        if math.isfinite(e_new):
            if e_new <= energy + c * alpha * slope:
                return LineSearchResult(y, e_new, terms_new, alpha)
            # below this the potential's round-off hides the decrease: fall back to the residual
            if e_new - energy <= noise and -alpha * slope <= noise and residual_decreases(y):
                return LineSearchResult(y, e_new, terms_new, alpha)
        alpha *= shrink
    return None
