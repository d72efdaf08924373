"""The compiled second-order kernel (torchbend.backends.native.bending_second_order): the general double
backward with directions in the positions and in the per-hinge parameters (k, rest, c, prev), against the
eager ``_second_order`` of the autograd Function and against torch.func of the plain autograd energy.
Skipped only where no C++ toolchain exists."""

import pytest
import torch

import torchbend as tb
from torchbend.backends import native
from torchbend.energies._bending_fn import _second_order
from torchbend.ops.psi import BendingModel
from torchbend.testing import plain_bending_energy

from .helpers import MODELS, rel, second_order_case

F64 = torch.float64


@pytest.fixture(scope="module")
def kernel():
    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")


def _expanded(p: dict, batch: tuple) -> list:
    """The parameters as ``(*batch, H)`` tensors (what the autograd reference differentiates)."""
    H = p["hinges"].shape[0]
    names = ("k", "rest") + (("c", "prev") if p["c"] is not None else ())
    return [p[n].to(F64).expand(batch + (H,)).clone() for n in names]


def _reference(p: dict, use_v: bool = True, use_t: bool = True):
    """``(dx, dp (..., H, 4), dg (..., H))`` by torch.func (float64) of the plain energy with per-hinge weights
    folded into ``a`` (psi is linear in ``a``)."""
    x = p["x"].to(F64)
    batch = x.shape[:-2]
    hinges, a, w = p["hinges"], p["a"].to(F64), p["w"].to(F64)
    params = _expanded(p, batch)
    damped = len(params) == 4
    n = len(params)

    def energy(y, ww, *ps):
        c, prev = (ps[2], ps[3]) if damped else (None, None)
        return plain_bending_energy(y, hinges, a * ww, ps[0], ps[1], p["model"], c, prev).sum()

    v = p["v"].to(F64) if use_v else torch.zeros_like(x)
    t = p["t"].to(F64) if use_t else torch.zeros(batch + (hinges.shape[0], 4), dtype=F64)
    tangents = (v, torch.zeros_like(w)) + tuple(t[..., i] for i in range(n))
    grad = torch.func.grad(energy, argnums=tuple(range(2 + n)))
    hvp = torch.func.jvp(lambda *args: grad(*args), (x, w) + tuple(params), tangents)[1]
    dx = hvp[0]
    dp = torch.zeros(batch + (hinges.shape[0], 4), dtype=F64)
    for i in range(n):
        dp[..., i] = hvp[2 + i]
    # dg_h = d psi_h [v, t] (unweighted): psi_h = d E / d w_h at w = 1... with E's weights w: d/dw_h of the
    # weighted energy is psi_h whatever w is, so its directional derivative in (x, params) is dg
    ones = torch.ones_like(w)

    def psi_per_hinge(y, *ps):
        return torch.func.grad(energy, argnums=1)(y, ones, *ps)

    dg = torch.func.jvp(psi_per_hinge, (x,) + tuple(params), (v,) + tuple(t[..., i] for i in range(n)))[1]
    return dx, dp, dg


def _native(p: dict, use_v: bool = True, use_t: bool = True):
    inc = native.incidence(p["hinges"], p["V"])
    return native.bending_second_order(p["x"], p["v"] if use_v else None, p["t"] if use_t else None, p["hinges"],
                                       p["a"], p["k"], p["rest"], p["c"], p["prev"], p["model"], p["w"], inc)


@pytest.mark.parametrize("per_hinge", [False, True])
@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("model", MODELS)
def test_second_order_matches_torch_func(kernel, dtype, model, damped, per_hinge):
    """Batched positions (2, V, 3), per-sample prev, per-hinge weights: dx, dp and dg against torch.func of the
    plain energy in float64 (float32: the kernel in float32 against the float64 reference)."""
    p = second_order_case(model, damped, dtype, per_hinge)
    dx, dp, dg = _native(p)
    assert dx.dtype == dtype and dx.shape == p["x"].shape
    assert dp.shape == p["t"].shape and dg.shape == p["w"].shape
    rx, rp, rg = _reference(p)
    tol = 1e-12 if dtype == F64 else 2e-5
    assert rel(dx.double(), rx) <= tol
    assert rel(dp.double(), rp) <= tol
    assert rel(dg.double(), rg) <= tol
    if not damped:
        assert bool((dp[..., 2:] == 0).all())


@pytest.mark.parametrize("model", MODELS)
def test_second_order_partial_directions(kernel, model):
    """v or t None: the same as zero directions (and both None: zeros)."""
    p = second_order_case(model, True, F64, True, seed=3)
    for use_v, use_t in ((True, False), (False, True)):
        got = _native(p, use_v, use_t)
        ref = _reference(p, use_v, use_t)
        for g, r in zip(got, ref):
            assert rel(g, r) <= 1e-12
    dx, dp, dg = _native(p, False, False)
    assert not dx.any() and not dp.any() and not dg.any()


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("model", MODELS)
def test_second_order_matches_eager_double_backward(kernel, model, damped):
    """Against ``_second_order`` of the autograd Function (its eager double backward, no tangent of gE), with a
    per-mesh cotangent gE and a single mesh (unbatched x)."""
    p = second_order_case(model, damped, F64, True, batch=(), seed=5)
    gE = torch.tensor(1.7, dtype=F64)
    params = _expanded(p, ())
    saved = (gE, p["x"], p["hinges"], None, p["a"], *params)
    n = len(params)
    t_params = tuple(p["t"][..., i] for i in range(n))
    rx, rps, rg = _second_order(BendingModel.parse(model), saved, None, p["v"], t_params)
    assert rx is not None and rg is not None
    p["w"] = gE.reshape(1)
    dx, dp, dg = _native(p)
    assert rel(dx, rx) <= 1e-13
    for i in range(n):
        ri = rps[i]
        assert ri is not None and rel(dp[..., i], ri) <= 1e-13
    assert rel(dg, rg) <= 1e-13


def test_second_order_hvp_consistency_and_unbatched_tangents(kernel):
    """Without tangents the position part is the HVP kernel's; tangents given as (H, 4) apply to every sample."""
    p = second_order_case("tan", True, F64, True, seed=7)
    inc = native.incidence(p["hinges"], p["V"])
    hv = native.bending_hvp(p["x"], p["v"], p["hinges"], p["a"], p["k"], p["rest"], p["c"], p["prev"], "tan", p["w"],
                            inc)
    dx, _, _ = _native(p, True, False)
    assert rel(dx, hv) <= 1e-14
    t1 = p["t"][0]
    got = native.bending_second_order(p["x"], p["v"], t1, p["hinges"], p["a"], p["k"], p["rest"], p["c"], p["prev"],
                                      "tan", p["w"], inc)
    p["t"] = t1.expand_as(p["t"]).contiguous()
    ref = _native(p)
    for g, r in zip(got, ref):
        assert torch.equal(g, r)


def test_second_order_fold_and_degenerate(kernel):
    """A folded tan hinge raises the usual ValueError; a collapsed edge stays finite (the eager policy)."""
    rest, faces = tb.scenes.single_hinge(0.0, dtype=F64)
    topo = tb.HingeTopology.from_faces(faces)
    one = torch.ones(1, dtype=F64)
    inc = native.incidence(topo.hinges, rest.shape[0])
    x = rest.clone()
    x[3] = torch.tensor([0.3, 0.8, 0.0], dtype=F64)
    v = torch.randn(x.shape, dtype=F64)
    with pytest.raises(ValueError, match="folded through"):
        native.bending_second_order(x, v, None, topo.hinges, one, one, one * 0, None, None, "tan", one, inc)
    y = rest.clone()
    y[2] = y[0]  # triangle A collapsed
    t = torch.randn(1, 4, dtype=F64)
    for model in MODELS:
        out = native.bending_second_order(y, v, t, topo.hinges, one, one, one * 0.1, one, one * 0.2, model, one, inc)
        assert all(bool(torch.isfinite(o).all()) for o in out)
