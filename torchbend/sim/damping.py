r"""Levenberg-Marquardt damping of a Newton solve, scaled by the lumped masses.

Far from an equilibrium a hanging garment's Hessian is singular or indefinite along soft modes: a
sleeve slides along the arm it hangs on, a skirt turns about its waist, a buckled membrane has
negative curvature.  The undamped Newton step along such a mode is huge (the Levenberg shift of a
singular matrix is tiny), the line search cuts it to a sliver and the solve crawls.  The damped
direction solves

    (H + mu M) p = -g,        M = the lumped mass matrix (free DOFs), mu [1/s^2] >= 0,

which is one Newton step of an implicit-Euler step from rest of size ``h = mu^(-1/2)`` (a proximal
step on the potential): every mode moves at most as far as it falls in time ``h``, soft modes are
bounded and stiff ones are untouched.  ``mu`` follows the agreement of the quadratic model with the
potential (Nielsen's rule): with ``rho`` the actual decrease over the decrease the model
``m(a p) = a g.p + a^2/2 p.H p`` predicts for the accepted step,

* a whole step (``alpha = 1``) with ``0.75 < rho < 1.33``: ``mu <- mu / 10``;
* else ``rho > 1/4``: ``mu <- mu max(1/3, 1 - (2 min(rho, 1) - 1)^3)`` (down by up to 3x), ``nu <- 2``;
* otherwise, or when the line search finds no decrease: ``mu <- max(mu, mu_min) nu``, ``nu <- 2 nu``;

and below ``1e-9`` of the reference, or once the residual is below ``1e-3`` of the force scale (near the
minimum), it is zero: the last iterations are undamped Newton steps (the
damping vanishes at convergence, so the equilibrium and the quadratic convergence are Newton's).  The
reference ``mu_ref`` is the median over free DOFs of ``H_ii / m_i`` at the first iterate [1/s^2]
(dimensionless in the stiffness: the same scale suits ``Y t = 1e2`` and ``1e7`` N/m); the first
direction is undamped (a stiff problem that Newton solves alone is not slowed) and the first
poor step, failed line search or far step sets ``mu = 2 mu_min``, ``mu_min = 1e-6 mu_ref``.  While ``mu > 0`` an exact Hessian
(``projection="exact"``) is replaced by its eigenvalue-magnitude projection (``"abs"``): far from the
minimum the exact model's negative curvature only misleads the step; once ``mu`` is zero the exact
Hessian drives the final iterations.

In a time step the same rule runs, without the far-step rule (a step's moves are ``v dt``, however far: its
inertia bounds them): a step whose Newton iterations all agree with the model is never damped, and one whose
line search keeps cutting the steps is.  Where it matters: after an impact the lagged friction of a pair holds
its whole impact force, and along a sliding pair's direction the friction potential has no curvature (it is
``mu lam |u|``), so the Newton step along it is bounded by the inertia alone; four sheets stacked vertex above
vertex hitting a floor at 3 m/s with friction 0.3 took steps 16-64x too long, and the step after the impact did
not converge in 60 iterations nor in its halves; damped, it converges in 50
(tests/test_contact_friction.py, benchmarks/results/damped_time_steps_amd_zen4_2026-12-07.txt).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ..options import Projection

__all__ = ["Damping"]


class Damping:
    """The damping state of one Newton solve (module docstring).  ``mass``: ``(V,)`` lumped masses [kg]."""


    MIN = 1e-6
    """``mu_min`` (the restart value after ``mu`` reached zero) relative to ``mu_ref``."""
    ZERO = 1e-9
    """Below this fraction of ``mu_ref`` the damping is switched off."""
    MAX = 1e12
    """Above this fraction of ``mu_ref`` a failed line search is final (the direction is gradient descent)."""

    def __init__(self, mass_free: Tensor, enabled: bool = True):
        self.mass, self.enabled = mass_free, enabled
        self.mu, self.nu, self.ref = 0.0, 2.0, math.nan
        self._pMp = 0.0
        self._mass_np = None  # the masses as a NumPy array (directions are NumPy), made on first use

    @property
    def active(self) -> bool:
        """Whether the next direction is damped."""
        return self.enabled and self.mu > 0

    @property
    def pending(self) -> bool:
        """Whether :meth:`start` has yet to set the reference."""
        return self.enabled and math.isnan(self.ref)

    def start(self, diag: Tensor) -> None:
        """Set ``mu_ref`` from the diagonal ``diag (nf,)`` of the Newton matrix at the first iterate."""
        m = self.mass.to(device=diag.device, dtype=diag.dtype)
        ratio = diag / m
        ratio = ratio[torch.isfinite(ratio) & (ratio > 0)]
        self.ref = float(ratio.median()) if ratio.numel() else 0.0
        if not self.ref > 0:
            self.enabled = False

    def matrix_option(self, option: Projection) -> Projection:
        """The projection of the Newton matrix: ``"abs"`` for an exact Hessian while damped."""
        return Projection.ABS if (self.active and option is Projection.NONE) else option

    def shift(self, like: Tensor) -> Tensor:
        """``mu m`` on the free DOFs ``(nf,)``, in the dtype and on the device of ``like``."""
        return self.mu * self.mass.to(device=like.device, dtype=like.dtype)

    def record_direction(self, p) -> None:
        """Remember ``p.M p`` of the direction ``p (nf,)`` on the free DOFs (for the model's prediction)."""
        if self._mass_np is None:
            self._mass_np = self.mass.detach().cpu().double().numpy()
        self._pMp = float((self._mass_np * p * p).sum()) if self.active else 0.0

    def predicted(self, slope: float, alpha: float) -> float:
        """The decrease [J] the undamped quadratic model predicts for the step ``alpha p``; ``slope = g.p``
        and ``p.(H + mu M) p = -g.p`` (the damped system solved exactly)."""
        pHp = -slope - self.mu * self._pMp
        return -(alpha * slope + 0.5 * alpha * alpha * pHp)

    def accepted(self, decrease: float, slope: float, alpha: float) -> None:
        """Update ``mu`` after an accepted step that lowered the potential by ``decrease`` [J]."""
        if not self.enabled:
            return
        pred = self.predicted(slope, alpha)
        rho = decrease / pred if pred > 0 else 0.0
        if alpha == 1.0 and 0.75 < rho < 1.33:
            self.mu *= 0.1  # the model is right about a whole step: nearly Newton's
            self.nu = 2.0
            if self.mu < self.ZERO * self.ref:
                self.mu = 0.0
        elif rho > 0.25:
            self.mu *= max(1.0 / 3.0, 1.0 - (2.0 * min(rho, 1.0) - 1.0) ** 3)
            self.nu = 2.0
            if self.mu < self.ZERO * self.ref:
                self.mu = 0.0
        else:
            self.increase()

    def increase(self) -> bool:
        """Raise ``mu`` after a poor or failed step; False when it is already at its bound."""
        if not self.enabled or self.mu > self.MAX * self.ref:
            return False
        self.mu = max(self.mu, self.MIN * self.ref) * self.nu
        self.nu *= 2.0
        return True

    def off(self) -> None:
        """No damping from now on (the switch to the exact Hessian near a minimum)."""
        self.mu = 0.0
