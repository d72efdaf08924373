"""Shared fixtures: float64 by default in tests (explicit dtypes everywhere), fixed seeds.

OpenMP workers wait passively (``OMP_WAIT_POLICY=PASSIVE``, set here before torch loads its OpenMP runtime, and
inherited by the tests' subprocesses): by default they spin for a while at the end of every parallel region, and
on a 2-core machine that another CPU-bound process shares, a spinning worker takes the core the other thread of
the region needs.  Measured on the project's 2-core machine beside ``python -c "while True: pass"``: 2000
gradients of a 2.6k-hinge sheet in 2 threads took 57 s spinning and 1.0 s waiting passively (1.7 s in one
thread).  The suite passes either way; only its time under load changes."""
import os
import sys

if "torch" not in sys.modules:  # set before the OpenMP runtime starts; the user's own setting wins
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest  # noqa: E402
import torch  # noqa: E402

from .helpers import DEVICES, DTYPES, MODELS, curved_sheet, reference_hessian, rel  # noqa: E402

# MODELS, rel and reference_hessian stay importable from here for the test files that still do
__all__ = ["MODELS", "reference_hessian", "rel"]


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture
def sheet():
    """A small random curved sheet (irregular triangles, boundary) and a perturbed state (float64)."""
    return curved_sheet()


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """``cpu``, and ``cuda`` where a CUDA device exists (marked ``gpu``; skipped elsewhere)."""
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=lambda d: str(d).removeprefix("torch."))
def dtype(request) -> torch.dtype:
    """``torch.float64`` and ``torch.float32``."""
    return request.param
