r"""Squared distances between mesh primitives for contact (eager reference), with the distance types of
Incremental Potential Contact, the edge-edge mollifier and the log barrier on squared distances.

Point-triangle ``(p, t0, t1, t2)`` and edge-edge ``(a0, a1, b0, b1)`` stencils, positions ``(N, 4, 3)``.  The
*type* of a stencil says which pair of sub-primitives is closest (classified without gradient): for a point
and a triangle ``PT_P0 .. PT_P2`` (a corner), ``PT_E01, PT_E12, PT_E20`` (an edge) or ``PT_FACE`` (the
interior); for two edges a corner pair (``EE_A0B0 .. EE_A1B1``), a corner and an edge (``EE_AB0, EE_AB1,
EE_A0B, EE_A1B``) or ``EE_LINES`` (the interiors; near-parallel edges fall to a corner-edge type).  Each
type's squared distance is one smooth formula::

    point-point   |p - q|^2
    point-line    |(p - e0) x (e1 - e0)|^2 / |e1 - e0|^2
    point-plane   ((p - t0) . n)^2 / |n|^2,       n = (t1 - t0) x (t2 - t0)
    line-line     ((b0 - a0) . n)^2 / |n|^2,      n = (a1 - a0) x (b1 - b0)

so that its derivatives (the solvers take them by automatic differentiation of these formulas) are those of
the distance wherever the type is constant.  The barrier of IPC on squared distances ``D = d^2``, activation
``Dhat = dhat^2``, stiffness ``kappa``::

    b(D) = -kappa (D - Dhat)^2 log(D / Dhat)   (0 < D < Dhat),    0 otherwise

and the mollifier of edge-edge pairs, ``m(c) = -c^2 / eps_x^2 + 2 c / eps_x`` for ``c < eps_x`` (1 otherwise),
``c = |(a1 - a0) x (b1 - b0)|^2``, ``eps_x = 1e-3 |a1 - a0|^2 |b1 - b0|^2`` at rest, which takes the barrier
of nearly parallel edges smoothly to zero (where the edge-edge distance is not smooth).
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["PT_P0", "PT_P1", "PT_P2", "PT_E01", "PT_E12", "PT_E20", "PT_FACE", "EE_A0B0", "EE_A0B1", "EE_A1B0",
           "EE_A1B1", "EE_AB0", "EE_AB1", "EE_A0B", "EE_A1B", "EE_LINES", "point_triangle_type", "edge_edge_type",
           "typed_distance_sq", "by_type", "point_triangle_distance_sq", "edge_edge_distance_sq", "barrier", "mollifier"]

PT_P0, PT_P1, PT_P2, PT_E01, PT_E12, PT_E20, PT_FACE = range(7)
EE_A0B0, EE_A0B1, EE_A1B0, EE_A1B1, EE_AB0, EE_AB1, EE_A0B, EE_A1B, EE_LINES = range(7, 16)


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


@torch.no_grad()
def point_triangle_type(X: Tensor) -> Tensor:
    """The distance type ``(N,)`` (int64, ``PT_*``) of point-triangle stencils ``X (N, 4, 3)``: the region of
    the triangle's Voronoi diagram the point lies in (Ericson's closest-point test, without gradient)."""
    p, a, b, c = X.unbind(-2)
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    t = torch.full(d1.shape, PT_FACE, dtype=torch.int64, device=X.device)
    # the checks of Ericson's test, last to first so that the first that holds wins
    t = torch.where((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), PT_E12, t)
    t = torch.where((vb <= 0) & (d2 >= 0) & (d6 <= 0), PT_E20, t)
    t = torch.where((vc <= 0) & (d1 >= 0) & (d3 <= 0), PT_E01, t)
    t = torch.where((d6 >= 0) & (d5 <= d6), PT_P2, t)
    t = torch.where((d3 >= 0) & (d4 <= d3), PT_P1, t)
    t = torch.where((d1 <= 0) & (d2 <= 0), PT_P0, t)
    return t


@torch.no_grad()
def edge_edge_type(X: Tensor, parallel: float = 1e-10) -> Tensor:
    """The distance type ``(N,)`` (``EE_*``) of edge-edge stencils ``X (N, 4, 3)`` (``a0, a1, b0, b1``): where
    the closest points of the two segments lie (Ericson's clamped segment-segment parameters; edges with
    ``|u x v|^2 <= parallel |u|^2 |v|^2`` are taken as parallel: a corner of one against the other).  Typed in
    float64 whatever ``X``'s dtype: in float32 ``|u|^2 |v|^2 - (u . v)^2`` of two parallel edges is round-off far
    above ``parallel`` and the clamped parameters noise (two parallel edges of a flat float32 grid 17 mm apart
    were typed as crossing lines, at distance 0)."""
    if X.dtype != torch.float64:
        X = X.double()
    a0, a1, b0, b1 = X.unbind(-2)
    u, v, w = a1 - a0, b1 - b0, a0 - b0
    a, b, c, d, e = _dot(u, u), _dot(u, v), _dot(v, v), _dot(u, w), _dot(v, w)
    den = a * c - b * b
    par = den <= parallel * a * c
    s = torch.where(par, torch.zeros_like(a), ((b * e - c * d) / torch.where(par, torch.ones_like(den), den)).clamp(0, 1))
    t = (b * s + e) / c
    # t outside [0, 1]: clamp it and recompute s for that end
    t_lo, t_hi = t < 0, t > 1
    t = t.clamp(0, 1)
    s = torch.where(t_lo, (-d / a).clamp(0, 1), torch.where(t_hi, ((b - d) / a).clamp(0, 1), s))
    s_end = torch.where(s <= 0, 0, torch.where(s >= 1, 1, -1))
    t_end = torch.where(t <= 0, 0, torch.where(t >= 1, 1, -1))
    table = torch.tensor([[EE_A0B0, EE_A0B1, EE_A0B], [EE_A1B0, EE_A1B1, EE_A1B], [EE_AB0, EE_AB1, EE_LINES]],
                         dtype=torch.int64, device=X.device)
    si = torch.where(s_end < 0, 2, s_end)
    ti = torch.where(t_end < 0, 2, t_end)
    kinds = table[si, ti]
    if bool(par.any()):  # parallel: the nearest of the four corner-segment pairs (a corner or an edge interior)
        kinds = _parallel_type(a0[par], a1[par], b0[par], b1[par], par, kinds)
    return kinds


def _point_segment(p: Tensor, e0: Tensor, e1: Tensor) -> tuple[Tensor, Tensor]:
    """(squared distance, where: 0 at e0, 1 at e1, 2 inside) of points to segments."""
    e = e1 - e0
    t = (_dot(p - e0, e) / _dot(e, e).clamp_min(torch.finfo(p.dtype).tiny)).clamp(0, 1)
    q = e0 + t[:, None] * e
    return _pp(p, q), torch.where(t <= 0, 0, torch.where(t >= 1, 1, 2))


def _parallel_type(a0, a1, b0, b1, par: Tensor, kinds: Tensor) -> Tensor:
    # corner of one edge against the other edge: a0-B, a1-B, b0-A, b1-A; each may end at a corner pair
    d_a0, w_a0 = _point_segment(a0, b0, b1)
    d_a1, w_a1 = _point_segment(a1, b0, b1)
    d_b0, w_b0 = _point_segment(b0, a0, a1)
    d_b1, w_b1 = _point_segment(b1, a0, a1)
    D = torch.stack([d_a0, d_a1, d_b0, d_b1], -1)
    k = D.argmin(-1)
    t_a0 = torch.tensor([EE_A0B0, EE_A0B1, EE_A0B], device=a0.device)[w_a0]
    t_a1 = torch.tensor([EE_A1B0, EE_A1B1, EE_A1B], device=a0.device)[w_a1]
    t_b0 = torch.tensor([EE_A0B0, EE_A1B0, EE_AB0], device=a0.device)[w_b0]
    t_b1 = torch.tensor([EE_A0B1, EE_A1B1, EE_AB1], device=a0.device)[w_b1]
    chosen = torch.stack([t_a0, t_a1, t_b0, t_b1], -1).gather(-1, k[:, None])[:, 0]
    out = kinds.clone()
    out[par] = chosen
    return out


def _pp(p: Tensor, q: Tensor) -> Tensor:
    d = p - q
    return _dot(d, d)


def _pe(p: Tensor, e0: Tensor, e1: Tensor) -> Tensor:
    e = e1 - e0
    cr = torch.linalg.cross(p - e0, e)
    return _dot(cr, cr) / _dot(e, e)


def _plane(p: Tensor, t0: Tensor, t1: Tensor, t2: Tensor) -> Tensor:
    n = torch.linalg.cross(t1 - t0, t2 - t0)
    h = _dot(p - t0, n)
    return h * h / _dot(n, n)


def _lines(a0: Tensor, a1: Tensor, b0: Tensor, b1: Tensor) -> Tensor:
    n = torch.linalg.cross(a1 - a0, b1 - b0)
    h = _dot(b0 - a0, n)
    return h * h / _dot(n, n)


_TYPED = {
    PT_P0: (_pp, (0, 1)), PT_P1: (_pp, (0, 2)), PT_P2: (_pp, (0, 3)),
    PT_E01: (_pe, (0, 1, 2)), PT_E12: (_pe, (0, 2, 3)), PT_E20: (_pe, (0, 3, 1)), PT_FACE: (_plane, (0, 1, 2, 3)),
    EE_A0B0: (_pp, (0, 2)), EE_A0B1: (_pp, (0, 3)), EE_A1B0: (_pp, (1, 2)), EE_A1B1: (_pp, (1, 3)),
    EE_AB0: (_pe, (2, 0, 1)), EE_AB1: (_pe, (3, 0, 1)), EE_A0B: (_pe, (0, 2, 3)), EE_A1B: (_pe, (1, 2, 3)),
    EE_LINES: (_lines, (0, 1, 2, 3)),
}
"""Each distance type's formula and the stencil corners it takes (point-triangle stencils: the point, then the
triangle; edge-edge: the first edge, then the second)."""


def typed_distance_sq(X: Tensor, kind: int) -> Tensor:
    """The squared distance ``(N,)`` of stencils ``X (N, 4, 3)`` that all have the type ``kind`` (one formula,
    smooth: differentiate it for the derivatives of the distance)."""
    if kind not in _TYPED:
        raise ValueError(f"unknown distance type {kind}")
    formula, corners = _TYPED[kind]
    xs = X.unbind(-2)
    return formula(*(xs[i] for i in corners))


def by_type(X: Tensor, types: Tensor):
    """For each distance type present in ``types (N,)``: ``(kind, sel (N,) bool, squared distances of X[sel])``."""
    for kind in torch.unique(types).tolist():
        sel = types == kind
        yield int(kind), sel, typed_distance_sq(X[sel], int(kind))


def _by_type(X: Tensor, types: Tensor) -> Tensor:
    out = X.new_zeros(X.shape[0])
    for _, sel, D in by_type(X, types):
        out = out.index_put((sel.nonzero()[:, 0],), D)
    return out


def point_triangle_distance_sq(X: Tensor) -> Tensor:
    """Squared point-triangle distances ``(N,)`` of stencils ``X (N, 4, 3)`` (``p, t0, t1, t2``) [m^2]."""
    return _by_type(X, point_triangle_type(X))


def edge_edge_distance_sq(X: Tensor) -> Tensor:
    """Squared segment-segment distances ``(N,)`` of stencils ``X (N, 4, 3)`` (``a0, a1, b0, b1``) [m^2]."""
    return _by_type(X, edge_edge_type(X))


def barrier(D: Tensor, dhat_sq: float, kappa: float) -> Tensor:
    """IPC's barrier on squared distances ``D`` [m^2] (module docstring) [J]; ``inf`` for ``D <= 0``."""
    inside = D < dhat_sq
    Ds = torch.where(inside, D, torch.full_like(D, dhat_sq))
    val = -kappa * (Ds - dhat_sq) ** 2 * torch.log(Ds / dhat_sq)
    val = torch.where(D > 0, val, torch.full_like(D, float("inf")))
    return torch.where(inside, val, torch.zeros_like(D))


def mollifier(X: Tensor, eps_x: Tensor) -> Tensor:
    """The edge-edge mollifier ``(N,)`` of stencils ``X (N, 4, 3)`` with thresholds ``eps_x (N,)`` [m^4]."""
    a0, a1, b0, b1 = X.unbind(-2)
    cr = torch.linalg.cross(a1 - a0, b1 - b0)
    c = _dot(cr, cr)
    r = c / eps_x
    return torch.where(c < eps_x, (2 - r) * r, torch.ones_like(c))
