"""Pure per-hinge geometry kernels: the bend angle, its gradient and its Hessian.

Everything here works on gathered stencils ``x4: (..., H, 4, 3)`` (the SPEC's order
``(x0, x1, x2, x3)``: hinge edge ``x0 -> x1``, wing of triangle A, wing of triangle B, see
:mod:`torchbend.topology`) and returns per-hinge quantities; scatter-adding them to vertices
happens outside (:mod:`torchbend.ops.stencil`).  No autograd is used or required: these are the
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

Layout
------
Internally every 3-vector is a triple of ``(..., H)`` tensors (structure of arrays): elementwise
kernels over contiguous per-hinge arrays run several times faster in eager PyTorch than
reductions over a trailing dimension of size 3.  The ``*_soa`` functions take and return that
layout (``xs = (x0, x1, x2, x3)``, each ``(c_x, c_y, c_z)``); the public functions take
``(..., H, 4, 3)`` stencils and convert.

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

from .stencil import nondegenerate

__all__ = [
    "hinge_angle",
    "hinge_angle_and_gradient",
    "hinge_angle_hvp",
    "hinge_angle_hessian",
    "hinge_angle_gradient_hvp",
    "to_soa",
    "from_soa",
    "hinge_angle_soa",
    "hinge_angle_gradient_hvp_soa",
    "hinge_energy_hessian_soa",
]

Vec = tuple  # (x, y, z) components, each (..., H)


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _add(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _neg(a: Vec) -> Vec:
    return (-a[0], -a[1], -a[2])


def _scale(a: Vec, s: Tensor) -> Vec:
    return (a[0] * s, a[1] * s, a[2] * s)


def _axpy(s: Tensor, a: Vec, b: Vec) -> Vec:
    """``s a + b``."""
    return (torch.addcmul(b[0], a[0], s), torch.addcmul(b[1], a[1], s), torch.addcmul(b[2], a[2], s))


def _cross(u: Vec, v: Vec) -> Vec:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _dot(u: Vec, v: Vec) -> Tensor:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def to_soa(x4: Tensor) -> tuple:
    """``(..., H, 4, 3)`` stencils -> 4 vertices x 3 components of ``(..., H)`` views."""
    return tuple(tuple(c.unbind(-1)) for c in x4.unbind(-2))


def from_soa(vs) -> Tensor:
    """Inverse of :func:`to_soa`: 4 x 3 components ``(..., H)`` -> ``(..., H, 4, 3)``."""
    flat = [c for v in vs for c in v]
    return torch.stack(flat, -1).unflatten(-1, (4, 3))


class _HalfHinge:
    """Local quantities of one half-hinge ``(a, b, c)`` (components ``(..., H)``)."""

    __slots__ = ("N", "n", "rho", "e", "u", "w", "inv_area2", "inv_elen", "_mh", "_mc_s")

    def __init__(self, xa: Vec, xb: Vec, xc: Vec, e: Vec | None = None):
        e = _sub(xb, xa) if e is None else e  # hinge edge
        u = _sub(xc, xa)  # edge opposite b
        w = _sub(xc, xb)  # edge opposite a
        N = _cross(e, u)
        ee, uu, ww = _dot(e, e), _dot(u, u), _dot(w, w)
        area2 = _dot(N, N).sqrt()  # |N| = 2 * area
        elen = ee.sqrt()
        # degenerate-geometry policy: a numerically collinear triangle (|N| <= eps * longest^2,
        # which includes a collapsed hinge edge) gets zero normal and zero derivatives
        valid = nondegenerate(area2, torch.maximum(torch.maximum(ee, uu), ww))
        one = torch.ones_like(area2)
        inv_area2 = torch.where(valid, torch.where(valid, area2, one).reciprocal(), 0.0)
        inv_elen = torch.where(valid, torch.where(valid, elen, one).reciprocal(), 0.0)
        # gradient coefficients rho_k = cos(alpha_other)/h_k, written without angles:
        #   cos(alpha_b)/h_a = -(e.w)/(|e||N|),  cos(alpha_a)/h_b = (e.u)/(|e||N|),  -1/h_c = -|e|/|N|
        s = inv_elen * inv_area2
        self.rho = (-_dot(e, w) * s, _dot(e, u) * s, -elen * inv_area2)
        self.N = N
        self.n = _scale(N, inv_area2)  # unit normal (zero for a degenerate triangle)
        self.e, self.u, self.w = e, u, w
        self.inv_area2, self.inv_elen = inv_area2, inv_elen
        self._mh = self._mc_s = None

    @property
    def mh(self) -> tuple[Vec, Vec, Vec]:
        """Outward in-plane edge normals over the altitude to the opposite vertex (second order only):
        ``m_a/h_a = (w x n)/|N|,  m_b/h_b = -(u x n)/|N|,  m_c/h_c = (e x n)/|N|``."""
        if self._mh is None:
            n, r = self.n, self.inv_area2
            self._mh = (_scale(_cross(self.w, n), r), _scale(_cross(n, self.u), r), _scale(_cross(self.e, n), r))
        return self._mh

    @property
    def mc_s(self) -> Vec:
        """``m_c / |e0|^2 = (e x n)/|e|^3`` (the B term); equals ``mh_c |N| / |e|^3``."""
        if self._mc_s is None:
            ie = self.inv_elen
            self._mc_s = _scale(_cross(self.e, self.n), ie * ie * ie)
        return self._mc_s

    def gradient(self) -> tuple[Vec, Vec, Vec]:
        return tuple(_scale(self.n, r) for r in self.rho)  # type: ignore[return-value]

    def hvp(self, va: Vec, vb: Vec, vc: Vec) -> tuple[Vec, Vec, Vec]:
        n = self.n
        ra, rb, rc = self.rho
        mha, mhb, mhc = self.mh
        wa, wb, wc = _dot(n, va), _dot(n, vb), _dot(n, vc)
        mu = _add(_add(_scale(mha, wa), _scale(mhb, wb)), _scale(mhc, wc))  # d n / d x [v]
        nu = _add(_add(_scale(va, ra), _scale(vb, rb)), _scale(vc, rc))
        # B = n m_c^T/|e|^2 enters as [[-B, B], [B^T, -B]] on the (a, b) blocks
        mc_s = self.mc_s
        bd = _dot(mc_s, _sub(vb, va))
        bb = _dot(mc_s, vb)
        oa = _axpy(_dot(mha, nu) + bd, n, _scale(mu, ra))
        ob = _axpy(wa, mc_s, _axpy(_dot(mhb, nu) - bb, n, _scale(mu, rb)))
        oc = _axpy(_dot(mhc, nu), n, _scale(mu, rc))
        return oa, ob, oc


def _outer(u: Tensor, v: Tensor) -> Tensor:
    """``u v^T`` over the last dimension: ``(..., 3, 3)``."""
    return u[..., :, None] * v[..., None, :]


def _theta(e: Vec, nA: Vec, nB: Vec) -> Tensor:
    """SPEC: ``theta = atan2(e0_hat . (nA x nB), nA . nB)``; the single formula used everywhere,
    so that angles (and hence energies and gradients) at the rest state vanish bit for bit."""
    elen = _dot(e, e).sqrt()
    inv = torch.where(elen > 0, torch.where(elen > 0, elen, torch.ones_like(elen)).reciprocal(), 0.0)
    return torch.atan2(_dot(e, _cross(nA, nB)) * inv, _dot(nA, nB))


def _halves(xs) -> tuple[_HalfHinge, _HalfHinge, Vec]:
    x0, x1, x2, x3 = xs
    e = _sub(x1, x0)
    return _HalfHinge(x0, x1, x2, e), _HalfHinge(x0, x1, x3, e), e


def hinge_angle_soa(xs) -> Tensor:
    """``theta: (..., H)`` from SoA stencils (see :func:`to_soa`)."""
    x0, x1, x2, x3 = xs
    e = _sub(x1, x0)
    # nA = e0 x (x2 - x0), nB = (x3 - x1) x e0 = (x3 - x0) x e0
    return _theta(e, _cross(e, _sub(x2, x0)), _cross(_sub(x3, x0), e))


def hinge_angle_gradient_hvp_soa(xs, vs=None):
    """``(theta, grad theta, Hess(theta) v)`` on SoA stencils; ``vs=None`` skips the HVP.

    ``grad`` and ``Hv`` are 4-tuples (per stencil vertex) of component triples ``(..., H)``."""
    hA, hB, e = _halves(xs)
    theta = _theta(e, hA.N, _neg(hB.N))  # hB.N = e0 x (x3 - x0) = -nB
    ga, gb, gc = hA.gradient()
    ka, kb, kc = hB.gradient()
    grad = (_sub(ga, ka), _sub(gb, kb), gc, _neg(kc))
    if vs is None:
        return theta, grad, None
    v0, v1, v2, v3 = vs
    a0, a1, a2 = hA.hvp(v0, v1, v2)
    b0, b1, b3 = hB.hvp(v0, v1, v3)
    return theta, grad, (_sub(a0, b0), _sub(a1, b1), a2, _neg(b3))


def hinge_angle(x4: Tensor) -> Tensor:
    """Signed bend angle ``theta: (..., H)`` in (-pi, pi] of stencils ``x4: (..., H, 4, 3)``."""
    return hinge_angle_soa(to_soa(x4))


def hinge_angle_and_gradient(x4: Tensor) -> tuple[Tensor, Tensor]:
    """``theta: (..., H)`` and ``d theta / d x4: (..., H, 4, 3)`` (tech report eqs. 18-21)."""
    theta, grad, _ = hinge_angle_gradient_hvp_soa(to_soa(x4))
    return theta, from_soa(grad)


def hinge_angle_hvp(x4: Tensor, v4: Tensor) -> Tensor:
    """``Hess(theta) v`` per hinge, ``(..., H, 4, 3)``, from the closed-form blocks (no 12x12 matrix)."""
    hv = hinge_angle_gradient_hvp(x4, v4)[2]
    assert hv is not None
    return hv


def hinge_angle_gradient_hvp(x4: Tensor, v4: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
    """``(theta, grad theta, Hess(theta) v)`` sharing one evaluation of the half-hinge quantities.

    ``x4, v4: (..., H, 4, 3)``; ``v4`` may be ``None`` (then the HVP is ``None``)."""
    theta, grad, hv = hinge_angle_gradient_hvp_soa(to_soa(x4), None if v4 is None else to_soa(v4))
    return theta, from_soa(grad), (None if hv is None else from_soa(hv))


def hinge_angle_hessian(x4: Tensor) -> Tensor:
    """Dense ``Hess(theta): (..., H, 12, 12)`` in stencil order, flat index ``3*k + j``."""
    return hinge_energy_hessian_soa(to_soa(x4), None, None)[0]


def _stack_vec(vs, dim: int = -1) -> Tensor:
    return torch.stack(vs, dim)


def hinge_energy_hessian_soa(xs, d1: Tensor | None, d2: Tensor | None) -> tuple[Tensor, Tensor]:
    """``d1 Hess(theta) + d2 g g^T`` as dense ``(..., H, 12, 12)`` blocks, and ``g: (..., H, 12)``.

    ``d1``/``d2`` are per-hinge scalars ``(..., H)`` (``psi'`` and ``psi''``); ``None`` means
    ``d1 = 1`` and ``d2 = 0`` (the angle Hessian itself).  Built from the half-hinge factors with one
    batched matrix product: with ``rho``, ``mh`` zero-padded to the 4 stencil vertices,

        X[(i,p),(j,q)] = d1 sum_s sign_s rho_s[i] mh_s[j,p] n_s[q],     Y = X + d2/2 g g^T,
        H = Y + Y^T + [[-Bs, Bs], [Bs^T, -Bs]] on the (x0, x1) blocks,   Bs = d1 (B_A - B_B)
    """
    hA, hB, _ = _halves(xs)
    ga, gb, gc = hA.gradient()
    ka, kb, kc = hB.gradient()
    g = torch.stack([c for v in (_sub(ga, ka), _sub(gb, kb), gc, _neg(kc)) for c in v], -1)  # (..., H, 12)
    zero = torch.zeros_like(hA.rho[0])
    one = None if d1 is None else d1
    rhoA = torch.stack((hA.rho[0], hA.rho[1], hA.rho[2], zero), -1)  # (..., H, 4)
    rhoB = -torch.stack((hB.rho[0], hB.rho[1], zero, hB.rho[2]), -1)  # minus: Hess = T''_A - T''_B
    if one is not None:
        rhoA = rhoA * one[..., None]
        rhoB = rhoB * one[..., None]
    z3 = torch.zeros_like(torch.stack(hA.n, -1))
    mhA = torch.stack((_stack_vec(hA.mh[0]), _stack_vec(hA.mh[1]), _stack_vec(hA.mh[2]), z3), -2)  # (..., H, 4, 3)
    mhB = torch.stack((_stack_vec(hB.mh[0]), _stack_vec(hB.mh[1]), z3, _stack_vec(hB.mh[2])), -2)
    # T[i, p, j, s] = rho_s[i] mh_s[j, p]
    T = torch.stack((rhoA[..., :, None, None] * mhA.transpose(-1, -2)[..., None, :, :],
                     rhoB[..., :, None, None] * mhB.transpose(-1, -2)[..., None, :, :]), -1)  # (..., H, i, p, j, s)
    batch = T.shape[:-4]
    N = torch.stack((_stack_vec(hA.n), _stack_vec(hB.n)), -2)  # (..., H, 2, 3)
    T = T.reshape((-1, 48, 2))
    Y = torch.bmm(T, N.reshape(-1, 2, 3)).reshape((-1, 12, 12))  # rows (i, p), cols (j, q)
    gf = g.reshape(-1, 12)
    if d2 is not None:
        Y.baddbmm_((0.5 * d2.reshape(-1, 1) * gf)[:, :, None], gf[:, None, :])
    Hs = Y + Y.transpose(-1, -2)
    Bs = _outer(_stack_vec(hA.n), _stack_vec(hA.mc_s)) - _outer(_stack_vec(hB.n), _stack_vec(hB.mc_s))
    if one is not None:
        Bs = Bs * one[..., None, None]
    Bs = Bs.reshape(-1, 3, 3)
    Hs[:, 0:3, 0:3] -= Bs
    Hs[:, 0:3, 3:6] += Bs
    Hs[:, 3:6, 0:3] += Bs.transpose(-1, -2)
    Hs[:, 3:6, 3:6] -= Bs
    return Hs.reshape(batch + (12, 12)), g
