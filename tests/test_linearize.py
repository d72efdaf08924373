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
