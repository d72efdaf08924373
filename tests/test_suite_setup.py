"""The test suite's own setup (tests/conftest.py): OpenMP workers wait passively, so that the suite's
multi-threaded tests do not stall beside another CPU-bound process on a 2-core machine."""
import os
import subprocess
import sys


def test_openmp_waits_passively_in_the_suite_and_its_subprocesses():
    assert os.environ.get("OMP_WAIT_POLICY", "").upper() == "PASSIVE" or "OMP_WAIT_POLICY" in os.environ
    out = subprocess.run([sys.executable, "-c", "import os; print(os.environ.get('OMP_WAIT_POLICY'))"],
                         capture_output=True, text=True, check=True).stdout.strip()
    assert out == os.environ["OMP_WAIT_POLICY"]
