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

import torchbend as tb  # noqa: E402
from torchbend.testing import plain_bending_energy  # noqa: E402

MODELS = ["quadratic", "tan", "sin"]


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture
def sheet():
    """A small random curved sheet (irregular triangles, boundary) and a perturbed state."""
    rest, faces = tb.scenes.random_curved_sheet(5, 4, amplitude=0.3, seed=3, dtype=torch.float64)
    gen = torch.Generator().manual_seed(7)
    x = rest + 0.05 * torch.randn(rest.shape, generator=gen, dtype=torch.float64)
    return rest, faces, x


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach(), b.detach()
    return float((a - b).norm() / b.norm())


def reference_hessian(bend: tb.BendingEnergy, x: torch.Tensor) -> torch.Tensor:
    """``(3V, 3V)`` torch.func Hessian of the plain autograd energy with ``bend``'s parameters."""
    n = x.numel()

    def energy(y):
        return plain_bending_energy(y, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, bend.model)

    return torch.func.hessian(energy)(x).reshape(n, n)
