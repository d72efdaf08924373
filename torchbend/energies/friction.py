r"""Lagged smooth Coulomb friction of Incremental Potential Contact for the colliders of a time step.

Over a time step from ``x_prev`` a vertex in contact with a collider (contact force magnitude ``lam``
[N] and unit normal ``n``, both *lagged*: taken at ``x_prev``) has the tangential displacement
``u = P (x - x_prev)``, ``P = I - n n^T``, and the friction potential

    D = mu lam f0(|u|)  [J],     f0(y) = -y^3 / (3 eps^2) + y^2 / eps + eps / 3   (y < eps),   y   (y >= eps)

with ``eps = eps_v dt`` [m] (``eps_v`` [m/s] the sliding speed below which friction is static-like), whose
force ``-dD/dx = -mu lam f1(|u|) u / |u|`` is Coulomb's ``mu lam`` against the sliding direction once a
vertex slides faster than ``eps_v``, and smoothly less below (``f1 = f0' = 2 y / eps - y^2 / eps^2``).  With
``a = f1(y) / y`` (``2 / eps - y / eps^2`` below ``eps``, ``1 / y`` above) and ``b = (f1'(y) y - f1(y)) / y``
(``-y / eps^2``, ``-1 / y``)::

    grad D = mu lam a(y) P u,         Hess D = mu lam P (a(y) I + b(y) u_hat u_hat^T) P

both continuous, and the Hessian is positive semi-definite (its eigenvalues ``a`` and ``a + b`` are >= 0):
no projection is needed.  Formed without dividing by ``y`` below ``eps`` (no NaN at ``u = 0``).

Along the slip of a sliding pair the exact curvature ``a + b`` is zero (``D`` grows as ``mu lam |u|``), so a Newton
step along it is bounded by the other terms alone (a time step's inertia) and may overshoot across the smoothed
kink at ``u = 0`` where the friction stops the slip (after an impact, where ``lam`` is the whole impact force).
:func:`friction_blocks` with ``slip = s`` keeps the share ``s`` of the curvature ``-b`` that the exact Hessian
removes along ``u_hat`` (``b -> (1 - s) b``, continuous at ``eps``; ``s = 1``: ``mu lam a P``, the curvature of
the quadratic that touches ``f0`` from above at ``|u|``).  A time step solved again after its exact solve
stopped uses it (``StepContext.friction_slip``); the gradient, and so the solution, stay exact.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["friction_energy", "friction_gradient", "friction_blocks"]


def _parts(x: Tensor, x_prev: Tensor, n: Tensor, eps: float):
    dx = x - x_prev
    u = dx - (dx * n).sum(-1, keepdim=True) * n
    y = u.norm(dim=-1)
    slow = y < eps
    y_safe = torch.where(slow, torch.full_like(y, eps), y)  # the fast branch's divisions only
    a = torch.where(slow, 2 / eps - y / (eps * eps), 1 / y_safe)
    return u, y, slow, y_safe, a


def friction_energy(x: Tensor, x_prev: Tensor, n: Tensor, weight: Tensor, eps: float) -> Tensor:
    """``sum_i weight_i f0(|u_i|)`` [J] for positions ``x (V, 3)``, the lagged ``x_prev (V, 3)``, unit normals
    ``n (V, 3)`` and ``weight = mu lam (V,)`` [N] (zero for vertices out of contact); ``eps = eps_v dt`` [m]."""
    _, y, slow, _, _ = _parts(x, x_prev, n, eps)
    f0 = torch.where(slow, -y ** 3 / (3 * eps * eps) + y * y / eps + eps / 3, y)
    return (weight * f0).sum()


def friction_gradient(x: Tensor, x_prev: Tensor, n: Tensor, weight: Tensor, eps: float) -> Tensor:
    """``dD/dx (V, 3)`` [N] (module docstring; ``u`` is already tangential, so ``P u = u``)."""
    u, _, _, _, a = _parts(x, x_prev, n, eps)
    return (weight * a)[:, None] * u


def friction_blocks(x: Tensor, x_prev: Tensor, n: Tensor, weight: Tensor, eps: float, slip: float = 0.0) -> Tensor:
    """Per-vertex Hessian blocks ``(V, 3, 3)`` [N/m] of :func:`friction_energy`, positive semi-definite; ``slip``
    in ``[0, 1]``: the share of the curvature along the slip that the exact Hessian (0) removes, kept (module
    docstring)."""
    u, y, slow, y_safe, a = _parts(x, x_prev, n, eps)
    y_div = torch.where(y > 0, y, torch.ones_like(y))
    u_hat = u / y_div[:, None]  # zero where u = 0
    b = (1.0 - slip) * torch.where(slow, -y / (eps * eps), -1 / y_safe)
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    P = eye - n[:, :, None] * n[:, None, :]
    H = a[:, None, None] * P + b[:, None, None] * u_hat[:, :, None] * u_hat[:, None, :]
    return weight[:, None, None] * H
