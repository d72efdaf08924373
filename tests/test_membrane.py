"""Membrane energies: derivatives, closed-form eigensystems, projections, invariance, bad input."""
import functools
import math
import re

import pytest
import torch

import torchbend as tb
from torchbend import MembraneEnergy, MembraneModel
from torchbend.ops.membrane import deformation_gradient, eigensystem

from .helpers import MEMBRANE_MODELS as MODELS
from .helpers import rel

F64 = torch.float64


def plain_psi(model, F, mu, lam):
    """Energy density of F (..., 3, 2) written with plain autograd ops (C = F^T F)."""
    C = F.transpose(-1, -2) @ F
    if model == "stvk":
        G = 0.5 * (C - torch.eye(2, dtype=F.dtype))
        return mu * (G * G).sum((-1, -2)) + 0.5 * lam * G.diagonal(dim1=-2, dim2=-1).sum(-1) ** 2
    tr = C.diagonal(dim1=-2, dim2=-1).sum(-1)
    det = C[..., 0, 0] * C[..., 1, 1] - C[..., 0, 1] * C[..., 1, 0]
    J = det.sqrt()  # s1 s2
    I1 = torch.sqrt(tr + 2 * J)  # s1 + s2
    if model == "arap":
        return mu * (tr - 2 * I1 + 2)
    if model == "symmetric_dirichlet":
        return mu * (tr + tr / det - 4)
    return 0.5 * mu * (tr - 2) - mu * torch.log(J) + 0.5 * lam * torch.log(J) ** 2


def plain_energy(mem, x):
    F = deformation_gradient(x, mem.faces, mem.shape_matrices)
    return (mem.rest_areas * mem.thickness * plain_psi(mem.model.value, F, mem.mu, mem.lam)).sum(-1)


@pytest.fixture
def cloth():
    rest, faces = tb.scenes.random_curved_sheet(4, 4, amplitude=0.3, seed=3, dtype=F64)
    gen = torch.Generator().manual_seed(4)
    x = rest + 0.08 * torch.randn(rest.shape, generator=gen, dtype=F64)
    return rest, faces, x


def _mem(rest, faces, model):
    return MembraneEnergy(faces, rest, model=model, young=1e4, poisson=0.3, thickness=1e-3)


@pytest.mark.parametrize("model", MODELS)
def test_energy_gradient_hvp_match_autograd_and_fd(cloth, model):
    rest, faces, x = cloth
    mem = _mem(rest, faces, model)
    y = x.clone().requires_grad_()
    yr = x.clone().requires_grad_()
    E, Er = mem(y), plain_energy(mem, yr)
    assert abs(E.item() - Er.item()) <= 1e-13 * abs(Er.item())
    (g,) = torch.autograd.grad(E, y, create_graph=True)
    (gr,) = torch.autograd.grad(Er, yr, create_graph=True)
    assert rel(g, gr) < 1e-12 and rel(mem.gradient(x), gr) < 1e-12
    v = torch.randn_like(x)
    (hv,) = torch.autograd.grad(g, y, v)
    (hvr,) = torch.autograd.grad(gr, yr, v)
    assert rel(hv, hvr) < 1e-12 and rel(mem.hvp(x, v), hvr) < 1e-12
    assert g.grad_fn.name().endswith("MembraneGradientBackward")
    # central differences over an epsilon sweep
    dE = (mem.gradient(x) * v).sum().item()
    errs_g, errs_h = [], []
    for eps in (1e-3, 1e-4, 1e-5, 1e-6):
        errs_g.append(abs((mem(x + eps * v) - mem(x - eps * v)).item() / (2 * eps) - dE) / abs(dE))
        fd = (mem.gradient(x + eps * v) - mem.gradient(x - eps * v)) / (2 * eps)
        errs_h.append(rel(fd, mem.hvp(x, v)))
    assert min(errs_g) < 1e-8 and min(errs_h) < 1e-8, (errs_g, errs_h)
    assert errs_g[1] < errs_g[0] / 50 and errs_h[1] < errs_h[0] / 50


@pytest.mark.parametrize("model", MODELS)
def test_gradcheck_gradgradcheck(model):
    rest, faces = tb.scenes.random_curved_sheet(3, 3, amplitude=0.3, seed=1, dtype=F64)
    mem = _mem(rest, faces, model)
    x = (rest + 0.05 * torch.randn_like(rest)).requires_grad_()
    assert torch.autograd.gradcheck(mem, (x,))
    assert torch.autograd.gradgradcheck(mem, (x,))
    assert torch.autograd.gradcheck(mem, (x,), check_forward_ad=True, check_backward_ad=False,
                                    check_batched_grad=False, check_undefined_grad=False)
    n = x.numel()
    Hf = torch.func.hessian(mem)(x.detach()).reshape(n, n)
    Hr = torch.func.hessian(lambda y: plain_energy(mem, y))(x.detach()).reshape(n, n)
    assert rel(Hf, Hr) < 1e-12


def _deformation_cases():
    gen = torch.Generator().manual_seed(0)
    r = lambda *s: torch.randn(*s, generator=gen, dtype=F64)  # noqa: E731
    base = r(40, 3, 2)
    Q, _ = torch.linalg.qr(r(40, 3, 3))
    planar = Q[..., :2]  # orthonormal columns: a rigid embedding
    return {
        "random": base,
        "nearly_degenerate": planar @ torch.diag(torch.tensor([1.0, 1e-3], dtype=F64)),
        "stretched": planar @ torch.diag(torch.tensor([3.0, 2.5], dtype=F64)),
        "compressed": planar @ torch.diag(torch.tensor([0.3, 0.5], dtype=F64)),
        "inverted": planar @ torch.tensor([[1.2, 0.1], [0.0, -0.8]], dtype=F64),
        "equal_stretch": planar * 1.3,
    }


@pytest.mark.parametrize("case", list(_deformation_cases()))
@pytest.mark.parametrize("model", MODELS)
def test_closed_form_eigensystem_reproduces_f_hessian(model, case):
    F = _deformation_cases()[case]
    mu, lam = torch.tensor(2.0, dtype=F64), torch.tensor(1.5, dtype=F64)
    l, Q, _, P = eigensystem(MembraneModel(model), F, mu, lam)
    I6 = torch.eye(6, dtype=F64)
    assert (Q.transpose(-1, -2) @ Q - I6).abs().max() < 1e-12
    M = (Q * l[..., None, :]) @ Q.transpose(-1, -2)

    def psi_f(f):
        return plain_psi(model, f.reshape(3, 2), mu, lam)

    Href = torch.func.vmap(torch.func.hessian(psi_f))(F.reshape(-1, 6))
    Pref = torch.func.vmap(torch.func.grad(psi_f))(F.reshape(-1, 6))
    per = (M - Href).flatten(1).norm(dim=1) / Href.flatten(1).norm(dim=1)
    assert per.max() <= 1e-10, per.max()
    assert rel(P.flatten(-2), Pref) <= 1e-12
    # the closed-form clamp equals a numerical eigh clamp of the same block
    Lr, Qr = torch.linalg.eigh(Href)
    clamp_ref = (Qr * Lr.clamp_min(0)[..., None, :]) @ Qr.transpose(-1, -2)
    clamp = (Q * l.clamp_min(0)[..., None, :]) @ Q.transpose(-1, -2)
    assert (clamp - clamp_ref).norm() <= 1e-10 * Href.norm()


@pytest.mark.parametrize("project", ["clamp", "abs"])
@pytest.mark.parametrize("model", MODELS)
def test_projected_element_hessians_are_psd(cloth, model, project):
    rest, faces, x = cloth
    x = x + 0.3 * torch.randn_like(x)
    mem = _mem(rest, faces, model)
    He = mem.element_hessians(x)
    n = x.numel()
    Hr = torch.func.hessian(lambda y: plain_energy(mem, y))(x).reshape(n, n)
    assert rel(mem.hessian(x).to_dense(), Hr) < 1e-12
    P = mem.element_hessians(x, projection=project)
    L = torch.linalg.eigvalsh(P)
    assert (L.min(-1).values >= -1e-12 * P.flatten(-2).norm(dim=-1)).all()
    v = torch.randn_like(x)
    Hp = mem.hessian(x, projection=project).to_dense()
    assert torch.linalg.eigvalsh(Hp).min() >= -1e-10 * Hp.norm()
    assert rel(Hp @ v.reshape(-1), mem.hvp(x, v, projection=project).reshape(-1)) < 1e-12
    assert (torch.linalg.eigvalsh(He).min(-1).values < 0).any() or model == "arap"


@pytest.mark.parametrize("model", MODELS)
def test_rigid_invariance_and_rest(cloth, model):
    rest, faces, x = cloth
    mem = _mem(rest, faces, model)
    assert abs(mem(rest).item()) <= 1e-14 * mem(x).item()
    assert mem.gradient(rest).abs().max() <= 1e-10 * mem.gradient(x).abs().max()
    Q, _ = torch.linalg.qr(torch.randn(3, 3, dtype=F64))
    Q = Q * torch.det(Q)
    E = mem(x).item()
    assert abs(mem(x @ Q.T + torch.tensor([1.0, -2.0, 3.0], dtype=F64)).item() - E) <= 1e-12 * E
    g = mem.gradient(x)
    assert g.sum(0).norm() <= 1e-12 * g.norm()


def test_bad_membrane_input(cloth):
    rest, faces, x = cloth
    bad = rest.clone()
    bad[faces[2, 2]] = 0.5 * (bad[faces[2, 0]] + bad[faces[2, 1]])
    with pytest.raises(ValueError, match=r"zero-area.*faces \[.*2"):
        MembraneEnergy(faces, bad, young=1.0, poisson=0.3, thickness=1.0)
    with pytest.raises(ValueError, match="thickness must be positive"):
        MembraneEnergy(faces, rest, young=1.0, poisson=0.3, thickness=0.0)
    for nu in (0.5, -1.0, 0.7):
        with pytest.raises(ValueError, match="poisson"):
            MembraneEnergy(faces, rest, young=1.0, poisson=nu, thickness=1.0)
    with pytest.raises(ValueError, match="young"):
        MembraneEnergy(faces, rest, young=-1.0, poisson=0.3, thickness=1.0)
    with pytest.raises(ValueError, match="unknown membrane model"):
        MembraneEnergy(faces, rest, model="hooke", young=1.0, poisson=0.3, thickness=1.0)
    mem = _mem(rest, faces, "stvk")
    with pytest.raises(ValueError, match="non-finite"):
        mem(torch.full_like(rest, math.nan))
    with pytest.raises(ValueError, match="unknown membrane projection"):
        mem.hvp(x, x, projection="gauss_newton")


def test_membrane_batched_and_float32(cloth):
    rest, faces, x = cloth
    mem = _mem(rest, faces, "stvk")
    xb = torch.stack([x, rest, 1.1 * x])
    E = mem(xb)
    assert E.shape == (3,) and abs(E[2].item() - mem(1.1 * x).item()) <= 1e-12 * E[2].item()
    assert mem.gradient(xb).shape == xb.shape
    assert torch.func.vmap(mem)(xb).shape == (3,)
    e32 = mem(x.float())
    assert e32.dtype == torch.float32
    print("membrane float32 vs float64 energy error:", abs(e32.item() - mem(x).item()) / mem(x).item())
    assert abs(e32.item() - mem(x).item()) <= 1e-4 * mem(x).item()


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_stvk_closed_form_blocks_and_hvp_match_eigensystem_and_torch_func(scale):
    """The unprojected StVK blocks and HVP in closed form (no eigensystem: ops.membrane.stvk_blocks,
    stvk_hvp_stress) equal the eigensystem's ``B^T Q diag(l) Q^T B`` and torch.func's Hessian of the plain energy
    per element to round-off, on stretched, compressed, inverted and collapsed triangles, at any length scale."""
    from torchbend.ops.membrane import deformation, stvk_blocks

    rest, faces = tb.scenes.random_curved_sheet(4, 4, amplitude=0.3, seed=5, dtype=F64)
    rest = scale * rest
    mem = _mem(rest, faces, "stvk")
    gen = torch.Generator().manual_seed(6)
    x = rest * torch.tensor([1.3, 0.6, 1.0], dtype=F64) + 0.1 * scale * torch.randn(rest.shape, generator=gen, dtype=F64)
    x[faces[0, 2]] = x[faces[0, 0]] + 0.5 * (x[faces[0, 1]] - x[faces[0, 0]])  # face 0 collapsed to a segment
    x[faces[1, 2]] = x[faces[1, 0]] - (x[faces[1, 2]] - x[faces[1, 0]])  # face 1 turned over
    H = mem.element_hessians(x, backend="eager")
    D = mem.shape_matrices
    F, _ = deformation(x, mem.faces, D)
    assert torch.equal(H, stvk_blocks(F, D, mem.mu, mem.lam) * (mem.rest_areas * mem.thickness)[:, None, None])
    # the compiled blocks (the default on the CPU for one mesh): the same formula, other rounding (a few ulps of
    # each block's largest entry)
    Hn = mem.element_hessians(x)
    scale = H.flatten(-2).abs().amax(-1)[:, None, None]
    assert float(((Hn - H).abs() / scale).max()) <= 16 * torch.finfo(F64).eps
    l, Q = mem.element_eigensystems(x)  # the eigensystem path, pulled back to positions here
    Z = (Q.transpose(-1, -2).unflatten(-1, (3, 2)) @ D.transpose(-1, -2)[:, None]).transpose(-1, -2).flatten(-2)
    He = (Z.transpose(-1, -2) * l[:, None, :]) @ Z
    norms = He.flatten(-2).norm(dim=-1)
    assert float(((H - He).flatten(-2).norm(dim=-1) / norms).max()) <= 1e-13
    coef = mem.rest_areas * mem.thickness

    def element(xt, Dt, c):
        Ft = xt.transpose(0, 1) @ Dt
        return c * plain_psi("stvk", Ft, mem.mu, mem.lam)

    Hf = torch.vmap(torch.func.hessian(element))(x[faces], D, coef).reshape(-1, 9, 9)
    assert float(((H - Hf).flatten(-2).norm(dim=-1) / norms).max()) <= 1e-13
    # the HVP is the assembled blocks' product; per sample over a batch
    v = torch.randn(x.shape, generator=gen, dtype=F64)
    xb = torch.stack((x, rest))
    hv = mem.hvp(xb, v.expand_as(xb))
    for b in range(2):
        ref = (mem.hessian(xb[b]).to_dense() @ v.reshape(-1)).reshape(-1, 3)
        assert rel(hv[b], ref) <= 1e-13
    assert torch.equal(mem.element_hessians(xb)[0], Hn)  # a batch takes the compiled blocks too


# -------------------------------------------------------------------- the compiled kernels (every model)
def _stretched_sheet(dtype, seed=0, collapse=True):
    """A stretched, sheared sheet with face 1 turned over and (``collapse``) face 0 collapsed to a segment."""
    rest, faces = tb.scenes.random_curved_sheet(9, 7, amplitude=0.3, seed=seed, dtype=dtype)
    gen = torch.Generator().manual_seed(seed + 1)
    x = rest * torch.tensor([1.2, 0.7, 1.0], dtype=dtype) + 0.05 * torch.randn(rest.shape, generator=gen, dtype=dtype)
    if collapse:
        x[faces[0, 2]] = x[faces[0, 0]] + 0.5 * (x[faces[0, 1]] - x[faces[0, 0]])
    x[faces[1, 2]] = x[faces[1, 0]] - (x[faces[1, 2]] - x[faces[1, 0]])
    return rest, faces, x


def _compiled_case(model, dtype, seed, collapse=None):
    """A membrane of ``model`` on :func:`_stretched_sheet` (collapsed face 0 for StVK by default) and a batch of two
    states; skips without the CPU extension."""
    from torchbend.backends import native

    if native.load() is None:
        pytest.skip("the CPU extension is not built")
    if collapse is None:  # StVK is a polynomial, exact at collapse; ARAP's cone there: its own test
        collapse = model == "stvk"
    rest, faces, x = _stretched_sheet(dtype, seed, collapse)
    mem = MembraneEnergy(faces, rest, model=model, young=2e4, poisson=0.35, thickness=5e-4).to(dtype)
    return mem, x, torch.stack((x, rest * 1.1))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("model", MODELS)
def test_compiled_blocks_match_the_eager_path(model, dtype):
    """native.membrane_blocks (csrc/membrane_math.h: StVK unprojected in closed form, the rest through the closed-form
    eigensystem) against element_hessians(backend='eager'), every projection: the same formulas in another order of
    operations (and hypot as a square root where no square can overflow), so within a few ulps of each block's largest
    entry (observed at most 12 over 20 sheets), on stretched, turned-over and (StVK, ARAP) collapsed triangles, one
    mesh and a batch; exactly symmetric; the default backend takes them; T = 0 gives no blocks."""
    from torchbend.backends import native

    mem, x, xb = _compiled_case(model, dtype, seed=0)
    eps = torch.finfo(dtype).eps
    D, coef = mem.shape_matrices.to(dtype), (mem.rest_areas * mem.thickness).to(dtype)
    mu, lam = mem.mu.to(dtype), mem.lam.to(dtype)
    for projection in ("none", "clamp", "abs"):
        for pos in (x, xb):
            ref = mem.element_hessians(pos, projection=projection, backend="eager")
            got, finite = native.membrane_blocks(pos, mem.faces, D, coef, mu, lam, model, projection)
            assert finite and got.shape == ref.shape and got.dtype == dtype
            scale = ref.flatten(-2).abs().amax(-1)[..., None, None]  # zero for a block clamped away entirely
            assert bool(((got - ref).abs() <= 32 * eps * scale).all())
            assert torch.equal(got, got.transpose(-1, -2))
            assert torch.equal(mem.element_hessians(pos, projection=projection), got)
    assert native.membrane_blocks(x, mem.faces[:0], D[:0], coef[:0], mu, lam, model, "clamp")[0].shape == (0, 9, 9)
    _, finite = native.membrane_blocks(x * 1e160, mem.faces, D, coef, mu, lam, model, projection)
    assert not finite  # overflow: element_hessians then takes the eager path, whose error names the faces


@pytest.mark.parametrize("model", MODELS)
def test_compiled_assembly_matches_the_eager_path(model):
    """MembraneEnergy.hessian through native.membrane_assemble (each block added to the CSR values as it is computed,
    in face order) against the eager blocks scattered by index_add_, every projection; an overflow falls back to the
    eager path, whose error names the faces."""
    mem, x, _ = _compiled_case(model, F64, seed=7)
    eps = torch.finfo(F64).eps
    for projection in ("none", "clamp", "abs"):
        H, He = mem.hessian(x, projection=projection), mem.hessian(x, projection=projection, backend="eager")
        assert torch.equal(H.crow_indices(), He.crow_indices()) and torch.equal(H.col_indices(), He.col_indices())
        assert float((H.values() - He.values()).abs().max()) <= 64 * eps * float(He.values().abs().max())
    with pytest.raises(ValueError, match="overflows"):
        mem.hessian(x * 1e160)


def test_compiled_arap_at_a_collapsed_triangle():
    """ARAP's Hessian has a cone at a collapsed triangle (the normal eigenvalues 2 mu (1 - 1/s2), s2 floored at eps):
    there s2 is rounding noise of the cross product (a few eps, rounded differently by the compiled kernel and by
    PyTorch's, with or without FMA contraction), so the compiled and eager blocks of that face agree only in being
    finite, symmetric and, projected, PSD; every other face within 32 eps of its largest entry."""
    mem, x, _ = _compiled_case("arap", F64, seed=0, collapse=True)
    eps = torch.finfo(F64).eps
    for projection in ("none", "clamp", "abs"):
        got, ref = mem.element_hessians(x, projection=projection), mem.element_hessians(x, projection=projection,
                                                                                         backend="eager")
        assert bool(torch.isfinite(got).all()) and torch.equal(got, got.transpose(-1, -2))
        scale = ref[1:].flatten(-2).abs().amax(-1)[..., None, None]
        assert bool(((got[1:] - ref[1:]).abs() <= 32 * eps * scale).all())
        if projection != "none":
            assert float(torch.linalg.eigvalsh(got[0]).min()) >= -1e-12 * float(got[0].abs().max())
    g, ge = mem.gradient(x), mem.gradient(x, backend="eager")
    assert bool(torch.isfinite(g).all()) and bool(torch.isfinite(ge).all())


def test_compiled_blocks_are_chosen_without_a_graph():
    """element_hessians takes the compiled blocks on the CPU (backend 'auto' or 'native', one mesh or a batch); a
    recorded graph (the eager blocks are differentiable) and backend='eager' take the eager formulas; the assembled
    Hessian from the compiled blocks equals the eager one to round-off."""
    mem, x, xb = _compiled_case("stvk", F64, seed=4)
    eager = mem.element_hessians(x, backend="eager")
    compiled = mem.element_hessians(x)
    assert torch.equal(compiled, mem.element_hessians(x, backend="native"))
    assert not torch.equal(compiled, eager)  # another rounding: the compiled kernel ran
    assert float((compiled - eager).abs().max()) <= 16 * torch.finfo(F64).eps * float(eager.abs().max())
    assert torch.equal(mem.element_hessians(xb, backend="native")[0], compiled)
    xg = x.clone().requires_grad_()
    Hg = mem.element_hessians(xg)
    assert Hg.requires_grad and torch.equal(Hg.detach(), eager)
    Ha, He = mem.hessian(x).to_dense(), mem.hessian(x, backend="eager").to_dense()
    assert float((Ha - He).abs().max()) <= 64 * torch.finfo(F64).eps * float(He.abs().max())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("model", MODELS)
def test_compiled_energy_and_gradient_match_the_eager_path(model, dtype):
    """The compiled energy and gradient (membrane_math.h membrane_face, sums in face order) against the eager
    Functions (backend='eager'), one mesh and a batch with per-sample weights (an energy's backward).  No collapsed
    triangle here: at one, ARAP's gradient depends on the rotation R = U V^T, which is not unique there and is
    decided by the rounding of F (both paths return a valid one; test_membrane_extremes covers collapse)."""
    mem, x, _ = _compiled_case(model, dtype, seed=9, collapse=model == "stvk")
    eps = torch.finfo(dtype).eps
    xb = torch.stack((x, x * 1.1, x.flip(0)))
    for pos in (x, xb):
        E, Ee = mem(pos), mem(pos, backend="eager")
        # the per-face terms are the same to a few ulps; their sum is rounded in another order
        coef_psi = (mem.rest_areas * mem.thickness).to(dtype).sum() * mem.mu.to(dtype)
        assert float((E - Ee).abs().max()) <= 64 * eps * float(Ee.abs().max() + coef_psi)
        g, ge = mem.gradient(pos), mem.gradient(pos, backend="eager")
        assert float((g - ge).abs().max()) <= 64 * eps * float(ge.abs().max())
        w = torch.rand(pos.shape[:-2], dtype=dtype, generator=torch.Generator().manual_seed(1))
        xg = pos.clone().requires_grad_()
        (gw,) = torch.autograd.grad((mem(xg) * w).sum(), xg)
        assert float((gw - w[..., None, None] * ge).abs().max()) <= 64 * eps * float(ge.abs().max())


@pytest.mark.parametrize("scale", [1e-170, 1e-30, 1e30, 1e150])
@pytest.mark.parametrize("model", MODELS)
def test_lane_kernels_at_extreme_scales(model, scale):
    """The gradients of ARAP, symmetric Dirichlet and neo-Hookean and every projected or non-StVK HVP run the thin
    SVD and the eigensystem over the lanes of a tile (cpu_membrane.cpp lane_svd, lane_density: hypot by a
    power-of-two scaling where squares would underflow or overflow; log J by tb_logv): the results stay within a few
    ulps of the eager path's (or raise its error)."""
    mem, x, _ = _compiled_case(model, F64, seed=3, collapse=False)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    y = x * scale
    ops = [functools.partial(lambda backend, p: mem.hvp(y, v, projection=p, backend=backend), p=p)
           for p in ("none", "clamp", "abs")]
    if model != "stvk":
        ops.append(functools.partial(lambda backend: mem.gradient(y, backend=backend)))
    for op in ops:
        try:
            ref = op("eager")
        except ValueError as e:  # the model is undefined or overflows there: the compiled path says the same
            with pytest.raises(ValueError, match=re.escape(str(e).split(":")[0])):
                op("auto")
            continue
        got = op("auto")
        assert float((got - ref).abs().max()) <= 16 * torch.finfo(F64).eps * float(ref.abs().max())


@pytest.mark.parametrize("model", MODELS)
def test_compiled_energy_gradcheck_and_fallbacks(model):
    """Through the compiled forward and double backward: gradcheck and gradgradcheck; under torch.func.vmap and for
    backend='eager' the eager Functions run; a result that overflows, and (neo-Hookean, symmetric Dirichlet) a
    collapsed triangle, fall back to the eager path, whose error names the faces."""
    mem, x, _ = _compiled_case(model, F64, seed=11, collapse=model == "stvk")  # ARAP has a kink at collapse
    xg = x.clone().requires_grad_()
    assert "Compiled" in type(mem(xg).grad_fn).__name__
    assert "Compiled" not in type(mem(xg, backend="eager").grad_fn).__name__
    assert torch.autograd.gradcheck(lambda y: mem(y), (xg,))
    assert torch.autograd.gradgradcheck(lambda y: mem(y), (xg,))
    xb = torch.stack((x, 1.05 * x))
    assert rel(torch.func.vmap(mem)(xb), mem(xb)) <= 1e-13
    with pytest.raises(ValueError, match="overflows"):
        mem.gradient(x * 1e160)
    if model in ("neohookean", "symmetric_dirichlet"):
        xc = x.clone()
        f = mem.faces[0]
        xc[f[2]] = xc[f[0]]  # an exactly collapsed triangle (J = 0)
        for op in (mem, mem.gradient, lambda y: mem.element_hessians(y, projection="clamp"),
                   lambda y: mem.hvp(y, torch.ones_like(y), projection="clamp")):
            with pytest.raises(ValueError, match="collapsed"):
                op(xc)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("model", MODELS)
def test_compiled_hvp_matches_the_eager_path(model, dtype):
    """The compiled Hessian-vector product (membrane_math.h membrane_face_hvp, every projection): MembraneEnergy.hvp
    and the double backward of the energy (the HVP, and the derivative in a per-sample weight: dE/dx . v) against
    the eager paths; a double backward that records a graph (third derivatives) keeps the eager path."""
    mem, x, xb = _compiled_case(model, dtype, seed=13)
    eps = torch.finfo(dtype).eps
    gen = torch.Generator().manual_seed(2)
    v = torch.randn(xb.shape, generator=gen, dtype=dtype)
    for pos, dv in ((x, v[0]), (xb, v)):
        for projection in ("none", "clamp", "abs"):
            hv, hve = mem.hvp(pos, dv, projection=projection), mem.hvp(pos, dv, projection=projection, backend="eager")
            assert float((hv - hve).abs().max()) <= 64 * eps * float(hve.abs().max())

        def double_backward(backend, create_graph=False, pos=pos, dv=dv):
            xg = pos.clone().requires_grad_()
            w = torch.rand(pos.shape[:-2], generator=torch.Generator().manual_seed(3), dtype=dtype).requires_grad_()
            (g,) = torch.autograd.grad((w * mem(xg, backend=backend)).sum(), xg, create_graph=True)
            return torch.autograd.grad((g * dv).sum(), (xg, w), create_graph=create_graph)

        (h, dw), (he, dwe) = double_backward("auto"), double_backward("eager")
        assert float((h - he).abs().max()) <= 64 * eps * float(he.abs().max())
        assert float((dw - dwe).abs().max()) <= 64 * eps * float(dwe.abs().max())
        h3, _ = double_backward("auto", create_graph=True)
        assert h3.requires_grad and float((h3.detach() - he).abs().max()) <= 64 * eps * float(he.abs().max())


# -------------------------------------------------------------------- torch.compile
@pytest.fixture
def fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


@pytest.mark.parametrize("model", MODELS)
def test_torch_compile_fullgraph_bending_and_membrane(fresh_dynamo, model):
    """A cloth energy of bending and membrane under torch.compile(fullgraph=True): no graph break (the membrane's
    operators torch.ops.torchbend.membrane_* and their Functions without jvp), the energy within 4 ulps of the eager
    call, a training step (loss.backward() inside the graph) with the eager gradients; a double backward through
    the compiled energy is the guard's clear error; torch.ops.torchbend.membrane_hvp gives the eager HVP."""
    from torchbend.backends import CompiledDoubleBackwardError, native

    if native.load() is None:
        pytest.skip("the CPU extension is not built")
    rest, faces = tb.scenes.random_curved_sheet(8, 7, amplitude=0.2, seed=5, dtype=F64)
    gen = torch.Generator().manual_seed(6)
    x = rest * 1.05 + 0.01 * torch.randn(rest.shape, generator=gen, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-4)
    mem = _mem(rest, faces, model)

    def energy(y):
        return bend(y) + mem(y)

    compiled = torch.compile(energy, fullgraph=True)
    e, ref = compiled(x), energy(x)
    assert float((e - ref).abs()) <= 4 * torch.finfo(F64).eps * float(ref.abs())
    if model == "stvk":  # 13,000 hinges: the hinges' sum is ATen's in compiled code too (ops.sum_last), bit for bit
        big_rest, big_faces = tb.scenes.random_curved_sheet(60, 60, amplitude=0.2, seed=5, dtype=F64)
        big_x = big_rest * 1.05 + 1e-3 * torch.randn(big_rest.shape, generator=gen, dtype=F64)
        big_bend = tb.BendingEnergy(big_faces, big_rest, model="tan", stiffness=1e-4)
        big_mem = _mem(big_rest, big_faces, model)

        def big_energy(y):
            return big_bend(y) + big_mem(y)

        assert torch.equal(torch.compile(big_energy, fullgraph=True)(big_x), big_energy(big_x))

    def step(y):
        loss = energy(y)
        loss.backward()
        return loss.detach()

    y1, y2 = x.clone().requires_grad_(), x.clone().requires_grad_()
    with torch._dynamo.config.patch(trace_autograd_ops=True):
        torch.compile(step, fullgraph=True)(y1)
    step(y2)
    assert y1.grad is not None and y2.grad is not None and rel(y1.grad, y2.grad) <= 1e-14
    yg = x.clone().requires_grad_()
    with pytest.raises(CompiledDoubleBackwardError):
        torch.autograd.grad(torch.compile(mem, fullgraph=True)(yg), yg, create_graph=True)
    D, coef = mem.shape_matrices, mem.rest_areas * mem.thickness
    v = torch.randn(x.shape, generator=gen, dtype=F64)
    hv, _ = torch.ops.torchbend.membrane_hvp(x, v, mem.faces, D, coef, mem.mu, mem.lam, x.new_ones(()), model, "clamp")
    assert rel(hv, mem.hvp(x, v, projection="clamp", backend="eager")) <= 1e-13


def test_torch_compile_membrane_operator_errors(fresh_dynamo):
    """Inside compiled code the membrane operators raise the eager path's errors: non-finite positions, and a
    collapsed triangle of a model undefined there, named by its faces."""
    from torchbend.backends import native

    if native.load() is None:
        pytest.skip("the CPU extension is not built")
    rest, faces = tb.scenes.random_curved_sheet(5, 4, amplitude=0.2, seed=2, dtype=F64)
    mem = _mem(rest, faces, "neohookean")
    compiled = torch.compile(mem, fullgraph=True)
    bad = rest.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        compiled(bad)
    flat = rest.clone()
    f = mem.faces[2]
    flat[f[2]] = flat[f[0]]
    with pytest.raises(ValueError, match="collapsed"):
        compiled(flat)


@pytest.mark.parametrize("model", MODELS)
def test_compiled_operators_are_deterministic_across_thread_counts(model):
    """The compiled energy, gradient, HVP (projected) and element blocks run their tiles in parallel chunks and sum
    and scatter in face order: one and two threads give the same bits (more faces than one chunk of 4096)."""
    n = 50
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=1, dtype=F64)
    gen = torch.Generator().manual_seed(5)
    x = rest * 1.05 + (0.3 / n) * torch.randn(rest.shape, generator=gen, dtype=F64)
    v = torch.randn(rest.shape, generator=gen, dtype=F64)
    mem = MembraneEnergy(faces, rest, model=model, young=1e5, poisson=0.3, thickness=1e-3)
    assert mem.face_count > 4096
    threads = torch.get_num_threads()
    results = {}
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            results[t] = (mem(x), mem.gradient(x), mem.hvp(x, v, projection="clamp"), mem.hvp(x, v),
                          mem.element_hessians(x, projection="clamp"))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(results[1], results[2]))
