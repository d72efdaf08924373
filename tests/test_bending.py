"""Bending energy: derivatives against independent references, invariants, extremes, bad input."""
import math
from unittest import mock

import pytest
import torch

import torchbend as tb
from torchbend import BendingEnergy
from torchbend.energies._bending_fn import bending_energy_raw
from torchbend.ops import hinge as geometry
from torchbend.options import Backend
from torchbend.testing import plain_bending_energy, plain_hinge_angles

from .helpers import MODELS, reference_hessian, rel

F64 = torch.float64


def _module(rest, faces, model, damped=False, **kw):
    H = tb.HingeTopology.from_faces(faces).hinge_count
    gen = torch.Generator().manual_seed(11)
    k = 0.5 + torch.rand(H, generator=gen, dtype=F64)
    return BendingEnergy(faces, rest, model=model, stiffness=k, damping=0.3 if damped else None, **kw)


def _damping_args(bend, damped, x):
    if not damped:
        return {}
    gen = torch.Generator().manual_seed(5)
    prev = bend.angles(x) + 0.05 * torch.randn(bend.hinge_count, generator=gen, dtype=F64)
    return {"theta_prev": prev, "dt": 0.1}


def _plain(bend, x, kw):
    c = None if not kw else bend.damping / kw["dt"]
    prev = kw.get("theta_prev")
    return plain_bending_energy(x, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, bend.model, c, prev)


# ----------------------------------------------------------------------------- angles
@pytest.mark.parametrize("theta", [0.0, 0.3, -0.7, 1.5, -2.9, 3.1, math.pi - 1e-6, -(math.pi - 1e-6)])
def test_single_hinge_angle_and_sign(theta):
    x, faces = tb.scenes.single_hinge(theta, dtype=F64)
    topo = tb.HingeTopology.from_faces(faces)
    got = tb.hinge_angles(x, topo)
    assert got.shape == (1,)
    assert abs(got.item() - theta) < 1e-12


def test_flat_angle_is_exactly_zero_and_sphere_positive():
    x, faces = tb.scenes.grid(4, 4, dtype=F64)
    theta = tb.hinge_angles(x, tb.HingeTopology.from_faces(faces))
    assert theta.shape == (21,) and torch.equal(theta, torch.zeros_like(theta))
    xs, fs = tb.scenes.icosphere(1, dtype=F64)
    assert (tb.hinge_angles(xs, tb.HingeTopology.from_faces(fs)) > 0).all()


def test_angles_match_plain_formula_batched(sheet):
    rest, faces, x = sheet
    topo = tb.HingeTopology.from_faces(faces)
    xb = torch.stack([x, rest, 2 * x])
    assert rel(tb.hinge_angles(xb, topo), plain_hinge_angles(xb, topo.hinges)) < 1e-14


# ----------------------------------------------------------------------------- derivatives vs references
@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("model", MODELS)
def test_energy_gradient_hvp_match_autograd(sheet, model, damped):
    rest, faces, x = sheet
    bend = _module(rest, faces, model, damped)
    kw = _damping_args(bend, damped, x)
    y = x.clone().requires_grad_()
    y_ref = x.clone().requires_grad_()
    E, E_ref = bend(y, **kw), _plain(bend, y_ref, kw)
    assert abs(E.item() - E_ref.item()) <= 1e-13 * abs(E_ref.item())
    (g,) = torch.autograd.grad(E, y, create_graph=True)
    (g_ref,) = torch.autograd.grad(E_ref, y_ref, create_graph=True)
    assert rel(g, g_ref) < 1e-13
    assert rel(bend.gradient(x, **kw), g_ref) < 1e-13
    v = torch.randn_like(x)
    (hv_ref,) = torch.autograd.grad(g_ref, y_ref, v)
    (hv_db,) = torch.autograd.grad(g, y, v)
    assert rel(bend.hvp(x, v, **kw), hv_ref) < 1e-12
    assert rel(hv_db, hv_ref) < 1e-12


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("model", MODELS)
def test_finite_difference_epsilon_sweep(sheet, model, damped):
    """Central differences of E (for the gradient) and of grad E (for the HVP) along a random
    direction: the error must fall like eps^2 until round-off, reaching <= 1e-8 relative."""
    rest, faces, x = sheet
    bend = _module(rest, faces, model, damped)
    kw = _damping_args(bend, damped, x)
    v = torch.randn_like(x)
    dE = (bend.gradient(x, **kw) * v).sum().item()
    Hv = bend.hvp(x, v, **kw)
    errs_g, errs_h = [], []
    for eps in [1e-2, 1e-3, 1e-4, 1e-5, 1e-6]:
        fd = (bend(x + eps * v, **kw) - bend(x - eps * v, **kw)).item() / (2 * eps)
        errs_g.append(abs(fd - dE) / abs(dE))
        fd_h = (bend.gradient(x + eps * v, **kw) - bend.gradient(x - eps * v, **kw)) / (2 * eps)
        errs_h.append(rel(fd_h, Hv))
    for errs in (errs_g, errs_h):
        assert min(errs) < 1e-8, errs
        # truncation regime: a 10x smaller step gives a >= 50x smaller error
        assert errs[2] < errs[1] / 50, errs


def _check_first_and_second_derivatives(bend, args, forward_ad=False):
    """gradcheck and gradgradcheck of the raw energy in (x, k, rest[, c, prev]); optionally forward mode."""

    def f(x, *params):
        return bending_energy_raw(x, bend.hinges, bend.weights, *params, model=bend.model)

    assert torch.autograd.gradcheck(f, args)
    assert torch.autograd.gradgradcheck(f, args)
    if forward_ad:
        assert torch.autograd.gradcheck(f, args, check_forward_ad=True, check_backward_ad=False,
                                        check_batched_grad=False, check_undefined_grad=False)


@pytest.mark.parametrize("damped", [False, True], ids=["elastic", "viscous"])
@pytest.mark.parametrize("model", MODELS)
def test_gradcheck_gradgradcheck_positions_stiffness_rest(model, damped):
    """In x, stiffness and rest angles (forward mode too), and with the viscous term in c and theta_prev."""
    rest, faces = tb.scenes.random_curved_sheet(3, 3, amplitude=0.4, seed=2 if damped else 1, dtype=F64)
    bend = BendingEnergy(faces, rest, model=model, stiffness=1.0)
    H = bend.hinge_count
    x = (rest + 0.05 * torch.randn_like(rest)).requires_grad_()
    k = (0.5 + torch.rand(H, dtype=F64)).requires_grad_()
    if not damped:
        r = (bend.rest_angles + 0.1 * torch.randn(H, dtype=F64)).requires_grad_()
        _check_first_and_second_derivatives(bend, (x, k, r), forward_ad=True)
        return
    r = bend.rest_angles.clone().requires_grad_()
    c = (0.5 + torch.rand(H, dtype=F64)).requires_grad_()
    p = (bend.rest_angles + 0.1 * torch.randn(H, dtype=F64)).requires_grad_()
    _check_first_and_second_derivatives(bend, (x, k, r, c, p))


def test_gradients_flow_to_stiffness_and_rest_angles(sheet):
    rest, faces, x = sheet
    H = tb.HingeTopology.from_faces(faces).hinge_count
    k = torch.nn.Parameter(torch.full((H,), 0.7, dtype=F64))
    r = torch.nn.Parameter(torch.zeros(H, dtype=F64) + 0.1)
    bend = BendingEnergy(faces, rest, model="tan", stiffness=k, rest_angles=r)
    assert {n for n, _ in bend.named_parameters()} == {"stiffness", "rest_angles"}
    bend(x).backward()
    k_ref = k.detach().clone().requires_grad_()
    r_ref = r.detach().clone().requires_grad_()
    plain_bending_energy(x, bend.hinges, bend.weights, k_ref, r_ref, "tan").backward()
    assert k.grad is not None and r.grad is not None and k_ref.grad is not None and r_ref.grad is not None
    assert rel(k.grad, k_ref.grad) < 1e-13
    assert rel(r.grad, r_ref.grad) < 1e-13
    # scalar learnable stiffness
    ks = torch.nn.Parameter(torch.tensor(2.0, dtype=F64))
    bend = BendingEnergy(faces, rest, model="sin", stiffness=ks)
    E = bend(x)
    E.backward()
    assert ks.grad is not None and ks.grad.shape == () and abs(ks.grad.item() - E.item() / 2.0) < 1e-12 * abs(E.item())


# ----------------------------------------------------------------------------- analytic double backward
def test_double_backward_runs_the_analytic_hvp(sheet):
    """The eager path (the compiled path's analogue: tests/test_ops.py)."""
    rest, faces, x = sheet
    bend = _module(rest, faces, "tan")
    bend.backend = Backend.EAGER
    y = x.clone().requires_grad_()
    (g,) = torch.autograd.grad(bend(y), y, create_graph=True)
    # the first derivative is the output of one analytic node, not an autograd graph of ops
    assert g.grad_fn.name() == "TanBendingGradientBackward"
    inner = {fn for fn, _ in g.grad_fn.next_functions if fn is not None}
    assert all(type(fn).__name__ == "AccumulateGrad" for fn in inner)  # leaves only: y
    calls = []
    orig = geometry.hinge_angle_gradient_hvp_soa

    def counting(xs, vs=None):
        calls.append(vs is not None)
        return orig(xs, vs)

    v = torch.randn_like(x)
    with mock.patch.object(geometry, "hinge_angle_gradient_hvp_soa", side_effect=counting):
        (hv,) = torch.autograd.grad(g, y, v)
    assert calls == [True]  # one call of the closed-form HVP kernel, nothing else
    assert rel(hv, bend.hvp(x, v)) < 1e-14


def test_torch_func_vmap_jacrev_hessian(sheet):
    rest, faces, x = sheet
    bend = _module(rest, faces, "tan")

    def e(y):
        return bend(y)

    def e_ref(y):
        return plain_bending_energy(y, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, "tan")

    n = 3 * x.shape[0]
    H_ref = torch.func.hessian(e_ref)(x).reshape(n, n)
    assert rel(torch.func.hessian(e)(x).reshape(n, n), H_ref) < 1e-13
    assert rel(torch.func.jacrev(torch.func.jacrev(e))(x).reshape(n, n), H_ref) < 1e-13
    xb = x + 0.01 * torch.randn((4,) + x.shape, dtype=F64)
    assert rel(torch.func.vmap(e)(xb), e_ref(xb)) < 1e-13
    assert rel(torch.func.vmap(torch.func.grad(e))(xb), torch.func.vmap(torch.func.grad(e_ref))(xb)) < 1e-13
    # and the hvp kernel reproduces the Hessian
    v = torch.randn_like(x)
    assert rel(bend.hvp(x, v).reshape(-1), H_ref @ v.reshape(-1)) < 1e-13


# ----------------------------------------------------------------------------- invariants
@pytest.mark.parametrize("model", MODELS)
def test_zero_net_force_torque_and_translation_null_space(sheet, model):
    rest, faces, x = sheet
    x = x + torch.tensor([3.0, -2.0, 1.0], dtype=F64)  # away from the origin: torque is not trivial
    bend = _module(rest, faces, model)
    g = bend.gradient(x)
    scale = g.norm()
    assert g.sum(0).norm() < 1e-13 * scale
    assert torch.linalg.cross(x, g, dim=-1).sum(0).norm() < 1e-12 * scale * x.norm()
    t = torch.tensor([0.3, -1.2, 0.7], dtype=F64).expand_as(x)
    Ht = bend.hvp(x, t)
    assert Ht.norm() < 1e-13 * bend.hvp(x, torch.randn_like(x)).norm()


@pytest.mark.parametrize("theta", [0.0, 0.4, -1.3, 2.8])
def test_single_hinge_null_space_of_theta_hessian(theta):
    x, faces = tb.scenes.single_hinge(theta, dtype=F64)
    x = x + 0.1 * torch.randn_like(x)  # generic hinge
    x4 = x[None]  # (H=1, 4, 3)
    e0 = x[1] - x[0]
    scaling = (x @ e0)[:, None] * e0  # v_i = (x_i . e0) e0 (tech report sec. 7)
    Hth = geometry.hinge_angle_hessian(x4)[0]
    norm = Hth.norm()
    assert (Hth @ scaling.reshape(-1)).norm() < 1e-13 * norm * scaling.norm()
    for j in range(3):
        t = torch.zeros(4, 3, dtype=F64)
        t[:, j] = 1
        assert (Hth @ t.reshape(-1)).norm() < 1e-13 * norm
    # the full energy Hessian shares the null space (gradient is orthogonal to it)
    bend = BendingEnergy(faces, tb.scenes.single_hinge(0.2, dtype=F64)[0], model="tan", stiffness=1.0)
    assert bend.hvp(x, scaling).norm() < 1e-12 * bend.hvp(x, torch.randn_like(x)).norm()


@pytest.mark.parametrize("model", MODELS)
def test_zero_energy_and_gradient_at_rest(sheet, model):
    rest, faces, _ = sheet
    bend = _module(rest, faces, model)
    assert bend(rest).item() == 0.0
    assert bend.gradient(rest).abs().max().item() == 0.0


def test_sphere_bending_energy_matches_16_pi():
    """Tech report sec. 2: sum_h 3|e|^2 theta^2 / (A_A + A_B) -> 16 pi for a sphere (any radius)."""
    x, faces = tb.scenes.icosphere(3, radius=2.5, dtype=F64)
    assert faces.shape[0] >= 1280
    bend = BendingEnergy(faces, x, model="quadratic", stiffness=1.0, rest_angles=0.0)
    E = bend(x).item()
    assert abs(E - 16 * math.pi) < 0.03 * 16 * math.pi, E
    g = bend.gradient(x)
    assert g.sum(0).norm() < 1e-12 * g.norm()


def test_rigid_motion_and_scale_invariance(sheet):
    rest, faces, x = sheet
    bend = _module(rest, faces, "tan")
    E = bend(x)
    Q, _ = torch.linalg.qr(torch.randn(3, 3, dtype=F64))
    Q = Q * torch.det(Q)  # proper rotation
    assert abs(bend(x @ Q.T + 5.0).item() - E.item()) < 1e-12 * E.item()
    # uniform scaling of rest and deformed shape leaves E unchanged and scales the gradient by 1/s
    for s in (1e-4, 1e4):
        b = _module(s * rest, faces, "tan")
        assert abs(b(s * x).item() - E.item()) < 1e-11 * E.item()
        assert rel(s * b.gradient(s * x), bend.gradient(x)) < 1e-11


# ----------------------------------------------------------------------------- extremes
def test_flat_hinge_exact_zero_gradient_and_finite_hvp():
    x, faces = tb.scenes.grid(5, 5, dtype=F64)
    v = torch.randn_like(x)
    for model in MODELS:
        bend = BendingEnergy(faces, x, model=model, stiffness=1.0)
        assert torch.equal(bend.gradient(x), torch.zeros_like(x))
        hv = bend.hvp(x, v)
        assert torch.isfinite(hv).all()
        ref = reference_hessian(bend, x)
        assert rel(hv.reshape(-1), ref @ v.reshape(-1)) < 1e-13
        assert hv.norm() > 0  # the flat Hessian is not zero: psi'' g g^T


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_tan_finite_near_pi_and_error_at_fold(sign):
    rest, faces = tb.scenes.single_hinge(0.0, dtype=F64)
    bend = BendingEnergy(faces, rest, model="tan", stiffness=1.0)
    x, _ = tb.scenes.single_hinge(sign * (math.pi - 1e-6), dtype=F64)
    v = torch.randn_like(x)
    for out in (bend(x), bend.gradient(x), bend.hvp(x, v)):
        assert torch.isfinite(out).all()
    assert bend(x).item() > 1e12  # grows without bound by design
    folded, _ = tb.scenes.single_hinge(math.pi, dtype=F64)
    with pytest.raises(ValueError, match="folded through"):
        bend(folded)
    # the other models stay finite at the fold
    assert torch.isfinite(BendingEnergy(faces, rest, model="sin", stiffness=1.0).gradient(folded)).all()


def test_sliver_and_degenerate_deformed_triangles_are_finite():
    rest, faces = tb.scenes.random_curved_sheet(4, 4, seed=4, dtype=F64)
    bend = BendingEnergy(faces, rest, model="tan", stiffness=1.0)
    x = rest.clone()
    x[5] = x[6]  # collapse an edge: zero-area triangles in the deformed state
    v = torch.randn_like(x)
    for out in (bend(x), bend.gradient(x), bend.hvp(x, v)):
        assert torch.isfinite(out).all()
    # a sliver (aspect ratio ~ 1e-7) in the rest shape is valid and accurate
    xs, fs = tb.scenes.single_hinge(0.0, dtype=F64)
    xs[2, 1] = 1e-7
    b = BendingEnergy(fs, xs, model="quadratic", stiffness=1.0)
    y = xs + 1e-9 * torch.randn_like(xs)
    y_ref = y.clone().requires_grad_()
    g_ref = torch.autograd.grad(
        plain_bending_energy(y_ref, b.hinges, b.weights, b.stiffness, b.rest_angles, "quadratic"), y_ref
    )[0]
    assert rel(b.gradient(y), g_ref) < 1e-8


def test_large_offset_keeps_accuracy(sheet):
    rest, faces, x = sheet
    bend = _module(rest, faces, "tan")
    g = bend.gradient(x)
    g_off = _module(rest + 1e4, faces, "tan").gradient(x + 1e4)
    # the offset costs the digits that the coordinates lose (1e4 * eps relative to unit-size features)
    assert rel(g_off, g) < 1e-9


def test_float32_follows_input_and_reports_error(sheet):
    rest, faces, x = sheet
    bend = _module(rest, faces, "tan")
    v = torch.randn_like(x)
    b32 = _module(rest.float(), faces, "tan")
    E32, g32, h32 = b32(x.float()), b32.gradient(x.float()), b32.hvp(x.float(), v.float())
    assert E32.dtype == g32.dtype == h32.dtype == torch.float32
    # a float64 module evaluated at float32 input also computes in float32
    assert bend(x.float()).dtype == torch.float32
    errs = {
        "energy": abs(E32.double().item() - bend(x).item()) / bend(x).item(),
        "gradient": rel(g32.double(), bend.gradient(x)),
        "hvp": rel(h32.double(), bend.hvp(x, v)),
    }
    print("float32 vs float64 relative error:", {k: f"{e:.2e}" for k, e in errs.items()})
    assert all(e < 1e-4 for e in errs.values())


# ----------------------------------------------------------------------------- module, batching, packing
def test_batched_equals_loop_and_module_to(sheet):
    rest, faces, x = sheet
    bend = _module(rest, faces, "sin")
    xb = torch.stack([x, rest, x + 0.01])[None].expand(2, 3, -1, -1)  # (2, 3, V, 3)
    E = bend(xb)
    assert E.shape == (2, 3)
    for i in range(3):
        assert abs(E[1, i].item() - bend(xb[1, i]).item()) < 1e-13 * (1 + abs(E[1, i].item()))
    v = torch.randn_like(xb)
    assert bend.gradient(xb).shape == xb.shape and bend.hvp(xb, v).shape == xb.shape
    assert rel(bend.hvp(xb, v)[0, 2], bend.hvp(xb[0, 2], v[0, 2])) < 1e-14
    b32 = bend.to(torch.float32)
    assert b32.weights.dtype == torch.float32 and b32.hinges.dtype == torch.int64
    assert b32(x.float()).dtype == torch.float32


def test_packed_meshes_give_per_mesh_energies():
    meshes = [tb.scenes.random_curved_sheet(4, 3, seed=s, dtype=F64) for s in (1, 2)] + [
        tb.scenes.icosphere(1, dtype=F64)
    ]
    packed = tb.pack_meshes(meshes)
    bend = BendingEnergy.packed(packed, model="tan", stiffness=0.5)
    deformed = [v + 0.03 * torch.randn_like(v) for v, _ in meshes]
    x = packed.pack(deformed)
    E = bend(x)
    assert E.shape == (3,)
    for m, ((v, f), y) in enumerate(zip(meshes, deformed)):
        single = BendingEnergy(f, v, model="tan", stiffness=0.5)
        assert abs(E[m].item() - single(y).item()) < 1e-13 * single(y).item()
    # gradients of per-mesh energies stay per mesh
    y = x.clone().requires_grad_()
    (g1,) = torch.autograd.grad(bend(y)[1], y)
    parts = packed.unpack(g1)
    assert parts[0].abs().max() == 0 and parts[2].abs().max() == 0
    assert rel(parts[1], BendingEnergy(*meshes[1][::-1], model="tan", stiffness=0.5).gradient(deformed[1])) < 1e-13
    assert bend(torch.stack([x, x])).shape == (2, 3)


# ----------------------------------------------------------------------------- bad input
@pytest.fixture
def small():
    rest, faces = tb.scenes.random_curved_sheet(3, 3, seed=0, dtype=F64)
    return rest, faces, BendingEnergy(faces, rest, model="tan", damping=0.1, stiffness=1.0)


def test_bad_positions(small):
    rest, faces, bend = small
    bad = rest.clone()
    bad[4, 1] = float("nan")
    with pytest.raises(ValueError, match=r"non-finite.*vertices \[4\]"):
        bend(bad)
    bad[4, 1] = float("inf")
    with pytest.raises(ValueError, match="non-finite"):
        bend.gradient(bad)
    with pytest.raises(ValueError, match="non-finite"):
        bend.hvp(rest, bad)
    with pytest.raises(ValueError, match="non-finite"):
        tb.hinge_angles(bad, bend.topology)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 9, 3\)"):
        bend(rest[:-1])
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 9, 3\)"):
        bend(rest[:, :2])
    with pytest.raises(ValueError, match="floating point"):
        bend(rest.long())
    with pytest.raises(ValueError, match="v must have shape"):
        bend.hvp(rest, rest[:-1])
    # the finite check can be switched off for speed
    fast = BendingEnergy(faces, rest, check_finite=False, stiffness=1.0)
    fast(bad)


def test_bad_rest_shape_and_parameters(small):
    rest, faces, bend = small
    topo = tb.HingeTopology.from_faces(faces)
    i0, i1 = topo.hinges[2, :2].tolist()
    degenerate = rest.clone()
    degenerate[i1] = degenerate[i0]  # collapse the edge of hinge 2
    with pytest.raises(ValueError, match=rf"zero-length edges \[\({i0}, {i1}\)\] \(hinge index .*: \[2\]\)"):
        BendingEnergy(faces, degenerate, stiffness=1.0)
    collinear = rest.clone()
    f0 = faces[0]
    collinear[f0[2]] = 0.5 * (collinear[f0[0]] + collinear[f0[1]])
    with pytest.raises(ValueError, match=r"zero-area.*faces \[.*0"):
        BendingEnergy(faces, collinear, stiffness=1.0)
    with pytest.raises(ValueError, match="unknown bending model 'cubic'"):
        BendingEnergy(faces, rest, model="cubic", stiffness=1.0)
    with pytest.raises(ValueError, match="stiffness must be non-negative"):
        BendingEnergy(faces, rest, stiffness=-1.0)
    with pytest.raises(ValueError, match=r"stiffness must be a scalar or have shape \(8,\)"):
        BendingEnergy(faces, rest, stiffness=torch.ones(3))
    with pytest.raises(ValueError, match="rest_angles must be finite"):
        BendingEnergy(faces, rest, rest_angles=float("nan"), stiffness=1.0)
    with pytest.raises(ValueError, match=r"\|theta\| < pi"):
        BendingEnergy(faces, rest, model="tan", rest_angles=math.pi, stiffness=1.0)
    with pytest.raises(ValueError, match=r"face 3 = \[2, 5, 4\] has index 5 >= V = 5"):
        BendingEnergy(faces, rest[:5], stiffness=1.0)  # too few rest positions: the first face that reaches past them
    with pytest.raises(ValueError, match=r"rest_positions must have shape \(\.\.\., 9, 3\)"):
        BendingEnergy(faces, rest[:5, :2], stiffness=1.0)


def test_bad_damping_arguments(small):
    rest, faces, bend = small
    prev = bend.angles(rest)
    with pytest.raises(ValueError, match="both theta_prev and dt"):
        bend(rest, theta_prev=prev)
    with pytest.raises(ValueError, match="dt must be positive"):
        bend(rest, theta_prev=prev, dt=0.0)
    with pytest.raises(ValueError, match=r"theta_prev must have shape \(\.\.\., 8\)"):
        bend(rest, theta_prev=prev[:-1], dt=0.1)
    with pytest.raises(ValueError, match="no damping"):
        BendingEnergy(faces, rest, stiffness=1.0)(rest, theta_prev=prev, dt=0.1)


def test_stiffness_from_material():
    k = tb.stiffness_from_material(1e6, 1e-3, 0.3)
    assert abs(k - 1e6 * 1e-9 / (24 * (1 - 0.09))) < 1e-18
    for args, match in [((-1, 1e-3, 0.3), "young"), ((1e6, 0.0, 0.3), "thickness"), ((1e6, 1e-3, 0.7), "poisson")]:
        with pytest.raises(ValueError, match=match):
            tb.stiffness_from_material(*args)


def test_stiffness_is_required():
    rest, faces = tb.scenes.grid(3, 3, dtype=F64)
    with pytest.raises(TypeError, match=r"stiffness is required.*\[N m\].*stiffness_from_material"):
        BendingEnergy(faces, rest, model="tan")
