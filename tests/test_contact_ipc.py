"""The log barrier of Incremental Potential Contact as a contact law of the analytic colliders
(``law="ipc"``, :class:`torchbend.energies.contact.LogBarrier`): its closed-form derivatives against
autograd of the barrier written on the gap and against central differences, C2 at the activation and
infinite on the surface; the colliders' gradient and Hessian blocks with it; the step bound that keeps every
vertex outside; solves that never reach the surface; and the errors of a state inside a barrier."""
import math

import pytest
import torch

import torchbend as tb
from torchbend.energies.colliders import _TensorCapsule
from torchbend.energies.contact import LogBarrier, contact_law
from torchbend.scenes.config import SceneConfig, build_collider, validate

from .helpers import assert_collider_derivatives_match_autograd

F64 = torch.float64


def gap_barrier(s: torch.Tensor, k: float, dhat: float) -> torch.Tensor:
    """The barrier as IPC writes it, on the gap ``s``: ``-k (s - dhat)^2 log(s / dhat)`` for ``0 < s < dhat``."""
    return torch.where(s < dhat, -k * (s - dhat) ** 2 * torch.log(s / dhat), torch.zeros_like(s))


@pytest.mark.parametrize("k,dhat", [(1.0, 2e-3), (3e4, 1e-4), (0.5, 0.3)])
def test_log_barrier_derivatives_are_those_of_the_gap_barrier(k, dhat):
    law = LogBarrier(k, dhat)
    s = (dhat * torch.cat([torch.logspace(-12, -0.01, 40, dtype=F64), torch.linspace(1.001, 2, 5, dtype=F64)]))
    d = dhat - s
    s = (dhat - d).requires_grad_()  # the gap the depth stands for (exact for s < dhat / 2, Sterbenz)
    e = gap_barrier(s, k, dhat)
    (g,) = torch.autograd.grad(e.sum(), s, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), s)
    torch.testing.assert_close(law.value(d), e.detach(), rtol=1e-12, atol=0)
    torch.testing.assert_close(law.slope(d), -g.detach(), rtol=1e-11, atol=0)  # d = dhat - s
    torch.testing.assert_close(law.curvature(d), h, rtol=1e-11, atol=0)
    assert bool((law.curvature(d) >= 0).all())  # convex


def test_log_barrier_derivatives_match_central_differences_over_an_epsilon_sweep():
    law, dhat = LogBarrier(2.0, 1e-3), 1e-3
    d = torch.tensor([1e-5, 2e-4, 5e-4, 9e-4, 9.99e-4], dtype=F64) * (dhat / 1e-3)
    best_g, best_h = math.inf, math.inf
    for eps in (1e-6, 1e-7, 1e-8, 1e-9):
        h = eps * dhat
        fd_g = (law.value(d + h) - law.value(d - h)) / (2 * h)
        fd_h = (law.slope(d + h) - law.slope(d - h)) / (2 * h)
        best_g = min(best_g, float(((fd_g - law.slope(d)).abs() / law.slope(d).abs()).max()))
        best_h = min(best_h, float(((fd_h - law.curvature(d)).abs() / law.curvature(d).abs()).max()))
    assert best_g < 1e-6 and best_h < 1e-6, (best_g, best_h)


def test_log_barrier_is_c2_at_the_activation_and_infinite_on_the_surface():
    law = LogBarrier(5.0, 2e-3)
    zero = torch.tensor([-1.0, -1e-9, 0.0], dtype=F64)
    for f in (law.value, law.slope, law.curvature):
        assert torch.equal(f(zero), torch.zeros(3, dtype=F64))
    tiny = torch.tensor([1e-9], dtype=F64)  # phi ~ k d^3 / dhat near the activation
    assert math.isclose(float(law.value(tiny)), 5.0 * 1e-27 / 2e-3, rel_tol=1e-5)
    on_or_inside = torch.tensor([2e-3, 3e-3, 1.0], dtype=F64)
    for f in (law.value, law.slope, law.curvature):
        assert bool(torch.isposinf(f(on_or_inside)).all())


def test_ipc_law_names_what_is_wrong():
    assert contact_law("ipc", 2.0, margin=1e-3) == LogBarrier(2.0, 1e-3)
    with pytest.raises(ValueError, match="ipc contact law needs margin > 0"):
        contact_law("ipc", 2.0)
    with pytest.raises(ValueError, match="ipc contact law has no power"):
        contact_law("ipc", 2.0, 3.0, margin=1e-3)
    with pytest.raises(ValueError, match="Sphere: the ipc contact law needs margin > 0"):
        tb.Sphere(radius=0.5, law="ipc", stiffness=1.0, margin=0.0)
    with pytest.raises(ValueError, match="stiffness must be positive"):
        LogBarrier(-1.0, 1e-3)
    with pytest.raises(ValueError, match="BodyContact: the ipc law is infinite inside the body"):
        tb.losses.BodyContact(stiffness=1.0, law="ipc", colliders=[tb.Plane()])


COLLIDERS = {
    "sphere": lambda **kw: tb.Sphere(center=(0.0, 0.0, -0.1), radius=0.3, **kw),
    "plane": lambda **kw: tb.Plane(point=(0.0, 0.0, 0.02), normal=(0.2, 0.0, 1.0), **kw),
    "capsule": lambda **kw: tb.Capsule(a=(-0.2, 0.0, -0.1), b=(0.3, 0.05, -0.05), radius=0.2, **kw),
}


def outside_points(c, n: int, dhat: float, seed: int) -> torch.Tensor:
    """``n`` points outside ``c``, about half of them within ``dhat`` of its surface."""
    gen = torch.Generator().manual_seed(seed)
    x = 0.8 * torch.rand(20 * n, 3, generator=gen, dtype=F64) - 0.4
    s, normal, _ = c._sd(x)
    near = x - (s - dhat * torch.rand(s.shape, generator=gen, dtype=F64))[:, None] * normal  # moved to a gap in (0, dhat)
    x = torch.cat([near[: n // 2], x[s > 0][: n - n // 2]])
    assert bool((c._sd(x)[0] > 0).all())
    return x


@pytest.mark.parametrize("name", list(COLLIDERS))
def test_ipc_collider_gradient_and_hessian_blocks_match_autograd(name):
    dhat = 0.01
    c = COLLIDERS[name](law="ipc", stiffness=3.0, margin=dhat)
    x = outside_points(c, 40, dhat, 3)
    assert_collider_derivatives_match_autograd(c, x, rtol=1e-11, hessian_rtol=1e-9, hessian_atol=1e-10)


@pytest.mark.parametrize("name", list(COLLIDERS))
def test_ipc_step_bound_never_lets_a_vertex_reach_the_surface(name):
    dhat = 0.01
    c = COLLIDERS[name](law="ipc", stiffness=3.0, margin=dhat)
    x = outside_points(c, 200, dhat, 7)
    gen = torch.Generator().manual_seed(8)
    target = 0.8 * torch.rand(x.shape, generator=gen, dtype=F64) - 0.4
    dx = 2.0 * (target - x)  # long steps, many of them through the collider
    alpha = c.max_step(x, dx, depth=1e-3)  # the depth of a penetrating law is not used by a bounded one
    assert bool(((alpha > 0) & (alpha <= 1)).all())
    t = torch.linspace(0, 1, 401, dtype=F64)
    path = x[None] + t[:, None, None] * (alpha[:, None] * dx)[None]
    s = c._sd(path.reshape(-1, 3))[0].reshape(len(t), -1)
    assert bool((s > 0).all()), float(s.min())
    full = x[None] + t[:, None, None] * dx[None]
    crossing = (c._sd(full.reshape(-1, 3))[0].reshape(len(t), -1) <= 0).any(0)  # the whole step would hit it
    assert int(crossing.sum()) > 20 and bool((alpha[crossing] < 1).all())
    assert bool(torch.isfinite(c.energy(x + alpha[:, None] * dx)))


def hanging_cloth(law: dict, n: int = 9):
    """A square cloth pinned at two corners, hanging over a capsule rail under it."""
    rest, faces = tb.scenes.grid(n, n, (0.3, 0.3), dtype=F64)
    rest = rest - torch.tensor([0.15, 0.15, 0.0], dtype=F64)
    rail = tb.Capsule(a=(-0.3, 0.0, -0.03), b=(0.3, 0.0, -0.03), radius=0.02, **law)
    corners = [0, n - 1]
    model = tb.ClothModel(faces, rest, bending=tb.BendingEnergy(faces, rest, stiffness=1e-4),
                          membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                          colliders=[rail], density=0.2, pinned=corners)
    return model, rest, rail


def test_static_solve_on_an_ipc_rail_converges_outside_it_in_force_balance():
    dhat = 2e-3
    model, rest, rail = hanging_cloth({"law": "ipc", "stiffness": 1.0, "margin": dhat})
    x, info = tb.solve_static(model, rest)
    assert info.converged, info.message
    s = rail._sd(x)[0]
    assert float(s.min()) > 0  # never on or inside the rail
    assert int((s < dhat).sum()) > 0  # the rail holds the cloth up
    g = model.gradient(x)
    free = torch.ones(x.shape[0], dtype=torch.bool)
    free[[0, 8]] = False
    assert float(g[free].norm(dim=-1).max()) <= info.tolerance


def test_implicit_steps_onto_an_ipc_rail_stay_outside_it():
    dhat = 2e-3
    model, rest, rail = hanging_cloth({"law": "ipc", "stiffness": 1.0, "margin": dhat}, n=7)
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    gaps = []
    for _ in range(12):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, info.message
        gaps.append(float(rail._sd(state.x)[0].min()))
    assert min(gaps) > 0 and gaps[-1] < dhat  # it fell onto the rail, never through it


def test_a_solve_cannot_start_inside_an_ipc_collider():
    model, rest, rail = hanging_cloth({"law": "ipc", "stiffness": 1.0, "margin": 2e-3}, n=5)
    inside = rest.clone()
    inside[12] = torch.tensor([0.0, 0.0, -0.03], dtype=F64)  # the rail's axis
    with pytest.raises(ValueError, match=r"x0: collider0: vertex 12 is 0.02 m inside the Capsule"):
        tb.solve_static(model, inside)
    with pytest.raises(ValueError, match=r"state.x: collider0: vertex 12 is 0.02 m inside the Capsule"):
        tb.implicit_euler_step(model, tb.ClothState(inside, torch.zeros_like(inside)), 0.01)


def test_config_colliders_take_the_ipc_law():
    cfg = validate({"colliders": [{"type": "capsule", "law": "ipc", "stiffness": 2.0, "margin": 1e-3}]}, SceneConfig)
    assert build_collider(cfg.colliders[0]).contact == LogBarrier(2.0, 1e-3)
    with pytest.raises(ValueError, match="the ipc law needs margin > 0"):
        validate({"colliders": [{"type": "sphere", "law": "ipc", "stiffness": 1.0, "margin": 0.0}]}, SceneConfig)
    with pytest.raises(ValueError, match="the ipc law has no power"):
        validate({"colliders": [{"type": "sphere", "law": "ipc", "margin": 1e-3, "power": 3}]}, SceneConfig)


# ---- the default law: ipc, margin 1 mm, stiffness chosen by the model from the cloth's weight
def test_colliders_default_to_the_ipc_law_and_a_penalty_keeps_its_defaults():
    c = tb.Sphere(radius=0.3)
    assert c.law == "ipc" and c.margin == tb.Sphere.DEFAULT_MARGIN == 1e-3 and c.stiffness is None
    with pytest.raises(ValueError, match="Sphere: stiffness=None: the ipc law's stiffness is chosen"):
        c.energy(torch.zeros(2, 3, dtype=F64))
    assert tb.Sphere(radius=0.3, stiffness=2.0).contact == LogBarrier(2.0, 1e-3)
    p = tb.Plane(law="penalty")
    assert p.margin == 0.0 and p.stiffness == 1e4 and p.contact == contact_law("penalty", 1e4)
    assert tb.Capsule(law="barrier").contact == contact_law("barrier", 1e4, 3.0)


@pytest.mark.parametrize("gravity", [(0.0, 0.0, -9.81), (0.0, -3.0, 0.0), (0.0, 0.0, 0.0)])
def test_a_model_chooses_the_ipc_stiffness_that_holds_ten_vertex_weights_at_half_the_margin(gravity):
    rest, faces = tb.scenes.grid(6, 6, (0.4, 0.4), dtype=F64)
    rail = tb.Capsule(a=(-0.5, 0.0, -0.05), b=(0.5, 0.0, -0.05), radius=0.02)
    model = tb.ClothModel(faces, rest, density=0.3, gravity=gravity, colliders=[rail, tb.Plane(law="penalty")])
    g = math.hypot(*gravity) or 9.81  # no gravity: a standard weight
    weight = g * 0.3 * 0.16 / 36  # |g| times the mean lumped vertex mass (the area over the vertex count)
    chosen, plane = model.colliders
    assert plane.stiffness == 1e4  # a stiffness given (or a penalty's default) is kept
    # the force -phi'(d) at the gap margin / 2 (d = margin / 2) is ten mean vertex weights
    force = chosen.contact.slope(torch.tensor([0.5 * chosen.margin], dtype=F64))
    torch.testing.assert_close(force, torch.tensor([10 * weight], dtype=F64), rtol=1e-12, atol=0)
    assert rail.stiffness is None  # the user's collider is not changed
    model.colliders = [rail]  # assigned colliders are chosen for too
    assert model.colliders[0].stiffness == chosen.stiffness


def test_a_tensor_capsule_keeps_its_end_points_when_its_stiffness_is_chosen():
    a = torch.tensor([-0.5, 0.0, -0.05], dtype=F64, requires_grad=True)
    cap = tb.Capsule(radius=0.02).transformed(a, torch.tensor([0.5, 0.0, -0.05], dtype=F64))
    chosen = cap.with_weight(1e-3)
    assert chosen.stiffness == pytest.approx(cap.stiffness_for(1e-3))
    assert isinstance(chosen, _TensorCapsule) and chosen.ends[0] is a  # the same tensor: a moved capsule keeps its graph
    x = torch.tensor([[0.0, 0.0, -0.0295]], dtype=F64)  # 0.5 mm above the rail
    chosen.energy(x).backward()
    assert a.grad is not None and float(a.grad.abs().sum()) > 0


def test_defaults_solve_a_cloth_onto_a_rail_and_keep_it_outside():
    model, rest, _ = hanging_cloth({})  # the rail with every contact default
    x, info = tb.solve_static(model, rest)
    assert info.converged, info.message
    s = model.colliders[0]._sd(x)[0]
    assert 0 < float(s.min()) < 1e-3 and info.min_distance == pytest.approx(float(s.min()))
    assert info.contact_count == int((s < 1e-3).sum()) > 0


def test_config_colliders_default_to_ipc():
    cfg = validate({"colliders": [{"type": "plane"}, {"type": "sphere", "law": "penalty"}]}, SceneConfig)
    ipc, pen = (build_collider(c) for c in cfg.colliders)
    assert isinstance(ipc, tb.Plane) and isinstance(pen, tb.Sphere)
    assert (ipc.law, ipc.margin, ipc.stiffness) == ("ipc", 1e-3, None)
    assert (pen.law, pen.margin, pen.stiffness) == ("penalty", 0.0, 1e4)
