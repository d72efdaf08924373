r"""Membrane (stretch) kernels per triangle: kinematics, energy densities and their closed-form
eigensystems (Smith, De Goes & Kim 2019).

Kinematics
----------
Each triangle ``(x0, x1, x2)`` has the deformation gradient ``F = Ds W`` (3x2), with the edge
vectors ``Ds = [x1 - x0, x2 - x0]`` (3x2) and ``W = Dm^{-1}``, ``Dm`` the rest edge matrix written in
the rest triangle's own plane (2x2, upper triangular).  The buffer ``D = [-(1,1) W; W]`` (3x2) keeps
``F = X D`` (``X = [x0 x1 x2]``) as a statement, but ``F`` is always computed from edge vectors
(relative coordinates: the result does not depend on where the mesh is).  ``f = vec(F)`` is the
row-major flattening (index ``2a + b``).  ``N = f0 x f1 = det(W) (e1 x e2)`` is computed from the edges
too, so it is exactly zero for a collapsed triangle.

A 3x2 ``F`` carries the paper's 2D analysis.  Its thin SVD ``F = U Sigma V^T`` has ``U = [u1 u2]``
(3x2, orthonormal columns), ``Sigma = diag(s1, s2)`` with ``s1 >= s2 >= 0`` and ``V`` a 2x2 rotation;
``n = u1 x u2`` is the deformed unit normal.  ``s2 = 0`` exactly when the triangle has collapsed
(zero deformed area: collinear vertices, a collapsed edge, or all three at one point).  A 3x2 ``F``
cannot invert: flipping a triangle over is a rotation in 3D, so ``J = s1 s2 >= 0`` always (there are
no "inverted" membrane elements).  The invariants are ``I1 = s1 + s2``, ``I2 = |F|^2``,
``I3 = s1 s2 = J`` (the area ratio).  An isotropic energy ``Psi(s1, s2)`` has, in the 6-dim space of
``f``, the orthonormal eigenvectors

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
* ``symmetric_dirichlet``: ``A t mu (|F|^2 + |F^+|^2 - 4) = A t mu sum_i (s_i - 1/s_i)^2`` (sec. 5.2);
* ``neohookean``: ``A t (mu/2 (I2 - 2) - mu log J + lam/2 log(J)^2)``, ``J = s1 s2``.

Numerical policy
----------------
* Collapsed triangles (``J = 0``): ``stvk`` is a polynomial in ``F`` and stays exact (energy,
  gradient, Hessian and eigensystem equal autograd of the plain formula; the frame ``u2``, ``n`` is
  then any orthonormal completion, which the Hessian does not depend on).  ``arap`` has a finite
  energy and gradient (``R`` is not unique there; a deterministic one is used), but its Hessian has
  a cone in the out-of-plane directions (``2 mu (1 - 1/s_i) -> -inf``): the twist and normal
  eigenvalues are evaluated with the stretches floored at ``eps`` of the dtype (relative to
  the rest stretch 1; ``2.2e-16`` in float64, ``1.2e-7`` in float32: the resolution of ``s2`` itself,
  which is known to ``~eps s1``), which is exact for ``s2 >= eps`` (a triangle compressed to 1e-9 of its
  height in float64, 1e-4 in float32, has its exact Hessian to ~1e-15 / ~1e-7) and finite
  (``>= -2 mu / eps``) below; ``clamp``/``abs`` projections stay PSD.  ``neohookean`` (``log J``) and ``symmetric_dirichlet`` (``1/s2``) are undefined there: every
  entry point raises the same ``ValueError`` naming the faces (:func:`check_collapsed`).
* Near collapse every formula is written without cancellation or intermediate overflow (the
  small scaling eigenvalue comes from the determinant, eigenvectors from non-cancelling
  components, squares through ``hypot``, ``s - 1/s`` as ``(s - 1)(s + 1)/s``), so a value that
  fits in the dtype comes out to a few ulps of its own magnitude given ``s``.  (``s2`` itself is
  known to ``eps s1`` only when the columns of ``F`` are nearly parallel: relative condition
  ``s1/s2``.)  Where a needed value does not fit the dtype, the entry point raises a ``ValueError``
  naming the faces (:func:`check_finite_values`) instead of returning Inf/NaN.  In float32 with
  ``mu ~ 4e4`` Pa: the ``symmetric_dirichlet`` Hessian (``~ mu s2^-4``) below ``s2 ~ 5e-9``, its
  gradient below ``~ 1e-11``, its energy below ``~ 1e-17``; the ``neohookean`` Hessian
  (``~ lam |log J| s2^-2``) below ``~ 5e-17``; absurd stretches.
* Position independence: ``F`` and ``N`` come from edge vectors, so a translated mesh gives the
  same values (bit for bit when the translated coordinates are exact), float32 included.
* These checks need data-dependent control flow and are skipped under ``torch.func`` transforms.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .._checks import is_traced
from ..options import Option

__all__ = ["MembraneModel", "rest_shape_matrices", "deformation_gradient", "deformation", "eigensystem",
           "stress", "energy_density", "check_collapsed", "check_finite_values"]

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
    """``D: (T, 3, 2)`` with ``F = X D`` (rows for ``x0, x1, x2``; rows 1-2 are ``W = Dm^{-1}``) and rest
    areas ``(T,)`` [m^2]; ValueError on zero-area faces."""
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


def _edges(x: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    x0 = x[..., faces[:, 0], :]
    return x[..., faces[:, 1], :] - x0, x[..., faces[:, 2], :] - x0  # (..., T, 3) each


def _from_edges(e1: Tensor, e2: Tensor, D: Tensor) -> Tensor:
    W = D[..., 1:, :]  # (T, 2, 2)
    return e1[..., :, None] * W[..., 0:1, :] + e2[..., :, None] * W[..., 1:2, :]  # (..., T, 3, 2)


def deformation_gradient(x: Tensor, faces: Tensor, D: Tensor) -> Tensor:
    """``F = Ds W: (..., T, 3, 2)`` of positions ``x: (..., V, 3)`` (from edge vectors; ``D`` as returned by
    :func:`rest_shape_matrices`).  Also the linear map of a direction ``v`` to ``dF``."""
    return _from_edges(*_edges(x, faces), D)


def deformation(x: Tensor, faces: Tensor, D: Tensor) -> tuple[Tensor, Tensor]:
    """``F: (..., T, 3, 2)`` and ``N = f0 x f1 = det(W) (e1 x e2): (..., T, 3)`` (exactly zero for a
    collapsed triangle, whatever the rounding of ``F``)."""
    e1, e2 = _edges(x, faces)
    W = D[..., 1:, :]
    detW = W[..., 0, 0] * W[..., 1, 1] - W[..., 0, 1] * W[..., 1, 0]
    return _from_edges(e1, e2, D), _cross_rounded_once(e1, e2) * detW[..., None]


def _cross_rounded_once(a: Tensor, b: Tensor) -> Tensor:
    """``a x b`` of ``(..., 3)``; below float64 evaluated in float64 and rounded once: the products of two
    float32 numbers are exact there, so the cross product of nearly parallel edges (a strongly compressed
    triangle, whose second stretch it gives) keeps its own relative accuracy instead of ``eps |a| |b|``."""
    if a.dtype == torch.float64 or not a.is_floating_point():
        return torch.linalg.cross(a, b, dim=-1)
    return torch.linalg.cross(a.double(), b.double(), dim=-1).to(a.dtype)


def _hypot3(v: Tensor) -> Tensor:
    """``|v|`` of ``(..., 3)`` without overflow or underflow of the squares."""
    return torch.hypot(torch.hypot(v[..., 0], v[..., 1]), v[..., 2])


def _unit_eigvec(d: Tensor, h12: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """Unit eigenvector ``(c, s)`` of ``[[m + d, h12], [h12, m - d]]`` for its eigenvalue ``m + r``
    (``r = hypot(d, h12)``), from components that do not cancel (each accurate to a few ulps of its
    own size); ``(1, 0)`` for a multiple of the identity."""
    pos = d >= 0
    x = torch.where(pos, d + r, h12)
    y = torch.where(pos, h12, r - d)
    nrm = torch.hypot(x, y)
    ok = nrm > 0
    safe = torch.where(ok, nrm, torch.ones_like(nrm))
    return torch.where(ok, x / safe, torch.ones_like(x)), torch.where(ok, y / safe, torch.zeros_like(y))


def _gram(F: Tensor, N: Tensor | None):
    f0, f1 = F[..., 0], F[..., 1]
    a, b, c = (f0 * f0).sum(-1), (f0 * f1).sum(-1), (f1 * f1).sum(-1)
    cr = torch.linalg.cross(f0, f1, dim=-1) if N is None else N
    d = 0.5 * a - 0.5 * c
    r = torch.hypot(d, b)
    s1 = torch.sqrt((0.5 * a + 0.5 * c) + r)  # no cancellation: every term >= 0
    J = _hypot3(cr)  # s1 s2, from the cross product (accurate for orthogonal-ish columns)
    ok = s1 > 0
    s2 = torch.where(ok, J / torch.where(ok, s1, torch.ones_like(s1)), torch.zeros_like(s1))
    return s1, s2, d, b, r, cr


def _singular_values(F: Tensor, N: Tensor | None = None) -> Tensor:
    s1, s2 = _gram(F, N)[:2]
    return torch.stack((s1, s2), -1)


def _thin_svd(F: Tensor, N: Tensor | None = None):
    """Closed-form thin SVD of ``F: (..., 3, 2)``: ``U (..., 3, 2)``, ``s (..., 2)``, ``V (..., 2, 2)``, ``n (..., 3)``.

    ``V`` is a rotation, ``s1 >= s2 >= 0`` (up to rounding), ``n = u1 x u2``; ``s1`` from ``F^T F`` with
    ``hypot`` (no cancellation), ``s2 = |f0 x f1| / s1`` (``N`` if given), ``v1`` from non-cancelling
    eigenvector components, ``u1 = F v1 / |F v1|``, ``n`` the normal made orthogonal to ``u1``.  Rank < 2
    gets a deterministic orthonormal completion (``U``, ``n`` stay orthonormal always)."""
    s1, s2, d, b, r, cr = _gram(F, N)
    cp, sp = _unit_eigvec(d, b, r)
    V = torch.stack((torch.stack((cp, -sp), -1), torch.stack((sp, cp), -1)), -2)  # columns v1, v2
    w = F[..., 0] * cp[..., None] + F[..., 1] * sp[..., None]  # F v1 = s1 u1
    nw = _hypot3(w)
    one = torch.ones_like(nw)
    okw = nw > 0
    u1 = torch.where(okw[..., None], w / torch.where(okw, nw, one)[..., None], _any_unit(F))
    m = cr - (cr * u1).sum(-1, keepdim=True) * u1
    nm = _hypot3(m)
    finfo = torch.finfo(F.dtype)
    okn = nm > finfo.tiny / finfo.eps
    n = torch.where(okn[..., None], m / torch.where(okn, nm, one)[..., None], _perp(u1))
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


# ------------------------------------------------------------------------------ 2x2 eigensystems
def _eig2(h11: Tensor, h12: Tensor, h22: Tensor):
    """Eigenvalues ``l1 >= l2`` and unit eigenvectors ``a1 = (c, s)`` (``a2 = (-s, c)``) of symmetric 2x2
    matrices.  The eigenvalue of larger magnitude is ``m +- r`` (same signs); the other one is
    ``det / big`` written as ``h11 (h22/big) - h12 (h12/big)`` (no ``m - r`` cancellation, no overflow)."""
    m, d = 0.5 * h11 + 0.5 * h22, 0.5 * h11 - 0.5 * h22
    r = torch.hypot(d, h12)
    big = m + torch.copysign(r, m)
    ok = big != 0
    sb = torch.where(ok, big, torch.ones_like(big))
    other = torch.where(ok, h11 * (h22 / sb) - h12 * (h12 / sb), torch.zeros_like(big))
    up = m >= 0
    return (torch.where(up, big, other), torch.where(up, other, big)), _unit_eigvec(d, h12, r)


def _eig2_diagonal(h11: Tensor, h22: Tensor):
    """``_eig2`` of ``diag(h11, h22)``: exact."""
    first = h11 >= h22
    one, zero = torch.ones_like(h11), torch.zeros_like(h11)
    return (torch.maximum(h11, h22), torch.minimum(h11, h22)), (torch.where(first, one, zero), torch.where(first, zero, one))


# ------------------------------------------------------------------------------ energies in singular values
# Each returns (psi,), (psi, (p1, p2)) or (psi, (p1, p2), (l1, l2), (c, s), (twist, flip, o1, o2)) for
# order 0, 1, 2: the density, psi_i = dPsi/ds_i, the 2x2 scaling eigensystem (eigenvector a1 = (c, s))
# and the other four eigenvalues.  Products with a large factor are ordered ((coef * i) * i) so that an
# intermediate overflows only if the result does.
def _stvk(s1, s2, mu, lam, order) -> tuple:
    q1, q2 = (s1 - 1) * (s1 + 1), (s2 - 1) * (s2 + 1)  # s^2 - 1 without cancellation
    S = 0.5 * (q1 + q2)  # tr G
    psi = 0.25 * mu * (q1 * q1 + q2 * q2) + 0.5 * lam * S * S
    if order == 0:
        return (psi,)
    c1, c2 = mu * q1 + lam * S, mu * q2 + lam * S  # psi_i / s_i
    p = (c1 * s1, c2 * s2)
    if order == 1:
        return psi, p
    k = 2 * mu + lam
    scaling = _eig2(c1 + k * s1 * s1, lam * s1 * s2, c2 + k * s2 * s2)
    twist = lam * S + mu * (q1 + s2 * (s2 - s1))  # (psi1 + psi2)/(s1 + s2)
    flip = lam * S + mu * (q1 + s2 * (s2 + s1))  # (psi1 - psi2)/(s1 - s2)
    return psi, p, *scaling, (twist, flip, c1, c2)


def _arap(s1, s2, mu, lam, order) -> tuple:
    d1, d2 = s1 - 1, s2 - 1
    psi = mu * (d1 * d1 + d2 * d2)
    if order == 0:
        return (psi,)
    two = 2 * mu
    p = (two * d1, two * d2)
    if order == 1:
        return psi, p
    # the cone at s_i = 0: the divisions see the stretches floored at eps (the resolution of s2 itself,
    # which is known to ~eps s1), so every valid triangle with s_i >= eps gets its exact eigenvalues and a
    # collapsed one finite ones (>= -2 mu / eps); the twist needs the floor only where s1 + s2 vanishes
    floor = torch.finfo(s1.dtype).eps
    t1, t2 = s1.clamp_min(floor), s2.clamp_min(floor)
    twist = two * (d1 + d2) / (t1 + s2)
    flip = two * torch.ones_like(s1)
    scaling = _eig2_diagonal(flip, flip)
    return psi, p, *scaling, (twist, flip, two * (t1 - 1) / t1, two * (t2 - 1) / t2)


def _symmetric_dirichlet(s1, s2, mu, lam, order) -> tuple:
    i1, i2 = 1 / s1, 1 / s2
    d1, d2 = (s1 - 1) * (s1 + 1) * i1, (s2 - 1) * (s2 + 1) * i2  # s - 1/s
    psi = (mu * d1) * d1 + (mu * d2) * d2
    if order == 0:
        return (psi,)
    two = 2 * mu
    p1, p2 = (two * d1) * (1 + i1 * i1), (two * d2) * (1 + i2 * i2)  # 2 mu (s - s^-3)
    if order == 1:
        return psi, (p1, p2)
    six = 6 * mu
    scaling = _eig2_diagonal(two + (((six * i1) * i1) * i1) * i1, two + (((six * i2) * i2) * i2) * i2)
    flip = two + ((two * i1) * i2) * (i1 * i1 + i1 * i2 + i2 * i2)
    # twist: near rest (p1 + p2)/(s1 + s2) keeps its digits; near collapse p2 may overflow first
    twist = torch.where(s2 < 0.5, two - ((two * i1) * i2) * (i1 * i1 - i1 * i2 + i2 * i2), (p1 + p2) / (s1 + s2))
    return psi, (p1, p2), *scaling, (twist, flip, p1 * i1, p2 * i2)


def _neohookean(s1, s2, mu, lam, order) -> tuple:
    lj = torch.log(s1) + torch.log(s2)  # log J (J = s1 s2 may underflow where s1, s2 do not)
    q1, q2 = (s1 - 1) * (s1 + 1), (s2 - 1) * (s2 + 1)
    psi = 0.5 * mu * (q1 + q2) - mu * lj + 0.5 * lam * lj * lj
    if order == 0:
        return (psi,)
    i1, i2 = 1 / s1, 1 / s2
    c1, c2 = mu * q1 + lam * lj, mu * q2 + lam * lj  # psi_i s_i
    p1, p2 = c1 * i1, c2 * i2
    if order == 1:
        return psi, (p1, p2)
    # Hessian in s: mu I + i2^2 K, K = [[A rho^2, lam rho], [lam rho, A]], rho = s2/s1, A = mu + lam (1 - log J),
    # det K = (A - lam)(A + lam) rho^2: the small eigenvalue of K is det K / big (no cancellation, no overflow)
    A = mu + lam * (1 - lj)
    rho = s2 * i1
    k11, k12 = A * rho * rho, lam * rho
    m, d = 0.5 * k11 + 0.5 * A, 0.5 * k11 - 0.5 * A
    r = torch.hypot(d, k12)
    big = m + torch.copysign(r, m)
    ok = big != 0
    other = ((((mu - lam * lj) * (A + lam)) / torch.where(ok, big, torch.ones_like(big))) * i1) * i1
    l_big, l_other = mu + (big * i2) * i2, mu + torch.where(ok, other, torch.zeros_like(other))
    up = m >= 0
    scaling = (torch.where(up, l_big, l_other), torch.where(up, l_other, l_big)), _unit_eigvec(d, k12, r)
    jm1 = (s1 - 1) + (s2 - 1) + (s1 - 1) * (s2 - 1)  # J - 1
    twist = ((mu * jm1 + lam * lj) * i1) * i2
    flip = ((mu * (s1 * s2 + 1) - lam * lj) * i1) * i2
    return psi, (p1, p2), *scaling, (twist, flip, p1 * i1, p2 * i2)


_DENSITIES = {
    MembraneModel.STVK: _stvk,
    MembraneModel.ARAP: _arap,
    MembraneModel.SYMMETRIC_DIRICHLET: _symmetric_dirichlet,
    MembraneModel.NEOHOOKEAN: _neohookean,
}


def _outer(u: Tensor, v: Tensor) -> Tensor:
    """``(..., 3) x (..., 2) -> (..., 3, 2)``."""
    return u[..., :, None] * v[..., None, :]


def eigensystem(model: MembraneModel, F: Tensor, mu: Tensor, lam: Tensor, N: Tensor | None = None):
    """Closed-form eigensystem of ``d^2Psi/df^2`` per element: ``(l (..., 6), Q (..., 6, 6))``.

    Columns of ``Q`` are the eigenvectors (row-major ``vec`` of 3x2 matrices): scaling 1, scaling 2
    (``l1 >= l2``), twist, flip, normal 1, normal 2.  Also returns ``psi`` and ``P = dPsi/dF (..., 3, 2)``.
    ``N = f0 x f1`` from :func:`deformation` (optional; exact zero at collapse)."""
    U, s, V, n = _thin_svd(F, N)
    psi, (p1, p2), (l1, l2), (c, sn), (tw, fl, o1, o2) = _DENSITIES[model](s[..., 0], s[..., 1], mu, lam, 2)
    u1, u2 = U[..., 0], U[..., 1]
    v1, v2 = V[..., 0], V[..., 1]
    o11, o22 = _outer(u1, v1).flatten(-2), _outer(u2, v2).flatten(-2)
    o21, o12 = _outer(u2, v1).flatten(-2), _outer(u1, v2).flatten(-2)
    c, sn = c[..., None], sn[..., None]
    Q = torch.stack(
        (c * o11 + sn * o22, c * o22 - sn * o11, _SQRT1_2 * (o21 - o12), _SQRT1_2 * (o21 + o12),
         _outer(n, v1).flatten(-2), _outer(n, v2).flatten(-2)),
        -1,
    )
    lam_all = torch.stack((l1, l2, tw, fl, o1, o2), -1)
    P = p1[..., None, None] * _outer(u1, v1) + p2[..., None, None] * _outer(u2, v2)
    return lam_all, Q, psi, P


def stress(model: MembraneModel, F: Tensor, mu: Tensor, lam: Tensor, N: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``psi (...,)`` and ``P = dPsi/dF = U diag(psi_i) V^T (..., 3, 2)`` per element (StVK: ``P = F S`` in
    closed form, ``S = 2 mu G + lam tr(G) I``, ``G = (F^T F - I) / 2``, without the singular value decomposition)."""
    if model is MembraneModel.STVK:
        return _stvk_stress(F, mu, lam)
    U, s, V, _ = _thin_svd(F, N)
    psi, (p1, p2) = _DENSITIES[model](s[..., 0], s[..., 1], mu, lam, 1)
    P = p1[..., None, None] * _outer(U[..., 0], V[..., 0]) + p2[..., None, None] * _outer(U[..., 1], V[..., 1])
    return psi, P


def _stvk_stress(F: Tensor, mu: Tensor, lam: Tensor) -> tuple[Tensor, Tensor]:
    """StVK's ``psi = mu |G|^2 + lam tr(G)^2 / 2`` and ``P = F S`` of ``F (..., T, 3, 2)`` (``mu``, ``lam`` broadcast
    with ``(..., T)``, as in :func:`stress`).  ``G``'s diagonal is ``(|f_a|^2 - 1) / 2``, as accurate as the singular values' ``(s - 1)(s + 1)``
    (both carry the rounding of ``F``)."""
    f0, f1 = F[..., 0], F[..., 1]
    g00 = 0.5 * ((f0 * f0).sum(-1) - 1)
    g11 = 0.5 * ((f1 * f1).sum(-1) - 1)
    g01 = 0.5 * (f0 * f1).sum(-1)
    tr = g00 + g11
    psi = mu * (g00 * g00 + g11 * g11 + 2 * g01 * g01) + 0.5 * lam * tr * tr
    s00, s11, s01 = 2 * mu * g00 + lam * tr, 2 * mu * g11 + lam * tr, 2 * mu * g01
    P = torch.stack((f0 * s00[..., None] + f1 * s01[..., None], f0 * s01[..., None] + f1 * s11[..., None]), -1)
    return psi, P


def energy_density(model: MembraneModel, F: Tensor, mu: Tensor, lam: Tensor, N: Tensor | None = None) -> Tensor:
    """``Psi(F)`` per element ``(..., T)`` (energy per unit rest area and thickness)."""
    s = _singular_values(F, N)
    return _DENSITIES[model](s[..., 0], s[..., 1], mu, lam, 0)[0]


# ------------------------------------------------------------------------------ checks
_UNDEFINED_AT_COLLAPSE = {
    MembraneModel.NEOHOOKEAN: "its -log(J) barrier is infinite there",
    MembraneModel.SYMMETRIC_DIRICHLET: "its energy (1/s2^2) is infinite there",
}


def stvk_blocks(F: Tensor, D: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """Unprojected StVK element Hessians ``d^2 Psi / dx^2`` per unit ``A t``: ``(..., T, 9, 9)`` (flat index
    ``3 k + i``: vertex ``k``, axis ``i``) of ``F (..., T, 3, 2)`` and ``D (T, 3, 2)``, in closed form without an
    eigensystem.  With ``S = 2 mu G + lam tr(G) I``, ``G = (F^T F - I)/2`` and ``t = D F^T (3 vertices x 3
    axes)``: ``H[k i, l j] = (D S D^T)_kl delta_ij + mu (D D^T)_kl (F F^T)_ij + mu t_kj t_li + lam t_ki t_lj``
    (the second variation ``dF : dF S + 2 mu |sym(F^T dF)|^2 + lam tr(F^T dF)^2``).  The eigensystem's
    ``Q diag(l) Q^T`` pulled back by ``D`` equals it to round-off (tests); ``mu``, ``lam`` broadcast over the
    batch dimensions (``(...,)`` per sample)."""
    m3, l3 = mu[..., None, None, None], lam[..., None, None, None]  # over (T, 2, 2) and (T, 3, 3)
    eye = torch.eye(2, dtype=F.dtype, device=F.device)
    G = 0.5 * (F.transpose(-1, -2) @ F - eye)  # (..., T, 2, 2)
    S = 2 * m3 * G + (l3 * (G[..., 0, 0] + G[..., 1, 1])[..., None, None]) * eye
    A = D @ S @ D.transpose(-1, -2)  # (..., T, 3, 3) over vertices
    B = m3 * (D @ D.transpose(-1, -2))  # mu D D^T over vertices
    FF = F @ F.transpose(-1, -2)  # (..., T, 3, 3) over axes
    t = D @ F.transpose(-1, -2)  # (..., T, 3 vertices, 3 axes)
    H = torch.mul(B[..., :, None, :, None], FF[..., None, :, None, :])  # (..., T, k, i, l, j)
    H.addcmul_((m3 * t)[..., :, None, None, :], t.transpose(-1, -2)[..., None, :, :, None])
    H.addcmul_((l3 * t)[..., :, :, None, None], t[..., None, None, :, :])
    H.diagonal(dim1=-3, dim2=-1).add_(A[..., None])  # (D S D^T)_kl on i = j
    return H.flatten(-4, -3).flatten(-2)


def stvk_hvp_stress(F: Tensor, dF: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """``dP = dF S + F dS`` of StVK (``S = 2 mu G + lam tr(G) I``, ``dS = 2 mu sym(F^T dF) + lam tr(F^T dF) I``):
    the unprojected second variation of ``Psi`` applied to ``dF``, ``(..., T, 3, 2)``, without an eigensystem."""
    mu, lam = mu[..., None, None, None], lam[..., None, None, None]
    eye = torch.eye(2, dtype=F.dtype, device=F.device)
    G = 0.5 * (F.transpose(-1, -2) @ F - eye)
    M = F.transpose(-1, -2) @ dF
    trG = (G[..., 0, 0] + G[..., 1, 1])[..., None, None]
    trM = (M[..., 0, 0] + M[..., 1, 1])[..., None, None]
    S = 2 * mu * G + lam * trG * eye
    dS = mu * (M + M.transpose(-1, -2)) + lam * trM * eye
    return dF @ S + F @ dS


def _faces_text(bad: Tensor) -> tuple[list[int], str]:
    """Face indices where ``bad (..., T)`` holds anywhere in the batch, and their text."""
    idx = torch.nonzero(bad.reshape(-1, bad.shape[-1]).any(0)).reshape(-1)
    first = idx[:8].tolist()
    return first, f"faces {first}" + (f" ... ({idx.numel()} in all)" if idx.numel() > 8 else "")


def check_collapsed(model: MembraneModel, F: Tensor, N: Tensor | None = None) -> None:
    """ValueError naming the faces where ``J = 0`` for the models undefined there (``neohookean``,
    ``symmetric_dirichlet``); skipped under ``torch.func`` transforms.  ``N`` from :func:`deformation`."""
    why = _UNDEFINED_AT_COLLAPSE.get(model)
    if why is None or is_traced(F) or (N is not None and is_traced(N)):
        return
    cr = torch.linalg.cross(F[..., 0], F[..., 1], dim=-1) if N is None else N
    bad = _hypot3(cr.detach()) == 0
    if bool(bad.any()):
        _, faces = _faces_text(bad)
        raise ValueError(
            f"membrane model '{model.value}' is undefined at collapsed triangles (zero deformed area, J = 0): "
            f"{faces}; {why}. Use 'stvk' or 'arap' for states that may collapse"
        )


def check_finite_values(model: MembraneModel, what: str, values: Tensor, F: Tensor, N: Tensor | None = None) -> None:
    """ValueError naming the faces where a per-element result ``values (..., T, *k)`` (``k`` = the trailing
    dimensions beyond ``F``'s batch) is not finite although ``J > 0``: the value overflows the dtype
    (nearly collapsed or absurdly stretched triangles).  Skipped under ``torch.func`` transforms."""
    if is_traced(values) or is_traced(F):
        return
    v = values.detach()
    if v.numel() == 0:  # an empty batch or no faces: nothing can overflow
        return
    if bool(torch.isfinite(v.sum())):  # one pass: a non-finite entry makes the sum non-finite
        return
    v = v.reshape(v.shape[: F.ndim - 2] + (-1,))
    bad = ~torch.isfinite(v).all(-1)
    if bool(bad.any()):
        _, faces = _faces_text(bad)
        b, t = torch.nonzero(bad.reshape(-1, bad.shape[-1]))[0].tolist()
        s = _singular_values(F.detach(), None if N is None else N.detach()).reshape(-1, bad.shape[-1], 2)[b, t]
        raise ValueError(
            f"membrane model '{model.value}': the {what} overflows {F.dtype} at {faces} (stretches s1 = "
            f"{float(s[0]):.3g}, s2 = {float(s[1]):.3g} at face {t}): these triangles are too close to "
            f"collapse (or too stretched) for {F.dtype}; evaluate in float64"
        )
