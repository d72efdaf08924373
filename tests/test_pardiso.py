"""The supernodal L D L^T of MKL PARDISO (torchbend/sim/pardiso.py) and the direct solver's use of it:
against dense NumPy solves and eigenvalues (the inertia), the symbolic analysis kept across values of one
pattern, shifts, singular matrices, a pattern mismatch; whole solves with factorization='ldlt' against 'lu'
(the same equilibria and steps), and the option's validation.  Skipped where MKL is not installed (the
extra torchbend[solvers]); the SuperLU path is the default there and tests/test_solver_linear.py covers it."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

import torchbend as tb
from torchbend import ClothState, implicit_euler_step, solve_static
from torchbend.options import Projection
from torchbend.scenes.config import build_scene, load_config
from torchbend.sim import linear, newton, pardiso
from torchbend.sim.options import Factorization

from .helpers import CONFIGS, cantilever

pytestmark = pytest.mark.skipif(not pardiso.available(), reason="MKL (PARDISO) not installed")


def sparse_symmetric(n, eigenvalues, seed=0) -> sp.csr_matrix:
    """A sparse symmetric ``(n, n)`` CSR matrix with a full diagonal and about the given eigenvalues:
    ``diag(eigenvalues)`` plus a small random symmetric coupling of a quarter of the entries (the tests take
    the exact eigenvalues from ``numpy.linalg.eigvalsh``)."""
    rng = np.random.default_rng(seed)
    C = rng.random((n, n)) * (rng.random((n, n)) < 0.25)
    C = 0.05 * np.abs(np.asarray(eigenvalues)).min() * (C + C.T)
    D = np.diag(np.asarray(eigenvalues, dtype=float)) + C
    return _with_diagonal(D)


def _with_diagonal(D) -> sp.csr_matrix:
    """Dense ``D`` as CSR with every diagonal entry stored (zeros included) and sorted columns."""
    n = D.shape[0]
    mask = (D != 0) | np.eye(n, dtype=bool)
    rows, cols = np.nonzero(mask)
    A = sp.csr_matrix((D[rows, cols], (rows, cols)), shape=(n, n))
    A.sort_indices()
    assert A.nnz == int(mask.sum())
    return A


def eig_inertia(A):
    lam = np.linalg.eigvalsh(A.toarray())
    return int((lam > 0).sum()), int((lam < 0).sum()), float(np.abs(lam).max() / np.abs(lam).min())


@pytest.mark.parametrize("eigs", [np.linspace(1.0, 1e4, 40), np.r_[-np.geomspace(1, 10, 7), np.geomspace(1e-3, 1e3, 33)]],
                         ids=["definite", "indefinite"])
def test_factor_solves_and_reports_the_inertia(eigs):
    n = int(eigs.shape[0])
    A = sparse_symmetric(n, eigs)
    b = np.random.default_rng(1).standard_normal(n)
    f = pardiso.SymmetricFactor(A.indptr, A.indices)
    assert f.factor(A.data)
    x = f.solve(b)
    ref = np.linalg.solve(A.toarray(), b)
    pos, neg, cond = eig_inertia(A)
    assert np.linalg.norm(x - ref) <= 1e3 * cond * np.finfo(float).eps * np.linalg.norm(ref)
    assert f.inertia == (pos, neg) and pos + neg == n
    assert f.positive_definite is (neg == 0)
    # several right-hand sides at once
    B = np.random.default_rng(2).standard_normal((n, 3))
    X = f.solve(B)
    assert X.shape == B.shape and np.allclose(A @ X, B, rtol=0, atol=1e3 * cond * np.finfo(float).eps * np.abs(B).max())


def test_the_analysis_is_kept_for_new_values_and_shifts():
    eigs = np.linspace(1.0, 10.0, 30)
    A = sparse_symmetric(30, eigs, seed=3)
    f = pardiso.SymmetricFactor(A.indptr, A.indices)
    b = np.ones(30)
    for scale, shift in ((1.0, 0.0), (2.0, 0.0), (1.0, -5.5), (1.0, 3.0)):
        assert f.factor(scale * A.data, shift)
        M = (scale * A + shift * sp.identity(30)).tocsr()
        assert np.allclose(M @ f.solve(b), b, rtol=0, atol=1e-10)
        assert f.inertia == eig_inertia(M)[:2]
    assert f._analysed


def test_pattern_errors_are_value_errors():
    A = sp.csr_matrix(np.array([[1.0, 2.0], [2.0, 0.0]]))
    A.eliminate_zeros()  # the (1, 1) entry is not stored
    with pytest.raises(ValueError, match="diagonal"):
        pardiso.SymmetricFactor(A.indptr, A.indices)
    B = sparse_symmetric(10, np.arange(1.0, 11.0))
    f = pardiso.SymmetricFactor(B.indptr, B.indices)
    other = sparse_symmetric(12, np.arange(1.0, 13.0))
    with pytest.raises(ValueError, match="pattern"):
        linear.direct_solve(other, np.ones(12), factor=f)
    with pytest.raises(RuntimeError, match="factor"):
        f.solve(np.ones(10))


def test_direct_solve_with_the_factor_matches_the_lu():
    """The same directions, shifts and definiteness through the factor as through SuperLU, on a definite
    and an indefinite matrix (its direction kept: a descent direction)."""
    n = 24
    rng = np.random.default_rng(4)
    for eigs in (np.geomspace(1e-2, 1e2, n), np.r_[-0.5, np.geomspace(1e-1, 1e1, n - 1)]):
        A = sparse_symmetric(n, eigs, seed=5)
        b = rng.standard_normal(n)
        f = pardiso.SymmetricFactor(A.indptr, A.indices)
        got, ref = linear.direct_solve(A, b, factor=f), linear.direct_solve(A, b)
        assert got.method in ("ldlt", "steepest") and ref.method in ("lu", "steepest")
        assert got.shifts == ref.shifts and got.positive_definite == ref.positive_definite
        assert np.allclose(got.p, ref.p, rtol=1e-8, atol=1e-12 * np.abs(ref.p).max())
        assert float(b @ got.p) > 0


def test_singular_matrix_is_shifted():
    A = _with_diagonal(np.diag([1.0, 0.0, 2.0]))
    f = pardiso.SymmetricFactor(A.indptr, A.indices)
    b = np.array([1.0, 1.0, 1.0])
    res = linear.direct_solve(A, b, factor=f)
    assert np.all(np.isfinite(res.p)) and float(b @ res.p) > 0 and res.positive_definite is False


def _solve_both(fn):
    out = {}
    for kind in ("lu", "ldlt"):
        out[kind] = fn(tb.LinearSolver("direct", factorization=kind))
    return out["lu"], out["ldlt"]


@pytest.mark.parametrize("projection", ["exact", "clamp"])
def test_static_solve_ldlt_equals_lu(projection):
    model, rest, _ = cantilever(8, 3)
    (x_lu, i_lu), (x_ld, i_ld) = _solve_both(lambda ls: solve_static(model, rest, projection=projection, linear_solver=ls))
    assert i_lu.converged and i_ld.converged
    scale = float((x_lu - rest).abs().max())
    assert float((x_ld - x_lu).abs().max()) <= 1e-6 * scale


def test_implicit_step_ldlt_equals_lu():
    cfg = load_config(f"{CONFIGS}/cloth_sphere.yaml")
    model, x0, _ = build_scene(cfg, resolution=(9, 9))
    state = ClothState(x0, torch.zeros_like(x0))
    dt = cfg["solver"]["dt"]
    for _ in range(3):
        (s_lu, i_lu), (s_ld, i_ld) = _solve_both(lambda ls, state=state: implicit_euler_step(model, state, dt, linear_solver=ls))
        assert i_lu.converged and i_ld.converged
        assert float((s_ld.x - s_lu.x).abs().max()) <= 1e-9
        state = s_lu


def test_default_uses_the_factor_and_keeps_it_per_pattern():
    model, rest, _ = cantilever(6, 3)
    x = rest + 1e-3 * torch.randn(rest.shape, dtype=rest.dtype, generator=torch.Generator().manual_seed(0)) \
        * (~model.pinned)[:, None]
    phi = newton._Potential(model, x, Projection.CLAMP)
    gf = phi.free_gradient(x)
    phi.direct_direction(x, gf)
    assert phi.linear_method == "ldlt" and phi.positive_definite is True
    first = phi.hessian_op.direct_factor()
    phi.direct_direction(rest, phi.free_gradient(rest))
    assert phi.hessian_op.direct_factor() is first  # one analysis per pattern


def test_factorization_option_is_validated():
    assert tb.LinearSolver(factorization="ldlt").factorization == Factorization.LDLT
    assert tb.LinearSolver().factorization == Factorization.AUTO
    with pytest.raises(ValueError, match="factorization"):
        tb.LinearSolver(factorization="cholmod")


# -------------------------------------------------------------------- reused factorisations
def test_reused_factor_solve_preconditions_cg_with_a_nearby_matrix():
    """CG preconditioned with the factorisation of a nearby matrix reaches the tolerance in a few iterations;
    with too few iterations, an indefinite factor or a foreign pattern it declines (None: factorise anew)."""
    n = 60
    A0 = sparse_symmetric(n, np.linspace(1.0, 50.0, n), seed=3)
    A = A0.copy()
    A.data = A.data * (1 + 0.02 * np.random.default_rng(4).standard_normal(A.nnz))
    A = sp.csr_matrix((A + A.T) * 0.5)
    A.sort_indices()
    assert A.nnz == A0.nnz
    f = pardiso.SymmetricFactor(A0.indptr, A0.indices)
    b = np.random.default_rng(5).standard_normal(n)
    p, its = linear.reused_factor_solve(A, b, f, tol=1e-8, maxiter=20)
    assert p is None and its == 0  # nothing factorised yet
    assert f.factor(A0.data) and f.positive_definite
    p, its = linear.reused_factor_solve(A, b, f, tol=1e-8, maxiter=20)
    assert p is not None and 1 <= its <= 10
    assert np.linalg.norm(A @ p - b) <= 1e-8 * np.linalg.norm(b)
    p_exact = np.linalg.solve(A.toarray(), b)
    assert np.linalg.norm(p - p_exact) <= 1e-6 * np.linalg.norm(p_exact)
    p, its = linear.reused_factor_solve(A, b, f, tol=1e-14, maxiter=1)
    assert p is None and its == 1  # not reached in one iteration
    B = sparse_symmetric(n, np.linspace(-5.0, 50.0, n), seed=3)
    assert f.factor(B.data) and not f.positive_definite
    assert linear.reused_factor_solve(A, b, f, tol=1e-8, maxiter=20) == (None, 0)


def test_reuse_factorization_option():
    assert tb.LinearSolver().reuse_factorization == "auto"
    from torchbend.sim.options import REUSE_MIN_UNKNOWNS

    auto = tb.LinearSolver()
    assert not auto.reuses_factorization(REUSE_MIN_UNKNOWNS - 1) and auto.reuses_factorization(REUSE_MIN_UNKNOWNS)
    assert tb.LinearSolver(reuse_factorization=True).reuses_factorization(3)
    assert not tb.LinearSolver(reuse_factorization=False).reuses_factorization(10**7)
    bad_values: tuple = (1, "yes", None)
    for bad in bad_values:
        with pytest.raises(ValueError, match="reuse_factorization"):
            tb.LinearSolver(reuse_factorization=bad)


def test_steps_with_reused_factorisations_match_fresh_ones():
    """Implicit steps of the drape while the cloth lands on the sphere (2-7 Newton iterations a step), every
    direction tried on the last factorisation first: they use it (CG iterations counted), converge, and land
    on the states of fresh factorisations within what the step tolerance allows: both residuals are below
    ``tol``, and the step's Hessian is at least ``M / dt^2`` (the elastic terms are convex there), so the
    states differ by at most ``2 tol dt^2 / m_min`` (measured: 7e-9 m against 1.0e-7 m)."""
    cfg = load_config(f"{CONFIGS}/cloth_sphere.yaml")
    model, x0, _ = build_scene(cfg, resolution=(11, 11))
    dt = cfg["solver"]["dt"]
    state = ClothState(x0, torch.zeros_like(x0))
    for _ in range(11):  # falling: one Newton iteration a step
        state, _info = implicit_euler_step(model, state, dt)
    m_min, cg, newton_its = float(model.mass.min()), 0, 0
    for _ in range(8):
        fresh, i_f = implicit_euler_step(model, state, dt, linear_solver=tb.LinearSolver(reuse_factorization=False))
        reused, i_r = implicit_euler_step(model, state, dt, linear_solver=tb.LinearSolver(reuse_factorization=True))
        assert i_f.converged and i_r.converged and i_f.cg_iterations == 0
        assert i_r.residual <= i_r.tolerance
        cg += i_r.cg_iterations
        newton_its += i_f.iterations
        assert float((reused.x - fresh.x).abs().max()) <= 2 * max(i_f.tolerance, i_r.tolerance) * dt**2 / m_min
        state = fresh
    assert cg > 0 and newton_its >= 16  # the landing: several Newton iterations per step


def test_static_solve_with_reused_factorisations():
    model, rest, _ = cantilever(8, 3)
    x_f, i_f = solve_static(model, rest, linear_solver=tb.LinearSolver(reuse_factorization=False))
    x_r, i_r = solve_static(model, rest, linear_solver=tb.LinearSolver(reuse_factorization=True))
    assert i_f.converged and i_r.converged and i_r.cg_iterations > 0
    scale = float((x_f - rest).abs().max())
    assert float((x_r - x_f).abs().max()) <= 1e-6 * scale


def test_single_precision_factorisation_is_a_preconditioner():
    """SymmetricFactor(single=True): the same inertia, solutions accurate to about cond(A) times float32's
    eps (not float64's), and as CG's preconditioner the float64 solution in two or three iterations."""
    n = 80
    A = sparse_symmetric(n, np.linspace(1.0, 100.0, n), seed=7)
    b = np.random.default_rng(8).standard_normal(n)
    f32 = pardiso.SymmetricFactor(A.indptr, A.indices, single=True)
    assert f32.single and f32.factor(A.data) and f32.positive_definite and f32.inertia == (n, 0)
    x = f32.solve(b)
    assert x.dtype == np.float64
    w = np.linalg.eigvalsh(A.toarray())
    cond = w[-1] / w[0]
    err = np.linalg.norm(A @ x - b) / np.linalg.norm(b)
    assert 1e-12 < err <= 10 * cond * np.finfo(np.float32).eps  # float32's accuracy, not float64's
    p, its = linear.reused_factor_solve(A, b, f32, tol=1e-12, maxiter=10)
    assert p is not None and its <= 4
    assert np.linalg.norm(A @ p - b) <= 1e-12 * np.linalg.norm(b)
    B = sparse_symmetric(n, np.linspace(-3.0, 100.0, n), seed=7)
    assert f32.factor(B.data) and not f32.positive_definite
    assert f32.inertia[1] == int((np.linalg.eigvalsh(B.toarray()) < 0).sum())
