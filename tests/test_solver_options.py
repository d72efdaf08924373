"""Solver options as objects: :class:`torchbend.NewtonOptions` and :class:`torchbend.LinearSolver` given as
``options=`` to the solvers and the adjoint, keywords over fields, the solvers' own defaults for fields left
``None``, validation naming the field, and the config's ``solver`` section mapped to them one to one."""
import math
import warnings

import pytest
import torch

import torchbend as tb
from torchbend.scenes.config import SceneConfig, validate

F64 = torch.float64


def _strip(nx: int = 6, ny: int = 3):
    """A clamped, sagging strip: bending, membrane and gravity, two pinned columns."""
    rest, faces = tb.scenes.grid(nx, ny, (0.12, 0.03), dtype=F64)
    pinned = rest[:, 0] <= rest[:, 0].unique()[1] + 1e-12
    model = tb.ClothModel(faces, rest, bending=tb.BendingEnergy(faces, rest, model="quadratic", stiffness=1e-4),
                          membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=1e-3),
                          density=0.2, pinned=pinned)
    return model, rest


def _same(a, b):
    (xa, ia), (xb, ib) = a, b
    assert ia.converged and ib.converged
    assert torch.equal(xa, xb) and ia.iterations == ib.iterations and ia.tolerance == ib.tolerance


def test_options_object_and_keywords_solve_alike():
    model, rest = _strip()
    opts = tb.NewtonOptions(projection="gauss_newton", linear_solver=tb.LinearSolver("cg", preconditioner="block_jacobi"),
                            tol=1e-8, max_iters=80)
    _same(tb.solve_static(model, rest, opts),
          tb.solve_static(model, rest, projection="gauss_newton", linear_solver=tb.LinearSolver("cg", "block_jacobi"),
                          tol=1e-8, max_iters=80))
    state = tb.ClothState(rest, torch.zeros_like(rest))
    step = tb.NewtonOptions(projection="clamp", tol=1e-7)
    (sa, ia), (sb, ib) = (tb.implicit_euler_step(model, state, 0.01, step),
                          tb.implicit_euler_step(model, state, 0.01, projection="clamp", tol=1e-7))
    assert ia.converged and torch.equal(sa.x, sb.x) and torch.equal(sa.v, sb.v) and ia.iterations == ib.iterations


def test_a_keyword_overrides_the_field_and_none_fields_take_each_solvers_default():
    model, rest = _strip()
    loose = tb.NewtonOptions(tol=1e-3)
    _, info = tb.solve_static(model, rest, loose, tol=1e-10)
    assert info.converged and math.isclose(info.tolerance, 1e-10 * info.force_scale, rel_tol=1e-12)
    _, static = tb.solve_static(model, rest, tb.NewtonOptions())
    assert math.isclose(static.tolerance, 1e-9 * static.force_scale, rel_tol=1e-12)  # the static default
    assert static.minimum is True  # check_minimum defaults to True for a static solve
    _, step = tb.implicit_euler_step(model, tb.ClothState(rest, torch.zeros_like(rest)), 0.01, tb.NewtonOptions())
    assert math.isclose(step.tolerance, 1e-6 * step.force_scale, rel_tol=1e-12)  # a step's default
    assert step.minimum is None  # not checked by default in a step
    _, capped = tb.solve_static(model, rest, tb.NewtonOptions(max_iters=1, continuation=False))
    assert capped.iterations == 1 and capped.stop_reason == "max_iters"


def test_max_cg_iters_keyword_replaces_the_linear_solvers_bound():
    model, rest = _strip(8, 3)
    cg = tb.NewtonOptions(linear_solver=tb.LinearSolver("cg", preconditioner="block_jacobi"), max_iters=3,
                          continuation=False)
    _, info = tb.solve_static(model, rest, cg, max_cg_iters=1)
    assert info.cg_iterations <= info.solves * 3 * 1 + 3  # one CG iteration per direction (and the curvature checks)
    _, free = tb.solve_static(model, rest, cg)
    assert free.cg_iterations > info.cg_iterations


def test_the_adjoint_takes_options():
    base, rest = _strip()
    faces = base.topology.faces
    k = torch.tensor(1e-4, dtype=F64, requires_grad=True)
    model = tb.ClothModel(faces, rest, bending=tb.BendingEnergy(faces, rest, model="quadratic", stiffness=k),
                          membrane=base.membrane, density=0.2, pinned=base.pinned)
    x, info = tb.solve_static_adjoint(model, rest, [k], options=tb.NewtonOptions(tol=1e-10, projection="exact"))
    assert info.converged and math.isclose(info.tolerance, 1e-10 * info.force_scale, rel_tol=1e-12)
    (g,) = torch.autograd.grad(x[:, 2].sum(), k)
    assert float(g) > 0  # stiffer: the free end sags less


@pytest.mark.parametrize("kw, match", [
    ({"tol": 0.0}, "tol must be positive"),
    ({"tol": math.inf}, "tol must be positive"),
    ({"max_iters": -1}, "max_iters must be an int >= 0"),
    ({"max_iters": 2.5}, "max_iters must be an int >= 0"),
    ({"check_minimum": "yes"}, "check_minimum must be True, False or None"),
    ({"time_limit": -1.0}, "time_limit must be positive"),
    ({"continuation": "sometimes"}, "continuation must be 'auto'"),
    ({"max_relax_steps": -2}, "max_relax_steps must be an int >= 0"),
    ({"max_substep_depth": True}, "max_substep_depth must be an int >= 0"),
    ({"projection": "newton"}, "projection"),
    ({"linear_solver": "qr"}, "linear_solver"),
])
def test_bad_options_are_value_errors_naming_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        tb.NewtonOptions(**kw)
    with pytest.raises(ValueError, match=match):
        tb.NewtonOptions().replace(**kw)


def test_options_must_be_newton_options():
    model, rest = _strip()
    with pytest.raises(ValueError, match="options must be a torchbend.NewtonOptions, got dict"):
        tb.solve_static(model, rest, {"tol": 1e-8})  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="options must be a torchbend.NewtonOptions"):
        tb.implicit_euler_step(model, tb.ClothState(rest, torch.zeros_like(rest)), 0.01, "exact")  # pyright: ignore[reportArgumentType]


def test_options_are_frozen_and_hashable():
    a = tb.NewtonOptions(projection="clamp")
    with pytest.raises(AttributeError):
        a.tol = 1.0  # type: ignore[misc]
    assert a == tb.NewtonOptions(projection=tb.Projection.CLAMP) and hash(a) == hash(a.replace())
    assert a.projection is tb.Projection.CLAMP and isinstance(a.linear_solver, tb.LinearSolver)


def test_config_solver_section_maps_to_newton_options_field_by_field():
    cfg = validate({"solver": {"projection": "gauss_newton", "tol": 1e-7, "max_iters": 12, "check_minimum": False,
                               "time_limit": 9.0, "continuation": "membrane", "max_relax_steps": 5,
                               "max_substep_depth": 1,
                               "linear_solver": {"method": "cg", "preconditioner": "ilu", "max_cg_iters": 40}}},
                   SceneConfig)
    assert cfg.solver.newton_options() == tb.NewtonOptions(
        projection="gauss_newton", tol=1e-7, max_iters=12, check_minimum=False, time_limit=9.0,
        continuation="membrane", max_relax_steps=5, max_substep_depth=1,
        linear_solver=tb.LinearSolver("cg", preconditioner="ilu", max_cg_iters=40))
    # every field of NewtonOptions has its key in the section, and the defaults agree
    from dataclasses import fields
    section = validate({}, SceneConfig).solver
    for f in fields(tb.NewtonOptions):
        assert f.name in type(section).model_fields, f.name
    assert section.newton_options() == tb.NewtonOptions()
    assert validate({"solver": {"linear_solver": "cg"}}, SceneConfig).solver.newton_options().linear_solver == \
        tb.LinearSolver("cg")


def test_config_solver_hessian_is_a_deprecated_alias_of_projection():
    with pytest.warns(DeprecationWarning, match="solver.hessian"):
        cfg = validate({"solver": {"hessian": "clamp"}}, SceneConfig)
    assert cfg.solver.newton_options().projection is tb.Projection.CLAMP
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        with pytest.raises(ValueError, match="'projection' or its deprecated alias 'hessian'"):
            validate({"solver": {"hessian": "clamp", "projection": "abs"}}, SceneConfig)
    with pytest.raises(ValueError, match="solver.projection"):
        validate({"solver": {"projection": "newton"}}, SceneConfig)
    with pytest.raises(ValueError, match="solver.linear_solver.preconditioner"):
        validate({"solver": {"linear_solver": {"method": "cg", "preconditioner": "jacobi"}}}, SceneConfig)
