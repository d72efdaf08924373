r"""Membrane (stretch) kernels per triangle: kinematics, energy densities and their closed-form
eigensystems (Smith, De Goes & Kim 2019).

Kinematics
----------
Each triangle ``(x0, x1, x2)`` has the deformation gradient ``F = Ds Dm^{-1}`` (3x2), with
``Ds = [x1 - x0, x2 - x0]`` (3x2) and ``Dm`` the rest edge matrix written in the rest triangle's own
plane (2x2).  Equivalently ``F = X D`` with ``X = [x0 x1 x2]`` (3x3) and the constant 3x2 matrix
``D = [-(1,1) W; W]``, ``W = Dm^{-1}``.  ``f = vec(F)`` is the row-major flattening (index ``2a + b``).

A 3x2 ``F`` carries the paper's 2D analysis.  Its thin SVD ``F = U Sigma V^T`` has ``U = [u1 u2]``
(3x2, orthonormal columns), ``Sigma = diag(s1, s2)`` with ``s1 >= s2 >= 0`` and ``V`` a 2x2 rotation;
``n = u1 x u2`` is the deformed unit normal.  The stretch tensor is ``S = V Sigma V^T`` (2x2) and
the invariants are ``I1 = tr S = s1 + s2``, ``I2 = |F|^2``, ``I3 = det S = s1 s2`` (the area ratio).
An isotropic energy ``Psi(s1, s2)`` has, in the 6-dim space of ``f``, the orthonormal eigenvectors

    scaling   d_{1,2} = U diag(a_{1,2}) V^T       a_{1,2}: eigenvectors of the 2x2 Hessian of Psi in (s1, s2)
    twist     t = (u2 v1^T - u1 v2^T)/sqrt(2)      lambda = (psi1 + psi2)/(s1 + s2)      (paper eq. 22a)
    flip      l = (u2 v1^T + u1 v2^T)/sqrt(2)      lambda = (psi1 - psi2)/(s1 - s2)      (paper eq. 22b)
    normal    o_i = n v_i^T  (i = 1, 2)            lambda = psi_i / s_i

with ``psi_i = dPsi/ds_i``.  The first four are the paper's 2D eigensystem embedded by ``U``; the
two out-of-plane modes are new for a 3x2 ``F``: moving ``F`` along ``n b^T`` changes ``F^T F`` only
at second order (``F^T n = 0``), by ``eps^2 b b^T``, so their curvature is ``2 dPsi/dC : b b^T``
(``C = F^T F``) and ``dPsi/dC = V diag(psi_i/(2 s_i)) V^T``.  Every eigenvalue is written in a
division-free form for the models below (no ``s1 - s2`` in a denominator), so equal stretches
are not special.

The position-space element Hessian is ``B^T (d^2Psi/df^2) B`` with ``B = df/dx`` (6x9, null space:
the translations).  The closed-form eigensystem is that of ``d^2Psi/df^2``: projecting it
(``clamp``/``abs`` on the six eigenvalues) and mapping back with ``B`` gives PSD element Hessians
without any numerical eigendecomposition.  (A 9x9 position-space eigensystem has no closed form
unless ``B`` is an isometry, i.e. for special rest triangles; projecting in ``f`` is what the
paper's projected Newton does.)

Models (energy of one triangle, rest area ``A``, thickness ``t``)
-----------------------------------------------------------------
``mu = Y/(2(1+nu))``, ``lam = Y nu/(1 - nu^2)`` (plane stress):

* ``stvk``: ``A t (mu |G|_F^2 + lam/2 tr(G)^2)``, ``G = (F^T F - I)/2``;
* ``arap``: ``A t mu |F - R|^2 = A t mu sum_i (s_i - 1)^2`` (paper sec. 5.1);
* ``symmetric_dirichlet``: ``A t mu (|F|^2 + |F^+|^2 - 4) = A t mu sum_i (s_i^2 + s_i^-2 - 2)`` (sec. 5.2);
* ``neohookean``: ``A t (mu/2 (I2 - 2) - mu log J + lam/2 log(J)^2)``, ``J = s1 s2`` (a barrier at
  ``J -> 0``; a collapsed triangle is an error).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .._checks import is_traced
from ..options import Option

__all__ = ["MembraneModel", "rest_shape_matrices", "deformation_gradient", "eigensystem", "energy_density",
           "check_collapsed"]

_SQRT1_2 = 1.0 / math.sqrt(2.0)


class MembraneModel(Option):
    """Isotropic membrane energy density (see the module docstring)."""

    __label__ = "membrane model"

    STVK = "stvk"
    ARAP = "arap"
    SYMMETRIC_DIRICHLET = "symmetric_dirichlet"
    NEOHOOKEAN = "neohookean"


# ------------------------------------------------------------------------------ kinematics
def rest_shape_matrices(rest: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """``D: (T, 3, 2)`` with ``F = X D`` and rest areas ``(T,)`` [m^2]; ValueError on zero-area faces."""
    X = rest.detach().to(torch.float64)
    p0, p1, p2 = X[faces[:, 0]], X[faces[:, 1]], X[faces[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    N = torch.linalg.cross(e1, e2, dim=-1)
    area2 = N.norm(dim=-1)
    longest2 = torch.stack(((e1 * e1).sum(-1), (e2 * e2).sum(-1), ((p2 - p1) ** 2).sum(-1)), -1).amax(-1)
    bad = torch.nonzero(~(area2 > torch.finfo(rest.dtype).eps * longest2)).reshape(-1)
    if bad.numel():
        raise ValueError(
            f"rest shape has zero-area (degenerate) triangles: faces {bad[:8].tolist()}"
            + (f" ... ({bad.numel()} in all)" if bad.numel() > 8 else "")
            + "; the membrane rest frame (Dm) is singular there"
        )
    l1 = e1.norm(dim=-1)
    t1 = e1 / l1[:, None]
    t2 = torch.linalg.cross(N / area2[:, None], t1, dim=-1)
    # Dm = [[|e1|, e2.t1], [0, e2.t2]] in the rest triangle's own frame; W = Dm^{-1}
    a, b, d = l1, (e2 * t1).sum(-1), (e2 * t2).sum(-1)
    W = torch.zeros(len(faces), 2, 2, dtype=torch.float64)
    W[:, 0, 0] = 1.0 / a
    W[:, 0, 1] = -b / (a * d)
    W[:, 1, 1] = 1.0 / d
    D = torch.cat((-W.sum(1, keepdim=True), W), 1)  # (T, 3, 2): rows for x0, x1, x2
    return D.to(rest.dtype), (0.5 * area2).to(rest.dtype)


def deformation_gradient(x: Tensor, faces: Tensor, D: Tensor) -> Tensor:
    """``F: (..., T, 3, 2)`` of positions ``x: (..., V, 3)``."""
    X = x[..., faces, :]  # (..., T, 3 vertices, 3 axes)
    return torch.einsum("...tka,tkb->...tab", X, D)


def _thin_svd(F: Tensor):
    """Closed-form thin SVD of ``F: (..., 3, 2)``: ``U (..., 3, 2)``, ``s (..., 2)``, ``V (..., 2, 2)``, ``n (..., 3)``.

    ``V`` is a rotation, ``s1 >= s2 >= 0``, ``n = u1 x u2``; ``s2 = |f0 x f1| / s1`` (accurate for
    slivers).  Degenerate ``F`` (rank < 2) gets an arbitrary orthonormal completion."""
    f0, f1 = F[..., 0], F[..., 1]
    a, b, c = (f0 * f0).sum(-1), (f0 * f1).sum(-1), (f1 * f1).sum(-1)
    cr = torch.linalg.cross(f0, f1, dim=-1)
    J = cr.norm(dim=-1)  # s1 s2
    half = 0.5 * (a + c)
    disc = torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    s1 = torch.sqrt(half + disc)
    tiny = torch.finfo(F.dtype).tiny
    ok1 = s1 > tiny
    s2 = torch.where(ok1, J / torch.where(ok1, s1, torch.ones_like(s1)), torch.zeros_like(s1))
    phi = 0.5 * torch.atan2(2.0 * b, a - c)
    cp, sp = torch.cos(phi), torch.sin(phi)
    V = torch.stack((torch.stack((cp, -sp), -1), torch.stack((sp, cp), -1)), -2)  # columns v1, v2
    u1 = f0 * cp[..., None] + f1 * sp[..., None]  # F v1 = s1 u1
    u1 = torch.where(ok1[..., None], u1 / torch.where(ok1, s1, torch.ones_like(s1))[..., None], _any_unit(F))
    okJ = J > torch.finfo(F.dtype).eps * (a + c)
    n = torch.where(okJ[..., None], cr / torch.where(okJ, J, torch.ones_like(J))[..., None], _perp(u1))
    u2 = torch.linalg.cross(n, u1, dim=-1)
    U = torch.stack((u1, u2), -1)
    return U, torch.stack((s1, s2), -1), V, n


def _any_unit(F: Tensor) -> Tensor:
    e = torch.zeros(F.shape[:-1], dtype=F.dtype, device=F.device)
    e[..., 0] = 1.0
    return e


def _perp(u: Tensor) -> Tensor:
    """A unit vector perpendicular to the unit vector ``u``."""
    alt = torch.zeros_like(u)
    use_y = u[..., 0].abs() > 0.9
    alt[..., 1] = use_y.to(u.dtype)
    alt[..., 0] = (~use_y).to(u.dtype)
    p = torch.linalg.cross(u, alt, dim=-1)
    return p / p.norm(dim=-1, keepdim=True)


# ------------------------------------------------------------------------------ energies in singular values
def _sigma_terms(model: MembraneModel, s: Tensor, mu: Tensor, lam: Tensor):
    """Energy density and its closed-form derivative data in ``(s1, s2)``.

    Returns ``psi``, ``(psi1, psi2)``, ``(h11, h12, h22)`` (Hessian in s), and the eigenvalues
    ``(twist, flip, out1, out2)``, all written without ``1/(s1 - s2)``."""
    s1, s2 = s[..., 0], s[..., 1]
    if model is MembraneModel.STVK:
        q1, q2 = s1 * s1 - 1.0, s2 * s2 - 1.0
        S = 0.5 * (q1 + q2)  # tr G
        psi = mu * 0.25 * (q1 * q1 + q2 * q2) + 0.5 * lam * S * S
        p1 = mu * q1 * s1 + lam * S * s1
        p2 = mu * q2 * s2 + lam * S * s2
        h11 = mu * (3 * s1 * s1 - 1) + lam * (S + s1 * s1)
        h22 = mu * (3 * s2 * s2 - 1) + lam * (S + s2 * s2)
        h12 = lam * s1 * s2
        flip = mu * (s1 * s1 + s1 * s2 + s2 * s2 - 1) + lam * S
        twist = mu * (s1 * s1 - s1 * s2 + s2 * s2 - 1) + lam * S
        o1 = mu * q1 + lam * S
        o2 = mu * q2 + lam * S
    elif model is MembraneModel.ARAP:
        psi = mu * ((s1 - 1) ** 2 + (s2 - 1) ** 2)
        p1, p2 = 2 * mu * (s1 - 1), 2 * mu * (s2 - 1)
        h11 = h22 = 2 * mu * torch.ones_like(s1)
        h12 = torch.zeros_like(s1)
        flip = 2 * mu * torch.ones_like(s1)
        twist = 2 * mu - 4 * mu / (s1 + s2)
        o1, o2 = 2 * mu - 2 * mu / s1, 2 * mu - 2 * mu / s2
    elif model is MembraneModel.SYMMETRIC_DIRICHLET:
        i1, i2 = 1.0 / s1, 1.0 / s2
        psi = mu * (s1 * s1 + i1 * i1 + s2 * s2 + i2 * i2 - 4.0)
        p1, p2 = 2 * mu * (s1 - i1**3), 2 * mu * (s2 - i2**3)
        h11, h22 = 2 * mu * (1 + 3 * i1**4), 2 * mu * (1 + 3 * i2**4)
        h12 = torch.zeros_like(s1)
        j3 = (i1 * i2) ** 3
        flip = 2 * mu * (1 + (s1 * s1 + s1 * s2 + s2 * s2) * j3)
        twist = 2 * mu * (1 - (s1 * s1 - s1 * s2 + s2 * s2) * j3)
        o1, o2 = 2 * mu * (1 - i1**4), 2 * mu * (1 - i2**4)
    else:  # NEOHOOKEAN
        J = s1 * s2
        lj = torch.log(J)
        psi = 0.5 * mu * (s1 * s1 + s2 * s2 - 2.0) - mu * lj + 0.5 * lam * lj * lj
        i1, i2 = 1.0 / s1, 1.0 / s2
        p1 = mu * s1 + (lam * lj - mu) * i1
        p2 = mu * s2 + (lam * lj - mu) * i2
        h11 = mu + (mu + lam * (1 - lj)) * i1 * i1
        h22 = mu + (mu + lam * (1 - lj)) * i2 * i2
        h12 = lam * i1 * i2
        flip = mu + (mu - lam * lj) * i1 * i2
        twist = mu + (lam * lj - mu) * i1 * i2
        o1 = mu + (lam * lj - mu) * i1 * i1
        o2 = mu + (lam * lj - mu) * i2 * i2
    return psi, (p1, p2), (h11, h12, h22), (twist, flip, o1, o2)


def _eig2(h11: Tensor, h12: Tensor, h22: Tensor):
    """Closed-form eigensystem of symmetric 2x2 matrices: ``(l1, l2)`` and unit ``(a1, a2)``."""
    mid = 0.5 * (h11 + h22)
    rad = torch.sqrt((0.5 * (h11 - h22)) ** 2 + h12 * h12)
    beta = 0.5 * torch.atan2(2.0 * h12, h11 - h22)
    cb, sb = torch.cos(beta), torch.sin(beta)
    return (mid + rad, mid - rad), (torch.stack((cb, sb), -1), torch.stack((-sb, cb), -1))


def eigensystem(model: MembraneModel, F: Tensor, mu: Tensor, lam: Tensor):
    """Closed-form eigensystem of ``d^2Psi/df^2`` per element: ``(l (..., 6), Q (..., 6, 6))``.

    Columns of ``Q`` are the eigenvectors (row-major ``vec`` of 3x2 matrices): scaling 1, scaling 2,
    twist, flip, normal 1, normal 2.  Also returns ``psi`` and ``P = dPsi/dF (..., 3, 2)``."""
    U, s, V, n = _thin_svd(F)
    psi, (p1, p2), (h11, h12, h22), (tw, fl, o1, o2) = _sigma_terms(model, s, mu, lam)
    (l1, l2), (a1, a2) = _eig2(h11, h12, h22)
    u1, u2 = U[..., 0], U[..., 1]
    v1, v2 = V[..., 0], V[..., 1]

    def outer(u, v):  # (..., 3) x (..., 2) -> (..., 6) row-major vec
        return (u[..., :, None] * v[..., None, :]).flatten(-2)

    o11, o22 = outer(u1, v1), outer(u2, v2)
    o21, o12 = outer(u2, v1), outer(u1, v2)
    Q = torch.stack(
        (
            a1[..., 0:1] * o11 + a1[..., 1:2] * o22,
            a2[..., 0:1] * o11 + a2[..., 1:2] * o22,
            _SQRT1_2 * (o21 - o12),
            _SQRT1_2 * (o21 + o12),
            outer(n, v1),
            outer(n, v2),
        ),
        -1,
    )
    lam_all = torch.stack((l1, l2, tw, fl, o1, o2), -1)
    P = p1[..., None, None] * (u1[..., :, None] * v1[..., None, :]) + p2[..., None, None] * (
        u2[..., :, None] * v2[..., None, :]
    )
    return lam_all, Q, psi, P


def check_collapsed(model: MembraneModel, F: Tensor) -> None:
    if model is not MembraneModel.NEOHOOKEAN or is_traced(F):
        return
    J = torch.linalg.cross(F[..., 0], F[..., 1], dim=-1).norm(dim=-1)
    bad = J.detach() <= 0
    if bool(bad.any()):
        idx = torch.nonzero(bad.reshape(-1, J.shape[-1]).any(0)).reshape(-1)[:8].tolist()
        raise ValueError(f"triangles {idx} have collapsed (J = 0): the neohookean energy is infinite there")


def energy_density(model: MembraneModel, F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """``Psi(F)`` per element ``(..., T)`` (energy per unit rest area and thickness)."""
    _, s, _, _ = _thin_svd(F)
    return _sigma_terms(model, s, mu, lam)[0]
