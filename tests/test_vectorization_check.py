"""tools/check_vectorization.py: its source-to-function mapping (fast) and the check itself (slow: it compiles
four translation units; CI runs the tool directly, see .ci/run)."""
from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOOL = os.path.join(ROOT, "tools", "check_vectorization.py")


def _tool():
    spec = importlib.util.spec_from_file_location("check_vectorization", TOOL)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


SOURCE = """\
#pragma once
// a comment (x)
template <typename T, int W> struct Half { T t[3][W]; };

template <typename T, int W>
TB_HD static inline void half_tile(const T (*A)[W], Half<T, W>& o) {
  TB_LANES(W) {
    o.t[0][l] = A[0][l];
  }
}
template <typename T, int W> TB_HD static inline void halves_tile(const T (*X)[W], Half<T, W>& hA) {
  for (int p = 0; p < 3; ++p) TB_LANES(W) hA.t[p][l] = X[p][l];
}
int declared_only(int x);
static void scatter(float* out, const float* in, int n) {
  for (int i = 0; i < n; ++i) out[i] += in[i];
  for (int i = 0; i < n; ++i) out[i] *= 2;
}
"""


def test_enclosing_functions_and_loop_counts(tmp_path, monkeypatch):
    cv = _tool()
    src = tmp_path / "kern.h"
    src.write_text(SOURCE)
    names = cv.enclosing_functions(str(src))
    lines = SOURCE.splitlines()
    at = {i + 1: names[i] for i in range(len(lines))}
    assert at[3] == "" and at[7] == "half_tile" and at[12] == "halves_tile"
    assert at[14] == "halves_tile"  # a declaration does not start a function
    assert at[16] == "scatter" and at[17] == "scatter"
    monkeypatch.setattr(cv.cfg, "CSRC", str(tmp_path))
    loops = [("kern.h", 7, 32), ("kern.h", 7, 32),  # one loop inlined twice counts once
             ("kern.h", 12, 16),                    # narrower than AVX2: not counted
             ("kern.h", 16, 32), ("kern.h", 17, 64), ("other.h", 3, 32)]
    assert cv.functions_vectorized(loops, 32) == {"half_tile": 1, "scatter": 2}
    assert cv.functions_vectorized(loops, 16) == {"half_tile": 1, "halves_tile": 1, "scatter": 2}


def test_report_line_format():
    cv = _tool()
    m = cv._REPORT.match("hinge_math.h:221:5: optimized: loop vectorized using 32 byte vectors")
    assert m is not None and (m.group("file"), m.group("line"), m.group("bytes")) == ("hinge_math.h", "221", "32")
    assert cv._REPORT.match("hinge_math.h:221:5: missed: couldn't vectorize loop") is None


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("g++") is None, reason="needs GCC")
def test_hot_loops_vectorize_for_avx2():
    run = subprocess.run([sys.executable, TOOL, "--arch", "x86-64-v3"], capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
