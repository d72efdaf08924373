"""IPC's lagged smooth friction between contact pairs (``SelfContact(friction=)``, ``MeshCollider(friction=)``):
the closest points' weights and normals against the pairs' own distances, the friction gradient and Hessian
against autograd and central differences, positive semi-definite blocks; in time steps a cloth on an inclined
body mesh, or on a pinned cloth layer, sticks below the friction angle and slides with Coulomb's acceleration
``g (sin a - mu cos a)`` above it, as on an analytic plane with ``friction=`` (tests/test_friction.py)."""
import math

import pytest
import torch

import torchbend as tb
from torchbend.ops.distance import by_type, edge_edge_type, point_triangle_type
from torchbend.options import Projection

F64 = torch.float64


def folded_sheet(seed: int = 0):
    """A 6 x 6 sheet folded over itself with its layers 0.6 mm apart (self-contact pairs of every type), and a
    lagged time-step context with friction; returns ``(model, term, x_prev, ctx)``."""
    flat, faces = tb.scenes.grid(6, 12, (0.05, 0.1), dtype=F64)
    y = flat[:, 1]
    fold = y > 0.05
    x = flat.clone()
    x[fold, 1] = 0.1 - y[fold] + 1e-3 * torch.rand(int(fold.sum()), generator=torch.Generator().manual_seed(seed),
                                                      dtype=F64)
    x[fold, 2] = 6e-4 + 2e-4 * torch.rand(int(fold.sum()), generator=torch.Generator().manual_seed(seed + 1),
                                          dtype=F64)
    sc = tb.SelfContact(dhat=1e-3, stiffness=1e3, friction=0.4, eps_v=1e-3)
    model = tb.ClothModel(faces, x, terms=[sc], density=0.2)
    ctx = tb.StepContext.for_step(model.terms, x, torch.zeros_like(x), 0.01)
    return model, sc, x, ctx


def test_pair_weights_give_the_closest_points_and_the_normal():
    _, sc, x, _ = folded_sheet()
    checked = 0
    for st, kind, eps in sc._groups(x):
        X = x[st]
        w, n, lam = sc._pair_frames(X, kind, eps)
        side_a = 1 if eps is None else 2
        torch.testing.assert_close(w[:, :side_a].sum(1), torch.ones(len(w), dtype=F64), rtol=0, atol=1e-12)
        torch.testing.assert_close(w[:, side_a:].sum(1), -torch.ones(len(w), dtype=F64), rtol=0, atol=1e-12)
        gap = (w[:, :, None] * X).sum(1)  # c_A - c_B
        classify = point_triangle_type if eps is None else edge_edge_type
        (_, _, D), = [g for g in by_type(X, classify(X))]  # one type per group
        torch.testing.assert_close(gap.norm(dim=-1), D.sqrt(), rtol=1e-10, atol=0)
        torch.testing.assert_close(gap / gap.norm(dim=-1, keepdim=True), n, rtol=0, atol=1e-10)
        assert bool((lam > 0).all()) and bool((w[:, :side_a] >= -1e-12).all()) and bool((w[:, side_a:] <= 1e-12).all())
        checked += len(w)
    assert checked > 20


def displaced(x, seed: int, scale: float):
    return x + scale * torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


@pytest.mark.parametrize("scale", [2e-6, 3e-5])  # slip below and above eps = eps_v dt = 1e-5 m
def test_friction_gradient_and_hessian_match_autograd(scale):
    model, sc, x_prev, ctx = folded_sheet()
    assert sc.name in ctx.lagged and len(ctx.lagged[sc.name]["weight"]) > 20
    x = displaced(x_prev, 3, scale)
    lagged = ctx.lagged.pop(sc.name)
    plain = tb.StepContext(x_prev=ctx.x_prev, v_prev=ctx.v_prev, dt=ctx.dt, x_hat=ctx.x_hat)
    ctx.lagged[sc.name] = lagged
    with torch.enable_grad():  # the friction part alone: the energy with the lagged data minus the one without
        y = x.clone().requires_grad_(True)
        e = sc.energy(y, ctx) - sc.energy(y, plain)
        (g,) = torch.autograd.grad(e, y, create_graph=True)
        vs = torch.randn((4, *x.shape), generator=torch.Generator().manual_seed(7), dtype=F64)
        Hv = torch.stack([torch.autograd.grad(g, y, v, retain_graph=True)[0] for v in vs])  # autograd's HVPs
    g = g.detach()
    g_friction = sc.gradient(x, ctx) - sc.gradient(x, plain)
    torch.testing.assert_close(g_friction, g, rtol=1e-9, atol=1e-12 * float(g.abs().max()))
    Hf = (sc.hessian(x, ctx, Projection.NONE) - sc.hessian(x, plain, Projection.NONE)).to_dense()
    ours = vs.reshape(4, -1) @ Hf  # symmetric
    torch.testing.assert_close(ours, Hv.reshape(4, -1), rtol=1e-8, atol=1e-9 * float(Hv.abs().max()))
    torch.testing.assert_close(Hf, Hf.T, rtol=0, atol=1e-12 * float(Hf.abs().max()))
    assert float(torch.linalg.eigvalsh(Hf).min()) >= -1e-9 * float(Hf.abs().max())  # PSD
    # projections leave the friction blocks as they are; the HVP is the matrix's
    Hc = (sc.hessian(x, ctx, Projection.CLAMP) - sc.hessian(x, plain, Projection.CLAMP)).to_dense()
    torch.testing.assert_close(Hc, Hf, rtol=1e-10, atol=1e-12 * float(Hf.abs().max()))
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    hv = sc.hvp(x, v, ctx)
    torch.testing.assert_close(hv.reshape(-1), sc.hessian(x, ctx, Projection.NONE).to_dense() @ v.reshape(-1), rtol=1e-10,
                               atol=1e-12 * float(hv.abs().max()))


def test_friction_gradient_matches_central_differences_over_an_epsilon_sweep():
    _, sc, x_prev, ctx = folded_sheet(seed=2)
    x = displaced(x_prev, 4, 2e-5)
    d = torch.randn(x.shape, generator=torch.Generator().manual_seed(6), dtype=F64)
    slope = float((sc.gradient(x, ctx) * d).sum())
    errs = []
    for h in (1e-7, 1e-8, 1e-9):
        fd = (float(sc.energy(x + h * d, ctx)) - float(sc.energy(x - h * d, ctx))) / (2 * h)
        errs.append(abs(fd - slope))
    assert min(errs) <= 1e-6 * abs(slope), (errs, slope)


def test_no_friction_at_the_start_of_a_step_and_none_in_static_solves():
    model, sc, x_prev, ctx = folded_sheet()
    static = tb.StepContext()
    f = ctx.lagged[sc.name]  # zero slip: each pair's f0(0) = eps / 3
    torch.testing.assert_close(sc.energy(x_prev, ctx) - sc.energy(x_prev, static), f["weight"].sum() * f["eps"] / 3,
                               rtol=1e-10, atol=0)
    # zero slip: the friction force is zero
    torch.testing.assert_close(sc.gradient(x_prev, ctx), sc.gradient(x_prev, static), rtol=0, atol=1e-15)
    assert sc.name not in static.lagged
    off = tb.SelfContact(dhat=1e-3, stiffness=1e3)
    tb.ClothModel(model.topology.faces, x_prev, terms=[off])
    quiet = tb.StepContext.for_step([off], x_prev, torch.zeros_like(x_prev), 0.01)
    assert off.name not in quiet.lagged  # friction 0: nothing lagged


def incline(angle_deg: float, mu: float, body: str, steps: int = 40):
    """A 10 cm sheet on an inclined body: a two-triangle ``MeshCollider`` or a pinned lower cloth layer
    (``SelfContact``); the mean downhill velocity after each step."""
    a = math.radians(angle_deg)
    n = torch.tensor([math.sin(a), 0.0, math.cos(a)], dtype=F64)
    downhill = torch.tensor([math.cos(a), 0.0, -math.sin(a)], dtype=F64)
    across = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    flat, faces = tb.scenes.grid(5, 5, (0.1, 0.1), dtype=F64)
    sheet = flat[:, :1] * downhill + flat[:, 1:2] * across + 5e-4 * n
    pinned = None
    if body == "mesh":
        corners = torch.stack([-downhill - across, 2 * downhill - across, 2 * downhill + across, -downhill + across])
        terms = [tb.MeshCollider(corners, torch.tensor([[0, 1, 2], [0, 2, 3]]), dhat=1e-3, friction=mu, eps_v=1e-4)]
        rest = sheet
    else:  # a larger layer under it, every vertex pinned, one mesh of two components
        low, low_faces = tb.scenes.grid(4, 4, (0.6, 0.4), dtype=F64)
        low = (low[:, :1] - 0.25) * downhill + (low[:, 1:2] - 0.15) * across
        rest = torch.cat([sheet, low])
        faces = torch.cat([faces, low_faces + len(sheet)])
        pinned = torch.arange(len(sheet), len(rest))
        terms = [tb.SelfContact(dhat=1e-3, friction=mu, eps_v=1e-4)]
    model = tb.ClothModel(faces, rest, bending=tb.BendingEnergy(faces, rest, stiffness=1e-5),
                          membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                          terms=terms, density=0.2, pinned=pinned)
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    v = []
    for _ in range(steps):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, info.message
        assert 0 < info.min_distance < 1e-3  # on the body, never through it
        v.append(float((state.v[:25] @ downhill).mean()))
    return v


@pytest.mark.parametrize("body", ["mesh", "layer"])
def test_a_cloth_on_an_inclined_body_sticks_below_the_friction_angle(body):
    v = incline(20.0, 0.5, body, steps=25)  # tan 20 deg = 0.36 < mu
    assert max(abs(s) for s in v[10:]) < 1e-4  # at most eps_v: static friction's creep
    assert abs(v[-1] - v[15]) < 1e-5


@pytest.mark.parametrize("body", ["mesh", "layer"])
def test_a_cloth_on_an_inclined_body_slides_with_the_coulomb_acceleration(body):
    mu, angle = 0.5, math.radians(35.0)
    v = incline(35.0, mu, body, steps=22)
    expected = 9.81 * (math.sin(angle) - mu * math.cos(angle))
    measured = (v[-1] - v[9]) / (0.01 * (len(v) - 10))
    assert math.isclose(measured, expected, rel_tol=0.02), (measured, expected)
    frictionless = incline(35.0, 0.0, body, steps=10)
    measured = (frictionless[-1] - frictionless[4]) / (0.01 * (len(frictionless) - 5))
    assert math.isclose(measured, 9.81 * math.sin(angle), rel_tol=0.02), measured


def stacked_sheets(n: int = 9, twist: float = 0.0, layers: int = 4):
    """``layers`` n x n sheets (0.3 m) stacked 2 mm apart, vertex above vertex (or each turned ``twist`` degrees from
    the one below), the lowest 1.2 mm above a plane, falling at 3 m/s; friction 0.3 between the layers and on the
    floor.  Returns ``(model, state)``."""
    flat, f = tb.scenes.grid(n, n, (0.3, 0.3), dtype=F64)
    flat = flat - torch.tensor([0.15, 0.15, 0.0], dtype=F64)
    parts, faces = [], []
    for k in range(layers):
        a = math.radians(twist * k)
        turn = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                            dtype=F64)
        parts.append(flat @ turn.T + torch.tensor([0.0, 0.0, 1.2e-3 + 2e-3 * k], dtype=F64))
        faces.append(f + k * len(flat))
    x0, faces = torch.cat(parts), torch.cat(faces)
    model = tb.ClothModel(faces, x0, density=0.2, terms=[tb.SelfContact(dhat=1e-3, friction=0.3)],
                          colliders=[tb.Plane(friction=0.3)],
                          membrane=tb.MembraneEnergy(faces, x0, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(faces, x0, stiffness=1e-5))
    v = torch.zeros_like(x0)
    v[:, 2] = -3.0
    return model, tb.ClothState(x0, v)


def _steps_converge(model, state, steps: int):
    from tests.test_self_contact import intersects

    topo = model.topology
    for i in range(steps):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, (i, info.message)
        assert info.min_distance > 0 and not intersects(state.x, topo.faces, topo.edges), i
    assert float(state.x[:, 2].min()) > 0
    return info


@pytest.mark.parametrize("twist", [0.0, 45.0])
def test_stacked_sheets_hitting_a_floor_with_friction_converge_in_every_step(twist):
    """Four 9 x 9 sheets stacked vertex above vertex (or each turned 45 degrees) hit a floor at 3 m/s with friction
    0.3 (:func:`stacked_sheets`).  In the step after the impact the lagged friction pins every layer with its whole
    impact force; an upper sheet slides off its unstable place above the lower one's vertices, and along a sliding
    pair's direction the friction has no curvature: the Newton steps overshot by 16-64x and the step did not
    converge in 60 iterations, nor its halves.  Damping after poor steps (torchbend.sim.damping, in time steps too)
    brings it to convergence in at most 60 iterations.  Every state is free of intersections (exact test)."""
    _steps_converge(*stacked_sheets(9, twist), steps=3)


@pytest.mark.slow
def test_a_finer_stack_converges_with_the_clamped_retry():
    """Four 15 x 15 sheets stacked vertex above vertex hit a floor at 3 m/s: the impact step's exact-Hessian
    iterates wander near the saddle of the aligned layers (decrements ~1e-8 J, full steps) and the step did not
    converge within its 30 s time limit (162 iterations, halves included); the step solved again with the clamped
    projection converges (torchbend.sim.newton._euler_step)."""
    model, state = stacked_sheets(15, 0.0)
    state, info = tb.implicit_euler_step(model, state, 0.01)
    assert info.converged and info.phase == "clamped" and info.solves == 2, info.message
    _steps_converge(model, state, steps=2)


def test_a_failed_exact_step_is_solved_again_with_the_clamped_projection_before_its_halves(monkeypatch):
    """The retry's order: with 5 iterations a solve, the impact step of :func:`stacked_sheets` is solved with the
    exact Hessian, again whole with the clamped projection, then as halves with the exact Hessian; with
    ``max_substep_depth=0`` (one solve asked for) or a projected Hessian there is no retry."""
    from torchbend.sim import newton

    real, seen = newton._euler_solve, []

    def spy(model, state, dt, option, *args, **kw):
        seen.append((dt, option.value))
        return real(model, state, dt, option, *args, **kw)

    monkeypatch.setattr(newton, "_euler_solve", spy)
    model, state = stacked_sheets(9, 0.0)
    _, info = tb.implicit_euler_step(model, state, 0.01, max_iters=5, max_substep_depth=1)
    assert seen[:3] == [(0.01, "none"), (0.01, "clamp"), (0.005, "none")] and not info.converged
    assert info.solves == len(seen) and info.iterations == 5 * len(seen)
    seen.clear()
    _, info = tb.implicit_euler_step(model, state, 0.01, max_iters=5, max_substep_depth=0)
    assert seen == [(0.01, "none")] and info.solves == 1 and info.iterations == 5
    seen.clear()
    _, info = tb.implicit_euler_step(model, state, 0.01, projection="clamp", max_iters=5, max_substep_depth=1)
    assert [o for _, o in seen] == ["clamp"] * len(seen) and seen[1][0] == 0.005 and info.phase != "clamped"



def test_a_retry_goes_on_from_the_best_state_of_an_exact_solve_cut_off_while_converging(monkeypatch):
    """An exact-Hessian solve stopped by its iteration cap (or a failed line search) while its residual was still falling (the last ten
    iterates' best at most half the best before them) is continued from its best state with the clamped projection,
    not started over: the impact step of four 9x9 sheets turned 45 degrees with 15 iterations a solve converges in
    the continuation (23 iterations, one solve more, no halves), where a retry from the step's start and the halves
    did not (75 iterations, five solves, not converged)."""
    from tests.test_self_contact import intersects
    from torchbend.sim import newton

    real, seen = newton._euler_solve, []

    def spy(model, state, dt, option, *args, **kw):
        new, info = real(model, state, dt, option, *args, **kw)
        seen.append((dt, option.value, kw.get("start"), new.x, info))
        return new, info

    monkeypatch.setattr(newton, "_euler_solve", spy)
    model, state = stacked_sheets(9, 45.0)
    new, info = tb.implicit_euler_step(model, state, 0.01, max_iters=15)
    assert [(dt, o) for dt, o, *_ in seen] == [(0.01, "none"), (0.01, "clamp")]
    exact, retry = seen[0][4], seen[1][4]
    assert not exact.converged and newton._still_converging(exact)
    start = seen[1][2]
    assert start is not None and torch.equal(start[0], seen[0][3])  # the exact solve's best state
    assert info.converged and info.phase == "clamped" and info.substeps == 1 and info.solves == 2
    assert info.iterations == exact.iterations + retry.iterations < 30
    assert info.min_distance > 0 and not intersects(new.x, model.topology.faces, model.topology.edges)
    seen.clear()  # a solve that was not converging any more starts over
    monkeypatch.setattr(newton, "_still_converging", lambda info: False)
    _, info = tb.implicit_euler_step(model, state, 0.01, max_iters=15)
    assert seen[1][2] is None and not info.converged and len(seen) > 2


def test_the_clamped_retry_is_begun_whatever_time_the_exact_solve_took(monkeypatch):
    """The retry does not depend on how long the exact solve took (a busy machine's slower solve once left the retry
    out where an idle machine ran it, and the same step gave another answer): an exact solve that took more than half
    of the step's time limit (here by a pause after it) is still followed by the clamped retry."""
    import time

    from torchbend.sim import newton

    real, seen = newton._euler_solve, []

    def spy(model, state, dt, option, *args, **kw):
        seen.append((dt, option.value))
        t0 = time.perf_counter()
        out = real(model, state, dt, option, *args, **kw)
        if len(seen) == 1:  # the exact solve: made to take 60% of the limit
            time.sleep(max(0.0, 0.6 * limit - (time.perf_counter() - t0)))
        return out

    monkeypatch.setattr(newton, "_euler_solve", spy)
    model, state = stacked_sheets(9, 0.0)
    limit = 4.0
    _, info = tb.implicit_euler_step(model, state, 0.01, max_iters=5, max_substep_depth=1, time_limit=limit)
    assert seen[:2] == [(0.01, "none"), (0.01, "clamp")], seen


def test_still_converging_compares_the_last_iterates_with_those_before():
    from torchbend.sim import newton

    def info(history):
        return newton.SolveInfo(residual_history=list(history))

    assert newton._still_converging(info([1.0] * 5 + [0.5 ** k for k in range(1, 11)]))
    assert not newton._still_converging(info([1.0, 0.1] + [0.08] * 10))  # flat over the last ten
    assert not newton._still_converging(info([1.0, 0.1, 0.01]))  # too short to say
    assert not newton._still_converging(info([1.0] * 11 + [0.6] * 10))  # the last ten: only 0.6 of the best before

def test_every_solve_of_a_retried_step_starts_from_the_step_s_contact_stiffness(monkeypatch):
    """An adaptive ``kappa`` (``stiffness=None``) is part of a term's pose: the clamped retry and the halves of a
    step start from the ``kappa`` of the step's start (before, each solve of the same start doubled it once more:
    1.26e6, 2.5e6, 5e6, 1e7 over a step, a retry and a half, and the next steps kept it); ``info.seconds`` counts
    the whole step."""
    import time

    from torchbend.sim import newton

    real, kappas = newton._euler_solve, []

    def spy(model, state, dt, option, *args, **kw):
        kappas.append(sc.stiffness)
        return real(model, state, dt, option, *args, **kw)

    monkeypatch.setattr(newton, "_euler_solve", spy)
    flat, f = tb.scenes.grid(6, 6, (0.1, 0.1), dtype=F64)
    x0 = torch.cat([flat + torch.tensor([0.0, 0.0, 1e-3], dtype=F64),
                    flat + torch.tensor([0.003, 0.002, 1e-3 + 5e-5], dtype=F64)])  # 5e-5 m < dhat / 10
    faces = torch.cat([f, f + len(flat)])
    sc = tb.SelfContact(dhat=1e-3, friction=0.3)
    model = tb.ClothModel(faces, x0, density=0.2, terms=[sc], colliders=[tb.Plane(friction=0.3)])
    k0 = sc.stiffness
    assert k0 is not None
    t0 = time.perf_counter()
    _, info = tb.implicit_euler_step(model, tb.ClothState(x0, torch.zeros_like(x0)), 0.01, max_iters=1,
                                     max_substep_depth=1)
    wall = time.perf_counter() - t0
    assert len(kappas) == 3 and kappas == [k0] * 3 and not info.converged, (kappas, k0)
    assert sc.stiffness == 2 * k0  # the returned solve's: the start's doubling, once
    assert info.seconds >= 0.9 * wall


@pytest.mark.parametrize("kept", ["retry", "exact"])
def test_a_callback_that_stops_the_clamped_retry_ends_the_step(monkeypatch, kept):
    """A callback's stop in the retry ends the step (no halves start), whichever of the two solves is returned
    (``kept="exact"``: the retry's residual is made the worse, so the exact solve's state, its bodies' poses and
    ``kappa`` are kept); ``info.seconds`` covers the whole step."""
    import time

    from torchbend.sim import newton

    real, seen = newton._euler_solve, []

    def spy(model, state, dt, option, *args, **kw):
        seen.append((dt, option.value))
        new, info = real(model, state, dt, option, *args, **kw)
        if kept == "exact" and option.value == "clamp":
            info.residual = math.inf
        return new, info

    monkeypatch.setattr(newton, "_euler_solve", spy)
    model, state = stacked_sheets(9, 0.0)
    sc = next(t for t in model.terms if isinstance(t, tb.SelfContact))
    starts, kappa = [0], []

    def callback(it, x, info):  # stop as soon as the second solve (the retry) iterates
        starts[0] += it == 1
        if it == 1:
            kappa.append(sc.stiffness)
        if starts[0] == 2:
            sc.stiffness = 3.0 * kappa[0]  # the retry's kappa, distinguishable from the exact solve's
        return starts[0] >= 2

    t0 = time.perf_counter()
    _, info = tb.implicit_euler_step(model, state, 0.01, max_iters=5, max_substep_depth=1, callback=callback)
    wall = time.perf_counter() - t0
    assert seen == [(0.01, "none"), (0.01, "clamp")] and info.stop_reason == "callback" and not info.converged
    assert info.phase == ("clamped" if kept == "retry" else "newton") and info.seconds >= 0.9 * wall
    assert sc.stiffness == (3.0 * kappa[0] if kept == "retry" else kappa[0])  # the returned solve's kappa


@pytest.mark.parametrize("slip", [0.5, 1.0])
def test_friction_blocks_keep_a_share_of_the_slip_curvature(slip):
    """``friction_blocks(..., slip=s)`` adds ``s`` times the curvature the exact Hessian removes along the slip,
    ``mu lam (a - f1') u_hat u_hat^T`` (``a - f1' = 1 / y`` sliding, ``y / eps^2`` below ``eps``): positive
    semi-definite, continuous at ``|u| = eps``, the exact blocks at ``s = 0``; ``s = 1``: ``mu lam a P``."""
    from torchbend.energies.friction import _parts, friction_blocks

    eps = 1e-5
    gen = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=F64), dim=-1)
    u = torch.randn(64, 3, generator=gen, dtype=F64)
    u = u - (u * n).sum(-1, keepdim=True) * n
    y = torch.logspace(-8, -3, 64, dtype=F64)
    u = u / u.norm(dim=-1, keepdim=True) * y[:, None]
    w = torch.rand(64, generator=gen, dtype=F64) + 0.1
    zero = torch.zeros_like(u)
    exact, kept = friction_blocks(u, zero, n, w, eps), friction_blocks(u, zero, n, w, eps, slip)
    _, _, _, _, a = _parts(u, zero, n, eps)
    removed = torch.where(y < eps, y / eps ** 2, 1 / y)  # a - f1'(y): the exact Hessian's -b
    uh = u / y[:, None]
    expected = exact + (slip * w * removed)[:, None, None] * uh[:, :, None] * uh[:, None, :]
    torch.testing.assert_close(kept, expected, rtol=1e-12, atol=0)
    assert float(torch.linalg.eigvalsh(kept).min()) >= -1e-12 * float(kept.abs().max())
    if slip == 1.0:
        P = torch.eye(3, dtype=F64) - n[:, :, None] * n[:, None, :]
        torch.testing.assert_close(kept, (w * a)[:, None, None] * P, rtol=1e-12, atol=1e-12 * float(kept.abs().max()))
    at = torch.tensor([[eps * (1 - 1e-12), 0.0, 0.0], [eps * (1 + 1e-12), 0.0, 0.0]], dtype=F64)
    side = friction_blocks(at, torch.zeros_like(at), torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=F64),
                           torch.ones(2, dtype=F64), eps, slip)
    torch.testing.assert_close(side[0], side[1], rtol=1e-9, atol=0)


@pytest.mark.slow
def test_stacks_hitting_a_mesh_floor_with_friction_one_converge_with_the_retry():
    """Three 13 x 13 sheets, each turned 30 degrees, hitting a MeshCollider floor at 4 m/s with friction 1: the step
    after the impact failed in all five solves (exact, clamped retry, halves) with the exact friction Hessian; the
    retry keeps half the slip curvature (newton.RETRY_FRICTION_SLIP) and converges."""
    from tests.test_self_contact import intersects

    flat, f = tb.scenes.grid(13, 13, (0.3, 0.3), dtype=F64)
    flat = flat - torch.tensor([0.15, 0.15, 0.0], dtype=F64)
    parts = []
    for k in range(3):
        a = math.radians(30.0 * k)
        turn = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                            dtype=F64)
        parts.append(flat @ turn.T + torch.tensor([0.0, 0.0, 1.2e-3 + 2e-3 * k], dtype=F64))
    x0, faces = torch.cat(parts), torch.cat([f + k * len(flat) for k in range(3)])
    floor = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]], dtype=F64)
    body = tb.MeshCollider(floor, torch.tensor([[0, 1, 2], [0, 2, 3]]), dhat=1e-3, friction=1.0)
    model = tb.ClothModel(faces, x0, density=0.2, terms=[tb.SelfContact(dhat=1e-3, friction=1.0), body],
                          membrane=tb.MembraneEnergy(faces, x0, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(faces, x0, stiffness=1e-5))
    v = torch.zeros_like(x0)
    v[:, 2] = -4.0
    state = tb.ClothState(x0, v)
    for i in range(3):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, (i, info.message)
        assert info.min_distance > 0 and not intersects(state.x, model.topology.faces, model.topology.edges), i
