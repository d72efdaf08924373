"""Mesh topology for hinge energies: the one place where the hinge convention is defined.

Hinge stencil.  A hinge is an interior edge with its two triangles, stored as four
vertex indices ``(i0, i1, i2, i3)``::

          x2
         /  \\
    A   /    \\
       x0 ---> x1        e0 = x1 - x0
        \\    /
    B    \\  /
          x3

``x0 -> x1`` is the shared edge with ``i0 < i1``; triangle A = ``(x0, x1, x2)`` and triangle
B = ``(x1, x0, x3)`` are both counter-clockwise.  Hinges are sorted by ``(i0, i1)``.
The bend angle is ``theta = atan2(e0_hat . (nA x nB), nA . nB)``, ``nA = e0 x (x2 - x0)``,
``nB = (x3 - x1) x e0``: 0 when flat, positive where the surface bends away from its normals.

Per-triangle edge maps (used by the per-triangle Hessian assembly): local edge ``k`` of face
``f`` is the edge *opposite* local vertex ``k``, i.e. it joins ``faces[f, k+1] -> faces[f, k+2]``
(indices mod 3).  ``face_edges[f, k]`` is its index into ``edges``, ``face_edge_hinges[f, k]`` its
hinge index or ``-1`` on the boundary, and ``face_edge_signs[f, k]`` is ``+1`` where the face
traverses the edge in its global direction ``edges[e, 0] -> edges[e, 1]`` (``edges[e, 0] <
edges[e, 1]``; for a hinge this face is triangle A) and ``-1`` otherwise.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .._checks import check_positions
from .._torch_compat import parse_to

__all__ = ["HingeTopology", "lumped_areas", "mesh_and_rest"]


def _as_faces_array(faces) -> np.ndarray:
    if isinstance(faces, Tensor):
        if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
            raise ValueError(f"faces must be an integer tensor, got dtype {faces.dtype}")
        arr = faces.detach().cpu().numpy()
    else:
        arr = np.asarray(faces)
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"faces must hold integers, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {tuple(arr.shape)}")
    if arr.shape[0] == 0:
        raise ValueError("faces is empty: a mesh needs at least one triangle")
    return arr.astype(np.int64, copy=False)


def _faces_str(fs, limit: int = 8) -> str:
    fs = list(fs)
    tail = f" ... ({len(fs)} in all)" if len(fs) > limit else ""
    return ", ".join(str(int(f)) for f in fs[:limit]) + tail


def _one_indexed_message(vertex_count: int) -> str:
    return (
        f"faces look 1-indexed (smallest index 1, largest {vertex_count} = V, the vertex count): indices must "
        "start at 0; subtract 1 (faces - 1), or read the file with tb.mesh.load, which returns 0-indexed faces"
    )


@dataclass(frozen=True, eq=False)
class HingeTopology:
    """Integer, no-grad connectivity of a triangle mesh (build once, share across calls).

    Attributes (all ``int64`` tensors on the CPU unless moved with :meth:`to`):
        faces: ``(F, 3)`` the validated faces.
        hinges: ``(H, 4)`` hinge stencils ``(i0, i1, i2, i3)`` (see module docstring).
        hinge_faces: ``(H, 2)`` the faces of triangles A and B of each hinge.
        edges: ``(E, 2)`` all undirected edges ``(min, max)``, sorted.
        edge_hinges: ``(E,)`` hinge index of each edge, ``-1`` for boundary edges.
        boundary_edges: ``(Eb, 2)`` boundary edges, oriented as their face traverses them.
        face_edges, face_edge_hinges, face_edge_signs: ``(F, 3)`` per-triangle edge maps.
        vertex_count: number of vertices ``V`` (positions are ``(..., V, 3)``).
    """

    faces: Tensor
    hinges: Tensor
    hinge_faces: Tensor
    edges: Tensor
    edge_hinges: Tensor
    boundary_edges: Tensor
    face_edges: Tensor
    face_edge_hinges: Tensor
    face_edge_signs: Tensor
    vertex_count: int

    @property
    def hinge_count(self) -> int:
        return int(self.hinges.shape[0])

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])

    @classmethod
    def from_faces(cls, faces, vertex_count: int | None = None) -> HingeTopology:
        """Build and validate the topology of ``faces: (F, 3)`` integer vertex indices.

        ``vertex_count`` (V) defaults to ``faces.max() + 1``; when given, every index must be
        in ``[0, V)``.  Raises ``ValueError`` naming the offending faces/edges for: wrong shape
        or dtype, empty faces, negative or out-of-range indices (faces numbered ``1..V``, as in
        OBJ files, are named as 1-indexed), a face repeating a vertex, an edge shared by three or
        more faces, and two neighbours with inconsistent orientation (they traverse their shared
        edge in the same direction).  Vertices used by no face are allowed (they get no hinge;
        ``tb.mesh.clean`` drops them).
        """
        F = _as_faces_array(faces)
        nf = F.shape[0]
        bad = np.nonzero((F < 0).any(1))[0]
        if bad.size:
            raise ValueError(f"faces hold negative vertex indices in faces [{_faces_str(bad)}]")
        vmax = int(F.max())
        if vertex_count is None:
            vertex_count = vmax + 1
        vertex_count = int(vertex_count)
        bad = np.nonzero((F >= vertex_count).any(1))[0]
        if bad.size:
            if int(F.min()) == 1 and vmax == vertex_count:
                raise ValueError(_one_indexed_message(vertex_count))
            f0 = int(bad[0])
            raise ValueError(
                f"vertex index out of range [0, {vertex_count}) in faces [{_faces_str(bad)}]: face {f0} = "
                f"{F[f0].tolist()} has index {int(F[f0].max())} >= V = {vertex_count} (largest index {vmax})"
            )
        bad = np.nonzero((F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0]))[0]
        if bad.size:
            raise ValueError(f"faces repeat a vertex: faces [{_faces_str(bad)}] = {F[bad[:4]].tolist()}")

        # directed half-edges: local edge k of face f runs faces[f, k+1] -> faces[f, k+2]
        src = np.roll(F, -1, axis=1).reshape(-1)
        dst = np.roll(F, -2, axis=1).reshape(-1)
        face_of = np.repeat(np.arange(nf), 3)
        lo, hi = np.minimum(src, dst), np.maximum(src, dst)
        key = lo * vertex_count + hi
        edge_keys, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        if (counts > 2).any():
            e = np.nonzero(counts > 2)[0][0]
            fs = face_of[inverse == e]
            k = int(edge_keys[e])
            raise ValueError(
                f"non-manifold edge ({k // vertex_count}, {k % vertex_count}) is shared by "
                f"{counts[e]} faces [{_faces_str(fs)}]; at most 2 allowed"
            )
        forward = src < dst  # half-edge runs in the global direction lo -> hi
        # orientation: an interior edge must be traversed once in each direction
        n_edges = edge_keys.shape[0]
        fwd_count = np.bincount(inverse, weights=forward, minlength=n_edges)
        interior = counts == 2
        bad_e = np.nonzero(interior & (fwd_count != 1))[0]
        if bad_e.size:
            pairs = [
                (int(edge_keys[e] // vertex_count), int(edge_keys[e] % vertex_count), face_of[inverse == e].tolist())
                for e in bad_e[:4]
            ]
            msg = "; ".join(f"edge ({a}, {b}) in faces {fs}" for a, b, fs in pairs)
            raise ValueError(
                f"inconsistently oriented neighbours ({bad_e.size} edges): {msg} traverse their shared "
                "edge in the same direction (or repeat a face); orient all faces counter-clockwise"
            )

        edges = np.stack([edge_keys // vertex_count, edge_keys % vertex_count], axis=1)
        edge_hinges = np.full(n_edges, -1, dtype=np.int64)
        interior_idx = np.nonzero(interior)[0]
        edge_hinges[interior_idx] = np.arange(interior_idx.size)
        # per interior edge: face A traverses it forward (i0 -> i1), face B backward
        opp = F.reshape(-1)  # local edge k is opposite local vertex k
        he = np.arange(3 * nf)
        a_he = np.empty(n_edges, dtype=np.int64)
        b_he = np.full(n_edges, -1, dtype=np.int64)
        a_he[inverse[forward]] = he[forward]
        b_he[inverse[~forward]] = he[~forward]
        hinges = np.stack(
            [edges[interior_idx, 0], edges[interior_idx, 1], opp[a_he[interior_idx]], opp[b_he[interior_idx]]], 1
        )
        hinge_faces = np.stack([face_of[a_he[interior_idx]], face_of[b_he[interior_idx]]], 1)
        boundary = np.nonzero(counts == 1)[0]
        bhe = np.where(np.isin(inverse, boundary))[0]
        boundary_edges = np.stack([src[bhe], dst[bhe]], 1)
        boundary_edges = boundary_edges[np.argsort(inverse[bhe], kind="stable")]

        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.int64)  # noqa: E731
        return cls(
            faces=t(F),
            hinges=t(hinges.reshape(-1, 4)),
            hinge_faces=t(hinge_faces.reshape(-1, 2)),
            edges=t(edges),
            edge_hinges=t(edge_hinges),
            boundary_edges=t(boundary_edges.reshape(-1, 2)),
            face_edges=t(inverse.reshape(nf, 3)),
            face_edge_hinges=t(edge_hinges[inverse].reshape(nf, 3)),
            face_edge_signs=t(np.where(forward, 1, -1).reshape(nf, 3)),
            vertex_count=vertex_count,
        )

    def to(self, *args, **kwargs) -> HingeTopology:
        """A copy with every index tensor on the device named by the arguments (as ``Tensor.to``).

        A dtype in the arguments is ignored: index tensors stay ``int64`` (as ``nn.Module.to`` casts
        only floating point tensors), so ``topo.to(torch.float32)`` is a copy."""
        device = parse_to(*args, **kwargs)[0]
        return dataclasses.replace(self, **{
            f.name: getattr(self, f.name).to(device)
            for f in dataclasses.fields(self)
            if device is not None and isinstance(getattr(self, f.name), Tensor)
        })


def mesh_and_rest(faces, rest_positions) -> tuple[HingeTopology, Tensor]:
    """Validated ``(topology, rest positions (V, 3) float)`` from faces (or a topology) and positions.

    ``V`` is the number of rest positions: a face index ``>= V`` is reported as such (naming the face)."""
    rest = torch.as_tensor(rest_positions)
    if not rest.is_floating_point():
        rest = rest.to(torch.get_default_dtype())
    if isinstance(faces, HingeTopology):
        topo = faces
        n = rest.shape[0] if rest.ndim == 2 and rest.shape[1] == 3 else None
        if n is not None and n != topo.vertex_count:
            _check_vertex_count(topo, n)
    else:
        V = rest.shape[0] if rest.ndim == 2 and rest.shape[1] == 3 else None
        topo = HingeTopology.from_faces(faces, V)
    check_positions(rest, topo.vertex_count, "rest_positions")
    if rest.ndim != 2:
        raise ValueError(f"rest_positions must have shape (V, 3), got {tuple(rest.shape)}")
    return topo, rest


def _check_vertex_count(topo: HingeTopology, n: int) -> None:
    """Name the two usual causes of a topology built for a vertex count other than the ``n`` rest positions."""
    V = topo.vertex_count
    if V == n + 1 and int(topo.faces.min()) == 1:
        raise ValueError(_one_indexed_message(n))
    if n > V:
        unused = f"vertex {V} is" if n == V + 1 else f"vertices {V} to {n - 1} are"
        raise ValueError(
            f"rest_positions has {n} vertices but the topology was built for V = {V} (HingeTopology.from_faces "
            f"takes V = faces.max() + 1 unless vertex_count is given): {unused} used by no face; tb.mesh.clean "
            f"drops unused vertices, or pass vertex_count={n} to HingeTopology.from_faces to keep them"
        )


def lumped_areas(faces: Tensor, rest: Tensor) -> Tensor:
    """Per-vertex lumped rest areas ``(V,)`` [m^2]: each triangle gives a third of its area to each of
    its vertices (times an areal density [kg/m^2]: the lumped masses of :class:`~torchbend.ClothModel`)."""
    X = rest.detach().to(torch.float64)
    F = faces.to(X.device)
    p0, p1, p2 = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    area = 0.5 * torch.linalg.cross(p1 - p0, p2 - p0, dim=-1).norm(dim=-1)
    out = X.new_zeros(X.shape[0]).index_add_(0, F.reshape(-1), (area / 3).repeat_interleave(3))
    return out.to(rest.dtype)
