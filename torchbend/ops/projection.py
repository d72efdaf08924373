"""PSD projections of per-element Hessian blocks (pure functions on ``(..., n, n)`` blocks)."""
from __future__ import annotations

import torch
from torch import Tensor

from ..options import Projection

__all__ = ["project_blocks", "project_eigenvalues", "BENDING_PROJECTIONS"]

BENDING_PROJECTIONS = frozenset(Projection)
"""Projections of hinge blocks: all of them."""


def project_eigenvalues(l: Tensor, projection: Projection) -> Tensor:
    """Eigenvalues after a ``none`` / ``clamp`` (``max(l, 0)``) / ``abs`` (``|l|``) projection."""
    if projection is Projection.NONE:
        return l
    if projection is Projection.ABS:
        return l.abs()
    if projection is Projection.CLAMP:
        return l.clamp_min(0)
    raise ValueError(f"eigenvalue projection must be 'none', 'clamp' or 'abs', got {projection.value!r}")


def _reduce_translation(Hb: Tensor) -> Tensor:
    """The 9x9 Hessian in relative coordinates ``y_k = x_k - x0`` (k = 1..3): the lower-right block."""
    return Hb[..., 3:, 3:]


def _expand_translation(R: Tensor) -> Tensor:
    """``D^T R D`` with ``y = D x`` (``y_k = x_k - x0``): 9x9 -> 12x12 (translations in the null space)."""
    shape = R.shape[:-2]
    R4 = R.reshape(shape + (3, 3, 3, 3))  # [k, p, l, q]
    col = R4.sum(-4, keepdim=True)  # sum over rows k
    top = -col  # block row 0: -sum_k R_kl
    out_rows = torch.cat((top, R4), -4)  # (4, 3, 3, 3)
    left = -out_rows.sum(-2, keepdim=True)  # column 0: -sum_l
    full = torch.cat((left, out_rows), -2)  # (4, 3, 4, 3)
    return full.reshape(shape + (12, 12))


def project_blocks(Hb: Tensor, projection: Projection, g: Tensor | None = None, d2: Tensor | None = None) -> Tensor:
    """PSD projection of symmetric hinge blocks ``(..., 12, 12)``.

    * ``clamp`` / ``abs``: ``Q max(L, 0) Q^T`` / ``Q |L| Q^T`` from ``torch.linalg.eigh``.
    * ``gauss_newton``: ``max(psi'', 0) g g^T`` (needs ``g`` and ``d2``).
    * ``reduced`` (structured): the hinge energy depends on positions only through the relative
      coordinates ``y_k = x_k - x0`` (translation invariance), so ``H = D^T H_y D`` with the fixed
      map ``D`` and ``H_y`` the lower-right 9x9 block of ``H``.  We clamp the eigenvalues of ``H_y``
      (a 9x9 instead of a 12x12 eigendecomposition: ``(9/12)^3 ~ 0.42`` of the flops) and map back.
      ``D^T P D`` is PSD whenever ``P`` is, keeps the three translations in the null space exactly
      (zero net force of every Newton step), and equals ``H`` whenever ``H`` is already PSD (then
      ``H_y`` is PSD and is left unchanged).  It is not the Frobenius-nearest PSD matrix (``clamp``
      is), since ``D`` is not orthogonal.
    """
    if projection is Projection.GAUSS_NEWTON:
        if g is None or d2 is None:
            raise ValueError("gauss_newton projection needs the angle gradients and psi''")
        gg = d2.clamp_min(0)[..., None] * g
        return gg[..., :, None] * g[..., None, :]
    if projection is Projection.REDUCED:
        return _expand_translation(_eig_project(_reduce_translation(Hb), Projection.CLAMP))
    return _eig_project(Hb, projection)


def _eig_project(M: Tensor, projection: Projection) -> Tensor:
    M = 0.5 * (M + M.transpose(-1, -2))
    if M.numel() == 0:
        return M
    L, Q = torch.linalg.eigh(M)
    L = L.clamp_min(0) if projection is not Projection.ABS else L.abs()
    return (Q * L[..., None, :]) @ Q.transpose(-1, -2)
