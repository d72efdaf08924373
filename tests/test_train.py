"""Training scripts: loss decreases, logs/checkpoints/resume, residual-loss gradient, material id, DDP."""
import json
import math
import os
import subprocess
import sys

import pytest
import torch
import yaml

import torchbend as tb

from .helpers import ROOT, train_script

common = train_script("common")
drape_net = train_script("drape_net")
material_id = train_script("material_id")
robot_drape = train_script("robot_drape")
hood_style = train_script("hood_style")
ClothPhysics, load_config, read_config = common.ClothPhysics, common.load_config, common.read_config

TINY = {
    "mesh": {"nx": 5, "size": [0.8, 0.8], "offset": [-0.4, -0.4, 0.32]},  # membrane, bending, gravity, ground, spheres
    "scene": {"fixed_conditions": True, "center_range": 0.0, "radius_min": 0.3},  # one sphere; 4 vertices over its cap
    "model": {"hidden": 16, "layers": 2},
    "train": {"steps": 8, "batch": 3, "lr": 1e-3, "lr_schedule": "constant", "log_every": 2, "mesh_every": 4,
              "checkpoint_every": 2},
    "eval": {"conditions": 4, "newton": 1, "time_limit": 5.0},
}


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(TINY))
    return str(path)


def test_energy_training_decreases_logs_checkpoints_and_resumes(tiny, tmp_path, capsys):
    out = str(tmp_path / "run")
    threads = torch.get_num_threads()
    r = drape_net.main(["--config", tiny, "--out", out, "--steps", "4", "--no-progress"])
    assert r["losses"][-1] < r["losses"][0]
    assert torch.get_num_threads() == threads  # train.threads (1) holds during the run only
    # the run ends with one summary line on stdout, its numbers in history.json
    summary = json.load(open(os.path.join(out, "history.json")))["summary"]
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("drape_net: energy loss") and "cap gap" in line and "drapes.png" in line
    assert summary["final_loss"] == pytest.approx(sum(r["losses"]) / 4) and summary["steps_run"] == 4
    assert summary["edge_length"] == pytest.approx((40 * 0.2 + 16 * 0.2 * math.sqrt(2)) / 56) and summary["conditions"] == 4
    assert summary["cap_gap"] > 0 and len(summary["newton"]) == 1
    assert os.path.isfile(os.path.join(out, "checkpoint.pt")) and os.path.isfile(os.path.join(out, "drapes.png"))
    events = os.listdir(os.path.join(out, "tb"))
    assert any(e.startswith("events.out.tfevents") for e in events)
    assert torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)["step"] == 4
    r2 = drape_net.main(["--config", tiny, "--out", out, "--steps", "8", "--resume", "--no-progress"])
    assert r2["start"] == 4 and len(r2["losses"]) == 4
    assert torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)["step"] == 8
    assert r2["losses"][-1] < r["losses"][0]


def test_residual_training_decreases(tiny, tmp_path):
    # far from equilibrium (free fall) the residual has no useful gradient: fine-tune an
    # energy-trained network, as one would in practice
    drape_net.main(["--config", tiny, "--out", str(tmp_path / "e"), "--steps", "30", "--lr", "3e-3", "--no-progress"])
    r = drape_net.main(["--config", tiny, "--out", str(tmp_path / "res"), "--steps", "6", "--loss", "residual",
                        "--lr", "1e-4", "--init", str(tmp_path / "e" / "checkpoint.pt"), "--no-progress"])
    assert r["losses"][-1] < r["losses"][0]


def test_residual_loss_gradient_matches_finite_differences(tiny):
    cfg = load_config(tiny, drape_net.Config)
    cfg["contact"]["stiffness"] = cfg["colliders"][0]["stiffness"] = 50.0
    torch.manual_seed(0)
    physics = ClothPhysics(cfg)
    scene = drape_net.SphereDrape(cfg, physics)
    net = drape_net.DrapeNet(len(physics.rest), 8, 1).double()
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.3)
    gen = torch.Generator().manual_seed(1)
    cond, center, radius = drape_net.sample_conditions(cfg, 2, gen, torch.float64, "cpu")

    def loss():
        return drape_net.loss_fn("residual", scene, scene.predict(net, cond, center, radius), center, radius)[0]

    params = list(net.parameters())
    L = loss()
    grads = torch.autograd.grad(L, params)
    direction = [torch.randn_like(p) for p in params]
    analytic = torch.stack([(g * d).sum() for g, d in zip(grads, direction, strict=True)]).sum().item()
    errs = []
    def shift(scale):
        with torch.no_grad():
            for p, d in zip(params, direction, strict=True):
                p.add_(scale * d)

    for eps in (1e-4, 1e-5, 1e-6):
        shift(eps)
        lp = loss().item()
        shift(-2 * eps)
        lm = loss().item()
        shift(eps)
        errs.append(abs((lp - lm) / (2 * eps) - analytic) / abs(analytic))
    assert min(errs) < 1e-6, errs


def test_material_identification_recovers_stiffness(tmp_path):
    r = material_id.main(["--out", str(tmp_path / "mid"), "--steps", "8", "--no-progress"])
    assert abs(r["k_fit"] - r["k_true"]) / r["k_true"] < 0.01
    assert os.path.isfile(os.path.join(tmp_path, "mid", "checkpoint.pt"))


def test_material_gradient_matches_finite_differences_of_the_equilibrium():
    cfg = load_config(os.path.join(ROOT, "configs", "train_material.yaml"), material_id.Config)
    cfg["mesh"]["nx"], cfg["mesh"]["ny"] = 9, 3
    x_obs, rest, k_true = material_id.observe(cfg)
    log_k = torch.tensor(math.log(1.7 * k_true), dtype=torch.float64, requires_grad=True)
    L, _, info = material_id.loss_of(cfg, log_k, None, x_obs)
    assert info.converged
    (g,) = torch.autograd.grad(L, log_k)
    h = 1e-5
    with torch.no_grad():
        lp = material_id.loss_of(cfg, log_k + h, None, x_obs)[0].item()
        lm = material_id.loss_of(cfg, log_k - h, None, x_obs)[0].item()
    fd = (lp - lm) / (2 * h)
    assert abs(fd - g.item()) <= 1e-5 * abs(fd), (fd, g.item())


@pytest.mark.parametrize(
    "patch, match",
    [
        ({"bending": {"model": "cubic"}}, r"'bending.model': unknown bending model 'cubic'"),
        ({"material": {"young": -1.0}}, "'material.young' must be positive"),
        ({"material": {"colour": "red"}}, r"material.colour"),
        ({"contact": {"law": "penalty", "power": 3}}, r"'contact': the penalty law has power 2"),
        ({"train": {"loss": "l2"}}, "'train.loss' must be"),
    ],
)
def test_bad_training_config_names_the_key(tmp_path, patch, match):
    cfg = {k: dict(v) for k, v in TINY.items()}
    for k, v in patch.items():
        cfg[k] = {**cfg.get(k, {}), **v}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with pytest.raises(ValueError, match=match):
        drape_net.main(["--config", str(path), "--out", str(tmp_path / "o"), "--steps", "1", "--no-progress"])
    with pytest.raises(ValueError, match="config file not found"):
        drape_net.main(["--config", str(tmp_path / "missing.yaml"), "--no-progress"])


def test_ddp_two_processes_keep_parameters_identical(tiny, tmp_path):
    out = str(tmp_path / "ddp")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           os.path.join(ROOT, "train", "drape_net.py"), "--config", tiny, "--out", out, "--steps", "3", "--no-progress"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    p0 = torch.load(os.path.join(out, "params_rank0.pt"))
    p1 = torch.load(os.path.join(out, "params_rank1.pt"))
    assert torch.equal(p0, p1)
    init = drape_net.DrapeNet(25, 16, 2).double()
    assert not torch.equal(p0, torch.cat([p.detach().reshape(-1) for p in init.parameters()]))
    assert json.load(open(os.path.join(out, "history.json")))["steps"] == 3


def test_robot_drape_training_conditioned_on_joint_angles(tmp_path):
    cfg = {"mesh": {"nx": 5, "size": [0.3, 0.3]}, "model": {"hidden": 16, "layers": 2},
           "train": {"steps": 20, "batch": 4, "lr": 3e-3, "log_every": 5, "checkpoint_every": 10}}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = str(tmp_path / "run")
    r = robot_drape.main(["--config", str(path), "--out", out, "--steps", "10", "--no-progress"])
    r2 = robot_drape.main(["--config", str(path), "--out", out, "--resume", "--no-progress"])
    assert r["start"] == 0 and r2["start"] == 10 and len(r2["losses"]) == 10
    for name in ("checkpoint.pt", "drapes.png", "history.json"):
        assert os.path.isfile(os.path.join(out, name))
    # predictions hold the corners exactly at the finger tips; Newton from them converges
    assert all(e["pin_error"] <= 1e-12 and e["converged"] for e in r2["eval"])
    # the trained network lowers the potential on a fixed batch of unseen joint vectors
    towel = robot_drape.HeldTowel(read_config(str(path), robot_drape.Config))
    untrained = robot_drape.DrapeNet(len(towel.rest), 16, 2, inputs=6).double()
    trained = robot_drape.DrapeNet(len(towel.rest), 16, 2, inputs=6).double()
    trained.load_state_dict(torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)["model"])
    q = towel.sample(8, torch.Generator().manual_seed(99)).requires_grad_()
    energy = {k: float(common.total(towel.physics.energies(towel.drape(n, q), None, None)).mean().detach())
              for k, n in (("untrained", untrained), ("trained", trained))}
    assert energy["trained"] < energy["untrained"]
    # the prediction is a batch function of q, differentiable in q through the forward kinematics
    x = towel.drape(trained, q)
    assert x.shape == (8, 25, 3)
    (gq,) = torch.autograd.grad(x[:, towel.pins.vertices].sum(), q)
    assert float(gq[:, :4].abs().min()) > 0


def test_hood_style_training_logs_every_term_to_tensorboard(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = {"convention": "torchbend", "mesh": {"nx": 5, "size": [0.8, 0.8], "offset": [-0.4, -0.4, 0.32]},
           "body": {"subdivisions": 1}, "model": {"hidden": 16, "layers": 2}, "eval": {"every": 2, "sequences": 1},
           "train": {"batch": 2, "rollout": 3, "log_every": 2, "checkpoint_every": 2}}
    path = tmp_path / "hood.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = str(tmp_path / "run")
    r = hood_style.main(["--config", str(path), "--out", out, "--steps", "4", "--seed", "1", "--no-progress"])
    terms = hood_style.TERMS["torchbend"]
    assert set(r["terms"]) == set(terms) and all(len(v) == 4 for v in r["terms"].values())
    assert all(math.isfinite(v) for v in r["losses"]) and all(math.isfinite(v) for vs in r["terms"].values() for v in vs)
    acc = EventAccumulator(os.path.join(out, "tb"))
    acc.Reload()
    assert {f"loss/{name}" for name in terms} | {"loss/total"} <= set(acc.Tags()["scalars"])
    for name in terms:  # the logged values are the per-term values of the run (unweighted, J)
        logged = {e.step: e.value for e in acc.Scalars(f"loss/{name}")}
        assert set(logged) == {2, 4}
        assert all(math.isclose(logged[s], r["terms"][name][s - 1], rel_tol=1e-6, abs_tol=1e-30) for s in logged)
    r2 = hood_style.main(["--config", str(path), "--out", out, "--steps", "6", "--resume", "--no-progress"])
    assert r2["start"] == 4 and len(r2["losses"]) == 2
    ck = torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)
    assert ck["step"] == 6 and ck["config"] == load_config(str(path), hood_style.Config, ["train.steps=6"])
    with pytest.raises(ValueError, match=r"does not fit this network \(config differs at model.hidden\)"):
        hood_style.main(["--config", str(path), "--out", out, "--steps", "7", "--resume", "--no-progress",
                         "--set", "model.hidden=8"])
    # another mesh plugs in; a sequence's HOOD materials convert to ours sample by sample
    grid, faces = tb.scenes.grid(4, 6, (0.4, 0.6))
    r3 = hood_style.main(["--config", str(path), "--out", str(tmp_path / "mesh"), "--steps", "2", "--no-progress"],
                         mesh=(grid + torch.tensor([-0.2, -0.3, 0.3]), faces))
    assert len(r3["losses"]) == 2
    seq = hood_style.Sequences(load_config(str(path), hood_style.Config), 4, torch.Generator().manual_seed(0),
                               torch.float64, "cpu")
    for b in range(4):
        mu, lam = tb.lame_parameters(float(seq.young[b]), float(seq.poisson[b]))
        assert math.isclose(mu, float(seq.lame_mu[b]), rel_tol=1e-12)
        assert math.isclose(lam, float(seq.lame_lambda[b]), rel_tol=1e-12, abs_tol=1e-9)
        assert math.isclose(24 * float(seq.bending_stiffness[b]), float(seq.bending_coeff[b]), rel_tol=1e-14)


def test_hood_style_trains_on_the_shipped_garment_from_its_config(tmp_path):
    skirt = tb.mesh.asset_path("skirt.obj")
    rest, faces = tb.mesh.load(skirt)
    cfg = {"convention": "torchbend", "mesh": {"type": "file", "path": skirt, "offset": [0.0, 0.0, 0.65]},
           "body": {"subdivisions": 1}, "model": {"hidden": 8, "layers": 1}, "eval": {"sequences": 1},
           "train": {"batch": 2, "rollout": 2, "log_every": 1}}
    path = tmp_path / "skirt.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = str(tmp_path / "run")
    r = hood_style.main(["--config", str(path), "--out", out, "--steps", "2", "--no-progress"])
    assert all(math.isfinite(v) for v in r["losses"]) and set(r["terms"]) == set(hood_style.TERMS["torchbend"])
    ck = torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)
    assert ck["model"]["net.2.weight"].shape == (3 * len(rest) + 3, 8)  # one output per welded skirt vertex
    assert ck["config"]["mesh"]["path"] == skirt
    # the welded mesh with its offset is the cloth the network steps
    c = load_config(str(path), hood_style.Config)
    x, f = hood_style.cloth_mesh(c, torch.float64)
    assert torch.equal(f, faces) and torch.allclose(x, rest + torch.tensor([0.0, 0.0, 0.65], dtype=torch.float64))
    # `mesh: path.obj` is short for the file variant; pins are refused (the cloth is free)
    path.write_text(yaml.safe_dump({"mesh": skirt}))
    assert load_config(str(path), hood_style.Config)["mesh"]["type"] == "file"
    path.write_text(yaml.safe_dump({"mesh": {"type": "file", "path": skirt, "pin": [0]}}))
    with pytest.raises(ValueError, match="'mesh.pin': hood_style pins no vertices"):
        hood_style.cloth_mesh(load_config(str(path), hood_style.Config), torch.float64)


def test_hood_style_default_is_hoods_convention(tmp_path):
    """The default config: HOOD's six criteria on the shipped skirt (y-up) over the walking mannequin, a held-out
    evaluation before and after training (loss, residual, angles, meshes) and its picture."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = str(tmp_path / "run")
    r = hood_style.main(["--out", out, "--steps", "3", "--no-progress", "--set", "model={hidden: 8, layers: 1}",
                         "--set", "train={batch: 2, rollout: 2, log_every: 1}", "--set", "eval.sequences=2"])
    assert set(r["terms"]) == set(hood_style.TERMS["hood"]) and set(r["eval"]) == {0, 3}
    assert all(math.isfinite(v) for vs in r["terms"].values() for v in vs)
    assert min(r["terms"]["collision"]) >= 0 and min(r["terms"]["stretching"]) >= 0
    acc = EventAccumulator(os.path.join(out, "tb"))
    acc.Reload()
    scalars = set(acc.Tags()["scalars"])
    assert {"eval/loss", "eval/residual_rms", "eval/mean_abs_theta_minus_rest"} <= scalars
    assert all(math.isfinite(e.value) and e.value >= 0 for e in acc.Scalars("eval/residual_rms"))
    assert os.path.getsize(os.path.join(out, "eval.png")) > 1000
    cfg = load_config(hood_style.CONFIG, hood_style.Config)
    rest, _ = hood_style.cloth_mesh(cfg, torch.float64)
    assert float(rest[:, 1].max() - rest[:, 1].min()) == pytest.approx(0.4)  # y-up: the skirt hangs along y
    seq = hood_style.Sequences(cfg, 64, torch.Generator().manual_seed(0), torch.float64, "cpu")
    assert float((seq.lame_lambda >= 2 * seq.lame_mu).double().mean()) > 0.1  # HOOD's independent draws


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_hood_style_without_cuda_names_the_device(tmp_path):
    with pytest.raises(SystemExit, match="--device cuda: CUDA is not available"):
        hood_style.main(["--out", str(tmp_path), "--steps", "1", "--device", "cuda", "--no-progress"])
    assert not os.listdir(tmp_path)  # nothing ran


@pytest.mark.slow  # about a minute on 2 cores (two minutes beside another CPU-bound job): -m slow
def test_drape_net_trains_on_the_shipped_skirt_with_its_waist_pinned(tmp_path):
    """configs/train_skirt.yaml: the shipped garment in a training config (``mesh: asset:skirt.obj`` with a
    pin region); the loss decreases and the network never moves the pinned waist ring."""
    from torchbend.scenes.config import ConfigError, build_mesh, build_pins

    path, out = os.path.join(ROOT, "configs", "train_skirt.yaml"), str(tmp_path / "skirt")
    small = ["--set", "train.batch=4", "--set", "scene.fixed_conditions=true", "--set", "model.hidden=32"]
    r = drape_net.main(["--config", path, "--out", out, "--steps", "5", "--no-progress"] + small)
    losses = r["losses"]
    assert len(losses) == 5 and all(math.isfinite(v) for v in losses)
    assert losses[-1] < losses[0], losses  # a fixed batch of conditions: the potential energy goes down
    cfg = load_config(path, drape_net.Config, ["model.hidden=32"])
    rest, faces = build_mesh(cfg["mesh"])
    pinned = build_pins(cfg["mesh"], rest)
    assert pinned is not None and len(rest) == 384 and int(pinned.sum()) == 32
    assert torch.equal(pinned, rest[:, 2] == 0.1)  # the waist ring: z = 0 in the file, offset by 0.1 m
    net = drape_net.DrapeNet(len(rest), 32, 3, pinned=pinned).double()
    net.load_state_dict(torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)["model"])
    cond, _, _ = drape_net.sample_conditions(cfg, 6, torch.Generator().manual_seed(5), torch.float64, "cpu")
    with torch.no_grad():
        x = net(cond, rest)
    assert torch.equal(x[:, pinned], rest[pinned].expand(6, -1, -1))  # exactly at rest
    assert float((x[:, ~pinned] - rest[~pinned]).abs().max()) > 1e-4  # the rest of the skirt moved
    # the residual loss would include the pins' reaction forces: refused with the key named
    with pytest.raises(ConfigError, match="'train.loss': 'residual' does not support a pinned mesh"):
        drape_net.main(["--config", path, "--out", str(tmp_path / "res"), "--loss", "residual", "--steps", "1",
                        "--no-progress"])


def _on_sphere(center, radius, polar_deg, azimuth_deg, offset):
    """The point at polar angle ``polar_deg`` from +z and ``azimuth_deg`` around it, ``offset`` [m]
    outside the sphere's surface (negative: inside)."""
    p, a = math.radians(polar_deg), math.radians(azimuth_deg)
    d = torch.tensor([math.sin(p) * math.cos(a), math.sin(p) * math.sin(a), math.cos(p)], dtype=torch.float64)
    return center + (radius + offset) * d


def test_cap_gap_of_a_hand_made_drape():
    center = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]], dtype=torch.float64)
    radius = torch.tensor([0.25, 0.1], dtype=torch.float64)
    # sample 0: over the cap (polar angle < 45 deg, above the centre) at 10, 20 and 5 mm (inside) from the
    # surface; at 60 deg latitude 0.3 m out and below the centre: not over the cap; the held top vertex
    # 0.2 m up counts only without the ``free`` mask
    c, r = center[0], float(radius[0])
    x0 = torch.stack([_on_sphere(c, r, 0, 0, 0.01), _on_sphere(c, r, 30, 40, 0.02), _on_sphere(c, r, 10, 200, -0.005),
                      _on_sphere(c, r, 60, 0, 0.3), _on_sphere(c, r, 120, 0, 0.0), _on_sphere(c, r, 0, 0, 0.2)])
    # sample 1: nothing over its cap (all below the sphere's centre)
    x1 = torch.stack([_on_sphere(center[1], 0.1, 100 + 10 * i, 30 * i, 0.01) for i in range(6)])
    x = torch.stack((x0, x1))
    free = torch.tensor([True] * 5 + [False])
    gap = drape_net.cap_gap(x, center, radius, free)
    assert gap[0].item() == pytest.approx((0.01 + 0.02 + 0.005) / 3, rel=1e-12)
    assert math.isnan(gap[1].item())
    assert drape_net.cap_gap(x, center, radius)[0].item() == pytest.approx((0.01 + 0.02 + 0.005 + 0.2) / 4, rel=1e-12)


def test_mean_edge_length_counts_each_edge_once():
    rest, faces = tb.scenes.grid(3, 3, (0.2, 0.2), dtype=torch.float64)
    # 12 axis-aligned edges of 0.1 m and 4 diagonals of 0.1 sqrt(2) m
    assert drape_net.mean_edge_length(rest, faces) == pytest.approx((12 * 0.1 + 4 * 0.1 * math.sqrt(2)) / 16, rel=1e-12)


def test_learning_rate_schedules():
    t = {"lr": 3e-3, "lr_schedule": "cosine", "lr_final": 0.01, "steps": 101}
    assert drape_net.learning_rate(t, 1) == pytest.approx(3e-3)
    assert drape_net.learning_rate(t, 51) == pytest.approx(3e-3 * (0.01 + 0.99 * 0.5))
    assert drape_net.learning_rate(t, 101) == pytest.approx(3e-5)
    assert drape_net.learning_rate({**t, "lr_schedule": "constant"}, 101) == 3e-3


def test_sphere_drape_holds_the_middle_vertex_and_checks_against_newton(tiny):
    cfg = load_config(tiny, drape_net.Config)
    physics = ClothPhysics(cfg)
    scene = drape_net.SphereDrape(cfg, physics)
    assert scene.held == 12 and int(scene.free.sum()) == 24  # the middle of the 5 x 5 grid
    cond, center, radius = drape_net.sample_conditions(cfg, 2, torch.Generator().manual_seed(3), torch.float64, "cpu")
    net = drape_net.DrapeNet(25, 8, 1).double()
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.1)
    x = scene.predict(net, cond, center, radius).detach()
    top = center + radius[:, None] * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    assert torch.equal(x[:, 12], top)
    # the solver model is the same potential, term for term
    m = scene.model(center[0].tolist(), float(radius[0]))
    assert torch.allclose(m.mass, physics.mass, rtol=1e-14, atol=0)
    phys = {k: float(v[0]) for k, v in physics.energies(x[:1], center[:1], radius[:1]).items()}
    mod = m.energies(x[0])
    assert mod["membrane"] == pytest.approx(phys["membrane"], rel=1e-12)
    assert mod["bending"] == pytest.approx(phys["bending"], rel=1e-12)
    assert mod["gravity"] == pytest.approx(phys["gravity"], rel=1e-12)
    # the ground is the config's collider (collider0 in both), the sphere the model's second collider
    assert mod["collider0"] == pytest.approx(phys["collider0"], rel=1e-12, abs=1e-15)
    assert mod["collider1"] == pytest.approx(phys["sphere"], rel=1e-12, abs=1e-15)
    # at an equilibrium: no gap to close; a millimetre off it: the energy difference and the distance back
    x_eq, info = tb.solve_static(m, x[0])
    assert info.converged
    (at_eq,) = scene.check(x_eq[None], center[:1], radius[:1])
    assert at_eq["converged"] and abs(at_eq["energy_gap"]) < 1e-12 and at_eq["rms_distance"] < 1e-9
    # vertical moves (orthogonal to the free turn about the vertical through the held vertex)
    delta = torch.zeros_like(x_eq)
    delta[:, 2] = 1e-3 * torch.randn(len(x_eq), generator=torch.Generator().manual_seed(0), dtype=torch.float64) * scene.free
    (off,) = scene.check((x_eq + delta)[None], center[:1], radius[:1])
    e_off = float(common.total(physics.energies((x_eq + delta)[None], center[:1], radius[:1])))
    e_eq = float(common.total(physics.energies(x_eq[None], center[:1], radius[:1])))
    assert off["converged"] and off["energy_gap"] == pytest.approx(e_off - e_eq, rel=1e-6)
    assert off["rms_distance"] == pytest.approx(float(delta.norm(dim=-1).pow(2).mean().sqrt()), rel=1e-4)
    assert off["relative_residual"] > at_eq["relative_residual"]


@pytest.mark.slow
def test_quick_start_drapes_rest_on_their_spheres(tmp_path):
    """The README's main job as it ships: the drapes of held-out spheres rest on them (mean cap gap
    below one edge length) and lie close to the Newton equilibria started from them."""
    r = drape_net.main(["--out", str(tmp_path / "qs"), "--no-progress"])
    s = r["summary"]
    assert s["cap_gap"] < s["edge_length"]
    assert s["newton_converged"] == len(s["newton"]) == 3
    assert s["relative_energy_gap"] < 0.1
    assert os.path.isfile(os.path.join(tmp_path, "qs", "drapes.png"))


def test_turned_onto_undoes_a_turn_about_the_vertical():
    gen = torch.Generator().manual_seed(4)
    p = torch.randn(20, 3, generator=gen, dtype=torch.float64)
    pivot = torch.tensor([0.3, -0.1, 0.7], dtype=torch.float64)
    c, s = math.cos(0.8), math.sin(0.8)
    q = p.clone()
    q[:, 0] = pivot[0] + c * (p[:, 0] - pivot[0]) - s * (p[:, 1] - pivot[1])
    q[:, 1] = pivot[1] + s * (p[:, 0] - pivot[0]) + c * (p[:, 1] - pivot[1])
    assert torch.allclose(drape_net.turned_onto(q, p, pivot), p, rtol=0, atol=1e-14)


def test_newton_check_means_count_only_the_solves_that_converged():
    checks = [{"converged": True, "energy_gap": 2e-3, "energy_prediction": 1.002, "rms_distance": 1e-3, "relative_residual": 0.1},
              {"converged": False, "energy_gap": 3e17, "energy_prediction": 1.0, "rms_distance": 4e14, "relative_residual": 0.3},
              {"converged": True, "energy_gap": 4e-3, "energy_prediction": 1.004, "rms_distance": 3e-3, "relative_residual": 0.2}]
    s = drape_net._newton_summary(checks)
    assert s["newton_converged"] == 2
    assert s["energy_gap"] == pytest.approx(3e-3) and s["rms_distance"] == pytest.approx(2e-3)
    assert s["relative_energy_gap"] == pytest.approx(3e-3, rel=1e-12)
    assert s["relative_residual"] == pytest.approx(0.2)  # at the predictions: every check counts
    none = drape_net._newton_summary([dict(c, converged=False) for c in checks])
    assert none["newton_converged"] == 0 and none["energy_gap"] is None and none["rms_distance"] is None
    summary = {"final_loss": 1.0, "final_window": 1, "edge_length": 0.1, "conditions": 3, "train_seconds": 1.0,
               "steps_run": 1, "eval_seconds": 1.0, "newton": checks, **none}
    line = drape_net.summary_line({"summary": summary, "loss_kind": "energy"}, "out")
    assert "not converged from any" in line and "e+17" not in line


def test_the_skirt_check_solves_with_the_pins_of_training():
    """The reference Newton solves of a pinned garment hold the same vertices the network never moves (without
    them the waist of a frictionless skirt slides off its hips and the check drifts)."""
    config = read_config(os.path.join(ROOT, "configs", "train_skirt.yaml"), drape_net.Config)
    cfg = config.model_dump(mode="json")
    physics = ClothPhysics(config)
    scene = drape_net.SphereDrape(cfg, physics)
    assert physics.pinned is not None and int(physics.pinned.sum()) == 32
    m = scene.model((0.0, 0.0, 0.0), 0.15)
    assert torch.equal(m.pinned, physics.pinned)
    assert [type(c).__name__ for c in m.colliders] == ["Sphere"]  # the hips under the contact law, no ground
    assert m.colliders[0].contact == physics.contact.contact_law()


def test_training_refuses_a_collider_with_the_ipc_law(tiny):
    # a network's prediction may lie inside a body, where the (default) ipc barrier of the solver is infinite
    cfg = load_config(tiny, drape_net.Config)
    cfg["colliders"] = [{"type": "plane", "point": [0.0, 0.0, -0.4]}]
    with pytest.raises(common.ConfigError, match=r"colliders\[0\].law': a training loss needs a law that is finite"):
        ClothPhysics(cfg)
    cfg["colliders"][0]["law"] = "penalty"
    assert ClothPhysics(cfg).solver_model.colliders[0].stiffness == 1e4
