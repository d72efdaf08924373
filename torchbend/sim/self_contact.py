r"""Self-contact of a cloth: IPC's log barrier on the squared distances of its point-triangle and edge-edge
pairs, as an energy term (:class:`SelfContact`, ``tb.SelfContact``), with a conservative step bound that keeps
every path of a solve free of intersections.

For positions ``x (V, 3)`` the pairs are every vertex against every triangle that does not contain it and
every edge against every edge that shares no vertex with it, closer than ``dhat`` (:func:`candidate_pairs`,
axis-aligned boxes, brute force in chunks).  The energy (:mod:`torchbend.ops.distance`)::

    E = sum_PT b(d^2) + sum_EE m_k b(d^2),      b(D) = -kappa (D - dhat^2)^2 log(D / dhat^2)

Every pair counts: a vertex nearest an edge or a corner counts once for each triangle (and edge) that finds it, as
the IPC toolkit's collision sets weigh such a contact by the number of pairs that find it; the energy is then
continuous where a point crosses above an edge or a vertex (counting such a contact once made it jump there: a pile
of grids twisted by 45 degrees, whose vertices lie above edges by symmetry, stalled Newton's line search).

``kappa`` [J/m^4] is ``stiffness``, or with ``stiffness=None`` chosen from the cloth's weight: the barrier force
``-b'(d^2) 2 d`` at half of ``dhat``, ``4.33 kappa dhat^3``, carries ten mean vertex weights ``m g``
(:meth:`SelfContact.bind`), and then adapted in IPC's way (IPC doubles kappa while a contact closes below 1e-9 of
the scene's bounding-box diagonal; here below ``ADAPT_FRACTION * dhat``): at the start of a time step whose
smallest distance is below ``ADAPT_FRACTION * dhat`` and no larger than at the last step's start, and within a time
step's solve at every accepted iterate whose smallest distance is below ``ADAPT_FRACTION * dhat`` and below
``ADAPT_DECREASE`` times the last iterate's (:meth:`SelfContact.adapt`; the solve then starts its bookkeeping over,
``SolveInfo.adaptations``), and before a stage of a body's move whose advance has so closed in on the cloth
(:func:`~torchbend.implicit_euler_step`), ``kappa`` doubles (at most ``KAPPA_GROWTH`` times the initial one), so
that contacts pressed hard stay at a distance the float arithmetic resolves and the intersection-free steps are not cut short; a
static solve keeps ``kappa`` as it is; ``bind`` (a new model) starts it over.  (A strip folded tightly onto itself,
its tan hinge pressing the layers together with ~1e3 N against a kappa that carries the cloth's weight, converged in
no step with the start-of-step rule alone: its layers were pressed to 1e-7 m.)  The gradient is the autograd of that
sum; the Hessian is the sparse sum of the per-pair ``12 x 12`` Hessians (batched double backward of the pairs' typed
formulas), each projected to PSD (eigenvalues clamped at zero, or their magnitudes) for a projected Newton matrix.

**Step bound** (:meth:`SelfContact.max_step`): along ``x + t dx`` every point of a primitive moves at most as
far as the farthest of its vertices, and a displacement the pair's four vertices share changes no distance, so two
primitives at distance ``d`` whose vertices' displacements less the pair's mean displacement are at most ``m_A``
and ``m_B`` long cannot meet before ``t = d / (m_A + m_B)`` (as additive CCD centres them: a cloth falling onto
itself as a whole is not held back; the displacements' own lengths where theirs is the smaller sum); the bound is
``0.9`` of the smallest such time over
the pairs whose boxes swept along the step come within ``dhat`` (other pairs cannot meet in the step), at most 1.
A pair whose first such advance ends before the bound advances again from the distance it reached, as additive
CCD does, until its distance falls below a tenth of its start or of ``dhat`` (the smaller; at least a floor that the
arithmetic resolves at the pair's coordinates, :data:`_RESOLVABLE`) or the bound is reached (:func:`_advance`):
pairs that slide along each other or part hold the step back no further than their distances fall.
No intersection can appear along a step so bounded (distances stay positive: above a tenth of each advance's
start).

**Friction** (``friction = mu > 0``, time steps only): IPC's lagged smooth Coulomb friction per pair in
contact at the step's start ``x_n`` (:meth:`SelfContact.begin_step`).  A pair's closest points are
``c_A = sum_k w_k x_k`` over side A (the point of a point-triangle pair, the first edge of an edge-edge pair)
and ``c_B`` over side B, with weights from the gradient of the squared distance ``D``: by the envelope
theorem ``dD/dx_k = 2 w_k (c_A - c_B)`` (signed weights, ``+`` on side A, ``-`` on side B), so the lagged
normal is ``n = (sum_A dD/dx_k) / |.|`` and ``w_k = dD/dx_k . n / |sum_A dD/dx_k|``.  The lagged normal force is
``lam = -b'(D) 2 sqrt(D)`` (times the mollifier of an edge-edge pair).  With the relative displacement
``delta = sum_k w_k (x_k - x_k^n)`` of the closest points the pair adds ``mu lam f0(|P delta|)``, ``P = I - n n^T``
(:mod:`torchbend.energies.friction`'s ``f0`` with ``eps = eps_v dt``): Coulomb's ``mu lam`` against the relative
sliding once it is faster than ``eps_v``.  Its gradient is ``w_k`` times the point friction's and its Hessian
``w_k w_l`` times the point friction's ``3 x 3`` block, positive semi-definite (no projection needed).  A body
mesh (:class:`MeshCollider`) moved since the last step moves within the step: its pairs' frames are taken at its
last pose and its vertices' displacement enters ``delta``, so a moving body drags the cloth (a still one holds it
as a collider with ``friction=`` does).
"""
from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from .._checks import nonnegative, positive
from ..backends import native
from ..energies.friction import friction_blocks, friction_energy, friction_gradient
from ..ops.distance import (
    EE_A0B0,
    barrier,
    by_type,
    edge_edge_type,
    mollifier,
    point_triangle_type,
    typed_distance_sq,
)
from ..options import Projection
from .terms import EnergyTerm, StepContext

__all__ = ["SelfContact", "MeshCollider", "box_pairs", "candidate_pairs", "vertex_boxes", "stencil_sum"]


def _box_pairs(lo_a: Tensor, hi_a: Tensor, lo_b: Tensor, hi_b: Tensor, pad: float) -> Tensor:
    """Index pairs ``(K, 2)`` of boxes of A and B that overlap after padding each by ``pad``.

    A uniform grid of cell size ``h`` = the largest box extent plus ``2 pad``: each box of B is filed under
    the cell of its lower corner, and a box of A can only meet boxes filed in the 27 cells around its own
    lower corner's (their lower corners lie within ``h`` of it on every axis); the candidates of those cells
    (sorted cell keys, ranges by ``searchsorted``) are then tested exactly.  Cost: the boxes and the pairs."""
    device = lo_a.device
    if lo_a.shape[0] == 0 or lo_b.shape[0] == 0:
        return torch.zeros((0, 2), dtype=torch.int64, device=device)
    ext = torch.maximum((hi_a - lo_a).amax(), (hi_b - lo_b).amax())
    h = float(ext) + 2 * pad
    h = h if h > 0 else 1.0
    origin = torch.minimum(lo_a.amin(0), lo_b.amin(0))
    ca = torch.floor((lo_a - origin) / h).to(torch.int64)
    cb = torch.floor((lo_b - origin) / h).to(torch.int64)
    span = int(torch.maximum(ca.amax(), cb.amax())) + 3  # keys of the cells (and their neighbours) are unique

    def key(c: Tensor) -> Tensor:
        return ((c[..., 0] + 1) * span + (c[..., 1] + 1)) * span + (c[..., 2] + 1)

    kb = key(cb)
    kb_sorted, order = torch.sort(kb)
    off = torch.stack(torch.meshgrid(*(torch.arange(-1, 2, device=device),) * 3, indexing="ij"), -1).reshape(27, 3)
    q = key(ca[:, None, :] + off[None])  # (A, 27)
    left = torch.searchsorted(kb_sorted, q, right=False)
    right = torch.searchsorted(kb_sorted, q, right=True)
    count = (right - left).reshape(-1)
    total = int(count.sum())
    if total == 0:
        return torch.zeros((0, 2), dtype=torch.int64, device=device)
    ia = torch.arange(lo_a.shape[0], device=device).repeat_interleave(27).repeat_interleave(count)
    start = left.reshape(-1).repeat_interleave(count)
    within = torch.arange(total, device=device) - (torch.cumsum(count, 0) - count).repeat_interleave(count)
    ib = order[start + within]
    hit = ((lo_a[ia] <= hi_b[ib] + 2 * pad) & (hi_a[ia] + 2 * pad >= lo_b[ib])).all(-1)
    return torch.stack([ia[hit], ib[hit]], 1)


def _native_ok(t: Tensor) -> bool:
    """Whether the compiled contact operators take ``t`` (a CPU float32/float64 tensor, the extension built)."""
    return t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) and native.load() is not None


def box_pairs(lo_a: Tensor, hi_a: Tensor, lo_b: Tensor, hi_b: Tensor, pad: float, upper: bool = False,
              ids_a: Tensor | None = None, ids_b: Tensor | None = None) -> Tensor:
    """Index pairs ``(K, 2)`` of boxes of A and B that overlap after padding each by ``pad``; ``upper`` (A = B):
    each pair once (``a < b``); ``ids_a (Na, ka)``, ``ids_b (Nb, kb)``: leave out the pairs whose rows share a value
    (primitives with a common vertex).  Compiled on the CPU (a uniform grid, its cells in a table or hashed: cost flat per
    box and per pair), else :func:`_box_pairs` and the filters in torch."""
    if _native_ok(lo_a):
        return native.contact_box_pairs(lo_a, hi_a, lo_b, hi_b, pad, upper, ids_a, ids_b)
    p = _box_pairs(lo_a, hi_a, lo_b, hi_b, pad)
    if upper:
        p = p[p[:, 0] < p[:, 1]]
    if ids_a is not None and ids_b is not None and p.shape[0]:
        p = p[(ids_a[p[:, 0]][:, :, None] != ids_b[p[:, 1]][:, None, :]).all(-1).all(-1)]
    return p


def candidate_pairs(x: Tensor, faces: Tensor, edges: Tensor, radius: float, dx: Tensor | None = None,
                    slack: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Point-triangle stencils ``(P, 4)`` (vertex, face's three), edge-edge stencils ``(Q, 4)`` (each edge pair
    once) and their edge indices ``(Q, 2)``, of the primitives whose boxes lie within ``radius`` [m], without
    the pairs that share a vertex.  With ``dx (V, 3)``: the boxes swept along ``x + t dx``, ``t`` in ``[0, 1]``
    (every pair that comes within ``radius`` on the way); ``slack`` [m] widens every vertex's box."""
    return _box_candidates(*vertex_boxes(x, dx, slack), faces, edges, radius)


def vertex_boxes(x: Tensor, dx: Tensor | None = None, slack: float = 0.0) -> tuple[Tensor, Tensor]:
    """Each vertex's box ``(lo, hi)``, each ``(V, 3)``: around ``x``, or swept along ``x + t dx`` (``t`` in
    ``[0, 1]``), widened by ``slack`` on every side."""
    x = x.detach()
    end = x if dx is None else x + dx.detach()
    return torch.minimum(x, end) - slack, torch.maximum(x, end) + slack


def _box_candidates(lo: Tensor, hi: Tensor, faces: Tensor, edges: Tensor, radius: float):
    """:func:`candidate_pairs` over the vertices' boxes ``lo``, ``hi`` (a primitive's box holds its vertices')."""
    if _native_ok(lo):
        return native.contact_candidates(lo, hi, faces, edges, radius)
    idx = torch.arange(lo.shape[0], device=lo.device)
    pt = box_pairs(lo, hi, lo[faces].amin(1), hi[faces].amax(1), 0.5 * radius, ids_a=idx[:, None], ids_b=faces)
    pt = torch.cat([pt[:, :1], faces[pt[:, 1]]], 1)
    elo, ehi = lo[edges].amin(1), hi[edges].amax(1)
    ee = box_pairs(elo, ehi, elo, ehi, 0.5 * radius, upper=True, ids_a=edges, ids_b=edges)
    return pt, torch.cat([edges[ee[:, 0]], edges[ee[:, 1]]], 1), ee


def _covers(cache: tuple | None, xa: Tensor, end: Tensor | None, radius: float) -> bool:
    """Whether the kept candidates ``cache`` (:meth:`_ContactPairs._active`'s: boxes ``lo``, ``hi``, their
    radius and slack, ...) serve the points ``xa``, and the step's ends ``end`` (given for a step bound): every
    point in its box, and a step's boxes not far smaller than the kept ones."""
    if cache is None or cache[0].shape != xa.shape or cache[0].device != xa.device or cache[0].dtype != xa.dtype \
            or cache[2] < radius:
        return False
    lo, hi = cache[0], cache[1]
    if not bool(((xa >= lo) & (xa <= hi)).all()):
        return False
    if end is None:
        return True
    return bool(((end >= lo) & (end <= hi)).all()) and \
        float((hi - lo).amax()) <= 2 * float((end - xa).abs().amax()) + 4 * cache[3]


def segments_cross_triangles(p0: Tensor, p1: Tensor, t0: Tensor, t1: Tensor, t2: Tensor) -> Tensor:
    """``(N,)``: whether each segment ``p0 p1`` passes through the interior of its triangle ``t0 t1 t2`` (Moller and
    Trumbore's test in float64, strict: the crossing point at least ``1e-12`` of the triangle's barycentric range
    and of the segment from their boundaries, the segment at least ``1e-12`` rad from the triangle's plane), so that
    rounding never reports a contact as a crossing; a segment through a triangle's edge crosses its neighbour or
    lies at distance 0 from that edge (what the distance check refuses)."""
    p0, p1, t0, t1, t2 = (t.double() for t in (p0, p1, t0, t1, t2))
    e1, e2, d = t1 - t0, t2 - t0, p1 - p0
    h = torch.linalg.cross(d, e2)
    a = (e1 * h).sum(-1)
    ok = a.abs() > 1e-12 * d.norm(dim=-1) * e1.norm(dim=-1) * e2.norm(dim=-1)
    f = 1.0 / torch.where(ok, a, torch.ones_like(a))
    r = p0 - t0
    u = f * (r * h).sum(-1)
    q = torch.linalg.cross(r, e1)
    v = f * (d * q).sum(-1)
    t = f * (e2 * q).sum(-1)
    m = 1e-12
    return ok & (u > m) & (v > m) & (u + v < 1 - m) & (t > m) & (t < 1 - m)


def mesh_crossing_pairs(faces: Tensor, edges: Tensor, pts: Tensor) -> tuple[Tensor, Tensor]:
    """``(edges (K, 2), triangles (K, 3))``: a mesh's edge-triangle pairs without a shared vertex whose boxes
    overlap over the points ``pts`` (every pair that may cross)."""
    faces, edges = faces.to(pts.device), edges.to(pts.device)
    p = box_pairs(pts[edges].amin(1), pts[edges].amax(1), pts[faces].amin(1), pts[faces].amax(1), 0.0,
                  ids_a=edges, ids_b=faces)
    return edges[p[:, 0]], faces[p[:, 1]]


def first_crossing(pts: Tensor, e: Tensor, f: Tensor) -> tuple[list[int], list[int]] | None:
    """The first of the edges ``e (K, 2)`` that passes through its triangle ``f (K, 3)`` over the points ``pts``
    (:func:`segments_cross_triangles`), as ``(edge, triangle)`` vertex lists, or None."""
    if e.shape[0] == 0:
        return None
    hit = segments_cross_triangles(pts[e[:, 0]], pts[e[:, 1]], pts[f[:, 0]], pts[f[:, 1]], pts[f[:, 2]])
    if not bool(hit.any()):
        return None
    k = int(hit.nonzero()[0, 0])
    return e[k].tolist(), f[k].tolist()


def _distances(xa: Tensor, st: Tensor, edge_edge: bool) -> tuple[Tensor, Tensor]:
    """``(types (N,), squared distances (N,))`` of point-triangle or edge-edge stencils ``st (N, 4)`` over the
    points ``xa`` (compiled on the CPU; else :mod:`torchbend.ops.distance`)."""
    if _native_ok(xa):
        return native.contact_distances(xa.detach(), st, edge_edge)
    X = xa.detach()[st]
    types = edge_edge_type(X) if edge_edge else point_triangle_type(X)
    D = X.new_empty(st.shape[0])
    for _, sel, d in by_type(X, types):
        D[sel] = d
    return types, D


class _ContactPairs:
    """The pairs of non-adjacent primitives of a mesh (the cloth's own, with a body's for :class:`MeshCollider`)
    within a distance: the broad phase (:func:`candidate_pairs`, reused while the points stay in their boxes), the
    pairs within ``dhat`` grouped by distance type, the conservative step bound and the smallest distance (module
    docstring).  The geometry of :class:`SelfContact`; ``bind`` sets the mesh."""

    dhat: float
    name: str
    faces: Tensor | None
    edges: Tensor | None
    _rest_len_sq: Tensor | None
    _cache: tuple | None
    _close_cache: tuple | None
    _V: int

    def _mesh(self) -> tuple[Tensor, Tensor]:
        if self.faces is None or self.edges is None:
            raise ValueError("SelfContact: the term has no mesh: give it to a ClothModel (terms=[...]) first")
        return self.faces, self.edges

    def _points(self, x: Tensor) -> Tensor:
        """The positions the pairs index: the cloth's ``x`` (a body collider appends its own vertices)."""
        return x

    def _points_require_grad(self) -> bool:
        """Whether positions other than the cloth's (a body's vertices) require grad."""
        return False

    def _candidates(self, lo: Tensor, hi: Tensor, radius: float) -> tuple[Tensor, Tensor, Tensor]:
        """Point-triangle and edge-edge stencils whose boxes (over the boxes ``lo``, ``hi`` of :meth:`_points`) lie
        within ``radius``, and the edge pairs' indices into the rest lengths (:func:`candidate_pairs` over the
        cloth's own mesh)."""
        faces, edges = self._mesh()
        return _box_candidates(lo, hi, faces.to(lo.device), edges.to(lo.device), radius)

    def _active(self, x: Tensor, dx: Tensor | None = None, radius: float | None = None):
        """The candidate pairs within ``radius`` (default ``dhat``) of ``x``, or of any point along ``x + t dx``
        (``t`` in ``[0, 1]``: the step bound's), and the edge pairs' mollifier thresholds.  Found over the points'
        boxes (swept along ``dx``, widened by a twentieth of ``dhat``), they serve every later ``x`` whose points
        all lie in their boxes (a body's vertices count as points too): a line search and the next iterate reuse
        the step's.  A step whose boxes are far smaller than the kept ones searches afresh."""
        r_need, c, xa = self.dhat if radius is None else radius, self._cache, self._points(x).detach()
        end = xa if dx is None else xa + torch.cat([dx.detach(), dx.new_zeros(xa.shape[0] - dx.shape[0], 3)]).to(xa)
        if c is not None and _covers(c, xa, None if dx is None else end, r_need):
            return c[4], c[5], c[6]
        slack = 0.05 * self.dhat
        lo, hi = torch.minimum(xa, end) - slack, torch.maximum(xa, end) + slack
        pt, ee, pairs = self._candidates(lo, hi, r_need)
        assert self._rest_len_sq is not None
        r = self._rest_len_sq.to(device=x.device, dtype=x.dtype)
        eps = 1e-3 * r[pairs[:, 0]] * r[pairs[:, 1]]  # the mollifier thresholds of the edge pairs
        self._cache = (lo, hi, r_need, slack, pt, ee, eps)
        return pt, ee, eps

    def _crossing_pairs(self, pts: Tensor) -> tuple[Tensor, Tensor]:
        return mesh_crossing_pairs(*self._mesh(), pts)

    def crossing(self, x: Tensor) -> tuple[list[int], list[int]] | None:
        """The first edge and triangle through each other at ``x`` (:meth:`_points` indices), or None."""
        pts = self._points(x).detach()
        return first_crossing(pts, *self._crossing_pairs(pts))

    def _close(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(stencils (N, 4), types (N,), eps_x (N,))``: the point-triangle pairs (``eps_x = 0``) then the
        edge-edge pairs (with their mollifier thresholds) closer than ``dhat`` at ``x``, every pair (module
        docstring: a contact found by several triangles counts for each).  The last ``x``'s are kept: a Newton
        iteration asks for the energy, the gradient and the Hessian at one ``x``."""
        xa = self._points(x).detach()  # a body's vertices too: a body may move between steps
        c = self._close_cache
        if c is not None and c[0].shape == xa.shape and c[0].dtype == xa.dtype and c[0].device == xa.device \
                and c[1] is self._cache and bool(torch.equal(c[0], xa)):
            return c[2]
        pt, ee, eps = self._active(x)
        dh2 = self.dhat ** 2
        parts = []
        for st, edge_edge, thresholds in ((pt, False, None), (ee, True, eps)):
            if not st.shape[0]:
                continue
            if _native_ok(xa):
                keep, types = native.contact_close(xa, st, edge_edge, dh2)
                st = st[keep]
            else:
                types, D = _distances(xa, st, edge_edge)
                keep = D < dh2
                st, types = st[keep], types[keep]
            if edge_edge:
                assert thresholds is not None
                parts.append((st, types, thresholds[keep].to(xa.dtype)))
            else:
                parts.append((st, types, xa.new_zeros(st.shape[0])))
        if parts:
            out = (torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts]), torch.cat([p[2] for p in parts]))
        else:
            out = (torch.zeros(0, 4, dtype=torch.int64, device=xa.device),
                   torch.zeros(0, dtype=torch.int64, device=xa.device), xa.new_zeros(0))
        self._close_cache = (xa.clone(), self._cache, out)
        return out

    def _groups(self, x: Tensor):
        """``[(stencils (N, 4), kind, eps_x or None)]`` of the pairs within ``dhat``, grouped by distance type
        (``eps_x`` None for point-triangle pairs)."""
        st, types, eps = self._close(x)
        out = []
        for kind in torch.unique(types).tolist():
            sel = types == kind
            out.append((st[sel], int(kind), None if kind < EE_A0B0 else eps[sel]))
        return out

    def max_step(self, x: Tensor, dx: Tensor, ctx: StepContext) -> float:
        return _path_bound(self, x, dx)

    def min_distance(self, x: Tensor, radius: float | None = None) -> tuple[float, int]:
        """(the smallest distance [m] between non-adjacent primitives within ``radius`` (default ``dhat``), or
        ``inf``; the number of pairs closer than ``dhat``)."""
        pt, ee, _ = self._active(x, radius=radius)
        best = _smallest_distance(self._points(x).detach(), ((pt, False), (ee, True)))
        count = int(self._close(x)[0].shape[0]) if best < self.dhat else 0
        return best, count

    def contact_stats(self, x: Tensor) -> tuple[float, int]:
        return _widened_min_distance(self, x) if self.faces is not None else (math.inf, 0)

    def inadmissible(self, x: Tensor) -> str:  # touching primitives, or an edge through a triangle
        return _self_inadmissible(self, x) if self.faces is not None else ""


def _path_bound(term: _ContactPairs, x: Tensor, dx: Tensor) -> float:
    """The step bound of ``term``'s pairs (module docstring) along ``dx``: the cloth's ``(V, 3)`` (a body is still
    during a step) or every point's (``term._points``: a body's move, the cloth still)."""
    dx = dx.detach()
    m = float(dx.abs().max()) if dx.numel() else 0.0
    if m == 0:
        return 1.0
    pt, ee, _ = term._active(x, dx)
    xa = term._points(x).detach()
    dx = torch.cat([dx, dx.new_zeros(xa.shape[0] - dx.shape[0], 3)]).to(xa.dtype)
    alpha = 1.0
    for st in (pt, ee):
        if not st.shape[0]:
            continue
        if _native_ok(xa):  # compiled: the same advancement
            alpha = min(alpha, native.contact_step_bound(xa, st, st is ee, dx, term.dhat))
        else:
            alpha = min(alpha, _advance(xa[st], dx[st], st is ee, alpha, term.dhat))
    return max(alpha, 0.0)


_MAX_ADVANCES = 64
"""Advances of :func:`_advance` per pair and step bound at most (the bound reached so far is kept: still safe)."""
_RESOLVABLE, _ROUNDING = 1024.0, 64.0
"""A pair advances past its first advance only where a tenth of its start (or of ``dhat``) is at least ``_RESOLVABLE``
double epsilons of its corners' scale (the distances along the step, measured in double whatever the dtype, are within
a small part of it); its floor (below which it advances no further) is that tenth and at least ``_ROUNDING``
epsilons of the positions' dtype (the bound keeps every pair at a tenth of its floor at least, 6.4 epsilons of the
scale, and rounding the step's end ``x + alpha dx`` to the dtype moves a pair's distance by at most 2 sqrt(3), about
3.5, of them; in float64 the first bound is the larger, and the floor is the tenth): the compiled
``contact_step_bound``'s ``kResolvable`` and ``kRounding``.  (The dtype's own 1024 epsilons held float32 pairs nearer
than ~2e-4 m at 0.2 m coordinates to their first advance: a float32 cloth sliding onto a sphere mesh at 8 m/s took
steps of 0.008 for 60 iterations and did not converge.  A float32 pair whose tenth of its start was under that floor
kept its first advance alone, where it now advances down to the floor: a float32 3 m cloth falling at 8 m/s onto a
1 m sphere mesh, its pairs 1e-5..1e-4 m apart at 1.5 m coordinates, took Newton steps of 0.014 for 300 iterations
and failed its first step.)"""


def _smallest_distance(xa: Tensor, groups) -> float:
    """The smallest distance [m] of the stencil groups ``[(stencils (N, 4), edge_edge)]`` over the points ``xa``,
    or ``inf`` where they are empty."""
    best = math.inf
    for st, edge_edge in groups:
        if st.shape[0]:
            best = min(best, float(_distances(xa, st, edge_edge)[1].min().clamp_min(0).sqrt()))
    return best


def _stencil_distances(X: Tensor, edge_edge: bool) -> Tensor:
    """The distances ``(N,)`` of the point-triangle or edge-edge stencils whose corners are ``X (N, 4, 3)``."""
    st = torch.arange(4 * X.shape[0], device=X.device).reshape(-1, 4)
    return _distances(X.reshape(-1, 3), st, edge_edge)[1].clamp_min(0).sqrt()


def _advance(X: Tensor, P: Tensor, edge_edge: bool, cap: float, dhat: float) -> float:
    """The step bound (module docstring) of the pairs with corners ``X (N, 4, 3)`` moving by ``P (N, 4, 3)`` along
    a step, at most ``cap``, by conservative advancement (additive CCD): a pair at distance ``d`` whose distance
    changes at most at the rate ``r`` (its corners' displacements as in the module docstring) advances by
    ``0.9 d / r`` (taken whole: the single bound) and again from the distance reached there, while its distance
    stays above a tenth of its start or of ``dhat``, the smaller (its time: the last one reached), up to the step's
    end (1); at most ``_MAX_ADVANCES`` advances.  The bound is the smallest pair time (``cap`` at most): a pair
    whose time passes the smallest one found stops advancing, which changes no result (the compiled
    ``contact_step_bound`` runs the same algorithm; the two agree to the rounding of their distance formulas).
    Along each advance the distance stays above a tenth of its value at the advance's start: no path so bounded
    meets.  A first advance alone (the single bound ``0.9 d / r``) holds
    back pairs that slide or part, whose distance does not fall: a fold whose hinges push its layers apart took
    ~1e-3 of each Newton step."""
    k = 2 if edge_edge else 1
    measured = _RESOLVABLE * torch.finfo(torch.float64).eps  # of the scale: what the distances in double resolve
    rounding = _ROUNDING * torch.finfo(X.dtype).eps  # of the scale: what rounding the step's end to the dtype moves
    scale = X.abs().amax((1, 2)).double() + P.abs().amax((1, 2)).double()
    X, P = X.double(), P.double()  # every distance in double, as the compiled bound's
    d = _stencil_distances(X, edge_edge)
    rel = P - 0.25 * (P[:, 0] + P[:, 1] + P[:, 2] + P[:, 3])[:, None]  # a move the four corners share changes no distance
    mv, ln = rel.norm(dim=-1), P.norm(dim=-1)
    rate = torch.minimum(mv[:, :k].amax(1) + mv[:, k:].amax(1), ln[:, :k].amax(1) + ln[:, k:].amax(1))
    step = 0.9 * d / rate.clamp_min(torch.finfo(d.dtype).tiny)
    bind = (rate > 0) & (step < cap)  # a pair's time is at least its first advance: the others cannot bind
    if not bool(bind.any()):
        return cap
    X, P, rate, t, scale = X[bind], P[bind], rate[bind], step[bind], scale[bind]
    # only where a tenth of the start (or of dhat) is at least `measured` of the corners' scale (their largest
    # coordinate plus their largest displacement component): the distances measured along the step are a small part
    # of it (a pair 1e-16 m apart at coordinates of 1 m keeps its first advance alone); the floor is that tenth and
    # at least `rounding` of the scale, so that the rounding of the step's end is less than the floor's tenth
    tenth = 0.1 * d[bind].clamp_max(dhat)
    floor = torch.maximum(tenth, rounding * scale)
    dn = _stencil_distances(X + t[:, None, None] * P, edge_edge)
    live = (dn >= floor) & (tenth >= measured * scale)
    best = cap  # the smallest time of the pairs that stopped
    for _ in range(_MAX_ADVANCES - 1):
        if bool((~live).any()):
            best = min(best, float(t[~live].min()))
        live &= t < best  # a pair past the smallest time cannot lower it
        if not bool(live.any()):
            break
        tn = t + 0.9 * dn / rate
        end = live & (tn >= 1.0)
        t = torch.where(end, torch.ones_like(t), t)
        live &= ~end
        dn_next = _stencil_distances(X + tn[:, None, None] * P, edge_edge)
        moved = live & (dn_next >= floor)
        t = torch.where(moved, tn, t)
        dn = torch.where(moved, dn_next, dn)
        live = moved
    return min(cap, float(t.min()))


def _check_same_mesh(term: _ContactPairs, faces: Tensor, V: int) -> None:
    """A ``ValueError`` if ``term`` is bound to a mesh other than ``faces`` over ``V`` vertices."""
    if term.faces is not None and (term._V != V or term.faces.shape != faces.shape
                                   or not torch.equal(term.faces.cpu(), faces.cpu())):
        who = type(term).__name__
        raise ValueError(f"{who} {term.name!r} is already part of a model of another mesh ({term._V} vertices, "
                         f"{term.faces.shape[0]} faces; this one has {V} and {faces.shape[0]}): give each model its "
                         f"own {who}")


def _widened_min_distance(term: _ContactPairs, x: Tensor) -> tuple[float, int]:
    """``(the smallest distance between non-adjacent primitives if it is within 64 dhat, else inf; the pairs
    closer than dhat)`` (:class:`~torchbend.SolveInfo`'s ``min_distance``, ``contact_count``).  With no pair within
    ``dhat`` the search widens fourfold, up to 64 ``dhat``, until it finds one: the value is exact wherever it is
    finite (every pair within the radius is a candidate).  The wider searches keep the solver's candidates."""
    d, count = term.min_distance(x)
    if d <= term.dhat:
        return d, count
    kept, radius = term._cache, term.dhat
    try:
        while d > radius and radius < 64 * term.dhat:
            radius *= 4
            d = term.min_distance(x, radius=radius)[0]
    finally:
        term._cache = kept
    return (d if d <= radius else math.inf), count


def _batched_hessians(energy, X: Tensor) -> Tensor:
    """``(N, 12, 12)`` Hessians of independent pairs' energies ``energy(Z) (N,)`` at ``X (N, 12)``: row ``j`` of
    every pair's Hessian is one batched backward of the ``j``-th gradient component summed over the pairs."""
    with torch.enable_grad():
        Z = X.detach().requires_grad_(True)
        (g,) = torch.autograd.grad(energy(Z).sum(), Z, create_graph=True)
        rows = [torch.autograd.grad(g[:, j].sum(), Z, retain_graph=j < 11, allow_unused=True)[0] for j in range(12)]
    return torch.stack([torch.zeros_like(Z) if r is None else r for r in rows], 1)


def _grow(term: SelfContact, d: float, last: float) -> bool:
    """Double an adaptive ``kappa`` (to at most ``KAPPA_GROWTH`` times its first) where the smallest distance ``d``
    [m] is below ``ADAPT_FRACTION * dhat`` and not above ``last``: True when it changed."""
    if term._kappa0 is None or term.stiffness is None or not (d < term.ADAPT_FRACTION * term.dhat and d <= last):
        return False
    grown = min(2 * term.stiffness, term.KAPPA_GROWTH * term._kappa0)
    changed, term.stiffness = grown > term.stiffness, grown
    return changed


def _kappa_state(self) -> tuple:
    """An adaptive ``kappa``'s state (the term's ``pose``): a time step solved again (a retry, its halves) starts
    from the state of the step's start, or the same start would double ``kappa`` once more."""
    return self.stiffness, self._last_min, self._solve_min


def _restore_kappa_state(self, pose: tuple) -> None:
    self.stiffness, self._last_min, self._solve_min = pose


def _closest(term: _ContactPairs, x: Tensor) -> float:
    """The smallest distance [m] of the pairs closer than ``dhat`` at ``x`` (those of the energy), or ``inf``."""
    st, types, _ = term._close(x)
    ee = types >= EE_A0B0
    return _smallest_distance(term._points(x).detach(), ((st[~ee], False), (st[ee], True)))


RESOLUTION = _ROUNDING
"""``dhat`` must span at least this many epsilons of the positions' dtype at their largest coordinate (the cloth's
and a body's), the step bound's rounding floor: below that the dtype cannot hold contacts apart (rounding a step's
end moves a distance by up to 3.5 of them, and the step bound advances a pair only above ``_ROUNDING`` of them).  Float32 at 1 km resolves 6e-5 m:
``dhat`` = 1 mm is 16 epsilons there, and a pile of sheets dropped onto a floor 1 km from the origin ended its
second step intersecting; float32 keeps ``dhat`` = 1 mm out to about 130 m."""


def _unresolved(term: _ContactPairs, x: Tensor) -> str:
    """Why ``term``'s ``dhat`` is too small for ``x``'s dtype at the scene's coordinates (:data:`RESOLUTION`), or ""."""
    pts = term._points(x).detach()
    scale = float(pts.abs().max()) if pts.numel() else 0.0
    floor = RESOLUTION * torch.finfo(x.dtype).eps * scale
    if term.dhat >= floor:
        return ""
    return (f"{term.name}: dhat = {term.dhat:.3g} m is below what {str(x.dtype).replace('torch.', '')} resolves at "
            f"these coordinates ({RESOLUTION:g} epsilons of the largest coordinate, {scale:.3g} m: {floor:.3g} m): "
            "move the scene near the origin, use float64 or a larger dhat")


def _self_inadmissible(term: _ContactPairs, x: Tensor) -> str:
    """Why a solve cannot start at ``x``: ``dhat`` below the dtype's resolution there, two primitives of the cloth
    touch, or an edge passes through a triangle."""
    unresolved = _unresolved(term, x)
    if unresolved:
        return unresolved
    d, _ = term.min_distance(x)
    if d <= 0:
        return f"{term.name}: two non-adjacent primitives of the cloth touch (distance {d:.3g} m): start apart"
    cross = term.crossing(x)
    if cross is not None:
        return (f"{term.name}: the cloth passes through itself: edge {tuple(cross[0])} crosses triangle "
                f"{tuple(cross[1])} (vertex indices): start from a state without intersections")
    return ""


class _LaggedFriction(_ContactPairs):
    """IPC's lagged friction of the contact pairs in a time step (module docstring): the pairs' frames at the
    step's start, the slip since, the friction's gradient and PSD blocks."""

    stiffness: float | None
    friction: float
    eps_v: float

    def _pair_frames(self, X: Tensor, kind: int, eps: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """``(w (N, 4), n (N, 3), lam (N,))``: the closest points' signed weights, the unit normal from side B to
        side A and the normal force magnitude [N] of stencils ``X (N, 4, 3)`` of one type (``eps``: the edge
        pairs' mollifier thresholds, None for point-triangle pairs)."""
        assert self.stiffness is not None
        with torch.enable_grad():
            Z = X.detach().requires_grad_(True)
            D = typed_distance_sq(Z, kind)
            (g,) = torch.autograd.grad(D.sum(), Z)
            Dd = D.detach().requires_grad_(True)
            (db,) = torch.autograd.grad(barrier(Dd, self.dhat ** 2, self.stiffness).sum(), Dd)
        D = D.detach()
        two_gap = g[:, :1].sum(1) if eps is None else g[:, :2].sum(1)  # 2 (c_A - c_B): side A's weights sum to 1
        size = two_gap.norm(dim=-1).clamp_min(torch.finfo(X.dtype).tiny)
        n = two_gap / size[:, None]
        w = (g * n[:, None, :]).sum(-1) / size[:, None]
        lam = (-db * 2 * D.clamp_min(0).sqrt()).clamp_min(0)
        if eps is not None:
            lam = lam * mollifier(X.detach(), eps)
        return w, n, lam

    def _compiled(self, x: Tensor) -> bool:
        """Whether the compiled pair kernels serve ``x``: a CPU float tensor, no graph to keep (neither ``x`` nor a
        body's vertices require grad while grad is enabled)."""
        graph = torch.is_grad_enabled() and (x.requires_grad or self._points_require_grad())
        return not graph and x.ndim == 2 and _native_ok(x)

    def _pair_terms(self, x: Tensor, want: int, projection: str = "none") -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(stencils (N, 4), E (N,), g (N, 12), H (N, 12, 12))`` of the pairs within ``dhat`` by the compiled
        kernels (:func:`torchbend.backends.native.contact_barrier`)."""
        st, types, eps = self._close(x)  # (a term without a mesh says so here)
        assert self.stiffness is not None
        return (st, *native.contact_barrier(self._points(x).detach(), st, types, eps, self.dhat ** 2, self.stiffness,
                                            want, projection))

    def _lag_friction(self, ctx: StepContext) -> None:
        """Store the friction pairs of the step's start ``ctx.x_prev`` (those pushing, ``lam > 0``) in
        ``ctx.lagged[name]``: stencils, closest-point weights, normals, ``mu lam`` and ``eps = eps_v dt``."""
        assert ctx.x_prev is not None and ctx.dt is not None
        x_prev = ctx.x_prev.detach()
        xa = self._points(x_prev).detach()
        parts = []
        for st, kind, eps in self._groups(x_prev):
            w, n, lam = self._pair_frames(xa[st], kind, eps)
            keep = lam > 0
            if bool(keep.any()):
                parts.append((st[keep], w[keep], n[keep], lam[keep]))
        if not parts:
            return
        st, w, n, lam = (torch.cat(p) for p in zip(*parts))
        ctx.lagged[self.name] = {"stencils": st, "w": w, "n": n, "weight": self.friction * lam, "x_prev": xa,
                                 "eps": self.eps_v * ctx.dt}

    def _slip(self, x: Tensor, ctx: StepContext | None):
        """``(lagged data, delta (M, 3))``: the pairs' relative displacements since the step's start, or None."""
        f = ctx.lagged.get(self.name) if ctx is not None else None
        if f is None or x.ndim != 2:
            return None
        st = f["stencils"]
        xa = self._points(x)
        delta = (f["w"][:, :, None] * (xa[st] - f["x_prev"][st].to(xa.dtype))).sum(1)
        return f, delta

    def _friction_force(self, x: Tensor, ctx: StepContext, like: Tensor) -> Tensor | None:
        """The friction's gradient ``(V, 3)`` (in ``like``'s dtype) at ``x`` in the step ``ctx``, or None."""
        s = self._slip(x.detach(), ctx)
        if s is None:
            return None
        f, delta = s
        gd = friction_gradient(delta, torch.zeros_like(delta), f["n"], f["weight"], f["eps"])
        out = like.new_zeros(self._points(x).shape[0], 3)
        out.index_add_(0, f["stencils"].reshape(-1),
                       (f["w"][:, :, None] * gd[:, None, :]).reshape(-1, 3).to(like.dtype))
        return out[:x.shape[0]]

    def _friction_blocks(self, x: Tensor, ctx: StepContext | None) -> tuple[Tensor, Tensor, Tensor] | None:
        """``(stencils (M, 4), w (M, 4), H (M, 3, 3))`` of the friction pairs: a pair's 12x12 Hessian is
        ``w_k w_l H`` (its closest-point weights ``w`` and its point block ``H``)."""
        s = self._slip(x.detach(), ctx)
        if s is None:
            return None
        f, delta = s
        slip = ctx.friction_slip if ctx is not None else 0.0
        H3 = friction_blocks(delta, torch.zeros_like(delta), f["n"], f["weight"], f["eps"], slip)
        return f["stencils"], f["w"].to(H3.dtype), H3


WEAK_FRACTION = 1e-3
"""A given ``stiffness`` below this fraction of the one ``stiffness=None`` would choose is warned about (the four
9x9 sheets of configs/pile.yaml with ``stiffness`` 1e3, 2e-4 of the choice: 6 of 40 steps did not converge, their
contacts pressed to 2.5e-6 m; with 1e5, 2e-2 of it: every step converged)."""


def _weight_kappa(mass: Tensor, dhat: float) -> float:
    """The ``kappa`` whose barrier force at ``dhat / 2`` carries ten mean vertex weights (``mass (V,)`` [kg]):
    ``-b'(D) 2 d`` at ``d = dhat / 2`` is ``4.33 kappa dhat^3`` (``D = d^2``)."""
    weight = 9.81 * float(mass.mean()) if mass.numel() else 1.0
    return 10 * weight / (4.33 * dhat ** 3)


def _friction_stencil_blocks(w: Tensor, H: Tensor) -> Tensor:
    """The 12x12 blocks ``w_k w_l H`` of friction pairs (closest-point weights ``w (M, 4)``, point blocks ``H (M, 3,
    3)``)."""
    return (w[:, :, None, None, None] * w[:, None, None, :, None] * H[:, None, :, None, :]).reshape(-1, 12, 12)


def _warn_weak(name: str, stiffness: float, chosen: float, dhat: float) -> None:
    warnings.warn(f"{name}: stiffness {stiffness:.3g} J/m^4 is {chosen / stiffness:.3g} times below the {chosen:.3g} "
                  f"J/m^4 whose barrier carries ten mean vertex weights at dhat / 2: contacts are pressed to a small "
                  f"fraction of dhat ({dhat:g} m), where the intersection-free steps are short and Newton may not "
                  "converge; stiffness=None chooses kappa from the cloth's weight and adapts it", UserWarning,
                  stacklevel=4)


class SelfContact(_LaggedFriction, EnergyTerm):
    """IPC's barrier between the cloth's own non-adjacent primitives (module docstring).

    Args:
        dhat: the activation distance [m] (> 0): pairs closer than this repel.
        stiffness: ``kappa`` [J/m^4] of the barrier on squared distances, or None: chosen from the cloth's
            weight when the term joins a :class:`~torchbend.ClothModel`.
        friction: Coulomb's ``mu`` (>= 0) between the layers in time steps (module docstring); 0: none.
        eps_v: the sliding speed [m/s] (> 0) below which the friction is smoothed (static-like).
    """

    contact, confines = True, False

    def __init__(self, dhat: float = 1e-3, stiffness: float | None = None, friction: float = 0.0,
                 eps_v: float = 1e-3, name: str = "self_contact"):
        who = type(self).__name__
        self.dhat = positive(dhat, f"{who}: dhat")
        self.stiffness = None if stiffness is None else positive(stiffness, f"{who}: stiffness")
        self._auto = stiffness is None  # chosen per model by bind
        self.friction = nonnegative(friction, f"{who}: friction")
        self.eps_v = positive(eps_v, f"{who}: eps_v")
        self.name = name
        self.faces: Tensor | None = None
        self.edges: Tensor | None = None
        self._rest_len_sq: Tensor | None = None
        self._cache: tuple | None = None  # (boxes lo, hi, radius, slack, pairs...) of _active
        self._close_cache: tuple | None = None  # (points, _cache, the pairs within dhat) of the last x (_close)
        self._V, self._kappa0 = 0, None  # the chosen initial kappa (stiffness=None), the last distances (_grow)
        self._last_min = self._solve_min = math.inf

    ADAPT_FRACTION = 0.1
    """A distance below this fraction of ``dhat`` (a step's start, a solve's iterate) doubles an adaptive ``kappa``."""
    ADAPT_DECREASE = 0.99
    """Within a solve, an iterate doubles ``kappa`` only if closer than this fraction of the last one's distance."""
    KAPPA_GROWTH = 100.0
    """An adaptive ``kappa`` grows to at most this many times its initial value."""

    def bind(self, topology, rest: Tensor, mass: Tensor) -> None:
        """Take the mesh of a model (faces, edges, the mollifier thresholds of its rest edges) and, for
        ``stiffness=None``, the barrier stiffness from its mean vertex weight.  A term is bound to one mesh: a model
        of another mesh needs its own term (a ``ValueError``)."""
        faces, edges = topology.faces.to(rest.device), topology.edges.to(rest.device)
        _check_same_mesh(self, faces, rest.shape[0])
        self.faces, self.edges, self._cache, self._close_cache = faces, edges, None, None
        self._V = rest.shape[0]
        e = rest[edges[:, 1]] - rest[edges[:, 0]]
        self._rest_len_sq = (e * e).sum(-1)
        chosen = _weight_kappa(mass, self.dhat)
        if self._auto:
            self.stiffness, self._kappa0, self._last_min = chosen, chosen, math.inf
        elif self.stiffness is not None and self.stiffness < WEAK_FRACTION * chosen:
            _warn_weak(self.name, self.stiffness, chosen, self.dhat)

    def _pair_energy(self, X: Tensor, kind: int, eps: Tensor | None) -> Tensor:
        assert self.stiffness is not None
        e = barrier(typed_distance_sq(X, kind), self.dhat ** 2, self.stiffness)
        return e if eps is None else e * mollifier(X, eps)

    def _pair_hessians(self, X: Tensor, kind: int, eps: Tensor | None) -> Tensor:
        """``(N, 12, 12)`` Hessians of the pairs' energies (``X (N, 12)``, :func:`_batched_hessians`)."""
        return _batched_hessians(lambda Z: self._pair_energy(Z.reshape(-1, 4, 3), kind, eps), X)

    def _barrier_energy(self, x: Tensor) -> Tensor:
        total = x.new_zeros(())
        xa = self._points(x)
        for st, kind, eps in self._groups(x):
            total = total + self._pair_energy(xa[st], kind, eps).sum()
        return total

    def adapt_stiffness(self, x: Tensor) -> None:
        """The update of an adaptive ``kappa`` (module docstring) at the start ``x (V, 3)`` of a time step."""
        if self._kappa0 is not None and self.faces is not None:
            _grow(self, d := self.min_distance(x.detach())[0], self._last_min)
            self._last_min = d

    def adapt(self, x: Tensor, ctx: StepContext, start: bool = False) -> bool:
        """The update of an adaptive ``kappa`` at an iterate ``x`` of a time step's solve (module docstring)."""
        if self._kappa0 is None or self.faces is None:
            return False
        last, self._solve_min = self._solve_min, _closest(self, x)
        return not start and self._solve_min < self.ADAPT_DECREASE * last and _grow(self, self._solve_min, last)

    pose, restore_pose = _kappa_state, _restore_kappa_state  # a step solved again starts from the step's kappa

    def begin_step(self, ctx: StepContext) -> None:
        if self.faces is None or ctx.x_prev is None or ctx.dt is None or ctx.x_prev.ndim != 2:
            return
        self.adapt_stiffness(ctx.x_prev)
        if self.friction > 0:
            self._lag_friction(ctx)

    def energy(self, x: Tensor, ctx: StepContext) -> Tensor:
        if self._compiled(x):
            total = self._pair_terms(x, 0)[1].sum()
        else:
            total = self._barrier_energy(x)
        s = self._slip(x, ctx)
        if s is not None:
            f, delta = s
            total = total + friction_energy(delta, torch.zeros_like(delta), f["n"], f["weight"], f["eps"])
        return total

    def gradient(self, x: Tensor, ctx: StepContext) -> Tensor:
        # a body mesh whose vertices require grad (the adjoint's parameters): the gradient keeps its graph to them
        graph = torch.is_grad_enabled() and self._points_require_grad()
        if self._compiled(x.detach()) and not graph:
            st, types, eps = self._close(x)
            assert self.stiffness is not None
            g = native.contact_gradient_sum(self._points(x).detach(), st, types, eps, self.dhat ** 2,
                                            self.stiffness)[:x.shape[0]]
            friction = self._friction_force(x, ctx, g)
            return g if friction is None else g + friction
        with torch.enable_grad():
            y = x.detach().requires_grad_(True)
            e = self._barrier_energy(y)
            g = torch.autograd.grad(e, y, create_graph=graph)[0] if e.requires_grad else torch.zeros_like(x)
        friction = self._friction_force(x, ctx, g)
        return g if friction is None else g + friction

    def hvp(self, x: Tensor, v: Tensor, ctx: StepContext, projection: Projection | None = None) -> Tensor:
        if x.ndim != 2:
            return super().hvp(x, v, ctx, projection)
        H = self.hessian(x, ctx, projection)
        return (H @ v.reshape(-1, 1).to(H.dtype)).reshape(x.shape).to(x.dtype)

    def hessian(self, x: Tensor, ctx: StepContext, projection: Projection | None = None) -> Tensor:
        proj = Projection.NONE if projection is None else Projection.parse(projection)
        xa = self._points(x).detach()
        stencils, blocks = [], []
        compiled = self._compiled(x.detach())
        fb = self._friction_blocks(x, ctx)
        if compiled:  # as _project: every projection but none and abs clamps
            mode = "abs" if proj is Projection.ABS else ("none" if proj is Projection.NONE else "clamp")
            # summed from the pairs' reduced coordinates (no 12x12 blocks), the friction's after them (positive
            # semi-definite: the same for every projection)
            st, types, eps = self._close(x)
            assert self.stiffness is not None
            return native.contact_hessian_sum(xa, st, types, eps, self.dhat ** 2, self.stiffness, mode, x.shape[0],
                                              fb)  # (the operator takes the friction blocks in x's dtype)
        for st, kind, eps in self._groups(x):
            stencils.append(st)
            blocks.append(_project(self._pair_hessians(xa[st].reshape(-1, 12), kind, eps), proj))
        if fb is not None:  # positive semi-definite: the same for every projection
            stencils.append(fb[0])
            blocks.append(_friction_stencil_blocks(fb[1], fb[2]))
        if not blocks:
            return stencil_sum(x.new_zeros(0, 4, dtype=torch.int64), x.new_zeros(0, 12, 12), x.shape[0])
        st, H = (stencils[0], blocks[0]) if len(blocks) == 1 else (torch.cat(stencils), torch.cat(blocks))
        H = H.to(x.dtype)
        return native.contact_stencil_sum(st, H, x.shape[0]) if _native_ok(H) else stencil_sum(st, H, x.shape[0])


class MeshCollider(SelfContact):
    """A rigid triangle-mesh body (``vertices (Vb, 3)`` [m], ``faces (Fb, 3)``) the cloth cannot pass through: the
    barrier of :class:`SelfContact` between the cloth and the body (cloth vertices against body triangles, body
    vertices against cloth triangles, cloth edges against body edges), the same step bound (the body does not
    move within a step).  Give it in ``colliders=`` (or ``terms=``) of a :class:`~torchbend.ClothModel`.  The
    body may be moved between steps by assigning ``vertices`` (a robot link, an animation frame; see below; a static
    solve refuses a start that the body's new pose intersects).  ``stiffness=None``: ``kappa`` from the
    cloth's weight, as :class:`SelfContact`'s.  ``friction = mu``: IPC's lagged friction on the body in time
    steps (module docstring).

    A time step carries out the move since the last step (:func:`~torchbend.implicit_euler_step`): where the
    body would come into contact with the cloth held still, it moves in stages, each as far as the step bound
    lets it, and the cloth is solved between stages, so a body pushes the cloth ahead of it instead of passing
    through it.  The friction's slip is relative to the body's move (a moving body drags the cloth)."""

    confines = True  # a body holds a cloth that has no pinned vertex, as the analytic colliders do

    def __init__(self, vertices, faces, dhat: float = 1e-3, stiffness: float | None = None, friction: float = 0.0,
                 eps_v: float = 1e-3, name: str = "mesh_collider"):
        super().__init__(dhat=dhat, stiffness=stiffness, friction=friction, eps_v=eps_v, name=name)
        self._vertices: Tensor | None = None
        self._start: Tensor | None = None  # the body's pose in the last step, while a move to _target is pending
        self._target: Tensor | None = None
        v = self._checked_vertices(vertices)
        f = torch.as_tensor(faces)
        if f.ndim != 2 or f.shape[-1] != 3 or f.is_floating_point() or f.numel() == 0:
            raise ValueError(f"MeshCollider: faces must be a non-empty (Fb, 3) integer tensor, got {tuple(f.shape)}")
        if int(f.min()) < 0 or int(f.max()) >= v.shape[0]:
            raise ValueError(f"MeshCollider: faces index vertices 0..{v.shape[0] - 1}, found {int(f.min())}.."
                             f"{int(f.max())}")
        self.vertices, self.body_faces = v, f.long()
        e = torch.cat([self.body_faces[:, [0, 1]], self.body_faces[:, [1, 2]], self.body_faces[:, [2, 0]]])
        self.body_edges = e.sort(1).values.unique(dim=0)

    def _checked_vertices(self, vertices) -> Tensor:
        v = vertices if isinstance(vertices, Tensor) else torch.as_tensor(  # a list: the dtype of the body's
            vertices, dtype=None if self._vertices is None else self._vertices.dtype)
        what = f"MeshCollider: vertices must be a finite (Vb, 3) float tensor, got {tuple(v.shape)} {v.dtype}"
        if v.ndim != 2 or v.shape[-1] != 3 or not v.is_floating_point():
            raise ValueError(what)
        if not bool(torch.isfinite(v.detach()).all()):
            raise ValueError(what + " with non-finite values")
        if self._vertices is not None and v.shape != self._vertices.shape:
            raise ValueError(f"MeshCollider: vertices moves the body's {self._vertices.shape[0]} vertices (the faces "
                             f"index them), got {tuple(v.shape)}")
        return v

    @property
    def vertices(self) -> Tensor:
        """The body's vertex positions ``(Vb, 3)`` [m]; assign new positions (same shape) to move it between steps."""
        assert self._vertices is not None
        return self._vertices

    @vertices.setter
    def vertices(self, value) -> None:
        v = self._checked_vertices(value)
        if self._vertices is not None and self._start is None:  # the pose of the last step: a step moves it from there
            self._start = self._vertices.detach().clone()  # (a copy: the caller may reuse the tensor it gave)
        self._vertices = self._target = v

    # ---- a move between steps, carried out by the next step (EnergyTerm.pending_move)
    def pending_move(self) -> bool:
        return self._start is not None and not torch.equal(self._start, self._goal().to(self._start))

    def _goal(self) -> Tensor:
        assert self._target is not None
        return self._target.detach()

    def place(self, s: float) -> None:
        if self._start is not None:
            self._vertices = self._target if s >= 1 else self._start + s * (self._goal().to(self._start) - self._start)

    def move_bound(self, x: Tensor) -> float:
        if self._start is None or self.faces is None:
            return 1.0
        rest = (self._goal() - self.vertices.detach()).to(device=x.device, dtype=x.dtype)
        return _path_bound(self, x, torch.cat([torch.zeros_like(x), rest]))

    def move_gap(self, x: Tensor) -> float:
        return self.min_distance(x)[0]

    def settle(self) -> None:
        self._start, self._target = None, self._vertices

    def pose(self) -> tuple:
        return self._start, self._target, self._vertices, _kappa_state(self)

    def restore_pose(self, pose: tuple) -> None:
        self._start, self._target, self._vertices, kappa = pose
        _restore_kappa_state(self, kappa)

    def bind(self, topology, rest: Tensor, mass: Tensor) -> None:
        super().bind(topology, rest, mass)
        self._V = rest.shape[0]
        vb = self.vertices.detach().to(device=rest.device, dtype=rest.dtype)
        be = self.body_edges.to(rest.device)
        d = vb[be[:, 1]] - vb[be[:, 0]]
        assert self._rest_len_sq is not None
        self._rest_len_sq = torch.cat([self._rest_len_sq, (d * d).sum(-1)])

    def _points(self, x: Tensor) -> Tensor:
        return torch.cat([x, self.vertices.to(device=x.device, dtype=x.dtype)])

    def _points_require_grad(self) -> bool:
        return self.vertices.requires_grad

    def _candidates(self, lo: Tensor, hi: Tensor, radius: float) -> tuple[Tensor, Tensor, Tensor]:
        faces, edges = self._mesh()
        faces, edges = faces.to(lo.device), edges.to(lo.device)
        V = self._V
        bf = self.body_faces.to(lo.device) + V
        be = self.body_edges.to(lo.device) + V
        half = 0.5 * radius
        a = box_pairs(lo[:V], hi[:V], lo[bf].amin(1), hi[bf].amax(1), half)  # cloth vertex - body triangle
        b = box_pairs(lo[V:], hi[V:], lo[faces].amin(1), hi[faces].amax(1), half)  # body vertex - cloth triangle
        pt = torch.cat([torch.cat([a[:, :1], bf[a[:, 1]]], 1), torch.cat([b[:, :1] + V, faces[b[:, 1]]], 1)])
        ee = box_pairs(lo[edges].amin(1), hi[edges].amax(1), lo[be].amin(1), hi[be].amax(1), half)
        stencils = torch.cat([edges[ee[:, 0]], be[ee[:, 1]]], 1)
        return pt, stencils, torch.stack([ee[:, 0], ee[:, 1] + edges.shape[0]], 1)

    def _crossing_pairs(self, pts: Tensor) -> tuple[Tensor, Tensor]:
        faces, edges = self._mesh()
        faces, edges = faces.to(pts.device), edges.to(pts.device)
        V = self._V
        bf, be = self.body_faces.to(pts.device) + V, self.body_edges.to(pts.device) + V
        box = (lambda idx: (pts[idx].amin(1), pts[idx].amax(1)))
        a = box_pairs(*box(edges), *box(bf), 0.0)  # cloth edge - body triangle
        b = box_pairs(*box(be), *box(faces), 0.0)  # body edge - cloth triangle
        return torch.cat([edges[a[:, 0]], be[b[:, 0]]]), torch.cat([bf[a[:, 1]], faces[b[:, 1]]])

    def inadmissible(self, x: Tensor) -> str:
        if self.faces is None:
            return ""
        unresolved = _unresolved(self, x)
        if unresolved:
            return unresolved
        d, _ = self.min_distance(x)
        if d <= 0:
            return f"{self.name}: the cloth touches the body mesh (distance {d:.3g} m): start apart"
        cross = self.crossing(x)
        if cross is not None:
            V = self._V
            (i, j), tri = cross
            if i < V:
                where = f"cloth edge {(i, j)} crosses body triangle {tuple(t - V for t in tri)}"
            else:
                where = f"body edge {(i - V, j - V)} crosses cloth triangle {tuple(tri)}"
            return (f"{self.name}: the cloth and the body mesh intersect: {where} (vertex indices): a body must "
                    "be moved so that it leaves the cloth outside it")
        return ""


def _project(H: Tensor, proj: Projection) -> Tensor:
    """The pairs' Hessians ``(N, 12, 12)`` projected to PSD (``clamp``; ``abs``): in the complement of the
    translations, which every pair's energy ignores, by the compiled Jacobi of the hinge blocks on the CPU, else by
    ``eigh``."""
    if proj is Projection.NONE or H.shape[0] == 0:
        return H
    mode = "abs" if proj is Projection.ABS else "clamp"
    if H.device.type == "cpu" and H.dtype in (torch.float32, torch.float64) and native.load() is not None:
        return native.project_blocks(H.contiguous(), mode, hinge=True)
    w, Q = torch.linalg.eigh(0.5 * (H + H.transpose(-1, -2)))
    w = w.abs() if proj is Projection.ABS else w.clamp_min(0)
    return (Q * w[:, None, :]) @ Q.transpose(-1, -2)


def stencil_sum(stencils: Tensor, H: Tensor, V: int) -> Tensor:
    """The ``(3V, 3V)`` torch sparse (COO, coalesced, in CSR order) sum of the Hessians ``H (M, 12, 12)`` of four-vertex stencils
    ``stencils (M, 4)`` (entry ``(3 a + p, 3 b + q)`` of a stencil: vertices ``stencils[a]``, ``stencils[b]``,
    axes ``p``, ``q``); vertices ``>= V`` (a body's) are not unknowns and are left out.  The 3x3 vertex blocks are
    summed per vertex pair (one sort of the pairs' keys) and laid out row by row."""
    dev, M = H.device, stencils.shape[0]
    vi = stencils[:, :, None].expand(M, 4, 4).reshape(-1)
    vj = stencils[:, None, :].expand(M, 4, 4).reshape(-1)
    own = (vi < V) & (vj < V)
    B = H.reshape(M, 4, 3, 4, 3).transpose(2, 3).reshape(-1, 3, 3)[own]
    keys, inverse = torch.unique(vi[own] * V + vj[own], sorted=True, return_inverse=True)
    U = keys.shape[0]
    blocks = H.new_zeros(U, 3, 3).index_add_(0, inverse, B)
    bi, bj = keys // V, keys % V
    nb = torch.bincount(bi, minlength=V)  # blocks per block row
    start = torch.cumsum(nb, 0) - nb  # the first block of each block row
    j = torch.arange(U, device=dev) - start[bi]  # each block's place in its block row
    ax = torch.arange(3, device=dev)
    # entry (p, q) of block u (row bi, place j): scalar row 3 bi + p holds the row's 3 nb entries in block order
    pos = ((9 * start[bi] + 3 * j)[:, None, None] + (3 * nb[bi])[:, None, None] * ax[:, None] + ax).reshape(-1)
    values = H.new_empty(9 * U)
    values[pos] = blocks.reshape(-1)
    cols = torch.empty(9 * U, dtype=torch.int64, device=dev)
    cols[pos] = (3 * bj[:, None, None] + ax).expand(U, 3, 3).reshape(-1)
    rows = torch.empty(9 * U, dtype=torch.int64, device=dev)
    rows[pos] = (3 * bi[:, None, None] + ax[:, None]).expand(U, 3, 3).reshape(-1)
    # row-major and unique by construction: coalesced (sums and differences of such matrices work as for any COO)
    return torch.sparse_coo_tensor(torch.stack([rows, cols]), values, (3 * V, 3 * V), is_coalesced=True,
                                   check_invariants=False)
