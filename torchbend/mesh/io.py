"""Mesh files in, clean triangle meshes out: :func:`load`, :func:`clean`, :func:`save_obj`, :class:`MeshReport`.

``load`` reads Wavefront OBJ with its own parser (no dependency: meshio's OBJ reader rejects files whose
texture coordinates outnumber their vertices, which is every garment with UV seams, and misreads negative
indices) and every other format through meshio (PLY, STL, OFF, VTK, ...; ``pip install meshio``).
Polygons are fan-triangulated.  :func:`clean` then

1. welds vertices closer than ``weld_tol`` times the diagonal of the mesh's bounding box (exports duplicate
   the vertices along UV seams: unwelded, every seam edge is two boundary edges and loses its hinge);
2. drops faces that welding made degenerate (a repeated vertex), with a warning;
3. removes vertices used by no face, with a warning;
4. reports boundary, non-manifold and inconsistently oriented edges (:class:`MeshReport`) without raising:
   :class:`~torchbend.mesh.HingeTopology` (and so every energy) raises on the last two with its own message.

Positions are in the file's units (metres for the energies' SI conventions).
"""
from __future__ import annotations

import contextlib
import os
import warnings
from dataclasses import dataclass, field
from io import StringIO
from typing import Literal, overload

import numpy as np
import torch
from torch import Tensor

from .._extras import require
from .topology import _one_indexed_message

__all__ = ["MeshReport", "asset_path", "clean", "load", "save", "save_obj"]

ASSETS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "assets")


@dataclass
class MeshReport:
    """What :func:`load` / :func:`clean` read, changed and found.

    Attributes:
        source: the file read, or ``None`` for in-memory arrays.
        vertices_read, faces_read: vertices and triangles (after fan triangulation) before cleaning.
        polygons_triangulated: faces with more than 3 corners that were fan-triangulated.
        weld_distance: the absolute welding distance [m] (``weld_tol`` x bounding-box diagonal), ``None``
            when welding is off.
        welded: vertices merged into an earlier one.
        degenerate_faces_dropped: faces that repeated a vertex (in the input or after welding).
        unused_removed: vertices used by no face, removed.
        vertices, faces: counts of the returned mesh.
        edge_count, boundary_edge_count: undirected edges, and those with one face.
        boundary_loop_count: connected components of the boundary edges (its loops on a manifold mesh).
        hinge_count: edges with two faces: the hinges :class:`~torchbend.BendingEnergy` builds.
        non_manifold_edges: ``(a, b)`` vertex pairs of edges shared by three or more faces.
        inconsistent_edges: ``(a, b)`` pairs whose two faces traverse the edge in the same direction.
    """

    source: str | None
    vertices_read: int
    faces_read: int
    polygons_triangulated: int = 0
    weld_distance: float | None = None
    welded: int = 0
    degenerate_faces_dropped: int = 0
    unused_removed: int = 0
    vertices: int = 0
    faces: int = 0
    edge_count: int = 0
    boundary_edge_count: int = 0
    boundary_loop_count: int = 0
    hinge_count: int = 0
    non_manifold_edges: list[tuple[int, int]] = field(default_factory=list)
    inconsistent_edges: list[tuple[int, int]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when the mesh is manifold and consistently oriented (HingeTopology accepts it)."""
        return not self.non_manifold_edges and not self.inconsistent_edges

    def __str__(self) -> str:
        src = self.source if self.source is not None else "in-memory mesh"
        parts = [f"{src}: {self.vertices_read} vertices and {self.faces_read} triangles read"]
        if self.polygons_triangulated:
            parts[-1] += f" ({self.polygons_triangulated} polygons fan-triangulated)"
        if self.weld_distance is None:
            parts.append("welding off")
        else:
            parts.append(f"{self.welded} vertices welded (distance {self.weld_distance:.3g})")
        if self.degenerate_faces_dropped:
            parts.append(f"{self.degenerate_faces_dropped} degenerate faces dropped")
        if self.unused_removed:
            parts.append(f"{self.unused_removed} unused vertices removed")
        parts.append(
            f"result: {self.vertices} vertices, {self.faces} faces, {self.edge_count} edges, "
            f"{self.hinge_count} hinges, {self.boundary_edge_count} boundary edges in "
            f"{self.boundary_loop_count} loop{'s' if self.boundary_loop_count != 1 else ''}"
        )
        text = "; ".join(parts) + "."
        if self.non_manifold_edges:
            a, b = self.non_manifold_edges[0]
            text += (f" {len(self.non_manifold_edges)} non-manifold edges, e.g. ({a}, {b}): HingeTopology and the "
                     "energies will raise 'non-manifold edge ... is shared by 3 or more faces; at most 2 allowed'.")
        if self.inconsistent_edges:
            a, b = self.inconsistent_edges[0]
            text += (f" {len(self.inconsistent_edges)} edges with inconsistently oriented neighbours, e.g. ({a}, {b}): "
                     "HingeTopology and the energies will raise 'inconsistently oriented neighbours ... orient all "
                     "faces counter-clockwise'.")
        if self.ok:
            text += " Manifold and consistently oriented."
        return text


def asset_path(name: str) -> str:
    """Absolute path of a mesh shipped with the package (``torchbend/mesh/assets/``), e.g. ``"skirt.obj"``."""
    path = os.path.join(ASSETS, name)
    if os.path.basename(name) != name or not os.path.isfile(path):
        have = sorted(os.listdir(ASSETS)) if os.path.isdir(ASSETS) else []
        raise ValueError(f"no shipped mesh named {name!r}; available: {have}")
    return path


# ---------------------------------------------------------------------------------------------------- reading


def _fan(poly: list[int]) -> list[tuple[int, int, int]]:
    return [(poly[0], poly[k], poly[k + 1]) for k in range(1, len(poly) - 1)]


def _obj_lines(path: str) -> list[str]:
    """The lines of an OBJ file, ``\\`` continuations joined (ValueError if it cannot be read)."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:  # -sig: a byte-order mark is not text
            return fh.read().replace("\\\r\n", " ").replace("\\\n", " ").splitlines()
    except OSError as e:
        raise ValueError(f"cannot read mesh file {path}: {e}") from None


def _numbers(tokens: list[str], what: str, line: str) -> list[float]:
    """The floats of a statement's tokens, else ValueError ``what`` and the line."""
    try:
        return [float(t) for t in tokens]
    except ValueError:
        raise ValueError(f"{what} {line.strip()!r}") from None


def _read_obj(path: str, corner_uvs: list | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """``(points (N, 3) float64, triangles (F, 3) int64 0-indexed, polygons fan-triangulated)`` of an OBJ file;
    with a list ``corner_uvs``, the texture coordinates of each triangle's corners are appended to it as one
    ``(F, 3, 2)`` array (ValueError naming the line of a corner without a ``vt`` index).

    Reads ``v`` (extra components such as ``w`` or vertex colours ignored) and ``f`` with any of the
    ``v``, ``v/vt``, ``v//vn``, ``v/vt/vn`` corner forms, 1-based or negative (relative) indices and
    ``\\`` line continuations; every other statement (``vt``, ``vn``, ``g``, ``o``, ``usemtl``, ``l``, ...)
    is ignored."""
    points: list[list[float]] = []
    tris: list[tuple[int, int, int]] = []
    texcoords: list[list[float]] = []
    tri_uv: list[tuple[int, int, int]] = []
    n_poly = 0
    for lineno, line in enumerate(_obj_lines(path), 1):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "v":
            points.append(_numbers(tok[1:4], f"{path}:{lineno}: bad vertex line", line))
            if len(points[-1]) != 3:
                raise ValueError(f"{path}:{lineno}: a vertex needs 3 coordinates, got {line.strip()!r}")
        elif tok[0] == "vt" and corner_uvs is not None:
            uv = _numbers(tok[1:3], f"{path}:{lineno}: bad texture coordinate line", line)
            texcoords.append(uv + [0.0] * (2 - len(uv)))
        elif tok[0] == "f":
            n = len(points)
            if corner_uvs is not None:
                tri_uv.extend(_fan([_uv_index(t, len(texcoords), path, lineno, line) for t in tok[1:]]))
            poly = [_vertex_index(t, n, path, lineno, line) for t in tok[1:]]
            if len(poly) < 3:
                raise ValueError(f"{path}:{lineno}: a face needs at least 3 corners, got {line.strip()!r}")
            n_poly += len(poly) > 3
            tris.extend(_fan(poly))
    if corner_uvs is not None:
        uv = np.asarray(texcoords, dtype=np.float64).reshape(-1, 2)
        corner_uvs.append(uv[np.asarray(tri_uv, dtype=np.int64).reshape(-1, 3)])
    return np.asarray(points, dtype=np.float64).reshape(-1, 3), np.asarray(tris, dtype=np.int64).reshape(-1, 3), n_poly


def _vertex_index(corner: str, n: int, path: str, lineno: int, line: str) -> int:
    """The 0-based vertex index of an OBJ face corner ``v[/vt[/vn]]`` (``n`` vertices read so far): OBJ indices are
    1-based, negative ones count back from the last vertex read."""
    try:
        i = int(corner.split("/", 1)[0])
    except ValueError:
        raise ValueError(f"{path}:{lineno}: bad face corner {corner!r} in {line.strip()!r}") from None
    j = i - 1 if i > 0 else n + i
    if i == 0 or not 0 <= j < n:
        raise ValueError(f"{path}:{lineno}: face index {i} refers to no vertex read so far ({n} read)")
    return j


def _uv_index(corner: str, n: int, path: str, lineno: int, line: str) -> int:
    """The 0-based ``vt`` index of an OBJ face corner ``v/vt[/vn]`` (``n`` texture coordinates read so far)."""
    parts = corner.split("/")
    try:
        i = int(parts[1])
    except (IndexError, ValueError):
        raise ValueError(f"{path}:{lineno}: face corner {corner!r} has no texture coordinate index (uvs=True needs "
                         f"v/vt corners): {line.strip()!r}") from None
    j = i - 1 if i > 0 else n + i
    if i == 0 or not 0 <= j < n:
        raise ValueError(f"{path}:{lineno}: texture coordinate index {i} refers to no vt read so far ({n} read)")
    return j


def _read_meshio(path: str) -> tuple[np.ndarray, np.ndarray, int]:
    """``(points (N, 3), triangles (F, 3), polygons fan-triangulated)`` of any file meshio reads."""
    meshio = require("meshio", f"reading {path} (.obj files are read without it)")
    out = StringIO()
    try:  # meshio prints its reasons and, for a file it cannot parse, calls sys.exit
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            m = meshio.read(path)
    except (Exception, SystemExit) as e:  # ReadError, KeyError, struct.error, SystemExit, ...
        m = _read_meshio_without_bom(meshio, path)
        if m is None:
            why = " ".join(out.getvalue().split()) or f"{type(e).__name__}: {e}"
            raise ValueError(f"cannot read mesh file {path}: {why}") from None
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise ValueError(f"{path}: points must be 2D or 3D, got shape {pts.shape}")
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.zeros((len(pts), 1))], 1)
    tris, n_poly = [], 0
    for block in m.cells:
        if block.type not in ("triangle", "quad") and not block.type.startswith("polygon"):
            continue  # lines, vertices, volume cells, higher-order elements
        data = np.asarray(block.data, dtype=np.int64)
        k = data.shape[1]
        if k > 3:
            n_poly += len(data)
        tris.extend(np.stack([data[:, 0], data[:, j], data[:, j + 1]], 1) for j in range(1, k - 1))
    faces = np.concatenate(tris, 0) if tris else np.zeros((0, 3), dtype=np.int64)
    return pts, faces, n_poly


_BOM = b"\xef\xbb\xbf"  # the UTF-8 byte-order mark some editors and exporters write first


def _read_meshio_without_bom(meshio, path: str):
    """meshio's reading of a text file that begins with a UTF-8 byte-order mark (which meshio's text readers
    take for part of the first line: ``ply``, ``OFF``, ...) from a copy without it; ``None`` if the file has
    no mark or the copy cannot be read either.  Tried only after the file itself failed to read (a binary
    file may begin with these bytes)."""
    import tempfile

    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError:
        return None
    if not data.startswith(_BOM):
        return None
    with tempfile.TemporaryDirectory() as tmp:
        copy = os.path.join(tmp, os.path.basename(path))
        with open(copy, "wb") as fh:
            fh.write(data[len(_BOM):])
        try:
            with contextlib.redirect_stdout(StringIO()), contextlib.redirect_stderr(StringIO()):
                return meshio.read(copy)
        except (Exception, SystemExit):
            return None


Cleaned = tuple[Tensor, Tensor] | tuple[Tensor, Tensor, MeshReport]


@overload
def load(path, *, weld_tol: float | None = ..., dtype=..., device=...,
         report: Literal[False] = ..., uvs: Literal[False] = ...) -> tuple[Tensor, Tensor]: ...
@overload
def load(path, *, weld_tol: float | None = ..., dtype=..., device=...,
         report: Literal[True], uvs: Literal[False] = ...) -> tuple[Tensor, Tensor, MeshReport]: ...
@overload
def load(path, *, weld_tol: float | None = ..., dtype=..., device=..., report: bool = ...,
         uvs: Literal[True]) -> tuple: ...
@overload
def load(path, *, weld_tol: float | None = ..., dtype=..., device=..., report: bool = ..., uvs: bool = ...) -> tuple: ...


def load(path, *, weld_tol: float | None = 1e-6, dtype=torch.float64, device=None, report: bool = False,
         uvs: bool = False) -> tuple:
    """Read a triangle mesh and :func:`clean` it.

    Args:
        path: an ``.obj`` file (read without dependencies), or any format meshio reads (``.ply``, ``.stl``,
            ``.off``, ``.vtk``, ...).  Polygons are fan-triangulated.  A UTF-8 byte-order mark at the start
            of a text file is skipped.
        weld_tol: vertices closer than ``weld_tol`` times the bounding-box diagonal are merged (UV seams);
            ``None`` or ``0`` keeps every vertex.
        dtype, device: of the returned positions (faces are ``int64`` on ``device``).
        report: also return a :class:`MeshReport`.
        uvs: also return the texture (pattern) coordinates of each face corner, ``(F, 3, 2)`` in ``dtype``: per
            corner, so that a UV seam survives the welding of its 3-D vertices (OBJ files with ``v/vt`` corners;
            :func:`save_obj` writes them back).

    Returns:
        ``positions (V, 3)`` [file units, m for the energies], ``faces (F, 3)`` int64 0-indexed, counter-clockwise
        as in the file, with ``uvs=True`` the corner UVs ``(F, 3, 2)``, and with ``report=True`` the
        :class:`MeshReport` (last).

    Raises ``ValueError`` naming the path for a missing or unreadable file, bad indices or no triangles.
    Warns (``UserWarning``) when unused vertices or degenerate faces are dropped.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"mesh file not found: {path}")
    corner_uvs: list = []
    if uvs and not path.lower().endswith(".obj"):
        raise ValueError(f"uvs=True reads the texture coordinates of OBJ files; {path} is not one")
    points, tris, n_poly = _read_obj(path, corner_uvs if uvs else None) if path.lower().endswith(".obj") else _read_meshio(path)
    if len(tris) == 0:
        raise ValueError(f"{path} holds no triangles or polygons ({len(points)} vertices)")
    positions = torch.as_tensor(points, dtype=dtype, device=device)
    kept: list = []
    out = _clean(positions, tris, weld_tol, report, source=path, polygons=n_poly, kept=kept)
    if not uvs:
        return out
    uv = torch.as_tensor(corner_uvs[0][kept[0]], dtype=dtype, device=device)
    return (*out[:2], uv, *out[2:])


@overload
def clean(positions, faces, *, weld_tol: float | None = ..., report: Literal[False] = ...) -> tuple[Tensor, Tensor]: ...
@overload
def clean(positions, faces, *, weld_tol: float | None = ..., report: Literal[True]) -> tuple[Tensor, Tensor, MeshReport]: ...
@overload
def clean(positions, faces, *, weld_tol: float | None = ..., report: bool = ...) -> Cleaned: ...


def clean(positions, faces, *, weld_tol: float | None = 1e-6, report: bool = False) -> Cleaned:
    """Weld, drop degenerate faces and unused vertices of an in-memory mesh (what :func:`load` does).

    Args:
        positions: ``(V, 3)`` float tensor [m] (or array-like); the result follows its dtype and device and,
            being an index selection of it, its autograd graph.
        faces: ``(F, 3)`` integer vertex indices, 0-indexed.
        weld_tol: relative welding distance (see :func:`load`); ``None`` or ``0`` disables welding.  Merged
            vertices take the position of the first (lowest-index) vertex of their cluster, and the kept
            vertices keep their relative order.  Clusters are the connected components of "closer than
            the welding distance", so a chain of close vertices welds into one.
        report: also return a :class:`MeshReport`.

    Returns ``positions (V', 3)``, ``faces (F', 3)`` int64 (and the report).
    """
    pos = torch.as_tensor(positions)
    if not pos.is_floating_point():
        pos = pos.to(torch.get_default_dtype())
    f = faces.detach().cpu().numpy() if isinstance(faces, Tensor) else np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and not np.issubdtype(f.dtype, np.integer)):
        raise ValueError(f"faces must be an (F, 3) integer array, got shape {tuple(f.shape)} and dtype {f.dtype}")
    if f.shape[0] == 0:
        raise ValueError("faces is empty: a mesh needs at least one triangle")
    return _clean(pos, f.astype(np.int64), weld_tol, report)


def _weld(P: np.ndarray, used: np.ndarray, weld_tol) -> tuple[np.ndarray, float | None]:
    """``(rep (V,), r)``: each vertex's representative (the lowest index of its cluster, the connected component
    of "closer than r" among the ``used`` vertices) and the weld distance ``r = weld_tol * diagonal`` (None:
    ``weld_tol`` None or 0, no welding)."""
    V = P.shape[0]
    rep = np.arange(V)
    if weld_tol is None or float(weld_tol) == 0:
        return rep, None
    weld_tol = float(weld_tol)
    if not (weld_tol > 0 and np.isfinite(weld_tol)):
        raise ValueError(f"weld_tol must be positive and finite (or None / 0 to disable), got {weld_tol}")
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import KDTree

    Pu = P[used]
    r = weld_tol * float(np.linalg.norm(Pu.max(0) - Pu.min(0)))
    pairs = used[KDTree(Pu).query_pairs(r, output_type="ndarray")]
    if len(pairs):
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(V, V))
        _, labels = connected_components(graph, directed=False)
        first = np.full(labels.max() + 1, V, dtype=np.int64)
        np.minimum.at(first, labels, np.arange(V))
        rep = first[labels]
    return rep, r


def _clean(pos: Tensor, F: np.ndarray, weld_tol, want_report: bool, source: str | None = None,
           polygons: int = 0, kept: list | None = None) -> Cleaned:
    """:func:`clean`; ``kept``: a list to which the mask of the input faces that remain is appended."""
    where = f"{source}: " if source is not None else ""
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"{where}positions must have shape (V, 3), got {tuple(pos.shape)}")
    V = pos.shape[0]
    if int(F.min()) < 0 or int(F.max()) >= V:
        if int(F.min()) == 1 and int(F.max()) == V:
            raise ValueError(where + _one_indexed_message(V))
        bad = np.nonzero(((F < 0) | (F >= V)).any(1))[0]
        raise ValueError(f"{where}vertex index out of range [0, {V}) in faces {bad[:8].tolist()}")
    P = pos.detach().cpu().to(torch.float64).numpy()
    used0 = np.flatnonzero(np.bincount(F.reshape(-1), minlength=V))  # np.unique(F), without its hashing
    bad_v = used0[~np.isfinite(P[used0]).all(1)]
    if bad_v.size:
        raise ValueError(f"{where}non-finite (NaN or Inf) coordinates at vertices {bad_v[:8].tolist()}")

    # 1. weld: cluster = connected component of "closer than r"; representative = lowest index
    rep, r = _weld(P, used0, weld_tol)
    welded = int((rep[used0] != used0).sum())
    F = rep[F]

    # 2. degenerate faces
    degenerate = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0])
    if kept is not None:
        kept.append(~degenerate)
    n_degenerate = int(degenerate.sum())
    if n_degenerate:
        F = F[~degenerate]
        warnings.warn(f"{where}dropped {n_degenerate} degenerate faces (a vertex repeated"
                      f"{' after welding' if welded else ''})", UserWarning, stacklevel=3)
        if len(F) == 0:
            raise ValueError(f"{where}no triangles left after dropping degenerate faces")

    # 3. unused vertices (welded-away duplicates are not counted)
    keep = np.flatnonzero(np.bincount(F.reshape(-1), minlength=V))
    n_unused = int(np.count_nonzero(rep == np.arange(V))) - len(keep)
    if n_unused:
        warnings.warn(f"{where}removed {n_unused} unused vertices (used by no face)", UserWarning, stacklevel=3)
    new_index = np.full(V, -1, dtype=np.int64)
    new_index[keep] = np.arange(len(keep))
    F = new_index[F]

    idx = torch.as_tensor(keep, device=pos.device)
    out_pos = pos.index_select(0, idx)
    out_faces = torch.as_tensor(F, dtype=torch.int64, device=pos.device)
    if not want_report:
        return out_pos, out_faces
    rep_obj = MeshReport(source=source, vertices_read=V, faces_read=len(F) + n_degenerate,
                         polygons_triangulated=polygons, weld_distance=r, welded=welded,
                         degenerate_faces_dropped=n_degenerate, unused_removed=n_unused,
                         vertices=len(keep), faces=len(F))
    _analyse_edges(F, len(keep), rep_obj)
    return out_pos, out_faces, rep_obj


def _analyse_edges(F: np.ndarray, V: int, report: MeshReport) -> None:
    """Fill the edge counts of ``report`` (the same edge and orientation rules as HingeTopology.from_faces)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    src = np.roll(F, -1, axis=1).reshape(-1)
    dst = np.roll(F, -2, axis=1).reshape(-1)
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    keys, inverse, counts = np.unique(lo * V + hi, return_inverse=True, return_counts=True)
    fwd = np.bincount(inverse.reshape(-1), weights=src < dst, minlength=len(keys))
    pair = lambda e: (int(keys[e] // V), int(keys[e] % V))  # noqa: E731
    report.edge_count = len(keys)
    report.hinge_count = int((counts == 2).sum())
    report.non_manifold_edges = [pair(e) for e in np.nonzero(counts > 2)[0]]
    report.inconsistent_edges = [pair(e) for e in np.nonzero((counts == 2) & (fwd != 1))[0]]
    boundary = keys[counts == 1]
    report.boundary_edge_count = len(boundary)
    if len(boundary):
        a, b = boundary // V, boundary % V
        verts, ab = np.unique(np.concatenate([a, b]), return_inverse=True)
        n = len(verts)
        graph = coo_matrix((np.ones(len(a)), (ab[: len(a)], ab[len(a):])), shape=(n, n))
        report.boundary_loop_count = int(connected_components(graph, directed=False)[0])


# ---------------------------------------------------------------------------------------------------- writing


def _mesh_arrays(positions, faces) -> tuple[np.ndarray, np.ndarray]:
    """``(positions (V, 3) float64, faces (F, 3) int64)`` as NumPy arrays, checked (ValueError naming the bad one)."""
    P = np.asarray(torch.as_tensor(positions).detach().cpu(), dtype=np.float64)
    Fa = np.asarray(torch.as_tensor(faces).detach().cpu(), dtype=np.int64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"positions must have shape (V, 3), got {P.shape}")
    if Fa.ndim != 2 or Fa.shape[1] != 3 or (Fa.size and (Fa.min() < 0 or Fa.max() >= len(P))):
        raise ValueError(f"faces must have shape (F, 3) with indices in [0, {len(P)})")
    return P, Fa


def save_obj(path, positions, faces, uvs=None, *, header: str | None = None) -> None:
    """Write a Wavefront OBJ file: ``v`` lines (9 significant digits), ``vt`` lines when ``uvs`` is given,
    1-indexed faces.

    Args:
        positions: ``(V, 3)`` [m]; faces: ``(F, 3)`` 0-indexed.
        uvs: texture/pattern coordinates, either ``(V, 2)`` (one per vertex, faces written ``f a/a b/b c/c``) or
            ``(F, 3, 2)`` (one per face corner, as :func:`load` with ``uvs=True`` returns them, so that seams
            survive: ``vt`` lines in corner order, faces written ``f a/k b/k+1 c/k+2``).
        header: comment lines written first (``# `` is prepended to each).
    """
    P, Fa = _mesh_arrays(positions, faces)
    lines = [f"# {h}" for h in header.splitlines()] if header else []
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in P]
    if uvs is not None:
        T = np.asarray(torch.as_tensor(uvs).detach().cpu(), dtype=np.float64)
        if T.shape == (len(Fa), 3, 2):
            lines += [f"vt {u:.9g} {v:.9g}" for u, v in T.reshape(-1, 2)]
            corners = np.arange(1, 3 * len(Fa) + 1).reshape(-1, 3)
            lines += ["f " + " ".join(f"{i}/{k}" for i, k in zip(f, c)) for f, c in zip((Fa + 1).tolist(), corners.tolist())]
        elif T.shape == (len(P), 2):
            lines += [f"vt {u:.9g} {v:.9g}" for u, v in T]
            lines += ["f " + " ".join(f"{i}/{i}" for i in f) for f in (Fa + 1).tolist()]
        else:
            raise ValueError(f"uvs must have shape ({len(P)}, 2) (per vertex) or ({len(Fa)}, 3, 2) (per face corner), "
                             f"got {T.shape}")
    else:
        lines += ["f " + " ".join(str(i) for i in f) for f in (Fa + 1).tolist()]
    with open(os.fspath(path), "w", encoding="utf-8", newline="\n") as fh:
        fh.write("\n".join(lines) + "\n")


def save(path, positions, faces, uvs=None, *, header: str | None = None) -> None:
    """Write a triangle mesh in the format its extension names: ``.obj`` by :func:`save_obj` (no dependency, with
    ``uvs`` and ``header``), any other format meshio writes (``.ply``, ``.stl``, ``.off``, ``.vtk``, ...) through
    meshio (the ``io`` extra; ``uvs`` and ``header`` are OBJ's only).  ``positions (V, 3)``, ``faces (F, 3)``
    0-indexed.  For an animation, write one file per saved step (``frame_0001.ply``, ...), as the scene runner
    does with OBJ."""
    path = os.fspath(path)
    if path.lower().endswith(".obj"):
        save_obj(path, positions, faces, uvs, header=header)
        return
    if uvs is not None or header is not None:
        raise ValueError(f"uvs and header are written to OBJ files only, not to {path}")
    P, Fa = _mesh_arrays(positions, faces)
    meshio = require("meshio", f"writing {path} (.obj files are written without it)")
    try:
        meshio.write_points_cells(path, P, [("triangle", Fa)])
    except Exception as e:  # meshio's unknown-format and writer errors
        raise ValueError(f"cannot write {path}: {type(e).__name__}: {e}") from None
