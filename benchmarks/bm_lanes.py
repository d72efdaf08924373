"""The lane functions of the CPU kernels timed alone, for each ``-march`` target and source tree (ns per lane).

    python benchmarks/bm_lanes.py                                   # this tree, native and x86-64-v3
    python benchmarks/bm_lanes.py --csrc /path/to/old/torchbend/csrc --rounds 5   # before/after, in turns

Compiles ``benchmarks/lanes/lanes.cpp`` (theta_tile over tiles of 16 stencils, psi_lane of the tan model,
tb_atan2v; 1e5 lanes of random data in L2, fastest of ``--repeat`` passes) with the extension's flags
(``-O3 -fno-math-errno -fno-trapping-math -march=<arch>``) against each csrc directory, then runs the programs in
turns for ``--rounds`` rounds and prints the median per build.  No extension build is needed: a change to the lane
code can be measured for the AVX2 (``x86-64-v3``) and the native code path of one machine in seconds.  The
operators themselves are measured by ``bm_throughput.py``; this isolates the per-lane mathematics.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import subprocess
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SOURCE = os.path.join(ROOT, "benchmarks", "lanes", "lanes.cpp")
FLAGS = ["-O3", "-std=c++17", "-fno-math-errno", "-fno-trapping-math"]


def _common():
    """benchmarks/common.py by its path (a plain ``import common`` may find another directory's module of that name
    when this script is loaded into a process that has one, as the tests do)."""
    spec = importlib.util.spec_from_file_location("_torchbend_bench_common", os.path.join(ROOT, "benchmarks", "common.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def build(csrc: str, arch: str, out: str) -> None:
    subprocess.run(["g++", *FLAGS, f"-march={arch}", f"-I{csrc}", SOURCE, "-o", out], check=True)


def run(exe: str, repeat: int) -> dict:
    text = subprocess.check_output([exe, str(repeat)], text=True)
    rows = [line.split() for line in text.splitlines()]
    out: dict = {r[0]: float(r[1]) for r in rows if r[0] != "#"}
    out["checksum"] = next(r[2] for r in rows if r[:2] == ["#", "checksum"])
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n", 1)[0])
    p.add_argument("--csrc", nargs="*", default=[], help="other csrc directories (default: only this tree's)")
    p.add_argument("--arch", nargs="+", default=["native", "x86-64-v3"])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--repeat", type=int, default=200)
    a = p.parse_args(argv)
    trees = [os.path.join(ROOT, "torchbend", "csrc")] + a.csrc
    common = _common()
    print(f"# {common.cpu_model()}; vector extensions: {', '.join(common.cpu_vector_extensions())}; {' '.join(FLAGS)}",
          flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        exes = {}
        for ti, tree in enumerate(trees):
            for arch in a.arch:
                exes[(ti, arch)] = os.path.join(tmp, f"lanes_{ti}_{arch}")
                build(tree, arch, exes[(ti, arch)])
        times: dict = {k: [] for k in exes}
        for _ in range(a.rounds):  # in turns: the machine's drift falls on every build alike
            for k, exe in exes.items():
                times[k].append(run(exe, a.repeat))
    names = [n for n in times[next(iter(times))][0] if n != "checksum"]
    print(f"# ns per lane, median of {a.rounds} rounds (each the fastest of {a.repeat} passes over 1e5 lanes)")
    print("| tree | -march | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for (ti, arch), rs in times.items():
        label = "this tree" if ti == 0 else trees[ti]
        print(f"| {label} | {arch} | " + " | ".join(f"{statistics.median(r[n] for r in rs):.2f}" for n in names) + " |")
    sums = {rs[0]["checksum"] for rs in times.values()}
    print("# outputs: " + ("the same bits in every build (checksum of all outputs)" if len(sums) == 1
                           else f"differ between builds (checksums {sorted(sums)})"))


if __name__ == "__main__":
    main()
