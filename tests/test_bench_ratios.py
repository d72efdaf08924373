"""benchmarks/bm_ratios.py (the kernels' ratios against their references, both timed in one process in turns) runs,
reports every pair it is asked for and records what it printed."""
import json
import os
import subprocess
import sys

import pytest

from tests.helpers import ROOT


def test_ratios_benchmark_reports_each_pair(tmp_path):
    out = tmp_path / "ratios.json"
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "bm_ratios.py"), "--sizes", "300", "--builds", "default",
           "--ops", "energy", "hvp", "--turns", "3", "--seconds", "0.01", "--json", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rec = json.loads(out.read_text())
    (build,) = rec["builds"]
    rows = build["rows"]
    # energy against autograd; the HVP against autograd, by the kernel and through torch.autograd
    assert [(r["op"], r["method"], r["reference"]) for r in rows] == [
        ("energy", "torchbend", "autograd"), ("hvp", "torchbend", "autograd"),
        ("hvp", "torchbend.backward", "autograd")]
    for r in rows:
        assert r["turns"] == 3 and r["hinges"] > 0
        assert r["ns"] > 0 and r["ref_ns"] > 0
        assert r["ratio_of_fastest"] == pytest.approx(r["ref_ns"] / r["ns"], rel=1e-12)
        assert r["ratio_min"] <= r["ratio_median"] <= r["ratio_max"]
        line = next(ln for ln in proc.stdout.splitlines() if f" {r['op']} " in ln and f" {r['method']} " in ln)
        assert f"{r['ns']:9.1f} ns" in line and (" met" in line or "NOT met" in line), line
