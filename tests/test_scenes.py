import math

import pytest
import torch

import torchbend as tb


@pytest.mark.parametrize(
    "make, V, F",
    [
        (lambda: tb.scenes.grid(4, 3), 12, 12),
        (lambda: tb.scenes.icosphere(2), 162, 320),
        (lambda: tb.scenes.cylinder(8, 3), 24, 32),
        (lambda: tb.scenes.random_curved_sheet(5, 5), 25, 32),
        (lambda: tb.scenes.single_hinge(0.5), 4, 2),
    ],
)
def test_scene_sizes_and_valid_topology(make, V, F):
    verts, faces = make()
    assert verts.shape == (V, 3) and faces.shape == (F, 3) and faces.dtype == torch.int64
    topo = tb.HingeTopology.from_faces(faces, vertex_count=V)  # validates orientation/manifoldness
    # outward / upward normals: positive projected or radial orientation
    n = torch.linalg.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    assert (n.norm(dim=-1) > 0).all()
    assert topo.hinge_count > 0


def test_icosphere_radius_and_outward_normals():
    verts, faces = tb.scenes.icosphere(2, radius=2.0, center=(1.0, 0.0, 0.0), dtype=torch.float64)
    c = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose((verts - c).norm(dim=-1), torch.full((len(verts),), 2.0, dtype=torch.float64))
    p = verts[faces]
    n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert ((n * (p.mean(1) - c)).sum(-1) > 0).all()


def test_single_hinge_angle_convention():
    for theta in (-2.0, 0.0, 1.0):
        x, f = tb.scenes.single_hinge(theta, dtype=torch.float64)
        assert math.isclose(tb.hinge_angles(x, tb.HingeTopology.from_faces(f)).item(), theta, abs_tol=1e-14)


def test_random_sheet_is_deterministic_and_dtype_follows():
    a, _ = tb.scenes.random_curved_sheet(4, 4, seed=3, dtype=torch.float32)
    b, _ = tb.scenes.random_curved_sheet(4, 4, seed=3, dtype=torch.float32)
    assert a.dtype == torch.float32 and torch.equal(a, b)


@pytest.mark.parametrize(
    "call",
    [
        lambda: tb.scenes.grid(1, 3),
        lambda: tb.scenes.grid(3, 3, size=(0.0, 1.0)),
        lambda: tb.scenes.icosphere(-1),
        lambda: tb.scenes.icosphere(1, radius=-2.0),
        lambda: tb.scenes.cylinder(2, 3),
        lambda: tb.scenes.single_hinge(4.0),
        lambda: tb.scenes.random_curved_sheet(3, 3, amplitude=float("nan")),
    ],
)
def test_bad_scene_arguments(call):
    with pytest.raises(ValueError):
        call()


def test_static_beam_kirchhoff_reference_follows_configured_gravity(tmp_path):
    """The beams scene compares the tip deflection with Kirchhoff's q L^4 / (8 D): q must use the
    configured gravity (not 9.81), so in the linear regime the ratio does not depend on g."""
    from torchbend.scenes.run import run_config

    def run(g, name):
        cfg = {
            "scene": {"kind": "static"},
            "mesh": {"type": "grid", "nx": 13, "ny": 3, "size": [0.3, 0.025], "pin": "first_two_columns"},
            "material": {"volumetric_density": 1000.0, "young": 5.0e7, "poisson": 0.3, "thicknesses": [5.0e-3]},
            "bending": {"model": "quadratic", "from_material": True},
            "membrane": {"model": "stvk"},
            "gravity": [0.0, 0.0, -g],
            "solver": {"tol": 1e-9, "max_iters": 50},
        }
        return run_config(cfg, str(tmp_path / name), progress=False)["steps"][0]

    earth, moon = run(9.81, "earth"), run(1.62, "moon")
    assert moon["kirchhoff_tip"] == pytest.approx(earth["kirchhoff_tip"] * 1.62 / 9.81, rel=1e-12)
    assert moon["tip_deflection"] == pytest.approx(earth["tip_deflection"] * 1.62 / 9.81, rel=2e-2)
    assert moon["ratio"] == pytest.approx(earth["ratio"], rel=2e-2)


def test_skirt_drape_config_runs_the_shipped_garment(tmp_path):
    """configs/skirt_drape.yaml: the shipped skirt (welded at its UV seams), waist pinned by a region,
    falls onto a body of a sphere and two capsules; a few steps converge with the default Newton
    options, the waist stays put and no vertex is deeper in a collider than the solver's contact depth."""
    import os

    from torchbend.scenes.config import build_scene, load_config
    from torchbend.scenes.run import run_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cfg = load_config(os.path.join(root, "configs", "skirt_drape.yaml"))
    assert cfg["mesh"]["path"] == "asset:skirt.obj"  # a shipped asset: not resolved against configs/
    model, x0, faces = build_scene(cfg)
    # the seams are welded: as many hinges as the welded mesh, more than the unwelded export
    _, _, welded = tb.mesh.load(tb.mesh.asset_path("skirt.obj"), report=True)
    _, _, raw = tb.mesh.load(tb.mesh.asset_path("skirt.obj"), weld_tol=None, report=True)
    assert model.bending is not None and len(x0) == welded.vertices == 384
    assert model.topology.hinge_count == model.bending.hinges.shape[0] == welded.hinge_count > raw.hinge_count
    # the pin region {z_min: -0.001} is the waist ring z = 0 (32 vertices), nothing else
    waist = x0[:, 2] == 0
    assert torch.equal(model.pinned, waist) and int(waist.sum()) == 32

    steps = 6
    stats = run_config(cfg, str(tmp_path), steps=steps, progress=False)
    assert len(stats["steps"]) == steps and all(s["converged"] for s in stats["steps"])
    assert all(s["iterations"] <= 30 for s in stats["steps"])  # the default max_iters of a time step
    x = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["x"]
    assert torch.equal(x[waist], x0[waist])  # pinned exactly
    assert float((x[~waist] - x0[~waist]).norm(dim=-1).max()) > 0.01  # the rest of the skirt fell
    # the skirt comes within the hips' margin by the last step and never touches them (the ipc law's barrier)
    assert stats["steps"][-1]["energies"]["collider0"] > 0
    hips = model.colliders[0]
    assert hips.law == "ipc" and 0 < float(hips._sd(x[~waist])[0].min()) < hips.margin
    assert all(float(c._sd(x)[0].min()) > 0 for c in model.colliders)
    assert stats["max_penetration"] == 0.0
    assert (tmp_path / "snapshot.png").is_file() and (tmp_path / "frames" / f"frame_{steps:04d}.obj").is_file()


def test_incline_config_slides_with_the_coulomb_acceleration(tmp_path):
    """configs/incline.yaml: a sheet on a plane with friction under gravity tilted past the friction angle."""
    import os

    from torchbend.scenes.config import load_config
    from torchbend.scenes.run import run_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cfg = load_config(os.path.join(root, "configs", "incline.yaml"))
    v = {}
    for steps in (10, 30):  # the downhill velocity after the settling of the first steps and 20 steps later
        stats = run_config(cfg, str(tmp_path / str(steps)), steps=steps, progress=False)
        assert all(s["converged"] for s in stats["steps"]) and stats["max_penetration"] == 0.0
        v[steps] = torch.load(tmp_path / str(steps) / "checkpoint.pt", weights_only=True)["v"]
    g = torch.tensor(cfg["gravity"], dtype=torch.float64)
    a = math.atan2(float(g[0]), -float(g[2]))  # the slope angle
    mu = cfg["colliders"][0]["friction"]
    expected = float(g.norm()) * (math.sin(a) - mu * math.cos(a))
    measured = float((v[30][:, 0] - v[10][:, 0]).mean()) / (20 * cfg["solver"]["dt"])
    assert math.isclose(measured, expected, rel_tol=0.02), (measured, expected)
    assert float(v[30][:, 1].abs().max()) < 1e-3 * float(v[30][:, 0].mean())  # straight down the slope


def test_incline_config_sticks_just_below_the_friction_angle(tmp_path):
    """configs/incline.yaml with mu = 0.6 (tan 30 deg = 0.96 mu): the sheet, started resting on the plane, stays
    put: it creeps below eps_v (IPC's smoothed static friction) and moves less than 0.1 mm in 30 steps (from 0.5 mm
    above the plane the barrier threw it up and it slid 0.7 mm while it came down)."""
    import os

    from torchbend.scenes.config import apply_overrides, build_scene, load_config
    from torchbend.scenes.run import run_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cfg = apply_overrides(load_config(os.path.join(root, "configs", "incline.yaml")), ["colliders[0].friction=0.6"])
    _, x0, _ = build_scene(cfg)
    stats = run_config(cfg, str(tmp_path), steps=30, progress=False)
    assert all(s["converged"] for s in stats["steps"]) and stats["max_penetration"] == 0.0
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert float(state["v"][:, 0].abs().max()) < cfg["colliders"][0]["eps_v"]
    assert float((state["x"] - x0)[:, 0].abs().max()) < 1e-4


def test_the_runners_energy_check_is_per_potential():
    """A step's ``energy_monotone`` (torchbend.scenes.run) compares the potential only within the stretches of
    ``energy_history`` that share one potential (``SolveInfo.adapted_at``: a barrier's stiffness adapted within the
    solve, the second half of a halved step), where it must not rise."""
    from torchbend.scenes.run import _monotone

    assert _monotone([3.0, 2.0, 1.0], [])
    assert not _monotone([3.0, 2.0, 2.5], [])
    assert _monotone([3.0, 2.0, 5.0, 4.0], [2])
    assert not _monotone([3.0, 2.0, 5.0, 6.0], [2])
    assert not _monotone([3.0, 4.0, 5.0, 4.0], [2])
