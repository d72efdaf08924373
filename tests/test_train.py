"""Training scripts: loss decreases, logs/checkpoints/resume, residual-loss gradient, material id, DDP."""
import importlib.util
import json
import math
import os
import subprocess
import sys
from types import ModuleType

import pytest
import torch
import yaml

import torchbend as tb

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_script(name: str) -> ModuleType:
    """Import ``train/<name>.py`` from its path, without touching ``sys.path``.

    The scripts import their siblings by plain name (``import common``, as ``python train/X.py``
    allows), so each is registered in ``sys.modules`` under that name; load a script's siblings
    before it (``common`` first, ``drape_net`` before ``robot_drape``)."""
    path = os.path.join(ROOT, "train", f"{name}.py")
    loaded = sys.modules.get(name)
    if loaded is not None and getattr(loaded, "__file__", None) == path:
        return loaded
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


common = load_script("common")
drape_net = load_script("drape_net")
material_id = load_script("material_id")
robot_drape = load_script("robot_drape")
hood_style = load_script("hood_style")
ClothPhysics, load_config = common.ClothPhysics, common.load_config

TINY = {
    "cloth": {"resolution": 5, "size": 0.8, "height": 0.32, "energies": ["membrane", "bending", "gravity", "sphere", "ground"]},
    "scene": {"fixed_conditions": True},
    "model": {"hidden": 16, "layers": 2},
    "train": {"steps": 8, "batch": 3, "lr": 1e-3, "log_every": 2, "mesh_every": 4, "checkpoint_every": 2},
}


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(TINY))
    return str(path)


def test_energy_training_decreases_logs_checkpoints_and_resumes(tiny, tmp_path):
    out = str(tmp_path / "run")
    r = drape_net.main(["--config", tiny, "--out", out, "--steps", "4", "--no-progress"])
    assert r["losses"][-1] < r["losses"][0]
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
    cfg["cloth"]["contact_stiffness"] = 50.0
    torch.manual_seed(0)
    physics = ClothPhysics(cfg)
    net = drape_net.DrapeNet(len(physics.rest), 8, 1).double()
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.3)
    gen = torch.Generator().manual_seed(1)
    cond, center, radius = drape_net.sample_conditions(cfg, 2, gen, torch.float64, "cpu")

    def loss():
        return drape_net.loss_fn("residual", physics, net(cond, physics.rest), center, radius)[0]

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
    cfg["beam"]["nx"], cfg["beam"]["ny"] = 9, 3
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
        ({"cloth": {"energies": ["membrane", "elastic"]}}, r"cloth.energies.*\['elastic'\]"),
        ({"cloth": {"bending_stiffness": -1.0}}, "'cloth.bending_stiffness' must be positive"),
        ({"cloth": {"colour": "red"}}, r"cloth.colour"),
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
    cfg = {"cloth": {"resolution": 5}, "model": {"hidden": 16, "layers": 2},
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
    towel = robot_drape.HeldTowel(load_config(str(path), robot_drape.Config))
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

    cfg = {"cloth": {"resolution": 5}, "body": {"subdivisions": 1}, "model": {"hidden": 16, "layers": 2},
           "train": {"batch": 2, "rollout": 3, "log_every": 2, "checkpoint_every": 2}}
    path = tmp_path / "hood.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = str(tmp_path / "run")
    r = hood_style.main(["--config", str(path), "--out", out, "--steps", "4", "--seed", "1", "--no-progress"])
    assert set(r["terms"]) == set(hood_style.TERMS) and all(len(v) == 4 for v in r["terms"].values())
    assert all(math.isfinite(v) for v in r["losses"]) and all(math.isfinite(v) for vs in r["terms"].values() for v in vs)
    acc = EventAccumulator(os.path.join(out, "tb"))
    acc.Reload()
    assert {f"loss/{name}" for name in hood_style.TERMS} | {"loss/total"} <= set(acc.Tags()["scalars"])
    for name in hood_style.TERMS:  # the logged values are the per-term values of the run (unweighted, J)
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
    cfg = {"mesh": {"type": "file", "path": skirt, "offset": [0.0, 0.0, 0.65]}, "body": {"subdivisions": 1},
           "model": {"hidden": 8, "layers": 1}, "train": {"batch": 2, "rollout": 2, "log_every": 1}}
    path = tmp_path / "skirt.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = str(tmp_path / "run")
    r = hood_style.main(["--config", str(path), "--out", out, "--steps", "2", "--no-progress"])
    assert all(math.isfinite(v) for v in r["losses"]) and set(r["terms"]) == set(hood_style.TERMS)
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


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_hood_style_without_cuda_names_the_device(tmp_path):
    with pytest.raises(SystemExit, match="--device cuda: CUDA is not available"):
        hood_style.main(["--out", str(tmp_path), "--steps", "1", "--device", "cuda", "--no-progress"])
    assert not os.listdir(tmp_path)  # nothing ran


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
