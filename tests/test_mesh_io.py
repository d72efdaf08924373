"""Mesh files: ``tb.mesh.load`` / ``clean`` (OBJ with UV seams, polygons, PLY), welding, the report, the shipped skirt."""
import math
import os
import warnings

import numpy as np
import pytest
import torch

import torchbend as tb
from torchbend.mesh.garments import skirt, write_skirt_asset


def write(path, text: str) -> str:
    with open(path, "w") as fh:
        fh.write(text)
    return str(path)


def seamed_grid_obj(path, nx=6, ny=5, cut=3, scale=1.0, jitter=0.0) -> tuple[str, torch.Tensor, torch.Tensor]:
    """A ``grid(nx, ny)`` exported as two UV islands: columns ``<= cut`` and ``>= cut``, the seam column
    duplicated (``jitter`` [relative] moves the copies apart), ``f v/vt`` faces, 1-indexed.
    Returns ``(path, seamless positions, seamless faces)``."""
    rest, faces = tb.scenes.grid(nx, ny, dtype=torch.float64)
    rest = rest * scale
    col = torch.arange(nx * ny) % nx
    a_ids = torch.nonzero(col <= cut).reshape(-1).tolist()
    b_ids = torch.nonzero(col >= cut).reshape(-1).tolist()
    index_a = {v: k for k, v in enumerate(a_ids)}
    index_b = {v: len(a_ids) + k for k, v in enumerate(b_ids)}
    lines = ["# two UV islands, seam column duplicated", "mtllib cloth.mtl", "o cloth"]
    for k, v in enumerate(a_ids + b_ids):
        x, y, z = rest[v].tolist()
        dz = jitter * scale * (1 if k >= len(a_ids) else 0)
        lines.append(f"v {x!r} {y!r} {z + dz!r}")
    for k, v in enumerate(a_ids + b_ids):
        x, y, _ = rest[v].tolist()
        lines.append(f"vt {x / scale + (0.5 if k >= len(a_ids) else 0.0)!r} {y / scale!r}")
    lines.append("usemtl cloth")
    for f in faces.tolist():
        island = index_a if min(col[i].item() for i in f) < cut else index_b
        lines.append("f " + " ".join(f"{island[i] + 1}/{island[i] + 1}" for i in f))
    return write(path, "\n".join(lines) + "\n"), rest, faces


def bent(x: torch.Tensor) -> torch.Tensor:
    """A smooth out-of-plane deformation of positions ``(V, 3)`` (a function of position only)."""
    s = x[:, 0].abs().max() + x[:, 1].abs().max()
    u, v = x[:, 0] / s, x[:, 1] / s
    return x + s * torch.stack((0 * u, 0 * u, 0.2 * torch.sin(3 * u) * torch.cos(2 * v) + 0.3 * u * u), -1)


def sorted_rows(x: torch.Tensor) -> np.ndarray:
    a = x.detach().numpy()
    return a[np.lexsort(a.T[::-1])]


def test_obj_with_uv_seams_welds_to_the_seamless_mesh(tmp_path):
    path, rest, faces = seamed_grid_obj(tmp_path / "seam.obj")
    seamless = tb.HingeTopology.from_faces(faces, len(rest))
    x, f, report = tb.mesh.load(path, report=True)
    assert (report.vertices_read, report.welded, report.vertices) == (35, 5, 30)
    assert x.dtype == torch.float64 and f.dtype == torch.int64 and int(f.min()) == 0
    np.testing.assert_array_equal(sorted_rows(x), sorted_rows(rest))
    topo = tb.HingeTopology.from_faces(f, len(x))
    assert topo.hinge_count == seamless.hinge_count == report.hinge_count
    assert report.boundary_edge_count == len(seamless.boundary_edges) and report.boundary_loop_count == 1
    # same energy for the same deformation (a function of position, so vertex order does not matter)
    stiff = 0.7
    e_ref = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=stiff)(bent(rest))
    e = tb.BendingEnergy(f, x, model="quadratic", stiffness=stiff)(bent(x))
    assert e_ref > 0 and torch.allclose(e, e_ref, rtol=1e-12, atol=0)

    # unwelded: each of the 4 seam edges is two boundary edges and loses its hinge (and its energy)
    xu, fu, ru = tb.mesh.load(path, weld_tol=None, report=True)
    assert (ru.vertices, ru.welded, ru.weld_distance) == (35, 0, None)
    assert tb.HingeTopology.from_faces(fu, len(xu)).hinge_count == seamless.hinge_count - 4 == ru.hinge_count
    assert ru.boundary_edge_count == report.boundary_edge_count + 2 * 4 and ru.boundary_loop_count == 2
    assert tb.BendingEnergy(fu, xu, model="quadratic", stiffness=stiff)(bent(xu)) < e_ref
    assert torch.equal(tb.mesh.load(path, weld_tol=0)[1], fu)
    assert "5 vertices welded" in str(report) and "Manifold and consistently oriented" in str(report)


@pytest.mark.parametrize("scale", [1e-4, 1.0, 1e4])
def test_weld_tolerance_is_relative_to_the_mesh_size(tmp_path, scale):
    # seam copies 1e-8 (relative) apart weld at every scale; grid neighbours (0.2 relative) never do
    path, rest, faces = seamed_grid_obj(tmp_path / "seam.obj", scale=scale, jitter=1e-8)
    x, f, report = tb.mesh.load(path, report=True)
    assert report.vertices == 30 and report.welded == 5
    assert report.weld_distance == pytest.approx(1e-6 * scale * math.sqrt(2), rel=1e-12)
    assert tb.HingeTopology.from_faces(f, len(x)).hinge_count == tb.HingeTopology.from_faces(faces).hinge_count
    np.testing.assert_allclose(sorted_rows(x), sorted_rows(rest), rtol=0, atol=2e-8 * scale)
    # a tolerance below the copies' distance keeps them apart
    assert tb.mesh.load(path, weld_tol=1e-9, report=True)[2].welded == 0


def test_obj_polygons_negative_indices_and_corner_forms(tmp_path):
    path = write(tmp_path / "poly.obj", "\n".join([
        "# a quad, a pentagon and a triangle", "v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0",
        "vn 0 0 1", "vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1", "g panel", "s off",
        "f 1/1/1 2/2/1 3/3/1 4/4/1",             # quad, v/vt/vn
        "v 2 0 0", "v 2.5 0.5 0", "v 2 1 0",
        "f 2//1 -3//1 -2//1 -1//1 \\", " 3//1",  # pentagon 2, 5, 6, 7, 3: v//vn, negative, continued line
        "v 1 2 0 0.5 0.5 0.5",                   # vertex colour ignored
        "f -5 -2 -1",                            # triangle 4, 7, 8 with negative indices
        "l 1 2",
    ]) + "\n")
    x, f, report = tb.mesh.load(path, report=True)
    assert f.tolist() == [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 6], [1, 6, 2], [3, 6, 7]]
    assert report.polygons_triangulated == 2 and report.faces == 6 and report.vertices == 8
    assert x[7].tolist() == [1.0, 2.0, 0.0]
    # the quad and the pentagon each triangulate into a fan: every face keeps the polygon's orientation (+z)
    x0, x1, x2 = x[f].unbind(1)
    assert (torch.linalg.cross(x1 - x0, x2 - x0)[:, 2] > 0).all()
    assert report.hinge_count == tb.HingeTopology.from_faces(f).hinge_count == 4  # edges 0-2, 1-2, 1-5, 1-6


def test_unused_vertices_are_dropped_with_a_warning(tmp_path):
    path = write(tmp_path / "unused.obj", "v 0 0 0\nv 9 9 9\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 7 7 7\nf 1 3 4\nf 3 5 4\n")
    with pytest.warns(UserWarning, match="removed 2 unused vertices"):
        x, f, report = tb.mesh.load(path, report=True)
    assert x.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
    assert f.tolist() == [[0, 1, 2], [1, 3, 2]] and report.unused_removed == 2
    # the far unused vertices do not enter the welding distance (bounding box of the used ones)
    assert report.weld_distance == pytest.approx(1e-6 * math.sqrt(2))
    # in memory: the same, following the input's dtype and autograd graph
    pos = torch.tensor([[0, 0, 0], [9, 9, 9], [1, 0, 0], [0, 1, 0]], dtype=torch.float32, requires_grad=True)
    with pytest.warns(UserWarning, match="removed 1 unused"):
        xc, fc = tb.mesh.clean(pos, [[0, 2, 3]])
    assert xc.dtype == torch.float32 and fc.tolist() == [[0, 1, 2]]
    xc.sum().backward()
    assert pos.grad is not None and pos.grad[:, 0].tolist() == [1, 0, 1, 1]


def test_faces_made_degenerate_by_welding_are_dropped(tmp_path):
    # a sliver whose two corners lie 1e-9 apart: welding collapses it
    pos = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1e-9, 0], [1, 1, 0]], dtype=torch.float64)
    faces = [[0, 1, 2], [1, 3, 4], [1, 4, 2]]
    with pytest.warns(UserWarning, match="dropped 1 degenerate faces"):
        x, f, report = tb.mesh.clean(pos, faces, report=True)
    assert f.tolist() == [[0, 1, 2], [1, 3, 2]] and report.welded == 1 and report.degenerate_faces_dropped == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no welding: nothing dropped, nothing to warn about
        assert tb.mesh.clean(pos, faces, weld_tol=None)[1].shape == (3, 3)


def test_ply_and_quads_through_meshio(tmp_path):
    meshio = pytest.importorskip("meshio")
    rest, faces = tb.scenes.grid(4, 3, dtype=torch.float64)
    for binary in (True, False):
        path = str(tmp_path / f"grid_{binary}.ply")
        meshio.write_points_cells(path, rest.numpy(), [("triangle", faces.numpy())], binary=binary)
        x, f = tb.mesh.load(path, dtype=torch.float32)
        assert x.dtype == torch.float32 and torch.equal(f, faces)
        assert torch.allclose(x.double(), rest, rtol=0, atol=1e-7)
    quads = np.array([[0, 1, 5, 4], [1, 2, 6, 5]])
    path = str(tmp_path / "quads.ply")
    meshio.write_points_cells(path, rest.numpy(), [("quad", quads)])
    with pytest.warns(UserWarning, match="removed 6 unused"):
        x, f, report = tb.mesh.load(path, report=True)
    assert f.tolist() == [[0, 1, 4], [1, 2, 5], [0, 4, 3], [1, 5, 4]] and report.polygons_triangulated == 2


def test_bad_files_raise_value_errors_naming_the_path(tmp_path):
    with pytest.raises(ValueError, match="mesh file not found: .*nope.obj"):
        tb.mesh.load(tmp_path / "nope.obj")
    with pytest.raises(ValueError, match="not found"):
        tb.mesh.load(tmp_path)
    with pytest.raises(ValueError, match=r"empty.obj holds no triangles"):
        tb.mesh.load(write(tmp_path / "empty.obj", "v 0 0 0\nv 1 0 0\n"))
    with pytest.raises(ValueError, match=r"range.obj:3: face index 4 refers to no vertex"):
        tb.mesh.load(write(tmp_path / "range.obj", "v 0 0 0\nv 1 0 0\nf 1 2 4\n"))
    with pytest.raises(ValueError, match=r"bad.obj:1: bad vertex line"):
        tb.mesh.load(write(tmp_path / "bad.obj", "v 0 zero 0\n"))
    pytest.importorskip("meshio")
    with pytest.raises(ValueError, match="cannot read mesh file .*garbage.ply"):
        tb.mesh.load(write(tmp_path / "garbage.ply", "this is not a ply file\n"))
    with pytest.raises(ValueError, match="no shipped mesh named 'dress.obj'; available: .*skirt.obj"):
        tb.mesh.asset_path("dress.obj")


def test_report_names_non_manifold_and_inconsistent_edges_without_raising():
    pos = torch.tensor([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=torch.float64)
    fin = [[0, 1, 2], [1, 0, 3], [0, 1, 4]]  # edge (0, 1) shared by three faces
    _, _, report = tb.mesh.clean(pos, fin, report=True)
    assert report.non_manifold_edges == [(0, 1)] and not report.ok and report.hinge_count == 0
    assert "1 non-manifold edges, e.g. (0, 1)" in str(report)
    with pytest.raises(ValueError, match=r"non-manifold edge \(0, 1\) is shared by 3 faces"):
        tb.HingeTopology.from_faces(fin)
    flipped = [[0, 1, 2], [0, 1, 3]]  # both traverse 0 -> 1
    _, _, report = tb.mesh.clean(pos[:4], flipped, report=True)
    assert report.inconsistent_edges == [(0, 1)] and "inconsistently oriented neighbours" in str(report)
    with pytest.raises(ValueError, match="inconsistently oriented neighbours"):
        tb.HingeTopology.from_faces(flipped)


def test_one_indexed_faces_and_unused_vertices_get_clear_messages():
    rest, faces = tb.scenes.grid(4, 4, dtype=torch.float64)
    msg = r"faces look 1-indexed \(smallest index 1, largest 16 = V.*subtract 1"
    with pytest.raises(ValueError, match=msg):
        tb.HingeTopology.from_faces(faces + 1, vertex_count=16)
    with pytest.raises(ValueError, match=msg):
        tb.BendingEnergy(faces + 1, rest, stiffness=1.0)
    with pytest.raises(ValueError, match=msg):  # topology built without V: index 0 unused, V = 17
        tb.BendingEnergy(tb.HingeTopology.from_faces(faces + 1), rest, stiffness=1.0)
    with pytest.raises(ValueError, match=msg):
        tb.mesh.clean(rest, faces + 1)
    # unused vertices: accepted by HingeTopology (no hinge) when V is known ...
    extra = torch.cat([rest, rest[:1] + 5])
    bend = tb.BendingEnergy(faces, extra, stiffness=1.0)
    assert bend.topology.vertex_count == 17 and torch.equal(bend(extra), torch.zeros((), dtype=torch.float64))
    # ... and named when the topology was built for fewer vertices than the positions
    with pytest.raises(ValueError, match="vertex 16 is used by no face; tb.mesh.clean drops unused vertices"):
        tb.BendingEnergy(tb.HingeTopology.from_faces(faces), extra, stiffness=1.0)


def test_shipped_skirt_welds_to_a_tube():
    x, f, report = tb.mesh.load(tb.mesh.asset_path("skirt.obj"), report=True)
    n_around, n_along = 32, 12
    assert report.vertices_read == 2 * (n_around // 2 + 1) * n_along and report.welded == 2 * n_along
    assert (report.vertices, report.faces) == (n_around * n_along, 2 * n_around * (n_along - 1))
    assert report.ok and report.boundary_loop_count == 2 and report.boundary_edge_count == 2 * n_around
    assert report.vertices - report.edge_count + report.faces == 0  # Euler characteristic of a tube
    bend = tb.BendingEnergy(f, x, stiffness=1.0)
    assert bend.topology.hinge_count == report.hinge_count == report.edge_count - 2 * n_around
    assert float(bend(x)) == 0.0 and math.isfinite(float(bend(bent(x))))
    waist = x[:, 2] == 0
    assert int(waist.sum()) == n_around
    torch.testing.assert_close(x[waist, :2].norm(dim=1), torch.full((n_around,), 0.15, dtype=torch.float64))
    hem = x[:, 2] == -0.4
    torch.testing.assert_close(x[hem, :2].norm(dim=1), torch.full((n_around,), 0.3, dtype=torch.float64))
    x0, x1, x2 = x[f].unbind(1)  # outward normals
    n, c = torch.linalg.cross(x1 - x0, x2 - x0), (x0 + x1 + x2) / 3
    assert ((n[:, :2] * c[:, :2]).sum(1) > 0).all()
    # unwelded, as shipped: the 2 * (n_along - 1) seam edges are boundary edges
    _, _, raw = tb.mesh.load(tb.mesh.asset_path("skirt.obj"), weld_tol=None, report=True)
    assert raw.hinge_count == report.hinge_count - 2 * (n_along - 1)


def test_shipped_skirt_equals_a_regeneration(tmp_path):
    path = write_skirt_asset(str(tmp_path / "skirt.obj"))
    shipped = tb.mesh.load(tb.mesh.asset_path("skirt.obj"), weld_tol=None)
    fresh = tb.mesh.load(path, weld_tol=None)
    torch.testing.assert_close(shipped[0], fresh[0], rtol=0, atol=1e-9)
    assert torch.equal(shipped[1], fresh[1])
    x, f, uv = skirt(dtype=torch.float64)
    torch.testing.assert_close(fresh[0], x, rtol=0, atol=1e-9)
    assert torch.equal(fresh[1], f)
    # the UVs are the sewing pattern: edge lengths within 0.1% of the 3D ones (the cone is developable)
    e = f[:, :2]
    ratio = (uv[e[:, 0]] - uv[e[:, 1]]).norm(dim=1) / (x[e[:, 0]] - x[e[:, 1]]).norm(dim=1)
    assert float((ratio - 1).abs().max()) < 1e-3
    with open(path) as fh:
        lines = fh.read().splitlines()
    assert sum(ln.startswith("vt ") for ln in lines) == len(x) and any(ln.startswith("f ") and "/" in ln for ln in lines)
    assert os.path.getsize(tb.mesh.asset_path("skirt.obj")) < 100_000


def test_save_obj_round_trip_and_reading_without_meshio(tmp_path, monkeypatch):
    rest, faces = tb.scenes.random_curved_sheet(4, 3, dtype=torch.float64)
    path = str(tmp_path / "sheet.obj")
    tb.mesh.save_obj(path, rest, faces, header="a sheet\nin metres")
    monkeypatch.setitem(__import__("sys").modules, "meshio", None)  # OBJ files need no meshio
    x, f = tb.mesh.load(path)
    torch.testing.assert_close(x, rest, rtol=1e-8, atol=0)
    assert torch.equal(f, faces)
    with open(path) as fh:
        assert fh.readline() == "# a sheet\n"
    with pytest.raises(ImportError, match=r"needs the 'meshio' package: pip install 'torchbend\[io\]'"):
        tb.mesh.load(write(tmp_path / "sheet.ply", "ply\n"))


def test_corner_uvs_survive_a_welded_seam_and_round_trip(tmp_path):
    """A tube cut open along a seam (two vertices per seam point, UVs u = 0 and u = 1): load(uvs=True) welds the
    3-D vertices and keeps each face corner's own UV; save_obj writes them back per corner and a second load
    gives the same mesh and UVs.  Meshes without vt corners, and non-OBJ files, refuse uvs=True."""
    n, m = 8, 3
    ring = torch.arange(n + 1, dtype=torch.float64) / n  # u = 0 .. 1: the last column repeats the first in 3-D
    u, h = torch.meshgrid(ring, torch.arange(m, dtype=torch.float64) / (m - 1), indexing="ij")
    angle = 2 * torch.pi * u.reshape(-1)
    pos = torch.stack((torch.cos(angle), torch.sin(angle), h.reshape(-1)), -1)
    pos[-m:] = pos[:m]  # exactly the same 3-D points on both sides of the seam
    idx = torch.arange((n + 1) * m).reshape(n + 1, m)
    a, b, c, d = idx[:-1, :-1].reshape(-1), idx[1:, :-1].reshape(-1), idx[1:, 1:].reshape(-1), idx[:-1, 1:].reshape(-1)
    faces = torch.cat((torch.stack((a, b, c), -1), torch.stack((a, c, d), -1)))
    uv_vertex = torch.stack((u.reshape(-1), h.reshape(-1)), -1)
    path = tmp_path / "tube.obj"
    tb.mesh.save_obj(path, pos, faces, uv_vertex)  # per-vertex UVs: the seam's vertices are distinct in the file
    x, f, uv = tb.mesh.load(path, uvs=True)
    assert len(x) == n * m and len(f) == len(faces)  # welded: one vertex per seam point
    assert torch.allclose(uv, uv_vertex[faces], atol=1e-9)  # the corner UVs of the file, face by face
    assert float(uv[..., 0].max()) == 1.0 and float(uv[..., 0].min()) == 0.0  # both sides of the seam kept
    out = tmp_path / "tube_corners.obj"
    tb.mesh.save(out, x, f, uv)
    x2, f2, uv2, report = tb.mesh.load(out, uvs=True, report=True)
    assert torch.equal(f2, f) and torch.allclose(x2, x, atol=1e-8) and torch.allclose(uv2, uv, atol=1e-9)
    assert report.vertices == n * m
    tb.mesh.save_obj(tmp_path / "plain.obj", x, f)
    with pytest.raises(ValueError, match="has no texture coordinate index"):
        tb.mesh.load(tmp_path / "plain.obj", uvs=True)
    with pytest.raises(ValueError, match=r"uvs must have shape"):
        tb.mesh.save_obj(tmp_path / "bad.obj", x, f, uv[:3])


def test_save_ply_through_meshio(tmp_path):
    pytest.importorskip("meshio")
    x, f = tb.scenes.grid(4, 3, dtype=torch.float64)
    tb.mesh.save(tmp_path / "grid.ply", x, f)
    x2, f2 = tb.mesh.load(tmp_path / "grid.ply")
    assert torch.equal(f2, f) and torch.allclose(x2, x)
    with pytest.raises(ValueError, match="OBJ files only"):
        tb.mesh.save(tmp_path / "grid.ply", x, f, uvs=torch.zeros(len(x), 2))
    with pytest.raises(ValueError, match="cannot write"):
        tb.mesh.save(tmp_path / "grid.unknownformat", x, f)
