"""tb.losses.SelfRepulsion: the self-contact loss keeps vertices on their side of nearby triangles."""
from __future__ import annotations

import pytest
import torch

import torchbend as tb
from torchbend.mesh.procedural import grid

F64 = torch.float64


def _two_sheets(gap: float, dtype=F64):
    """Two 5x5 sheets of 4 cm, ``gap`` apart along z, as one mesh (the upper one shifted off the lower grid lines and diagonals)."""
    a, fa = grid(5, 5, (0.04, 0.04), dtype=dtype)
    b = a + torch.tensor([0.0031, 0.0017, gap], dtype=dtype)
    return torch.cat([a, b]), torch.cat([fa, fa + len(a)])


def test_no_pairs_on_a_flat_sheet_and_no_energy_when_apart():
    x, f = grid(6, 6, (0.05, 0.05), dtype=F64)
    loss = tb.losses.SelfRepulsion(f, x)
    assert len(loss.pairs(x)[0]) == 0 and float(loss(x, x_curr=x)) == 0.0
    x2, f2 = _two_sheets(3e-3)
    loss2 = tb.losses.SelfRepulsion(f2, x2)
    i, f_, side = loss2.pairs(x2)
    assert len(i) > 0 and set(side.tolist()) == {-1.0, 1.0}  # each sheet's vertices over/under the other's faces
    assert float(loss2(x2, x_curr=x2)) == 0.0  # 3 mm apart, margin 1 mm


def test_a_vertex_through_the_other_sheet_pays_and_is_pushed_back():
    x_curr, f = _two_sheets(3e-3)
    loss = tb.losses.SelfRepulsion(f, x_curr, stiffness=1e4)
    upper = torch.arange(25, 50)
    x = x_curr.clone()
    x[upper[12], 2] = -2e-3  # the middle vertex of the upper sheet 2 mm below the lower one
    x.requires_grad_()
    e = loss(x, x_curr=x_curr)
    (g,) = torch.autograd.grad(e, x)
    assert float(e.detach()) > 0
    assert float(g[upper[12], 2]) < 0  # descent raises it back above
    # the energy is the cubic penalty of its depth (plus the margin) against the face below it
    i, f_, side = loss.pairs(x_curr)
    mine = torch.from_numpy(i) == upper[12]
    assert int(mine.sum()) >= 1


def test_gradcheck_and_batches():
    x_curr, f = _two_sheets(3e-3)
    loss = tb.losses.SelfRepulsion(f, x_curr, eps=2e-3)
    g = torch.Generator().manual_seed(0)
    x = torch.stack([x_curr + 1.5e-3 * torch.randn(x_curr.shape, generator=g, dtype=F64) for _ in range(2)])
    assert torch.autograd.gradcheck(lambda y: loss(y, x_curr=x_curr), (x.clone().requires_grad_(),))
    batched = loss(x, x_curr=x_curr)
    assert batched.shape == (2,) and float(batched.min()) > 0
    for b in range(2):
        torch.testing.assert_close(batched[b], loss(x[b], x_curr=x_curr), rtol=1e-14, atol=0)
    v32 = loss(x.float(), x_curr=x_curr.float())
    assert v32.dtype == torch.float32 and torch.allclose(v32.double(), batched, rtol=1e-4)


def test_bad_inputs_are_value_errors():
    x, f = _two_sheets(3e-3)
    with pytest.raises(ValueError, match="radius"):
        tb.losses.SelfRepulsion(f, x, radius=0.0)
    loss = tb.losses.SelfRepulsion(f, x)
    with pytest.raises(ValueError, match="x_curr"):
        loss(x, x_curr=x[:10])
