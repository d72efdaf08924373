"""Pure per-hinge geometry kernels: the bend angle, its gradient and its Hessian.

Everything here works on gathered stencils ``x4: (..., H, 4, 3)`` (the SPEC's order
``(x0, x1, x2, x3)``: hinge edge ``x0 -> x1``, wing of triangle A, wing of triangle B, see
:mod:`torchbend.topology`) and returns per-hinge quantities; scatter-adding them to vertices
happens outside (:mod:`torchbend._assemble`).  No autograd is used or required: these are the
closed forms of Tamstorf & Grinspun (2013), eqs. (4)-(6), and the tech report, eqs. (18)-(21)
and the half-hinge blocks of sec. 6.

The half-hinge
--------------
The tech report splits the Hessian of ``theta`` into one "half-hinge" per triangle.  With both
triangles written with the same vertex order ``(a, b, c) = (x0, x1, wing)`` the two halves are
the *same* function ``T`` of their three vertices, and

    grad theta = T'(x0, x1, x2) - T'(x0, x1, x3),      Hess theta = T''(x0, x1, x2) - T''(x0, x1, x3)

(``T`` is the azimuth of the half-plane through the edge and the wing; the minus sign is the
orientation flip of triangle B, whose CCW order is ``(x1, x0, x3)``).  Per half-hinge, with
``N = (b - a) x (c - a)`` (twice the area times the unit normal ``n``), the altitudes ``h_k``
from vertex ``k`` to its opposite edge, the interior angles ``alpha_k`` and the outward unit
in-plane edge normals ``m_k`` (edge opposite ``k``):

    grad_k T = rho_k n,    rho = (cos(alpha_b)/h_a,  cos(alpha_a)/h_b,  -1/h_c)

and the 3x3 blocks (tech report sec. 6, ``H_ij = d/dx_j (d T/dx_i)``)

    H_aa = cos(alpha_b)/h_a^2 S(m_a n^T) - B        H_ab = (cos(alpha_b) m_b n^T + cos(alpha_a) n m_a^T)/(h_a h_b) + B
    H_bb = cos(alpha_a)/h_b^2 S(m_b n^T) - B        H_ac = (cos(alpha_b) m_c n^T - n m_a^T)/(h_a h_c)
    H_cc = -S(m_c n^T)/h_c^2                        H_bc = (cos(alpha_a) m_c n^T - n m_b^T)/(h_b h_c)

with ``S(A) = A + A^T`` and ``B = n m_c^T / |e0|^2`` (the term that is transposed in the per-triangle
assembly; summed over both halves it is symmetric).  Applied to a direction ``v`` these blocks
collapse to dot products (no 12x12 matrix is formed):

    (H v)_k = rho_k mu + n (m_k/h_k . nu) + [B terms],   mu = sum_k (m_k/h_k)(n . v_k),  nu = sum_k rho_k v_k

where ``mu`` is the directional derivative of ``n``.

Degenerate deformed geometry
----------------------------
A triangle of zero area (or a hinge edge of zero length) in the *deformed* state has no normal,
and the closed forms divide by its area and edge length.  Policy: a half-hinge whose triangle is
numerically collinear (``|N| <= eps * longest_edge^2``, which includes a collapsed hinge edge) has
zero normal and zero angle derivatives, so the hinge's gradient and Hessian are those of its other
half: finite, never NaN (an exactly collinear triangle also has ``theta = atan2(0, 0) = 0``).
Rest shapes with such triangles are rejected upstream (:func:`torchbend.rest_hinge_weights`).
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "hinge_angle",
    "hinge_angle_and_gradient",
    "hinge_angle_hvp",
    "hinge_angle_hessian",
    "hinge_angle_gradient_hvp",
]


def _cross(u: Tensor, v: Tensor) -> Tensor:
    # explicit components: faster than linalg.cross for small trailing dims and vmap-friendly
    u0, u1, u2 = u.unbind(-1)
    v0, v1, v2 = v.unbind(-1)
    return torch.stack((u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0), dim=-1)


def _dot(u: Tensor, v: Tensor) -> Tensor:
    return (u * v).sum(-1)


def _floor(t: Tensor) -> Tensor:
    """Clamp a non-negative magnitude away from zero (degenerate-geometry policy)."""
    return t.clamp_min(torch.finfo(t.dtype).tiny)


class _HalfHinge:
    """Local quantities of one half-hinge ``(a, b, c)``; all fields ``(..., H[, 3])``."""

    __slots__ = ("N", "n", "rho", "mh", "mc_s", "area2", "elen")

    def __init__(self, xa: Tensor, xb: Tensor, xc: Tensor):
        e = xb - xa  # hinge edge
        u = xc - xa  # edge opposite b
        w = xc - xb  # edge opposite a
        N = _cross(e, u)
        area2 = torch.linalg.vector_norm(N, dim=-1)  # |N| = 2 * area
        elen = torch.linalg.vector_norm(e, dim=-1)
        # degenerate-geometry policy: a numerically collinear triangle (|N| <= eps * longest^2,
        # which includes a collapsed hinge edge) gets zero normal and zero derivatives
        longest2 = torch.maximum(torch.maximum(_dot(e, e), _dot(u, u)), _dot(w, w))
        valid = area2 > torch.finfo(area2.dtype).eps * longest2
        one = torch.ones_like(area2)
        inv_area2 = torch.where(valid, 1.0 / torch.where(valid, area2, one), 0.0)
        inv_elen = torch.where(valid, 1.0 / torch.where(valid, elen, one), 0.0)
        n = N * inv_area2[..., None]  # unit normal (zero for a degenerate triangle)
        # gradient coefficients rho_k = cos(alpha_other)/h_k, written without angles:
        #   cos(alpha_b)/h_a = -(e.w)/(|e||N|),  cos(alpha_a)/h_b = (e.u)/(|e||N|),  -1/h_c = -|e|/|N|
        s = inv_elen * inv_area2
        rho_a = -_dot(e, w) * s
        rho_b = _dot(e, u) * s
        rho_c = -elen * inv_area2
        # outward in-plane edge normals divided by the altitude to the opposite vertex:
        #   m_a/h_a = (w x n)/|N|,  m_b/h_b = -(u x n)/|N|,  m_c/h_c = (e x n)/|N|
        en = _cross(e, n)
        self.N = N
        self.n = n
        self.rho = (rho_a, rho_b, rho_c)
        self.mh = (
            _cross(w, n) * inv_area2[..., None],
            -_cross(u, n) * inv_area2[..., None],
            en * inv_area2[..., None],
        )
        # m_c / |e0|^2 = (e x n)/|e|^3  (the B term)
        self.mc_s = en * (inv_elen * inv_elen * inv_elen)[..., None]
        self.area2 = area2
        self.elen = elen

    def gradient(self) -> tuple[Tensor, Tensor, Tensor]:
        return tuple(r[..., None] * self.n for r in self.rho)  # type: ignore[return-value]

    def hvp(self, va: Tensor, vb: Tensor, vc: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        n = self.n
        ra, rb, rc = self.rho
        mha, mhb, mhc = self.mh
        wa, wb, wc = _dot(n, va), _dot(n, vb), _dot(n, vc)
        mu = mha * wa[..., None] + mhb * wb[..., None] + mhc * wc[..., None]
        nu = ra[..., None] * va + rb[..., None] * vb + rc[..., None] * vc
        # B = n m_c^T/|e|^2 enters as [[-B, B], [B^T, -B]] on the (a, b) blocks
        bd = _dot(self.mc_s, vb - va)
        bb = _dot(self.mc_s, vb)
        oa = ra[..., None] * mu + n * (_dot(mha, nu) + bd)[..., None]
        ob = rb[..., None] * mu + n * (_dot(mhb, nu) - bb)[..., None] + self.mc_s * wa[..., None]
        oc = rc[..., None] * mu + n * _dot(mhc, nu)[..., None]
        return oa, ob, oc

    def blocks(self) -> Tensor:
        """Dense half-hinge Hessian ``(..., H, 3, 3, 3, 3)`` indexed ``[i, j, p, q]`` (vertex i, j)."""
        n, rho, mh = self.n, self.rho, self.mh
        rows = []
        for i in range(3):
            row = []
            for j in range(3):
                # H_ij = rho_i mh_j n^T + rho_j n mh_i^T  (read off the HVP above)
                row.append(
                    rho[i][..., None, None] * _outer(mh[j], n) + rho[j][..., None, None] * _outer(n, mh[i])
                )
            rows.append(row)
        B = _outer(n, self.mc_s)
        rows[0][0] = rows[0][0] - B
        rows[0][1] = rows[0][1] + B
        rows[1][0] = rows[1][0] + B.transpose(-1, -2)
        rows[1][1] = rows[1][1] - B
        return torch.stack([torch.stack(r, dim=-3) for r in rows], dim=-4)


def _outer(u: Tensor, v: Tensor) -> Tensor:
    """``u v^T`` over the last dimension: ``(..., 3, 3)``."""
    return u[..., :, None] * v[..., None, :]


def _theta(e: Tensor, nA: Tensor, nB: Tensor) -> Tensor:
    """SPEC: ``theta = atan2(e0_hat . (nA x nB), nA . nB)``; the single formula used everywhere,
    so that angles (and hence energies and gradients) at the rest state vanish bit for bit."""
    e_hat = e / _floor(torch.linalg.vector_norm(e, dim=-1))[..., None]
    return torch.atan2(_dot(e_hat, _cross(nA, nB)), _dot(nA, nB))


def _angle(hA: _HalfHinge, hB: _HalfHinge, e: Tensor) -> Tensor:
    # hB.N = e0 x (x3 - x0) = -nB
    return _theta(e, hA.N, -hB.N)


def _halves(x4: Tensor) -> tuple[_HalfHinge, _HalfHinge]:
    x0, x1, x2, x3 = x4.unbind(-2)
    return _HalfHinge(x0, x1, x2), _HalfHinge(x0, x1, x3)


def hinge_angle(x4: Tensor) -> Tensor:
    """Signed bend angle ``theta: (..., H)`` in (-pi, pi] of stencils ``x4: (..., H, 4, 3)``."""
    x0, x1, x2, x3 = x4.unbind(-2)
    e = x1 - x0
    # nA = e0 x (x2 - x0), nB = (x3 - x1) x e0 = (x3 - x0) x e0
    return _theta(e, _cross(e, x2 - x0), _cross(x3 - x0, e))


def hinge_angle_and_gradient(x4: Tensor) -> tuple[Tensor, Tensor]:
    """``theta: (..., H)`` and ``d theta / d x4: (..., H, 4, 3)`` (tech report eqs. 18-21)."""
    theta, grad, _ = hinge_angle_gradient_hvp(x4, None)
    return theta, grad


def _hvp(hA: _HalfHinge, hB: _HalfHinge, v4: Tensor) -> Tensor:
    v0, v1, v2, v3 = v4.unbind(-2)
    a0, a1, a2 = hA.hvp(v0, v1, v2)
    b0, b1, b3 = hB.hvp(v0, v1, v3)
    return torch.stack((a0 - b0, a1 - b1, a2, -b3), dim=-2)


def hinge_angle_hvp(x4: Tensor, v4: Tensor) -> Tensor:
    """``Hess(theta) v`` per hinge, ``(..., H, 4, 3)``, from the closed-form blocks (no 12x12 matrix)."""
    return _hvp(*_halves(x4), v4)


def hinge_angle_gradient_hvp(x4: Tensor, v4: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
    """``(theta, grad theta, Hess(theta) v)`` sharing one evaluation of the half-hinge quantities.

    ``v4`` may be ``None`` (then the HVP is ``None``)."""
    hA, hB = _halves(x4)
    theta = _angle(hA, hB, x4[..., 1, :] - x4[..., 0, :])
    ga, gb, gc = hA.gradient()
    ka, kb, kc = hB.gradient()
    grad = torch.stack((ga - ka, gb - kb, gc, -kc), dim=-2)
    return theta, grad, (None if v4 is None else _hvp(hA, hB, v4))


def hinge_angle_hessian(x4: Tensor) -> Tensor:
    """Dense ``Hess(theta): (..., H, 12, 12)`` in stencil order, flat index ``3*k + j``."""
    hA, hB = _halves(x4)
    A = hA.blocks()  # (..., H, 3, 3, 3, 3) over (x0, x1, x2)
    B = hB.blocks()  # over (x0, x1, x3)
    shape = A.shape[:-4]
    H = A.new_zeros(shape + (4, 4, 3, 3))
    ia = [0, 1, 2]
    ib = [0, 1, 3]
    for i in range(3):
        for j in range(3):
            H[..., ia[i], ia[j], :, :] += A[..., i, j, :, :]
            H[..., ib[i], ib[j], :, :] -= B[..., i, j, :, :]
    return H.permute(*range(len(shape)), -4, -2, -3, -1).reshape(shape + (12, 12))
