"""benchmarks/bm_lanes.py (the lane functions timed alone, per -march and source tree) runs and reports every function."""
import shutil

import pytest

from tests.helpers import benchmark_script

pytestmark = pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")


def test_lanes_benchmark_reports_each_function(capsys):
    bm = benchmark_script("bm_lanes")
    bm.main(["--arch", "x86-64-v3", "--rounds", "1", "--repeat", "2"])
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| this tree | x86-64-v3 |"))
    cells = [c.strip() for c in row.strip("|").split("|")][2:]
    assert len(cells) == 3 and all(float(c) > 0 for c in cells), row
    assert "# outputs: the same bits in every build" in out  # one build: its own checksum
