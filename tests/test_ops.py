"""The compiled operators (``torch.ops.torchbend.*``) behind the default path: every op against the eager
closed forms (the oracle) in both dtypes, all models, with and without damping, batched and packed;
``torch.library.opcheck``; gradcheck/gradgradcheck through the compiled path; ``torch.compile`` with
``fullgraph=True`` and ``torch.export``; the checks that stay on inside compiled code."""
import math

import pytest
import torch

import torchbend as tb
from torchbend import BendingEnergy
from torchbend.backends import native, ops

from .conftest import MODELS

F64, F32 = torch.float64, torch.float32


@pytest.fixture(scope="module", autouse=True)
def kernel():
    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")


def _eps_ulp(a, b, dtype, scale=None) -> float:
    """``|a - b| / |scale|`` in ulps of ``dtype`` (normwise; ``scale`` defaults to ``b``)."""
    a, b = a.detach().double(), b.detach().double()
    ref = b if scale is None else scale.detach().double()
    return float((a - b).norm() / ref.norm()) / torch.finfo(dtype).eps


def _magnitudes(bend, x, call, v) -> dict[str, torch.Tensor]:
    """What the results of :func:`_everything` are sums of, in absolute value: each entry the sum over hinges
    (and over the batch, for parameters shared by it) of the magnitudes of the per-hinge terms, ``sum_h |psi_h|``,
    ``sum_h |g_h|``, ``sum_h |H_h| |v_h|``, ``sum_b |d psi_bh / d p_h|`` (float64, from the plain energy of
    :mod:`torchbend.testing`).

    A sum of terms each computed to a few ulps of its own size is correct to a few ulps of the sum of their
    magnitudes, not of the sum itself: where the hinges' forces at a vertex nearly cancel (random positions),
    ``|sum_h g_h|`` is several times smaller than ``sum_h |g_h|``, and two correct implementations that round or
    sum in another order (another vector width, fused multiply-adds or not, ATen's AVX2 or AVX-512 kernels)
    differ by more ulps of the result than of the terms.  The tolerance is taken relative to these magnitudes:
    the conditioning of the sum, not one CPU's rounding."""
    from torchbend.testing import plain_bending_energy

    x64 = x.detach().double()
    prev64 = call.get("theta_prev")
    p = tb.energies.HingeParams.bind(bend, x64, None if prev64 is None else prev64.double(), call.get("dt"))
    hinges, model = bend.hinges, bend.model
    batch, H = x64.shape[:-2], hinges.shape[0]
    shape = (*batch, H)
    k, rest = p.k.expand(shape).reshape(-1), p.rest.expand(shape).reshape(-1)
    damped = p.c is not None and p.prev is not None
    c = p.c.expand(shape).reshape(-1) if p.c is not None else k
    prev = p.prev.expand(shape).reshape(-1) if p.prev is not None else k
    a = p.a.expand(shape).reshape(-1)
    xh = x64[..., hinges, :].reshape(-1, 4, 3)
    stencil = torch.arange(4)[None]

    def psi(xs, a_, k_, rest_, c_, prev_):
        return plain_bending_energy(xs, stencil, a_[None], k_, rest_[None], model,
                                    c_ if damped else None, prev_[None] if damped else None)

    args = (xh, a, k, rest, c, prev)
    e = torch.vmap(psi)(*args).reshape(shape)
    g = torch.vmap(torch.func.grad(psi))(*args).reshape(*shape, 12)
    Hh = torch.vmap(torch.func.hessian(psi))(*args).reshape(*shape, 12, 12)
    vh = v.detach().double()[..., hinges, :].reshape(*shape, 12)

    def scatter(per_hinge):  # (*batch, H, 12) -> (*batch, V, 3)
        out = x64.new_zeros(x64.shape).reshape(-1, *x64.shape[-2:])
        out.index_add_(1, hinges.reshape(-1), per_hinge.reshape(-1, 4 * H, 3))
        return out.reshape(x64.shape)

    hv = scatter((Hh.abs() @ vh.abs()[..., None])[..., 0])
    out = {"energy": e.abs().sum(-1), "gradient": scatter(g.abs()), "hvp": hv, "hvp_method": hv}
    params = [q for q in (bend.stiffness, bend.rest_angles) if q.requires_grad]
    if params:
        dk, drest = torch.vmap(torch.func.grad(psi, argnums=(2, 3)))(*args)
        for i, d in enumerate((dk, drest)[:len(params)]):
            out[f"param{i}"] = d.reshape(-1, H).abs().sum(0)
    return out


def _grad(t: torch.Tensor) -> torch.Tensor:
    assert t.grad is not None
    return t.grad


def _setup(model, dtype, damped, batch, learn=False, packed=False):
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=3, dtype=F64)
    gen = torch.Generator().manual_seed(7)
    kw: dict = dict(model=model, damping=0.3 if damped else None, stiffness=1.0)
    if packed:
        rest2, faces2 = tb.scenes.random_curved_sheet(4, 4, amplitude=0.2, seed=5, dtype=F64)
        meshes = tb.pack_meshes([(rest, faces), (rest2, faces2)])
        bend = BendingEnergy.packed(meshes, **kw)
        rest = meshes.verts
    else:
        bend = BendingEnergy(faces, rest, **kw)
    H = bend.hinge_count
    if learn:  # per-hinge learnable stiffness and rest angles
        bend.stiffness = torch.nn.Parameter(0.5 + torch.rand(H, generator=gen, dtype=F64))
        bend.rest_angles = torch.nn.Parameter(bend.rest_angles.detach() + 0.1 * torch.randn(H, generator=gen, dtype=F64))
    bend = bend.to(dtype)
    x = (rest + 0.05 * torch.randn((*batch, *rest.shape), generator=gen, dtype=F64)).to(dtype)
    call = {}
    if damped:
        call = dict(theta_prev=(bend.angles(x) + 0.3 * torch.randn(x.shape[:-2] + (H,), generator=gen, dtype=F64)
                                .to(dtype)), dt=0.01)
    return bend, x, call


def _direction(x):
    return torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=F64).to(x.dtype)


def _everything(bend, x, call, backend):
    """Energy, gradient (backward), HVP (double backward) and parameter gradients with ``backend`` meaning it."""
    with tb.use_backend(backend):
        y = x.clone().requires_grad_()
        E = bend(y, **call)
        params = [p for p in (bend.stiffness, bend.rest_angles) if p.requires_grad]
        g = torch.autograd.grad(E.sum(), [y, *params], create_graph=True)
        v = _direction(x)
        (hv,) = torch.autograd.grad(g[0], y, v)
        with torch.no_grad():  # learnable parameters: hvp() records no graph here
            hv_method = bend.hvp(x, v, **call)
        out = {"energy": E, "gradient": g[0], "hvp": hv, "hvp_method": hv_method}
        for i in range(len(params)):
            out[f"param{i}"] = g[1 + i]
    return out


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("batch", [(), (2,)])
@pytest.mark.parametrize("learn", [False, True])
def test_compiled_ops_match_eager_within_4_ulp(dtype, model, damped, batch, learn):
    """Without learnable parameters the double backward is the HVP operator, with them the second-order one.

    4 ulps normwise of the magnitudes the results are sums of (:func:`_magnitudes`): the conditioning of the
    per-vertex sums, so that the bound holds for every instruction set the kernels and ATen are built for."""
    bend, x, call = _setup(model, dtype, damped, batch, learn=learn)
    a, b = _everything(bend, x, call, "native"), _everything(bend, x, call, "eager")
    scale = _magnitudes(bend, x, call, _direction(x))
    for name in a:
        assert a[name].dtype == dtype and a[name].shape == b[name].shape, name
        assert scale[name].shape == b[name].shape, name
        err = _eps_ulp(a[name], b[name], dtype, scale[name])
        assert err <= 4, f"{name}: {err:.2f} ulp normwise of the summed magnitudes ({_eps_ulp(a[name], b[name], dtype):.2f} of the result)"


@pytest.mark.parametrize("dtype", [F64, F32])
def test_compiled_ops_packed_meshes(dtype):
    bend, x, _ = _setup("tan", dtype, False, (), packed=True)
    a, b = _everything(bend, x, {}, "native"), _everything(bend, x, {}, "eager")
    assert a["energy"].shape == (2,)
    scale = _magnitudes(bend, x, {}, _direction(x))
    for name in a:
        assert _eps_ulp(a[name], b[name], dtype, scale[name]) <= 4, name


def test_the_default_path_runs_the_operators(monkeypatch):
    """No opt-in: a plain module call, its backward and double backward go through torch.ops.torchbend."""
    bend, x, _ = _setup("tan", F64, False, ())
    calls = []
    for name in ("bending_energy", "bending_gradient", "bending_energy_gradient", "bending_hvp"):
        orig = getattr(native, name)

        def spy(*args, _orig=orig, _name=name, **kw):
            calls.append(_name)
            return _orig(*args, **kw)

        monkeypatch.setattr(native, name, spy)
    y = x.clone().requires_grad_()
    (g,) = torch.autograd.grad(bend(y), y, create_graph=True)
    assert g.grad_fn is not None and g.grad_fn.name().startswith("TanBendingGradient")
    torch.autograd.grad(g, y, torch.ones_like(x))
    # the recorded forward computes the gradient with the energy (one pass), the double backward the HVP
    assert calls == ["bending_energy_gradient", "bending_hvp"]
    calls.clear()
    with torch.no_grad():
        bend(y)
    (g,) = torch.autograd.grad(bend(y), y)  # a plain backward: no second kernel call
    assert calls == ["bending_energy", "bending_energy_gradient"]
    assert torch.equal(g, bend.gradient(x))


# ----------------------------------------------------------------------------- torch.library
def _op_args(model="tan", damped=False, batch=()):
    bend, x, call = _setup(model, F64, damped, batch)
    p = tb.energies.HingeParams.bind(bend, x, call.get("theta_prev"), call.get("dt"))
    a, k, rest, c, prev = p.astuple()
    return bend, x, (bend.hinges, a, k, rest, c, prev, model)


@pytest.mark.parametrize("damped", [False, True])
def test_opcheck_every_operator(damped):
    bend, x, (hinges, a, k, rest, c, prev, model) = _op_args("tan", damped, (2,))
    ptr, idx = bend._incidence()
    w = torch.rand(x.shape[:-2] + (hinges.shape[0],), dtype=F64)
    v = torch.randn_like(x)
    base = (hinges, a, k, rest, c, prev, model)
    cases = {
        "bending_energy": (x, *base, True),
        "bending_gradient": (x, *base, w, ptr, idx, True, False),
        "bending_energy_gradient": (x, *base, ptr, idx, True, False),
        "bending_hvp": (x, v, *base, w, ptr, idx),
        "bending_second_order": (x, v, torch.randn(x.shape[:-2] + (hinges.shape[0], 4), dtype=F64), *base, w, ptr,
                                 idx),
        "hinge_hessians": (x, *base),
    }
    for name, args in cases.items():
        torch.library.opcheck(getattr(torch.ops.torchbend, name).default, args)
    torch.library.opcheck(torch.ops.torchbend.bending_gradient.default, (x, *base, w, ptr, idx, False, False))
    torch.library.opcheck(torch.ops.torchbend.bending_second_order.default, (x, None, None, *base, w, ptr, idx))
    # the assembly: one mesh
    bend1, x1, (h1, a1, k1, r1, c1, p1, m1) = _op_args("tan", damped, ())
    from torchbend.energies.sparse import HessianPattern

    pat, topo = HessianPattern(bend1.topology), bend1.topology
    for per_triangle in (False, True):
        torch.library.opcheck(torch.ops.torchbend.assemble.default,
                              (x1, h1, a1, k1, r1, c1, p1, m1, pat.hinge_blocks, topo.faces, topo.face_edge_hinges,
                               topo.face_edge_signs, pat.face_blocks, pat.row_len, pat.nnz, per_triangle))
    Hb = torch.ops.torchbend.hinge_hessians(x, *base)[0]
    for mode in ("clamp", "abs", "reduced"):
        torch.library.opcheck(torch.ops.torchbend.project_blocks.default, (Hb, mode, True))
    for mode in ("clamp", "abs"):
        torch.library.opcheck(torch.ops.torchbend.project_blocks.default, (Hb[..., 3:, 3:].contiguous(), mode, False))
    with pytest.raises(ValueError, match="mode must be"):
        torch.ops.torchbend.project_blocks(Hb, "reduced")  # not declared hinge blocks
    with pytest.raises(ValueError, match="mode must be"):
        torch.ops.torchbend.project_blocks(Hb, "gauss_newton", True)
    assert set(cases) | {"assemble", "project_blocks"} <= set(ops.OPS)
    for name in ops.OPS:
        assert hasattr(torch.ops.torchbend, name)


# ----------------------------------------------------------------------------- gradcheck through the compiled path
@pytest.mark.parametrize("model", MODELS)
def test_gradcheck_and_gradgradcheck_compiled_path(model):
    bend, x, _ = _setup(model, F64, False, (), learn=True)
    assert tb.backends.select_backend("energy", "auto", x) is tb.Backend.NATIVE

    def f(y, k, r):
        bend.stiffness, bend.rest_angles = k, r
        return bend(y)

    k = bend.stiffness.detach().clone().requires_grad_()
    r = bend.rest_angles.detach().clone().requires_grad_()
    y = x.clone().requires_grad_()
    del bend.stiffness, bend.rest_angles  # plain attributes during the check (tensors with requires_grad)
    assert torch.autograd.gradcheck(f, (y, k, r))
    assert torch.autograd.gradgradcheck(f, (y, k, r))


# ----------------------------------------------------------------------------- torch.compile / torch.export
@pytest.fixture
def fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


@pytest.mark.parametrize("damped", [False, True])
def test_torch_compile_fullgraph_energy(fresh_dynamo, damped):
    bend, x, call = _setup("tan", F64, damped, (2,))
    compiled = torch.compile(bend, fullgraph=True)
    assert _eps_ulp(compiled(x, **call), bend(x, **call), F64) <= 4  # the graph may sum in another order


def test_torch_compile_fullgraph_training_step(fresh_dynamo):
    """loss = energy, then .backward(), all inside one compiled graph (learnable stiffness and rest angles)."""
    bend, x, _ = _setup("quadratic", F64, False, (), learn=True)

    def step(y):
        loss = bend(y).sum()
        loss.backward()
        return loss.detach()

    compiled = torch.compile(step, fullgraph=True)
    y1, y2 = x.clone().requires_grad_(), x.clone().requires_grad_()
    with torch._dynamo.config.patch(trace_autograd_ops=True):  # (a config patch, undone exactly)
        l1 = compiled(y1)
    g1 = [_grad(p).clone() for p in (y1, bend.stiffness, bend.rest_angles)]
    bend.zero_grad()
    l2 = step(y2)
    g2 = [_grad(p) for p in (y2, bend.stiffness, bend.rest_angles)]
    assert _eps_ulp(l1, l2, F64) <= 4
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, rtol=1e-14, atol=0)


def test_compiled_module_backward_and_eager_double_backward(fresh_dynamo):
    """A compiled forward with its (compiled) backward; second order runs eagerly through the same operators
    (PyTorch cannot differentiate twice through a compiled region, pytorch#91469)."""
    bend, x, _ = _setup("tan", F64, False, ())
    compiled = torch.compile(bend, fullgraph=True)
    y = x.clone().requires_grad_()
    compiled(y).backward()
    z = x.clone().requires_grad_()
    (g,) = torch.autograd.grad(bend(z), z, create_graph=True)
    assert torch.allclose(_grad(y), g, rtol=1e-14, atol=0)
    v = torch.randn_like(x)
    (hv,) = torch.autograd.grad(g, z, v)
    assert torch.allclose(hv, bend.hvp(x, v), rtol=1e-13, atol=0)


def test_double_backward_through_a_compiled_energy_raises_a_clear_error(fresh_dynamo):
    """create_graph=True through a compiled region: PyTorch cannot differentiate the backward it compiled (the
    gradient's graph would not lead back to x, and the next grad would fail with "appears to not have been used
    in the graph"); the error names the limitation and the eager alternatives, which give the analytic HVP."""
    bend, x, _ = _setup("tan", F64, False, ())
    compiled = torch.compile(bend, fullgraph=True)
    y = x.clone().requires_grad_()
    with pytest.raises(tb.backends.CompiledDoubleBackwardError, match=r"create_graph=True.*without torch.compile.*hvp"):
        torch.autograd.grad(compiled(y), y, create_graph=True)
    v = torch.randn_like(x)

    def hvp(z):  # the whole double backward inside a compiled function
        (g,) = torch.autograd.grad(bend(z), z, create_graph=True)
        return torch.autograd.grad(g, z, v)[0]

    with pytest.raises(tb.backends.CompiledDoubleBackwardError, match="differentiated with create_graph=True"):
        torch.compile(hvp)(x.clone().requires_grad_())
    # the alternatives the message names agree with each other
    z = x.clone().requires_grad_()
    (g,) = torch.autograd.grad(bend(z), z, create_graph=True)
    (hv,) = torch.autograd.grad(g, z, v)
    assert torch.allclose(hv, bend.hvp(x, v), rtol=1e-13, atol=0)
    # first order through the compiled region is unaffected: backward(), and retain_graph without create_graph
    compiled(y).backward()
    g1 = _grad(y).clone()
    assert torch.allclose(g1, g.detach(), rtol=1e-14, atol=0)


def test_compiled_energy_backward_with_retain_graph_is_not_refused(fresh_dynamo):
    import torch._functorch.config as functorch_config

    bend, x, _ = _setup("quadratic", F64, False, ())
    # PyTorch's own retain_graph limit, lifted by the config's patch (undone exactly: a monkeypatch of the config
    # module deletes the entry on undo, which breaks every later compilation)
    with functorch_config.patch(donated_buffer=False):
        compiled = torch.compile(bend, fullgraph=True)
        y = x.clone().requires_grad_()
        e = compiled(y)
        e.backward(retain_graph=True)
        e.backward()
    z = x.clone().requires_grad_()
    bend(z).backward()
    assert torch.allclose(_grad(y), 2 * _grad(z), rtol=1e-14, atol=0)


def test_torch_export_energy_module():
    bend, x, _ = _setup("sin", F64, False, ())
    exported = torch.export.export(bend, (x,))
    targets = {str(n.target) for n in exported.graph.nodes if n.op == "call_function"}
    assert "torchbend.bending_energy.default" in targets
    assert _eps_ulp(exported.module()(x), bend(x), F64) <= 4


def test_checks_stay_on_inside_compiled_code(fresh_dynamo):
    bend, x, _ = _setup("tan", F64, False, ())
    compiled = torch.compile(bend, fullgraph=True)
    compiled(x)
    bad = x.clone()
    bad[3, 1] = math.nan
    with pytest.raises(ValueError, match="non-finite"):
        compiled(bad)
    # a hinge folded flat onto itself (|theta| = pi): the same ValueError compiled and eager
    rest, faces = tb.scenes.single_hinge(0.0, dtype=F64)
    folded = rest.clone()
    folded[3] = torch.tensor([0.3, 0.8, 0.0], dtype=F64)
    hinge = BendingEnergy(faces, rest, model="tan", stiffness=1.0)
    compiled = torch.compile(hinge, fullgraph=True)
    compiled(rest)
    for f in (hinge, compiled):
        with pytest.raises(ValueError, match=r"hinges \[0\] have folded through"):
            f(folded)


def test_unsupported_dtype_falls_back_with_one_warning():
    rest, faces = tb.scenes.random_curved_sheet(4, 4, amplitude=0.3, seed=3, dtype=F64)
    bend = BendingEnergy(faces, rest, model="quadratic", stiffness=1.0).to(torch.bfloat16)
    x = rest.to(torch.bfloat16)
    tb.backends._warned.clear()
    with pytest.warns(RuntimeWarning, match="energy runs on the eager path: the compiled kernels take float32"):
        e = bend(x)
    assert torch.isfinite(e)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bend(x)  # once only


@pytest.mark.parametrize("dtype", [F64, F32])
def test_checks_inside_the_kernels(dtype):
    """Eagerly too, the compiled operators check x (and v) themselves, before any work: the ValueErrors of the
    Python checks, also for a vertex in no hinge and for one sample of a batch; check_finite=False skips them."""
    rest, faces = tb.scenes.random_curved_sheet(5, 4, amplitude=0.3, seed=3, dtype=F64)
    rest = torch.cat([rest, torch.zeros(1, 3, dtype=F64)])  # a vertex in no face
    V = rest.shape[0]
    bend = BendingEnergy(faces, rest, model="tan", stiffness=1.0).to(dtype)
    x = rest.to(dtype).expand(2, V, 3).clone()
    assert tb.backends.select_backend("energy", "auto", x) is tb.Backend.NATIVE
    for vert in (3, V - 1):
        bad = x.clone()
        bad[1, vert, 2] = math.nan
        for call in (bend, bend.gradient, lambda y: bend.hvp(y, x), bend.hinge_hessians):
            with pytest.raises(ValueError, match=rf"x holds non-finite .* vertices \[{vert}\]"):
                call(bad)
    bad_v = x.clone()
    bad_v[0, 2, 0] = math.inf
    with pytest.raises(ValueError, match="v holds non-finite"):
        bend.hvp(x, bad_v)
    bend.check_finite = False
    bad = x.clone()
    bad[1, 3, 2] = math.nan
    e = bend(bad)
    assert torch.isfinite(e[0]) and torch.isnan(e[1])
