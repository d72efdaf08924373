"""benchmarks/bm_ratios.py (the kernels' ratios against their references, both timed in one process in turns) runs,
reports every pair it is asked for, prints the verdict its numbers give and caps the turns of a slow reference."""
import json
import os
import subprocess
import sys

import pytest

from tests.helpers import ROOT


def run_ratios(tmp_path, *args):
    out = tmp_path / "ratios.json"
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "bm_ratios.py"), "--sizes", "300", "--builds", "default",
           "--ops", "energy", "hvp", "--seconds", "0.01", "--json", str(out), *args]
    env = dict(os.environ, PYTHONPATH=ROOT)  # this tree's torchbend, whatever is installed
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (build,) = json.loads(out.read_text())["builds"]
    assert build["kernels"] == {} or build["kernels"]["package"] == os.path.join(ROOT, "torchbend")
    return build["rows"], proc.stdout


def test_ratios_benchmark_reports_each_pair(tmp_path):
    rows, stdout = run_ratios(tmp_path, "--turns", "4")
    # energy against autograd; the HVP against autograd, by the kernel and through torch.autograd
    assert [(r["op"], r["method"], r["reference"]) for r in rows] == [
        ("energy", "torchbend", "autograd"), ("hvp", "torchbend", "autograd"),
        ("hvp", "torchbend.backward", "autograd")]
    for r in rows:
        assert r["turns"] == 4 and r["hinges"] > 0
        assert r["ns"] > 0 and r["ref_ns"] > 0
        assert r["ratio_of_fastest"] == pytest.approx(r["ref_ns"] / r["ns"], rel=1e-12)
        assert r["ratio_min"] <= r["ratio_median"] <= r["ratio_max"]
        line = next(ln for ln in stdout.splitlines() if f" {r['op']} " in ln and f" {r['method']} " in ln)
        assert f"{r['ns']:9.1f} ns" in line and f"x{r['ratio_median']:6.1f} median" in line, line
        assert ("NOT met" in line) == (r["ratio_median"] < r["target"]), line  # the verdict of the median


def test_ratios_benchmark_caps_the_turns_of_a_slow_reference(tmp_path):
    rows, _ = run_ratios(tmp_path, "--turns", "5", "--slow-s", "0")  # every reference counts as slow
    assert rows and all(r["turns"] == 3 for r in rows)
