"""Bending at the extremes (issue: reliability): folded tan hinges in every entry point, continuity of the
quadratic and sin energies through +-pi, meshes without hinges, scale-relative degeneracy tests and
errors that name the culprit."""
import math

import mpmath as mp
import pytest
import torch

import torchbend as tb
from torchbend.backends import native
from torchbend.testing import plain_bending_energy

BACKENDS = ["eager", pytest.param("native", marks=pytest.mark.skipif(native.load() is None,
                                                                      reason="C++ extension unavailable"))]


def _call(bend, x, entry):
    v = torch.ones_like(x)
    return {
        "forward": lambda: bend(x),
        "gradient": lambda: bend.gradient(x),
        "backward": lambda: torch.autograd.grad(bend(x.clone().requires_grad_()), x, allow_unused=True),
        "hvp": lambda: bend.hvp(x, v),
        "hvp_clamp": lambda: bend.hvp(x, v, projection="clamp"),
        "hvp_gauss_newton": lambda: bend.hvp(x, v, projection="gauss_newton"),
        "hinge_hessians": lambda: bend.hinge_hessians(x),
        "hinge_hessians_abs": lambda: bend.hinge_hessians(x, projection="abs"),
        "hessian_triangle": lambda: bend.hessian(x),
        "hessian_hinge": lambda: bend.hessian(x, assembly="hinge"),
        "hessian_clamp": lambda: bend.hessian(x, projection="clamp"),
    }[entry]()


ENTRIES = ["forward", "gradient", "backward", "hvp", "hvp_clamp", "hvp_gauss_newton", "hinge_hessians",
           "hinge_hessians_abs", "hessian_triangle", "hessian_hinge", "hessian_clamp"]


def _folded(dtype):
    """A hinge folded flat onto itself (|theta| = pi in the dtype) on a flat rest shape."""
    rest, faces = tb.scenes.single_hinge(0.0, dtype=torch.float64)
    x = rest.clone()
    x[3] = torch.tensor([0.3, 0.8, 0.0], dtype=torch.float64)  # wing B on top of wing A
    return faces, rest.to(dtype), x.to(dtype)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("entry", ENTRIES)
def test_folded_tan_hinge_raises_in_every_entry_point(entry, dtype, backend):
    faces, rest, x = _folded(dtype)
    bend = tb.BendingEnergy(faces, rest, model="tan", backend=backend, stiffness=1.0)
    assert float(tb.hinge_angles(x, bend.topology).abs()) == pytest.approx(math.pi)
    with pytest.raises(ValueError, match=r"hinges \[0\] have folded through"):
        _call(bend, x, entry)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("entry", ENTRIES)
def test_float32_hinge_just_inside_the_barrier_is_refused_consistently(entry, backend):
    """pi - 1e-10 rounds to float32's pi (> pi): every entry point raises, none returns sign-flipped values."""
    rest, faces = tb.scenes.single_hinge(0.0, dtype=torch.float32)
    x, _ = tb.scenes.single_hinge(math.pi - 1e-10, dtype=torch.float32)
    bend = tb.BendingEnergy(faces, rest, model="tan", backend=backend, stiffness=1.0)
    with pytest.raises(ValueError, match="folded through"):
        _call(bend, x, entry)


@pytest.mark.parametrize("backend", BACKENDS)
def test_tan_just_inside_the_barrier_is_finite_and_correct(dtype, backend):
    """The largest angles below pi that the dtype resolves: finite values with the right sign."""
    delta = 1e-6 if dtype == torch.float64 else 1e-3
    rest, faces = tb.scenes.single_hinge(0.0, dtype=dtype)
    x, _ = tb.scenes.single_hinge(math.pi - delta, dtype=dtype)
    bend = tb.BendingEnergy(faces, rest, model="tan", backend=backend, stiffness=1.0)
    xd = x.double()
    ref = tb.BendingEnergy(faces, rest.double(), model="tan", backend="eager", stiffness=1.0)
    g, g_ref = bend.gradient(x), ref.gradient(xd)
    Hb, Hb_ref = bend.hinge_hessians(x), ref.hinge_hessians(xd)
    tol = 1e-9 if dtype == torch.float64 else 2e-2  # float32 carries the rounding of the inputs near pi
    assert torch.isfinite(Hb).all() and torch.isfinite(g).all()
    assert torch.linalg.norm(g.double() - g_ref) <= tol * torch.linalg.norm(g_ref)
    assert torch.linalg.norm(Hb.double() - Hb_ref) <= tol * torch.linalg.norm(Hb_ref)


# ------------------------------------------------------------------------------ continuity through +-pi
def _term40(model: str, theta: float, ref: float, a: float):
    """``a (phi(theta') - phi(ref))^2`` at 40 digits, ``theta'`` on the branch nearest ``ref``."""
    with mp.workdps(40):
        t, r = mp.mpf(theta), mp.mpf(ref)
        t = t + 2 * mp.pi if t - r <= -mp.pi else (t - 2 * mp.pi if t - r > mp.pi else t)
        f = (lambda u: u) if model == "quadratic" else (lambda u: 2 * mp.sin(u / 2))
        return mp.mpf(a) * (f(t) - f(r)) ** 2


def _turning(theta: float):
    x, faces = tb.scenes.single_hinge(theta, dtype=torch.float64)
    return x, faces


@pytest.mark.parametrize("model", ["quadratic", "sin"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_energy_continuous_through_pi(model, backend):
    """A rest angle near pi: a 2e-6 rad turn through pi costs ~k a (1e-6)^2, not a jump of 2 pi."""
    rest_angle = math.pi - 1e-6
    rest, faces = _turning(rest_angle)
    bend = tb.BendingEnergy(faces, rest, model=model, stiffness=3.0, backend=backend)
    before, _ = _turning(math.pi - 2e-6)
    after, _ = _turning(-math.pi + 1e-6)  # turned on through pi by 2e-6 rad in all
    a = float(bend.weights[0])

    def expected(x):
        return 3.0 * float(_term40(model, float(bend.angles(x)), float(bend.rest_angles[0]), a))

    for y in (before, after):
        assert float(bend(y)) == pytest.approx(expected(y), rel=1e-6)
    assert float(bend(after)) < 1e-10  # not a jump of (2 pi)^2
    # the whole sweep across pi is small and smooth
    angles = [math.pi - 3e-6 + i * 1e-6 for i in range(7)]
    E = torch.stack([bend(_turning(math.remainder(t, 2 * math.pi))[0]) for t in angles])
    assert float(E.max()) < 1e-9
    d2 = E[2:] - 2 * E[1:-1] + E[:-2]
    assert float(d2.abs().max()) <= 4 * 3.0 * a * (1e-6) ** 2 + 1e-20


@pytest.mark.parametrize("model", ["quadratic", "sin"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_derivatives_through_pi_match_references(model, backend):
    """Past pi (theta = -pi + 0.2, rest = pi - 0.1): gradient vs central differences over an epsilon sweep,
    blocks and hvp vs autograd of the plain (branch-aware) energy, eager and compiled."""
    rest_angle = math.pi - 0.1
    rest, faces = _turning(rest_angle)
    x, _ = _turning(-math.pi + 0.2)
    x = x + 0.05 * torch.randn(x.shape, dtype=x.dtype, generator=torch.Generator().manual_seed(0))
    bend = tb.BendingEnergy(faces, rest, model=model, stiffness=2.0, backend=backend)
    assert float(bend.angles(x)) < -2.5  # the hinge has turned through pi
    g = bend.gradient(x)
    errs = []
    for h in (1e-4, 1e-5, 1e-6):
        fd = torch.zeros(12, dtype=x.dtype)
        for i in range(12):
            d = torch.zeros(12, dtype=x.dtype)
            d[i] = h
            fd[i] = (bend(x + d.view(4, 3)) - bend(x - d.view(4, 3))) / (2 * h)
        errs.append(float((fd - g.reshape(-1)).abs().max()))
    assert min(errs) < 1e-8 * max(1.0, float(g.abs().max()))
    plain = lambda y: plain_bending_energy(y, bend.hinges, bend.weights, 2.0, bend.rest_angles, model)  # noqa: E731
    H_ref = torch.func.hessian(plain)(x).reshape(12, 12)
    assert torch.allclose(bend.hinge_hessians(x)[0], H_ref, atol=1e-10, rtol=1e-9)
    v = torch.randn(x.shape, dtype=x.dtype, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(bend.hvp(x, v).reshape(-1), H_ref @ v.reshape(-1), atol=1e-10, rtol=1e-9)
    assert torch.allclose(torch.from_numpy(tb.to_scipy(bend.hessian(x)).toarray()), H_ref, atol=1e-10, rtol=1e-9)


@pytest.mark.parametrize("model", ["quadratic", "sin"])
def test_viscous_term_continuous_through_pi(model):
    """theta_prev near pi, theta just past -pi: the viscous term sees a small change, not 2 pi."""
    rest, faces = _turning(0.0)
    bend = tb.BendingEnergy(faces, rest, model=model, stiffness=0.0, damping=1.0)
    x, _ = _turning(-math.pi + 1e-3)
    prev = torch.tensor([math.pi - 1e-3], dtype=torch.float64)
    E = float(bend(x, theta_prev=prev, dt=0.1))
    a = float(bend.weights[0])
    assert E == pytest.approx(10.0 * float(_term40(model, float(bend.angles(x)), float(prev), a)), rel=1e-9, abs=1e-30)
    assert E < 1e-3  # not 10 a (2 pi)^2
    xr = x.clone().requires_grad_()
    (g,) = torch.autograd.grad(bend(xr, theta_prev=prev, dt=0.1), xr)
    plain = plain_bending_energy(xr, bend.hinges, bend.weights, 0.0, bend.rest_angles, model,
                                 c=torch.tensor(10.0, dtype=torch.float64), prev=prev)
    (g_ref,) = torch.autograd.grad(plain, xr)
    assert torch.allclose(g, g_ref, rtol=1e-9, atol=1e-14)
    assert torch.allclose(bend.gradient(x, theta_prev=prev, dt=0.1), g_ref, rtol=1e-9, atol=1e-14)


def test_tan_is_not_unwrapped():
    """tan keeps theta: its energy near -pi with a rest angle near pi is huge (the barrier), not small."""
    rest, faces = _turning(math.pi - 0.1)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1.0)
    x, _ = _turning(-math.pi + 0.1)
    assert float(bend(x)) > 100.0


# ------------------------------------------------------------------------------ meshes without hinges, errors
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kw", [{}, {"assembly": "hinge"}, {"projection": "clamp"}, {"projection": "gauss_newton"}])
def test_mesh_without_hinges_gives_zero_hessian(kw, backend):
    x, faces = tb.scenes.single_hinge(0.3, dtype=torch.float64)
    bend = tb.BendingEnergy(faces[:1], x[:3], backend=backend, stiffness=1.0)
    assert bend.hinge_count == 0
    H = bend.hessian(x[:3], **kw)
    assert H.shape == (9, 9) and H.layout == torch.sparse_csr
    assert float(H.to_dense().abs().max()) == 0.0
    assert bend.hinge_hessians(x[:3]).shape == (0, 12, 12)
    assert float(bend.hvp(x[:3], torch.ones_like(x[:3])).abs().max()) == 0.0


@pytest.mark.parametrize("cls", ["bending", "membrane"])
def test_face_index_out_of_range_names_the_face(cls):
    x, _ = tb.scenes.single_hinge(0.3, dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [1, 0, 9]])
    with pytest.raises(ValueError, match=r"face 1 = \[1, 0, 9\] has index 9 >= V = 4"):
        if cls == "bending":
            tb.BendingEnergy(faces, x, stiffness=1.0)
        else:
            tb.MembraneEnergy(faces, x, young=1e3, poisson=0.3, thickness=1e-3)


def test_unused_vertices_are_allowed():
    x, faces = tb.scenes.single_hinge(0.3, dtype=torch.float64)
    x5 = torch.cat((x, torch.zeros(1, 3, dtype=x.dtype)))
    bend = tb.BendingEnergy(faces, x5, stiffness=1.0)
    assert bend.vertex_count == 5 and float(bend.gradient(x5)[4].abs().max()) == 0.0


@pytest.mark.parametrize("scale", [1e-7, 1e6])
def test_float32_degeneracy_tests_are_relative_to_the_mesh(scale):
    """A float32 mesh with edges far below float32's epsilon (or far above 1) is well shaped: accepted, and
    its energy and gradient scale as the float64 ones do."""
    v, f = tb.scenes.grid(4, 4)
    rest = (v.double() * scale)
    x = rest.clone()
    x[5, 2] += 0.2 * scale
    b64 = tb.BendingEnergy(f, rest, model="quadratic", stiffness=1.0)
    b32 = tb.BendingEnergy(f, rest.float(), model="quadratic", stiffness=1.0)
    assert torch.allclose(b32.weights.double(), b64.weights, rtol=1e-6)
    assert float(b32(x.float())) == pytest.approx(float(b64(x)), rel=1e-4)
    g32, g64 = b32.gradient(x.float()).double(), b64.gradient(x)
    assert torch.linalg.norm(g32 - g64) <= 1e-4 * torch.linalg.norm(g64)


def test_zero_length_rest_edge_is_still_an_error():
    v, f = tb.scenes.grid(4, 4)
    v = v.double()
    v[1] = v[0]
    with pytest.raises(ValueError, match=r"zero-length edges \[\(0, 1\)\]"):
        tb.BendingEnergy(f, v, stiffness=1.0)
