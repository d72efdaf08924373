"""HOOD's criteria (torchbend.losses.hood) against a plain PyTorch transcription of HOOD's formulas
(torchbend.testing.hood_reference_loss: autograd for every derivative, hinges, rest frames, normals and
nearest centroids computed independently), on a curved, stretched garment over a moving body."""
from __future__ import annotations

import math

import pytest
import torch

import torchbend as tb
from torchbend.losses import hood
from torchbend.mesh.garments import skirt
from torchbend.mesh.procedural import grid, mannequin
from torchbend.testing import hood_reference_loss

TERMS = ("stretching", "bending", "inertia", "gravity", "collision", "friction")


def _scene(B: int = 3, seed: int = 0, dtype=torch.float64):
    """A welded flared skirt (curved rest shape) on the mannequin's hips, stretched 5% along and squeezed around,
    three states per sample; the body translated and turned per step."""
    g = torch.Generator().manual_seed(seed)
    pos, faces, _ = skirt(16, 6, dtype=dtype)
    rest, faces = tb.mesh.clean(pos, faces)
    body, body_faces = mannequin(2, 8, 4, dtype=dtype)

    def turn(p, angle, shift):
        c, s = math.cos(angle), math.sin(angle)
        R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
        return p @ R.T + torch.tensor(shift, dtype=dtype)

    def cloth(scale):  # narrower than the rest shape: the upper skirt cuts into the hips
        noise = 2e-3 * torch.randn((B, *rest.shape), generator=g, dtype=dtype)
        return rest * torch.tensor([scale, scale, 1.05], dtype=dtype) + noise

    bodies = [torch.stack([turn(body, 0.02 * (b + 1) * k, (0.0, 0.003 * k, -0.002 * k)) for b in range(B)])
              for k in range(3)]
    return dict(rest=rest, faces=faces, body_faces=body_faces, x_prev=cloth(0.89), x_curr=cloth(0.9),
                x=cloth(0.91), body_prev=bodies[0], body_curr=bodies[1], body_next=bodies[2])


def _materials(B, dtype=torch.float64):
    m = hood.sample_materials(B, generator=torch.Generator().manual_seed(1), dtype=dtype)
    return {k: m[k] for k in ("density", "lame_mu", "lame_lambda", "bending_coeff")}


def _terms(s, mats):
    f, r, bf = s["faces"], s["rest"], s["body_faces"]
    return {"stretching": hood.Stretching(f, r, lame_mu=mats["lame_mu"], lame_lambda=mats["lame_lambda"]),
            "bending": hood.Bending(f, r, bending_coeff=mats["bending_coeff"]),
            "inertia": hood.Inertia(f, r, density=mats["density"]),
            "gravity": hood.Gravity(f, r, density=mats["density"]),
            "collision": hood.Collision(bf),
            "friction": hood.Friction(f, r, bf, density=mats["density"])}


def _inputs(name, s):
    return {"inertia": dict(x_curr=s["x_curr"], x_prev=s["x_prev"]),
            "collision": dict(x_curr=s["x_curr"], body_curr=s["body_curr"], body_next=s["body_next"]),
            "friction": dict(x_curr=s["x_curr"], body_prev=s["body_prev"], body_curr=s["body_curr"])}.get(name, {})


def _reference(s, mats, x):
    return hood_reference_loss(x, s["faces"], s["rest"], x_curr=s["x_curr"], x_prev=s["x_prev"],
                               body_prev=s["body_prev"], body_curr=s["body_curr"], body_next=s["body_next"],
                               body_faces=s["body_faces"], **mats)


def test_scene_exercises_every_term():
    s = _scene()
    ref = _reference(s, _materials(3), s["x"])
    for name in TERMS:
        assert bool((ref[name] != 0).all()), name  # contact and friction are active in every sample


@pytest.mark.parametrize("name", TERMS)
def test_values_and_gradients_match_the_transcription(name):
    s, mats = _scene(), _materials(3)
    term = _terms(s, mats)[name]
    x = s["x"].clone().requires_grad_()
    value = term(x, **_inputs(name, s))
    (grad,) = torch.autograd.grad(value.sum(), x)
    xr = s["x"].clone().requires_grad_()
    ref = _reference(s, mats, xr)[name]
    (grad_ref,) = torch.autograd.grad(ref.sum(), xr)
    assert value.shape == (3,)
    torch.testing.assert_close(value, ref.detach(), rtol=1e-12, atol=0)
    err = float((grad - grad_ref).abs().max() / grad_ref.abs().max())
    assert err <= 1e-12, f"{name}: gradient differs by {err:.2e} of its largest entry"


def test_unbatched_equals_each_sample():
    s, mats = _scene(B=2), _materials(2)
    for name, term in _terms(s, {k: v[0] for k, v in mats.items()}).items():
        one = {k: (v[0] if torch.is_tensor(v) and v.ndim == 3 else v) for k, v in _inputs(name, s).items()}
        batched = {k: (v[:1] if torch.is_tensor(v) and v.ndim == 3 else v) for k, v in _inputs(name, s).items()}
        a, b = term(s["x"][0], **one), term(s["x"][:1], **batched)
        assert a.shape == ()
        torch.testing.assert_close(a, b[0], rtol=1e-14, atol=0)


def test_bending_gradcheck_and_second_derivatives():
    """The compiled hinge angle with an x-dependent stiffness: gradcheck and gradgradcheck against finite
    differences, also at a flat hinge."""
    x0, faces = grid(3, 3, dtype=torch.float64)
    term = hood.Bending(faces, x0, bending_coeff=torch.tensor([2.0, 0.5], dtype=torch.float64))
    x = torch.stack([x0, x0]) + 0.05 * torch.randn(2, *x0.shape, generator=torch.Generator().manual_seed(3),
                                                   dtype=torch.float64)
    x[1] = x0  # flat
    x.requires_grad_()
    assert torch.autograd.gradcheck(lambda y: term(y), (x,))
    assert torch.autograd.gradgradcheck(lambda y: term(y, bending_coeff=2.0), (x[:1].detach().requires_grad_(),))


def test_stretching_gradgradcheck_and_material_gradients():
    x0, faces = grid(3, 3, dtype=torch.float64)
    mu = torch.tensor([2e4, 3e4], dtype=torch.float64, requires_grad=True)
    lam = torch.tensor([7e4, -1e4], dtype=torch.float64, requires_grad=True)  # lam >= 2 mu and lam < 0: stable in 2-D
    term = hood.Stretching(faces, x0, lame_mu=mu, lame_lambda=lam)
    x = (torch.stack([x0, x0]) * 1.03 + 0.01 * torch.randn(2, *x0.shape, generator=torch.Generator().manual_seed(4),
                                                           dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda y, m, l: term(y, lame_mu=m, lame_lambda=l), (x, mu, lam))
    assert torch.autograd.gradgradcheck(lambda y: term(y), (x,))


def test_invariants_rest_and_rigid_motion():
    s = _scene(B=1)
    mats = {k: v for k, v in _materials(1).items()}
    t = _terms(s, mats)
    rest = s["rest"][None]
    assert float(t["stretching"](rest)) == pytest.approx(0.0, abs=1e-20)
    # a rigid rotation changes neither stretching nor bending
    c, sn = math.cos(0.7), math.sin(0.7)
    R = torch.tensor([[c, 0, sn], [0, 1, 0], [-sn, 0, c]], dtype=torch.float64)
    x = s["x"]
    for name in ("stretching", "bending"):
        torch.testing.assert_close(t[name](x @ R.T), t[name](x), rtol=1e-12, atol=0)


def test_collision_weight_ramp():
    c = hood.Collision(torch.tensor([[0, 1, 2]]), weight_start=5e3, weight_max=5e5, start_rampup_iteration=10,
                       n_rampup_iterations=100)
    assert c.weight(0) == c.weight(10) == 5e3
    assert c.weight(60) == pytest.approx(5e3 + 0.5 * (5e5 - 5e3))
    assert c.weight(10**6) == 5e5


def test_inertia_first_step_dt():
    s, mats = _scene(B=2), _materials(2)
    term = _terms(s, mats)["inertia"]
    kw = _inputs("inertia", s)
    regular = term(s["x"], **kw)
    first = term(s["x"], **kw, first_step=torch.tensor([True, False]))
    torch.testing.assert_close(first[0], regular[0] * (hood.REGULAR_DT / hood.FIRST_STEP_DT) ** 2, rtol=1e-13, atol=0)
    torch.testing.assert_close(first[1], regular[1], rtol=0, atol=0)


def test_composes_with_cloth_loss():
    s, mats = _scene(), _materials(3)
    loss = tb.ClothLoss(_terms(s, mats), reduction="none")
    total, parts = loss(s["x"], x_curr=s["x_curr"], x_prev=s["x_prev"], body_prev=s["body_prev"], body_curr=s["body_curr"],
                 body_next=s["body_next"])
    ref = _reference(s, mats, s["x"])
    torch.testing.assert_close(total, sum(ref[n] for n in TERMS), rtol=1e-12, atol=0)
    for name in TERMS:
        torch.testing.assert_close(parts[name], ref[name].detach(), rtol=1e-12, atol=0)


def test_material_conversions():
    # HOOD's default bending_coeff is 50 D of its default material (mu, lambda -> Y, nu; t = 4.7e-4 m)
    mu, lam = hood.DEFAULT_MATERIAL["lame_mu"], hood.DEFAULT_MATERIAL["lame_lambda"]
    nu = lam / (2 * mu + lam)
    young = 4 * mu * (mu + lam) / (2 * mu + lam)
    coeff = hood.bending_coeff_from_material(young, hood.DEFAULT_MATERIAL["thickness"], nu)
    assert coeff == pytest.approx(hood.DEFAULT_MATERIAL["bending_coeff"], rel=1e-6)
    assert hood.lame_from_material(young, nu) == pytest.approx((mu, lam), rel=1e-12)
    # HOOD's cloth is 50/12 times stiffer in bending than torchbend's stiffness of the same material
    k = tb.stiffness_from_material(2e5, 5e-4, 0.3)
    assert hood.stiffness_from_bending_coeff(hood.bending_coeff_from_material(2e5, 5e-4, 0.3)) / k == pytest.approx(50 / 12)
    # and the conversion reproduces HOOD's hinge energy with torchbend's energy at rest lengths
    x0, faces = grid(4, 4, dtype=torch.float64)
    x = x0.clone()
    x[..., 2] = 0.1 * torch.sin(3 * x0[..., 0])
    term = hood.Bending(faces, x0, bending_coeff=3e-5)
    ours = tb.BendingEnergy(faces, x0, model="quadratic", stiffness=hood.stiffness_from_bending_coeff(3e-5),
                            rest_angles=0.0)
    torch.testing.assert_close(term(x0 + (x - x0) * 1e-3), ours(x0 + (x - x0) * 1e-3), rtol=1e-5, atol=0)


def test_sampler_ranges_and_independence():
    m = hood.sample_materials(4000, generator=torch.Generator().manual_seed(0))
    for name, (lo, hi) in hood.HOOD_RANGES.items():
        assert float(m[name].min()) >= lo and float(m[name].max()) <= hi
        assert float(m[f"{name}_input"].min()) >= 0 and float(m[f"{name}_input"].max()) <= 1
    frac = float((m["lame_lambda"] >= 2 * m["lame_mu"]).double().mean())
    assert 0.25 < frac < 0.37  # about 31% of HOOD's draws have lambda >= 2 mu
    # log-uniform bending_coeff: its median is the geometric mean of the range
    lo, hi = hood.HOOD_RANGES["bending_coeff"]
    assert float(m["bending_coeff"].median()) == pytest.approx(math.sqrt(lo * hi), rel=0.15)


@pytest.mark.parametrize("bad, match", [
    (dict(lame_mu=-1.0), "lame_mu must be positive"),
    (dict(lame_lambda=-3e4, lame_mu=2e4), "2-D stability"),
])
def test_bad_materials_are_value_errors(bad, match):
    x0, faces = grid(3, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=match):
        term = hood.Stretching(faces, x0, **bad)
        term(x0)


def test_bad_body_inputs_are_value_errors():
    s = _scene(B=1)
    c = hood.Collision(s["body_faces"])
    with pytest.raises(ValueError, match="body_next"):
        c(s["x"], x_curr=s["x_curr"], body_curr=s["body_curr"], body_next=s["body_next"][:, :5])
    with pytest.raises(ValueError, match="x_curr"):
        c(s["x"], x_curr=s["x_curr"][:, :5], body_curr=s["body_curr"], body_next=s["body_next"])
    with pytest.raises(ValueError, match="body_faces"):
        hood.Collision(torch.zeros(0, 3, dtype=torch.int64))


def test_float32_follows_input():
    s = _scene(B=1, dtype=torch.float32)
    mats = {k: v.float() for k, v in _materials(1).items()}
    for name, term in _terms(s, mats).items():
        v = term(s["x"], **_inputs(name, s))
        assert v.dtype == torch.float32 and bool(torch.isfinite(v).all()), name


def test_criteria_is_hoods_batch_mean():
    s, mats = _scene(), _materials(3)
    loss = hood.criteria(s["faces"], s["rest"], s["body_faces"], density=mats["density"], lame_mu=mats["lame_mu"],
                         lame_lambda=mats["lame_lambda"], bending_coeff=mats["bending_coeff"])
    total, parts = loss(s["x"], x_curr=s["x_curr"], x_prev=s["x_prev"], body_prev=s["body_prev"],
                        body_curr=s["body_curr"], body_next=s["body_next"], iteration=0)
    ref = _reference(s, mats, s["x"])
    assert set(parts) == set(TERMS)
    torch.testing.assert_close(total, torch.stack([ref[n] for n in TERMS]).sum(0).mean(), rtol=1e-12, atol=0)


def test_nearest_kdtree_equals_brute_force():
    """The CPU's k-d tree and the brute-force blocks the GPU runs find the same centroids and distances (also
    with the bound friction uses, where the points beyond it only need to be marked)."""
    from torchbend.losses.hood._common import nearest

    g = torch.Generator().manual_seed(7)
    points, targets = torch.rand(2, 500, 3, generator=g, dtype=torch.float64), torch.rand(2, 300, 3, generator=g,
                                                                                        dtype=torch.float64)
    d_tree, i_tree = nearest(points, targets, method="kdtree")
    d_brute, i_brute = nearest(points, targets, method="brute")
    assert torch.equal(i_tree, i_brute)
    torch.testing.assert_close(d_tree, d_brute, rtol=1e-12, atol=1e-15)
    d_b, i_b = nearest(points, targets, bound=0.05, method="kdtree")
    inside = d_brute < 0.05**2
    assert bool(inside.any()) and bool((~inside).any())
    assert torch.equal(i_b[inside], i_brute[inside]) and bool(torch.isinf(d_b[~inside]).all())


def test_signatures_of_the_issue_and_hoods_names():
    """``Stretching(faces, rest, mu, lam, thickness)`` and ``Bending(faces, rest, bending_coeff)`` positionally, HOOD's
    ``lame_mu``/``lame_lambda`` as keywords (at construction and per call), not both."""
    x0, faces = grid(3, 3, dtype=torch.float64)
    x = x0 * 1.02
    a = hood.Stretching(faces, x0, 2e4, 5e4, 1e-3)(x)
    b = hood.Stretching(faces, x0, lame_mu=2e4, lame_lambda=5e4, thickness=1e-3)(x)
    c = hood.Stretching(faces, x0, thickness=1e-3)(x, mu=2e4, lam=5e4)
    assert float(a) > 0 and float(a) == float(b) == float(c)
    assert float(hood.Bending(faces, x0, 2e-5)(x)) == float(hood.Bending(faces, x0, bending_coeff=2e-5)(x))
    with pytest.raises(ValueError, match="mu or lame_mu, not both"):
        hood.Stretching(faces, x0, mu=1e4, lame_mu=1e4)


def test_hood_losses_compile_fullgraph():
    """HOOD's stretching and bending in a ClothLoss under torch.compile(fullgraph=True): no graph break (the
    material checks run eagerly only), the loss and a training step's gradient as the eager ones."""
    s, mats = _scene(), _materials(3)
    terms = _terms(s, mats)
    loss = tb.ClothLoss({k: terms[k] for k in ("stretching", "bending")}, reduction="sum")

    def step(y):
        value = loss(y)[0]
        value.backward()
        return value.detach()

    torch._dynamo.reset()
    try:
        y1, y2 = s["x"].clone().requires_grad_(), s["x"].clone().requires_grad_()
        with torch._dynamo.config.patch(trace_autograd_ops=True):
            l1 = torch.compile(step, fullgraph=True)(y1)
        l2 = step(y2)
    finally:
        torch._dynamo.reset()
    torch.testing.assert_close(l1, l2, rtol=4 * torch.finfo(torch.float64).eps, atol=0)
    g1, g2 = y1.grad, y2.grad
    assert g1 is not None and g2 is not None
    torch.testing.assert_close(g1, g2, rtol=1e-13, atol=1e-13 * float(g2.abs().max()))
