"""One config system and one CLI: the schema (unknown keys, bad values, shipped configs), overrides,
the shared flags of every script, the device error, weights_only checkpoints with --resume, scene
snapshots with every collider, the beams report's Kirchhoff column."""
import glob
import logging
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

import torchbend as tb
from torchbend.scenes import cli
from torchbend.scenes.config import (
    ConfigError,
    FileMesh,
    GridMesh,
    PhysicsConfig,
    SceneConfig,
    SphereSpec,
    apply_overrides,
    build_model,
    build_scene,
    load_config,
    read_config,
    validate,
)
from torchbend.scenes.run import main as scenes_main
from torchbend.scenes.run import run_config

from .helpers import ROOT, train_script

drape_net, hood_style, material_id, robot_drape = (train_script(n) for n in ("drape_net", "hood_style", "material_id",
                                                                              "robot_drape"))
CONFIGS = os.path.join(ROOT, "configs")
SCRIPTS = {"drape_net": drape_net, "material_id": material_id, "robot_drape": robot_drape, "hood_style": hood_style}
TINY = {"mesh": {"nx": 5, "size": [0.8, 0.8], "offset": [-0.4, -0.4, 0.32]}, "scene": {"fixed_conditions": True}, "model": {"hidden": 8, "layers": 1},
        "train": {"steps": 2, "batch": 2, "log_every": 1, "mesh_every": 2, "checkpoint_every": 1}}


def _write(tmp_path, cfg, name="c.yaml") -> str:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


def _schema_of(path: str):
    """A config's schema: the script its header names (``train/X.py``), else the scene schema."""
    head = open(path).read(400)
    m = re.search(r"train/(\w+)\.py", head)
    return SCRIPTS[m.group(1)].Config if m else SceneConfig


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(CONFIGS, "*.yaml"))), ids=os.path.basename)
def test_every_shipped_config_validates(path):
    schema = _schema_of(path)
    cfg = load_config(path, schema)
    raw = yaml.safe_load(open(path))
    assert set(raw) <= set(cfg)  # every section given is kept, defaults fill the rest
    assert validate(cfg, schema).model_dump(mode="json") == cfg  # the dict form round-trips


@pytest.mark.parametrize("cfg, message", [
    ({"solver": {"x": 1}}, "unknown config key 'solver.x' (allowed: dt, steps,"),
    ({"colliders": [{"type": "plane"}, {"type": "sphere", "foo": 1}]}, "unknown config key 'colliders[1].foo'"),
    ({"robot": {"pins": [{"link": "world", "vertices": [0]}, {"link": "gripper", "nearest": [[0, 0, 0]], "bar": 2}]}},
     "unknown config key 'robot.pins[1].bar' (allowed: link, vertices, nearest)"),
    ({"robot": {"capsules": [{"link": "forearm", "lenght": 0.2}]}}, "unknown config key 'robot.capsules[0].lenght'"),
    ({"solvr": {"dt": 0.1}}, "unknown config key 'solvr' (allowed: mesh, material,"),
    ({"mesh": {"type": "file", "path": "a.obj", "nx": 3}}, "unknown config key 'mesh.nx'"),
])
def test_unknown_keys_are_named_by_their_path(cfg, message):
    with pytest.raises(ConfigError) as e:
        validate(cfg, SceneConfig)
    assert message in str(e.value)


@pytest.mark.parametrize("cfg, message", [
    ({"solver": {"steps": "many"}}, "config key 'solver.steps' must be an integer, got 'many'"),
    ({"solver": {"steps": 2.5}}, "config key 'solver.steps' must be an integer, got 2.5"),
    ({"solver": {"tol": -1e-6}}, "config key 'solver.tol' must be positive, got -1e-06"),
    ({"material": {"density": True}}, "config key 'material.density' must be a number, got True"),
    ({"material": {"poisson": 0.7}}, "config key 'material.poisson' must be <= 0.5, got 0.7"),
    ({"material": {"young": "inf"}}, "config key 'material.young' must be a finite number"),
    ({"gravity": [0, 0]}, "config key 'gravity' must be a list of 3 numbers"),
    ({"mesh": {"nx": 1}}, "config key 'mesh.nx' must be >= 2, got 1"),
    ({"mesh": {"pin": "edges"}}, "config key 'mesh.pin' must be 'first_two_columns', 'corners', a list"),
    ({"mesh": 3}, "config key 'mesh' must be a mapping, got 3"),
    ({"scene": {"kind": "quasi"}}, "config key 'scene.kind' must be one of 'dynamic', 'robot', 'static', got 'quasi'"),
    ({"colliders": [{"type": "cone"}]}, "config key 'colliders[0].type' must be one of 'sphere', 'plane', 'capsule'"),
    ({"colliders": [{"radius": 1.0}]}, "config key 'colliders[0]' needs a 'type' key"),
    ({"colliders": [{"type": "capsule", "radius": 0}]}, "config key 'colliders[0].radius' must be positive, got 0"),
    ({"bending": {"model": "cubic", "stiffness": 1.0}}, "config key 'bending.model': unknown bending model 'cubic'"),
    ({"bending": {"model": "tan"}}, "config key 'bending': give either 'stiffness'"),
    ({"solver": {"hessian": "newton"}}, "config key 'solver.hessian': unknown Hessian projection 'newton'"),
    ({"robot": {"pins": [{"link": "gripper"}]}}, "config key 'robot.pins[0]': give either 'vertices"),
    ({"robot": {"trajectory": [{"t": 0.0, "q": [0.0, "x"]}]}}, "config key 'robot.trajectory[0].q[1]' must be a finite number"),
    ({"robot": {"pins": [{"vertices": [0]}]}}, "missing config key 'robot.pins[0].link'"),
])
def test_bad_values_are_value_errors_naming_the_path(cfg, message):
    with pytest.raises(ValueError) as e:
        validate(cfg, SceneConfig)
    assert message in str(e.value)


@pytest.mark.parametrize("script, cfg, message", [
    ("drape_net", {"train": {"lr": 0}}, "config key 'train.lr' must be positive, got 0"),
    ("drape_net", {"scene": {"radius_min": 0.3, "radius_max": 0.2}}, "config key 'scene': radius_max (0.2) must not be below"),
    ("drape_net", {"bending": {"model": "cubic"}}, "config key 'bending.model': unknown bending model"),
    ("drape_net", {"cloth": {"resolution": 5}}, "unknown config key 'cloth' (allowed: mesh, material, bending, membrane,"),
    ("robot_drape", {"mesh": {"height": 0.3}}, "unknown config key 'mesh.height'"),
    ("robot_drape", {"robot": {"nominal": "up"}}, "config key 'robot.nominal' must be a list"),
    ("material_id", {"identify": {"steps": 0}}, "config key 'identify.steps' must be positive, got 0"),
    ("material_id", {"mesh": {"nx": 1}}, "config key 'mesh.nx' must be >= 2, got 1"),
    ("hood_style", {"sampling": {"lame_mu": [6e4, 1.5e4]}}, "config key 'sampling.lame_mu' must be a pair [lo, hi] with lo <= hi"),
    ("hood_style", {"sampling": {"density": [0.1]}}, "config key 'sampling.density' must be a pair [lo, hi], got [0.1]"),
    ("hood_style", {"sampling": {"bending_coeff": [0, 1e-4]}}, "config key 'sampling.bending_coeff[0]' must be positive"),
    ("hood_style", {"sampling": {"lame_lambda_ratio": [0.2, 2.5]}}, "config key 'sampling.lame_lambda_ratio[1]' must be < 2"),
    ("hood_style", {"body": {"radius": [0.3, 0.2]}}, "config key 'body.radius' must be a pair [lo, hi] with lo <= hi"),
    ("hood_style", {"loss": {"weights": {"strech": 1.0}}}, "unknown config key 'loss.weights.strech' (allowed: stretch,"),
    ("hood_style", {"contact": {"margin": -1e-3}}, "config key 'contact.margin' must be non-negative"),
    ("hood_style", {"loss": {"contact_eps": 1e-3}}, "unknown config key 'loss.contact_eps'"),
    ("hood_style", {"train": {"rollout": 0}}, "config key 'train.rollout' must be positive, got 0"),
    ("hood_style", {"train": {"dtype": "float16"}}, "config key 'train.dtype' must be one of 'float32', 'float64'"),
    ("hood_style", {"mesh": {"type": "file", "path": "a.obj", "nx": 3}}, "unknown config key 'mesh.nx'"),
])
def test_training_schemas_extend_the_same_system(tmp_path, script, cfg, message):
    with pytest.raises(ConfigError) as e:
        load_config(_write(tmp_path, cfg), SCRIPTS[script].Config)
    assert message in str(e.value) and str(tmp_path) in str(e.value)  # names the file too


def test_overrides_set_nested_keys_and_are_validated(tmp_path):
    cfg = {"colliders": [{"type": "sphere", "radius": 0.3}], "solver": {"tol": 1e-6}}
    out = apply_overrides(cfg, ["solver.tol=1e-8", "colliders[0].center=[0, 0, 0.1]", "output.every=5",
                                "mesh.size=[2, 1]"])
    assert out["solver"]["tol"] == "1e-8"  # YAML reads 1e-8 as a string: the schema converts it
    c = validate(out, SceneConfig)
    sphere, grid = c.colliders[0], c.mesh
    assert isinstance(sphere, SphereSpec) and isinstance(grid, GridMesh)
    assert c.solver.tol == 1e-8 and sphere.center == (0.0, 0.0, 0.1) and c.output.every == 5 and grid.size == (2.0, 1.0)
    # a dotted index into a list as the bracketed one
    out = apply_overrides(out, ["colliders.0.friction=0.5", "colliders.-1.radius=0.2"])
    assert out["colliders"][0]["friction"] == 0.5 and out["colliders"][0]["radius"] == 0.2
    for bad, message in [("solver.tol", "must be KEY=VALUE"), ("colliders[3].radius=1", "no list element [3]"),
                         ("colliders.3.radius=1", "no list element [3]"),
                         ("colliders.--1.radius=1", "not inside a mapping"), ("colliders[--1].radius=1", "name[index]"),
                         ("colliders.\u00b2.radius=1", "not inside a mapping"),
                         ("colliders.x=1", "not inside a mapping"), ("=1", "must be KEY=VALUE")]:
        with pytest.raises(ConfigError, match=re.escape(message)):
            apply_overrides({"colliders": [], "solver": {}}, [bad])
    path = _write(tmp_path, {"solver": {"dt": 0.01}})
    with pytest.raises(ConfigError, match="unknown config key 'solver.tol_x'"):
        load_config(path, overrides=["solver.tol_x=1"])


def test_file_mesh_variant_parses_and_resolves_its_path(tmp_path):
    # the mesh file is read only by the builder (torchbend.mesh.load); here only the schema
    path = _write(tmp_path, {"mesh": "garments/shirt.obj"})
    cfg = load_config(path)
    assert cfg["mesh"] == {"type": "file", "path": str(tmp_path / "garments" / "shirt.obj"), "weld_tol": 1e-6,
                           "offset": [0.0, 0.0, 0.0], "pin": None}
    m = validate({"mesh": {"type": "file", "path": "/abs/s.obj", "weld_tol": 1e-4, "pin": [0, 3]}}, SceneConfig).mesh
    assert isinstance(m, FileMesh) and m.weld_tol == 1e-4 and m.pin == [0, 3]
    with pytest.raises(ConfigError, match="config key 'mesh.weld_tol' must be non-negative"):
        validate({"mesh": {"type": "file", "path": "s.obj", "weld_tol": -1}}, SceneConfig)


def test_grid_pin_by_vertex_indices():
    model, x0, _ = build_scene({"mesh": {"nx": 4, "ny": 3, "pin": [0, 5, 11]}})
    assert model.pinned.nonzero()[:, 0].tolist() == [0, 5, 11]
    with pytest.raises(ConfigError, match=re.escape("'mesh.pin': vertex indices [12] out of range [0, 12)")):
        build_scene({"mesh": {"nx": 4, "ny": 3, "pin": [12]}})


def test_pin_region_selects_by_rest_coordinates_before_the_offset():
    # a 4 x 3 grid on [0, 1] x [0, 1] (columns x = 0, 1/3, 2/3, 1), moved by the offset
    model, x0, _ = build_scene({"mesh": {"nx": 4, "ny": 3, "offset": [5.0, 0.0, 2.0], "pin": {"x_max": 0.4}}})
    assert model.pinned.nonzero()[:, 0].tolist() == [0, 1, 4, 5, 8, 9]  # x <= 0.4 in mesh coordinates
    box = {"x_min": 0.3, "x_max": 0.7, "y_min": 0.5, "nearest": [[0.0, 0.0, 0.0], [0.98, 1.02, 0.0]]}
    model, _, _ = build_scene({"mesh": {"nx": 4, "ny": 3, "offset": [5.0, 0.0, 2.0], "pin": box}})
    assert model.pinned.nonzero()[:, 0].tolist() == [0, 5, 6, 9, 10, 11]  # the box, plus the nearest vertices
    # the shipped skirt by its asset name: {z_min: -0.001} is exactly the waist ring z = 0
    model, x0, _ = build_scene({"mesh": {"type": "file", "path": "asset:skirt.obj", "pin": {"z_min": -0.001}}})
    assert torch.equal(model.pinned, x0[:, 2] == 0) and int(model.pinned.sum()) == 32
    with pytest.raises(ConfigError, match=re.escape("config key 'mesh.pin': the region holds no vertex (the mesh spans "
                                                    "x [0, 1], y [0, 1], z [0, 0] m")):
        build_scene({"mesh": {"nx": 4, "ny": 3, "offset": [0.0, 0.0, 1.0], "pin": {"z_min": 0.5}}})


@pytest.mark.parametrize("mesh, message", [
    ({"type": "file", "path": "s.obj", "pin": {"z_mim": 0.0}},
     "unknown config key 'mesh.pin.z_mim' (allowed: x_min, x_max, y_min, y_max, z_min, z_max, nearest)"),
    ({"type": "file", "path": "s.obj", "pin": {}}, "config key 'mesh.pin': a pin region needs at least one of x_min"),
    ({"nx": 3, "pin": {"y_min": 1.0, "y_max": 0.0}}, "config key 'mesh.pin': y_min (1.0) must not exceed y_max (0.0)"),
    ({"type": "file", "path": "s.obj", "pin": {"z_min": "low"}}, "config key 'mesh.pin.z_min' must be a finite number"),
    ({"type": "file", "path": "s.obj", "pin": {"nearest": [[0, 0]]}},
     "config key 'mesh.pin.nearest[0]' must be a list of 3 numbers"),
    ({"type": "file", "path": "s.obj", "pin": [0, -2]}, "config key 'mesh.pin[1]' must be non-negative, got -2"),
    ({"type": "file", "path": "s.obj", "pin": "corners"},
     "config key 'mesh.pin' must be a list of vertex indices, a region {x_min: ..., z_max: ..., nearest: ...} or null"),
    ({"type": "file", "path": "asset:dress.obj"}, "config key 'mesh.path': no shipped mesh named 'dress.obj'; "
                                                  "available: ['skirt.obj']"),
    ("asset:dress.obj", "config key 'mesh.path': no shipped mesh named 'dress.obj'"),
])
def test_bad_pin_regions_and_asset_names_are_named_by_their_path(mesh, message):
    with pytest.raises(ConfigError) as e:
        validate({"mesh": mesh}, SceneConfig)
    assert message in str(e.value)


def test_asset_meshes_are_not_resolved_against_the_config_folder(tmp_path):
    cfg = load_config(_write(tmp_path, {"mesh": "asset:skirt.obj"}))
    assert cfg["mesh"]["path"] == "asset:skirt.obj"
    # the training scripts take the same mesh section, the path shorthand included
    train = load_config(_write(tmp_path, {"mesh": "asset:skirt.obj"}, "t.yaml"), drape_net.Config)
    assert train["mesh"]["type"] == "file" and train["mesh"]["path"] == "asset:skirt.obj"
    assert load_config(_write(tmp_path, {}, "none.yaml"), drape_net.Config)["mesh"]["type"] == "grid"  # the default cloth
    local = load_config(_write(tmp_path, {"mesh": "garment.obj"}, "l.yaml"), drape_net.Config)
    assert local["mesh"]["path"] == str(tmp_path / "garment.obj")


def test_scenes_and_every_training_script_speak_one_physics_dialect(tmp_path):
    """The physics sections (mesh, material, bending, membrane, colliders, contact, gravity) are the same
    schema in a scene config and in every training config: one block validates alike in all of them and
    builds the same model."""
    physics = {"mesh": {"type": "grid", "nx": 5, "ny": 4, "size": [0.3, 0.2], "offset": [0.0, 0.0, 0.1]},
               "material": {"young": 3e4, "poisson": 0.25, "thickness": 1e-3, "density": 0.3},
               "bending": {"model": "sin", "stiffness": 2e-5}, "membrane": {"model": "arap"},
               "colliders": [{"type": "plane", "point": [0, 0, -0.1], "law": "barrier", "stiffness": 1e5, "power": 3}],
               "contact": {"law": "penalty", "stiffness": 1e3}, "gravity": [0.0, 0.0, -9.0]}
    path = _write(tmp_path, physics)
    scene = load_config(path)
    model = build_scene(scene)[0]
    x = model.rest_positions + 0.01 * torch.randn(model.vertex_count, 3, dtype=torch.float64,
                                                  generator=torch.Generator().manual_seed(0))
    for name, module in SCRIPTS.items():
        assert issubclass(module.Config, PhysicsConfig), name
        for key in physics:
            assert module.Config.model_fields[key].annotation == PhysicsConfig.model_fields[key].annotation
        cfg = load_config(path, module.Config)
        assert {k: cfg[k] for k in physics} == {k: scene[k] for k in physics}, name
        built = build_model(read_config(path, module.Config))
        assert built.energies(x) == model.energies(x), name


# ------------------------------------------------------------------------------ CLI
COMMON = ["--config", "--set", "--seed", "--device", "--out", "--resume", "--log-level", "--no-progress"]
MAINS = {"scenes": scenes_main, "drape_net": drape_net.main, "material_id": material_id.main,
         "robot_drape": robot_drape.main, "hood_style": hood_style.main}
OWN = {"scenes": ["--steps", "--resolution"], "drape_net": ["--loss", "--lr", "--init", "--steps"],
       "material_id": ["--steps"], "robot_drape": ["--steps"], "hood_style": ["--steps"]}


@pytest.mark.parametrize("name", sorted(MAINS))
def test_every_script_takes_the_common_flags(name, capsys):
    with pytest.raises(SystemExit) as e:
        MAINS[name](["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    flags = set(re.findall(r"(--[a-z][a-z-]*)", text))
    assert set(COMMON + OWN[name]) <= flags, set(COMMON + OWN[name]) - flags


def _unavailable_device() -> str:
    return "cuda:99" if torch.cuda.is_available() else "cuda"


@pytest.mark.parametrize("name", sorted(MAINS))
def test_unavailable_device_is_one_line(name, tmp_path):
    argv = [os.path.join(CONFIGS, "beams.yaml")] if name == "scenes" else []
    with pytest.raises(SystemExit) as e:
        MAINS[name](argv + ["--device", _unavailable_device(), "--out", str(tmp_path)])
    msg = str(e.value.code)
    assert "\n" not in msg and f"--device {_unavailable_device()}" in msg and "error" in msg
    assert not os.listdir(tmp_path)  # nothing ran
    with pytest.raises(SystemExit, match="not a torch device"):
        MAINS[name](argv + ["--device", "gpu0"])


def test_device_error_from_the_command_line_has_no_traceback():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, "-m", "torchbend.scenes", os.path.join(CONFIGS, "beams.yaml"), "--device",
                          _unavailable_device()], capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("python -m torchbend.scenes: error: --device"), res.stderr
    assert "Traceback" not in res.stderr


def test_config_errors_exit_with_one_line_from_run_main(tmp_path):
    with pytest.raises(SystemExit) as e:
        cli.run_main(lambda: scenes_main([os.path.join(CONFIGS, "beams.yaml"), "--set", "solver.tol_x=1"]), "prog")
    msg = str(e.value.code)
    assert msg.startswith("prog: error: config ") and "unknown config key 'solver.tol_x'" in msg and "\n" not in msg


def test_material_id_runs_on_the_cpu_only():
    dev = cli.resolve_device("cpu", supported=("cpu",))
    assert dev == torch.device("cpu")
    with pytest.raises(SystemExit, match="runs on cpu only"):
        cli.resolve_device("meta", prog="x", supported=("cpu",))


# ------------------------------------------------------------------------------ checkpoints
def _plain(obj) -> bool:
    """Only tensors and plain Python values (what weights_only=True loads)."""
    if isinstance(obj, dict):
        return all(isinstance(k, (str, int)) and _plain(v) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        return all(_plain(v) for v in obj)
    return obj is None or isinstance(obj, (torch.Tensor, str, int, float, bool))


def test_checkpoint_is_weights_only_and_resume_restores_model_optimizer_step(tmp_path, caplog):
    path, out = _write(tmp_path, TINY), str(tmp_path / "run")
    with caplog.at_level(logging.INFO, logger="train"):
        r = drape_net.main(["--config", path, "--out", out, "--no-progress", "--seed", "3", "--set", "train.lr=2e-3"])
    assert r["start"] == 0 and len(r["losses"]) == 2
    assert any("energy loss" in m and out in m for m in caplog.messages)  # the final summary, at INFO
    ck = torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)
    assert set(ck) == {"step", "model", "optimizer", "config"} and ck["step"] == 2 and _plain(ck)
    assert ck["config"]["train"]["seed"] == 3 and ck["config"]["train"]["lr"] == 2e-3  # the flags are in it
    assert ck["config"] == load_config(path, drape_net.Config, ["train.seed=3", "train.lr=2e-3"])
    # resuming at the saved step runs nothing and keeps the weights
    r0 = drape_net.main(["--config", path, "--out", out, "--no-progress", "--resume", "--seed", "3",
                         "--set", "train.lr=2e-3"])
    assert r0["start"] == 2 and r0["losses"] == []
    same = torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)
    for k, v in ck["model"].items():
        assert torch.equal(v, same["model"][k])
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="train"):
        r2 = drape_net.main(["--config", path, "--out", out, "--no-progress", "--resume", "--steps", "4", "--seed", "3",
                             "--set", "train.lr=2e-3"])
    assert r2["start"] == 2 and len(r2["losses"]) == 2
    assert not caplog.messages  # more steps: the same run
    with caplog.at_level(logging.WARNING, logger="train"):
        drape_net.main(["--config", path, "--out", out, "--no-progress", "--resume", "--steps", "4", "--seed", "3"])
    assert any("differs from the checkpoint's at train.lr" in m for m in caplog.messages)
    ck2 = torch.load(os.path.join(out, "checkpoint.pt"), weights_only=True)
    assert ck2["step"] == 4
    assert all(int(s["step"]) == 4 for s in ck2["optimizer"]["state"].values())  # Adam continued, not restarted
    # a checkpoint holding arbitrary objects is refused with its path named
    torch.save({"step": 1, "obj": logging.getLogger("x")}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="cannot be read with weights_only=True"):
        cli.load_checkpoint(str(tmp_path / "bad.pt"))
    with pytest.raises(ValueError, match="no checkpoint at"):
        cli.load_checkpoint(str(tmp_path / "none.pt"))


def test_scene_resume_continues_exactly(tmp_path):
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    cfg["output"]["every"] = 2
    full = run_config(cfg, str(tmp_path / "full"), steps=6, resolution=(5, 5), progress=False)
    run_config(cfg, str(tmp_path / "part"), steps=4, resolution=(5, 5), progress=False)
    ck = torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=True)
    assert ck["step"] == 4 and _plain(ck)
    resumed = run_config(cfg, str(tmp_path / "part"), steps=6, resolution=(5, 5), progress=False, resume=True)
    assert len(resumed["steps"]) == 6
    x_full = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=True)["x"]
    x_res = torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=True)["x"]
    assert torch.equal(x_full, x_res)
    assert [s["iterations"] for s in resumed["steps"]] == [s["iterations"] for s in full["steps"]]


# ------------------------------------------------------------------------------ snapshots
def test_snapshot_draws_every_collider(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchbend.scenes.plot import draw_colliders, snapshot

    sphere, plane = tb.Sphere((0.1, 0.0, 0.2), 0.3), tb.Plane(point=(0, 0, -0.5), normal=(0, 1, 1))
    capsule = tb.Capsule((0, 0, 0), (0.4, 0.2, 0.0), 0.05)
    fig = plt.figure()
    ax = fig.add_subplot(projection="3d")
    bounds = np.array([[-0.5, -0.5, 0.0], [0.5, 0.5, 0.1]])
    drawn = draw_colliders(ax, [sphere, plane, capsule], bounds)
    plt.close(fig)
    assert len(drawn) == 3
    s, p, c = drawn
    assert np.allclose(np.linalg.norm(s - np.array(sphere.center), axis=1), 0.3)
    n = np.array(plane.normal)
    assert np.allclose((p - np.array(plane.point)) @ n, 0.0, atol=1e-12) and np.ptp(p, axis=0).max() >= 0.6
    a, b = np.array(capsule.a), np.array(capsule.b)
    t = np.clip(((c - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
    assert np.allclose(np.linalg.norm(c - (a + t[:, None] * (b - a)), axis=1), 0.05)
    rest, faces = tb.scenes.grid(4, 4, dtype=torch.float64)
    snapshot(str(tmp_path / "s.png"), [([(rest, faces)], [sphere, plane, capsule])], titles=["t"])
    assert (tmp_path / "s.png").stat().st_size > 1000


def test_robot_snapshot_includes_table_and_link_capsules(tmp_path, monkeypatch):
    import torchbend.scenes.run as run

    seen = {}
    monkeypatch.setattr(run, "snapshot", lambda path, panels, **kw: seen.update(panels=panels))
    cfg = load_config(os.path.join(CONFIGS, "robot_fold.yaml"))
    run_config(cfg, str(tmp_path), steps=2, resolution=(5, 5), progress=False)
    (meshes, colliders), = seen["panels"]
    assert sum(isinstance(c, tb.Plane) for c in colliders) == 1  # the table
    assert sum(isinstance(c, tb.Capsule) for c in colliders) == len(cfg["robot"]["capsules"]) == 3  # the arm's links


# ------------------------------------------------------------------------------ beams report
def test_beams_report_splits_kirchhoff_ratio(tmp_path):
    cfg = load_config(os.path.join(CONFIGS, "beams.yaml"))
    cfg["material"]["thicknesses"] = [2e-3, 1e-2]
    steps = run_config(cfg, str(tmp_path), resolution=(21, 4), progress=False)["steps"]
    thin, thick = steps
    for s in steps:  # tip/Kirchhoff = (tip/linear) x (linear/Kirchhoff)
        assert s["ratio"] == pytest.approx(s["nonlinearity"] * s["linear_to_kirchhoff"], rel=1e-12)
    # the mesh factor does not depend on the thickness (a property of the discrete energy on this grid)
    assert thin["linear_to_kirchhoff"] == pytest.approx(thick["linear_to_kirchhoff"], rel=1e-4)
    assert thick["nonlinearity"] > 0.99 and thin["nonlinearity"] < 0.95  # large deflection stiffens the thin one
    assert 0.2 < thick["linear_to_kirchhoff"] < 0.8


def test_hinge_energy_of_a_cylinder_on_a_grid_is_three_times_kirchhoff():
    """The reason for the beams' linear/Kirchhoff factor: a regular grid bent into a cylinder of
    curvature kappa stores about 3 k kappa^2 per area (k = D/2; plate theory: D kappa^2 / 2 = k kappa^2),
    while a sphere of radius R stores k (2H)^2 = 4 k / R^2 per area, as plate theory does."""
    L, W, nx, ny = 0.3, 0.3, 61, 61
    rest, faces = tb.scenes.grid(nx, ny, (L, W), dtype=torch.float64)
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=1.0)
    kappa = 2.0
    u = rest[:, 0] - L / 2
    cyl = torch.stack((torch.sin(kappa * u) / kappa, rest[:, 1], (1 - torch.cos(kappa * u)) / kappa), -1)
    # interior hinges only see the curvature: (nx - 2) of (nx - 1) columns of vertical hinges
    assert float(bend(cyl)) / (kappa**2 * L * W) == pytest.approx(3.0 * (nx - 2) / (nx - 1), rel=1e-3)
    sphere, sfaces = tb.scenes.icosphere(4, radius=1.0, dtype=torch.float64)
    sbend = tb.BendingEnergy(sfaces, sphere, model="quadratic", stiffness=1.0)
    sbend.rest_angles = torch.zeros_like(sbend.rest_angles)
    assert float(sbend(sphere)) / (4 * 4 * math.pi) == pytest.approx(1.0, rel=0.02)


def test_demo_takes_the_device_flag():
    import runpy

    demo = runpy.run_path(os.path.join(ROOT, "examples", "demo.py"))
    with pytest.raises(SystemExit) as e:
        demo["main"](["--device", _unavailable_device()])
    assert "\n" not in str(e.value.code) and "--device" in str(e.value.code)
