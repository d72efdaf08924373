"""Bending models ``phi(theta)`` and the per-hinge scalar energy ``psi`` with its derivatives.

Per hinge (SPEC sec. 1, Tamstorf & Grinspun 2013 eq. (8) and the viscous term of sec. 5)::

    psi = a * [ k (phi(theta) - phi(theta_rest))^2 + c (phi(theta) - phi(theta_prev))^2 ]

with ``a = 3|e0_rest|^2 / (A_A + A_B)`` (rest shape), ``k`` the stiffness [N m] and
``c = k_d / dt`` the viscous (Rayleigh) coefficient; the ``c`` term is present only when damping is
asked for.  All geometric work (``grad theta``, ``Hess theta``) is shared: the models and the
damping only change the scalars computed here.

``psi`` is treated as a function of the five scalars ``p = (theta, k, theta_rest, c, theta_prev)``;
:func:`psi_derivatives` returns its gradient and Hessian in ``p`` in closed form, which is all the
autograd Functions need for the first and second derivatives with respect to positions,
stiffness and rest angles.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..options import Option

__all__ = ["BendingModel", "phi", "psi_derivatives", "psi_theta_derivatives", "contract_hessian",
           "THETA", "K", "REST", "C", "PREV"]


class BendingModel(Option):
    """The curvature measure ``phi(theta)`` (SPEC sec. 1)."""

    __label__ = "bending model"

    QUADRATIC = "quadratic"  # phi = theta                (Discrete Shells, Grinspun et al. 2003)
    TAN = "tan"  # phi = 2 tan(theta/2)     (Tamstorf-Grinspun 2013 sec. 5; unbounded at +-pi)
    SIN = "sin"  # phi = 2 sin(theta/2)     (Bergou/Wardetzky-style)


def phi(model: BendingModel, theta: Tensor, order: int = 2) -> tuple[Tensor, ...]:
    """``(phi, phi', phi'')`` (the first ``order + 1`` of them) at ``theta``, elementwise."""
    if model is BendingModel.QUADRATIC:
        out = (theta, torch.ones_like(theta), torch.zeros_like(theta))
    elif model is BendingModel.TAN:
        t = torch.tan(0.5 * theta)
        sec2 = 1.0 + t * t
        out = (2.0 * t, sec2, sec2 * t)
    elif model is BendingModel.SIN:
        s, c = torch.sin(0.5 * theta), torch.cos(0.5 * theta)
        out = (2.0 * s, c, -0.5 * s)
    else:  # pragma: no cover - BendingModel.parse guards this
        raise ValueError(f"unknown bending model {model!r}")
    return out[: order + 1]


# parameter slots of psi
THETA, K, REST, C, PREV = range(5)


def _phi_at_reference(model: BendingModel, t, derivatives: bool) -> tuple:
    """``(phi, phi', phi'')`` at a reference angle; the derivatives (``None`` without ``derivatives``)
    are needed only for the parameter derivatives."""
    if derivatives:
        return phi(model, t)
    return phi(model, t, order=0)[0], None, None


def psi_derivatives(model: BendingModel, theta, k, rest, a, c=None, prev=None, *, hessian: bool,
                    params: bool = True):
    """Value, gradient and (optionally) Hessian of ``psi`` in ``p = (theta, k, rest, c, prev)``.

    The one implementation of ``psi`` and its derivatives (every eager path uses it; the compiled
    kernels transcribe it).  Returns ``(psi, grad, hess)``: ``grad`` a list of 5 tensors (``None``
    for absent slots), ``hess`` a dict ``{(i, j): tensor}`` of the nonzero entries with ``i <= j``
    (or ``None``).  With ``params=False`` only the ``theta`` entries are formed (``psi'``, ``psi''``:
    what the position Hessians need)."""
    f, f1, f2 = phi(model, theta)
    r, r1, r2 = _phi_at_reference(model, rest, params)
    two_a = 2.0 * a
    d1 = f - r
    kd = k * d1
    psi = a * kd * d1
    grad: list = [None] * 5
    hess: dict = {}
    s, kc = kd, k
    if c is not None:  # viscous term
        p, p1, p2 = _phi_at_reference(model, prev, params)
        d2 = f - p
        cd = c * d2
        psi = psi + a * cd * d2
        s, kc = kd + cd, k + c
        if params:
            grad[C] = a * d2 * d2
            grad[PREV] = -2.0 * a * cd * p1
        if params and hessian:
            hess[(THETA, C)] = two_a * d2 * f1
            hess[(THETA, PREV)] = -two_a * c * f1 * p1
            hess[(C, PREV)] = -two_a * d2 * p1
            hess[(PREV, PREV)] = two_a * c * (p1 * p1 - d2 * p2)
    if params:
        grad[K] = a * d1 * d1
        grad[REST] = -two_a * kd * r1
    grad[THETA] = two_a * s * f1
    if not hessian:
        return psi, grad, None
    hess[(THETA, THETA)] = two_a * (kc * f1 * f1 + s * f2)
    if params:
        hess[(THETA, K)] = two_a * d1 * f1
        hess[(THETA, REST)] = -two_a * k * f1 * r1
        hess[(K, REST)] = -two_a * d1 * r1
        hess[(REST, REST)] = two_a * k * (r1 * r1 - d1 * r2)
    return psi, grad, hess


def contract_hessian(hess: dict, vec: list) -> list:
    """``z_i = sum_j hess_ij vec_j`` for a symmetric ``hess`` stored as ``{(i<=j): value}``.

    ``vec`` entries may be ``None`` (zero).  Returns a list of 5 (``None`` where zero).
    """
    z: list = [None] * 5
    for (i, j), h in hess.items():
        for a, b in ((i, j), (j, i)) if i != j else ((i, j),):
            if vec[b] is None:
                continue
            term = h * vec[b]
            z[a] = term if z[a] is None else z[a] + term
    return z


def psi_theta_derivatives(model: BendingModel, theta, a, k, rest, c=None, prev=None) -> tuple[Tensor, Tensor]:
    """``(psi', psi'')`` in ``theta`` (the scalars of every position Hessian; see :func:`psi_derivatives`)."""
    _, grad, hess = psi_derivatives(model, theta, k, rest, a, c, prev, hessian=True, params=False)
    assert hess is not None
    return grad[THETA], hess[(THETA, THETA)]
