"""The edges of the input envelope: ClothLoss weights, BodyContact's power, Python-number parameters in the
positions' dtype, ClothModel's pinned vertices (mask or indices), unknown model names, files with a UTF-8
byte-order mark."""
import math

import pytest
import torch

import torchbend as tb
from torchbend import losses as L
from torchbend.energies import _bending_fn, _membrane_fn
from torchbend.energies.colliders import Capsule, Plane, Sphere
from torchbend.sim.model import ClothModel

F64 = torch.float64


@pytest.fixture(scope="module")
def mesh():
    rest, faces = tb.scenes.random_curved_sheet(4, 3, amplitude=0.3, seed=2, dtype=F64)
    return rest, faces


# ------------------------------------------------------------------------------------------ ClothLoss weights


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, torch.tensor(math.nan)])
def test_cloth_loss_rejects_a_non_finite_weight(mesh, bad):
    rest, faces = mesh
    terms = {"gravity": L.Gravity(faces, rest, 0.2), "bend": L.Bending(faces, rest, 1e-3)}
    with pytest.raises(ValueError, match="weight of term 'bend' must be finite"):
        L.ClothLoss(terms, {"bend": bad})


def test_cloth_loss_rejects_a_weight_made_non_finite_later(mesh):
    """``loss.weights`` may change between calls: a NaN set there is caught at the call, naming the term."""
    rest, faces = mesh
    loss = L.ClothLoss({"gravity": L.Gravity(faces, rest, 0.2), "bend": L.Bending(faces, rest, 1e-3)})
    x = rest + 0.01 * torch.randn_like(rest)
    total, _ = loss(x)
    assert torch.isfinite(total)
    loss.weights["gravity"] = math.nan
    with pytest.raises(ValueError, match="weight of term 'gravity' must be finite"):
        loss(x)
    loss.weights["gravity"] = "heavy"  # type: ignore[assignment]
    with pytest.raises(ValueError, match="weight of term 'gravity' must be a number"):
        loss(x)
    loss.weights["gravity"] = 0.5  # a finite one is fine again, and weighs the term
    total_half, values = loss(x)
    torch.testing.assert_close(total_half, 0.5 * values["gravity"] + values["bend"])


def test_cloth_loss_accepts_finite_and_zero_weights(mesh):
    rest, faces = mesh
    loss = L.ClothLoss({"gravity": L.Gravity(faces, rest, 0.2), "bend": L.Bending(faces, rest, 1e-3)},
                       {"gravity": -2.0, "bend": 0})
    total, values = loss(rest + 0.01 * torch.randn_like(rest))
    assert set(values) == {"gravity"}
    torch.testing.assert_close(total, -2.0 * values["gravity"])


# ---------------------------------------------------------------------------------------- BodyContact power


@pytest.mark.parametrize("power", [math.nan, math.inf, -math.inf, 0.0, -2.0, 1.0, 0.5])
def test_body_contact_rejects_a_bad_power(power):
    with pytest.raises(ValueError, match="BodyContact: power must be > 1 and finite"):
        L.BodyContact(stiffness=1.0, power=power, colliders=[Sphere()])


def test_body_contact_rejects_a_power_that_is_no_number():
    with pytest.raises(ValueError, match="BodyContact: power must be a number"):
        L.BodyContact(stiffness=1.0, power="cubic", colliders=[Sphere()])  # type: ignore[arg-type]


def test_body_contact_accepts_a_finite_power_above_one():
    term = L.BodyContact(stiffness=2.0, eps=0.0, power=2.5, colliders=[Plane()])
    x = torch.tensor([[0.0, 0.0, -0.1], [0.0, 0.0, 0.3]], dtype=F64)
    torch.testing.assert_close(term(x), torch.tensor(2.0 * 0.1 ** 2.5, dtype=F64), rtol=1e-14, atol=0)


# ------------------------------------------------------------------ Python numbers follow the positions' dtype


def _shell(center, radius: float, n: int, spread: float) -> torch.Tensor:
    """``n`` points near the sphere ``|x - center| = radius`` (within ``spread``), float64."""
    gen = torch.Generator().manual_seed(3)
    d = torch.randn(n, 3, generator=gen, dtype=F64)
    d = d / d.norm(dim=-1, keepdim=True)
    r = radius + spread * (2 * torch.rand(n, 1, generator=gen, dtype=F64) - 1)
    return torch.tensor(center, dtype=F64) + r * d


def test_body_contact_sphere_numbers_are_not_rounded_to_float32():
    """``sphere_center``/``sphere_radius`` given as Python numbers enter a float64 run in float64: the penalty
    matches a float64 reference to rounding (a float32 detour would be off by ~1e-7 relative)."""
    center, radius, eps, k = (0.1, 0.2, 0.3), 0.7, 0.05, 3.0
    x = _shell(center, radius, 64, 0.04)
    term = L.BodyContact(stiffness=k, eps=eps, power=3.0)
    E = term(x, sphere_center=center, sphere_radius=radius)
    s = (x - torch.tensor(center, dtype=F64)).norm(dim=-1) - radius
    ref = k * (eps - s).clamp_min(0).pow(3).sum()
    assert float(ref) > 0
    assert E.dtype == F64
    torch.testing.assert_close(E, ref, rtol=1e-13, atol=0)
    # float32 positions: a float32 result
    assert term(x.float(), sphere_center=center, sphere_radius=radius).dtype == torch.float32


def test_pinning_stiffness_number_is_not_rounded_to_float32():
    x = torch.randn(6, 3, dtype=F64)
    target = torch.randn(2, 3, dtype=F64)
    term = L.Pinning([1, 4], 0.1, target)
    d = x[[1, 4]] - target
    ref = 0.5 * (0.1 * (d * d).sum(-1)).sum(-1)
    torch.testing.assert_close(term(x), ref, rtol=1e-15, atol=0)
    assert term(x.float()).dtype == torch.float32


def test_capsule_with_number_end_points_is_not_rounded_to_float32():
    """A capsule moved with one tensor end point and one given as numbers (``transformed``): the number end
    keeps float64, so it is the same capsule as one built from numbers alone."""
    a, b, radius = (0.0, 0.0, 0.0), (0.1, 0.2, 0.3), 0.2
    gen = torch.Generator().manual_seed(1)
    x = 0.15 * torch.randn(40, 3, generator=gen, dtype=F64) + torch.tensor(b, dtype=F64) / 2
    plain = Capsule(a=a, b=b, radius=radius, stiffness=1e4, law="penalty")
    moved = Capsule(radius=radius, stiffness=1e4, law="penalty").transformed(torch.tensor(a, dtype=F64), list(b))
    assert float(plain.energy(x)) > 0
    torch.testing.assert_close(moved.energy(x), plain.energy(x), rtol=1e-14, atol=0)
    torch.testing.assert_close(moved.gradient(x), plain.gradient(x), rtol=1e-13, atol=1e-15)
    assert moved.energy(x.float()).dtype == torch.float32


@pytest.mark.parametrize("collider", [Sphere(center=(0.1, 0.2, 0.3), radius=0.7, stiffness=3.0, margin=0.01, law="penalty"),
                                      Plane(point=(0.1, 0.2, 0.3), normal=(0.3, 0.1, 1.0), stiffness=3.0, law="penalty"),
                                      Capsule(a=(0.1, 0.2, 0.3), b=(0.7, 0.1, 0.3), radius=0.3, stiffness=3.0, law="penalty")],
                         ids=["sphere", "plane", "capsule"])
def test_collider_numbers_follow_the_positions_dtype(collider):
    """The colliders' Python-number parameters are used in the positions' dtype: float64 energies match a float64
    evaluation of the signed distance, float32 positions give float32 results."""
    x = _shell((0.1, 0.2, 0.3), 0.7, 50, 0.1)
    s = collider.signed_distance(x)
    assert collider.margin is not None and collider.stiffness is not None
    if isinstance(collider, Sphere):
        ref_s = (x - torch.tensor(collider.center, dtype=F64)).norm(dim=-1) - collider.radius
    elif isinstance(collider, Plane):
        ref_s = (x - torch.tensor(collider.point, dtype=F64)) @ torch.tensor(collider.normal, dtype=F64)
    else:
        pa, pb = torch.tensor(collider.a, dtype=F64), torch.tensor(collider.b, dtype=F64)
        t = (((x - pa) @ (pb - pa)) / ((pb - pa) @ (pb - pa))).clamp(0, 1)
        ref_s = (x - (pa + t[:, None] * (pb - pa))).norm(dim=-1) - collider.radius
    torch.testing.assert_close(s, ref_s, rtol=1e-13, atol=1e-15)
    d = (collider.margin - ref_s).clamp_min(0)
    assert float(d.max()) > 0
    torch.testing.assert_close(collider.energy(x), 0.5 * collider.stiffness * (d * d).sum(), rtol=1e-13, atol=0)
    for out in (collider.energy(x.float()), collider.gradient(x.float()), collider.hessian_blocks(x.float())):
        assert out.dtype == torch.float32


# ----------------------------------------------------------------------------------- ClothModel pinned vertices


def test_cloth_model_pinned_list_of_v_indices(mesh):
    """A Python list of integer indices whose length is V is read as indices, not mistaken for a mask."""
    rest, faces = mesh
    V = rest.shape[0]
    idx = [3, 5] * (V // 2) + [3] * (V % 2)
    assert len(idx) == V
    model = ClothModel(faces, rest, pinned=idx)
    want = torch.zeros(V, dtype=torch.bool)
    want[[3, 5]] = True
    assert torch.equal(model.pinned, want)
    assert torch.equal(ClothModel(faces, rest, pinned=list(range(V))).pinned, torch.ones(V, dtype=torch.bool))
    assert torch.equal(ClothModel(faces, rest, pinned=torch.tensor(idx)).pinned, want)  # the same as a tensor


def test_cloth_model_pinned_masks_and_short_index_lists(mesh):
    rest, faces = mesh
    V = rest.shape[0]
    mask = torch.zeros(V, dtype=torch.bool)
    mask[[0, 2]] = True
    assert torch.equal(ClothModel(faces, rest, pinned=mask).pinned, mask)
    assert torch.equal(ClothModel(faces, rest, pinned=mask.tolist()).pinned, mask)  # a list of bools is a mask
    assert torch.equal(ClothModel(faces, rest, pinned=[0, 2]).pinned, mask)
    assert torch.equal(ClothModel(faces, rest, pinned=[]).pinned, torch.zeros(V, dtype=torch.bool))
    assert torch.equal(ClothModel(faces, rest, pinned=None).pinned, torch.zeros(V, dtype=torch.bool))


@pytest.mark.parametrize(("pinned", "match"), [
    ("short_mask", r"pinned must have shape \(\d+,\) \(a bool mask"),
    ("float", "integer vertex indices"),
    ("2d", "integer vertex indices"),
    ("out_of_range", r"pinned indices must lie in \[0, "),
    ("negative", r"pinned indices must lie in \[0, "),
])
def test_cloth_model_rejects_bad_pinned(mesh, pinned, match):
    rest, faces = mesh
    V = rest.shape[0]
    value = {"short_mask": [True] * (V - 1), "float": [0.0, 1.0], "2d": [[0, 1]], "out_of_range": [0, V],
             "negative": [-1]}[pinned]
    with pytest.raises(ValueError, match=match):
        ClothModel(faces, rest, pinned=value)


def test_cloth_model_pinned_indices_hold_their_vertices_in_a_solve(mesh):
    """The indices are pinned where the solver looks: a static solve keeps exactly those vertices."""
    rest, faces = mesh
    V = rest.shape[0]
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=1e-3)
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=1e5, poisson=0.3, thickness=1e-3)
    idx = [0, 1, 2] * V  # 3V indices (V of them would be read the same way)
    model = ClothModel(faces, rest, bending=bend, membrane=mem, density=0.2, pinned=idx[:V])
    x, info = tb.solve_static(model, rest.clone())
    assert torch.equal(x[[0, 1, 2]], rest[[0, 1, 2]])
    assert float((x[3:] - rest[3:]).abs().max()) > 0  # the others sag
    assert torch.equal(ClothModel(faces, rest, pinned=idx).pinned, model.pinned)


# --------------------------------------------------------------------------------------- unknown model names


def _models_listed(message: str, names) -> bool:
    return all(repr(n) in message for n in names)


def test_unknown_bending_model_names_the_choices(mesh):
    rest, faces = mesh
    choices = ("quadratic", "tan", "sin")
    calls = [lambda: tb.BendingEnergy(faces, rest, model="tangent", stiffness=1.0),
             lambda: L.Bending(faces, rest, 1.0, model="tangent"),
             lambda: _bending_fn.energy_function("tangent"),
             lambda: _bending_fn.gradient_function("tangent")]
    bend = tb.BendingEnergy(faces, rest, stiffness=1.0)
    ones = torch.ones((), dtype=F64)
    for raw in (_bending_fn.bending_energy_raw, _bending_fn.bending_gradient_raw):
        calls.append(lambda raw=raw: raw(rest, bend.hinges, bend.weights, ones, bend.rest_angles, model="tangent"))
    calls.append(lambda: _bending_fn.bending_hvp_raw(rest, rest, bend.hinges, bend.weights, ones, bend.rest_angles,
                                                     model="tangent"))
    for call in calls:
        with pytest.raises(ValueError, match="unknown bending model 'tangent'") as err:
            call()
        assert _models_listed(str(err.value), choices)


def test_bending_raw_entries_take_model_names(mesh):
    """The functional entries take a model's name as well as the enum (same values)."""
    rest, faces = mesh
    bend = tb.BendingEnergy(faces, rest, model="sin", backend="eager", stiffness=1.0)
    x = rest + 0.01 * torch.randn_like(rest)
    ones = torch.ones((), dtype=F64)
    args = (x, bend.hinges, bend.weights, ones, bend.rest_angles)
    torch.testing.assert_close(_bending_fn.bending_energy_raw(*args, model="sin"), bend(x))
    torch.testing.assert_close(_bending_fn.bending_gradient_raw(*args, model="sin"), bend.gradient(x))


def test_unknown_membrane_model_names_the_choices(mesh):
    rest, faces = mesh
    choices = ("stvk", "arap", "symmetric_dirichlet", "neohookean")
    calls = [lambda: tb.MembraneEnergy(faces, rest, model="hooke", young=1e5, poisson=0.3, thickness=1e-3),
             lambda: L.Stretch(faces, rest, young=1e5, poisson=0.3, thickness=1e-3, model="hooke"),
             lambda: _membrane_fn.energy_function("hooke"),
             lambda: _membrane_fn.gradient_function("hooke")]
    for call in calls:
        with pytest.raises(ValueError, match="unknown membrane model 'hooke'") as err:
            call()
        assert _models_listed(str(err.value), choices)


def test_cloth_model_takes_projection_names(mesh):
    """ClothModel's Hessian, HVP and block diagonal take a projection's name (and list the choices for an
    unknown one) as well as the enum."""
    rest, faces = mesh
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3)
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=1e5, poisson=0.3, thickness=1e-3)
    model = ClothModel(faces, rest, bending=bend, membrane=mem, colliders=[Sphere(center=(0, 0, -1), radius=0.9)])
    x = rest + 0.01 * torch.randn_like(rest)
    v = torch.randn_like(x)
    from torchbend.options import Projection

    for name in ("none", "clamp", "gauss_newton"):
        member = Projection(name)
        assert abs(model.hessian(x, name) - model.hessian(x, member)).max() == 0
        torch.testing.assert_close(model.hvp(x, v, name), model.hvp(x, v, member), rtol=0, atol=0)
        torch.testing.assert_close(model.block_diagonal(x, name), model.block_diagonal(x, member), rtol=0, atol=0)
    for call in (lambda: model.hessian(x, "clamped"), lambda: model.hvp(x, v, "clamped"),
                 lambda: model.block_diagonal(x, "clamped")):
        with pytest.raises(ValueError, match="unknown Hessian projection 'clamped'") as err:
            call()
        assert _models_listed(str(err.value), ("none", "clamp", "abs", "gauss_newton"))


# ---------------------------------------------------------------------------------------- byte-order marks

_BOM = b"\xef\xbb\xbf"
_TRIANGLES = {
    "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.5\nf 1 2 3\nf 2 4 3\n",
    "ply": ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
            "0 0 0\n1 0 0\n0 1 0\n1 1 0.5\n3 0 1 2\n3 1 3 2\n"),
    "off": "OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n1 1 0.5\n3 0 1 2\n3 1 3 2\n",
}


@pytest.mark.parametrize("ext", sorted(_TRIANGLES))
def test_load_reads_a_file_with_a_utf8_byte_order_mark(tmp_path, ext):
    """A text mesh file written with a UTF-8 byte-order mark reads as the same file without it (its first line,
    the first vertex of an OBJ or the header of a PLY/OFF, is read, not dropped)."""
    if ext != "obj":
        pytest.importorskip("meshio")
    text = _TRIANGLES[ext].encode()
    plain, marked = tmp_path / f"plain.{ext}", tmp_path / f"marked.{ext}"
    plain.write_bytes(text)
    marked.write_bytes(_BOM + text)
    x0, f0 = tb.mesh.load(plain)
    x1, f1 = tb.mesh.load(marked)
    assert x1.shape == (4, 3) and f1.shape == (2, 3)
    assert torch.equal(x0, x1) and torch.equal(f0, f1)
    torch.testing.assert_close(x1[0], torch.zeros(3, dtype=F64))  # the first vertex, from the first line


def test_load_obj_with_a_byte_order_mark_before_a_comment(tmp_path):
    path = tmp_path / "commented.obj"
    path.write_bytes(_BOM + b"# exported\r\n" + _TRIANGLES["obj"].replace("\n", "\r\n").encode())
    x, f, report = tb.mesh.load(path, report=True)
    assert x.shape == (4, 3) and f.tolist() == [[0, 1, 2], [1, 3, 2]]
    assert report.vertices_read == 4
