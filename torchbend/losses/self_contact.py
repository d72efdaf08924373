r"""Self-contact as a training loss: a one-sided repulsion that keeps each cloth vertex on the side of the nearby
triangles it was on at the current state (ContourCraft-style; Grigorev et al. 2024), batched over ``(B, V, 3)``.

For the prediction ``x`` and the current state ``x_curr`` (both ``(B, V, 3)`` [m], one topology)::

    pairs (i, f): vertex i not in triangle f, the projection of x_curr_i onto f's plane inside f, and
                  |(x_curr_i - x_curr_f0) . n_f(x_curr)| < radius        (found at x_curr, without gradient)
    s_if = sign((x_curr_i - x_curr_f0) . n_f(x_curr))                    (the side the vertex is on now)
    d_if = s_if (x_i - x_f0) . n_f(x)                                     (its signed distance at the prediction)
    E = stiffness * sum_(i,f) max(eps - d_if, 0)^3                        [J]

A prediction that keeps every vertex at least ``eps`` on its side of every nearby triangle costs nothing; one
that passes a vertex through a triangle pays the cube of the depth (plus ``eps``), differentiable in ``x`` (the
vertex and the triangle's three vertices).  The pairs come from a k-d tree of the current state (SciPy, on the
CPU) per sample; their number is flat per vertex for a given ``radius``.  The solver's self-contact is
:class:`torchbend.SelfContact` (IPC's barrier, intersection-free by construction); this term is the penalty a
network is trained with.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .._checks import nonnegative, positive
from ..mesh.topology import mesh_and_rest
from ._base import LossTerm, check_points

__all__ = ["SelfRepulsion"]


def _unit_normals(p: Tensor, faces: Tensor) -> Tensor:
    p0 = p[..., faces[:, 0], :]
    n = torch.linalg.cross(p[..., faces[:, 1], :] - p0, p[..., faces[:, 2], :] - p0, dim=-1)
    return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True).clamp_min(torch.finfo(p.dtype).tiny)


def _pairs(x: np.ndarray, faces: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(vertex, face, side)`` of one sample's current state ``x (V, 3)`` (float64)."""
    from scipy.spatial import KDTree

    p0, p1, p2 = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    centroid = (p0 + p1 + p2) / 3
    reach = np.sqrt(np.max(np.stack([((p - centroid) ** 2).sum(-1) for p in (p0, p1, p2)]), axis=0))  # (F,)
    tree = KDTree(x)
    lists = tree.query_ball_point(centroid, reach + radius)
    f = np.repeat(np.arange(len(faces)), [len(v) for v in lists])
    i = np.fromiter((k for v in lists for k in v), dtype=np.int64, count=len(f))
    keep = (faces[f] != i[:, None]).all(1)
    i, f = i[keep], f[keep]
    e1, e2, w = p1[f] - p0[f], p2[f] - p0[f], x[i] - p0[f]
    n = np.cross(e1, e2)
    nn = np.maximum((n * n).sum(-1), np.finfo(np.float64).tiny)
    dist = (w * n).sum(-1) / np.sqrt(nn)
    # barycentric coordinates of the projection (the triangle's plane): inside, strictly
    b1 = (np.cross(w, e2) * n).sum(-1) / nn
    b2 = (np.cross(e1, w) * n).sum(-1) / nn
    inside = (b1 > 0) & (b2 > 0) & (b1 + b2 < 1) & (np.abs(dist) < radius)
    side = np.where(dist[inside] < 0, -1.0, 1.0)
    return i[inside], f[inside], side


class SelfRepulsion(LossTerm):
    """Self-contact penalty of a cloth against itself (module docstring) [J].

    Args:
        faces: ``(F, 3)`` int triangles (or a :class:`~torchbend.HingeTopology`); rest: ``(V, 3)`` [m] (checked
            against the faces only).
        eps: the margin kept on each side [m] (ContourCraft: 1 mm); radius: the reach of the pairs at the current
            state [m] (ContourCraft's correspondence distance: 5 mm); stiffness: ``k`` [J/m^3].

    ``forward(x, *, x_curr)``: ``x``, ``x_curr`` ``(B, V, 3)`` or ``(V, 3)`` [m] -> ``(B,)`` or ``()`` [J].
    ``pairs(x_curr)`` gives the pairs of one state (``(vertex, face, side)`` NumPy arrays) for inspection.
    """

    inputs = ("x_curr",)
    faces: Tensor

    def __init__(self, faces, rest: Tensor, *, eps: float = 1e-3, radius: float = 5e-3, stiffness: float = 1e4):
        super().__init__()
        topo, rest = mesh_and_rest(faces, rest)
        self.register_buffer("faces", topo.faces.to(rest.device))
        self.vertex_count = topo.vertex_count
        name = self.term_name
        self.eps, self.radius = nonnegative(eps, f"{name}: eps"), positive(radius, f"{name}: radius")
        self.stiffness = positive(stiffness, f"{name}: stiffness")

    def pairs(self, x_curr: Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _pairs(x_curr.detach().to(torch.float64).cpu().numpy(), self.faces.cpu().numpy(), self.radius)

    def forward(self, x: Tensor, *, x_curr) -> Tensor:
        x = self._positions(x, self.vertex_count, self.faces.device)
        x_curr = check_points(x_curr, "x_curr", self.term_name, count=self.vertex_count, batch=tuple(x.shape[:-2]),
                              device=x.device, dtype=x.dtype)
        xs = x.reshape(-1, *x.shape[-2:])
        cs = x_curr.expand_as(x).reshape(-1, *x.shape[-2:])
        out = []
        for b in range(xs.shape[0]):
            i, f, side = (torch.from_numpy(a).to(x.device) for a in self.pairs(cs[b]))
            if i.numel() == 0:
                out.append(xs[b].sum() * 0)
                continue
            tri = self.faces[f]
            n = _unit_normals(xs[b], tri)
            d = side.to(x.dtype) * ((xs[b][i] - xs[b][tri[:, 0]]) * n).sum(-1)
            out.append(self.stiffness * (self.eps - d).clamp_min(0).pow(3).sum())
        return torch.stack(out).reshape(x.shape[:-2])

    def extra_repr(self) -> str:
        return f"faces={self.faces.shape[0]}, eps={self.eps}, radius={self.radius}, stiffness={self.stiffness}"
