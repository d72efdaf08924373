"""Cloth model and Newton solvers: cantilever acceptance, drape, failure reporting, bad input, CLI."""
import json
import math
import os
from typing import cast

import pytest
import torch

import torchbend as tb
from torchbend import Capsule, ClothModel, ClothState, Plane, Sphere, implicit_euler_step, solve_static
from torchbend.options import Projection
from torchbend.scenes.config import build_scene, load_config
from torchbend.scenes.run import run_config
from torchbend.sim import newton

from .helpers import CONFIGS, SIM_DIR, DevicelessFactories, cantilever, tip

F64 = torch.float64


def test_static_cantilever_converges_and_solvers_agree():
    tips = []
    for nx, ny in [(11, 3), (21, 6), (41, 11)]:
        model, rest, kirchhoff = cantilever(nx, ny)
        x, info = solve_static(model, rest, linear_solver="direct", tol=1e-9)
        weight = float(model.external_force().sum(0).norm())
        assert info.converged and info.iterations <= 30, info.message
        assert info.residual <= 1e-9 * weight
        assert torch.equal(x[model.pinned], rest[model.pinned])  # pinned DOFs eliminated
        assert all(b <= a + 1e-12 * abs(a) for a, b in zip(info.energy_history, info.energy_history[1:], strict=False))
        tips.append(tip(x, rest))
        print(f"cantilever {nx}x{ny}: tip {tips[-1]:.6e} m, Kirchhoff {kirchhoff:.6e} m, ratio {tips[-1] / kirchhoff:.4f}, "
              f"{info.iterations} Newton iterations")
        if nx <= 21:
            x_cg, info_cg = solve_static(model, rest, linear_solver="cg", tol=1e-9)
            assert info_cg.converged and info_cg.iterations <= 30
            assert float((x_cg - x).norm() / (x - rest).norm()) <= 1e-8
    # the tip deflection converges under refinement: successive differences shrink
    assert abs(tips[2] - tips[1]) < abs(tips[1] - tips[0])


def test_failure_is_reported_and_leaves_input_untouched():
    model, rest, _ = cantilever(11, 3)
    x0 = rest.clone()
    x, info = solve_static(model, x0, max_iters=1, continuation=False)
    assert not info.converged and "no convergence" in info.message and info.stop_reason == "max_iters"
    assert torch.equal(x0, rest)  # the input is untouched, the progress kept: the best iterate comes back
    assert model.potential(x) < model.potential(rest)
    free = ~model.pinned
    assert info.energy == model.potential(x)
    assert info.residual == pytest.approx(float(model.gradient(x)[free].norm()), rel=1e-12)
    state = ClothState(rest.clone(), torch.zeros_like(rest))
    new, info = implicit_euler_step(model, state, 0.05, max_iters=0)
    assert not info.converged and torch.equal(state.x, rest) and new is not state
    assert torch.equal(new.v, (new.x - state.x) / 0.05)  # a consistent state, not the old one
    assert torch.isfinite(torch.tensor(info.residual))


def test_soft_shell_converges_by_the_membrane_homotopy():
    """The softest paper beam (5e-4 m, large rotation): Newton alone needs ~85 iterations from the flat
    state; the default continuation (membrane-stiffness homotopy) converges in a bounded number, to the
    same equilibrium as a long plain Newton run, and leaves the user's membrane moduli untouched."""
    cfg = load_config(os.path.join(CONFIGS, "beams.yaml"))
    model, x0, _ = build_scene(cfg, thickness=5e-4, resolution=(31, 4))
    assert model.membrane is not None
    mu = model.membrane.mu.clone()
    x, info = solve_static(model, x0)
    assert info.converged and "membrane-stiffness homotopy" in info.message and info.solves == 4, info.message
    assert info.iterations <= newton._AUTO_FIRST_ITERS + 40  # the first attempt, then at most 40 in the homotopy
    assert torch.equal(model.membrane.mu, mu)
    x_plain, plain = solve_static(model, x0, continuation=False, max_iters=400)
    assert plain.converged and plain.iterations > info.iterations
    assert float((x - x_plain).norm() / (x_plain - x0).norm()) <= 1e-6
    with pytest.raises(ValueError, match="continuation"):
        solve_static(model, x0, continuation="sometimes")


@pytest.mark.parametrize("hessian", ["exact", "clamp", "gauss_newton"])
def test_drape_no_penetration_energy_monotone(hessian):
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    model, x0, faces = build_scene(cfg, resolution=(11, 11))
    state = ClothState(x0, torch.zeros_like(x0))
    sphere = model.colliders[0]
    edge = 1.0 / 10
    its = []
    for _ in range(40):
        state, info = implicit_euler_step(model, state, 0.01, projection=hessian)
        assert info.converged, info.message
        hist = info.energy_history
        assert all(b <= a + 1e-12 * max(abs(a), 1.0) for a, b in zip(hist, hist[1:], strict=False))
        its.append(info.iterations)
        assert float(sphere.depth(state.x).max()) <= 0.01 * edge
    assert torch.isfinite(state.x).all()
    # the cloth has reached the sphere and rests on it
    assert float(sphere.depth(state.x).max()) > -0.01
    print(f"drape 11x11 {hessian}: mean Newton iterations per step {sum(its) / len(its):.2f}")


def test_viscous_bending_damping_enters_the_step():
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    model, x0, _ = build_scene(cfg, resolution=(7, 7))
    state = ClothState(x0 + 0.01 * torch.randn_like(x0), torch.zeros_like(x0))
    bend = cast(tb.BendingEnergy, model.bending)
    s1, _ = implicit_euler_step(model, state, 0.01)
    bend.damping = cast(torch.Tensor, bend.damping) * 1e6  # much more viscous: less bending motion
    s2, _ = implicit_euler_step(model, state, 0.01)
    d1 = (bend.angles(s1.x) - bend.angles(state.x)).abs().sum()
    d2 = (bend.angles(s2.x) - bend.angles(state.x)).abs().sum()
    assert d2 < d1


def test_colliders_derivatives_match_autograd():
    x = torch.randn(50, 3, dtype=F64) * 0.5
    for c in (Sphere((0.1, 0.0, 0.0), 0.4, stiffness=100.0, margin=0.05, law="penalty"),
              Plane((0, 0, 0.1), (0, 1, 1), stiffness=50.0, law="penalty"),
              Capsule((-0.3, 0, 0), (0.3, 0.1, 0), 0.3, stiffness=70.0, law="penalty")):
        y = x.clone().requires_grad_()
        (g,) = torch.autograd.grad(c.energy(y), y)
        assert float((c.gradient(x) - g).norm()) <= 1e-12 * max(float(g.norm()), 1.0)
        H = torch.func.hessian(lambda z, c=c: c.energy(z))(x).reshape(150, 150)
        blocks = torch.block_diag(*c.hessian_blocks(x))
        assert float((blocks - H).norm()) <= 1e-10 * max(float(H.norm()), 1.0)
        assert (torch.linalg.eigvalsh(c.hessian_blocks(x, projection="clamp")) >= -1e-12).all()


def test_model_tensors_live_on_the_device_of_the_rest_positions():
    rest, faces = tb.scenes.grid(5, 3, (0.2, 0.05), dtype=F64)
    meta = rest.to("meta")  # shapes only: a tensor created on the CPU cannot mix with it
    colliders = (Sphere((0.1, 0.0, -0.3), 0.3, margin=0.01, law="penalty"), Plane((0, 0, -0.1), (0, 0, 1), law="penalty"))
    x = torch.empty(15, 3, dtype=F64, device="meta")
    for pinned in (None, [0, 5, 10], rest[:, 0] <= 0):
        model = ClothModel(faces, meta, density=0.5, pinned=pinned, colliders=colliders)
        tensors = {k: v for k, v in vars(model).items() if isinstance(v, torch.Tensor)}
        assert {"rest_positions", "mass", "pinned", "gravity"} <= set(tensors)
        for name, t in tensors.items():
            assert t.device.type == "meta", name
        assert model.mass.dtype == model.gravity.dtype == F64 and model.pinned.dtype == torch.bool
        assert model.mass.shape == (15,) and model.pinned.shape == (15,) and model.gravity.shape == (3,)
        derived = {"external_force": model.external_force(), "gradient": model.gradient(x),
                   "hvp": model.hvp(x, x, Projection.NONE), "block_diagonal": model.block_diagonal(x, Projection.CLAMP)}
        for name, t in derived.items():
            assert t.device.type == "meta", name
    with pytest.raises(ValueError, match=r"pinned must have shape \(15,\)"):
        ClothModel(faces, meta, pinned=torch.zeros(4, dtype=torch.bool))
    # the dtype follows the rest positions too
    model = ClothModel(faces, rest.float(), pinned=[0, 5])
    assert model.mass.dtype == model.gravity.dtype == torch.float32 and int(model.pinned.sum()) == 2


def test_solvers_create_no_tensor_on_a_default_device():
    recorder = DevicelessFactories()
    with recorder:  # the recorder itself: a call without device= from a file of torchbend/sim is caught
        exec(compile("torch.zeros(3, dtype=torch.float64)", os.path.join(SIM_DIR, "newton.py"), "exec"), {"torch": torch})
    assert len(recorder.calls) == 1 and recorder.seen == 1
    recorder = DevicelessFactories()
    with recorder:
        model, rest, _ = cantilever(5, 3)
        for linear in ("direct", "cg"):
            x, info = solve_static(model, rest, linear_solver=linear, tol=1e-8)
            assert info.converged, info.message
        solve_static(model, rest, max_iters=1, continuation=True, max_relax_steps=5)
        cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))  # damping and a collider
        scene, x0, faces = build_scene(cfg, resolution=(5, 5))
        scene = ClothModel(faces, x0, bending=scene.bending, membrane=scene.membrane, pinned=[0, 4],
                           colliders=scene.colliders)
        for linear in ("direct", "cg"):
            state, info = implicit_euler_step(scene, ClothState(x0, torch.zeros_like(x0)), 0.01, linear_solver=linear)
            assert info.converged, info.message
    assert recorder.seen > 0
    assert recorder.calls == [], recorder.calls


def test_collider_hessian_is_block_diagonal():
    rest, faces = tb.scenes.grid(8, 5, (1.0, 1.0), dtype=F64)
    x = rest + 0.3 * torch.randn_like(rest)
    colliders = (Sphere((0.5, 0.5, 0.0), 0.4, stiffness=100.0, margin=0.05, law="penalty"),
                 Capsule((0, 0, 0), (1, 1, 0), 0.3, stiffness=70.0, law="penalty"))
    model = ClothModel(faces, rest, colliders=colliders)
    for option in (Projection.NONE, Projection.CLAMP):
        H = model.hessian(x, option)
        blocks = colliders[0].hessian_blocks(x, projection=option) + colliders[1].hessian_blocks(x, projection=option)
        assert H.shape == (120, 120)
        assert torch.equal(torch.from_numpy(H.toarray()), torch.block_diag(*blocks))


def test_bad_solver_input():
    model, rest, _ = cantilever(5, 3)
    faces = model.topology.faces
    with pytest.raises(ValueError, match=r"x0 must have shape \(15, 3\)"):
        solve_static(model, rest[:-1])
    with pytest.raises(ValueError, match="pinned indices must lie in"):
        ClothModel(faces, rest, pinned=[0, 99])
    with pytest.raises(ValueError, match=r"pinned must have shape \(15,\)"):
        ClothModel(faces, rest, pinned=torch.zeros(4, dtype=torch.bool))
    with pytest.raises(ValueError, match="density must be positive"):
        ClothModel(faces, rest, density=0.0)
    with pytest.raises(ValueError, match="dt must be positive"):
        implicit_euler_step(model, ClothState(rest, torch.zeros_like(rest)), 0.0)
    with pytest.raises(ValueError, match="Sphere.radius must be positive"):
        Sphere((0, 0, 0), -1.0)
    with pytest.raises(ValueError, match="Capsule.radius must be positive"):
        Capsule((0, 0, 0), (1, 0, 0), 0.0)
    with pytest.raises(ValueError, match="projection must be one of"):
        solve_static(model, rest, projection="newton")
    with pytest.raises(ValueError, match="linear_solver must be"):
        solve_static(model, rest, linear_solver="lu")
    with pytest.raises(ValueError, match="state.v must have shape"):
        implicit_euler_step(model, ClothState(rest, torch.zeros(3, 3)), 0.1)


def test_cli_dynamic_and_static_scenes(tmp_path):
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    stats = run_config(cfg, str(tmp_path / "sphere"), steps=3, resolution=(7, 7), progress=False)
    assert len(stats["steps"]) == 3 and all(s["converged"] for s in stats["steps"])
    assert (tmp_path / "sphere" / "snapshot.png").stat().st_size > 1000
    assert (tmp_path / "sphere" / "frames" / "frame_0003.obj").exists()
    saved = json.loads((tmp_path / "sphere" / "stats.json").read_text())
    assert saved["steps"][0]["iterations"] >= 1 and "membrane" in saved["steps"][0]["energies"]
    beams = load_config(os.path.join(CONFIGS, "beams.yaml"))
    beams["material"]["thicknesses"] = [1e-2]
    stats = run_config(beams, str(tmp_path / "beams"), resolution=(21, 4), progress=False)
    s = stats["steps"][0]
    assert s["converged"] and 0.1 < s["ratio"] < 2.0 and math.isfinite(s["tip_deflection"])


@pytest.mark.parametrize(
    "patch, match",
    [
        ({"bending": {"model": "cubic", "stiffness": 1.0}}, "bending.*unknown bending model"),
        ({"bending": {"model": "tan", "stiffness": -1.0}}, "'bending.stiffness' must be non-negative"),
        ({"membrane": {"model": "hooke"}}, "membrane.*unknown membrane model"),
        ({"colliders": [{"type": "cone"}]}, r"'colliders\[0\].type'"),
        ({"colliders": [{"type": "sphere", "radius": -1}]}, r"'colliders\[0\].radius' must be positive"),
        ({"material": {"density": -2}}, "'material.density' must be positive"),
    ],
)
def test_bad_config_values_name_the_key(patch, match):
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    cfg.update(patch)
    with pytest.raises(ValueError, match=match):
        build_scene(cfg, resolution=(5, 5))


def test_missing_config_and_unknown_key(tmp_path):
    with pytest.raises(ValueError, match="config file not found"):
        load_config(str(tmp_path / "nope.yaml"))
    p = tmp_path / "bad.yaml"
    p.write_text("mesh: {nx: 5}\nsolvr: {dt: 0.1}\n")
    with pytest.raises(ValueError, match=r"unknown config key 'solvr'"):
        load_config(str(p))


@pytest.mark.slow
@pytest.mark.parametrize("n", [41, 81])
def test_drape_full_resolutions(n, tmp_path):
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    stats = run_config(cfg, str(tmp_path), resolution=(n, n), progress=False)
    assert all(s["converged"] for s in stats["steps"])
    assert stats["max_penetration"] <= 0.01 * (1.0 / (n - 1))


@pytest.mark.slow
@pytest.mark.parametrize("resolution", [(61, 6), (131, 6), (196, 7)])
def test_beams_paper_resolutions(resolution, tmp_path):
    cfg = load_config(os.path.join(CONFIGS, "beams.yaml"))
    stats = run_config(cfg, str(tmp_path), resolution=resolution, progress=False)
    assert all(s["converged"] for s in stats["steps"])
