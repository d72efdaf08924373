"""Empty batches ``x (0, V, 3)`` through every entry point: the bending energy on the eager path and on the
compiled kernels (energy, gradient, backward, double backward, HVP, projected HVPs, per-hinge blocks, the
viscous term, parameter gradients, packed meshes), every :class:`~torchbend.MembraneEnergy` method, and
:class:`~torchbend.losses.ClothLoss` with every reduction.

Each result must have the shape of a non-empty batch's result with the batch dimension 0, the dtype of the
positions, no NaN, and gradients of the positions' shape (zero gradients for the parameters)."""
import pytest
import torch

import torchbend as tb
from torchbend import losses as L
from torchbend.backends import native

from .helpers import MEMBRANE_MODELS, MODELS

PROJECTIONS = ["clamp", "abs", "gauss_newton", "reduced"]


def _backends():
    yield "eager"
    yield pytest.param("native", marks=pytest.mark.skipif(native.load() is None, reason="no C++ kernels here"))


BACKENDS = list(_backends())


@pytest.fixture(params=BACKENDS)
def backend(request) -> str:
    return request.param


@pytest.fixture(params=MODELS)
def bending_model(request) -> str:
    return request.param


@pytest.fixture(scope="module")
def mesh():
    rest, faces = tb.scenes.random_curved_sheet(4, 3, amplitude=0.3, seed=2, dtype=torch.float64)
    return rest, faces


def _states(rest: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """An empty batch ``(0, V, 3)`` and a batch of two perturbed states, in ``dtype``."""
    gen = torch.Generator().manual_seed(5)
    full = (rest + 0.02 * torch.randn((2,) + tuple(rest.shape), generator=gen, dtype=torch.float64)).to(dtype)
    return full[:0].clone(), full


def _like(out: torch.Tensor, ref: torch.Tensor, dtype: torch.dtype) -> None:
    """``out`` is the empty-batch version of ``ref``: batch dimension 0, the rest of ``ref``'s shape, dtype."""
    assert isinstance(out, torch.Tensor)
    assert out.shape[0] == 0 and out.shape[1:] == ref.shape[1:], (tuple(out.shape), tuple(ref.shape))
    assert out.dtype == dtype
    assert not bool(torch.isnan(ref).any())  # (the non-empty batch is a valid input: the comparison is meaningful)


def _bending(faces, rest, model, backend, dtype, **kw) -> tb.BendingEnergy:
    return tb.BendingEnergy(faces, rest.to(dtype), model=model, backend=backend, **{"stiffness": 1.0, **kw})


@pytest.fixture
def bending(mesh, backend, bending_model, dtype) -> tuple[tb.BendingEnergy, torch.Tensor, torch.Tensor]:
    """A bending energy of ``mesh`` in ``dtype``, an empty batch and a batch of two (:func:`_states`)."""
    rest, faces = mesh
    return (_bending(faces, rest, bending_model, backend, dtype), *_states(rest, dtype))


# ------------------------------------------------------------------------------------------- bending energy


def test_bending_first_order(bending, dtype):
    """Energy ``(0,)``, gradient ``(0, V, 3)`` and angles ``(0, H)``, eager and compiled."""
    bend, x0, x2 = bending
    _like(bend(x0), bend(x2), dtype)
    _like(bend.gradient(x0), bend.gradient(x2), dtype)
    _like(bend.angles(x0), bend.angles(x2), dtype)
    assert bend(x0).shape == (0,)


def test_bending_hvp_and_blocks(bending, dtype):
    """HVP ``(0, V, 3)``, every projected HVP, and the per-hinge blocks ``(0, H, 12, 12)`` (plain and projected)."""
    bend, x0, x2 = bending
    v0, v2 = torch.randn_like(x0), torch.randn_like(x2)
    _like(bend.hvp(x0, v0), bend.hvp(x2, v2), dtype)
    for project in PROJECTIONS:
        _like(bend.hvp(x0, v0, projection=project), bend.hvp(x2, v2, projection=project), dtype)
    blocks = bend.hinge_hessians(x0)
    _like(blocks, bend.hinge_hessians(x2), dtype)
    assert blocks.shape == (0, bend.hinge_count, 12, 12)
    for project in PROJECTIONS:
        _like(bend.hinge_hessians(x0, projection=project), bend.hinge_hessians(x2, projection=project), dtype)


def test_bending_backward_and_double_backward(mesh, backend, bending_model, dtype):
    """``backward`` gives ``x.grad (0, V, 3)`` and a zero stiffness gradient; the double backward (the HVP of
    ``create_graph=True``) gives ``(0, V, 3)`` too."""
    rest, faces = mesh
    k = torch.nn.Parameter(torch.tensor(0.7, dtype=dtype))
    bend = _bending(faces, rest, bending_model, backend, dtype, stiffness=k)
    x0, _ = _states(rest, dtype)
    x = x0.clone().requires_grad_()
    bend(x).sum().backward()
    assert x.grad is not None and x.grad.shape == x.shape and x.grad.dtype == dtype
    assert k.grad is not None and k.grad.shape == () and float(k.grad) == 0.0

    x = x0.clone().requires_grad_()
    v = torch.randn_like(x)
    (g,) = torch.autograd.grad(bend(x).sum(), x, create_graph=True)
    assert g.shape == x.shape
    hv, gk = torch.autograd.grad((g * v).sum(), (x, k))
    assert hv.shape == x.shape and hv.dtype == dtype
    assert gk.shape == () and float(gk) == 0.0
    # the gradient entry point's own double backward
    x = x0.clone().requires_grad_()
    (hv2,) = torch.autograd.grad((bend.gradient(x) * v).sum(), x)
    assert hv2.shape == x.shape


def test_bending_viscous_and_packed(mesh, backend):
    """The viscous term (``theta_prev (0, H)``) and a packed module's per-mesh energies ``(0, M)``."""
    rest, faces = mesh
    bend = _bending(faces, rest, "tan", backend, torch.float64, damping=0.1)
    x0, x2 = _states(rest, torch.float64)
    prev0, prev2 = bend.angles(x0), bend.angles(x2).flip(0)
    _like(bend(x0, theta_prev=prev0, dt=0.01), bend(x2, theta_prev=prev2, dt=0.01), torch.float64)
    _like(bend.gradient(x0, theta_prev=prev0, dt=0.01), bend.gradient(x2, theta_prev=prev2, dt=0.01), torch.float64)

    v1, f1 = tb.scenes.grid(3, 3, dtype=torch.float64)
    v2, f2 = tb.scenes.icosphere(1, radius=0.5, dtype=torch.float64)
    packed = tb.pack_meshes([(v1, f1), (v2, f2)])
    pb = tb.BendingEnergy.packed(packed, model="tan", backend=backend, stiffness=1.0)
    xp = packed.verts + 0.01 * torch.randn_like(packed.verts)
    E0 = pb(xp.expand(0, -1, -1).clone())
    assert E0.shape == (0, 2) and E0.dtype == torch.float64
    _like(pb.gradient(xp.expand(0, -1, -1).clone()), pb.gradient(xp.expand(2, -1, -1).clone()), torch.float64)


def test_bending_without_hinges(backend):
    """A mesh without interior edges (one triangle): every entry point gives zeros of the right shape,
    empty batch or not."""
    faces = torch.tensor([[0, 1, 2]])
    rest = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)
    bend = tb.BendingEnergy(faces, rest, backend=backend, stiffness=1.0)
    for B in (0, 2):
        x = rest + 0.1 * torch.randn(B, 3, 3, dtype=torch.float64)
        assert bend(x).shape == (B,) and bool((bend(x) == 0).all())
        for out in (bend.gradient(x), bend.hvp(x, x), bend.hvp(x, x, projection="clamp"), bend.hvp(x, x, projection="gauss_newton")):
            assert out.shape == (B, 3, 3) and bool((out == 0).all())
        assert bend.hinge_hessians(x).shape == (B, 0, 12, 12)


def test_compiled_entry_points_really_run_compiled(mesh):
    """The compiled half of these tests is not the eager path in disguise: the backend chosen for the empty
    batch is the native one where the kernels are built."""
    if native.load() is None:
        pytest.skip("no C++ kernels here")
    from torchbend import backends

    rest, faces = mesh
    x0, _ = _states(rest, torch.float64)
    for op in ("energy", "gradient", "hvp", "hinge_hessians", "hvp_projected"):
        assert backends.select_backend(op, "native", x0) is backends.Backend.NATIVE


# ------------------------------------------------------------------------------------------ membrane energy


@pytest.mark.parametrize("model", MEMBRANE_MODELS)
def test_membrane_every_method(mesh, model, dtype):
    rest, faces = mesh
    mem = tb.MembraneEnergy(faces, rest.to(dtype), model=model, young=1e5, poisson=0.3, thickness=1e-3)
    x0, x2 = _states(rest, dtype)
    v0, v2 = torch.randn_like(x0), torch.randn_like(x2)
    _like(mem(x0), mem(x2), dtype)
    _like(mem.gradient(x0), mem.gradient(x2), dtype)
    for project in (None, "clamp", "abs"):
        _like(mem.hvp(x0, v0, projection=project), mem.hvp(x2, v2, projection=project), dtype)
        He = mem.element_hessians(x0, projection=project)
        _like(He, mem.element_hessians(x2, projection=project), dtype)
        assert He.shape == (0, mem.face_count, 9, 9)
    (l0, Q0), (l2, Q2) = mem.element_eigensystems(x0), mem.element_eigensystems(x2)
    _like(l0, l2, dtype)
    _like(Q0, Q2, dtype)
    _like(mem.deformation_gradients(x0), mem.deformation_gradients(x2), dtype)

    x = x0.clone().requires_grad_()
    mem(x).sum().backward()
    assert x.grad is not None and x.grad.shape == x.shape and x.grad.dtype == dtype
    x = x0.clone().requires_grad_()
    (g,) = torch.autograd.grad(mem(x).sum(), x, create_graph=True)
    (hv,) = torch.autograd.grad((g * v0).sum(), x)
    assert g.shape == x.shape and hv.shape == x.shape
    x = x0.clone().requires_grad_()
    (hv2,) = torch.autograd.grad((mem.gradient(x) * v0).sum(), x)
    assert hv2.shape == x.shape


# -------------------------------------------------------------------------------------------------- losses


def _loss_terms(faces, rest):
    bx, bf = tb.scenes.icosphere(1, radius=0.3, dtype=torch.float64)
    return {
        "stretch": L.Stretch(faces, rest, young=1e5, poisson=0.3, thickness=1e-3),
        "bend": L.Bending(faces, rest, 1e-3),
        "gravity": L.Gravity(faces, rest, 0.2),
        "inertia": L.Inertia(faces, rest, 0.2, 0.01),
        "pin": L.Pinning([0, 1], 10.0, rest[:2]),
        "spheres": L.BodyContact(stiffness=1e3, colliders=[tb.Sphere(center=(0.0, 0.0, -1.0), radius=0.5)]),
        "body_contact": L.BodyContact(stiffness=1e3, body_faces=bf),
        "energy": tb.BendingEnergy(faces, rest, stiffness=1.0),
    }, bx


@pytest.mark.parametrize("reduction", ["mean", "sum", "none"])
def test_cloth_loss_every_reduction(mesh, reduction):
    """An empty batch: ``"mean"`` and ``"sum"`` give 0 (documented; torch's mean of nothing is NaN), ``"none"``
    a ``(0,)`` tensor; every term's value is reduced the same way and the gradient is ``(0, V, 3)``."""
    rest, faces = mesh
    terms, body = _loss_terms(faces, rest)
    loss = L.ClothLoss(terms, reduction=reduction)
    x0, x2 = _states(rest, torch.float64)
    x = x0.clone().requires_grad_()
    def spheres(B):
        return {"sphere_center": torch.zeros(B, 3, dtype=torch.float64), "sphere_radius": torch.ones(B, dtype=torch.float64)}

    inputs = {"x_prev": x0, "v_prev": torch.zeros_like(x0), "body_contact": {"body": body}, "spheres": spheres(0)}
    total, values = loss(x, **inputs)
    assert set(values) == set(terms)
    want = (0,) if reduction == "none" else ()
    for v in (total, *values.values()):
        assert v.shape == want and v.dtype == torch.float64
        assert not bool(torch.isnan(v).any())
        if reduction != "none":
            assert float(v) == 0.0
    (g,) = torch.autograd.grad(total.sum(), x, create_graph=True)
    assert g.shape == x.shape
    (hv,) = torch.autograd.grad((g * torch.ones_like(g)).sum(), x, allow_unused=True, materialize_grads=True)
    assert hv.shape == x.shape
    # the same loss on a non-empty batch is a number (the empty batch is the only special case)
    inputs2 = dict(inputs, x_prev=x2, v_prev=torch.zeros_like(x2), spheres=spheres(2))
    total2, _ = loss(x2, **inputs2)
    assert total2.shape == ((2,) if reduction == "none" else ()) and bool(torch.isfinite(total2).all())


def test_per_sample_materials_on_an_empty_batch(mesh):
    """Per-sample materials of batch size 0 go with an empty batch."""
    rest, faces = mesh
    x0, _ = _states(rest, torch.float64)
    e = torch.zeros(0, dtype=torch.float64)
    stretch = L.Stretch(faces, rest, young=e + 1e5, poisson=e + 0.3, thickness=e + 1e-3)
    assert stretch(x0).shape == (0,) and stretch.gradient(x0).shape == x0.shape
    bend = L.Bending(faces, rest, e + 1e-3)
    assert bend(x0).shape == (0,) and bend.gradient(x0).shape == x0.shape
    assert L.Gravity(faces, rest, e + 0.2)(x0).shape == (0,)
    assert L.Inertia(faces, rest, 0.2, e + 0.01)(x0, x_hat=x0, density=e + 0.1).shape == (0,)
