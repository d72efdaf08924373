"""Linear solves of the Newton directions (torchbend/sim/linear.py): against dense NumPy solves, the
Cholesky / LU choice and the inertia they report, truncated CG on indefinite matrices, the assembled free
Hessian against ClothModel.hessian, and the CG path's device-following (no host round trip per iteration)."""
import os
import warnings

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from torch.overrides import TorchFunctionMode

from torchbend import ClothModel, ClothState, Sphere, implicit_euler_step, solve_static
from torchbend.options import Projection
from torchbend.scenes.config import build_scene, load_config
from torchbend.sim import linear, newton
from torchbend.sim.terms import InertiaTerm, StepContext

from .helpers import CONFIGS, DIRECT_METHOD, DevicelessFactories, cantilever, requires_gpu

F64 = torch.float64
requires_cholespy = pytest.mark.skipif(not linear.has_cholespy(), reason="cholespy not installed")


def random_symmetric(n, eigenvalues, seed=0):
    """A symmetric ``(n, n)`` matrix (``scipy.sparse`` CSR, dense pattern) with the given eigenvalues, so
    that its inertia and condition are known."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = (Q * np.asarray(eigenvalues, dtype=float)) @ Q.T
    return sp.csr_matrix(0.5 * (A + A.T))


def inertia(A):
    lam = np.linalg.eigvalsh(A.toarray())
    return int((lam < 0).sum())


# -------------------------------------------------------------------- direct solves
@pytest.mark.parametrize("cholesky", [False, pytest.param(True, marks=requires_cholespy)])
def test_direct_solve_positive_definite_matches_dense(cholesky):
    n = 30
    A = random_symmetric(n, np.geomspace(1e-3, 1e3, n), seed=1)
    b = np.random.default_rng(2).standard_normal(n)
    res = linear.direct_solve(A, b, cholesky=cholesky)
    ref = np.linalg.solve(A.toarray(), b)
    assert res.shifts == 0 and res.positive_definite is True
    assert res.method == ("cholesky" if cholesky else "lu")
    assert np.linalg.norm(res.p - ref) <= 1e-10 * np.linalg.norm(ref)


@pytest.mark.parametrize("cholesky", [False, pytest.param(True, marks=requires_cholespy)])
def test_direct_solve_indefinite_falls_back_to_lu_and_shifts(cholesky):
    n = 24
    lam = np.r_[-2.0, -0.5, np.linspace(1.0, 10.0, n - 2)]
    A = random_symmetric(n, lam, seed=3)
    assert inertia(A) == 2
    rng = np.random.default_rng(4)
    ref_solve = lambda M, b: np.linalg.solve(M.toarray() if sp.issparse(M) else M, b)
    descent = non_descent = 0
    for _ in range(20):
        b = rng.standard_normal(n)
        res = linear.direct_solve(A, b, cholesky=cholesky)
        assert res.positive_definite is False and res.method == "lu"  # the Cholesky (if asked) failed
        assert float(b @ res.p) > 0  # always a descent direction for the gradient -b
        if res.shifts == 0:  # the indefinite Newton direction happened to be a descent direction: kept
            descent += 1
            ref = ref_solve(A, b)
        else:  # the Levenberg-shifted system, mu = 1e-8 max|diag| 10^(shifts - 1)
            non_descent += 1
            mu = 1e-8 * float(abs(A.diagonal()).max()) * 10.0 ** (res.shifts - 1)
            ref = ref_solve(A.toarray() + mu * np.eye(n), b)
        assert np.linalg.norm(res.p - ref) <= 1e-8 * np.linalg.norm(ref)
    assert descent and non_descent  # both branches were exercised


def test_direct_solve_stops_at_an_indefinite_matrix_when_asked():
    """``indefinite_stop=True`` (a time step that takes the clamped Hessian's direction instead): the first,
    unshifted solution comes back with ``positive_definite=False`` and no shifted retries, descent or not;
    a positive definite matrix is solved as without it."""
    n = 24
    A = random_symmetric(n, np.r_[-2.0, -0.5, np.linspace(1.0, 10.0, n - 2)], seed=3)
    rng = np.random.default_rng(4)
    retried = 0
    for _ in range(10):
        b = rng.standard_normal(n)
        retried += linear.direct_solve(A, b).shifts > 0
        res = linear.direct_solve(A, b, indefinite_stop=True)
        assert res.positive_definite is False and res.shifts == 0
        np.testing.assert_allclose(res.p, np.linalg.solve(A.toarray(), b), rtol=1e-8)
    assert retried  # without it, some of these were retried with shifts
    P = random_symmetric(n, np.linspace(1.0, 10.0, n), seed=5)
    b = rng.standard_normal(n)
    res = linear.direct_solve(P, b, indefinite_stop=True)
    assert res.positive_definite is True and res.shifts == 0
    np.testing.assert_allclose(res.p, np.linalg.solve(P.toarray(), b), rtol=1e-10)


def test_lu_inertia_flag_matches_eigenvalues():
    rng = np.random.default_rng(5)
    for seed in range(12):
        n = 20
        negatives = seed % 4  # 0 (PD), 1, 2, 3 negative eigenvalues
        lam = np.r_[-rng.uniform(0.1, 5, negatives), rng.uniform(0.1, 5, n - negatives)]
        A = random_symmetric(n, lam, seed=seed)
        b = rng.standard_normal(n)
        p, definite = linear.lu_solve(A, b)
        assert p is not None and np.linalg.norm(A @ p - b) <= 1e-10 * np.linalg.norm(b) * np.linalg.cond(A.toarray())
        assert definite is (negatives == 0)


def test_singular_matrix_gets_a_shift_or_steepest_descent():
    A = sp.csr_matrix(np.diag([1.0, 2.0, 0.0]))
    b = np.array([1.0, 1.0, 1.0])
    res = linear.direct_solve(A, b)
    assert res.shifts >= 1 and res.positive_definite is False and float(b @ res.p) > 0
    zero = linear.direct_solve(sp.csr_matrix((3, 3)), b)  # a zero matrix: the shift 1e-8 (unit scale)
    assert zero.shifts == 1 and np.allclose(zero.p, b / 1e-8, rtol=1e-12)
    zero = linear.direct_solve(sp.csr_matrix((3, 3)), b, max_shifts=1)  # no shift allowed: steepest descent
    assert zero.method == "steepest" and np.array_equal(zero.p, b)


@requires_cholespy
def test_cholesky_failure_prints_nothing(capfd):
    A = sp.csr_matrix(np.diag([1.0, -1.0, 2.0]))
    assert linear.cholesky_solve(A, np.ones(3)) is None
    out, err = capfd.readouterr()
    assert "positive definite" not in out + err


# -------------------------------------------------------------------- CG
def spd_problem(n=60, seed=0, cond=1e4):
    A = random_symmetric(n, np.geomspace(1.0, cond, n), seed=seed)
    b = np.random.default_rng(seed + 1).standard_normal(n)
    return A, b


def torch_csr(A):
    A = sp.csr_matrix(A)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(torch.as_tensor(A.indptr, dtype=torch.int64),
                                       torch.as_tensor(A.indices, dtype=torch.int64),
                                       torch.as_tensor(A.data, dtype=F64), size=A.shape, check_invariants=True)


@pytest.mark.parametrize("kind", ["none", "block_jacobi", "ilu", "amg"])
def test_pcg_matches_dense_solve(kind):
    if kind == "amg" and not linear.has_pyamg():
        pytest.skip("pyamg not installed")
    A, b = spd_problem()
    At, bt = torch_csr(A), torch.as_tensor(b)
    if kind == "none":
        M = lambda r: r
    elif kind == "block_jacobi":
        Ad = A.toarray()
        blocks = torch.as_tensor(np.stack([Ad[i:i + 3, i:i + 3] for i in range(0, Ad.shape[0], 3)]))
        M = linear.block_jacobi(blocks)
    elif kind == "ilu":
        M = linear.ilu(A, bt)
    else:
        M = linear.amg(A, bt)
    assert M is not None
    res = linear.pcg(lambda d: At @ d, bt, M, tol=1e-12, maxiter=1000)
    ref = np.linalg.solve(A.toarray(), b)
    assert res.converged and res.negative_curvature is None
    assert np.linalg.norm(res.x.numpy() - ref) <= 1e-8 * np.linalg.norm(ref)
    if kind == "ilu":
        assert res.iterations <= 5  # the incomplete factor is nearly exact here


def thin_stiff_strip(pattern: str = "one_way"):
    """A 16 x 4 cantilever strip, 0.2 x 0.05 m, Y t = 1e5 N/m, t = 1e-4 m (membrane stiffness 1e8 times
    the bending's: the solver sweep's worst conditioning), every quad split along one diagonal."""
    import torchbend as tb

    nx, ny, t, young = 16, 4, 1e-4, 1e9
    rest, faces = tb.scenes.grid(nx, ny, (0.2, 0.05), dtype=F64)
    if pattern == "one_way":
        i, j = torch.meshgrid(torch.arange(nx - 1), torch.arange(ny - 1), indexing="ij")
        a = (i + nx * j).reshape(-1)
        faces = torch.cat((torch.stack((a, a + 1, a + nx + 1), -1), torch.stack((a, a + nx + 1, a + nx), -1)))
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=tb.stiffness_from_material(young, t, 0.3))
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=young, poisson=0.3, thickness=t)
    pinned = rest[:, 0] <= rest[:, 0].unique()[1] + 1e-12
    return ClothModel(faces, rest, bending=bend, membrane=mem, density=0.1, gravity=(0, 0, -9.81), pinned=pinned), rest


def test_ilu_preconditioner_is_symmetric_positive_definite_on_a_thin_stiff_sheet():
    """The incomplete factorisation CG uses is ``L |D| L^T``: symmetric and positive definite.  The incomplete
    LU's own ``U^-1 L^-1`` is not symmetric on this Hessian (condition ~1e8; entries dropped), and CG with it
    did not converge in 2,000 iterations; with ``L |D| L^T`` it converges in a few."""
    model, rest = thin_stiff_strip()
    x = rest.clone()
    x[:, 2] -= 0.02 * (rest[:, 0] / 0.2) ** 2  # a sagging strip
    phi = newton._Potential(model, x, Projection.GAUSS_NEWTON)
    A = phi.free_hessian(x)
    As = sp.csr_matrix(phi.hessian_op.to_scipy(A))
    n = As.get_shape()[0]
    M = linear.ilu(As, A.values())
    assert M is not None
    Minv = torch.stack([M(e) for e in torch.eye(n, dtype=F64)], 1)
    assert float((Minv - Minv.T).abs().max()) <= 1e-12 * float(Minv.abs().max())
    assert float(torch.linalg.eigvalsh(0.5 * (Minv + Minv.T))[0]) > 0
    b = torch.as_tensor(np.random.default_rng(0).standard_normal(n))
    res = linear.pcg(lambda d: A @ d, b, M, tol=1e-8, maxiter=2000)
    ref = np.linalg.solve(As.toarray(), b.numpy())
    assert res.converged and res.iterations <= 50
    assert np.linalg.norm(res.x.numpy() - ref) <= 1e-6 * np.linalg.norm(ref)


@pytest.mark.parametrize("hessian,pattern", [("gauss_newton", "one_way"), ("exact", "criss")])
def test_thin_stiff_strip_converges_alike_from_starts_a_few_ulps_apart(hessian, pattern):
    """Whether the solve converges must not hang on the last bits of the start (or of a kernel's rounding:
    another CPU's vector width or FMA contraction): from rest positions scaled by ``1 + k 4e-16`` every
    start converges to the same equilibrium in a bounded number of iterations (with the nonsymmetric
    incomplete-LU preconditioner two of eight such starts of the one-way strip ran 2,100 iterations and
    failed)."""
    model, rest = thin_stiff_strip(pattern)
    xs = []
    for k in range(4):
        x, info = solve_static(model, rest * (1 + k * 4e-16), projection=hessian, linear_solver="cg")
        assert info.converged, f"start {k}: {info.message}"
        assert info.iterations <= 300, f"start {k}: {info.iterations} Newton iterations"
        xs.append(x)
    span = float((xs[0] - rest).norm())
    assert span > 1e-3
    assert max(float((x - xs[0]).norm()) for x in xs) <= 1e-6 * span


def test_truncated_pcg_returns_descent_directions_on_indefinite_matrices():
    n = 42
    lam = np.r_[-3.0, -1.0, np.geomspace(0.1, 100.0, n - 2)]
    A = random_symmetric(n, lam, seed=7)
    At = torch_csr(A)
    Ad = A.toarray()
    blocks = torch.as_tensor(np.stack([Ad[i:i + 3, i:i + 3] for i in range(0, n, 3)]))
    preconds = [lambda r: r, linear.block_jacobi(blocks)]  # SPD: block eigenvalues in absolute value
    rng = np.random.default_rng(8)
    truncated = 0
    for M in preconds:
        for trial in range(10):
            b = torch.as_tensor(rng.standard_normal(n))
            for maxiter in (1, 3, 10, 200):
                res = linear.pcg(lambda d: At @ d, b, M, tol=1e-12, maxiter=maxiter)
                assert float(b @ res.x) > 0, (trial, maxiter)  # a descent direction for the gradient -b
                if res.negative_curvature is not None:
                    truncated += 1
                    d = res.negative_curvature.numpy()
                    assert d @ Ad @ d <= 0
                assert res.iterations <= maxiter
    assert truncated > 0


def test_pcg_reports_a_breakdown_of_an_indefinite_preconditioner():
    """A preconditioner that is not positive definite stops CG at ``r . M r <= 0``: flagged as a breakdown
    (not convergence, not negative curvature of A); an SPD one never breaks down."""
    n = 30
    A = random_symmetric(n, np.geomspace(1.0, 1e3, n), seed=3)
    At, b = torch_csr(A), torch.as_tensor(np.random.default_rng(4).standard_normal(n))
    flip = torch.ones(n, dtype=F64)
    flip[::2] = -1.0  # an indefinite diagonal preconditioner
    for M, broken in ((lambda r: flip * r, True), (lambda r: -r, True), (lambda r: r, False)):
        res = linear.pcg(lambda d: At @ d, b, M, tol=1e-12, maxiter=200)
        assert res.breakdown is broken
        if broken:
            assert not res.converged and res.negative_curvature is None
        else:
            assert res.converged
    zero = linear.pcg(lambda d: At @ d, torch.zeros(n, dtype=F64), lambda r: r, tol=1e-12, maxiter=10)
    assert zero.converged and not zero.breakdown


def test_cg_direction_retries_block_jacobi_after_a_breakdown(monkeypatch):
    """When the incomplete factorisation is not positive definite (a breakdown of its CG), the Newton
    direction comes from block-Jacobi CG and matches the direct one."""
    model, rest, _ = cantilever(6, 3)
    x = rest + 1e-3 * torch.randn_like(rest) * (~model.pinned)[:, None]
    phi = newton._Potential(model, x, Projection.CLAMP)
    gf = phi.free_gradient(x)
    p_direct, _ = phi.direct_direction(x, gf)
    A, b = phi.free_hessian(x), -torch.as_tensor(gf)
    bj = linear.block_jacobi(phi.hessian_op.diagonal_blocks(A))
    u = torch.zeros(len(gf), dtype=F64)
    u[9] = 1.0

    def indefinite(r):  # block-Jacobi with one eigenvalue flipped negative
        return bj(r) - 3.0 * (u @ r) * (bj(u) @ u) * u

    broken = linear.pcg(lambda d: A @ d, b, indefinite, tol=1e-12, maxiter=200)
    assert broken.breakdown and float(b @ broken.x) > 0  # a descent direction, but a poor one
    assert np.linalg.norm(broken.x.numpy() - p_direct) > 1e-2 * np.linalg.norm(p_direct)
    monkeypatch.setattr(linear, "ilu", lambda A, like, **kw: indefinite)
    phi.linear = newton.LinearSolver("cg", preconditioner="ilu")
    p_cg, _ = phi.cg_direction(x, gf, relative_residual=0.0)
    assert phi.linear_method == "cg/block_jacobi"
    assert np.linalg.norm(p_cg - p_direct) <= 1e-6 * np.linalg.norm(p_direct)


def test_pcg_device_checks_every_few_iterations_give_the_same_result():
    A, b = spd_problem(cond=1e3)
    At, bt = torch_csr(A), torch.as_tensor(b)
    one = linear.pcg(lambda d: At @ d, bt, lambda r: r, tol=1e-10, maxiter=500, check_every=1)
    eight = linear.pcg(lambda d: At @ d, bt, lambda r: r, tol=1e-10, maxiter=500, check_every=8)
    assert one.converged and eight.converged and one.iterations == eight.iterations
    assert torch.equal(one.x, eight.x)  # iterations past the stop change nothing


def test_cg_iteration_bound():
    assert linear.cg_iteration_bound(10) == 20  # 2n for small systems
    assert linear.cg_iteration_bound(5043) == int(20 * np.sqrt(5043))
    assert linear.cg_iteration_bound(5043, 7) == 7 and linear.cg_iteration_bound(10, 0) == 1


# -------------------------------------------------------------------- the assembled free Hessian
def drape_model(n=7):
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    scene, x0, faces = build_scene(cfg, resolution=(n, n))
    sphere = scene.colliders[0]  # with a penalty, so that vertices moved into the sphere give collider blocks
    model = ClothModel(faces, x0, bending=scene.bending, membrane=scene.membrane, pinned=[0, n - 1],
                       colliders=[Sphere(sphere.center, sphere.radius, law="penalty", margin=0.01)])
    return model, x0


@pytest.mark.parametrize("option", [Projection.NONE, Projection.CLAMP, Projection.GAUSS_NEWTON])
def test_free_hessian_matches_model_hessian(option):
    model, x0 = drape_model()
    x = x0 + 0.05 * torch.randn_like(x0)
    x[:, 2] -= 0.05  # some vertices inside the sphere's margin: collider blocks
    assert float(model.colliders[0].depth(x).max()) > 0
    free = (~model.pinned).repeat_interleave(3)
    assert model.bending is not None
    dt = 0.01
    ctx = StepContext.for_step(model.terms, x0, 0.1 * torch.randn_like(x0), dt)  # lagged angles, inertia
    terms = model.terms + (InertiaTerm(model.mass),)
    fh = linear.FreeHessian(model, free)
    A = fh.assemble(x, terms, ctx, option)
    assert A.layout == torch.sparse_csr and A.device == x.device and A.dtype == x.dtype
    w = (model.mass / dt**2).repeat_interleave(3)
    ref = model.hessian(x, option, ctx) + sp.diags(w.numpy())
    ref = ref.tocsr()[free.numpy()][:, free.numpy()].toarray()
    got = fh.to_scipy(A).toarray()
    assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max()
    assert np.array_equal(got, got.T) or np.abs(got - got.T).max() <= 1e-12 * np.abs(ref).max()
    # the diagonal blocks for block-Jacobi
    blocks = fh.diagonal_blocks(A).numpy()
    assert np.array_equal(blocks[1], got[3:6, 3:6])
    # the pattern is kept: a second assembly at another state scatters into it
    A2 = fh.assemble(x0, model.terms, ctx, option)
    ref2 = model.hessian(x0, option, ctx).tocsr()[free.numpy()][:, free.numpy()].toarray()
    assert np.abs(fh.to_scipy(A2).toarray() - ref2).max() <= 1e-12 * np.abs(ref2).max()


class _PairsTerm:
    """A term whose Hessian is the sum of given 2x2 vertex-pair couplings (a stand-in for contact pairs whose set
    changes from one iterate to the next)."""

    def __init__(self, V):
        self.V, self.pairs = V, []

    def vertex_blocks(self, x, ctx, option):
        return None

    def hessian(self, x, ctx, option):
        n = 3 * self.V
        H = torch.zeros(n, n, dtype=x.dtype)
        for a, b, w in self.pairs:
            for i in (3 * a, 3 * a + 1, 3 * a + 2):
                for j in (3 * b, 3 * b + 1, 3 * b + 2):
                    H[i, j] += w
                    H[j, i] += w
        return H.to_sparse_csr()


def test_free_hessian_keeps_its_pattern_while_the_contact_pairs_change():
    """A term whose pattern changes (the contact pairs of a new iterate), in a solve (``begin_solve``): entries
    already in the pattern are placed in it (the pattern object, and a PARDISO factorisation bound to it, serve on),
    new ones grow it with the old entries kept, a pattern mostly of old entries is rebuilt from the terms' own, and
    a new solve starts from the terms' own; outside a solve the pattern is the terms' own every time.  The values
    are the sum's every time."""
    V = 12
    x = torch.zeros(V, 3, dtype=F64)

    class Owner:  # FreeHessian holds its model weakly
        pass

    owner = Owner()
    free = torch.ones(3 * V, dtype=torch.bool)
    free[:3] = False  # vertex 0 pinned: its entries are left out
    diag, a, b = _PairsTerm(V), _PairsTerm(V), _PairsTerm(V)
    diag.pairs = [(v, v, 1.0) for v in range(V)]
    terms = [diag, a, b]

    def assemble(fh):
        A = fh.assemble(x, terms, None, Projection.NONE)
        ref = torch.stack([t.hessian(x, None, None).to_dense() for t in terms]).sum(0)[free][:, free].numpy()
        assert np.array_equal(fh.to_scipy(A).toarray(), ref)
        assert fh._pattern is not None
        return fh._pattern

    def exact(pat):
        return pat.used == pat.nnz

    # outside a solve (ClothModel.hessian's): the terms' own pattern after every change
    plain = linear.FreeHessian(owner, free)
    a.pairs = [(0, 5, 1.0), (1, 2, 2.0), (3, 4, 3.0), (6, 7, 4.0)]
    first = assemble(plain)
    a.pairs = [(1, 2, 5.0)]
    assert assemble(plain) is not first and exact(plain._pattern)

    fh = linear.FreeHessian(owner, free)
    fh.begin_solve()
    a.pairs = [(0, 5, 1.0), (1, 2, 2.0), (3, 4, 3.0), (6, 7, 4.0)]
    first = assemble(fh)
    factor = fh.direct_factor()
    assert factor is not None or not linear.pardiso.available()
    a.pairs = [(1, 2, 5.0), (6, 7, 6.0)]  # fewer pairs, all in the pattern: the same pattern, zeros kept
    assert assemble(fh) is first and not exact(first) and fh.direct_factor() is factor
    a.pairs = [(1, 2, 5.0), (8, 9, 7.0)]  # a new pair: a new pattern with the old entries kept
    grown = assemble(fh)
    assert grown is not first and not exact(grown)
    a.pairs = [(3, 4, 1.0), (6, 7, 2.0)]  # old pairs again: placed in the grown pattern
    assert assemble(fh) is grown
    a.pairs = [(10, 11, 1.0)]  # the old entries would be more than a third: the terms' own pattern
    assert exact(assemble(fh))
    # two terms changing at once, the first placed, the second not: a grown pattern, the sums right
    a.pairs, b.pairs = [], [(1, 2, 1.0)]
    assert not exact(assemble(fh))
    a.pairs, b.pairs = [(1, 2, 3.0)], []
    assemble(fh)
    # a new solve starts from the terms' own pattern; an exact one stays (with its factorisation)
    kept = fh._pattern
    assert not exact(kept)
    fh.begin_solve()
    own = assemble(fh)
    assert exact(own) and own is not kept and own.nnz == linear._Pattern(fh._free, [], own.device).nnz + 9 * 2
    factor = fh.direct_factor()
    fh.begin_solve()
    assert assemble(fh) is own and fh.direct_factor() is factor
    # an exception part way leaves no pattern behind that disagrees with the recorded term patterns
    a.pairs, b.pairs = [(3, 4, 1.0)], [(5, 6, 1.0)]
    assemble(fh)
    a.pairs, b.pairs = [(5, 6, 2.0)], [(7, 8, 1.0)]
    with pytest.MonkeyPatch.context() as mp:
        def fail(*args, **kwargs):
            raise MemoryError("test")
        mp.setattr(linear, "_Pattern", fail)
        with pytest.raises(MemoryError):
            fh.assemble(x, terms, None, Projection.NONE)
    a.pairs, b.pairs = [(3, 4, 1.0)], [(5, 6, 1.0)]
    assemble(fh)  # the values checked against the dense sum


def test_cg_direction_matches_direct_direction():
    model, rest, _ = cantilever(6, 3)
    x = rest + 1e-3 * torch.randn_like(rest) * (~model.pinned)[:, None]
    for option in (Projection.CLAMP, Projection.NONE):
        phi = newton._Potential(model, x, option)
        gf = phi.free_gradient(x)
        p_direct, shifts = phi.direct_direction(x, gf)
        assert shifts == 0 and phi.positive_definite is True and phi.linear_method == DIRECT_METHOD
        for pre in ("auto", "block_jacobi", "ilu"):
            phi.linear = newton.LinearSolver("cg", preconditioner=pre)
            p_cg, its = phi.cg_direction(x, gf, relative_residual=0.0)  # the tightest forcing term
            assert its >= 1 and phi.linear_method.startswith("cg/")
            assert np.linalg.norm(p_cg - p_direct) <= 1e-6 * np.linalg.norm(p_direct), (option, pre)
        phi = newton._Potential(model, x, option, linear=newton.LinearSolver("cg", "block_jacobi", max_cg_iters=2))
        p2, its = phi.cg_direction(x, gf, relative_residual=0.0)
        assert its <= 2 and float(gf @ p2) < 0  # truncated, still a descent direction


def test_without_the_optional_back_ends(monkeypatch):
    """Without cholespy the Cholesky request falls back to the LU; without pyamg "amg" to block-Jacobi."""
    monkeypatch.setattr(linear, "_cholespy", None)
    monkeypatch.setattr(linear, "_pyamg", None)
    assert not linear.has_cholespy() and not linear.has_pyamg()
    A, b = spd_problem(n=30)
    res = linear.direct_solve(A, b, cholesky=True)
    assert res.method == "lu" and res.positive_definite is True
    assert np.linalg.norm(res.p - np.linalg.solve(A.toarray(), b)) <= 1e-10 * np.linalg.norm(res.p)
    assert linear.cholesky_solve(A, b) is None and linear.amg(A, torch.as_tensor(b)) is None
    model, rest, _ = cantilever(5, 3)
    phi = newton._Potential(model, rest, Projection.CLAMP)
    M, used = linear.make_preconditioner("amg", phi.free_hessian(rest), phi.hessian_op)
    assert used is linear.Preconditioner.BLOCK_JACOBI
    for solver in (newton.LinearSolver("cg", preconditioner="amg"), newton.LinearSolver("direct", cholesky=True)):
        x, info = solve_static(model, rest, linear_solver=solver, tol=1e-8)
        assert info.converged, (solver, info.message)


def test_unknown_preconditioner_is_a_value_error():
    model, rest, _ = cantilever(4, 3)
    phi = newton._Potential(model, rest, Projection.NONE)
    A = phi.free_hessian(rest)
    with pytest.raises(ValueError, match="preconditioner must be one of"):
        linear.make_preconditioner("jacobi", A, phi.hessian_op)
    partial = torch.ones(3 * model.vertex_count, dtype=torch.bool)
    partial[1] = False  # one coordinate of a vertex: the free DOFs must be whole vertices
    with pytest.raises(ValueError, match="free_mask must be a"):
        linear.FreeHessian(model, partial)


def test_linear_solver_options_object():
    """``tb.LinearSolver`` carries the linear-solve options into the solvers (no private attributes): the
    preconditioner and the CG bound it names are the ones used; bad fields are ValueErrors naming them."""
    import torchbend as tb

    assert tb.LinearSolver.parse("cg") == tb.LinearSolver("cg") and tb.LinearSolver().is_direct
    assert tb.LinearSolver.DIRECT is newton.LinearMethod.DIRECT
    cases: tuple[tuple[dict, str], ...] = (({"method": "qr"}, "linear_solver must be one of"),
                    ({"preconditioner": "jacobi"}, "preconditioner must be one of"),
                    ({"cholesky": "yes"}, "cholesky must be True or False"),
                    ({"max_cg_iters": 0}, "max_cg_iters must be an int >= 1"))
    for kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            tb.LinearSolver(**kw)
    model, rest, _ = cantilever(6, 3)
    _, info = tb.solve_static(model, rest, linear_solver=tb.LinearSolver("cg", preconditioner="block_jacobi",
                                                                       max_cg_iters=7), max_iters=3, continuation=False)
    directions = sum(info.linear_methods.values())
    assert set(info.linear_methods) == {"cg/block_jacobi"} and directions > 0
    assert 0 < info.cg_iterations <= 7 * directions


# -------------------------------------------------------------------- device-following
class HostTransfers(TorchFunctionMode):
    """Counts the calls that copy a tensor to the host or read a value from it."""

    NAMES = {"cpu", "numpy", "item", "tolist", "__bool__", "__float__", "__int__"}

    def __init__(self):
        super().__init__()
        self.counts: dict = {}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in self.NAMES:
            self.counts[name] = self.counts.get(name, 0) + 1
        return func(*args, **(kwargs or {}))


def test_cg_path_follows_the_device_and_reads_the_host_only_every_few_iterations():
    """The GPU code path (torch CG, assembled torch CSR operator, torch block-Jacobi) run on the CPU: no
    tensor factory without an explicit device, host copies independent of the CG iteration count, and
    the stopping test read once every ``check_every`` iterations."""
    model, rest, _ = cantilever(8, 3, young=1e9, t=1e-3)  # stiff: many block-Jacobi iterations
    x = rest + 1e-4 * torch.randn_like(rest) * (~model.pinned)[:, None]
    copies = {}
    for cap in (4, 16):
        phi = newton._Potential(model, x, Projection.CLAMP,
                                linear=newton.LinearSolver("cg", preconditioner="block_jacobi", max_cg_iters=cap))
        gf = phi.free_gradient(x)
        recorder, transfers = DevicelessFactories(), HostTransfers()
        with recorder:  # (one mode at a time: a nested mode would hide the calling frame)
            p, its = phi.cg_direction(x, gf, relative_residual=0.0)
        assert its == cap and recorder.seen > 0 and recorder.calls == [], recorder.calls
        with transfers:
            p2, _ = phi.cg_direction(x, gf, relative_residual=0.0)
        assert np.array_equal(p, p2)
        copies[cap] = {k: v for k, v in transfers.counts.items() if k not in ("__bool__",)}
    assert copies[4] == copies[16]  # no host copy per CG iteration
    A = phi.free_hessian(x)
    b = -torch.as_tensor(gf)
    M = linear.block_jacobi(phi.hessian_op.diagonal_blocks(A))
    transfers = HostTransfers()
    with transfers:
        res = linear.pcg(lambda d: A @ d, b, M, tol=1e-30, maxiter=64, check_every=8)
    assert res.iterations == 64
    assert transfers.counts.get("__bool__", 0) <= 64 // 8 + 3  # the device-side stopping test, read every 8
    # and whole solves through that path leave nothing on a default device
    recorder = DevicelessFactories()
    cg = newton.LinearSolver("cg", preconditioner="block_jacobi")
    with recorder:
        m5, r5, _ = cantilever(5, 3)
        x5, info = solve_static(m5, r5, linear_solver=cg, tol=1e-8)
        assert info.converged, info.message
        scene, x0 = drape_model(5)
        state, info = implicit_euler_step(scene, ClothState(x0, torch.zeros_like(x0)), 0.01, linear_solver=cg)
        assert info.converged, info.message
    assert recorder.seen > 0 and recorder.calls == [], recorder.calls


@pytest.mark.gpu
@requires_gpu
@pytest.mark.parametrize("hessian", ["exact", "clamp"])
def test_cg_solve_on_cuda_matches_cpu(hessian):
    model, rest, _ = cantilever(11, 3)
    x_cpu, info_cpu = solve_static(model, rest, projection=hessian, linear_solver="cg", tol=1e-9)
    dev = torch.device("cuda")
    bend, mem = model.bending, model.membrane
    assert bend is not None and mem is not None
    gpu = ClothModel(model.topology.faces, rest.to(dev), bending=bend.to(dev), membrane=mem.to(dev),
                     density=model.density, pinned=model.pinned.to(dev))
    x_gpu, info_gpu = solve_static(gpu, rest.to(dev), projection=hessian, linear_solver="cg", tol=1e-9)
    assert info_cpu.converged and info_gpu.converged, (info_cpu.message, info_gpu.message)
    assert x_gpu.device.type == "cuda"
    assert float((x_gpu.cpu() - x_cpu).norm() / (x_cpu - rest).norm()) <= 1e-7
