"""Bending models ``phi(theta)`` and the per-hinge scalar energy ``psi`` with its derivatives.

Per hinge (Tamstorf & Grinspun 2013 eq. (8) and the viscous term of sec. 5; ``theta`` as
:func:`torchbend.hinge_angles` defines it, on the stencils of :mod:`torchbend.mesh.topology`)::

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

import math

import torch
from torch import Tensor

from .._checks import is_traced
from ..options import Option

__all__ = ["BendingModel", "phi", "phi_difference", "half_angle_sincos", "check_fold", "psi_derivatives", "psi_theta_derivatives", "contract_hessian",
           "THETA", "K", "REST", "C", "PREV"]


class BendingModel(Option):
    """The curvature measure ``phi(theta)`` (:class:`BendingModel`)."""

    __label__ = "bending model"

    QUADRATIC = "quadratic"  # phi = theta                (Discrete Shells, Grinspun et al. 2003)
    TAN = "tan"  # phi = 2 tan(theta/2)     (Tamstorf-Grinspun 2013 sec. 5; unbounded at +-pi)
    SIN = "sin"  # phi = 2 sin(theta/2)     (Bergou/Wardetzky-style)


def phi(model: BendingModel, theta: Tensor, order: int = 2) -> tuple[Tensor, ...]:
    """``(phi, phi', phi'')`` (the first ``order + 1`` of them) at ``theta``, elementwise."""
    if model is BendingModel.QUADRATIC:
        out = (theta, torch.ones_like(theta), torch.zeros_like(theta))
    elif model is BendingModel.TAN:
        sh, ch = half_angle_sincos(theta)
        t = sh / ch
        sec2 = 1.0 + t * t
        out = (2.0 * t, sec2, sec2 * t)
    elif model is BendingModel.SIN:
        s, c = torch.sin(0.5 * theta), torch.cos(0.5 * theta)
        out = (2.0 * s, c, -0.5 * s)
    else:  # pragma: no cover - BendingModel.parse guards this
        raise ValueError(f"unknown bending model {model!r}")
    return out[: order + 1]


def half_angle_sincos(theta: Tensor) -> tuple[Tensor, Tensor]:
    """``(sin(theta/2), cos(theta/2))`` to a few ulps for every ``theta`` in [-pi, pi], near +-pi too.

    ``cos(theta/2)`` vanishes at +-pi, where ``theta/2`` rounded to the dtype is off by up to an ulp of
    pi/2 (and an argument reduction by pi/2 may keep too few digits of pi): relative to the tiny cosine
    that is a large error.  For ``|theta| > pi/2`` both come from the complement
    ``w = (pi - |theta|)/2`` instead, formed exactly (``pi_hi - |theta|`` is exact by Sterbenz, then the
    tail ``pi_lo``): ``sin(theta/2) = sign(theta) cos(w)``, ``cos(theta/2) = sin(w)``.  One sine and one
    cosine, of an argument in [-pi/4, pi/4] (no argument reduction)."""
    hi, lo = _PI_SPLIT[theta.dtype] if theta.dtype in _PI_SPLIT else _PI_SPLIT[torch.float64]
    a = theta.abs()
    big = a > 0.5 * _PI
    w = 0.5 * ((hi - a) + lo)
    arg = torch.where(big, w, 0.5 * theta)
    sn, cs = torch.sin(arg), torch.cos(arg)
    return torch.where(big, torch.copysign(cs, theta), sn), torch.where(big, sn, cs)


# parameter slots of psi
THETA, K, REST, C, PREV = range(5)

_PI = math.pi
_TWO_PI = 2.0 * math.pi
# pi = hi + lo per dtype (hi = pi rounded to the dtype, lo = the rest rounded): half_angle_sincos
_PI_SPLIT = {
    torch.float64: (math.pi, 1.2246467991473532e-16),
    torch.float32: (3.1415927410125732, -8.742278000372485e-08),
    torch.float16: (3.140625, 9.676535897932385e-04),
    torch.bfloat16: (3.140625, 9.676535897932385e-04),
}


def phi_difference(model: BendingModel, theta: Tensor, ref) -> tuple[Tensor, Tensor, Tensor]:
    """``(phi(theta') - phi(ref), phi'(theta'), phi''(theta'))`` on the branch nearest ``ref`` (continuous
    through +-pi for the quadratic and sin models).

    ``theta' = ref + wrap(theta - ref)`` (``wrap`` into (-pi, pi]) for ``quadratic`` and ``sin``, so that
    their energies are continuous where a hinge turns through +-pi; ``theta' = theta`` for ``tan``
    (its barrier at +-pi is the point).  The difference is formed without cancellation:
    ``2 tan(t/2) - 2 tan(r/2) = 2 sin((t - r)/2) / (cos(t/2) cos(r/2))`` where ``t`` and ``r`` have the same
    sign (``t - r`` is then exact or correctly rounded with ``|t - r| < pi``), and
    ``2 (sin(t/2) cos(r/2) - sin(r/2) cos(t/2)) / (cos(t/2) cos(r/2))`` where their signs differ (two terms
    of one sign: no cancellation; there ``sin((t - r)/2)`` would be the sine of an angle near pi formed
    from the rounded ``t - r``, which near +-pi on opposite sides loses everything); the half-angle sines
    and cosines come from :func:`half_angle_sincos`, accurate near +-pi.  Likewise
    ``2 sin(t/2) - 2 sin(r/2) = 4 cos((t + r)/4) sin((t - r)/4)``, so ``psi`` and ``psi'`` keep their
    relative accuracy when ``theta`` is close to the reference."""
    delta = theta - ref
    if model is BendingModel.TAN:
        ref_t = torch.as_tensor(ref, dtype=theta.dtype, device=theta.device)
        sh, ch = half_angle_sincos(theta)
        sr, cr = half_angle_sincos(ref_t)
        opposite = (theta < 0) != (ref_t < 0)
        num = torch.where(opposite, sh * cr - sr * ch, torch.sin(0.5 * delta))
        t = sh / ch
        sec2 = 1.0 + t * t
        return 2.0 * num / (ch * cr), sec2, sec2 * t
    turns = torch.ceil((delta - _PI) / _TWO_PI)  # theta' = theta - 2 pi turns; 0 unless |theta - ref| > pi
    wrapped = turns != 0
    dw = torch.where(wrapped, delta - _TWO_PI * turns, delta)
    if model is BendingModel.QUADRATIC:
        return dw, torch.ones_like(dw), torch.zeros_like(dw)
    if model is BendingModel.SIN:
        h = 0.5 * theta
        sign = 1.0 - 2.0 * torch.remainder(turns, 2.0)  # sin/cos(theta'/2) = (-1)^turns sin/cos(theta/2)
        q = 0.25 * dw
        return 4.0 * torch.cos(0.5 * ref + q) * torch.sin(q), sign * torch.cos(h), -0.5 * sign * torch.sin(h)
    raise ValueError(f"unknown bending model {model!r}")  # pragma: no cover - BendingModel.parse guards this


def check_fold(model: BendingModel, theta: Tensor) -> None:
    """``ValueError`` where a ``tan`` hinge has folded through (``|theta| >= pi`` in theta's dtype): its energy
    is unbounded there by design, so every entry point refuses rather than return a huge or sign-flipped number.
    Skipped while tracing (``torch.compile``, ``vmap``): the check needs the values."""
    if model is not BendingModel.TAN or theta.numel() == 0 or is_traced(theta):
        return
    folded = theta.detach().abs() >= torch.tensor(_PI, dtype=theta.dtype)
    if bool(folded.any()):
        idx = torch.nonzero(folded.reshape(-1, theta.shape[-1]).any(0)).reshape(-1)
        raise ValueError(
            f"hinges {idx[:8].tolist()}" + (f" ... ({idx.numel()} in all)" if idx.numel() > 8 else "")
            + " have folded through (|theta| = pi): the 'tan' bending energy is unbounded there by design "
            "(it forbids interpenetration); use smaller steps or the 'quadratic'/'sin' model"
        )


def _phi_at_reference(model: BendingModel, t, derivatives: bool) -> tuple:
    """``(phi', phi'')`` at a reference angle (``None`` without ``derivatives``): the parameter
    derivatives need them."""
    if derivatives:
        return phi(model, t)[1:]
    return None, None


def psi_derivatives(model: BendingModel, theta, k, rest, a, c=None, prev=None, *, hessian: bool,
                    params: bool = True):
    """Value, gradient and (optionally) Hessian of ``psi`` in ``p = (theta, k, rest, c, prev)``.

    The one implementation of ``psi`` and its derivatives (every eager path uses it; the compiled
    kernels transcribe it).  Each term is evaluated on the branch of its reference angle
    (:func:`phi_difference`), and a folded ``tan`` hinge is an error (:func:`check_fold`).  Returns
    ``(psi, grad, hess)``: ``grad`` a list of 5 tensors (``None`` for absent slots), ``hess`` a dict
    ``{(i, j): tensor}`` of the nonzero entries with ``i <= j`` (or ``None``).  With ``params=False``
    only the ``theta`` entries are formed (``psi'``, ``psi''``: what the position Hessians need)."""
    check_fold(model, theta)
    d1, f1, f2 = phi_difference(model, theta, rest)
    r1, r2 = _phi_at_reference(model, rest, params)
    two_a = 2.0 * a
    kd = k * d1
    psi = a * kd * d1
    grad: list = [None] * 5
    hess: dict = {}
    s, h2 = kd, k * f1 * f1 + kd * f2
    if c is not None:  # viscous term, on the branch of theta_prev
        d2, g1, g2 = phi_difference(model, theta, prev)
        p1, p2 = _phi_at_reference(model, prev, params)
        cd = c * d2
        psi = psi + a * cd * d2
        s, h2 = s + cd, h2 + c * g1 * g1 + cd * g2
        if params:
            grad[C] = a * d2 * d2
            grad[PREV] = -2.0 * a * cd * p1
        if params and hessian:
            hess[(THETA, C)] = two_a * d2 * g1
            hess[(THETA, PREV)] = -two_a * c * g1 * p1
            hess[(C, PREV)] = -two_a * d2 * p1
            hess[(PREV, PREV)] = two_a * c * (p1 * p1 - d2 * p2)
        grad[THETA] = two_a * (kd * f1 + cd * g1)
    else:
        grad[THETA] = two_a * (kd * f1)
    if params:
        grad[K] = a * d1 * d1
        grad[REST] = -two_a * kd * r1
    if not hessian:
        return psi, grad, None
    hess[(THETA, THETA)] = two_a * h2
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
