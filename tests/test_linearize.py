"""ClothModel.linearize: the Hessian assembled once as an operator: its products equal the matrix-free HVPs, it
takes tensors and arrays, and a CG Newton written on it by a user reaches solve_static's equilibrium."""
import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch

import torchbend as tb

from .helpers import cantilever, rel

F64 = torch.float64


@pytest.fixture(scope="module")
def beam():
    model, rest, _ = cantilever(11, 3, young=1e6, t=1e-3)
    gen = torch.Generator().manual_seed(3)
    x = rest + 1e-3 * torch.randn(rest.shape, generator=gen, dtype=F64)
    x[model.pinned] = rest[model.pinned]
    return model, rest, x


@pytest.mark.parametrize("projection", ["exact", "clamp", "gauss_newton"])
def test_products_equal_the_matrix_free_hvps(beam, projection):
    model, _, x = beam
    op = model.linearize(x, projection)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    ref = model.hvp(x, v, projection)
    assert rel(op @ v, ref) <= 1e-12
    flat = op @ v.reshape(-1)
    assert flat.shape == (v.numel(),) and rel(flat.reshape(-1, 3), ref) <= 1e-12
    arr = op.matvec(v.reshape(-1).numpy())
    assert isinstance(arr, np.ndarray) and np.allclose(arr, ref.reshape(-1).numpy(), rtol=0, atol=1e-12 * float(ref.norm()))
    v32 = v.float()
    assert (op @ v32).dtype == torch.float32
    with pytest.raises(ValueError, match="v must have shape"):
        _ = op @ v[:3]
    # the free block is the matrix the solvers use: no pinned DOF in it, symmetric
    free = op.free
    n_free = 3 * int((~model.pinned).sum())
    assert free.shape == (n_free, n_free) and abs(free - free.T).max() <= 1e-12 * abs(free).max()


def test_a_users_cg_newton_on_it_reaches_solve_statics_equilibrium(beam):
    """A plain Newton loop a user writes: linearise (clamped, PSD), SciPy CG on the free DOFs, a backtracking
    line search; it stops at solve_static's equilibrium within 1e-6 of the displacement."""
    model, rest, _ = beam
    x_ref, info = tb.solve_static(model, rest)
    assert info.converged
    x = rest.clone()
    free = ~model.pinned
    for _ in range(100):
        g = model.gradient(x)[free].reshape(-1).numpy()
        if np.linalg.norm(g) <= 1e-10 * float(model.external_force(F64).norm()):
            break
        op = model.linearize(x, "clamp")
        p, _ = spla.cg(op.as_linear_operator(free=True), -g, rtol=1e-10, maxiter=2000)
        step = torch.zeros_like(x)
        step[free] = torch.as_tensor(p).reshape(-1, 3)
        e0, alpha = model.potential(x), 1.0
        while model.potential(x + alpha * step) > e0 + 1e-4 * alpha * float(g @ p) and alpha > 1e-8:
            alpha *= 0.5
        x = x + alpha * step
    assert rel(x - rest, x_ref - rest) <= 1e-6


def test_a_damped_cg_newton_on_it_takes_solve_statics_iterations(beam):
    """The damped Newton a user writes on linearize (benchmarks/bm_linearize.py: the exact Hessian with a
    Levenberg-Marquardt shift, SciPy CG, the step bound, Armijo) reaches solve_static's equilibrium in at most
    twice its Newton iterations: the operator loses nothing against the solver's own assembly."""
    import scipy.sparse as sp

    model, rest, _ = beam
    x_ref, info = tb.solve_static(model, rest)
    assert info.converged
    x, free = rest.clone(), ~model.pinned
    scale = float(model.external_force(F64).norm())
    lam, e, its = 0.0, float(model.potential(x)), 0
    while its < 100:
        g = model.gradient(x)[free].reshape(-1).numpy()
        if np.linalg.norm(g) <= 1e-10 * scale:
            break
        A = model.linearize(x, "exact").free
        floor = 1e-8 * float(abs(A.diagonal()).max())
        while True:
            M = A + lam * sp.identity(A.shape[0], format="csr") if lam else A
            p, _ = spla.cg(M, -g, rtol=1e-10, maxiter=2000)
            step = torch.zeros_like(x)
            step[free] = torch.as_tensor(p).reshape(-1, 3)
            alpha = min(1.0, model.max_step(x, step))
            e1 = float(model.potential(x + alpha * step))
            if float(g @ p) < 0 and e1 <= e + 1e-4 * alpha * float(g @ p):
                x, e, lam = x + alpha * step, e1, (lam / 10 if lam > floor else 0.0)
                break
            lam = max(10 * lam, floor)
        its += 1
    assert its <= 2 * info.iterations
    assert rel(x - rest, x_ref - rest) <= 1e-6


@pytest.mark.parametrize("kind", ["auto", "ilu", "amg", "block_jacobi"])
def test_preconditioner_is_spd_and_cuts_cg_iterations(beam, kind):
    """op.preconditioner(kind): symmetric and positive definite on random vectors (also where the exact Hessian is
    indefinite), and CG with it reaches the same solution in fewer iterations than without; block-Jacobi is the
    inverse of the 3x3 diagonal blocks (|eigenvalues|)."""
    if kind == "amg":
        pytest.importorskip("pyamg")
    model, _, x = beam
    op = model.linearize(x, "clamp")
    A, M = op.free, op.preconditioner(kind)
    gen = np.random.default_rng(0)
    u, w = gen.standard_normal(A.shape[0]), gen.standard_normal(A.shape[0])
    Mu, Mw = M @ u, M @ w
    assert abs(float(Mu @ w) - float(u @ Mw)) <= 1e-8 * float(np.linalg.norm(Mu) * np.linalg.norm(w))
    assert float(u @ Mu) > 0 and float(w @ Mw) > 0
    assert (M @ u[:, None]).shape == (A.shape[0], 1)
    b = A @ gen.standard_normal(A.shape[0])
    counts = {}
    for name, pre in (("none", None), ("with", M)):
        n = [0]
        sol, status = spla.cg(A, b, rtol=1e-10, maxiter=5000, M=pre, callback=lambda _, n=n: n.__setitem__(0, n[0] + 1))
        assert status == 0 and np.linalg.norm(A @ sol - b) <= 1e-9 * np.linalg.norm(b)
        counts[name] = n[0]
    assert counts["with"] < counts["none"]
    if kind == "block_jacobi":
        blk = A[:3, :3].toarray()
        lam, Q = np.linalg.eigh(blk)
        r = gen.standard_normal(A.shape[0])
        assert np.allclose((M @ r)[:3], Q @ ((Q.T @ r[:3]) / np.abs(lam)), rtol=1e-10, atol=0)
    Mi = op.preconditioner(kind, free=False)
    assert Mi.shape == op.shape
