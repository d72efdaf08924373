"""The solver's default time budget, its progress lines and phase, and the opt-in Levenberg-Marquardt damping."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

import torchbend as tb
from torchbend.scenes.schema import SolverSection
from torchbend.sim import newton
from torchbend.sim import options as sim_options
from torchbend.sim.damping import Damping
from torchbend.sim.linear import FreeHessian

from .helpers import DIRECT_METHOD, cantilever


def test_time_limit_auto_is_the_per_solver_default_and_none_lifts_it():
    for kind, where in (("static", "solve_static"), ("step", "implicit_euler_step")):
        opts, ctl = sim_options.resolve_options(None, where, kind)
        assert opts.time_limit == "auto" and ctl.time_limit == sim_options.DEFAULT_TIME_LIMITS[kind]
        assert ctl.deadline is not None and ctl.deadline > ctl.started
        _, ctl = sim_options.resolve_options(None, where, kind, time_limit=None)
        assert ctl.time_limit is None and ctl.deadline is None
        _, ctl = sim_options.resolve_options(tb.NewtonOptions(time_limit=3.0), where, kind)
        assert ctl.time_limit == 3.0
    assert SolverSection().newton_options().time_limit == "auto"
    assert SolverSection(time_limit=None).newton_options().time_limit is None
    with pytest.raises(ValueError, match="time_limit"):
        tb.NewtonOptions(time_limit="soon")
    with pytest.raises(ValueError, match="damping"):
        tb.NewtonOptions(damping="yes")  # type: ignore[arg-type]


def test_the_default_budget_returns_the_best_state_with_the_reason(monkeypatch):
    model, rest, _ = cantilever(11, 3)
    monkeypatch.setitem(sim_options.DEFAULT_TIME_LIMITS, "static", 1e-9)
    monkeypatch.setitem(sim_options.DEFAULT_TIME_LIMITS, "step", 1e-9)
    x, info = tb.solve_static(model, rest)
    assert not info.converged and info.stop_reason == "time_limit" and "time limit" in info.message
    assert info.phase == "newton" and torch.equal(x, rest)  # nothing was accepted before the budget ran out
    state, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
    assert not info.converged and info.stop_reason == "time_limit" and bool(torch.isfinite(state.x).all())
    x, info = tb.solve_static(model, rest, time_limit=None)  # lifted: converges
    assert info.converged and info.phase == "newton"


def test_progress_goes_to_stderr_after_five_seconds_when_logging_is_not_configured(monkeypatch, capsys):
    model, rest, _ = cantilever(11, 3)
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [])
    monkeypatch.setattr(newton, "_INFO_AFTER_S", -1.0)  # every call counts as a long one
    handler = next(h for h in newton._log.handlers if isinstance(h, newton._Progress))
    monkeypatch.setattr(handler, "stream", __import__("sys").stderr)
    x, info = tb.solve_static(model, rest)
    err = capsys.readouterr().err
    assert info.converged
    assert "newton it 0: residual" in err and "solve_static: converged (phase newton" in err
    monkeypatch.setattr(newton, "_INFO_AFTER_S", 1e9)  # a short call says nothing
    tb.solve_static(model, rest)
    assert capsys.readouterr().err == ""


def test_free_hessian_shift_adds_the_diagonal():
    model, rest, _ = cantilever(7, 3)
    phi = newton._Potential(model, rest, tb.Projection.parse("exact"))
    A = phi.free_hessian(rest + 1e-3 * torch.randn_like(rest, generator=torch.Generator().manual_seed(0)))
    d = torch.linspace(1.0, 2.0, A.shape[0], dtype=A.dtype)
    op = FreeHessian.for_model(model, phi.free_mask)
    B = op.shifted(A, d)
    assert torch.equal(B.to_dense(), A.to_dense() + torch.diag(d))
    assert torch.equal(op.diagonal(A), A.to_dense().diagonal())


def test_damping_follows_the_model_and_vanishes():
    d = Damping(torch.ones(6, dtype=torch.float64))
    d.start(torch.full((6,), 1e4, dtype=torch.float64))
    assert d.ref == 1e4 and d.mu == 0.0 and not d.active  # the first direction is Newton's
    assert d.increase() and d.mu == pytest.approx(2 * Damping.MIN * 1e4) and d.active
    d.mu, d.nu = 10.0, 2.0
    mu = d.mu
    d.record_direction(np.ones(6))
    slope = -1.0
    d.accepted(d.predicted(slope, 1.0), slope, 1.0)  # the model exact over a whole step: down tenfold
    assert d.mu == pytest.approx(mu / 10)
    d.accepted(0.0, slope, 1.0)  # no decrease: up
    assert d.mu > mu / 10 and d.nu == 4.0
    while d.increase():
        pass
    assert d.mu > Damping.MAX * d.ref
    d.off()
    assert not d.active


def test_damped_and_plain_newton_reach_the_same_equilibrium():
    model, rest, _ = cantilever(21, 6)
    x_plain, plain = tb.solve_static(model, rest, continuation=False)
    x_damped, damped = tb.solve_static(model, rest, continuation=False, damping=True)
    assert plain.converged and damped.converged
    scale = float((x_plain - rest).norm())
    assert float((x_damped - x_plain).norm()) <= 1e-7 * scale
    assert damped.minimum is True


def _tube_on_capsule() -> tuple[tb.ClothModel, torch.Tensor]:
    p, f, uv = tb.mesh.skirt(12, 7, waist_radius=0.06, hem_radius=0.06, length=0.3, dtype=torch.float64)
    rest = torch.stack((-p[:, 2], p[:, 0], p[:, 1]), -1).contiguous()
    rest, faces = tb.mesh.clean(rest, f)[:2]
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=tb.stiffness_from_material(2e5, 5e-4, 0.3))
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=2e5, poisson=0.3, thickness=5e-4)
    arm = tb.Capsule((-0.1, 0.0, 0.0), (0.4, 0.0, 0.0), radius=0.04, law="penalty")
    return tb.ClothModel(faces, rest, bending=bend, membrane=mem, colliders=[arm], density=0.2), rest


def test_damping_holds_a_cloth_that_can_slide_along_a_collider():
    """A tube on a capsule, nothing pinned: free to slide along the capsule (a singular Hessian).  The damped
    solve converges to a state that still hangs on the capsule; its potential is no higher than the
    undamped solve's (which may slide off the end and fall: unbounded below)."""
    model, rest = _tube_on_capsule()
    x, info = tb.solve_static(model, rest, continuation=False, damping=True, max_iters=150)
    assert info.converged, info.message
    assert float(x[:, 2].max()) >= 0.035  # the top still rests on the arm (radius 4 cm)
    assert float(x[:, 0].min()) > -0.1 and float(x[:, 0].max()) < 0.4  # on the capsule, not off its ends


@pytest.mark.parametrize("reuse", [False, True])
def test_an_impact_step_with_an_indefinite_exact_hessian_takes_the_clamped_direction(monkeypatch, reuse):
    """A tube falling onto a capsule: in the impact steps the exact Hessian of the incremental potential is
    indefinite; the step then solves with the clamped one (counted in ``regularized_steps``) and converges.
    With ``reuse_factorization=True`` the single-precision preconditioned CG gives way to the same decision
    where the matrix is not positive definite."""
    p, f, _ = tb.mesh.skirt(12, 7, waist_radius=0.06, hem_radius=0.06, length=0.3, dtype=torch.float64)
    rest = torch.stack((-p[:, 2], p[:, 0], p[:, 1]), -1).contiguous()
    rest, faces = tb.mesh.clean(rest, f)[:2]
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=tb.stiffness_from_material(2e5, 5e-4, 0.3))
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=2e5, poisson=0.3, thickness=5e-4)
    model = tb.ClothModel(faces, rest, bending=bend, membrane=mem, density=0.2,
                          colliders=[tb.Capsule((-0.1, 0.0, 0.0), (0.4, 0.0, 0.0), radius=0.04, law="penalty")])
    methods: list = []
    real = newton._Potential.direct_direction

    def spy(self, x, gf, *args):
        out = real(self, x, gf, *args)
        methods.append(self.linear_method)
        return out

    monkeypatch.setattr(newton._Potential, "direct_direction", spy)
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    solver = tb.LinearSolver(reuse_factorization=reuse)
    for _ in range(12):
        state, info = tb.implicit_euler_step(model, state, 0.01, linear_solver=solver)
        assert info.converged and info.substeps == 1, info.message
    assert any(m.endswith("/clamp") for m in methods)
    reused = reuse and DIRECT_METHOD == "ldlt"  # (the single-precision preconditioner is PARDISO's)
    assert methods.count(DIRECT_METHOD) > 0 if not reused else any(m.startswith("ldlt32") for m in methods)
    assert float(state.x[:, 2].max()) > 0.035  # resting on the arm, not through it


def test_auto_gives_a_damped_garment_on_a_collider_a_long_first_attempt():
    """continuation="auto" with the damping and a collider: the first attempt may take 4 max_iters iterations
    (newton._DAMPED_FIRST_FACTOR), so a tube that the damped Newton finishes in more than max_iters iterations
    converges in that one solve, to the equilibrium a long damped run reaches; without a collider (the
    cantilever) the first attempt is cut at min(max_iters, 40) as before and the homotopy follows."""
    model, rest = _tube_on_capsule()
    _, long_run = tb.solve_static(model, rest, continuation=False, max_iters=150)
    assert long_run.converged and long_run.iterations > 10, long_run.message
    max_iters = max(long_run.iterations // 2, 1)  # the run needs more than max_iters, less than 4 max_iters
    _, info = tb.solve_static(model, rest, max_iters=max_iters)
    assert info.converged and info.solves == 1 and info.phase == "newton", info.message
    assert info.iterations == long_run.iterations and info.energy == long_run.energy
    _, cut = tb.solve_static(model, rest, max_iters=max_iters, damping=False)
    assert cut.solves > 1  # undamped: the 40-iteration rule, then the homotopy
    beam, beam_rest, _ = cantilever(11, 3)
    _, first = tb.solve_static(beam, beam_rest, max_iters=1, continuation=False)
    _, auto = tb.solve_static(beam, beam_rest, max_iters=1)
    assert not first.converged and auto.solves > 1  # no collider: one iteration, then the homotopy
