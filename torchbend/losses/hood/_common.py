"""Shared pieces of the HOOD-convention terms: rest triangles, lumped masses, nearest body faces."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ...mesh.topology import lumped_areas, mesh_and_rest
from .._base import LossTerm, check_points, lumped_masses

__all__ = ["HoodTerm", "face_centroids", "face_normals", "nearest"]

_CDIST_BLOCK = 1 << 22  # entries of one block of a brute-force distance matrix (off the CPU)


class HoodTerm(LossTerm):
    """A HOOD-convention term over a cloth mesh: faces, rest areas, lumped rest areas per vertex."""

    faces: Tensor  # (F, 3) int64
    face_areas: Tensor  # (F,) [m^2]
    vertex_areas: Tensor  # (V,) [m^2]

    def _set_mesh(self, faces, rest: Tensor) -> Tensor:
        topo, rest = mesh_and_rest(faces, rest)
        f = topo.faces.to(rest.device)
        X = rest.detach().to(torch.float64)
        p0, p1, p2 = X[f[:, 0]], X[f[:, 1]], X[f[:, 2]]
        area = 0.5 * torch.linalg.cross(p1 - p0, p2 - p0, dim=-1).norm(dim=-1)
        bad = torch.nonzero(~(area > 0)).reshape(-1)
        if bad.numel():
            raise ValueError(f"{self.term_name}: rest triangle {int(bad[0])} (faces {f[bad[0]].tolist()}) has zero "
                             f"area; {bad.numel()} degenerate rest triangle(s) in all")
        self.register_buffer("faces", f)
        self.register_buffer("face_areas", area.to(rest.dtype))
        self.register_buffer("vertex_areas", lumped_areas(f, rest))
        self._topology = topo
        return rest

    @property
    def vertex_count(self) -> int:
        return int(self.vertex_areas.shape[0])

    def _masses(self, x: Tensor, density) -> Tensor:
        """HOOD's ``v_mass``: lumped masses ``(V,)`` or ``(B, V)`` [kg], a third of each rest triangle's mass."""
        return lumped_masses(self.density if density is None else density, self.vertex_areas, x, self.term_name)

    def _points(self, t, name: str, x: Tensor, count: int | None = None) -> Tensor:
        """A second set of positions (previous cloth, body) checked against ``x``'s batch, device and dtype."""
        return check_points(t, name, self.term_name, count=count, batch=tuple(x.shape[:-2]), device=x.device,
                            dtype=x.dtype)


def face_centroids(p: Tensor, faces: Tensor) -> Tensor:
    """Centroids ``(..., F, 3)`` of the triangles ``faces (F, 3)`` of ``p (..., V, 3)``."""
    return (p[..., faces[:, 0], :] + p[..., faces[:, 1], :] + p[..., faces[:, 2], :]) / 3


def face_normals(p: Tensor, faces: Tensor) -> Tensor:
    """Unit normals ``(..., F, 3)`` of the triangles, ``(p1 - p0) x (p2 - p0)`` normalised (zero for a
    collapsed triangle)."""
    p0 = p[..., faces[:, 0], :]
    n = torch.linalg.cross(p[..., faces[:, 1], :] - p0, p[..., faces[:, 2], :] - p0, dim=-1)
    return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True).clamp_min(torch.finfo(p.dtype).tiny)


def _nearest_one(points: Tensor, targets: Tensor, bound: float | None, method: str) -> tuple[Tensor, Tensor]:
    if method == "kdtree":
        from scipy.spatial import KDTree

        tree = KDTree(targets.detach().to(torch.float64).numpy(), leafsize=24, balanced_tree=False,
                      compact_nodes=False)  # (a third of the default build and query time here; the same answer)
        d, i = tree.query(points.detach().to(torch.float64).numpy(), k=1,
                          distance_upper_bound=math.inf if bound is None else bound)
        idx = torch.from_numpy(i).to(torch.int64)
        idx[idx == targets.shape[0]] = 0  # beyond the bound: d is inf
        return (torch.from_numpy(d) ** 2).to(points.dtype), idx
    rows = max(1, _CDIST_BLOCK // max(1, targets.shape[0]))
    d2, idx = [], []
    for s in range(0, points.shape[0], rows):
        d = torch.cdist(points[s:s + rows].detach(), targets.detach())
        m = d.min(-1)
        d2.append(m.values ** 2)
        idx.append(m.indices)
    return torch.cat(d2), torch.cat(idx)


def nearest(points: Tensor, targets: Tensor, bound: float | None = None, method: str | None = None) -> tuple[Tensor, Tensor]:
    """Squared distance and index of the nearest of ``targets (..., M, 3)`` to each of ``points (..., N, 3)``
    (batch dimensions broadcast; no gradient: a piecewise-constant choice).  A k-d tree (SciPy) on the CPU,
    blocks of a brute-force distance matrix elsewhere: the same answer as HOOD's ``knn_points`` up to ties.
    ``bound`` [m]: points farther than it from every target may get ``inf`` and index 0 (a faster search
    where only the points within the bound matter).  ``method``: ``"kdtree"`` or ``"brute"`` (default: by device)."""
    method = method or ("kdtree" if points.is_cpu else "brute")
    if method not in ("kdtree", "brute"):
        raise ValueError(f"nearest: method must be 'kdtree' or 'brute', got {method!r}")
    batch = torch.broadcast_shapes(points.shape[:-2], targets.shape[:-2])
    p = points.expand(*batch, *points.shape[-2:]).reshape(-1, *points.shape[-2:])
    t = targets.expand(*batch, *targets.shape[-2:]).reshape(-1, *targets.shape[-2:])
    out = [_nearest_one(p[b], t[b], bound, method) for b in range(p.shape[0])]
    d2 = torch.stack([o[0] for o in out]).reshape(*batch, points.shape[-2]).to(points.device)
    idx = torch.stack([o[1] for o in out]).reshape(*batch, points.shape[-2]).to(points.device)
    return d2, idx


def take(values: Tensor, idx: Tensor) -> Tensor:
    """``values (..., M, 3)`` at ``idx (..., N)`` -> ``(..., N, 3)`` (batch dimensions broadcast)."""
    batch = torch.broadcast_shapes(values.shape[:-2], idx.shape[:-1])
    v = values.expand(*batch, *values.shape[-2:])
    i = idx.expand(*batch, idx.shape[-1])
    return torch.gather(v, -2, i[..., None].expand(*i.shape, 3))
