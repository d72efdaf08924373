"""Command lines: every mistake a user can make (bad options, config values and files, devices,
robot links and joints, checkpoints of another run) ends with one line on stderr and a non-zero
exit status, never a traceback; messages quote at most about 200 characters of a value.

The command lines run in child processes: one helper process imports torch and the scripts once,
then forks a child per command line that runs it as ``python -m torchbend.scenes`` or
``python train/X.py`` would (``runpy``, the interpreter's handling of ``SystemExit`` and of uncaught
exceptions, stderr captured at the file descriptor).  A few run as real subprocesses too."""
import json
import logging
import os
import subprocess
import sys

import pytest
import torch
import yaml

import torchbend as tb
from torchbend.scenes import cli
from torchbend.scenes.config import (
    QUOTE_LIMIT,
    ConfigError,
    SceneConfig,
    build_mesh,
    load_config,
    one_line,
    short_repr,
    validate,
)
from torchbend.scenes.run import run_config

from .helpers import train_script

drape_net, material_id = train_script("drape_net"), train_script("material_id")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIGS = os.path.join(ROOT, "configs")
LONG = "x" * 5000  # an extremely long value
MAX_LINE = 3 * QUOTE_LIMIT + 200  # an error line quoting a long value once, clipped, plus the message

DRIVER = r'''
import json, os, runpy, signal, sys, tempfile
root = sys.argv[1]
sys.path.insert(0, os.path.join(root, "train"))
import torch  # noqa: F401  (imported once, before the children fork)
import torchbend.scenes.run  # noqa: F401
import common, drape_net, hood_style, material_id, robot_drape  # noqa: F401,E401
import tqdm  # noqa: F401
from torch.utils.tensorboard import SummaryWriter  # noqa: F401

results = []
for argv in json.load(sys.stdin):
    fd, err = tempfile.mkstemp()
    os.close(fd)
    pid = os.fork()
    if pid == 0:  # the child: run the command line as the interpreter would
        signal.alarm(120)
        os.dup2(os.open(err, os.O_WRONLY), 2)
        os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
        code = 0
        try:
            if argv[0] == "-m":
                sys.argv = [argv[1]] + argv[2:]
                runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
            else:
                sys.argv = list(argv)
                sys.path[0] = os.path.dirname(os.path.abspath(argv[0]))
                runpy.run_path(argv[0], run_name="__main__")
        except SystemExit as e:
            if e.code is None:
                code = 0
            elif isinstance(e.code, int):
                code = e.code
            else:
                print(e.code, file=sys.stderr)
                code = 1
        except BaseException:
            sys.excepthook(*sys.exc_info())
            code = 1
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    with open(err, errors="replace") as f:
        results.append({"rc": os.waitstatus_to_exitcode(status), "stderr": f.read()})
    os.unlink(err)
json.dump(results, sys.stdout)
'''


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])}


def _command(argv: list[str]) -> list[str]:
    """``["scenes", ...]`` -> ``-m torchbend.scenes ...``; ``["drape_net", ...]`` -> ``train/drape_net.py ...``."""
    if argv[0] == "scenes":
        return ["-m", "torchbend.scenes", *argv[1:]]
    return [os.path.join(ROOT, "train", f"{argv[0]}.py"), *argv[1:]]


def _run_all(commands: list[list[str]], cwd: str) -> list[dict]:
    if not hasattr(os, "fork"):  # one subprocess per command line
        out = []
        for c in commands:
            r = subprocess.run([sys.executable, *c], capture_output=True, text=True, cwd=cwd, env=_env(), timeout=300)
            out.append({"rc": r.returncode, "stderr": r.stderr})
        return out
    res = subprocess.run([sys.executable, "-c", DRIVER, ROOT], input=json.dumps(commands), capture_output=True,
                         text=True, cwd=cwd, env=_env(), timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout)


def assert_one_line_error(rc: int, stderr: str, *needles: str) -> str:
    """A user error: non-zero exit status (no signal), no traceback, exactly one non-empty line on
    stderr saying ``error:``, naming each of ``needles``, of bounded length."""
    assert rc > 0, f"exit status {rc}: {stderr[-2000:]}"
    assert "Traceback" not in stderr, stderr[-3000:]
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr[-3000:]
    line = lines[0]
    assert "error:" in line, line
    for needle in needles:
        assert needle in line, (needle, line)
    assert len(line) <= MAX_LINE, (len(line), line[:500])
    return line


# ------------------------------------------------------------------------------ fixtures
FILES = {"latin1": "latin1.yaml", "empty": "empty.yaml", "list": "list.yaml", "badyaml": "bad.yaml",
         "dir": "a_folder", "missing": "missing.yaml", "file": "a_file.txt", "tiny_drape": "tiny_drape.yaml",
         "tiny_material": "tiny_material.yaml", "notmesh": "notmesh.obj", "scene_ck": "scene_run",
         "drape_ck": "drape_run", "material_ck": "material_run", "garbage_ck": "garbage_run",
         "truncated_ck": "truncated_run", "out": "out"}


def _files(d: str) -> dict:
    """The bad inputs (configs, meshes, checkpoints) written into the folder ``d``: their paths."""
    p = {k: os.path.join(d, v) for k, v in FILES.items()}
    with open(p["latin1"], "wb") as f:
        f.write("solver: {dt: 0.01}  # d\u00e9j\u00e0 vu\n".encode("latin-1"))
    open(p["empty"], "w").close()
    with open(p["list"], "w") as f:
        f.write("- solver\n- mesh\n")
    with open(p["badyaml"], "w") as f:
        f.write("solver: {dt: 0.01\nmesh: [1, 2\n")
    os.makedirs(p["dir"])
    with open(p["file"], "w") as f:
        f.write("not a folder\n")
    with open(p["notmesh"], "w") as f:
        f.write("this is no mesh\n")
    tiny = {"mesh": {"nx": 5, "size": [0.8, 0.8], "offset": [-0.4, -0.4, 0.32]}, "model": {"hidden": 8, "layers": 1}, "train": {"steps": 2, "batch": 2},
            "eval": {"conditions": 3, "newton": 0}}
    with open(p["tiny_drape"], "w") as f:
        yaml.safe_dump(tiny, f)
    with open(p["tiny_material"], "w") as f:
        yaml.safe_dump({"mesh": {"type": "grid", "nx": 5, "ny": 2, "size": [0.2, 0.03], "pin": "first_two_columns"},
                        "identify": {"fit_rest_angles": True, "steps": 2}}, f)
    for k in ("scene_ck", "drape_ck", "material_ck", "garbage_ck", "truncated_ck"):
        os.makedirs(p[k])
    # a scene checkpoint: cloth_sphere at its 21 x 21 grid
    scene_cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    ck = os.path.join(p["scene_ck"], "checkpoint.pt")
    cli.save_checkpoint(ck, step=2, x=torch.zeros(441, 3), v=torch.zeros(441, 3), steps=[], pin_error=[], config=scene_cfg)
    with open(ck, "rb") as f:
        data = f.read()
    with open(os.path.join(p["truncated_ck"], "checkpoint.pt"), "wb") as f:
        f.write(data[: len(data) // 2])
    with open(os.path.join(p["garbage_ck"], "checkpoint.pt"), "wb") as f:
        f.write(b"\x00garbage, not a checkpoint\n" * 10)
    # a drape_net checkpoint of another config: a 6 x 6 cloth (this run's is 5 x 5)
    other = load_config(p["tiny_drape"], drape_net.Config, ["mesh.nx=6"])
    net = drape_net.DrapeNet(36, 8, 1)
    cli.save_checkpoint(os.path.join(p["drape_ck"], "checkpoint.pt"), step=2, model=net.state_dict(),
                        optimizer=torch.optim.Adam(net.parameters()).state_dict(), config=other)
    # a material_id checkpoint of another beam (6 x 2: more rest angles than this run's 5 x 2)
    other = load_config(p["tiny_material"], material_id.Config, ["mesh.nx=6"])
    hinges = material_id.build(other, torch.tensor(1.0, dtype=torch.float64))[2].hinge_count
    log_k, shift = torch.zeros((), dtype=torch.float64), torch.zeros(hinges, dtype=torch.float64)
    cli.save_checkpoint(os.path.join(p["material_ck"], "checkpoint.pt"), step=1, log_k=log_k, shift=shift,
                        optimizer=torch.optim.LBFGS([log_k, shift]).state_dict(), config=other)
    return p


def _cases(p: dict) -> list:
    """``(id, argv, needles)``: each command line and what its error line must name."""
    sphere, robot = os.path.join(CONFIGS, "cloth_sphere.yaml"), os.path.join(CONFIGS, "robot_fold.yaml")
    tiny, out = ["--config", p["tiny_drape"]], ["--out", p["out"]]
    return [
        # scenes: options
        ("scenes-steps-0", ["scenes", sphere, "--steps", "0"], ["--steps", "0"]),
        ("scenes-steps-negative", ["scenes", sphere, "--steps", "-3"], ["--steps", "-3"]),
        ("scenes-resolution-0", ["scenes", sphere, "--resolution", "0", "5"], ["--resolution", "0"]),
        ("scenes-resolution-huge", ["scenes", sphere, "--resolution", "100000", "100000"],
         ["--resolution", "100000 x 100000"]),
        ("scenes-seed-garbage", ["scenes", sphere, "--seed", "abc"], ["--seed", "'abc'"]),
        ("scenes-seed-huge", ["scenes", sphere, "--seed", "99999999999999999999999"], ["--seed"]),
        ("scenes-out-is-a-file", ["scenes", sphere, "--out", p["file"]], ["--out", "not a directory"]),
        ("scenes-log-level-long", ["scenes", sphere, "--log-level", LONG], ["--log-level"]),
        ("scenes-device-bogus", ["scenes", sphere, "--device", "bogus"], ["--device bogus", "not a torch device"]),
        ("scenes-device-cuda-99", ["scenes", sphere, "--device", "cuda:99"], ["--device cuda:99"]),
        ("scenes-device-meta", ["scenes", sphere, "--device", "meta"], ["--device meta", "cpu or cuda"]),
        ("scenes-device-cpu-1", ["scenes", sphere, "--device", "cpu:1"], ["--device cpu:1"]),
        ("scenes-device-long", ["scenes", sphere, "--device", LONG], ["--device xxxx"]),
        # scenes: config files
        ("scenes-latin1-config", ["scenes", p["latin1"]], [p["latin1"], "not UTF-8", "line 1"]),
        ("scenes-empty-config", ["scenes", p["empty"]], [p["empty"], "empty"]),
        ("scenes-list-config", ["scenes", p["list"]], [p["list"], "mapping", "a list"]),
        ("scenes-invalid-yaml", ["scenes", p["badyaml"]], [p["badyaml"], "invalid YAML at line"]),
        ("scenes-directory-config", ["scenes", p["dir"]], [p["dir"], "directory"]),
        ("scenes-missing-config", ["scenes", p["missing"]], [p["missing"], "not found"]),
        # scenes: --set
        ("scenes-set-wrong-type", ["scenes", sphere, "--set", "solver.steps=many"], ["solver.steps", "'many'"]),
        ("scenes-set-huge-grid", ["scenes", sphere, "--set", "mesh.nx=1000000000"], ["mesh", "1000000000"]),
        ("scenes-set-long-value", ["scenes", sphere, "--set", f"mesh.nx={LONG}"], ["mesh.nx", "xxxx"]),
        ("scenes-set-long-key", ["scenes", sphere, "--set", f"{LONG}=1"], ["unknown config key"]),
        ("scenes-set-long-model", ["scenes", sphere, "--set", f"bending.model={LONG}"], ["bending.model"]),
        ("scenes-set-nested-garbage", ["scenes", sphere, "--set", "solver=" + "[" * 5000 + "]" * 5000],
         ["nested too deeply"]),
        ("scenes-set-pin-out-of-range", ["scenes", sphere, "--set", "mesh.pin=[100000]"], ["mesh.pin", "100000"]),
        ("scenes-not-a-mesh", ["scenes", sphere, "--set", f"mesh={p['notmesh']}"], ["mesh.path", p["notmesh"]]),
        # scenes: robot links and joints
        ("scenes-robot-link", ["scenes", robot, "--set", "robot.pins[0].link=no_such_link"],
         ["robot.pins[0].link", "no_such_link"]),
        ("scenes-robot-capsule-link", ["scenes", robot, "--set", "robot.capsules[0].link=elbow_x"], ["elbow_x"]),
        ("scenes-robot-joints", ["scenes", robot, "--set", "robot.trajectory[0].q=[1, 2]"],
         ["robot.trajectory[0].q", "length 2"]),
        ("scenes-robot-urdf", ["scenes", robot, "--set", "robot.urdf=no_such.urdf"], ["no_such.urdf"]),
        # scenes: --resume
        ("scenes-resume-none", ["scenes", sphere, "--resume", *out], ["no checkpoint"]),
        ("scenes-resume-garbage", ["scenes", sphere, "--resume", "--out", p["garbage_ck"]], ["not a torch checkpoint"]),
        ("scenes-resume-truncated", ["scenes", sphere, "--resume", "--out", p["truncated_ck"]],
         ["not a torch checkpoint"]),
        ("scenes-resume-other-script", ["scenes", sphere, "--resume", "--out", p["drape_ck"]], ["another script"]),
        ("scenes-resume-other-scene", ["scenes", robot, "--resume", "--out", p["scene_ck"]],
         ["another scene", "scene.kind"]),
        ("scenes-resume-other-resolution", ["scenes", sphere, "--resume", "--out", p["scene_ck"], "--resolution", "3",
                                            "3"], ["(441, 3)", "(9, 3)"]),
        # drape_net
        ("drape-steps-0", ["drape_net", "--steps", "0"], ["--steps"]),
        ("drape-lr-nan", ["drape_net", "--lr", "nan"], ["--lr"]),
        ("drape-seed-negative", ["drape_net", "--seed", "-1"], ["--seed", "-1"]),
        ("drape-set-seed-huge", ["drape_net", *tiny, "--set", "train.seed=99999999999999999999"], ["train.seed"]),
        ("drape-set-resolution-huge", ["drape_net", *tiny, "--set", "mesh.nx=100000"], ["mesh", "100000"]),
        ("drape-set-batch-huge", ["drape_net", *tiny, "--set", "train.batch=100000000"], ["train.batch"]),
        ("drape-set-network-huge", ["drape_net", *tiny, "--set", "model.hidden=100000", "--set", "model.layers=3", *out],
         ["parameters", "model.hidden"]),
        ("drape-device-meta", ["drape_net", "--device", "meta"], ["--device meta"]),
        ("drape-latin1-config", ["drape_net", "--config", p["latin1"]], ["not UTF-8"]),
        ("drape-resume-other-config", ["drape_net", *tiny, "--resume", "--out", p["drape_ck"]],
         ["does not fit", "mesh.nx"]),
        ("drape-resume-other-script", ["drape_net", *tiny, "--resume", "--out", p["scene_ck"]], ["another script"]),
        ("drape-init-other-script", ["drape_net", *tiny, "--init", os.path.join(p["scene_ck"], "checkpoint.pt"), *out],
         ["--init", "no network weights"]),
        # robot_drape
        ("robot-steps-negative", ["robot_drape", "--steps", "-3"], ["--steps", "-3"]),
        ("robot-joints", ["robot_drape", "--set", "robot.nominal=[1, 2]"], ["robot.nominal", "length 2"]),
        ("robot-urdf", ["robot_drape", "--set", "robot.urdf=no_such.urdf"], ["no_such.urdf"]),
        ("robot-resume-other-script", ["robot_drape", "--resume", "--out", p["drape_ck"]], ["another script"]),
        # material_id
        ("material-steps-0", ["material_id", "--steps", "0"], ["--steps"]),
        ("material-device-cuda", ["material_id", "--device", "cuda"], ["--device cuda"]),
        ("material-set-beam-huge", ["material_id", "--set", "mesh.nx=100000000"], ["mesh", "100000000"]),
        ("material-set-seed-huge", ["material_id", "--set", "identify.seed=99999999999999999999"], ["identify.seed"]),
        ("material-empty-config", ["material_id", "--config", p["empty"]], ["empty"]),
        ("material-resume-other-beam", ["material_id", "--config", p["tiny_material"], "--resume", "--out",
                                        p["material_ck"]], ["does not fit", "mesh.nx", "rest-angle"]),
        ("material-resume-garbage", ["material_id", "--resume", "--out", p["garbage_ck"]], ["not a torch checkpoint"]),
        # hood_style
        ("hood-steps-0", ["hood_style", "--steps", "0"], ["--steps"]),
        ("hood-set-subdivisions-huge", ["hood_style", "--set", "body.subdivisions=30"], ["body.subdivisions"]),
        ("hood-set-network-huge", ["hood_style", "--set", "model.hidden=1000000", "--set", "mesh={type: grid, nx: 3}", *out],
         ["parameters"]),
        ("hood-list-config", ["hood_style", "--config", p["list"]], ["mapping"]),
        ("hood-missing-mesh", ["hood_style", "--set", "mesh=/no/such/garment.obj"], ["mesh.path", "/no/such/garment.obj"]),
        ("hood-resume-other-script", ["hood_style", "--resume", "--out", p["material_ck"]], ["another script"]),
    ]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict:
    return _files(str(tmp_path_factory.mktemp("cli_errors")))


@pytest.fixture(scope="module")
def results(files, tmp_path_factory) -> dict:
    """Every command line of :func:`_cases`, run (in a fresh working directory: nothing is written
    into the repository)."""
    cases = _cases(files)
    cwd = str(tmp_path_factory.mktemp("cwd"))
    out = _run_all([_command(argv) for _, argv, _ in cases], cwd)
    assert not os.listdir(cwd), os.listdir(cwd)  # no output written for a failed command
    return {case[0]: (r["rc"], r["stderr"]) for case, r in zip(cases, out, strict=True)}


@pytest.mark.parametrize("case", [c[0] for c in _cases(dict.fromkeys(FILES, "PATH"))])
def test_user_error_is_one_line_without_traceback(case, files, results):
    needles = {c[0]: c[2] for c in _cases(files)}[case]
    assert_one_line_error(*results[case], *needles)


def test_real_subprocesses_give_one_line(files, tmp_path):
    """The same through the interpreter itself: a config that is not UTF-8, ``--steps 0`` of a
    training script."""
    commands = [(["scenes", files["latin1"]], ["not UTF-8"]), (["drape_net", "--steps", "0"], ["--steps"])]
    for argv, needles in commands:
        r = subprocess.run([sys.executable, *_command(argv)], capture_output=True, text=True, cwd=str(tmp_path),
                           env=_env(), timeout=300)
        assert_one_line_error(r.returncode, r.stderr, *needles)


def test_long_values_are_quoted_clipped(results):
    """A 5000-character value appears with at most about 200 of its characters."""
    for case in ("scenes-set-long-value", "scenes-set-long-key", "scenes-set-long-model", "scenes-log-level-long",
                 "scenes-device-long"):
        line = results[case][1].strip()
        assert "x" * (QUOTE_LIMIT + 1) not in line and "X" * (QUOTE_LIMIT + 1) not in line, line[:400]


# ------------------------------------------------------------------------------ the pieces, in process
def test_one_line_and_short_repr():
    assert short_repr("abc") == "'abc'"
    long = short_repr("y" * 5000)
    assert len(long) <= QUOTE_LIMIT + 30 and long.startswith("'yyy")
    assert len(short_repr(list(range(10_000)))) < QUOTE_LIMIT
    deep: list = []
    for _ in range(50):
        deep = [deep]
    assert len(short_repr(deep)) < QUOTE_LIMIT
    line = one_line("first\n  second 'q" + "z" * 900 + "' and " + "w" * 700 + " end")
    assert "\n" not in line and line.startswith("first second 'qzzz") and line.endswith(" end")
    assert "z" * (QUOTE_LIMIT + 1) not in line and "w" * (QUOTE_LIMIT + 1) not in line
    assert len(one_line("word " * 2000)) < 1100
    assert str(ConfigError("a\nb")) == "a b"


def test_config_error_names_at_most_five_problems():
    cfg = {"solver": {f"x{i}": 1 for i in range(8)}}
    with pytest.raises(ConfigError) as e:
        validate(cfg, SceneConfig)
    msg = str(e.value)
    assert msg.count("unknown config key") == 5 and "... and 3 more" in msg


def test_run_main_user_errors_are_one_line_bugs_keep_their_traceback(caplog):
    def raising(exc):
        def main():
            raise exc
        return main

    cases = [(ValueError("bad value\nsecond line"), "prog: error: bad value second line"),
             (FileNotFoundError(2, "No such file or directory", "/no/such"), "prog: error: No such file or directory: /no/such"),
             (MemoryError(), "prog: error: out of memory"),
             (RuntimeError("[enforce fail] DefaultCPUAllocator: can't allocate memory: you tried 1e12 bytes"),
              "prog: error: out of memory")]
    for exc, start in cases:
        with pytest.raises(SystemExit) as e:
            cli.run_main(raising(exc), "prog")
        assert str(e.value.code).startswith(start) and "\n" not in str(e.value.code), e.value.code
    for bug in (RuntimeError("a bug"), KeyError("k"), TypeError("t")):  # not a user's mistake: raised as is
        with pytest.raises(type(bug)):
            cli.run_main(raising(bug), "prog")
    with pytest.raises(SystemExit) as e:
        cli.run_main(raising(KeyboardInterrupt()), "prog")
    assert e.value.code == 130


def test_run_main_prints_the_traceback_at_debug_level(capsys):
    level = logging.getLogger("torchbend").level
    logging.getLogger("torchbend").setLevel(logging.DEBUG)
    try:
        with pytest.raises(SystemExit):
            cli.run_main(lambda: (_ for _ in ()).throw(ValueError("shown with its traceback")), "prog")
    finally:
        logging.getLogger("torchbend").setLevel(level)
    assert "Traceback" in capsys.readouterr().err


def test_option_types():
    assert cli.positive_int("3") == 3 and cli.seed("0") == 0 and cli.positive_float("1e-3") == 1e-3
    for fn, text in [(cli.positive_int, "0"), (cli.positive_int, "-3"), (cli.positive_int, "x"), (cli.seed, "-1"),
                     (cli.seed, str(2**32)), (cli.positive_float, "nan"), (cli.positive_float, "-1"),
                     (cli.positive_float, "inf")]:
        with pytest.raises(Exception, match="must be"):
            fn(text)


def test_restore_refuses_optimizer_state_of_other_shapes(tmp_path):
    """``load_state_dict`` checks only the parameter counts: Adam's and L-BFGS's state of another
    network would fail at the next step, so :func:`cli.restore` compares the shapes."""
    def adam_state(net):
        opt = torch.optim.Adam(net.parameters())
        net(torch.ones(1, net.in_features)).sum().backward()
        opt.step()
        return opt.state_dict()

    net = torch.nn.Linear(2, 3)
    other = adam_state(torch.nn.Linear(3, 2))  # two parameters too, of other shapes
    with pytest.raises(ConfigError, match=r"does not fit this network \(config differs at model.hidden\).*exp_avg"):
        cli.restore("ck.pt", ["model.hidden"], (torch.optim.Adam(net.parameters()), other))
    cli.restore("ck.pt", [], (torch.optim.Adam(net.parameters()), adam_state(torch.nn.Linear(2, 3))))  # fits

    def lbfgs_state(params):
        opt = torch.optim.LBFGS(params, max_iter=1)

        def closure():
            opt.zero_grad()
            loss = torch.stack([(p ** 2).sum() for p in params]).sum()
            loss.backward()
            return loss

        opt.step(closure)
        return opt.state_dict()

    small, large = [torch.ones(2, requires_grad=True)], [torch.ones(5, requires_grad=True)]
    with pytest.raises(ConfigError, match="does not fit this run"):
        cli.restore("ck.pt", [], (torch.optim.LBFGS(small, max_iter=1), lbfgs_state(large)), what="run")


def test_resume_checkpoint_checks_the_script_and_its_fields(tmp_path):
    cfg = {"train": {"steps": 3}, "model": {"hidden": 8}}
    path = str(tmp_path / "ck.pt")
    cli.save_checkpoint(path, step=2, model={}, optimizer={}, config={"train": {"steps": 2}, "model": {"hidden": 4}})
    ck, changed = cli.resume_checkpoint(path, cfg, {"model": dict}, ignore=("train.steps",))
    assert ck["step"] == 2 and changed == ["model.hidden"]
    for state, match in [({"step": 2, "config": {"beam": {}}}, "another script"),
                         ({"step": 2}, "holds no config"),
                         ({"step": "two", "model": {}, "config": cfg}, "its step is 'two'"),
                         ({"step": 2, "config": cfg}, "'model' is missing"),
                         ({"step": 2, "model": [1], "config": cfg}, "'model' is a list")]:
        torch.save(state, path)
        with pytest.raises(ConfigError, match=match):
            cli.resume_checkpoint(path, cfg, {"model": dict})


def test_unreadable_mesh_file_is_a_config_error(monkeypatch):
    import torchbend.mesh

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(torchbend.mesh, "load", denied)
    with pytest.raises(ConfigError, match="config key 'mesh.path': cannot read garment.obj: Permission denied"):
        build_mesh({"type": "file", "path": "garment.obj"})


def test_resolution_and_steps_are_checked_by_the_library_too(tmp_path):
    for resolution in [(0, 5), (2.5, 3), (100_000, 100_000)]:
        with pytest.raises(ConfigError, match="--resolution"):
            build_mesh({"type": "grid"}, resolution=resolution)
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    for steps in (0, -3):
        with pytest.raises(ConfigError, match="--steps"):
            run_config(cfg, str(tmp_path / "run"), steps=steps, resolution=(3, 3), progress=False)
    assert not os.path.exists(tmp_path / "run")


def test_material_id_observation_that_does_not_converge_is_a_config_error(monkeypatch):
    cfg = load_config(os.path.join(CONFIGS, "train_material.yaml"), material_id.Config, ["mesh.nx=4", "mesh.ny=2"])

    def no_convergence(model, x0, **kwargs):
        return x0, type("Info", (), {"converged": False, "message": "max_iters reached"})()

    monkeypatch.setattr(tb, "solve_static", no_convergence)
    with pytest.raises(ConfigError, match="synthetic observation .* did not converge: max_iters reached"):
        material_id.observe(cfg)
