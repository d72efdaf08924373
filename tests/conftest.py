"""Shared fixtures: float64 by default in tests (explicit dtypes everywhere), fixed seeds."""
import pytest
import torch

import torchbend as tb
from torchbend.testing import plain_bending_energy

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
