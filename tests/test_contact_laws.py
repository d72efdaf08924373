"""One contact module for the solver and the losses: the penalty and power-barrier laws of
:mod:`torchbend.energies.contact` (closed-form derivatives against autograd), the colliders with either law
(gradient and Hessian blocks against autograd, a static solve resting on a barrier), the contact loss with
the same laws, and the config's ``law`` key."""
import math

import pytest
import torch

import torchbend as tb
from torchbend.energies.contact import Penalty, PowerBarrier, contact_law
from torchbend.scenes.config import SceneConfig, build_collider, validate

from .helpers import assert_collider_derivatives_match_autograd

F64 = torch.float64


@pytest.mark.parametrize("law", [Penalty(3.0), PowerBarrier(5.0), PowerBarrier(2.0, 2.0), PowerBarrier(1.5, 1.5),
                                 PowerBarrier(7.0, 4.5)], ids=repr)
def test_law_derivatives_are_those_of_autograd(law):
    d = torch.linspace(-0.3, 0.4, 29, dtype=F64).requires_grad_()
    d = d[d.detach() != 0].detach().requires_grad_()  # the kink at 0 is not differentiable for p < 2
    (g,) = torch.autograd.grad(law.value(d).sum(), d, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), d)
    torch.testing.assert_close(law.slope(d.detach()), g.detach(), rtol=1e-14, atol=0)
    torch.testing.assert_close(law.curvature(d.detach()), h, rtol=1e-13, atol=0)
    assert bool((law.value(d.detach())[d.detach() < 0] == 0).all())
    assert bool(torch.isfinite(law.curvature(torch.zeros(3, dtype=F64))).all())  # no inf at contact onset


def test_the_penalty_is_the_barrier_of_power_two_at_half_the_stiffness():
    d = torch.linspace(-1, 1, 11, dtype=F64)
    for f in ("value", "slope", "curvature"):
        torch.testing.assert_close(getattr(Penalty(4.0), f)(d), getattr(PowerBarrier(2.0, 2.0), f)(d), rtol=1e-15, atol=0)


def test_contact_law_names_what_is_wrong():
    assert contact_law("barrier", 2.0) == PowerBarrier(2.0, 3.0)
    assert contact_law("penalty", 2.0) == Penalty(2.0)
    with pytest.raises(ValueError, match="contact law must be one of"):
        contact_law("spring", 1.0)
    with pytest.raises(ValueError, match="penalty contact law has power 2"):
        contact_law("penalty", 1.0, 3.0)
    with pytest.raises(ValueError, match="power must be > 1"):
        PowerBarrier(1.0, 1.0)
    with pytest.raises(ValueError, match="stiffness must be positive"):
        Penalty(-1.0)
    with pytest.raises(ValueError, match="Sphere: the penalty contact law has power 2"):
        tb.Sphere(radius=0.5, power=3.0, law="penalty")


COLLIDERS = [
    lambda **kw: tb.Sphere(center=(0.0, 0.0, -0.1), radius=0.3, **kw),
    lambda **kw: tb.Plane(point=(0.0, 0.0, 0.02), normal=(0.2, 0.0, 1.0), **kw),
    lambda **kw: tb.Capsule(a=(-0.2, 0.0, -0.1), b=(0.3, 0.05, -0.05), radius=0.2, **kw),
]


@pytest.mark.parametrize("make", COLLIDERS, ids=["sphere", "plane", "capsule"])
@pytest.mark.parametrize("law", [{"law": "barrier", "power": 3.0, "stiffness": 5e5},
                                 {"law": "barrier", "power": 2.5, "stiffness": 5e4},
                                 {"law": "penalty", "stiffness": 1e3}], ids=["p3", "p2.5", "penalty"])
def test_collider_gradient_and_hessian_blocks_match_autograd(make, law):
    c = make(margin=0.01, **law)
    gen = torch.Generator().manual_seed(2)
    x = 0.35 * torch.rand(40, 3, generator=gen, dtype=F64) - 0.15
    assert_collider_derivatives_match_autograd(c, x, rtol=1e-12, hessian_rtol=1e-10, hessian_atol=1e-10)


def test_a_strip_rests_on_a_barrier_plane_above_the_margin_depth_the_law_gives():
    """A free square sheet dropped on a barrier plane: at rest every vertex carries its weight,
    phi'(d) = m g, so its depth is d = (m g / (p k))^(1/(p-1)) below the margin."""
    rest, faces = tb.scenes.grid(4, 4, (0.1, 0.1), dtype=F64)
    k, p, margin = 1e6, 3.0, 2e-3
    plane = tb.Plane(point=(0.0, 0.0, 0.0), stiffness=k, margin=margin, law="barrier", power=p)
    model = tb.ClothModel(faces, rest, membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=1e-3),
                          density=0.2, colliders=[plane])
    x, info = tb.solve_static(model, rest + torch.tensor([0.0, 0.0, 0.01], dtype=F64), tol=1e-11)
    assert info.converged, info.message
    w = model.mass * 9.81
    depth = (w / (p * k)) ** (1 / (p - 1))
    torch.testing.assert_close(margin - x[:, 2], depth, rtol=1e-6, atol=0)


def test_the_contact_loss_takes_the_same_laws():
    x = torch.tensor([[[0.0, 0.0, -0.01], [0.0, 0.0, 0.5], [0.1, 0.0, 0.002]]], dtype=F64)
    plane = tb.Plane(point=(0.0, 0.0, 0.0), stiffness=1.0)  # the loss uses its signed distance only
    barrier = tb.losses.BodyContact(stiffness=2.0, eps=0.004, power=3.0, colliders=[plane])
    penalty = tb.losses.BodyContact(stiffness=2.0, eps=0.004, law="penalty", colliders=[plane])
    d = 0.004 - x[0, :, 2]
    assert math.isclose(float(barrier(x)), float(PowerBarrier(2.0, 3.0).value(d).sum()), rel_tol=1e-14)
    assert math.isclose(float(penalty(x)), float(Penalty(2.0).value(d).sum()), rel_tol=1e-14)
    # the solver's collider with the same law and margin has the same energy
    same = tb.Plane(point=(0.0, 0.0, 0.0), stiffness=2.0, margin=0.004, law="barrier", power=3.0)
    assert math.isclose(float(barrier(x)), float(same.energy(x[0])), rel_tol=1e-14)
    with pytest.raises(ValueError, match="BodyContact: the penalty contact law has power 2"):
        tb.losses.BodyContact(stiffness=1.0, law="penalty", power=3.0, colliders=[plane])


def test_config_colliders_take_the_law():
    cfg = validate({"colliders": [{"type": "plane", "law": "barrier", "power": 3, "stiffness": 1e5, "margin": 1e-3}]},
                   SceneConfig)
    c = build_collider(cfg.colliders[0])
    assert isinstance(c, tb.Plane) and c.contact == PowerBarrier(1e5, 3.0) and c.margin == 1e-3
    penalty = validate({"colliders": [{"type": "sphere", "law": "penalty"}]}, SceneConfig).colliders[0]
    assert build_collider(penalty).contact == Penalty(1e4)  # the penalty's defaults: 1e4 N/m, margin 0
    with pytest.raises(ValueError, match="'colliders\\[0\\]': the penalty law has power 2"):
        validate({"colliders": [{"type": "sphere", "law": "penalty", "power": 3}]}, SceneConfig)
    with pytest.raises(ValueError, match="colliders\\[0\\].law"):
        validate({"colliders": [{"type": "sphere", "law": "spring"}]}, SceneConfig)


@pytest.mark.parametrize("make", COLLIDERS, ids=["sphere", "plane", "capsule"])
def test_collider_energy_and_gradient_of_a_batch_are_those_of_each_sample(make):
    c = make(margin=0.01, law="barrier", power=3.0, stiffness=5e5)
    x = 0.35 * torch.rand(4, 2, 30, 3, generator=torch.Generator().manual_seed(5), dtype=F64) - 0.15
    e, g = c.energy(x), c.gradient(x)
    assert e.shape == (4, 2) and g.shape == x.shape
    for i in range(4):
        for j in range(2):
            assert float(e[i, j]) == float(c.energy(x[i, j]))
            assert torch.equal(g[i, j], c.gradient(x[i, j]))
