import dataclasses

import numpy as np
import pytest
import torch

import torchbend as tb
from torchbend import HingeTopology


def test_single_hinge_stencil():
    _, faces = tb.scenes.single_hinge(0.3)
    topo = HingeTopology.from_faces(faces)
    assert topo.hinges.tolist() == [[0, 1, 2, 3]]
    assert topo.hinge_faces.tolist() == [[0, 1]]
    assert topo.vertex_count == 4 and topo.hinge_count == 1 and topo.face_count == 2
    assert topo.boundary_edges.shape == (4, 2)


def test_swapped_faces_keep_stencil_order():
    # same hinge, faces listed the other way round and rotated: stencil is still (0, 1, 2, 3)
    topo = HingeTopology.from_faces([[3, 1, 0], [2, 0, 1]])
    assert topo.hinges.tolist() == [[0, 1, 2, 3]]
    assert topo.hinge_faces.tolist() == [[1, 0]]


@pytest.mark.parametrize("mesh", ["grid", "cylinder", "icosphere"])
def test_hinges_are_consistent_with_faces(mesh):
    if mesh == "grid":
        _, F = tb.scenes.grid(5, 4)
    elif mesh == "cylinder":
        _, F = tb.scenes.cylinder(6, 4)
    else:
        _, F = tb.scenes.icosphere(2)
    topo = HingeTopology.from_faces(F)
    H, Fa = topo.hinges.numpy(), topo.faces.numpy()
    # deterministic order: sorted by (i0, i1), i0 < i1
    assert (H[:, 0] < H[:, 1]).all()
    keys = H[:, 0] * topo.vertex_count + H[:, 1]
    assert (np.diff(keys) > 0).all()
    # Euler: every edge is a hinge or a boundary edge, 3F = 2 H + B
    assert 3 * len(Fa) == 2 * len(H) + len(topo.boundary_edges)
    if mesh == "icosphere":
        assert len(topo.boundary_edges) == 0

    def cyclic(face, tri):
        return any(list(np.roll(face, r)) == tri for r in range(3))

    for h, (fa, fb) in zip(H, topo.hinge_faces.numpy()):
        assert cyclic(Fa[fa], [h[0], h[1], h[2]])  # triangle A = (x0, x1, x2) CCW
        assert cyclic(Fa[fb], [h[1], h[0], h[3]])  # triangle B = (x1, x0, x3) CCW
    # per-triangle edge maps: local edge k joins faces[f, k+1] -> faces[f, k+2]
    E = topo.edges.numpy()
    for f in range(len(Fa)):
        for k in range(3):
            s, d = Fa[f, (k + 1) % 3], Fa[f, (k + 2) % 3]
            e = int(topo.face_edges[f, k])
            assert sorted((s, d)) == list(E[e])
            assert topo.face_edge_signs[f, k].item() == (1 if s < d else -1)
            h = int(topo.face_edge_hinges[f, k])
            assert h == topo.edge_hinges[e].item()
            if h >= 0:
                assert sorted(H[h, :2]) == sorted((s, d))
                assert topo.hinge_faces[h, 0 if s < d else 1].item() == f


def test_to_device_copies_fields():
    _, F = tb.scenes.grid(3, 3)
    topo = HingeTopology.from_faces(F).to("cpu")
    assert topo.hinges.device.type == "cpu" and topo.vertex_count == 9


def test_to_after_hessian_keeps_index_dtype_and_is_an_immutable_value():
    """Nothing is cached on the topology (the CSR pattern lives on the energy), so .to() works after a
    Hessian was built; a dtype argument leaves the int64 index tensors alone (as nn.Module.to)."""
    rest, F = tb.scenes.random_curved_sheet(4, 4, dtype=torch.float64)
    bend = tb.BendingEnergy(F, rest, model="quadratic", stiffness=1.0)
    bend.hessian(rest + 0.01)
    topo = bend.topology
    for args in ((torch.float32,), ("cpu",), ("cpu", torch.float64), ()):
        moved = topo.to(*args)
        assert moved is not topo and moved.vertex_count == topo.vertex_count
        assert moved.hinges.dtype == torch.int64 and torch.equal(moved.hinges, topo.hinges)
        assert torch.equal(moved.face_edge_signs, topo.face_edge_signs)
    assert set(vars(topo)) == {f.name for f in dataclasses.fields(HingeTopology)}
    with pytest.raises(dataclasses.FrozenInstanceError):
        topo.vertex_count = 3  # type: ignore[misc]


@pytest.mark.parametrize(
    "faces, match",
    [
        (torch.tensor([[0.0, 1.0, 2.0]]), "integer"),
        (np.array([[0.5, 1, 2]]), "integers"),
        (torch.tensor([0, 1, 2]), r"shape \(F, 3\)"),
        (torch.zeros((0, 3), dtype=torch.int64), "empty"),
        (torch.tensor([[0, 1, 2], [0, -1, 2]]), r"negative.*faces \[1\]"),
        (torch.tensor([[0, 1, 1]]), r"repeat a vertex.*faces \[0\]"),
        (torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]]), r"non-manifold edge \(0, 1\).*3 faces \[0, 1, 2\]"),
        (torch.tensor([[0, 1, 2], [0, 1, 3]]), r"inconsistently oriented.*edge \(0, 1\) in faces \[0, 1\]"),
    ],
)
def test_invalid_topology(faces, match):
    with pytest.raises(ValueError, match=match):
        HingeTopology.from_faces(faces)


def test_index_out_of_range_names_faces():
    with pytest.raises(ValueError, match=r"out of range \[0, 4\) in faces \[1\]"):
        HingeTopology.from_faces([[0, 1, 2], [1, 0, 7]], vertex_count=4)
