"""The compiled C++ kernels (torchbend.backends.native): same blocks as the closed form in eager
PyTorch and as torch.func; the eager path runs where they do not apply.  Skipped only where no C++
toolchain exists."""
import os

import pytest
import torch

import torchbend as tb
from torchbend.backends import native
from torchbend.testing import plain_bending_energy

from .helpers import MESHES, MODELS, SAME_FORMULA, mesh_cases, per_hinge_reference, random_bending, rel

F64 = torch.float64


@pytest.fixture(scope="module")
def kernel():
    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")


def _both(fn):
    """``fn()`` with ``backend="auto"`` meaning native, then meaning eager."""
    with tb.use_backend("native"):
        a = fn()
    with tb.use_backend("eager"):
        b = fn()
    return a, b


@pytest.mark.parametrize("model", MODELS)
def test_native_blocks_match_eager_and_torch_func(kernel, sheet, model):
    rest, faces, x = sheet
    bend = random_bending(rest, faces, model, damped=True)
    kw = {"theta_prev": bend.angles(x) + 0.03 * torch.randn(bend.hinge_count, dtype=F64), "dt": 0.05}
    fused, eager = _both(lambda: bend.hinge_hessians(x, **kw))
    assert rel(fused, eager) <= SAME_FORMULA
    assert rel(fused, per_hinge_reference(bend, x, kw)) <= 1e-12
    # everything built on the blocks follows: hinge assembly, projections
    for project in (None, "clamp", "abs", "reduced"):
        a, b = _both(lambda project=project: bend.hessian(x, assembly="hinge", projection=project).to_dense())
        assert rel(a, b) <= 1e-14


def _eigh_projection(M: torch.Tensor, abs_mode: bool) -> torch.Tensor:
    """The reference: eigh of the symmetric part in float64, scaled to entries of at most 1 first (eigh itself
    overflows on blocks of 1e200)."""
    M = M.double()
    s = M.abs().amax((-1, -2), keepdim=True).clamp_min(1e-300)
    L, Q = torch.linalg.eigh(0.5 * (M + M.transpose(-1, -2)) / s)
    return (Q * (L.abs() if abs_mode else L.clamp_min(0))[..., None, :]) @ Q.transpose(-1, -2) * s


def test_native_projection_jacobi_matches_eigh(kernel, dtype):
    """The compiled PSD projections (cyclic Jacobi, 8 blocks at a time): clamp and abs of symmetric 9x9 and
    12x12 blocks equal eigh's to a few eps of the block norm, whatever the scale (1e-200, 1e200), for zero
    blocks, repeated and zero eigenvalues, batch shapes and a last partial tile; the result is symmetric and
    PSD (clamp, abs) and leaves a PSD block as it is."""
    gen = torch.Generator().manual_seed(7)
    eps = torch.finfo(dtype).eps
    for n in (9, 12):
        A = torch.randn(2, 13, n, n, dtype=F64, generator=gen)
        A[0, 0] = 0
        A[0, 1] = torch.diag(torch.tensor([1., 1, 1, -1, -1, -1, 2, 2, 2] + [0.] * (n - 9), dtype=F64))
        A[0, 2] = A[0, 2] @ A[0, 2].T  # PSD: unchanged
        if dtype == F64:
            A[1, 0] *= 1e-200
            A[1, 1] *= 1e200
        A = A.to(dtype)
        for abs_mode in (False, True):
            P = native.project_blocks(A, "abs" if abs_mode else "clamp")
            assert P.shape == A.shape and P.dtype == dtype and bool(torch.isfinite(P).all())
            R = _eigh_projection(A, abs_mode)
            s = A.double().abs().amax((-1, -2), keepdim=True).clamp_min(1e-300)  # norms in units of the block
            err = ((P.double() - R) / s).flatten(-2).norm(dim=-1) / (A.double() / s).flatten(-2).norm(dim=-1)
            assert float(err.nan_to_num(0.0).max()) <= 50 * eps and int(err.isnan().sum()) == 1  # nan: zero block
            assert torch.equal(P, P.transpose(-1, -2)) and not P[0, 0].any()
            Pd = P.double()
            scale = Pd.abs().amax((-1, -2)).clamp_min(1e-300)
            assert float((torch.linalg.eigvalsh(Pd / scale[..., None, None])).min()) >= -50 * eps
        assert rel(native.project_blocks(A[0, 2:3], "clamp"), A[0, 2:3]) <= 50 * eps


def test_native_projection_of_hinge_blocks(kernel, dtype):
    """Hinge blocks are projected in the 9-dimensional complement of the translations (the same matrix as the
    12x12 projection, a smaller eigenproblem): equal to eigh's clamp / abs of the full blocks, the translations
    still in the null space; through the modules, every projection of the compiled path equals the eager one."""
    rest, faces = tb.scenes.random_curved_sheet(9, 7, amplitude=0.3, seed=5, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2).to(dtype)
    gen = torch.Generator().manual_seed(5)
    x = (rest + 0.02 * torch.randn((2,) + rest.shape, generator=gen, dtype=F64)).to(dtype)
    Hb = bend.hinge_hessians(x)
    eps = torch.finfo(dtype).eps
    t = torch.eye(3, dtype=F64).repeat(4, 1)  # (12, 3): the three translations
    for abs_mode in (False, True):
        mode = "abs" if abs_mode else "clamp"
        P = native.project_blocks(Hb, mode, True)
        R = _eigh_projection(Hb, abs_mode)
        err = (P.double() - R).flatten(-2).norm(dim=-1) / Hb.double().flatten(-2).norm(dim=-1)
        assert float(err.max()) <= 50 * eps
        assert rel(P, native.project_blocks(Hb, mode, False)) <= 50 * eps
        assert float((P.double() @ t).norm() / P.double().norm()) <= 50 * eps
    # reduced: the lower-right 9x9 clamped (as eigh), mapped back by D^T P D
    from torchbend.ops.projection import Projection, project_blocks

    Pr = native.project_blocks(Hb, "reduced", True)
    assert rel(Pr, project_blocks(Hb.double(), Projection.REDUCED)) <= 50 * eps
    assert float((Pr.double() @ t).norm() / Pr.double().norm()) <= 50 * eps
    with pytest.raises(ValueError, match="reduced"):
        native.project_blocks(Hb[..., 3:, 3:].contiguous(), "reduced", False)
    tol = 1e-13 if dtype == F64 else 1e-4
    for project in ("clamp", "abs", "reduced"):
        a, b = _both(lambda project=project: bend.hinge_hessians(x, projection=project))
        assert rel(a, b) <= tol
        v = torch.randn(x.shape, generator=gen, dtype=F64).to(dtype)
        a, b = _both(lambda project=project, v=v: bend.hvp(x, v, projection=project))
        assert rel(a, b) <= tol


def test_native_float32_batched_and_degenerate(kernel):
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=1, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2)
    gen = torch.Generator().manual_seed(0)
    xb = rest + 0.02 * torch.randn((3,) + rest.shape, generator=gen, dtype=F64)
    xb[1, faces[0, 1]] = xb[1, faces[0, 0]]  # a collapsed edge in one sample: finite, same policy
    fused, eager = _both(lambda: bend.hinge_hessians(xb))
    assert fused.shape == (3, bend.hinge_count, 12, 12)
    assert bool(torch.isfinite(fused).all())
    # each path lies within a few ulps of a 40-digit reference (benchmarks/accuracy.py), in rounding that depends
    # on the CPU's vector width and FMA contraction: normwise, they differ by at most twice that
    assert rel(fused, eager) <= 16 * torch.finfo(F64).eps
    b32 = tb.BendingEnergy(faces, rest.float(), model="tan", stiffness=1e-2)
    f32, e32 = _both(lambda: b32.hinge_hessians(xb.float()))
    assert f32.dtype == torch.float32 and rel(f32, e32) <= 16 * torch.finfo(torch.float32).eps
    assert rel(f32.double(), eager) <= 1e-5


def test_native_falls_back_when_a_graph_is_recorded(kernel, sheet):
    rest, faces, x = sheet
    bend = random_bending(rest, faces, "tan")
    xg = x.clone().requires_grad_()
    Hb = bend.hinge_hessians(xg)  # differentiable: the eager path runs
    assert Hb.requires_grad
    (g,) = torch.autograd.grad(Hb.sum(), xg)
    assert bool(torch.isfinite(g).all())


def test_native_batched_theta_prev_and_nonfinite_positions(kernel):
    """Per-sample damping angles go through the fused pass; NaN positions raise the usual ValueError."""
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=2, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="sin", stiffness=1e-2, damping=1e-3)
    gen = torch.Generator().manual_seed(1)
    xb = rest + 0.05 * torch.randn((2,) + rest.shape, generator=gen, dtype=F64)
    prev = bend.angles(xb) + 0.05 * torch.randn((2, bend.hinge_count), generator=gen, dtype=F64)
    fused, eager = _both(lambda: bend.hinge_hessians(xb, theta_prev=prev, dt=0.01))
    assert fused.shape == (2, bend.hinge_count, 12, 12) and rel(fused, eager) <= SAME_FORMULA
    for project in ("gauss_newton", "reduced"):
        a, b = _both(lambda project=project: bend.hinge_hessians(xb, theta_prev=prev, dt=0.01, projection=project))
        assert rel(a, b) <= 1e-14
    v = torch.randn(xb.shape, generator=gen, dtype=F64)
    for project in ("clamp", "gauss_newton"):
        a, b = _both(lambda project=project: bend.hvp(xb, v, theta_prev=prev, dt=0.01, projection=project))
        assert rel(a, b) <= 1e-14
    bad = xb.clone()
    bad[1, 4, 2] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite .* vertices \[4\]"):
        bend.hinge_hessians(bad, theta_prev=prev, dt=0.01)


def test_native_backend_option_per_module_and_call(kernel, sheet):
    """backend="native" runs the kernel or says why it cannot; "eager" never runs it."""
    rest, faces, x = sheet
    bend = tb.BendingEnergy(faces, rest, model="tan", backend="native", stiffness=1.0)
    with pytest.raises(ValueError, match="autograd graph"):
        bend.hinge_hessians(x.clone().requires_grad_())
    assert rel(bend.hinge_hessians(x), bend.hinge_hessians(x, backend="eager")) <= SAME_FORMULA
    assert bend(x).shape == ()  # no compiled energy yet: eager, whatever is asked
    with pytest.raises(ValueError, match="unknown backend"):
        tb.BendingEnergy(faces, rest, backend="cuda", stiffness=1.0)


@pytest.mark.parametrize("mesh", MESHES)
@pytest.mark.parametrize("model", MODELS)
def test_native_assembly_both_paths_match_eager(kernel, mesh, model):
    """The C++ per-hinge and per-triangle assemblies (conditional transpose, mixed edge orientations,
    boundaries, damping) give the eager matrices and the torch.func Hessian of the plain energy."""
    rest, faces = mesh_cases()[mesh]
    gen = torch.Generator().manual_seed(2)
    x = rest + 0.05 * torch.randn(rest.shape, generator=gen, dtype=F64)
    bend = random_bending(rest, faces, model, damped=True)
    kw = {"theta_prev": bend.angles(x) + 0.03 * torch.randn(bend.hinge_count, generator=gen, dtype=F64), "dt": 0.05}
    for assembly in ("hinge", "triangle"):
        fused, eager = _both(lambda assembly=assembly: bend.hessian(x, assembly=assembly, **kw).to_dense())
        assert rel(fused, eager) <= 1e-14
    Dt, Dh = (bend.hessian(x, assembly=a).to_dense() for a in ("triangle", "hinge"))  # both in C++
    assert rel(Dt, Dh) <= 1e-13
    n = 3 * len(x)
    ref = torch.func.hessian(
        lambda y: plain_bending_energy(y, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, model)
    )(x).reshape(n, n)
    assert rel(Dt, ref) <= 1e-13


@pytest.mark.parametrize("per_triangle", [False, True])
def test_native_assembly_any_hinge_order(kernel, per_triangle):
    """The C++ assembly zeroes the values just ahead of its scatter and adds each face's block after the last
    of its hinges: the CSR values do not depend on the order of the hinges (shuffled, reversed) and equal the
    eager index_add into the full position maps (``hinge_pos``, ``face_pos``) of the block bases."""
    from torchbend.energies.sparse import HessianPattern

    rest, faces = tb.scenes.random_curved_sheet(9, 7, amplitude=0.3, seed=4, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2)
    x = rest + 0.01 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    topo, pat, H = bend.topology, HessianPattern(bend.topology), bend.hinge_count
    a, k, r = bend.weights, bend.stiffness.expand(H).contiguous(), bend.rest_angles

    def values(order):
        inv = torch.empty_like(order)
        inv[order] = torch.arange(H)
        feh = torch.where(topo.face_edge_hinges >= 0, inv[topo.face_edge_hinges.clamp_min(0)], -1)
        return torch.ops.torchbend.assemble(x, topo.hinges[order], a[order], k[order], r[order], None, None, "tan",
                                            pat.hinge_blocks[order], topo.faces, feh, topo.face_edge_signs,
                                            pat.face_blocks, pat.row_len, pat.nnz, per_triangle)

    base = values(torch.arange(H))
    for order in (torch.randperm(H, generator=torch.Generator().manual_seed(5)), torch.arange(H - 1, -1, -1)):
        assert rel(values(order), base) <= SAME_FORMULA
    ref = bend.hessian(x, assembly="triangle" if per_triangle else "hinge", backend="eager").values()
    assert rel(base, ref) <= 1e-14
    # the full position maps (the block bases spread over the rows) reach every CSR position
    counts = torch.bincount(pat.hinge_pos.reshape(-1), minlength=pat.nnz)
    assert counts.min() >= 1 and pat.face_pos[pat.face_has_hinge].max() < pat.nnz


def test_native_out_buffers(kernel):
    """out=(Hb, g): the blocks and gradients are written into the caller's buffers and returned, equal to
    fresh outputs; buffers of the wrong shape, dtype or layout, or overlapping x, are refused."""
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=3, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2, damping=1e-3)
    gen = torch.Generator().manual_seed(3)
    xb = rest + 0.05 * torch.randn((2,) + rest.shape, generator=gen, dtype=F64)
    H = bend.hinge_count
    a, k, r = bend.weights, torch.tensor(1e-2, dtype=F64), bend.rest_angles
    c, prev = torch.full((H,), 0.1, dtype=F64), bend.angles(xb) + 0.01
    args = (xb, bend.hinges, a, k, r, c, prev, "tan")
    Hb0, g0, d20 = native.bending_hessians(*args)
    hb, g = torch.full((2, H, 12, 12), float("nan"), dtype=F64), torch.full((2, H, 12), float("nan"), dtype=F64)
    for _ in range(2):  # reused
        Hb1, g1, d21 = native.bending_hessians(*args, out=(hb, g))
        assert Hb1.data_ptr() == hb.data_ptr() and g1.data_ptr() == g.data_ptr()
        assert torch.equal(Hb1, Hb0) and torch.equal(g1, g0) and torch.equal(d21, d20)
    bad = [
        ((torch.empty(2, H, 12, 13, dtype=F64), g), "must have shape"),
        ((hb.float(), g), "x's dtype"),
        ((hb, torch.empty(2, 12, H, dtype=F64).transpose(1, 2)), "contiguous"),
        ((hb, hb.view(-1)[: 2 * H * 12].view(2, H, 12)), "overlap"),
    ]
    for out, match in bad:
        with pytest.raises(RuntimeError, match=match):
            native.bending_hessians(*args, out=out)
    xr = torch.empty(2 * H * 144, dtype=F64)
    xr[: xb.numel()] = xb.reshape(-1)
    with pytest.raises(RuntimeError, match="overlaps x"):
        native.bending_hessians(xr[: xb.numel()].view(xb.shape), *args[1:], out=(xr.view(2, H, 12, 12), g))


def _scatter_case(n: int, perm: bool, batch: tuple = ()):
    """A random curved sheet (hinges in topology order, or randomly permuted: the per-hinge-buffer
    fallback of the per-vertex sums), positions, directions, tangents and weights."""
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=3, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3, check_finite=False)
    gen = torch.Generator().manual_seed(4)
    hinges, a, r = bend.hinges, bend.weights.to(F64), bend.rest_angles.to(F64)
    if perm:
        p = torch.randperm(hinges.shape[0], generator=gen)
        hinges, a, r = hinges[p], a[p], r[p]
    x = rest + (0.1 / n) * torch.randn(batch + rest.shape, generator=gen, dtype=F64)
    v = torch.randn(x.shape, generator=gen, dtype=F64)
    t = torch.randn(batch + (hinges.shape[0], 4), generator=gen, dtype=F64)
    w = 0.5 + torch.rand(batch + (hinges.shape[0],), generator=gen, dtype=F64)
    k = bend.stiffness.to(F64).reshape(1)
    inc = native.incidence(hinges, x.shape[-2])

    def run():
        gx, _ = native.bending_gradient(x, hinges, a, k, r, None, None, "tan", w, inc, False)
        hv = native.bending_hvp(x, v, hinges, a, k, r, None, None, "tan", w, inc)
        dx = native.bending_second_order(x, v, t, hinges, a, k, r, None, None, "tan", w, inc)[0]
        dv = native.bending_second_order(x, v, None, hinges, a, k, r, None, None, "tan", w, inc)[0]
        return gx, hv, dx, dv

    def reference():
        xr = x.clone().requires_grad_(True)
        e = plain_bending_energy(xr, hinges, a * w, k, r, "tan").sum()
        (g,) = torch.autograd.grad(e, xr, create_graph=True)
        (hv,) = torch.autograd.grad((g * v).sum(), xr)
        return g.detach(), hv

    return run, reference


@pytest.mark.parametrize("shuffled", [False, True])
@pytest.mark.parametrize("assembly", ["triangle", "hinge"])
def test_native_assembly_in_parts_same_bits_for_any_thread_count(assembly, shuffled):
    """The C++ assembly runs in parts over the block rows, one per thread (a mesh of 33k+ hinges has two): each
    value is added to by one part in one order, so 1 and 2 threads give the same bits, hinges in mesh order or
    shuffled (every hinge then straddles the parts), and the eager assembly's values to round-off."""
    rest, faces = tb.scenes.random_curved_sheet(110, 110, amplitude=0.3, seed=6, dtype=F64)
    if shuffled:  # vertices renumbered at random: most hinges straddle the two parts
        perm = torch.randperm(rest.shape[0], generator=torch.Generator().manual_seed(7))
        inv = torch.empty_like(perm)
        inv[perm] = torch.arange(perm.shape[0])
        rest, faces = rest[perm], inv[faces]
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2)
    assert bend.hinge_count >= 2 * 16384
    x = rest + 1e-4 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(8), dtype=F64)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = bend.hessian(x, assembly=assembly).values()
        torch.set_num_threads(2)
        two = bend.hessian(x, assembly=assembly).values()
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)
    ref = bend.hessian(x, assembly=assembly, backend="eager").values()
    assert rel(one, ref) <= 1e-14


@pytest.mark.parametrize("perm", [False, True])
@pytest.mark.parametrize("batch", [(), (2,)])
def test_native_vertex_sums_deterministic_across_threads(kernel, perm, batch):
    """The per-vertex sums of the gradient, HVP and second-order kernels (blocks of consecutive hinges, or
    the incidence-list gather for unordered hinges): bit-identical run to run and for 1 or 2 threads,
    and equal to autograd of the plain energy."""
    run, reference = _scatter_case(60, perm, batch)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = run()
        torch.set_num_threads(2)
        two, again = run(), run()
    finally:
        torch.set_num_threads(threads)
    for p, q, s in zip(one, two, again):
        assert torch.equal(p, q) and torch.equal(q, s)
    g, hv = reference()
    assert rel(one[0], g) <= 1e-12
    assert rel(one[1], hv) <= 1e-12
    assert rel(one[3], hv) <= 1e-12


def test_native_blocks_same_bits_aligned_or_not(kernel, dtype):
    """A full tile of blocks is transposed in registers into a 64-byte aligned output, a partial tile or an
    unaligned out= buffer is copied lane by lane: the same bits either way."""
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=3, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="sin", stiffness=0.3).to(dtype)
    H = bend.hinge_count
    assert H % 8  # the last tile is partial
    x = (rest + 0.05 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(2), dtype=F64)).to(dtype)
    args = (x, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, None, None, "sin")
    Hb, g, d2 = native.bending_hessians(*args)
    assert Hb.data_ptr() % 64 == 0
    hb = torch.empty(H * 144 + 1, dtype=dtype)[1:].view(H, 12, 12)  # 4 or 8 bytes off the alignment
    gs = torch.empty(H * 12 + 1, dtype=dtype)[1:].view(H, 12)
    Hb1, g1, d21 = native.bending_hessians(*args, out=(hb, gs))
    assert Hb1.data_ptr() == hb.data_ptr()
    assert torch.equal(Hb1, Hb) and torch.equal(g1, g) and torch.equal(d21, d2)
    with tb.use_backend("eager"):
        ref = bend.hinge_hessians(x)
    assert rel(Hb, ref) <= 50 * torch.finfo(dtype).eps


@pytest.mark.parametrize("damped", [False, True])
def test_native_gather_same_bits_full_or_partial_tiles(kernel, dtype, damped):
    """A full float64 tile of consecutive hinges of one sample is gathered across its lanes (vector loads of each
    component, the parameters as runs), a partial tile, one that wraps into the next sample or a float32 tile lane
    by lane:
    each hinge's angle, energy, blocks and angle gradient are the same bits whichever path loaded it.  In a
    batch of 3 samples of H (not a multiple of 8) hinges with per-sample parameters, most hinges sit in
    tiles of the other kind than in the per-sample calls."""
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=4, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=0.3)
    H, B = bend.hinge_count, 3
    assert H % 8
    gen = torch.Generator().manual_seed(5)
    xb = (rest + 0.05 * torch.randn((B,) + rest.shape, generator=gen, dtype=F64)).to(dtype)
    k = (0.1 + torch.rand((B, H), generator=gen, dtype=F64)).to(dtype)
    r = (bend.rest_angles + 0.1 * torch.randn((B, H), generator=gen, dtype=F64)).to(dtype)
    a = bend.weights.to(dtype)
    c = (0.01 * torch.rand((B, H), generator=gen, dtype=F64)).to(dtype) if damped else None
    prev = (bend.angles(xb.double()) + 0.05 * torch.randn((B, H), generator=gen, dtype=F64)).to(dtype) if damped else None
    mod = native.load()
    code = native.model_code("tan")
    psi, theta, _ = mod.bending_energy(xb, bend.hinges, a, k.reshape(-1), r.reshape(-1),
                                       None if c is None else c.reshape(-1), None if prev is None else prev.reshape(-1),
                                       code, False)
    Hb, g, _ = native.bending_hessians(xb, bend.hinges, a, k.reshape(-1), r.reshape(-1),
                                       None if c is None else c.reshape(-1), None if prev is None else prev.reshape(-1),
                                       "tan")
    for b in range(B):
        cb, pb = (None, None) if c is None or prev is None else (c[b], prev[b])
        psi1, theta1, _ = mod.bending_energy(xb[b], bend.hinges, a, k[b], r[b], cb, pb, code, False)
        assert torch.equal(psi1, psi[b]) and torch.equal(theta1, theta[b])
        Hb1, g1, _ = native.bending_hessians(xb[b], bend.hinges, a, k[b], r[b], cb, pb, "tan")
        assert torch.equal(Hb1, Hb[b]) and torch.equal(g1, g[b])
    ref = plain_bending_energy(xb.double(), bend.hinges, a.double(), k.double(), r.double(), "tan",
                               None if c is None else c.double(), None if prev is None else prev.double())
    assert rel(psi.double().sum(-1), ref) <= 100 * torch.finfo(dtype).eps


def test_large_outputs_reuse_released_memory(kernel):
    """With the (opt-in) cache on, blocks of 4 MB or more take memory released by earlier outputs (warm pages, no
    page faults): never that of a live tensor; native.empty_output_cache() frees it, a limit of 0 turns the cache off."""
    default = native.output_cache_info()["limit"]
    native.set_output_cache_limit(2048)
    try:
        _check_output_cache_reuse()
    finally:
        native.set_output_cache_limit(default / 2**20)


def _check_output_cache_reuse():
    rest, faces = tb.scenes.random_curved_sheet(40, 40, amplitude=0.3, seed=3, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1.0)
    assert bend.hinge_count * 144 * 8 >= 4 << 20
    gen = torch.Generator().manual_seed(4)
    x1, x2 = (rest + 0.01 * torch.randn(rest.shape, generator=gen, dtype=F64) for _ in range(2))
    native.empty_output_cache()
    a = bend.hinge_hessians(x1)
    ref = a.clone()
    b = bend.hinge_hessians(x2)  # a is alive: other memory
    assert a.data_ptr() != b.data_ptr() and torch.equal(a, ref)
    ptr, hits = a.data_ptr(), native.output_cache_info()["hits"]
    del a
    assert native.output_cache_info()["blocks"] >= 1
    c = bend.hinge_hessians(x1)
    assert c.data_ptr() == ptr and torch.equal(c, ref)
    assert native.output_cache_info()["hits"] == hits + 1
    del b, c
    native.empty_output_cache()
    assert native.output_cache_info()["blocks"] == 0 and native.output_cache_info()["bytes"] == 0
    limit = native.output_cache_info()["limit"]
    try:
        native.set_output_cache_limit(0)
        d = bend.hinge_hessians(x1)
        assert torch.equal(d, ref)
        del d
        assert native.output_cache_info()["blocks"] == 0
    finally:
        native.set_output_cache_limit(limit / 2**20)
    assert native.output_cache_info()["limit"] == limit


def test_large_fresh_outputs_written_whole(kernel):
    """Without the cache, a large output (4 MiB or more: its pages populated in one pass before the kernel writes
    them) holds the same blocks as a caller's NaN-filled buffer, at one and two threads; a non-finite x raises the
    usual ValueError (checked before any output is made), with or without the caller's buffers."""
    rest, faces = tb.scenes.random_curved_sheet(40, 40, amplitude=0.3, seed=5, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1.0)
    H = bend.hinge_count
    assert H * 144 * 8 >= 4 << 20
    x = rest + 0.01 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(6), dtype=F64)
    a, k, r = bend.weights, torch.tensor(1.0, dtype=F64), bend.rest_angles
    hb, g = torch.full((H, 12, 12), float("nan"), dtype=F64), torch.full((H, 12), float("nan"), dtype=F64)
    native.bending_hessians(x, bend.hinges, a, k, r, None, None, "tan", out=(hb, g))
    assert bool(torch.isfinite(hb).all()) and bool(torch.isfinite(g).all())
    threads = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            fresh, gf, _ = native.bending_hessians(x, bend.hinges, a, k, r, None, None, "tan")
            assert torch.equal(fresh, hb) and torch.equal(gf, g)
            assert torch.equal(bend.hinge_hessians(x), hb)
    finally:
        torch.set_num_threads(threads)
    bad = x.clone()
    bad[7, 1] = float("inf")
    with pytest.raises(ValueError, match=r"non-finite .* vertices \[7\]"):
        bend.hinge_hessians(bad)
    with pytest.raises(ValueError, match="non-finite"):
        native.bending_hessians(bad, bend.hinges, a, k, r, None, None, "tan", out=(hb, g), check=True)
    with pytest.raises(ValueError, match="non-finite"):
        native.bending_hessians(bad, bend.hinges, a, k, r, None, None, "tan", check=True)


def test_output_cache_default_limit(kernel):
    """The cache is opt-in: it keeps TORCHBEND_OUTPUT_CACHE_MB megabytes when that is set, none by default (no
    memory outside PyTorch's allocator is held unless asked for)."""
    env = os.environ.get("TORCHBEND_OUTPUT_CACHE_MB")
    expected = int(env) << 20 if env is not None else 0
    assert native.output_cache_info()["limit"] == expected


def test_native_collapsed_edge_finite_with_denormals_flushed(kernel):
    """A collapsed edge (the bend angle's atan2(0, 0)) stays finite with denormals flushed to zero
    (``torch.set_flush_denormal(True)``): the lane atan2's floor on its denominator is a normal number."""
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=1, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2)
    x = rest.clone()
    x[faces[0, 1]] = x[faces[0, 0]]  # a collapsed edge
    if not torch.set_flush_denormal(True):
        pytest.skip("this CPU cannot flush denormals")
    try:
        with tb.use_backend("native"):
            e, g = bend(x), bend.gradient(x)
    finally:
        torch.set_flush_denormal(False)
    with tb.use_backend("native"):
        e0, g0 = bend(x), bend.gradient(x)
    assert bool(torch.isfinite(e)) and bool(torch.isfinite(g).all())
    assert torch.equal(e, e0) and torch.equal(g, g0)  # no denormal on the way: the same bits
