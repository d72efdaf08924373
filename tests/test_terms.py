"""The energy-term protocol (torchbend/sim/terms.py): a term of one's own, written with the documented protocol
only, in ClothModel, solve_static, implicit_euler_step and solve_static_adjoint, against closed forms.

Zero-length springs ``k_i |x_i - a_i|^2 / 2`` with ``k_i = kappa m_i`` and anchors ``a = rest + c`` (a rigid
translation of the rest state) under gravity have the equilibrium ``x = rest + c + g / kappa``: a translation,
so the membrane and the bending stay at rest and exert no force, and the closed form holds with them in the
model.  The same for an implicit-Euler step from ``(rest, v0)`` with uniform ``v0``:
``x = (x_hat / dt^2 + kappa a + g) / (1 / dt^2 + kappa)`` per vertex."""
from __future__ import annotations

import warnings

import pytest
import torch

import torchbend as tb
from torchbend.sim.terms import InertiaTerm

F64 = torch.float64
KAPPA = 40.0  # [1/s^2]: k_i / m_i
SHIFT = torch.tensor([0.01, -0.02, 0.03], dtype=F64)  # [m]: anchors = rest + SHIFT
G = torch.tensor([0.0, 0.0, -9.81], dtype=F64)


class AnchorSprings(tb.EnergyTerm):
    """The README's example: per-vertex 3x3 Hessian blocks."""

    name = "anchors"

    def __init__(self, k, a):
        self.k, self.a = k, a

    def energy(self, x, ctx):
        return 0.5 * (self.k[:, None] * (x - self.a) ** 2).sum()

    def gradient(self, x, ctx):
        return self.k[:, None] * (x - self.a)

    def vertex_blocks(self, x, ctx, projection=None):
        return self.k[:, None, None] * torch.eye(3, dtype=x.dtype, device=x.device)


class CoupledAnchorSprings(tb.EnergyTerm):
    """The same springs, with the energy only (autograd derivatives) and the Hessian as a general ``(3V, 3V)``
    sparse COO matrix (the path of a term that couples vertices)."""

    name = "coupled"

    def __init__(self, k, a):
        self.k, self.a = k, a

    def energy(self, x, ctx):
        return 0.5 * (self.k[:, None] * (x - self.a) ** 2).sum()

    def hessian(self, x, ctx, projection=None):
        n = 3 * x.shape[0]
        i = torch.arange(n, device=x.device)
        return torch.sparse_coo_tensor(torch.stack((i, i)), self.k.repeat_interleave(3).to(x.dtype), (n, n),
                                       check_invariants=False)


def sheet(n: int = 6):
    rest, faces = tb.scenes.grid(n, n, (0.3, 0.3), dtype=F64)
    mem = tb.MembraneEnergy(faces, rest, young=2e5, poisson=0.3, thickness=5e-4)
    bend = tb.BendingEnergy(faces, rest, stiffness=1e-5)
    return rest, faces, mem, bend


def springs_model(kind: type = AnchorSprings, **kw):
    rest, faces, mem, bend = sheet()
    probe = tb.ClothModel(faces, rest, density=0.2)
    springs = kind(KAPPA * probe.mass, rest + SHIFT)
    return tb.ClothModel(faces, rest, density=0.2, terms=[mem, bend, springs], **kw), rest, springs


@pytest.mark.parametrize("kind", [AnchorSprings, CoupledAnchorSprings])
@pytest.mark.parametrize("linear_solver", ["direct", "cg"])
def test_own_term_static_equilibrium_is_the_closed_form(kind, linear_solver):
    model, rest, _ = springs_model(kind)
    assert [t.name for t in model.terms] == ["membrane", "bending", "gravity", kind.name]
    x, info = tb.solve_static(model, rest, linear_solver=linear_solver)
    assert info.converged, info.message
    expected = rest + SHIFT + G / KAPPA
    assert float((x - expected).abs().max()) <= 1e-9 * float((expected - rest).abs().max())
    assert set(info.energies) == {"membrane", "bending", "gravity", kind.name}


def test_own_term_implicit_step_is_the_closed_form():
    model, rest, _ = springs_model()
    v0 = torch.tensor([0.1, 0.0, -0.05], dtype=F64).expand_as(rest).clone()
    dt = 0.02
    state, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), v0), dt)
    assert info.converged, info.message
    x_hat = rest + dt * v0
    expected = (x_hat / dt**2 + KAPPA * (rest + SHIFT) + G) / (1 / dt**2 + KAPPA)
    assert float((state.x - expected).abs().max()) <= 1e-9 * float((expected - rest).abs().max())
    assert torch.allclose(state.v, (state.x - rest) / dt, rtol=1e-12, atol=0)


def test_own_term_in_the_adjoint():
    """``L = sum_i m_i . x_i``: ``dL/da = kappa M lambda`` with ``H lambda = M 1``; the membrane and bending are
    translation invariant, so ``lambda = 1 / kappa`` and ``dL/da_i = m_i`` in each component."""
    model, rest, springs = springs_model()
    springs.a = springs.a.clone().requires_grad_(True)
    x, info = tb.solve_static_adjoint(model, rest, [springs.a])
    assert info.converged, info.message
    (model.mass[:, None] * x).sum().backward()
    grad = springs.a.grad
    assert grad is not None
    expected = model.mass[:, None].expand_as(grad)
    assert float((grad - expected).abs().max()) <= 1e-8 * float(expected.abs().max())


def test_default_derivatives_of_a_term_are_autograd():
    model, rest, _ = springs_model(CoupledAnchorSprings)
    term = model.terms[-1]
    assert isinstance(term, CoupledAnchorSprings)
    x = rest + 1e-2 * torch.randn_like(rest, generator=torch.Generator().manual_seed(0))
    ctx = tb.StepContext()
    assert torch.allclose(term.gradient(x, ctx), term.k[:, None] * (x - term.a), rtol=1e-13, atol=0)
    v = torch.randn_like(x, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(term.hvp(x, v, ctx), term.k[:, None] * v, rtol=1e-13, atol=0)
    blocks = term.block_diagonal(x, ctx)
    assert torch.allclose(blocks, term.k[:, None, None] * torch.eye(3, dtype=F64), rtol=1e-13, atol=0)
    # the model's Hessian, HVP and gradient include the term
    H = model.hessian(x, "exact")
    without = tb.ClothModel(model.topology, rest, density=0.2, membrane=model.membrane, bending=model.bending)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        diff = (H - without.hessian(x, "exact")).toarray()
    assert abs(diff - torch.diag(term.k.repeat_interleave(3)).numpy()).max() <= 1e-9 * float(term.k.max())
    assert torch.allclose(model.gradient(x) - without.gradient(x), term.k[:, None] * (x - term.a), rtol=1e-9,
                          atol=1e-12)


def test_a_term_without_a_hessian_says_what_to_define():
    class EnergyOnly(tb.EnergyTerm):
        name = "energy_only"

        def energy(self, x, ctx):
            return (x**4).sum()

    rest, faces, _, _ = sheet()
    model = tb.ClothModel(faces, rest, terms=[EnergyOnly()], pinned=[0])
    with pytest.raises(NotImplementedError, match=r"EnergyOnly \('energy_only'\) must define hessian"):
        tb.solve_static(model, rest)


def test_terms_argument_is_checked():
    rest, faces, mem, bend = sheet()
    with pytest.raises(ValueError, match=r"terms\[1\] must be an EnergyTerm"):
        tb.ClothModel(faces, rest, terms=[mem, "springs"])
    with pytest.raises(ValueError, match=r"terms\[0\] is a second bending energy"):
        tb.ClothModel(faces, rest, terms=[bend], bending=bend)
    a = AnchorSprings(torch.ones(len(rest), dtype=F64), rest)
    b = AnchorSprings(torch.ones(len(rest), dtype=F64), rest)
    with pytest.raises(ValueError, match=r"the name 'anchors' .* is already taken"):
        tb.ClothModel(faces, rest, terms=[a, b])
    b.name = "gravity"
    with pytest.raises(ValueError, match=r"the name 'gravity' .* is already taken"):
        tb.ClothModel(faces, rest, terms=[b])
    # the shorthands and terms= build the same model
    sphere = tb.Sphere((0, 0, -1), 0.5, stiffness=1.0)  # a stiffness given: the model keeps the collider itself
    m1 = tb.ClothModel(faces, rest, terms=[mem, bend, sphere])
    m2 = tb.ClothModel(faces, rest, membrane=mem, bending=bend, colliders=[sphere])
    assert [t.name for t in m1.terms] == [t.name for t in m2.terms] == ["membrane", "bending", "gravity", "collider0"]
    assert m1.membrane is mem and m1.bending is bend and m1.colliders == (sphere,)


def test_a_confining_term_lifts_the_rigid_body_diagnosis():
    """Without pins or colliders a cloth under gravity is unbounded below, unless a term confines it."""
    rest, faces, mem, _ = sheet()
    free = tb.ClothModel(faces, rest, membrane=mem)
    _, info = tb.solve_static(free, rest)
    assert info.stop_reason == "rigid_body_modes"
    model, rest, _ = springs_model()
    assert not bool(model.pinned.any())
    _, info = tb.solve_static(model, rest)
    assert info.converged and info.stop_reason != "rigid_body_modes"


def test_cloth_loss_of_the_model_terms_is_the_model_potential():
    """``model.loss()`` composes the model's own term objects over a batch: per sample, its values are the
    model's energies and its total the potential, and its autograd gradient is the model's gradient."""
    model, rest, springs = springs_model()
    model.colliders = (tb.Sphere((0.15, 0.15, -0.3), 0.3, law="penalty"),)  # finite for every sample
    gen = torch.Generator().manual_seed(3)
    x = rest + 0.01 * torch.randn((4, *rest.shape), generator=gen, dtype=F64)
    loss = model.loss(reduction="none")
    assert set(loss.terms) == {"membrane", "bending", "gravity", "collider0", "anchors"}
    total, values = loss(x)
    for i in range(len(x)):
        e = model.energies(x[i])
        for name, v in e.items():
            assert abs(float(values[name][i]) - v) <= 1e-13 * max(abs(v), 1e-30), name
        assert abs(float(total[i]) - model.potential(x[i])) <= 1e-12 * sum(abs(v) for v in e.values())
    y = x[1].clone().requires_grad_(True)
    summed, _ = model.loss(reduction="sum")(y[None])
    (g,) = torch.autograd.grad(summed, y)
    ref = model.gradient(x[1])
    assert float((g - ref).abs().max()) <= 1e-9 * float(ref.abs().max())
    # an empty batch
    empty, _ = model.loss()(x[:0])
    assert float(empty) == 0.0


def test_projection_keyword_and_its_deprecated_alias():
    """``projection=`` everywhere a Hessian is projected; ``project=`` gives the same result with a
    DeprecationWarning, and the two disagreeing is a ValueError."""
    rest, faces, mem, bend = sheet()
    x = rest + 0.01 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    v = torch.randn_like(x)
    sphere = tb.Sphere((0.15, 0.15, -0.2), 0.25, law="penalty")
    calls = [(bend.hessian, (x,), "BendingEnergy.hessian"), (bend.hvp, (x, v), "BendingEnergy.hvp"),
             (bend.hinge_hessians, (x,), "BendingEnergy.hinge_hessians"),
             (mem.hessian, (x,), "MembraneEnergy.hessian"), (mem.hvp, (x, v), "MembraneEnergy.hvp"),
             (mem.element_hessians, (x,), "MembraneEnergy.element_hessians"),
             (sphere.hessian_blocks, (x,), "Collider.hessian_blocks")]
    for fn, args, where in calls:
        new = fn(*args, projection="clamp")
        with pytest.warns(DeprecationWarning, match=rf"{where}: project= is deprecated, use projection="):
            old = fn(*args, project="clamp")
        dense = (lambda t: t.to_dense()) if new.layout != torch.strided else (lambda t: t)
        assert torch.equal(dense(new), dense(old)), where
        with pytest.raises(ValueError, match=rf"{where}: projection='abs' and project='clamp' disagree"), \
                pytest.warns(DeprecationWarning):
            fn(*args, projection="abs", project="clamp")


def test_solver_projection_keyword_and_its_deprecated_alias():
    model, rest, _ = springs_model()
    x_new, info_new = tb.solve_static(model, rest, projection="clamp")
    with pytest.warns(DeprecationWarning, match="solve_static: hessian= is deprecated, use projection="):
        x_old, info_old = tb.solve_static(model, rest, hessian="clamp")
    assert info_new.converged and torch.equal(x_new, x_old) and info_new.iterations == info_old.iterations
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    with pytest.warns(DeprecationWarning, match="implicit_euler_step: hessian= is deprecated"):
        tb.implicit_euler_step(model, state, 0.01, hessian="gauss_newton")
    with pytest.raises(ValueError, match="projection='clamp' and hessian='abs' disagree"), pytest.warns(DeprecationWarning):
        tb.solve_static(model, rest, projection="clamp", hessian="abs")


STIFFENING = 100.0


class StiffeningSprings(AnchorSprings):
    """The springs, stiffened a hundredfold at the first accepted iterate of a solve (as a barrier adapts its
    stiffness: :meth:`EnergyTerm.adapt`)."""

    name = "stiffening"

    def __init__(self, k, a):
        super().__init__(k, a)
        self.stiffened = False

    def adapt(self, x, ctx, start=False):
        if start or self.stiffened:
            return False
        self.k, self.stiffened = STIFFENING * self.k, True
        return True


@pytest.mark.parametrize("max_iters", [1, 30])
def test_a_term_that_adapts_within_a_solve_restarts_its_bookkeeping(max_iters):
    """A term that changes its energy at an iterate of a time step (``adapt`` True) makes a new potential: the step
    converges to the new potential's solution (the closed form with the springs' new stiffness), counts the change
    in ``info.adaptations`` (``info.adapted_at``: where ``energy_history`` changes potential) and reports the energy
    of the returned state under the new potential; stopped right after the change (``max_iters=1``) it returns the
    iterate after the change, not a lower one of the old potential.  A static solve keeps its potential."""
    model, rest, springs = springs_model(StiffeningSprings)
    x, info = tb.solve_static(model, rest)
    assert info.converged and not springs.stiffened and info.adaptations == 0
    v0 = torch.tensor([0.1, 0.0, -0.05], dtype=F64).expand_as(rest).clone()
    dt = 0.02
    state, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), v0), dt, max_iters=max_iters,
                                         max_substep_depth=0)
    assert springs.stiffened and info.adaptations == 1 and info.adapted_at == [1]
    ctx = tb.StepContext.for_step(model.terms, rest, v0, dt)
    potential = sum(float(t.energy(state.x, ctx)) for t in model.terms) + float(InertiaTerm(model.mass).energy(state.x, ctx))
    assert info.energy == pytest.approx(potential, rel=1e-12)
    if max_iters > 1:
        assert info.converged, info.message
        kappa = STIFFENING * KAPPA
        expected = ((rest + dt * v0) / dt**2 + kappa * (rest + SHIFT) + G) / (1 / dt**2 + kappa)
        assert float((state.x - expected).abs().max()) <= 1e-9 * float((expected - rest).abs().max())
    else:
        assert not info.converged and info.best_iteration == 1
