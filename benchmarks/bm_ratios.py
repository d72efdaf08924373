"""The CPU kernels' speed ratios measured side by side: torchbend's default path and the reference it is compared with,
in one process, in alternated turns.

    python benchmarks/bm_ratios.py                                   # 1e5 and 1e6 hinges; this build, then x86-64-v3
    python benchmarks/bm_ratios.py --sizes 1e5 --builds default --turns 9 --ops energy gradient hvp

BENCHMARKS.md (``report.py``) times every method of a size in a row, and the rows of the x86-64-v3 build in another
process after the whole report: a ratio there divides two times taken minutes (or half an hour) apart, and on a
shared 2-core VM the speed of a phase moves by 10-30% (``benchmarks/results/amd_zen4_2026-12-06.txt``, section 10).
Here both sides of each ratio are timed in the same process, turn after turn (the reference first in odd turns,
second in even ones), each turn's time the fastest call within ``--seconds``.  Reported per ratio: each side's
fastest call over all turns (ns a hinge), the ratio of those, and the median and range of the per-turn ratios.

The pairs (the CPU kernels issue's acceptance, float64, one thread): the energy, gradient and HVP of the default path
(``bend(x)``, ``bend.gradient``, ``bend.hvp``) against eager autograd of the plain energy (>= 5x, 8x, 20x), the HVP
through ``torch.autograd`` (double backward of ``bend(x)``) against the same (>= 10x), and the per-hinge blocks
(``bend.hinge_hessians``, fresh outputs) against ``vmap(hessian)`` of ``torch.func`` (>= 100x); the methods are
:func:`bm_throughput.torch_methods`, the report's.  Each build other than ``default`` (the one this process loads) is
measured in a child process with the kernels JIT-built for ``-march=<build>`` (``TORCHBEND_PREBUILT=0
TORCHBEND_CPU_ARCH=<build>``), the reference timed again there.  A reference that takes seconds a call (torch.func's blocks at 1e6 hinges) gets
three turns (:data:`SLOW_TURNS`, ``--slow-s``).  No assertions: this measures and prints.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import torch
from bm_throughput import MAX_REPEAT, parse_size, scene, torch_methods
from common import bench, kernel_build, machine

from torchbend.energies.sparse import HessianPattern

# (op, torchbend's method, the reference's method, the target ratio)
PAIRS = [
    ("energy", "torchbend", "autograd", 5.0),
    ("gradient", "torchbend", "autograd", 8.0),
    ("hvp", "torchbend", "autograd", 20.0),
    ("hvp", "torchbend.backward", "autograd", 10.0),
    ("hinge_hessians", "torchbend", "torch.func", 100.0),
]


SLOW_S, SLOW_TURNS = 5.0, 3
"""A reference whose warm-up call took over SLOW_S seconds (torch.func's blocks of 1e6 hinges: about a minute a call
on a 2-core VM) gets at most SLOW_TURNS turns."""


def fastest(fn, seconds: float) -> float:
    """The fastest call of ``fn`` (seconds) among those of about ``seconds`` (at least one; :func:`common.bench`)."""
    return bench(fn, budget=seconds, min_repeat=1, max_repeat=MAX_REPEAT, warmup=0)["min"]


def measure(sizes, ops, turns: int, seconds: float, log=print, slow_s: float = SLOW_S) -> list[dict]:
    """The ratios of :data:`PAIRS` (those of ``ops``) at each size, float64, in this process; a reference whose warm-up
    call took over ``slow_s`` seconds gets at most :data:`SLOW_TURNS` turns."""
    rows = []
    for size in sizes:
        bend, x, v = scene(size, torch.float64, torch.device("cpu"))
        H = bend.hinge_count
        methods = torch_methods(bend, x, v, HessianPattern(bend.topology))
        for op, ours, ref, target in PAIRS:
            if op not in ops:
                continue
            fa, fb = methods[ours][op], methods[ref][op]
            grad = torch.no_grad() if op == "energy" else torch.enable_grad()
            with grad:
                fa()  # warm-up (and the first call's one-off costs)
                t0 = time.perf_counter()
                fb()
                slow = time.perf_counter() - t0 > slow_s
                n_turns = min(turns, SLOW_TURNS) if slow else turns
                ta, tb, per_turn = [], [], []
                for t in range(n_turns):
                    if t % 2 == 0:
                        b = fastest(fb, seconds)
                        a = fastest(fa, seconds)
                    else:
                        a = fastest(fa, seconds)
                        b = fastest(fb, seconds)
                    ta.append(a)
                    tb.append(b)
                    per_turn.append(b / a)
            row = {"hinges": H, "op": op, "method": ours, "reference": ref, "target": target,
                   "ns": min(ta) / H * 1e9, "ref_ns": min(tb) / H * 1e9, "ratio_of_fastest": min(tb) / min(ta),
                   "ratio_median": statistics.median(per_turn), "ratio_min": min(per_turn),
                   "ratio_max": max(per_turn), "turns": n_turns}
            rows.append(row)
            log(format_row(row))
    return rows


def format_row(r: dict) -> str:
    met = "met" if r["ratio_median"] >= r["target"] else "NOT met"
    return (f"{r['hinges']:>8d} {r['op']:>15s} {r['method']:>18s} {r['ns']:9.1f} ns | {r['reference']:>10s} "
            f"{r['ref_ns']:10.1f} ns | x{r['ratio_of_fastest']:6.1f} fastest, x{r['ratio_median']:6.1f} median "
            f"({r['ratio_min']:.1f}-{r['ratio_max']:.1f}) of {r['turns']} turns | >= {r['target']:.0f}x {met}")


HEADER = (f"{'hinges':>8s} {'op':>15s} {'method':>18s} {'':>12s} | {'reference':>10s} {'':>13s} | ratios "
          "(reference / method)")


def child(build: str, a) -> dict:
    """This script's measurement in a child process with the kernels built for ``-march=build`` (``portable``,
    ``none`` or empty: no ``-march``), importing the torchbend this process imported; a child that fails is recorded
    as such (``{"build", "failed"}``), not raised."""
    import torchbend

    package_root = os.path.dirname(os.path.dirname(os.path.abspath(torchbend.__file__)))
    expect = "none" if build.strip().lower() in ("", "none", "portable") else build
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "rows.json")
        cmd = [sys.executable, os.path.abspath(__file__), "--builds", "default", "--sizes", *map(str, a.sizes),
               "--ops", *a.ops, "--turns", str(a.turns), "--seconds", str(a.seconds), "--threads", str(a.threads),
               "--slow-s", str(a.slow_s), "--json", out, "--quiet-header"]
        path = os.pathsep.join([package_root] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))
        env = dict(os.environ, TORCHBEND_PREBUILT="0", TORCHBEND_CPU_ARCH=build, OMP_NUM_THREADS=str(a.threads),
                   PYTHONPATH=path)
        proc = subprocess.run(cmd, env=env)
        if proc.returncode != 0:
            print(f"the -march={build} child failed (exit {proc.returncode})", flush=True)
            return {"build": build, "failed": f"exit {proc.returncode}"}
        with open(out) as f:
            rec = json.load(f)["builds"][0]
    built = rec["kernels"]
    if built.get("march") != expect or built.get("package") != os.path.dirname(os.path.abspath(torchbend.__file__)):
        raise RuntimeError(f"the -march={build} child ran kernels built for {built or 'nothing'}")
    rec["build"] = build
    return rec


def write(path: str | None, builds: list) -> None:
    """The record so far to ``path`` (after every build: a later one that fails keeps the earlier ones)."""
    if path:
        with open(path, "w") as f:
            json.dump({"machine": machine(), "builds": builds}, f, indent=1)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=parse_size, nargs="+", default=[100_000, 1_000_000])
    p.add_argument("--builds", nargs="+", default=["default", "x86-64-v3"],
                   help="'default': the kernels this process loads; any other: a -march value, JIT-built in a child")
    p.add_argument("--ops", nargs="+", default=sorted({op for op, *_ in PAIRS}), choices=sorted({op for op, *_ in PAIRS}))
    p.add_argument("--turns", type=int, default=5)
    p.add_argument("--seconds", type=float, default=0.5, help="per method and turn: the fastest call within this")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--slow-s", type=float, default=SLOW_S,
                   help=f"a reference whose warm-up call takes longer gets at most {SLOW_TURNS} turns")
    p.add_argument("--json", help="write the record to this JSON file")
    p.add_argument("--quiet-header", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    builds = []
    for build in a.builds:
        if build != "default":
            print(f"\nkernels built for -march={build} (a child process, TORCHBEND_PREBUILT=0 "
                  f"TORCHBEND_CPU_ARCH={build}):", flush=True)
            builds.append(child(build, a))
            write(a.json, builds)
            continue
        kern = kernel_build()
        if not a.quiet_header:
            print("machine:", machine(), flush=True)
            print(f"kernels: -march={kern.get('march')} ({kern.get('source')}, {kern.get('module')})", flush=True)
            print(f"float64, one process, {a.turns} alternated turns, fastest call of {a.seconds} s per side and turn",
                  flush=True)
        print(HEADER, flush=True)
        builds.append({"build": "default", "kernels": kern,
                       "rows": measure(a.sizes, a.ops, a.turns, a.seconds, log=lambda s: print(s, flush=True),
                                       slow_s=a.slow_s)})
        write(a.json, builds)


if __name__ == "__main__":
    main()
