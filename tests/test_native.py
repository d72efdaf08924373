"""The optional fused C++ kernel (torchbend.native): same blocks as the closed form in eager PyTorch
and as torch.func; falls back where it does not apply.  Skipped only where no C++ toolchain exists."""
import pytest
import torch

import torchbend as tb
import torchbend.native as native

from .conftest import MODELS, rel
from .test_hessian import _bend, _meshes, _per_hinge_reference

F64 = torch.float64


@pytest.fixture(scope="module")
def kernel():
    was = native.enabled()
    if not native.enable():
        native.disable()
        pytest.skip(f"C++ kernel could not be built here: {native._state['failed']}")
    yield
    if not was:
        native.disable()


def _both(fn):
    native.enable(build=False)
    a = fn()
    native.disable()
    b = fn()
    native.enable(build=False)
    return a, b


@pytest.mark.parametrize("model", MODELS)
def test_native_blocks_match_eager_and_torch_func(kernel, sheet, model):
    rest, faces, x = sheet
    bend = _bend(rest, faces, model, damped=True)
    kw = {"theta_prev": bend.angles(x) + 0.03 * torch.randn(bend.hinge_count, dtype=F64), "dt": 0.05}
    fused, eager = _both(lambda: bend.hinge_hessians(x, **kw))
    assert rel(fused, eager) <= 1e-15
    assert rel(fused, _per_hinge_reference(bend, x, kw)) <= 1e-12
    # everything built on the blocks follows: hinge assembly, projections
    for project in (None, "clamp", "reduced"):
        a, b = _both(lambda: bend.hessian(x, assembly="hinge", project=project).to_dense())
        assert rel(a, b) <= 1e-14


def test_native_float32_batched_and_degenerate(kernel):
    rest, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=1, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2)
    gen = torch.Generator().manual_seed(0)
    xb = rest + 0.02 * torch.randn((3,) + rest.shape, generator=gen, dtype=F64)
    xb[1, faces[0, 1]] = xb[1, faces[0, 0]]  # a collapsed edge in one sample: finite, same policy
    fused, eager = _both(lambda: bend.hinge_hessians(xb))
    assert fused.shape == (3, bend.hinge_count, 12, 12)
    assert bool(torch.isfinite(fused).all())
    assert rel(fused, eager) <= 1e-15
    b32 = tb.BendingEnergy(faces, rest.float(), model="tan", stiffness=1e-2)
    f32, e32 = _both(lambda: b32.hinge_hessians(xb.float()))
    assert f32.dtype == torch.float32 and rel(f32, e32) <= 1e-6
    assert rel(f32.double(), eager) <= 1e-5


def test_native_falls_back_when_a_graph_is_recorded(kernel, sheet):
    rest, faces, x = sheet
    bend = _bend(rest, faces, "tan")
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
    assert fused.shape == (2, bend.hinge_count, 12, 12) and rel(fused, eager) <= 1e-15
    for project in ("gauss_newton", "reduced"):
        a, b = _both(lambda: bend.hinge_hessians(xb, theta_prev=prev, dt=0.01, project=project))
        assert rel(a, b) <= 1e-14
    v = torch.randn(xb.shape, generator=gen, dtype=F64)
    for project in ("clamp", "gauss_newton"):
        a, b = _both(lambda: bend.hvp(xb, v, theta_prev=prev, dt=0.01, project=project))
        assert rel(a, b) <= 1e-14
    bad = xb.clone()
    bad[1, 4, 2] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite .* vertices \[4\]"):
        bend.hinge_hessians(bad, theta_prev=prev, dt=0.01)


def test_native_reused_output_buffers_never_alias_live_results(kernel):
    """Large outputs come from a cache of freed buffers: a result still held is never handed out
    again, and a dropped one is reused (no fresh page faults in Newton loops)."""
    rest, faces = tb.scenes.random_curved_sheet(16, 16, amplitude=0.2, seed=0, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3)
    assert bend.hinge_count * 144 * 8 > 256 << 10  # large enough for the cache
    gen = torch.Generator().manual_seed(0)
    xs = [rest + 0.01 * torch.randn(rest.shape, generator=gen, dtype=F64) for _ in range(3)]
    native.empty_cache()
    held = [bend.hinge_hessians(x) for x in xs]  # all alive at once: three distinct buffers
    assert len({h.data_ptr() for h in held}) == 3
    native.disable()
    ref = [bend.hinge_hessians(x) for x in xs]
    native.enable(build=False)
    for h, r in zip(held, ref):
        assert rel(h, r) <= 1e-15
    ptrs = {h.data_ptr() for h in held}
    del h, held
    cached = native.cached_bytes()
    assert cached >= 3 * bend.hinge_count * 144 * 8
    again = bend.hinge_hessians(xs[0])
    assert again.data_ptr() in ptrs and native.cached_bytes() < cached  # a dropped buffer was reused
    assert rel(again, ref[0]) <= 1e-15
    native.empty_cache()
    assert native.cached_bytes() == 0


@pytest.mark.parametrize("mesh", ["sheet", "icosphere", "cylinder", "permuted"])
@pytest.mark.parametrize("model", MODELS)
def test_native_assembly_both_paths_match_eager(kernel, mesh, model):
    """The C++ per-hinge and per-triangle assemblies (conditional transpose, mixed edge orientations,
    boundaries, damping) give the eager matrices and the torch.func Hessian of the plain energy."""
    rest, faces = _meshes()[mesh]
    gen = torch.Generator().manual_seed(2)
    x = rest + 0.05 * torch.randn(rest.shape, generator=gen, dtype=F64)
    bend = _bend(rest, faces, model, damped=True)
    kw = {"theta_prev": bend.angles(x) + 0.03 * torch.randn(bend.hinge_count, generator=gen, dtype=F64), "dt": 0.05}
    for assembly in ("hinge", "triangle"):
        fused, eager = _both(lambda: bend.hessian(x, assembly=assembly, **kw).to_dense())
        assert rel(fused, eager) <= 1e-14
    Dt, Dh = (bend.hessian(x, assembly=a).to_dense() for a in ("triangle", "hinge"))  # both in C++
    assert rel(Dt, Dh) <= 1e-13
    n = 3 * len(x)
    ref = torch.func.hessian(
        lambda y: tb.reference.plain_bending_energy(y, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, model)
    )(x).reshape(n, n)
    assert rel(Dt, ref) <= 1e-13
