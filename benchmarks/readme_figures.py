"""Measure every time and accuracy figure that README.md and the docs quote, record them, and rewrite them there.

    python benchmarks/readme_figures.py                  # measure everything (about 10 min on 2 cores)
    python benchmarks/readme_figures.py --only tests,robot_drape   # re-measure some, keep the others
    python benchmarks/readme_figures.py --readme-only    # rewrite README.md from the JSON, measure nothing
    python benchmarks/readme_figures.py --quick          # reduced runs that check this script: writes
                                                         # readme_figures_quick.json, leaves README.md alone

README.md (and every page of docs/) shows each figure between markers, ``<!-- fig:NAME -->47 s<!-- /fig -->``; the text between
them is ``figures[NAME]`` of ``benchmarks/results/readme_figures.json``, which also records the machine
(CPU, cores, load averages before and after each measurement, versions, commit) and each measurement's
command and raw numbers.  ``tests/test_readme_figures.py`` checks that README.md and the JSON agree and
that no unmarked time or accuracy figure is left in README.md's prose.

Measurements (each a fresh subprocess, as a newcomer runs it, under ``timeout``):

- ``compile``: ``pip wheel --no-build-isolation --no-deps`` of a copy of the tracked sources (the build
  ``pip install --no-build-isolation -e .`` runs: the CUDA one too where torch is a CUDA build), wall and CPU
  time, then the same again (the compiled modules reused), then the first call of the built package
  (the prebuilt module only loaded).  The wheel, unpacked, is the package the runs below import.
- ``jit``: the first call of the sources' package with an empty ``TORCH_EXTENSIONS_DIR`` (the compile on
  first use where the install built nothing); the warmed folder serves the test suite.
- ``quickstart``: ``python train/drape_net.py``; its ``history.json`` summary (cap gap, Newton checks).
- ``tests``: ``python -m pytest -q``, wall time and counts.
- ``robot_fold``: ``python -m torchbend.scenes configs/robot_fold.yaml``.
- ``robot_drape``: ``python train/robot_drape.py``: time and its held-out comparison with Newton.
- ``hood``: ``python benchmarks/bm_hood.py --vertices 10000 --batch 1``: HOOD's whole loss, forward + backward,
  torchbend.losses.hood against its plain PyTorch transcription (one thread).
- ``beams``: ``python -m torchbend.scenes configs/beams.yaml`` at the paper's three resolutions: the
  linear/Kirchhoff ratio and the Newton iterations of the softest beam.
"""
from __future__ import annotations

import argparse
import datetime
import glob
import json
import math
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(ROOT, "README.md")
RESULTS = os.path.join(ROOT, "benchmarks", "results", "readme_figures.json")
QUICK_RESULTS = os.path.join(ROOT, "benchmarks", "results", "readme_figures_quick.json")


def documents() -> list[str]:
    """README.md and the guides and pages of ``docs/``: the files whose figures this script measures and rewrites."""
    return [README] + sorted(glob.glob(os.path.join(ROOT, "docs", "**", "*.md"), recursive=True))


MARKER = re.compile(r"<!-- fig:([A-Za-z0-9_]+) -->(.*?)<!-- /fig -->", re.S)
MEASUREMENTS = ("jit", "compile", "import", "quickstart", "tests", "robot_fold", "robot_drape", "beams", "hood")
BEAM_RESOLUTIONS = ((61, 6), (131, 6), (196, 7))
NOTE = ("the project's shared 2-core CPU machine: other engineers' jobs ran at the same time (see the load "
        "averages of each measurement); times vary with that load")


# ------------------------------------------------------------------------------ formatting
def seconds(v: float) -> str:
    """``47 s``, ``6.2 s``, ``0.8 s``."""
    return f"{v:.0f} s" if v >= 9.95 else f"{v:.1f} s"


def milliseconds(v: float) -> str:
    return f"{1e3 * v:.0f} ms" if v >= 9.95e-3 else f"{1e3 * v:.1f} ms"


def sig(v: float, digits: int = 2) -> str:
    """``v`` rounded to ``digits`` significant digits, written without an exponent."""
    if v == 0 or not math.isfinite(v):
        return str(v)
    decimals = digits - 1 - math.floor(math.log10(abs(v)))
    return f"{v:.{decimals}f}" if decimals >= 0 else f"{round(v, decimals):.0f}"


def listing(items: list[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


# ------------------------------------------------------------------------------ machine and runs
def machine() -> dict:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    return {"cpu": cpu, "vector_extensions": vector_extensions(), "cores": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(),
            "torch": torch.__version__, "commit": commit + (" (with uncommitted changes)" if dirty else ""),
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "note": NOTE}


VECTOR_FLAGS = {"avx2": "AVX2", "fma": "FMA", "avx512f": "AVX-512", "amx_tile": "AMX", "asimd": "NEON", "sve": "SVE"}
"""The /proc/cpuinfo flags that name the vector instruction sets the kernels are built for, and their names."""


def vector_extensions() -> list[str]:
    """The vector instruction sets of this CPU (:data:`VECTOR_FLAGS`; empty where /proc/cpuinfo is missing)."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((set(line.split(":", 1)[1].split()) for line in f if line.startswith(("flags", "Features"))), set())
    except OSError:
        flags = set()
    return [name for flag, name in VECTOR_FLAGS.items() if flag in flags]


def machine_figure(results: dict) -> str:
    """Where the figures were measured: each CPU (model and vector extensions) with the measurements run on it."""
    groups: dict[str, list[str]] = {}
    for name in MEASUREMENTS:
        m = results.get("measurements", {}).get(name)
        if m is None:
            continue
        cpu = m.get("machine") or {"cpu": "an unrecorded CPU"}
        exts = cpu.get("vector_extensions")
        label = cpu["cpu"] + (f" ({', '.join(exts)})" if exts else "")
        groups.setdefault(label, []).append(name)
    if len(groups) == 1:
        return f"a 2-core {next(iter(groups))}"
    return "; ".join(f"{label} for {listing(names)}" for label, names in groups.items())


def load() -> list[float]:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover - not on Linux/macOS
        return []


def run(cmd: list[str], *, env: dict, timeout: float, cwd: str = ROOT) -> dict:
    """Run ``cmd``; wall and CPU (user + system of the children) time [s], return code, output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load0 = load()
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
        rc, out, err = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as e:
        rc, out, err = "timeout", str(e.stdout or ""), str(e.stderr or "")
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"cmd": " ".join(cmd), "rc": rc, "wall": wall, "cpu": cpu, "load_before": load0, "load_after": load(),
            "stdout": out, "stderr": err}


def checked(r: dict, what: str) -> dict:
    if r["rc"] != 0:
        raise RuntimeError(f"{what}: `{r['cmd']}` failed ({r['rc']}):\n{(r['stdout'] + r['stderr'])[-3000:]}")
    return r


def record(r: dict, **extra) -> dict:
    """What the JSON keeps of a run (no output)."""
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items() if k not in ("stdout", "stderr")} | extra


class Context:
    """The scratch folder, the environments of the runs and the reduced settings of ``--quick``."""

    def __init__(self, quick: bool, scratch: str):
        self.quick, self.scratch = quick, scratch
        self.python = sys.executable
        base = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "TORCH_EXTENSIONS_DIR")}
        self.ext = os.path.join(scratch, "torch_extensions")
        # the sources' package (tests, JIT build) and, once `compile` ran, the built wheel unpacked
        self.source_env = {**base, "PYTHONPATH": ROOT, "TORCH_EXTENSIONS_DIR": self.ext}
        self.package_env = dict(self.source_env)

    def out(self, name: str) -> str:
        return os.path.join(self.scratch, name)


FIRST_CALL = ("import json, time; t = time.perf_counter(); import torch, torchbend as tb; "
              "x, f = tb.scenes.grid(5, 5, dtype=torch.float64); tb.BendingEnergy(f, x, stiffness=1.0)(x); "
              "from torchbend.backends import native; print(json.dumps({**native.build_info(), "
              "'first_call': time.perf_counter() - t, 'file': tb.__file__}))")


# ------------------------------------------------------------------------------ measurements
def measure_compile(ctx: Context) -> dict:
    src, dist, site = ctx.out("src"), ctx.out("dist"), ctx.out("site")
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    for rel in filter(None, files.split("\0")):
        if os.path.isfile(os.path.join(ROOT, rel)):
            os.makedirs(os.path.dirname(os.path.join(src, rel)), exist_ok=True)
            shutil.copy2(os.path.join(ROOT, rel), os.path.join(src, rel))
    env = {**ctx.source_env, "TORCHBEND_BUILD_NATIVE": "1"}
    env.pop("PYTHONPATH")
    cmd = [ctx.python, "-m", "pip", "wheel", "-q", "--no-build-isolation", "--no-deps", "-w", dist, "."]
    first = checked(run(cmd, env=env, timeout=1200, cwd=src), "compile")
    wheel = next(os.path.join(dist, f) for f in os.listdir(dist) if f.endswith(".whl"))
    built = sorted(n for n in zipfile.ZipFile(wheel).namelist() if n.endswith(".so") or n.endswith(".pyd"))
    shutil.rmtree(dist)
    again = checked(run(cmd, env=env, timeout=1200, cwd=src), "compile (again)")
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    ctx.package_env = {**ctx.source_env, "PYTHONPATH": site}
    call = checked(run([ctx.python, "-c", FIRST_CALL], env=ctx.package_env, timeout=300, cwd=ctx.scratch), "first call")
    info = json.loads(call["stdout"].strip().splitlines()[-1])
    if info["source"] != "install":
        raise RuntimeError(f"the built package did not load its prebuilt module: {info}")
    return {"runs": [record(first), record(again), record(call)], "modules": built,
            "figures": {"compile_s": seconds(first["wall"]), "compile_cpu_s": seconds(first["cpu"]),
                        "compile_again_s": seconds(again["wall"]), "prebuilt_load": milliseconds(info["seconds"])},
            "values": {"compile_s": first["wall"], "compile_cpu_s": first["cpu"], "compile_again_s": again["wall"],
                       "prebuilt_load_s": info["seconds"]}}


def measure_jit(ctx: Context) -> dict:
    shutil.rmtree(ctx.ext, ignore_errors=True)
    env = {**ctx.source_env, "TORCHBEND_PREBUILT": "0"}
    r = checked(run([ctx.python, "-c", FIRST_CALL], env=env, timeout=900, cwd=ctx.scratch), "JIT build")
    info = json.loads(r["stdout"].strip().splitlines()[-1])
    if info["source"] != "jit":
        raise RuntimeError(f"expected a JIT build, got {info}")
    return {"runs": [record(r)], "figures": {"jit_s": seconds(info["seconds"])}, "values": {"jit_s": info["seconds"]}}


def measure_import(ctx: Context) -> dict:
    """``import torchbend`` after ``import torch``: torchbend's own cumulative time under ``python -X importtime``
    (the sources' package), the fastest of three fresh interpreters (issue target: at most 1 s)."""
    runs, times = [], []
    for _ in range(3):
        r = checked(run([ctx.python, "-X", "importtime", "-c", "import torch, torchbend"], env=ctx.source_env,
                        timeout=300, cwd=ctx.scratch), "import")
        rows = [line.split("|") for line in r["stderr"].splitlines() if line.startswith("import time:")]
        times.extend(int(row[1]) * 1e-6 for row in rows if len(row) == 3 and row[2].strip() == "torchbend")
        runs.append(record(r))
    best = min(times)
    return {"runs": runs, "figures": {"import_s": f"{best:.2f} s"}, "values": {"import_s": times}}


def measure_hood(ctx: Context) -> dict:
    """The ``total`` row of ``benchmarks/bm_hood.py`` at 10k vertices, batch 1 (2k with ``--quick``)."""
    cmd = [ctx.python, "benchmarks/bm_hood.py", "--vertices", "2000" if ctx.quick else "10000", "--batch", "1",
           "--budget", "0.2" if ctx.quick else "1.0"]
    r = checked(run(cmd, env=ctx.source_env, timeout=1200), "hood loss")
    rows = [line.split() for line in r["stdout"].splitlines() if line.strip().startswith("total")]
    ours, plain = float(rows[-1][1]) * 1e-3, float(rows[-1][2]) * 1e-3
    return {"runs": [record(r, table=r["stdout"].strip().splitlines()[-10:])],
            "figures": {"hood_ms": milliseconds(ours), "hood_plain_s": seconds(plain)},
            "values": {"torchbend_s": ours, "plain_s": plain}}


def train_run(ctx: Context, script: str, quick_steps: int, timeout: float, what: str) -> tuple[dict, dict]:
    """``python train/<script>.py`` into its own output folder (``quick_steps`` steps with ``--quick``):
    the run's record and its ``history.json``."""
    out = ctx.out(script)
    cmd = [ctx.python, f"train/{script}.py", "--out", out, "--no-progress"]
    cmd += ["--steps", str(quick_steps)] if ctx.quick else []
    r = checked(run(cmd, env=ctx.package_env, timeout=timeout), what)
    with open(os.path.join(out, "history.json")) as f:
        return r, json.load(f)


def measure_quickstart(ctx: Context) -> dict:
    r, history = train_run(ctx, "drape_net", 100, 600, "quick start")
    s = history["summary"]
    checks = s["newton"]
    v = {"wall_s": r["wall"], "train_s": s["train_seconds"], "steps": s["steps_run"], "final_loss_J": s["final_loss"],
         "cap_gap_m": s["cap_gap"], "edge_length_m": s["edge_length"], "conditions": s["conditions"],
         "energy_gap_J": s["energy_gap"], "relative_energy_gap": s["relative_energy_gap"], "rms_distance_m": s["rms_distance"],
         "newton_converged": s["newton_converged"], "newton_checks": len(checks)}
    fig = {"quickstart_s": seconds(r["wall"]), "quickstart_train_s": seconds(s["train_seconds"]),
           "quickstart_steps": str(s["steps_run"]), "quickstart_gap": f"{sig(1e3 * s['cap_gap'])} mm",
           "quickstart_gap_edges": sig(s["cap_gap"] / s["edge_length"]),
           "quickstart_energy_gap": f"{sig(100 * s['relative_energy_gap'])}%",
           "quickstart_rms": f"{sig(1e3 * s['rms_distance'])} mm"}
    return {"runs": [record(r, summary_line=r["stdout"].strip().splitlines()[-1])], "figures": fig, "values": v}


def _pytest_counts(text: str) -> dict:
    tail = [line for line in text.strip().splitlines() if re.search(r"\d+ (passed|failed)", line)]
    if not tail:
        raise RuntimeError(f"no pytest summary in:\n{text[-2000:]}")
    counts = {k: int(n) for n, k in re.findall(r"(\d+) (passed|failed|skipped|deselected|errors?|xfailed|xpassed)", tail[-1])}
    gpu = sum(int(n) for n, reason in re.findall(r"^SKIPPED \[(\d+)\] [^:]+:\d+: (.*)$", text, flags=re.M)
              if re.search(r"CUDA|GPU", reason))
    # the comparisons of README.md with the JSON skip while this script measures (and runs them after)
    own = sum(int(n) for n, reason in re.findall(r"^SKIPPED \[(\d+)\] [^:]+:\d+: (.*)$", text, flags=re.M)
              if "readme_figures.py is measuring" in reason)
    counts["passed"] = counts.get("passed", 0) + own
    counts["skipped"] = counts.get("skipped", 0) - own
    return counts | {"skipped_gpu": gpu, "skipped_while_measuring": own}


def measure_tests(ctx: Context) -> dict:
    cmd = [ctx.python, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider"] + (["tests/test_readme.py"] if ctx.quick else [])
    r = run(cmd, env={**ctx.source_env, "TORCHBEND_README_FIGURES": "measuring"}, timeout=2400)
    counts = _pytest_counts(r["stdout"])
    if r["rc"] != 0 or counts.get("failed"):
        raise RuntimeError(f"the test suite failed:\n{r['stdout'][-3000:]}")
    return {"runs": [record(r, counts=counts)], "values": {"wall_s": r["wall"], **counts},
            "figures": {"tests_s": seconds(r["wall"]), "tests_passed": str(counts.get("passed", 0)),
                        "tests_skipped": str(counts.get("skipped", 0)), "tests_skipped_gpu": str(counts["skipped_gpu"])}}


def measure_robot_fold(ctx: Context) -> dict:
    cmd = [ctx.python, "-m", "torchbend.scenes", "configs/robot_fold.yaml", "--out", ctx.out("robot_fold"),
           "--no-progress"] + (["--steps", "10"] if ctx.quick else [])
    r = checked(run(cmd, env=ctx.package_env, timeout=900), "robot_fold")
    return {"runs": [record(r)], "figures": {"robot_fold_s": seconds(r["wall"])}, "values": {"wall_s": r["wall"]}}


def measure_robot_drape(ctx: Context) -> dict:
    r, h = train_run(ctx, "robot_drape", 50, 900, "robot_drape")
    rms = [e["rms_distance_to_equilibrium"] for e in h["eval"]]
    gaps = [e["energy_gap"] for e in h["eval"]]
    return {"runs": [record(r)],
            "values": {"wall_s": r["wall"], "steps": h["steps"], "rms_distance_m": rms, "energy_gap_J": gaps,
                       "converged": [e["converged"] for e in h["eval"]]},
            "figures": {"robot_drape_s": seconds(r["wall"]), "robot_drape_steps": str(h["steps"]),
                        "robot_drape_rms": listing([sig(1e3 * v) for v in rms]) + " mm",
                        "robot_drape_energy_gap": f"{sig(1e3 * min(gaps))} to {sig(1e3 * max(gaps))} mJ"}}


def measure_beams(ctx: Context) -> dict:
    runs, rows = [], []
    for nx, ny in BEAM_RESOLUTIONS[:1] if ctx.quick else BEAM_RESOLUTIONS:
        out = ctx.out(f"beams_{nx}x{ny}")
        cmd = [ctx.python, "-m", "torchbend.scenes", "configs/beams.yaml", "--resolution", str(nx), str(ny),
               "--out", out, "--no-progress"]
        r = checked(run(cmd, env=ctx.package_env, timeout=900), "beams")
        with open(os.path.join(out, "stats.json")) as f:
            steps = json.load(f)["steps"]
        softest = min(steps, key=lambda s: s["thickness"])
        rows.append({"resolution": [nx, ny], "linear_to_kirchhoff": [s["linear_to_kirchhoff"] for s in steps],
                     "softest_iterations": softest["iterations"], "converged": all(s["converged"] for s in steps)})
        runs.append(record(r))
    first = rows[0]["linear_to_kirchhoff"]
    return {"runs": runs, "values": {"resolutions": rows},
            "figures": {"beams_linear_to_kirchhoff": f"{sum(first) / len(first):.2f}",
                        "beams_softest_iterations": listing([str(r["softest_iterations"]) for r in rows])}}


# ------------------------------------------------------------------------------ README
def readme_markers(text: str) -> dict[str, list[str]]:
    """``{name: [text between its markers, ...]}`` of a README text."""
    out: dict[str, list[str]] = {}
    for name, value in MARKER.findall(text):
        out.setdefault(name, []).append(value)
    return out


def rewrite(text: str, figures: dict[str, str]) -> str:
    """``text`` with every marked figure replaced by ``figures[name]`` (a name without a figure: ``KeyError``)."""
    missing = sorted(set(readme_markers(text)) - set(figures))
    if missing:
        raise KeyError(f"README.md marks figures that no measurement produced: {missing}")
    return MARKER.sub(lambda m: f"<!-- fig:{m.group(1)} -->{figures[m.group(1)]}<!-- /fig -->", text)


def combined_figures(results: dict) -> dict[str, str]:
    """Every measurement's figures, and those made of several (install plus quick start)."""
    figures: dict[str, str] = {}
    for name in MEASUREMENTS:
        figures.update(results.get("measurements", {}).get(name, {}).get("figures", {}))
    m = results.get("measurements", {})
    figures["machine"] = machine_figure(results)
    if "compile" in m and "quickstart" in m:
        figures["install_and_quickstart_s"] = seconds(m["compile"]["values"]["compile_s"] + m["quickstart"]["values"]["wall_s"])
    return figures


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--only", help=f"comma-separated measurements to run (others keep their recorded values): {', '.join(MEASUREMENTS)}")
    p.add_argument("--quick", action="store_true", help="reduced runs (check the script); own JSON, README untouched")
    p.add_argument("--readme-only", action="store_true", help="rewrite README.md from the recorded JSON, measure nothing")
    p.add_argument("--keep", action="store_true", help="keep the scratch folder (runs' outputs)")
    a = p.parse_args(argv)
    path = QUICK_RESULTS if a.quick else RESULTS
    results: dict = {}
    if os.path.exists(path):
        with open(path) as f:
            results = json.load(f)
    if not a.readme_only:
        names = MEASUREMENTS if not a.only else tuple(n.strip() for n in a.only.split(","))
        unknown = sorted(set(names) - set(MEASUREMENTS))
        if unknown:
            p.error(f"unknown measurements {unknown}; choose from {', '.join(MEASUREMENTS)}")
        if a.quick and "compile" in names and not a.only:
            names = tuple(n for n in names if n != "compile")  # --quick skips the compile unless asked for
        scratch = tempfile.mkdtemp(prefix="readme_figures_")
        ctx = Context(a.quick, scratch)
        results["machine"] = machine()
        results.setdefault("measurements", {})
        try:
            # the JIT build (measured or not) warms the extensions folder of the runs that import the sources
            order = ("jit",) + tuple(n for n in MEASUREMENTS if n in names and n != "jit")
            for name in order:
                print(f"readme_figures: {name} ...", file=sys.stderr, flush=True)
                t0 = time.perf_counter()
                m = globals()[f"measure_{name}"](ctx)
                if name not in names:
                    continue
                mach = {k: results["machine"][k] for k in ("cpu", "vector_extensions", "cores")}
                results["measurements"][name] = {**m, "measured": results["machine"]["date"], "machine": mach,
                                                 "quick": a.quick}
                print(f"readme_figures: {name}: {m['figures']} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        finally:
            if a.keep:
                print(f"readme_figures: outputs kept in {scratch}", file=sys.stderr)
            else:
                shutil.rmtree(scratch, ignore_errors=True)
        results["figures"] = combined_figures(results)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            json.dump(results, f, indent=1)
            f.write("\n")
        print(f"readme_figures: wrote {os.path.relpath(path, ROOT)}", file=sys.stderr)
    if a.quick:
        return
    for path in documents():
        with open(path, encoding="utf-8") as f:
            text = f.read()
        new = rewrite(text, results.get("figures", {}))
        name = os.path.relpath(path, ROOT)
        if new != text:
            with open(path, "w", encoding="utf-8") as f:
                f.write(new)
            print(f"readme_figures: {name} updated", file=sys.stderr)
        else:
            print(f"readme_figures: {name} already matches", file=sys.stderr)
    check = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_readme_figures.py"],
                           cwd=ROOT, capture_output=True, text=True)
    if check.returncode != 0:
        raise SystemExit(f"readme_figures: tests/test_readme_figures.py fails after the rewrite:\n{check.stdout[-3000:]}")


if __name__ == "__main__":
    main()
