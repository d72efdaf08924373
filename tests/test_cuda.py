"""The CUDA driver: with a GPU (``-m gpu``) every CUDA operation is compared with the eager reference on the
same device.  That it builds, links, imports and registers every kernel (CI, no GPU): tests/test_build.py."""
from typing import Any

import pytest
import torch

import torchbend as tb
from torchbend.backends import cuda

from .helpers import MODELS, requires_gpu, round_off, second_order_case

# The CI check that the CUDA part builds, links, imports and registers every kernel (no GPU needed) is
# tests/test_build.py::test_cuda_module_builds_imports_and_registers_every_kernel.


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.gpu
@requires_gpu
def test_cuda_ops_match_eager(dtype, model, damped):
    dev = torch.device("cuda")
    gen = torch.Generator().manual_seed(0)
    v, f = tb.scenes.grid(12, 9)
    rest = v.to(dtype)
    x = rest + 0.05 * torch.randn((3, *rest.shape), dtype=dtype, generator=gen)
    kw: dict = {"damping": 0.3} if damped else {}
    bend = tb.BendingEnergy(f, rest, model=model, stiffness=torch.rand(1, generator=gen).item() + 0.5,
                            **kw).to(dev)
    x, d = x.to(dev), torch.randn(x.shape, dtype=dtype, generator=gen).to(dev)
    ex = {"theta_prev": bend.angles(x) + 0.01, "dt": 0.1} if damped else {}
    p, _ = bend._bind(x, "eager", ex.get("theta_prev"), ex.get("dt"))
    tol = round_off(dtype)

    def close(a, r):
        assert float((a - r).norm()) <= tol * float(r.norm()) + 1e-30

    close(cuda.bending_energy(x, bend.hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model).sum(-1), bend(x, backend="eager", **ex))
    w = torch.ones(1, dtype=dtype, device=dev)
    gx, gp = cuda.bending_gradient(x, bend.hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model, w, None, True)
    close(gx, bend.gradient(x, backend="eager", **ex))
    psi, gx1, gp1 = cuda.bending_energy_gradient(x, bend.hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model, None, True)
    close(psi.sum(-1), bend(x, backend="eager", **ex))
    assert gp1 is not None and gp is not None and torch.equal(gp1, gp)  # per hinge: the same bits
    close(gx1, gx)  # atomic sums: the order may differ
    close(cuda.bending_hvp(x, d, bend.hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model, w), bend.hvp(x, d, backend="eager", **ex))
    Hb, g, d2 = cuda.bending_hessians(x, bend.hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model)
    close(Hb, bend.hinge_hessians(x, backend="eager", **ex))
    # parameter gradients against autograd of the eager energy in the stiffness and rest angles
    k = torch.full((bend.hinge_count,), float(bend.stiffness), dtype=dtype, device=dev, requires_grad=True)
    r = bend.rest_angles.detach().clone().requires_grad_()
    from torchbend.energies._bending_fn import bending_energy_raw

    E = bending_energy_raw(x, bend.hinges, bend.weights.to(dtype), k, r, p.c, p.prev, model=bend.model).sum()
    gk, gr = torch.autograd.grad(E, (k, r))
    assert gp is not None
    close(gp[..., 0].sum(0), gk)
    close(gp[..., 1].sum(0), gr)


@pytest.mark.gpu
@requires_gpu
def test_cuda_fold_raises():
    rest, faces = tb.scenes.single_hinge(0.0, dtype=torch.float64)
    x = rest.clone()
    x[3] = torch.tensor([0.3, 0.8, 0.0], dtype=torch.float64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1.0).cuda()
    p, _ = bend._bind(x.cuda(), "eager")
    with pytest.raises(ValueError, match="folded through"):
        cuda.bending_energy(x.cuda(), bend.hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model)


@pytest.mark.gpu
@requires_gpu
@pytest.mark.parametrize("model", ["tan", "quadratic"])
def test_cuda_default_path_matches_eager_through_autograd(model):
    """BendingEnergy on a CUDA tensor runs the kernels by default: energy, backward, double backward
    (autograd's HVP) and hvp() agree with the eager path; gradcheck/gradgradcheck pass through them."""
    v, f = tb.scenes.grid(6, 5)
    gen = torch.Generator().manual_seed(1)
    x = (v.double() + 0.05 * torch.randn(v.shape, dtype=torch.float64, generator=gen)).cuda()
    d = torch.randn(x.shape, dtype=torch.float64, generator=gen).cuda()
    bend = tb.BendingEnergy(f, v.double(), model=model, stiffness=1.0).cuda()
    assert tb.select_backend("energy", "auto", x) is tb.Backend.NATIVE

    def second(backend):
        y = x.clone().requires_grad_()
        (g,) = torch.autograd.grad(bend(y, backend=backend), y, create_graph=True)
        (hv,) = torch.autograd.grad(g, y, d)
        return g.detach(), hv

    g0, hv0 = second("auto")
    g1, hv1 = second("eager")
    assert torch.allclose(g0, g1, rtol=1e-12, atol=1e-14) and torch.allclose(hv0, hv1, rtol=1e-11, atol=1e-13)
    assert torch.allclose(bend.hvp(x, d), hv1, rtol=1e-11, atol=1e-13)
    y = x.clone().requires_grad_()
    # the CUDA scatter adds with atomics (summation order varies run to run): round-off nondeterminism
    assert torch.autograd.gradcheck(lambda z: bend(z), (y,), nondet_tol=1e-9)
    assert torch.autograd.gradgradcheck(lambda z: bend(z), (y,), nondet_tol=1e-9)


@pytest.mark.parametrize("per_hinge", [False, True])
@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.gpu
@requires_gpu
def test_cuda_second_order_matches_cpu(dtype, model, damped, per_hinge):
    """The CUDA general double backward against the CPU kernel (itself checked against torch.func and the
    eager double backward in tests/test_native_second_order.py): batched x, per-sample prev, per-hinge
    weights, directions in x and in (k, rest, c, prev), each of them absent in turn."""
    from torchbend.backends import native

    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")
    p = second_order_case(model, damped, dtype, per_hinge)
    inc = native.incidence(p["hinges"], p["V"])
    names = ("x", "hinges", "a", "k", "rest", "c", "prev", "v", "t", "w")
    q: dict[str, Any] = {n: (None if p[n] is None else p[n].cuda()) for n in names}
    tol = round_off(dtype)
    for use_v, use_t in ((True, True), (True, False), (False, True)):
        ref = native.bending_second_order(p["x"], p["v"] if use_v else None, p["t"] if use_t else None, p["hinges"],
                                          p["a"], p["k"], p["rest"], p["c"], p["prev"], model, p["w"], inc)
        got = cuda.bending_second_order(q["x"], q["v"] if use_v else None, q["t"] if use_t else None, q["hinges"],
                                        q["a"], q["k"], q["rest"], q["c"], q["prev"], model, q["w"])
        for g, r in zip(got, ref):
            assert g.device.type == "cuda" and g.dtype == dtype and g.shape == r.shape
            assert float((g.cpu() - r).norm()) <= tol * float(r.norm()) + 1e-30


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("model", ["stvk", "arap", "symmetric_dirichlet", "neohookean"])
@pytest.mark.gpu
@requires_gpu
def test_cuda_membrane_matches_the_cpu_kernels(model, dtype):
    """The membrane's CUDA kernels (membrane_math.h, one thread per triangle, atomic scatter) against the CPU
    kernels (checked against the eager reference in tests/test_membrane.py): energy, gradient, projected HVP and
    projected element Hessians of a batch, through MembraneEnergy (the default backend takes them on CUDA tensors)
    and through autograd (the energy's backward and double backward)."""
    rest, faces = tb.scenes.random_curved_sheet(9, 7, amplitude=0.3, seed=3, dtype=dtype)
    gen = torch.Generator().manual_seed(4)
    x = torch.stack((rest * 1.1, rest + 0.02 * torch.randn(rest.shape, generator=gen, dtype=dtype)))
    v = torch.randn(x.shape, generator=gen, dtype=dtype)
    mem = tb.MembraneEnergy(faces, rest, model=model, young=2e4, poisson=0.35, thickness=5e-4).to(dtype)
    gmem = tb.MembraneEnergy(faces, rest, model=model, young=2e4, poisson=0.35, thickness=5e-4).to(dtype).cuda()
    xc, vc = x.cuda(), v.cuda()
    tol = round_off(dtype)

    def close(got, ref):
        assert got.device.type == "cuda" and got.shape == ref.shape
        assert float((got.cpu() - ref).norm()) <= tol * float(ref.norm()) + 1e-30

    close(gmem(xc), mem(x))
    close(gmem.gradient(xc), mem.gradient(x))
    for projection in ("none", "clamp"):
        close(gmem.hvp(xc, vc, projection=projection), mem.hvp(x, v, projection=projection))
        close(gmem.element_hessians(xc, projection=projection), mem.element_hessians(x, projection=projection))
    xg = xc.clone().requires_grad_()
    (g,) = torch.autograd.grad(gmem(xg).sum(), xg, create_graph=True)
    (h,) = torch.autograd.grad((g * vc).sum(), xg)
    close(g.detach(), mem.gradient(x))
    close(h, mem.hvp(x, v))


@pytest.mark.gpu
@requires_gpu
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_contact_barrier_matches_the_cpu_kernels(dtype):
    """One thread per stencil over contact_math.h (bending_cuda.cu) against the CPU driver (cpu_contact.cpp), which
    the CPU tests compare with the eager reference: energies, gradients and unprojected Hessians of every type."""
    from torchbend.backends import native
    g = torch.Generator().manual_seed(0)
    X = torch.randn(2000, 4, 3, generator=g, dtype=torch.float64)
    X[:, 1:] = X[:, :1] + 0.5 * (X[:, 1:] - X[:, :1])
    xa, st = X.reshape(-1, 3).to(dtype), torch.arange(8000).reshape(-1, 4)
    for edge_edge in (False, True):
        types, D = native.contact_distances(xa, st, edge_edge)
        a, b = X[:, 1] - X[:, 0], X[:, 3] - X[:, 2]
        eps = ((a * a).sum(-1) * (b * b).sum(-1) * 0.5).to(dtype) if edge_edge else None
        dh2 = float(D.double().median()) * 2
        ref = native.contact_barrier(xa, st, types, eps, dh2, 1.0, 2, "none")
        got = cuda.contact_barrier(xa.cuda(), st.cuda(), types.cuda(), None if eps is None else eps.cuda(), dh2, 1.0, 2)
        tol = 1e-10 if dtype == torch.float64 else 1e-3
        for r, c in zip(ref, got):
            fin = torch.isfinite(r)
            torch.testing.assert_close(c.cpu()[fin], r[fin], rtol=tol, atol=tol * float(r[fin].abs().max()))
