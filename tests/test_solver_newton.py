"""Newton loop of the cloth solvers: round-off-aware stopping, best-iterate returns, negative-curvature
escape, progress reporting, argument checks, and the adjoint's refusal of unconverged solves."""
import logging
import math
import os

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

import torchbend as tb
from torchbend import ClothModel, ClothState, implicit_euler_step, solve_static, solve_static_adjoint
from torchbend.options import Projection
from torchbend.scenes.config import build_scene, load_config
from torchbend.sim import newton
from torchbend.sim.curvature import count_below, curvature_tolerance, smallest_eigenpair
from torchbend.testing import plain_bending_energy

from .helpers import CONFIGS, cantilever, tip

F64 = torch.float64


# -------------------------------------------------------------------- independent reference
def plain_potential(model: ClothModel, rest: torch.Tensor):
    """The static potential written with plain autograd ops (StVK membrane on the flat rest triangles in
    their ``z = 0`` plane, hinge bending from :func:`torchbend.testing.plain_bending_energy`, gravity)."""
    faces = model.topology.faces
    mem, bend = model.membrane, model.bending
    assert mem is not None and bend is not None and float(rest[:, 2].abs().max()) == 0.0
    X = rest[faces]
    Dm = torch.stack((X[:, 1, :2] - X[:, 0, :2], X[:, 2, :2] - X[:, 0, :2]), -1)  # (T, 2, 2)
    W, area = torch.linalg.inv(Dm), 0.5 * torch.linalg.det(Dm).abs()
    young, nu = mem.young, mem.poisson
    mu, lam = young / (2 * (1 + nu)), young * nu / (1 - nu**2)  # plane stress
    force = model.external_force(F64)

    def energy(x):
        P = x[faces]
        F = torch.stack((P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), -1) @ W  # (T, 3, 2)
        G = 0.5 * (F.transpose(-1, -2) @ F - torch.eye(2, dtype=F64))
        tr = G.diagonal(dim1=-2, dim2=-1).sum(-1)
        psi = mu * (G * G).sum((-1, -2)) + 0.5 * lam * tr * tr
        e_mem = (area * mem.thickness * psi).sum()
        e_bend = plain_bending_energy(x, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, bend.model)
        return e_mem + e_bend - (force * x).sum()

    return energy


def dense_newton_reference(model, rest, x, iters=4):
    """Newton on :func:`plain_potential` from ``x`` (pinned DOFs fixed) with its dense autograd Hessian at
    ``x`` (a chord iteration: ``x`` is close to the equilibrium).  Returns ``(x_ref, H_ff at x)``."""
    energy = plain_potential(model, rest)
    assert abs(float(energy(x)) - model.potential(x)) <= 1e-10 * max(abs(model.potential(x)), 1e-30)
    free = (~model.pinned).repeat_interleave(3)
    n = x.numel()
    H = torch.autograd.functional.hessian(energy, x)
    assert isinstance(H, torch.Tensor)
    H = H.reshape(n, n)[free][:, free]
    y = x.clone()
    for _ in range(iters):
        yg = y.clone().requires_grad_()
        (g,) = torch.autograd.grad(energy(yg), yg)
        p = torch.linalg.solve(H, -g.reshape(-1)[free])
        step = torch.zeros(n, dtype=F64)
        step[free] = p
        y = y + step.reshape(-1, 3)
    return y, H


# -------------------------------------------------------------------- stopping rule
# (Y t [N/m], t [m]) across soft to stiff, thin to thick; the stiff thin strip of issue 16 is (1e6, 1e-3)
STRIPS = [(1e2, 1e-3), (1e2, 1e-2), (1e4, 1e-2), (1e5, 1e-2), (1e6, 1e-3), (1e7, 1e-4), (1e7, 1e-3), (1e7, 1e-2)]
SOFT_LARGE_ROTATION = [(1e2, 1e-4), (1e4, 1e-4), (1e4, 1e-3), (1e5, 1e-4), (1e5, 1e-3)]


def _check_strip(nx, ny, Yt, t, **kw):
    model, rest, _ = cantilever(nx, ny, young=Yt / t, t=t)
    x0 = rest.clone()
    x, info = solve_static(model, x0, **kw)  # default tol
    assert info.converged and info.stop_reason in ("residual", "round-off floor"), info.message
    assert info.message.startswith(f"converged ({info.stop_reason})")
    assert torch.equal(x0, rest) and tip(x, rest) > 0
    assert info.minimum is True and info.min_eigenvalue > 0
    free = ~model.pinned
    assert info.residual == pytest.approx(float(model.gradient(x)[free].norm()), rel=1e-12)
    assert info.energy == model.potential(x)
    if info.stop_reason == "residual":
        assert info.residual <= info.tolerance == pytest.approx(1e-9 * info.force_scale, rel=1e-12)
    x_ref, H = dense_newton_reference(model, rest, x)
    err = float((x_ref - x).norm() / (x - rest).norm())
    assert err <= 1e-6, err
    assert float(torch.linalg.eigvalsh(H)[0]) > 0  # a minimum of the independent potential
    return info, err


@pytest.mark.parametrize("nx, ny, Yt, t", [(11, 3, *c) for c in STRIPS] + [
    pytest.param(20, 4, *c, marks=() if c in ((1e2, 1e-2), (1e7, 1e-3)) else pytest.mark.slow) for c in STRIPS])
def test_cantilever_strips_converge_with_the_default_tolerance(nx, ny, Yt, t):
    info, err = _check_strip(nx, ny, Yt, t)
    print(f"{nx}x{ny} Yt={Yt:.0e} t={t:.0e}: {info.message}, {info.iterations} iterations, "
          f"residual {info.residual:.2e} N, scale {info.force_scale:.2e} N, reference error {err:.1e}")


@pytest.mark.slow
@pytest.mark.parametrize("nx, ny", [(11, 3), (20, 4)])
@pytest.mark.parametrize("Yt, t", SOFT_LARGE_ROTATION)
def test_soft_strips_with_large_rotations_converge(nx, ny, Yt, t):
    """Large rotations need more Newton iterations than the default budget (a globalisation matter, not
    the stopping rule): the tolerance stays the default."""
    _check_strip(nx, ny, Yt, t, max_iters=300)


@pytest.mark.parametrize("young, t", [(1e9, 1e-3), (1e10, 1e-3)])
def test_stiff_thin_strips_stop_at_their_round_off_floor(young, t):
    """Y = 1e9 Pa, t = 1 mm, 20x4 (issue 16) and ten times stiffer: the residual cannot fall below the
    round-off of forces of size Y t h, far above 1e-9 times the weight; the solver converges (by the
    residual test, whose force scale includes the internal forces, or at the round-off floor) instead
    of returning x0."""
    model, rest, kirchhoff = cantilever(20, 4, young=young, t=t)
    x, info = solve_static(model, rest)
    assert info.converged and info.iterations <= 20, info.message
    assert 0.4 < tip(x, rest) / kirchhoff < 1.0  # deflected (discrete and linear theory agree)
    # the residual is at its floor: the gradient of the same state rounded differently varies as much
    free = ~model.pinned
    gen = torch.Generator().manual_seed(0)
    spread = max(float((model.gradient(x * (1 + 2e-16 * torch.randn(x.shape, generator=gen, dtype=F64)))
                        - model.gradient(x))[free].norm()) for _ in range(5))
    assert info.residual <= 10 * spread
    weight = float(model.external_force().sum(0).norm())
    assert spread > 1e-9 * weight  # ... which the old rule (1e-9 times the weight) could never meet
    x_ref, _ = dense_newton_reference(model, rest, x)
    assert float((x_ref - x).norm() / (x - rest).norm()) <= 1e-6
    if young == 1e10:  # here the floor lies above tol times the force scale: the floor test fires
        assert info.stop_reason == "round-off floor" and info.residual > info.tolerance
        assert info.message.startswith("converged (round-off floor)")


def test_dynamic_force_scale_includes_the_inertial_force():
    model, rest, _ = cantilever(11, 3)
    v = torch.zeros_like(rest)
    v[:, 2] = 2.0
    v[model.pinned] = 0
    dt = 0.01
    _, info = implicit_euler_step(model, ClothState(rest, v), dt)
    assert info.converged, info.message
    inertial = float((model.mass[:, None] * v / dt).norm())  # |M v_n| / dt, zero at x = x_hat
    assert info.force_scale >= inertial
    assert info.residual <= info.tolerance


# -------------------------------------------------------------------- best iterate on failure
def test_failed_static_solve_returns_the_best_iterate_and_describes_it():
    model, rest, _ = cantilever(20, 4, young=1e6, t=1e-4)  # large rotations: many iterations
    x0 = rest.clone()
    e0 = model.potential(rest)
    for k in (1, 3):
        x, info = solve_static(model, x0, max_iters=k, continuation=False)
        assert not info.converged and info.stop_reason == "max_iters" and f"in {k} Newton" in info.message
        assert torch.equal(x0, rest)
        assert info.energy == model.potential(x) == min(info.energy_history) < e0
        assert info.residual == pytest.approx(float(model.gradient(x)[~model.pinned].norm()), rel=1e-12)
        assert info.residual == info.residual_history[info.best_iteration]
    # max_iters=0 evaluates x0 only
    x, info = solve_static(model, x0, max_iters=0)
    assert not info.converged and torch.equal(x, rest) and info.iterations == 0 and info.energy == e0


def test_continuation_failure_aggregates_and_keeps_the_best():
    model, rest, _ = cantilever(11, 3, young=1e6, t=1e-4)
    x1, first = solve_static(model, rest, max_iters=2, continuation=False)
    x, info = solve_static(model, rest, max_iters=2, continuation=True, max_relax_steps=5)
    assert not info.converged
    assert info.message.startswith("no convergence: ") and "solves (continuation)" in info.message
    assert info.solves >= 3 and info.iterations > first.iterations
    assert f"{info.iterations} Newton iterations in {info.solves} solves" in info.message
    assert model.potential(x) == info.energy <= first.energy == model.potential(x1)


def test_failed_dynamic_step_returns_the_best_state_with_consistent_velocity():
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    model, x0, _ = build_scene(cfg, resolution=(7, 7))
    state = ClothState(x0.clone(), torch.zeros_like(x0))
    dt = 0.05
    new, info = implicit_euler_step(model, state, dt, max_iters=1, max_substep_depth=0)
    assert not info.converged and info.stop_reason == "max_iters"
    assert torch.equal(state.x, x0) and bool(state.v.eq(0).all())  # input untouched
    assert not torch.equal(new.x, x0)  # the cloth moved: a loop ignoring `converged` does not freeze
    assert torch.allclose(new.v, (new.x - x0) / dt, rtol=0, atol=1e-15)
    # substeps: counts of every solve in the message
    new, info = implicit_euler_step(model, state, 0.2, max_iters=1, max_substep_depth=2)
    assert not info.converged and "solves (substeps)" in info.message and info.solves >= 2
    assert f"{info.iterations} Newton iterations in {info.solves} solves" in info.message
    assert bool(torch.isfinite(new.x).all()) and not torch.equal(new.x, x0)


def test_line_search_and_evaluation_failures_return_the_best_iterate(monkeypatch):
    model, rest, _ = cantilever(11, 3)
    real = newton._Potential.gradient
    calls = {"n": 0}

    def flaky(self, y):
        calls["n"] += 1
        if calls["n"] == 3:
            raise ValueError("hinge 4 has folded through (tan model)")
        return real(self, y)

    monkeypatch.setattr(newton._Potential, "gradient", flaky)
    x, info = solve_static(model, rest, continuation=False)
    assert not info.converged and info.stop_reason == "evaluation_error" and "folded through" in info.message
    assert info.energy == model.potential(x) < model.potential(rest)
    monkeypatch.setattr(newton._Potential, "gradient", real)
    # a line search that finds no decrease: the message names the direction
    monkeypatch.setattr(newton, "armijo_backtracking", lambda *a, **k: None)
    x, info = solve_static(model, rest, continuation=False, damping=False)
    assert not info.converged and info.stop_reason == "line_search" and info.line_search_failures == 1
    assert "line search exhausted" in info.message and "the Newton direction" in info.message
    assert torch.equal(x, rest)
    # damped: each failure raises the damping and retries (an iteration each) until the damping is at its bound
    x, info = solve_static(model, rest, continuation=False)  # damped (the default)
    assert not info.converged and info.stop_reason == "line_search" and info.line_search_failures > 1
    assert info.iterations == info.line_search_failures - 1 and torch.equal(x, rest)


def test_unpinned_cloth_without_colliders_is_diagnosed_before_iterating():
    rest, faces = tb.scenes.grid(9, 9, (1.0, 1.0), dtype=F64)
    model = ClothModel(faces, rest, density=0.2,
                       membrane=tb.MembraneEnergy(faces, rest, young=1e4, poisson=0.3, thickness=1e-3),
                       bending=tb.BendingEnergy(faces, rest, stiffness=1e-4))
    for linear in ("direct", "cg"):
        x, info = solve_static(model, rest, linear_solver=linear)
        assert not info.converged and info.stop_reason == "rigid_body_modes" and info.iterations == 0
        assert "rigid-body modes" in info.message and "pin vertices or add a collider" in info.message
        assert torch.equal(x, rest)
    # a collider bounds it below: no diagnosis
    model = ClothModel(faces, rest, density=0.2, colliders=[tb.Plane((0, 0, -0.1), (0, 0, 1))],
                       membrane=tb.MembraneEnergy(faces, rest, young=1e4, poisson=0.3, thickness=1e-3))
    _, info = solve_static(model, rest, max_iters=2, continuation=False)
    assert info.stop_reason != "rigid_body_modes"


# -------------------------------------------------------------------- minima
def upright_strip(nx, ny, *, L, W=0.02, young=1e6, t=1e-3, nu=0.3, rho=1000.0):
    """A strip standing upright (length along +z, width along x), clamped at its two bottom rows, under
    gravity -z.  Returns ``(model, rest, critical length [m], free length [m])`` with the critical
    length of the heavy column clamped at its foot, ``l_c = 1.986 (D / q)^(1/3)`` (``D`` the plate
    bending stiffness times the width, ``q`` the weight per length)."""
    flat, faces = tb.scenes.grid(nx, ny, (L, W), dtype=F64)
    rest = torch.stack((flat[:, 1], torch.zeros_like(flat[:, 0]), flat[:, 0]), -1)
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=tb.stiffness_from_material(young, t, nu))
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=young, poisson=nu, thickness=t)
    rows = flat[:, 0].unique()
    model = ClothModel(faces, rest, bending=bend, membrane=mem, density=rho * t, gravity=(0, 0, -9.81),
                       pinned=flat[:, 0] <= rows[1] + 1e-12)
    D = young * t**3 / (12 * (1 - nu**2)) * W
    q = rho * t * W * 9.81
    return model, rest, 1.986 * (D / q) ** (1 / 3), L - float(rows[1])


def test_upright_strip_beyond_its_buckling_length_buckles():
    model, rest, l_c, length = upright_strip(18, 3, L=0.085)
    assert length > 1.9 * l_c  # well beyond the critical length (no imperfection given)
    free = (~model.pinned).repeat_interleave(3)
    # without the check, Newton stops at the straight, unstable state: a saddle
    x_s, info_s = solve_static(model, rest, check_minimum=False)
    assert info_s.converged and info_s.minimum is None and float(x_s[:, 1].abs().max()) == 0.0
    H_s = torch.from_numpy(model.hessian(x_s, Projection.NONE).toarray())[free][:, free]
    assert float(torch.linalg.eigvalsh(H_s)[0]) < 0
    # evaluated only (max_iters=0): the saddle is reported, not left
    x_e, info_e = solve_static(model, x_s, max_iters=0)
    assert info_e.converged and info_e.minimum is False and torch.equal(x_e, x_s)
    assert "not a verified minimum" in info_e.message and info_e.min_eigenvalue < 0
    # with it (the default), the solver steps off the saddle; default options (the large rotations that
    # follow are globalised by the membrane homotopy)
    x, info = solve_static(model, rest)
    assert info.converged and info.minimum is True and info.negative_curvature_steps >= 1, info.message
    H = torch.from_numpy(model.hessian(x, Projection.NONE).toarray())[free][:, free]
    lam = torch.linalg.eigvalsh(H)
    assert float(lam[0]) >= -1e-9 * float(lam.abs().max())  # PSD on the free DOFs
    assert info.min_eigenvalue == pytest.approx(float(lam[0]), rel=1e-6)
    assert float(x[:, 1].abs().max()) > 0.1 * length  # buckled out of its plane
    assert info.energy < info_s.energy


def test_projected_hessians_do_not_claim_minima():
    model, rest, _ = cantilever(11, 3)
    for hessian in ("clamp", "gauss_newton"):
        _, info = solve_static(model, rest, projection=hessian)
        assert info.converged and info.minimum is None and math.isnan(info.min_eigenvalue)


@pytest.mark.parametrize("shift", [-3.0, -0.5, -0.01, 0.0, 0.5])
def test_smallest_eigenpair_matches_a_dense_solver(shift):
    rng = np.random.default_rng(int(10 * abs(shift)) + 3)
    for n in (40, 150, 300):  # dense and sparse paths
        A = sp.random(n, n, density=6 / n, rng=rng)
        A = sp.csr_matrix((A + A.T) * 0.5 + sp.diags(rng.uniform(0, 3, size=n)) + shift * sp.identity(n))
        w = np.linalg.eigvalsh(A.toarray())
        found = smallest_eigenpair(A)
        assert found is not None
        lam, v = found
        assert abs(lam - w[0]) <= 1e-10 * max(1.0, abs(w).max())
        assert np.linalg.norm(A @ v - lam * v) <= 1e-8 and abs(np.linalg.norm(v) - 1) <= 1e-12
        for sigma in (-0.3, 0.0, 0.7):
            assert count_below(A, sigma) == int((w < sigma).sum())
        assert 0 < curvature_tolerance(A) < 1e-10


def test_smallest_eigenpair_beyond_a_cluster_near_zero():
    """A negative eigenvalue far below many small positive ones (a soft strip's near-null modes): Lanczos
    about the shift finds only the cluster, the inertia count says an eigenvalue lies below it, and the
    bracketing must reach it (it once returned the cluster's smallest, and a saddle was called a minimum)."""
    rng = np.random.default_rng(11)
    n = 300
    w = np.concatenate([[-21.9], rng.uniform(1e-4, 1e-2, size=40), rng.uniform(1e2, 1e4, size=n - 41)])
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = sp.csr_matrix((Q * w) @ Q.T)
    found = smallest_eigenpair(A)
    assert found is not None
    lam, v = found
    assert abs(lam - (-21.9)) <= 1e-10 * 1e4
    assert np.linalg.norm(A @ v - lam * v) <= 1e-8 * 1e4


def test_smallest_eigenpair_does_not_depend_on_earlier_calls():
    """The eigenvector (the direction of a negative-curvature step) is the same whatever ran before it in the
    process: the Lanczos start vector is fixed (ARPACK's default comes from a generator whose state persists)."""
    rng = np.random.default_rng(5)
    n = 200
    A = sp.random(n, n, density=6 / n, rng=rng)
    A = sp.csr_matrix((A + A.T) * 0.5 + sp.diags(rng.uniform(0, 3, size=n)) - 0.7 * sp.identity(n))
    first = smallest_eigenpair(A)
    for _ in range(3):  # other Lanczos runs in between
        spla.eigsh(sp.csc_matrix(A), k=4, sigma=0.5, which="LM")
    again = smallest_eigenpair(A)
    assert first is not None and again is not None
    assert first[0] == again[0] and np.array_equal(first[1], again[1])


# -------------------------------------------------------------------- progress and controls
def test_callback_logging_time_limit_and_max_cg_iters(caplog, monkeypatch):
    model, rest, _ = cantilever(11, 3, young=1e6, t=1e-4)
    seen = []
    x, info = solve_static(model, rest, callback=lambda it, x, info: seen.append((it, info.residual)) or it == 2)
    assert not info.converged and info.stop_reason == "callback" and "callback" in info.message
    assert [s[0] for s in seen] == [1, 2] and info.iterations == 2
    with caplog.at_level(logging.DEBUG, logger="torchbend.sim"):
        solve_static(model, rest, max_iters=3, continuation=False)
    lines = [r.getMessage() for r in caplog.records if r.name == "torchbend.sim"]
    assert sum(m.startswith("newton it ") for m in lines) == 4 and "residual" in lines[0] and "potential" in lines[0]
    assert any("no convergence in 3 Newton iterations" in m for m in lines)
    x, info = solve_static(model, rest, time_limit=1e-9, continuation=True)
    assert not info.converged and info.stop_reason == "time_limit" and "time limit" in info.message
    assert torch.equal(x, rest) and info.solves == 1
    seen_bounds = []
    real = newton._Potential.cg_direction

    def spy(self, *args, **kw):
        seen_bounds.append(self.max_cg_iters)
        return real(self, *args, **kw)

    monkeypatch.setattr(newton._Potential, "cg_direction", spy)
    solve_static(model, rest, linear_solver="cg", max_cg_iters=7, max_iters=1, continuation=False, damping=False)
    implicit_euler_step(model, ClothState(rest, torch.zeros_like(rest)), 0.01, linear_solver="cg", max_cg_iters=5,
                        max_iters=1, max_substep_depth=0)
    assert seen_bounds == [7, 5]


@pytest.mark.parametrize("kw, match", [
    ({"max_iters": -1}, "max_iters must be an int >= 0"),
    ({"max_iters": 2.5}, "max_iters must be an int >= 0"),
    ({"max_iters": True}, "max_iters must be an int >= 0"),
    ({"tol": -1.0}, "tol must be positive"),
    ({"tol": 0.0}, "tol must be positive"),
    ({"tol": math.nan}, "tol must be positive"),
    ({"tol": None}, "tol must be positive"),
    ({"time_limit": 0.0}, "time_limit must be positive"),
    ({"time_limit": -3}, "time_limit must be positive"),
    ({"max_cg_iters": 0}, "max_cg_iters must be an int >= 1"),
    ({"callback": 3}, "callback must be callable"),
])
def test_bad_controls_are_value_errors_naming_them(kw, match):
    model, rest, _ = cantilever(5, 3)
    with pytest.raises(ValueError, match=match):
        solve_static(model, rest, **kw)
    with pytest.raises(ValueError, match=match):
        implicit_euler_step(model, ClothState(rest, torch.zeros_like(rest)), 0.01, **kw)


# -------------------------------------------------------------------- adjoint
def test_adjoint_refuses_an_unconverged_solve_unless_asked():
    base, rest, _ = cantilever(11, 3)
    faces = base.topology.faces
    k = torch.nn.Parameter(torch.tensor(tb.stiffness_from_material(5e7, 1e-2, 0.3), dtype=F64))
    model = ClothModel(faces, rest, bending=tb.BendingEnergy(faces, rest, model="quadratic", stiffness=k),
                       membrane=base.membrane, density=base.density, pinned=base.pinned)
    x, info = solve_static_adjoint(model, rest, [k], max_iters=1, continuation=False)
    assert not info.converged
    with pytest.raises(RuntimeError, match="did not converge .*no convergence in 1 Newton iterations"):
        x[:, 2].sum().backward()
    x, info = solve_static_adjoint(model, rest, [k], max_iters=1, allow_unconverged=True)
    (g,) = torch.autograd.grad(x[:, 2].sum(), k)
    assert bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0
    x, info = solve_static_adjoint(model, rest, [k])
    assert info.converged
    (g,) = torch.autograd.grad(x[:, 2].sum(), k)
    assert float(g.sum()) > 0  # stiffer: the tip sags less (z grows)
