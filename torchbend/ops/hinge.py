"""Pure per-hinge geometry kernels: the bend angle, its gradient and its Hessian.

Everything here works on gathered stencils ``x4: (..., H, 4, 3)`` (the stencil order of :mod:`torchbend.mesh.topology`
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
assembly; summed over both halves it is symmetric).

Accuracy: everything in terms of ``N``
--------------------------------------
The kernels never normalize ``N``.  With the edges ``e = b - a``, ``u = c - a``, ``w = c - b``:

    grad_k T = t_k N,        t = (-(e.w), e.u, -|e|^2) / (|e| |N|^2)          (t_k = rho_k / |N|)
    mh_k = m_k / h_k:        mh_a = (w x N)/|N|^2,  mh_b = (N x u)/|N|^2,  mh_c = (e x N)/|N|^2
    H_ij = mh_j g_i^T + g_j mh_i^T  (g_i = t_i N),  B = bl mh_c^T with bl = N / |e|^3

and applied to a direction ``v`` (no 12x12 matrix is formed):

    (H v)_k = t_k mu + (mh_k . nu) N + [B terms],   mu = sum_k mh_k (N . v_k),  nu = sum_k t_k v_k.

``N`` is the cross product of the triangle's two *shortest* edges (:func:`_normal`; ``e x u = e x w =
u x w``).  Where the digits went before (float64, against a 40-digit reference, ``benchmarks/accuracy.py``):

- ``N = e x u`` whatever the shape: a cross product's rounding errors are ``~eps |p| |q|``, so for a
  triangle with a small angle at ``a`` the relative error of ``N`` is ``~eps / sin(alpha_a)`` (Kahan's
  needle).  It is mostly an error in ``|N|``, which ``n = N/|N|`` hides but ``rho = .../|N|`` and
  ``1/h = |e|/|N|`` do not: on needles the angle gradient lost 490 ulps (median; max 15000), its Hessian 900
  (max 29000); now 0.7 / 0.8 and 0.8 / 1.5.
  From the two shortest edges (the cross product at the largest angle) the error is ``~eps`` unless the
  largest angle is near 180 degrees, where every formula loses ``eps / sin``.
- Each factor normalized separately: ``n = N (1/|N|)``, ``rho = c (1/|e|)(1/|N|)``, ``mh = (w x n)(1/|N|)``
  (a cross product with the already rounded ``n``), ``mc = (e x n)(1/|e|)^3``: some ten roundings per Hessian
  entry, where ``t = c (1/|e|)(1/|N|^2)`` and ``mh = (w x N)(1/|N|^2)`` take about half as many.  The angle Hessian
  went from median 1.4 / max 3.8 ulps to 1.1 / 2.9 on well-shaped hinges, from 1.6 / 12.4 to 1.3 / 4.6
  on random ones (autograd: 1.9 / 3.5 and 1.9 / 5.5; benchmarks/results/accuracy_after.txt).

``theta`` itself keeps the defining formula with ``nA = e x (x2 - x0)``, ``nB = (x3 - x0) x e``
(:func:`hinge_angle_soa`, and the compiled ``hinge_psi``), so that angles at the rest state vanish bit for
bit; on needles its error (~100 eps, max 14000) still limits the energy and its derivatives (from the
shortest-edge normals it would be ~0.3 eps: the same change in ``hinge_angle_soa`` and ``hinge_psi``).

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
zero angle derivatives, so the hinge's gradient and Hessian are those of its other
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


def _normal(e: Vec, u: Vec, w: Vec, ee: Tensor, uu: Tensor, ww: Tensor) -> Vec:
    """``N = e x u = e x w = u x w`` of the triangle with edges ``e = b - a``, ``u = c - a``, ``w = c - b``,
    from its two shortest edges (the cross product at the largest angle): the rounding errors of a cross
    product are ``~eps |p| |q|``, so this choice keeps the relative error of ``N`` near ``eps`` unless the
    largest angle is close to 180 degrees, where the others lose ``~eps / sin(smallest angle)`` (Kahan)."""
    # selections as exact blends m a + (1 - m) b with m in {0, 1} (several times faster than torch.where)
    m = (ee >= torch.maximum(uu, ww)).to(ee.dtype)  # e longest (ties included)
    m1 = 1.0 - m
    k = m1 * (ww >= uu).to(ee.dtype)  # else w longest (ties with u included)
    k1 = 1.0 - k
    p = tuple(torch.addcmul(ei * m1, ui, m) for ui, ei in zip(u, e, strict=True))  # u x w | e x w | e x u
    q = tuple(torch.addcmul(wi * k1, ui, k) for ui, wi in zip(u, w, strict=True))
    return _cross(p, q)


class _HalfHinge:
    """Local quantities of one half-hinge ``(a, b, c)`` (components ``(..., H)``), in terms of the
    unnormalized normal ``N`` (see the module docstring, "Accuracy")."""

    __slots__ = ("N", "t", "e", "u", "w", "inn", "ie", "_mh", "_bl")

    def __init__(self, xa: Vec, xb: Vec, xc: Vec, e: Vec | None = None, ee: Tensor | None = None):
        e = _sub(xb, xa) if e is None else e  # hinge edge
        u = _sub(xc, xa)  # edge opposite b
        w = _sub(xc, xb)  # edge opposite a
        ee_: Tensor = _dot(e, e) if ee is None else ee
        uu, ww = _dot(u, u), _dot(w, w)
        N = _normal(e, u, w, ee_, uu, ww)
        nn = _dot(N, N)
        # degenerate-geometry policy: a numerically collinear triangle (|N| <= eps * longest^2,
        # which includes a collapsed hinge edge) gets zero derivatives
        valid = nondegenerate(nn.sqrt(), torch.maximum(torch.maximum(ee_, uu), ww)).to(nn.dtype)
        invalid = 1.0 - valid
        nn = nn + invalid  # unchanged where valid, >= 1 where not (so are the edge lengths below)
        ee_ = ee_ + invalid
        elen = ee_.sqrt()
        inn = valid / nn  # 1/|N|^2, 0 if degenerate
        ie = elen.reciprocal()
        # t_k = rho_k / |N|:  -(e.w)/(|e| |N|^2),  (e.u)/(|e| |N|^2),  -|e|/|N|^2  (reciprocals, not
        # divisions: one rounding more, but divisions cost the compiled blocks ~10%)
        self.t = (-_dot(e, w) * ie * inn, _dot(e, u) * ie * inn, -elen * inn)
        self.N, self.e, self.u, self.w = N, e, u, w
        self.inn, self.ie = inn, ie
        self._mh = self._bl = None

    @property
    def mh(self) -> tuple[Vec, Vec, Vec]:
        """Outward in-plane edge normals over the altitude to the opposite vertex (second order only):
        ``m_a/h_a = (w x N)/|N|^2,  m_b/h_b = (N x u)/|N|^2,  m_c/h_c = (e x N)/|N|^2`` (0 if degenerate)."""
        if self._mh is None:
            N, r = self.N, self.inn
            self._mh = (_scale(_cross(self.w, N), r), _scale(_cross(N, self.u), r), _scale(_cross(self.e, N), r))
        return self._mh

    @property
    def bl(self) -> Vec:
        """``N / |e|^3``: the B term is ``B = n m_c^T / |e|^2 = bl mh_c^T``."""
        if self._bl is None:
            ie = self.ie
            self._bl = _scale(self.N, ie * ie * ie)
        return self._bl

    def hvp(self, va: Vec, vb: Vec, vc: Vec) -> tuple[Vec, Vec, Vec]:
        N = self.N
        ta, tb, tc = self.t
        mha, mhb, mhc = self.mh
        wa, wb, wc = _dot(N, va), _dot(N, vb), _dot(N, vc)
        mu = _add(_add(_scale(mha, wa), _scale(mhb, wb)), _scale(mhc, wc))  # |N| d n / d x [v]
        nu = _add(_add(_scale(va, ta), _scale(vb, tb)), _scale(vc, tc))
        # B = bl mhc^T enters as [[-B, B], [B^T, -B]] on the (a, b) blocks
        bl = self.bl
        bd = _dot(mhc, _sub(vb, va))
        oa = _axpy(_dot(mha, nu), N, _axpy(bd, bl, _scale(mu, ta)))
        ob = _axpy(_dot(bl, va), mhc, _axpy(_dot(mhb, nu), N, _axpy(-_dot(mhc, vb), bl, _scale(mu, tb))))
        oc = _axpy(_dot(mhc, nu), N, _scale(mu, tc))
        return oa, ob, oc


def _outer(u: Tensor, v: Tensor) -> Tensor:
    """``u v^T`` over the last dimension: ``(..., 3, 3)``."""
    return u[..., :, None] * v[..., None, :]


def _theta(e: Vec, nA: Vec, nB: Vec, ee: Tensor | None = None) -> Tensor:
    """The defining formula ``theta = atan2(e0_hat . (nA x nB), nA . nB)`` (``ee = e . e`` if already computed)."""
    # as atan2(e . (nA x nB), |e| nA . nB): no division (a collapsed edge gives atan2(0, 0) = 0)
    elen = (_dot(e, e) if ee is None else ee).sqrt()
    return torch.atan2(_dot(e, _cross(nA, nB)), elen * _dot(nA, nB))


_EXP_CLAMP = 1000  # |log2| of the largest stencil scale factor (float64's exponents reach +-1022)


def _stencil_theta(xs) -> Tensor:
    """The bend angle of SoA stencils: the single formula used everywhere (:func:`hinge_angle_soa`,
    :func:`hinge_angle_gradient_hvp_soa`; the compiled ``stencil_theta`` does the same), so that angles
    (and hence energies and gradients) at the rest state vanish bit for bit.

    Scale range.  ``e . (nA x nB)`` is a product of five lengths and ``nA . nB`` of four: in the input's
    dtype they would overflow or underflow for edges beyond ~1e+-7 (float32) or ~1e+-61 (float64), which
    gives wrong angles or NaN.  So the edges ``x_k - x0`` are scaled per hinge by the power of two that
    brings their largest component into [1, 2) (exact: the angle is bit for bit the unscaled one wherever
    that did not over- or underflow), and float32 (and half) stencils are evaluated in float64, from the
    exact float64 differences, then rounded once: every finite float32 stencil gets its angle to about
    half an ulp, float64 stencils with any finite edges (a tiny edge in a huge stencil is degenerate
    geometry, not a scale)."""
    x0, x1, x2, x3 = xs
    dtype = x0[0].dtype
    if dtype != torch.float64:
        return _stencil_theta(tuple(tuple(c.double() for c in v) for v in xs)).to(dtype)
    e, u, w = _sub(x1, x0), _sub(x2, x0), _sub(x3, x0)
    m = e[0].abs()
    for c in (e[1], e[2], *u, *w):
        m = torch.maximum(m, c.abs())
    ex = torch.frexp(m)[1].clamp(-_EXP_CLAMP, _EXP_CLAMP)  # m = f 2^ex, f in [0.5, 1) (0 for m = 0)
    p = torch.ldexp(torch.ones_like(m), 1 - ex)  # m p in [1, 2)
    e, u, w = _scale(e, p), _scale(u, p), _scale(w, p)
    # nA = e0 x (x2 - x0), nB = (x3 - x1) x e0 = (x3 - x0) x e0
    return _theta(e, _cross(e, u), _cross(w, e))


def _halves(xs) -> tuple[_HalfHinge, _HalfHinge, Vec, Tensor]:
    x0, x1, x2, x3 = xs
    e = _sub(x1, x0)
    ee = _dot(e, e)
    return _HalfHinge(x0, x1, x2, e, ee), _HalfHinge(x0, x1, x3, e, ee), e, ee


def _gradient(hA: _HalfHinge, hB: _HalfHinge) -> tuple[Vec, Vec, Vec, Vec]:
    """``grad theta = T'_A - T'_B`` per stencil vertex (``g_k = t_k N`` per half)."""
    (ta, tb, tc), (sa, sb, sc) = hA.t, hB.t
    NA, NB = hA.N, hB.N

    def diff(t: Tensor, s: Tensor) -> Vec:
        return tuple(torch.addcmul(a * t, b, s, value=-1.0) for a, b in zip(NA, NB, strict=True))  # type: ignore[return-value]

    return diff(ta, sa), diff(tb, sb), _scale(NA, tc), _scale(NB, -sc)


def hinge_angle_soa(xs) -> Tensor:
    """``theta: (..., H)`` from SoA stencils (see :func:`to_soa`)."""
    return _stencil_theta(xs)


def hinge_angle_gradient_hvp_soa(xs, vs=None):
    """``(theta, grad theta, Hess(theta) v)`` on SoA stencils; ``vs=None`` skips the HVP.

    ``grad`` and ``Hv`` are 4-tuples (per stencil vertex) of component triples ``(..., H)``."""
    hA, hB, _, _ = _halves(xs)
    # the defining formula as hinge_angle_soa evaluates it, so that angles at the rest state vanish bit for bit
    # (scaled, float32 in float64: _stencil_theta); the half-hinge normals N are formed differently
    theta = _stencil_theta(xs)
    grad = _gradient(hA, hB)
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
    batched matrix product: with ``t``, ``mh`` zero-padded to the 4 stencil vertices (module docstring),

        X[(i,p),(j,q)] = d1 sum_s sign_s t_s[i] mh_s[j,p] N_s[q],     Y = X + d2/2 g g^T,
        H = Y + Y^T + [[-Bs, Bs], [Bs^T, -Bs]] on the (x0, x1) blocks,   Bs = d1 (B_A - B_B)
    """
    hA, hB, _, _ = _halves(xs)
    g = torch.stack([c for v in _gradient(hA, hB) for c in v], -1)  # (..., H, 12)
    zero = torch.zeros_like(hA.t[0])
    tA = torch.stack((hA.t[0], hA.t[1], hA.t[2], zero), -1)  # (..., H, 4)
    tB = -torch.stack((hB.t[0], hB.t[1], zero, hB.t[2]), -1)  # minus: Hess = T''_A - T''_B
    if d1 is not None:
        tA = tA * d1[..., None]
        tB = tB * d1[..., None]
    z3 = torch.zeros_like(torch.stack(hA.N, -1))
    mhA = torch.stack((_stack_vec(hA.mh[0]), _stack_vec(hA.mh[1]), _stack_vec(hA.mh[2]), z3), -2)  # (..., H, 4, 3)
    mhB = torch.stack((_stack_vec(hB.mh[0]), _stack_vec(hB.mh[1]), z3, _stack_vec(hB.mh[2])), -2)
    # T[i, p, j, s] = t_s[i] mh_s[j, p]
    T = torch.stack((tA[..., :, None, None] * mhA.transpose(-1, -2)[..., None, :, :],
                     tB[..., :, None, None] * mhB.transpose(-1, -2)[..., None, :, :]), -1)  # (..., H, i, p, j, s)
    batch = T.shape[:-4]
    N = torch.stack((_stack_vec(hA.N), _stack_vec(hB.N)), -2)  # (..., H, 2, 3)
    T = T.reshape((-1, 48, 2))
    Y = torch.bmm(T, N.reshape(-1, 2, 3)).reshape((-1, 12, 12))  # rows (i, p), cols (j, q)
    gf = g.reshape(-1, 12)
    if d2 is not None:
        Y.baddbmm_((0.5 * d2.reshape(-1, 1) * gf)[:, :, None], gf[:, None, :])
    Hs = Y + Y.transpose(-1, -2)
    Bs = _outer(_stack_vec(hA.bl), _stack_vec(hA.mh[2])) - _outer(_stack_vec(hB.bl), _stack_vec(hB.mh[2]))
    if d1 is not None:
        Bs = Bs * d1[..., None, None]
    Bs = Bs.reshape(-1, 3, 3)
    Hs[:, 0:3, 0:3] -= Bs
    Hs[:, 0:3, 3:6] += Bs
    Hs[:, 3:6, 0:3] += Bs.transpose(-1, -2)
    Hs[:, 3:6, 3:6] -= Bs
    return Hs.reshape(batch + (12, 12)), g
