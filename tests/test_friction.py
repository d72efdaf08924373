"""Lagged smooth Coulomb friction of the colliders (``friction=``, ``eps_v=``;
:mod:`torchbend.energies.friction`): the closed-form gradient and Hessian blocks against autograd and central
differences, positive semi-definite, finite at zero slip; in time steps a cloth on an incline sticks below
``tan(angle) = mu`` and slides with acceleration ``g (sin a - mu cos a)`` above it; static solves have none."""
import math

import pytest
import torch

import torchbend as tb
from torchbend.energies.friction import friction_blocks, friction_energy, friction_gradient
from torchbend.scenes.config import SceneConfig, build_collider, validate

F64 = torch.float64


def friction_case(seed: int, eps: float):
    gen = torch.Generator().manual_seed(seed)
    V = 30
    x_prev = torch.rand(V, 3, generator=gen, dtype=F64)
    n = torch.nn.functional.normalize(torch.randn(V, 3, generator=gen, dtype=F64), dim=-1)
    # slips from far below eps to far above it
    scale = eps * torch.logspace(-3, 2, V, dtype=F64)[:, None]
    x = x_prev + scale * torch.randn(V, 3, generator=gen, dtype=F64)
    weight = torch.rand(V, generator=gen, dtype=F64) + 0.1
    return x, x_prev, n, weight


@pytest.mark.parametrize("eps", [1e-5, 1e-2])
def test_friction_gradient_and_blocks_match_autograd(eps):
    x, x_prev, n, w = friction_case(1, eps)
    x = x.requires_grad_()
    (g,) = torch.autograd.grad(friction_energy(x, x_prev, n, w, eps), x, create_graph=True)
    torch.testing.assert_close(friction_gradient(x.detach(), x_prev, n, w, eps), g.detach(), rtol=1e-12,
                               atol=1e-12 * float(g.detach().abs().max()))
    H = torch.stack([torch.autograd.grad(g[:, j].sum(), x, retain_graph=True)[0] for j in range(3)], -1)
    blocks = friction_blocks(x.detach(), x_prev, n, w, eps)
    torch.testing.assert_close(blocks, H.transpose(-1, -2), rtol=1e-10, atol=1e-10 * float(H.abs().max()))
    ev = torch.linalg.eigvalsh(blocks)
    assert float(ev.min()) >= -1e-12 * float(ev.abs().max())  # PSD without a projection


def test_friction_gradient_matches_central_differences_over_an_epsilon_sweep():
    eps = 1e-3
    x, x_prev, n, w = friction_case(2, eps)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    exact = float((friction_gradient(x, x_prev, n, w, eps) * v).sum())
    hv = (friction_blocks(x, x_prev, n, w, eps) @ v[:, :, None])[:, :, 0]
    best_g, best_h = math.inf, math.inf
    for h in (1e-5, 1e-6, 1e-7, 1e-8):
        h = h * eps
        fd = (float(friction_energy(x + h * v, x_prev, n, w, eps)) - float(friction_energy(x - h * v, x_prev, n, w, eps))) / (2 * h)
        best_g = min(best_g, abs(fd - exact) / abs(exact))
        fd_h = (friction_gradient(x + h * v, x_prev, n, w, eps) - friction_gradient(x - h * v, x_prev, n, w, eps)) / (2 * h)
        best_h = min(best_h, float((fd_h - hv).norm() / hv.norm()))
    assert best_g < 1e-8 and best_h < 1e-6, (best_g, best_h)


def test_friction_is_finite_and_zero_force_at_zero_slip():
    x_prev = torch.rand(4, 3, dtype=F64)
    n = torch.tensor([[0.0, 0.0, 1.0]] * 4, dtype=F64)
    x = x_prev.clone()
    x[1, 2] += 1e-3  # a normal motion only: no slip
    x[2, 0] += 1e-300  # a subnormal slip
    w = torch.ones(4, dtype=F64)
    g, H = friction_gradient(x, x_prev, n, w, 1e-4), friction_blocks(x, x_prev, n, w, 1e-4)
    assert bool(torch.isfinite(g).all() and torch.isfinite(H).all())
    assert float(g.abs().max()) < 1e-290
    P = torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    torch.testing.assert_close(H[0], 2 / 1e-4 * P, rtol=1e-14, atol=0)  # mu lam f1'(0) on the tangent plane


def incline(angle_deg: float, mu: float, steps: int = 40, law=None):
    """A 10 cm sheet resting on a plane inclined by ``angle_deg``: the mean downhill velocity after each step."""
    a = math.radians(angle_deg)
    n = torch.tensor([math.sin(a), 0.0, math.cos(a)], dtype=F64)
    downhill = torch.tensor([math.cos(a), 0.0, -math.sin(a)], dtype=F64)
    flat, faces = tb.scenes.grid(5, 5, (0.1, 0.1), dtype=F64)
    rest = flat[:, :1] * downhill + flat[:, 1:2] * torch.tensor([0.0, 1.0, 0.0], dtype=F64) + 5e-4 * n
    law = law or {"law": "ipc", "stiffness": 1.0, "margin": 1e-3}
    plane = tb.Plane(point=(0.0, 0.0, 0.0), normal=tuple(n.tolist()), friction=mu, eps_v=1e-4, **law)
    model = tb.ClothModel(faces, rest, bending=tb.BendingEnergy(faces, rest, stiffness=1e-5),
                          membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                          colliders=[plane], density=0.2)
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    v = []
    for _ in range(steps):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, info.message
        assert not plane.contact.bounded or float(plane._sd(state.x)[0].min()) > 0  # ipc: never on the plane
        v.append(float((state.v @ downhill).mean()))
    return v


@pytest.mark.parametrize("law", [None, {"law": "penalty", "stiffness": 1e4}], ids=["ipc", "penalty"])
def test_a_cloth_on_an_incline_sticks_below_the_friction_angle(law):
    mu = 0.5
    v = incline(20.0, mu, law=law)  # tan 20 deg = 0.36 < mu
    assert max(abs(s) for s in v[10:]) < 1e-4  # at most eps_v: static friction's creep
    assert abs(v[-1] - v[20]) < 1e-5


@pytest.mark.parametrize("angle", [35.0, 50.0])
def test_a_cloth_on_an_incline_slides_with_the_coulomb_acceleration_above_it(angle):
    mu = 0.5
    v = incline(angle, mu)
    a = math.radians(angle)
    expected = 9.81 * (math.sin(a) - mu * math.cos(a))
    measured = (v[-1] - v[19]) / (0.01 * (len(v) - 20))
    assert math.isclose(measured, expected, rel_tol=0.02), (measured, expected)


def test_frictionless_incline_accelerates_at_g_sin_a_and_static_solves_have_no_friction():
    v = incline(30.0, 0.0, steps=25)
    assert math.isclose((v[-1] - v[9]) / (0.01 * 15), 9.81 * 0.5, rel_tol=1e-6)
    flat, faces = tb.scenes.grid(4, 4, (0.1, 0.1), dtype=F64)
    model = tb.ClothModel(faces, flat + torch.tensor([0.0, 0.0, 5e-4], dtype=F64),
                          membrane=tb.MembraneEnergy(faces, flat, young=1e5, poisson=0.3, thickness=5e-4), density=0.2,
                          colliders=[tb.Plane(friction=0.8, law="ipc", stiffness=1.0, margin=1e-3)])
    x = flat + torch.tensor([0.03, 0.0, 5e-4], dtype=F64)
    ctx = tb.StepContext()
    for term in model.terms:
        term.begin_step(ctx)
    assert not ctx.lagged  # no time step: no lagged friction data
    torch.testing.assert_close(model.terms[-1].energy(x, ctx), model.colliders[0].energy(x), rtol=0, atol=0)


def test_friction_arguments_are_checked_and_kept_by_configs_and_moved_capsules():
    with pytest.raises(ValueError, match="Sphere.friction"):
        tb.Sphere(friction=-0.1)
    with pytest.raises(ValueError, match="Plane.eps_v"):
        tb.Plane(eps_v=0.0)
    cap = tb.Capsule(friction=0.3, eps_v=1e-3).transformed((0.0, 0.0, 0.0), torch.tensor([1.0, 0.0, 0.0]))
    assert cap.friction == 0.3 and cap.eps_v == 1e-3
    cfg = validate({"colliders": [{"type": "plane", "friction": 0.4, "eps_v": 2e-3}]}, SceneConfig)
    c = build_collider(cfg.colliders[0])
    assert c.friction == 0.4 and c.eps_v == 2e-3
