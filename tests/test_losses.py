"""Physics losses as modules (torchbend.losses): every term against a plain hand-written reference
(autograd of a direct formula), per-sample materials against a loop over samples with scalar ones,
ClothLoss's weights, sum, routing and values, the HOOD/SNUG conversions, device and dtype following,
ValueErrors, and the training-friendly bending default."""
import math

import pytest
import torch

import torchbend as tb
from torchbend import losses as L
from torchbend.testing import plain_bending_energy

F64 = torch.float64
B = 3
requires_gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, requires_gpu])]


@pytest.fixture
def cloth():
    """A flat 5x5 grid cloth 0.4 m wide and a batch of 3 perturbed states."""
    rest, faces = tb.scenes.grid(5, 5, (0.4, 0.4), dtype=F64)
    gen = torch.Generator().manual_seed(1)
    x = rest + 0.03 * torch.randn((B, *rest.shape), generator=gen, dtype=F64)
    return rest, faces, x


def grads(f, *inputs, create_graph=False):
    """Gradients of ``f(*inputs).sum()`` with respect to ``inputs`` (each made a fresh leaf)."""
    leaves = [t.detach().clone().requires_grad_() for t in inputs]
    out = f(*leaves)
    return out.detach(), torch.autograd.grad(out.sum(), leaves, create_graph=create_graph)


# ------------------------------------------------------------------------------ plain references
def ref_masses(faces, rest, density):
    """Lumped masses by a loop over the triangles: a third of each triangle's area to each corner."""
    m = [0.0] * rest.shape[0]
    for f in faces.tolist():
        p = [rest[i] for i in f]
        area = 0.5 * float(torch.linalg.cross(p[1] - p[0], p[2] - p[0]).norm())
        for i in f:
            m[i] += density * area / 3
    return torch.tensor(m, dtype=F64)


def ref_stvk(x, faces, rest, mu, lam, t):
    """StVK ``sum_T A t (mu |G|^2 + lam/2 tr(G)^2)`` written with Gram matrices: ``C = Gbar^-1 g`` with the rest
    and deformed edge Gram matrices ``Gbar = Dbar^T Dbar``, ``g = Ds^T Ds`` (similar to ``F^T F``), ``G = (C - I)/2``.
    Also HOOD's/SNUG's stretch criterion as assumed in torchbend.energies.materials."""
    def gram(p):
        e1, e2 = p[..., faces[:, 1], :] - p[..., faces[:, 0], :], p[..., faces[:, 2], :] - p[..., faces[:, 0], :]
        return torch.stack((torch.stack(((e1 * e1).sum(-1), (e1 * e2).sum(-1)), -1),
                            torch.stack(((e2 * e1).sum(-1), (e2 * e2).sum(-1)), -1)), -2)
    Gbar = gram(rest)
    area = 0.5 * torch.sqrt(torch.linalg.det(Gbar))
    G = 0.5 * (torch.linalg.solve(Gbar, gram(x)) - torch.eye(2, dtype=x.dtype))
    trG = G.diagonal(dim1=-2, dim2=-1).sum(-1)
    normG2 = (G * G.transpose(-1, -2)).sum((-1, -2))  # tr(G G): |G|_F^2 of the (symmetric) Green strain
    return (area * t * (mu * normG2 + 0.5 * lam * trG * trG)).sum(-1)


def ref_hood_bending(x, faces, rest, bending_coeff):
    """HOOD's bending criterion as assumed in torchbend.energies.materials: per interior edge
    ``bending_coeff |e|^2 theta^2 / (8 (A_A + A_B))`` (rest |e| and areas), hinges found by a plain edge dict."""
    by_edge: dict = {}
    for fi, f in enumerate(faces.tolist()):
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            by_edge.setdefault((min(a, b), max(a, b)), []).append(fi)
    pairs = [(e, fs) for e, fs in by_edge.items() if len(fs) == 2]
    edges = torch.tensor([e for e, _ in pairs])
    fa, fb = torch.tensor([fs[0] for _, fs in pairs]), torch.tensor([fs[1] for _, fs in pairs])

    def normals(p):
        q = p[..., faces, :]
        return torch.linalg.cross(q[..., 1, :] - q[..., 0, :], q[..., 2, :] - q[..., 0, :], dim=-1)

    n = normals(x)
    nA, nB = n[..., fa, :], n[..., fb, :]
    theta = torch.atan2(torch.linalg.cross(nA, nB, dim=-1).norm(dim=-1), (nA * nB).sum(-1))
    area = 0.5 * normals(rest).norm(dim=-1)
    e2 = ((rest[edges[:, 1]] - rest[edges[:, 0]]) ** 2).sum(-1)
    return (bending_coeff * e2 * theta**2 / (8 * (area[fa] + area[fb]))).sum(-1)


# ------------------------------------------------------------------------------ mass terms
def test_gravity_matches_lumped_mass_formula(cloth):
    rest, faces, x = cloth
    m = ref_masses(faces, rest, 0.2)
    g = torch.tensor([0.3, -1.0, -9.81], dtype=F64)
    term = L.Gravity(faces, rest, 0.2, gravity=tuple(g.tolist()))
    E, (gx,) = grads(term, x)
    assert torch.allclose(E, -(m[:, None] * g * x).sum((-1, -2)), rtol=1e-14, atol=0)
    assert torch.allclose(gx, (-m[:, None] * g).expand_as(x), rtol=1e-14, atol=1e-18)
    assert term(x[0]).shape == ()
    # per-sample density: each sample equals a term built with its scalar density
    rho = torch.tensor([0.1, 0.2, 0.45], dtype=F64)
    batched = term(x, density=rho)
    for b in range(B):
        assert torch.allclose(batched[b], L.Gravity(faces, rest, float(rho[b]), gravity=tuple(g.tolist()))(x[b]),
                              rtol=1e-14, atol=0)


def test_inertia_is_the_incremental_potential(cloth):
    rest, faces, x = cloth
    gen = torch.Generator().manual_seed(2)
    x_prev, v_prev = rest + 0.01 * torch.randn(rest.shape, generator=gen, dtype=F64), torch.randn(
        (B, *rest.shape), generator=gen, dtype=F64)
    dt = 1 / 30
    m = ref_masses(faces, rest, 0.2)
    term = L.Inertia(faces, rest, 0.2, dt)
    E, (gx,) = grads(lambda y: term(y, x_prev=x_prev, v_prev=v_prev), x)
    x_hat = x_prev + dt * v_prev
    ref = (m[:, None] / (2 * dt * dt) * (x - x_hat) ** 2).sum((-1, -2))
    assert torch.allclose(E, ref, rtol=1e-13, atol=0)
    assert torch.allclose(gx, m[:, None] / dt**2 * (x - x_hat), rtol=1e-12, atol=1e-15)
    assert torch.allclose(term(x, x_hat=x_hat), E, rtol=1e-14, atol=0)
    # per-sample dt and density equal a loop over samples with scalar ones
    dts, rho = torch.tensor([0.01, 0.02, 0.05], dtype=F64), torch.tensor([0.1, 0.3, 0.2], dtype=F64)
    batched = term(x, x_prev=x_prev, v_prev=v_prev, dt=dts, density=rho)
    for b in range(B):
        single = L.Inertia(faces, rest, float(rho[b]), float(dts[b]))(x[b], x_prev=x_prev, v_prev=v_prev[b])
        assert torch.allclose(batched[b], single, rtol=1e-13, atol=0)


def test_pinning_penalty(cloth):
    rest, faces, x = cloth
    pins = [0, 4, 12]
    k = torch.tensor([10.0, 20.0, 30.0], dtype=F64)
    target = rest[pins] + 0.1
    term = L.Pinning(pins, k, target)
    E, (gx,) = grads(term, x)
    d = x[:, pins] - target
    assert torch.allclose(E, 0.5 * (k * (d * d).sum(-1)).sum(-1), rtol=1e-14, atol=0)
    expect = torch.zeros_like(x)
    expect[:, pins] = k[:, None] * d
    assert torch.allclose(gx, expect, rtol=1e-14, atol=0)
    mask = torch.zeros(25, dtype=torch.bool)
    mask[pins] = True
    per_sample = target + torch.arange(B, dtype=F64)[:, None, None]
    assert torch.allclose(L.Pinning(mask, k)(x, pin_targets=per_sample),
                          torch.stack([term(x[b], pin_targets=per_sample[b]) for b in range(B)]), rtol=1e-14, atol=0)


# ------------------------------------------------------------------------------ elastic terms
@pytest.mark.parametrize("young_grad", [False, True])
def test_stretch_matches_plain_stvk_with_per_sample_materials(cloth, young_grad):
    rest, faces, x = cloth
    Y = torch.tensor([1e4, 3e4, 5e4], dtype=F64, requires_grad=young_grad)
    nu = torch.tensor([0.1, 0.3, 0.45], dtype=F64)
    t = torch.tensor([1e-3, 5e-4, 2e-3], dtype=F64)
    term = L.Stretch(faces, rest, young=1e4, poisson=0.3, thickness=1e-3)
    mu, lam = Y / (2 * (1 + nu)), Y * nu / (1 - nu * nu)

    def ours(y):
        return term(y, young=Y, poisson=nu, thickness=t)

    E, (gx,) = grads(ours, x)
    Er, (gr,) = grads(lambda y: ref_stvk(y, faces, rest, mu[:, None], lam[:, None], t[:, None]), x)
    assert torch.allclose(E, Er, rtol=1e-12, atol=0)
    assert torch.allclose(gx, gr, rtol=1e-10, atol=1e-12 * float(gr.abs().max()))
    v = torch.randn_like(x)
    # Hessian-vector products: the analytic double backward against autograd of the plain formula
    xa = x.detach().clone().requires_grad_()
    (ga,) = torch.autograd.grad(ours(xa).sum(), xa, create_graph=True)
    (hv,) = torch.autograd.grad((ga * v).sum(), xa)
    xb = x.detach().clone().requires_grad_()
    (gb,) = torch.autograd.grad(ref_stvk(xb, faces, rest, mu[:, None], lam[:, None], t[:, None]).sum(), xb,
                                create_graph=True)
    (hr,) = torch.autograd.grad((gb * v).sum(), xb)
    assert torch.allclose(hv, hr, rtol=1e-9, atol=1e-11 * float(hr.abs().max()))
    # the closed-form gradient method
    assert torch.allclose(term.gradient(x, young=Y, poisson=nu, thickness=t), gr, rtol=1e-10,
                          atol=1e-12 * float(gr.abs().max()))
    if young_grad:  # at fixed nu the energy is linear in Y
        (gY,) = torch.autograd.grad(ours(x).sum(), Y)
        assert torch.allclose(gY, Er.detach() / Y.detach(), rtol=1e-12, atol=0)
    # each sample equals the package's MembraneEnergy with that sample's scalar material
    for b in range(B):
        mem = tb.MembraneEnergy(faces, rest, young=float(Y.detach()[b]), poisson=float(nu[b]),
                                 thickness=float(t[b]))
        assert torch.allclose(E[b], mem(x[b]), rtol=1e-13, atol=0)


@pytest.mark.parametrize("model", ["arap", "neohookean", "symmetric_dirichlet"])
def test_stretch_other_models_per_sample_equal_a_loop(cloth, model):
    rest, faces, x = cloth
    Y, nu = torch.tensor([1e4, 3e4, 5e4], dtype=F64), torch.tensor([0.1, 0.3, 0.45], dtype=F64)
    term = L.Stretch(faces, rest, young=Y, poisson=nu, thickness=1e-3, model=model)
    E, (gx,) = grads(term, x)
    for b in range(B):
        mem = tb.MembraneEnergy(faces, rest, model=model, young=float(Y[b]), poisson=float(nu[b]), thickness=1e-3)
        e, (g,) = grads(mem, x[b])
        assert torch.allclose(E[b], e, rtol=1e-12, atol=0)
        assert torch.allclose(gx[b], g, rtol=1e-10, atol=1e-12 * float(g.abs().max()))


@pytest.mark.parametrize("model", ["quadratic", "tan", "sin"])
def test_bending_matches_plain_energy_with_per_sample_stiffness(model):
    rest, faces = tb.scenes.random_curved_sheet(5, 4, amplitude=0.3, seed=3, dtype=F64)
    gen = torch.Generator().manual_seed(7)
    x = rest + 0.05 * torch.randn((B, *rest.shape), generator=gen, dtype=F64)
    k = torch.tensor([1e-4, 3e-3, 0.2], dtype=F64)
    term = L.Bending(faces, rest, 1.0, model=model)
    bend = term.bending
    E, (gx,) = grads(lambda y: term(y, bending_stiffness=k), x)
    Er, (gr,) = grads(lambda y: plain_bending_energy(y, bend.hinges, bend.weights, k[:, None], bend.rest_angles,
                                                     model), x)
    assert torch.allclose(E, Er, rtol=1e-12, atol=0)
    assert torch.allclose(gx, gr, rtol=1e-10, atol=1e-12 * float(gr.abs().max()))
    assert torch.allclose(term.gradient(x, bending_stiffness=k), gr, rtol=1e-10, atol=1e-12 * float(gr.abs().max()))
    for b in range(B):
        ref = tb.BendingEnergy(faces, rest, model=model, stiffness=float(k[b]))(x[b])
        assert torch.allclose(E[b], ref, rtol=1e-13, atol=0)


def test_bending_defaults_to_quadratic_and_learns_its_stiffness(cloth):
    rest, faces, x = cloth
    assert L.Bending(faces, rest, 1e-3).bending.model is tb.BendingModel.QUADRATIC
    k = torch.nn.Parameter(torch.tensor(2e-3, dtype=F64))
    term = L.Bending(faces, rest, k)
    assert any(p is k for p in term.parameters())
    E = term(x)
    (gk,) = torch.autograd.grad(E.sum(), k)
    assert torch.allclose(gk, (E / k).sum().detach(), rtol=1e-13, atol=0)


# ------------------------------------------------------------------------------ contact
def ref_vertex_normals(body, faces):
    n = torch.zeros_like(body)
    for f in faces.tolist():
        fn = torch.linalg.cross(body[..., f[1], :] - body[..., f[0], :], body[..., f[2], :] - body[..., f[0], :], dim=-1)
        for i in f:
            n[..., i, :] = n[..., i, :] + fn
    return n / n.norm(dim=-1, keepdim=True)


def test_body_mesh_contact_is_hoods_cubic_penalty(cloth):
    rest, faces, _ = cloth
    body, bfaces = tb.scenes.icosphere(2, 0.15, (0.2, 0.2, 0.0), dtype=F64)
    gen = torch.Generator().manual_seed(3)
    x = rest + torch.tensor([0.0, 0.0, 0.13]) + 0.02 * torch.randn((B, *rest.shape), generator=gen, dtype=F64)
    bodies = body + 0.01 * torch.randn((B, *body.shape), generator=gen, dtype=F64)
    k, eps = 1e5, 4e-3
    term = L.BodyContact(stiffness=k, eps=eps, body_faces=bfaces)
    idx = ((x[:, :, None] - bodies[:, None]) ** 2).sum(-1).argmin(-1)  # (B, V) nearest body vertex

    def ref(y, bod):
        n = ref_vertex_normals(bod, bfaces)
        p = torch.stack([bod[b, idx[b]] for b in range(B)])
        nn_ = torch.stack([n[b, idx[b]] for b in range(B)])
        return k * ((eps - ((y - p) * nn_).sum(-1)).clamp_min(0) ** 3).sum(-1)

    E, (gx, gb) = grads(lambda y, bod: term(y, body=bod), x, bodies)
    Er, (gxr, gbr) = grads(ref, x, bodies)
    assert (Er > 0).all()  # some vertices are within eps of the body in every sample
    assert torch.allclose(E, Er, rtol=1e-13, atol=0)
    assert torch.allclose(gx, gxr, rtol=1e-12, atol=1e-12 * float(gxr.abs().max()))
    assert torch.allclose(gb, gbr, rtol=1e-12, atol=1e-12 * float(gbr.abs().max()))
    # an unbatched (shared) body equals the batched one repeated
    assert torch.allclose(term(x, body=body), term(x, body=body.expand(B, -1, -1)), rtol=1e-15, atol=0)


def test_contact_with_colliders_and_per_sample_spheres(cloth):
    rest, faces, _ = cloth
    gen = torch.Generator().manual_seed(4)
    x = rest + 0.05 * torch.randn((B, *rest.shape), generator=gen, dtype=F64)
    k, eps = 1e4, 0.01
    sphere, plane = tb.Sphere(center=(0.2, 0.2, -0.1), radius=0.15), tb.Plane(point=(0, 0, -0.02), normal=(0, 0.3, 1))
    capsule = tb.Capsule(a=(0.0, 0.2, -0.05), b=(0.4, 0.25, -0.05), radius=0.06)

    def pen(s):
        return k * ((eps - s).clamp_min(0) ** 3).sum(-1)

    def ref(y):
        n = torch.tensor([0, 0.3, 1], dtype=F64) / math.sqrt(1.09)
        s_sphere = (y - torch.tensor([0.2, 0.2, -0.1], dtype=F64)).norm(dim=-1) - 0.15
        s_plane = (y - torch.tensor([0, 0, -0.02], dtype=F64)) @ n
        a, b = torch.tensor([0.0, 0.2, -0.05], dtype=F64), torch.tensor([0.4, 0.25, -0.05], dtype=F64)
        u = ((y - a) @ (b - a) / ((b - a) @ (b - a))).clamp(0, 1)
        s_caps = (y - (a + u[..., None] * (b - a))).norm(dim=-1) - 0.06
        return pen(s_sphere) + pen(s_plane) + pen(s_caps)

    term = L.BodyContact(stiffness=k, eps=eps, colliders=[sphere, plane, capsule])
    E, (gx,) = grads(term, x)
    Er, (gr,) = grads(ref, x)
    assert (Er > 0).all() and torch.allclose(E, Er, rtol=1e-12, atol=0)
    assert torch.allclose(gx, gr, rtol=1e-11, atol=1e-12 * float(gr.abs().max()))
    # per-sample spheres: a loop over samples with one static sphere each
    centers = torch.tensor([[0.2, 0.2, -0.1], [0.1, 0.25, -0.12], [0.3, 0.1, -0.08]], dtype=F64)
    radii = torch.tensor([0.15, 0.12, 0.14], dtype=F64)
    spheres = L.BodyContact(stiffness=k, eps=eps)
    batched = spheres(x, sphere_center=centers, sphere_radius=radii)
    for b in range(B):
        one = L.BodyContact(stiffness=k, eps=eps, colliders=[tb.Sphere(center=tuple(centers[b].tolist()),
                                                                       radius=float(radii[b]))])
        assert torch.allclose(batched[b], one(x[b]), rtol=1e-13, atol=0)
    # a vertex exactly at a sphere's centre: finite gradient
    y = x[0].clone()
    y[0] = centers[0]
    _, (g0,) = grads(lambda z: spheres(z, sphere_center=centers[0], sphere_radius=radii[0]), y)
    assert torch.isfinite(g0).all()


# ------------------------------------------------------------------------------ HOOD / SNUG conversions
def test_hood_bending_coefficient_is_24_times_ours(cloth):
    rest, faces, x = cloth  # flat rest shape (HOOD's bending has zero rest angles)
    bc = torch.tensor([1e-5, 4e-5, 1e-3], dtype=F64)
    k = tb.bending_stiffness_from_hood(bc)
    assert isinstance(k, torch.Tensor)
    assert torch.allclose(k, bc / 24, rtol=1e-15, atol=0)
    bc_back = tb.hood_bending_coeff(k)
    assert isinstance(bc_back, torch.Tensor)
    assert torch.allclose(bc_back, bc, rtol=1e-15, atol=0)
    assert tb.hood_bending_coeff(1.0) == 24.0 and tb.bending_stiffness_from_hood(24.0) == 1.0
    term = L.Bending(faces, rest, 1.0)
    E, (gx,) = grads(lambda y: term(y, bending_stiffness=k), x)
    Er, (gr,) = grads(lambda y: ref_hood_bending(y, faces, rest, bc[:, None]), x)
    assert torch.allclose(E, Er, rtol=1e-12, atol=0)
    assert torch.allclose(gx, gr, rtol=1e-10, atol=1e-12 * float(gr.abs().max()))


def test_hood_stretch_from_lame_parameters(cloth):
    rest, faces, x = cloth
    lame_mu, lame_lambda, t = 23600.0, 44400.0, 4.7e-4  # HOOD's default material
    Y, nu = tb.material_from_lame(lame_mu, lame_lambda)
    assert abs(Y - 7e4) / 7e4 < 2e-3 and abs(nu - 0.485) < 1e-3  # Y = 7e4 Pa, nu = 0.485 (rounded in HOOD)
    assert all(math.isclose(a, b, rel_tol=1e-14) for a, b in zip(tb.lame_parameters(float(Y), float(nu)), (lame_mu, lame_lambda)))
    term = L.Stretch(faces, rest, young=Y, poisson=nu, thickness=t)
    assert torch.allclose(term(x), ref_stvk(x, faces, rest, lame_mu, lame_lambda, t), rtol=1e-12, atol=0)
    # per-sample tensors
    mus, lams = torch.tensor([1e4, 2e4, 3e4], dtype=F64), torch.tensor([5e3, 0.0, 5e4], dtype=F64)
    Ys, nus = tb.material_from_lame(mus, lams)
    assert torch.allclose(term(x, young=Ys, poisson=nus), ref_stvk(x, faces, rest, mus[:, None], lams[:, None], t),
                          rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="lam must lie in"):
        tb.material_from_lame(1.0, 2.5)
    with pytest.raises(ValueError, match="mu must be positive"):
        tb.material_from_lame(torch.tensor([1.0, -1.0]), 0.0)
    with pytest.raises(ValueError, match="bending_coeff must be finite and non-negative"):
        tb.bending_stiffness_from_hood(-1.0)


def test_energy_scale_is_mass_gravity_size(cloth):
    rest, faces, _ = cloth
    assert math.isclose(L.energy_scale(faces, rest, 0.2), 0.2 * 0.16 * 9.81 * 0.4 * math.sqrt(2), rel_tol=1e-12)


# ------------------------------------------------------------------------------ ClothLoss
class Counting(torch.nn.Module):
    """A plain module term (no ``inputs``) that counts its calls."""

    def __init__(self):
        super().__init__()
        self.calls = 0

    def forward(self, x):
        self.calls += 1
        return (x * x).sum((-1, -2))


def test_cloth_loss_weights_sum_values_and_routing(cloth):
    rest, faces, x = cloth
    x = x.clone().requires_grad_()
    rho = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    terms = {"gravity": L.Gravity(faces, rest, 0.2), "inertia": L.Inertia(faces, rest, 0.2, 0.02),
             "bending": L.Bending(faces, rest, 1e-3), "plain": Counting(), "off": Counting()}
    loss = tb.ClothLoss(terms, {"inertia": 0.5, "plain": 2.0, "off": 0.0})
    total, values = loss(x, density=rho, x_hat=rest, bending_stiffness=torch.tensor([1e-3, 2e-3, 3e-3], dtype=F64))
    assert set(values) == {"gravity", "inertia", "bending", "plain"} and terms["off"].calls == 0
    assert all(not v.requires_grad and v.shape == () for v in values.values())
    g = terms["gravity"](x, density=rho)
    i = terms["inertia"](x, x_hat=rest, density=rho)  # density reaches both mass terms
    bnd = terms["bending"](x, bending_stiffness=torch.tensor([1e-3, 2e-3, 3e-3], dtype=F64))
    p = (x * x).sum((-1, -2))
    for name, v in (("gravity", g), ("inertia", i), ("bending", bnd), ("plain", p)):
        assert torch.allclose(values[name], v.mean(), rtol=1e-15, atol=0)
    assert torch.allclose(total, (g + 0.5 * i + bnd + 2 * p).mean(), rtol=1e-14, atol=0)
    (gx,) = torch.autograd.grad(total, x)
    (gr,) = torch.autograd.grad((g + 0.5 * i + bnd + 2 * p).mean(), x)
    assert torch.allclose(gx, gr, rtol=1e-13, atol=1e-18)
    # reductions and the un-reduced energies
    per = tb.ClothLoss(terms, {"off": 0.0}, reduction="none")(x.detach(), density=rho, x_hat=rest)
    assert per[0].shape == (B,) and per[1]["gravity"].shape == (B,)
    summed = tb.ClothLoss(terms, {"off": 0.0}, reduction="sum")(x.detach(), density=rho, x_hat=rest)
    assert torch.allclose(summed[0], per[0].sum(), rtol=1e-14, atol=0)
    assert set(loss.energies(x, x_hat=rest)) == set(values)
    loss.weights["off"] = 1.0  # weights may change between calls
    assert "off" in loss(x, x_hat=rest)[1]


def test_cloth_loss_routes_term_specific_inputs(cloth):
    rest, faces, x = cloth
    ground = L.BodyContact(stiffness=1e3, eps=0.0, power=2.0, colliders=[tb.Plane(point=(0, 0, 0.01))])
    sphere = L.BodyContact(stiffness=1e3, eps=0.0, power=2.0)
    loss = tb.ClothLoss({"ground": ground, "sphere": sphere}, reduction="none")
    c, r = torch.tensor([0.2, 0.2, -0.05], dtype=F64), torch.tensor(0.1, dtype=F64)
    _, values = loss(x, sphere={"sphere_center": c, "sphere_radius": r})
    assert torch.equal(values["ground"], ground(x).detach())  # the ground gets no sphere
    assert torch.equal(values["sphere"], sphere(x, sphere_center=c, sphere_radius=r).detach())
    assert (values["ground"] > 0).all() and (values["sphere"] > 0).all()
    # shared inputs reach both terms of the class
    _, both = loss(x, sphere_center=c, sphere_radius=r)
    assert torch.allclose(both["ground"], values["ground"] + values["sphere"], rtol=1e-14, atol=0)
    with pytest.raises(ValueError, match=r"inputs of term 'sphere' must be a mapping of the names it takes"):
        loss(x, sphere={"density": 0.2})
    with pytest.raises(ValueError, match=r"term names \['density'\] are also input names"):
        tb.ClothLoss({"density": L.Gravity(faces, rest, 0.2)})


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda loss, x: loss(x, x_hat=x, colour=1), r"no term takes the inputs \['colour'\]"),
        (lambda loss, x: loss(x[:, :20]), r"term 'gravity': Gravity: x must have shape \(25, 3\) or \(B, 25, 3\), got \(3, 20, 3\)"),
        (lambda loss, x: loss(x), r"term 'inertia': Inertia: needs x_hat or both x_prev and v_prev"),
        (lambda loss, x: loss(x, x_hat=x, density=torch.ones(2, dtype=F64)),
         r"term 'gravity': Gravity: density must be a scalar or have shape \(3,\) \(one per sample\), got shape \(2,\)"),
        (lambda loss, x: loss(x, x_hat=x, density=-1.0), "Gravity: density must be positive"),
        (lambda loss, x: loss(x, x_hat=x[:2]), r"Inertia: x_hat has batch size 2"),
        (lambda loss, x: loss(x, x_hat=x, young=torch.tensor([1.0, 2.0, 3.0]), poisson=0.5),
         r"term 'stretch': Stretch: poisson must lie in the open interval"),
        (lambda loss, x: loss(x, x_hat=x, bending_stiffness=torch.ones(3, 1)), "Bending: bending_stiffness must be"),
        (lambda loss, x: loss(x, x_hat=x, sphere_center=torch.zeros(3)), "need both sphere_center and sphere_radius"),
        (lambda loss, x: loss(x, x_hat=x, sphere_center=torch.zeros(2, 3), sphere_radius=1.0),
         r"sphere_center must have shape \(3,\) or \(3, 3\)"),
    ],
)
def test_bad_inputs_name_the_term_and_the_shape(cloth, call, match):
    rest, faces, x = cloth
    loss = tb.ClothLoss({"gravity": L.Gravity(faces, rest, 0.2), "inertia": L.Inertia(faces, rest, 0.2, 0.01),
                         "stretch": L.Stretch(faces, rest, young=1e4, poisson=0.3, thickness=1e-3),
                         "bending": L.Bending(faces, rest, 1e-3), "contact": L.BodyContact(stiffness=1.0)})
    with pytest.raises(ValueError, match=match):
        call(loss, x)


def test_bad_construction_is_a_value_error(cloth):
    rest, faces, _ = cloth
    cases = [
        (lambda: L.Gravity(faces, rest, 0.0), "Gravity: density must be positive"),
        (lambda: L.Inertia(faces, rest, 0.2, torch.ones(2, 2)), r"Inertia: dt must be a scalar or have shape \(B,\)"),
        (lambda: L.Stretch(faces, rest, young=1e4, poisson=-1.0, thickness=1e-3), "poisson must lie in"),
        (lambda: L.Bending(faces, rest, -1.0), "Bending: stiffness must be non-negative"),
        (lambda: L.Pinning([0, 0], 1.0), "distinct"),
        (lambda: L.Pinning([0, 1], torch.ones(3)), r"stiffness must be a scalar or have shape \(2,\)"),
        (lambda: L.BodyContact(stiffness=1.0, power=1.0), "power must be > 1"),
        (lambda: L.BodyContact(stiffness=1.0, body_faces=torch.ones(3, 2, dtype=torch.long)), r"\(Fb, 3\)"),
        (lambda: L.BodyContact(stiffness=1.0, colliders=["sphere"]),  # pyright: ignore[reportArgumentType]
         "torchbend colliders"),
        (lambda: tb.ClothLoss({}), "non-empty"),
        (lambda: tb.ClothLoss({"g": L.Gravity(faces, rest, 0.2)}, {"h": 1.0}), r"unknown terms \['h'\]"),
        (lambda: tb.ClothLoss({"g": L.Gravity(faces, rest, 0.2)}, reduction="max"), "reduction must be"),
    ]
    for make, match in cases:
        with pytest.raises(ValueError, match=match):
            make()
    with pytest.raises(ValueError, match="nothing to collide with"):
        L.BodyContact(stiffness=1.0)(rest)
    with pytest.raises(ValueError, match="pass the body positions"):
        L.BodyContact(stiffness=1.0, body_faces=faces)(rest)
    with pytest.raises(ValueError, match="pin index 30 out of range"):
        L.Pinning([30], 1.0, torch.zeros(1, 3, dtype=F64))(rest)
    with pytest.raises(ValueError, match="non-finite"):
        L.Gravity(faces, rest, 0.2)(rest * float("nan"))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_terms_follow_the_dtype_and_device_of_the_inputs(cloth, device, dtype):
    rest, faces, x = cloth
    body, bfaces = tb.scenes.icosphere(1, 0.15, (0.2, 0.2, -0.12), dtype=F64)
    loss = tb.ClothLoss({
        "stretch": L.Stretch(faces, rest, young=1e4, poisson=0.3, thickness=1e-3),
        "bending": L.Bending(faces, rest, 1e-3),
        "gravity": L.Gravity(faces, rest, 0.2),
        "inertia": L.Inertia(faces, rest, 0.2, 0.02),
        "pin": L.Pinning([0], 10.0, rest[:1]),
        "contact": L.BodyContact(stiffness=1e4, body_faces=bfaces, colliders=[tb.Plane(point=(0, 0, -0.05))]),
    }).to(device)
    xd = x.to(device=device, dtype=dtype).requires_grad_()
    young, density = torch.tensor([1e4, 2e4, 3e4], dtype=F64), torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    center = torch.tensor([0.2, 0.2, -0.1], dtype=F64)
    # per-sample materials given on the CPU in float64 are moved and cast to the positions' device and dtype
    total, values = loss(xd, x_hat=rest.to(device=device, dtype=dtype), body=body.to(device=device, dtype=dtype),
                         young=young, density=density, sphere_center=center, sphere_radius=0.1)
    assert total.dtype == dtype and total.device.type == device
    assert all(v.dtype == dtype and v.device.type == device for v in values.values())
    (g,) = torch.autograd.grad(total, xd)
    assert g.dtype == dtype and torch.isfinite(g).all()
    _, ref_values = loss.to("cpu")(x, x_hat=rest, body=body, young=young, density=density, sphere_center=center,
                                   sphere_radius=0.1)
    tol = 1e-12 if dtype == F64 else 1e-4
    for name, v in ref_values.items():
        assert abs(float(values[name]) - float(v)) <= tol * (abs(float(v)) + 1e-6), name


def test_module_on_another_device_is_a_value_error(cloth):
    rest, faces, x = cloth
    term = L.Gravity(faces, rest, 0.2).to("meta")
    with pytest.raises(ValueError, match="Gravity: x is on cpu but the term is on meta"):
        term(x)


# ------------------------------------------------------------------------------ training-friendly default
def test_default_bending_loss_keeps_gradients_of_a_random_prediction_order_one():
    """A random initial prediction (rest plus noise of one edge length): the quadratic default's gradient
    relative to its value, ``r = |dE/dx| |x - rest| / E`` (2 for a quadratic form with an isotropic
    Hessian), stays below 20, while the tan barrier gives ``r > 1e4`` and gradients 1e6 times larger on
    the same inputs (hinges near pi)."""
    n, size = 9, 0.8
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=F64)
    gen = torch.Generator().manual_seed(0)
    x = rest + size / (n - 1) * torch.randn((8, *rest.shape), generator=gen, dtype=F64)
    out = {}
    for model in ("quadratic", "tan"):
        term = L.Bending(faces, rest, 1e-4, **({} if model == "quadratic" else {"model": model}))
        E, (g,) = grads(term, x)
        r = g.flatten(1).norm(dim=1) * (x - rest).flatten(1).norm(dim=1) / E
        out[model] = (float(r.max()), float(g.abs().max()))
    (r_quad, g_quad), (r_tan, g_tan) = out["quadratic"], out["tan"]
    assert 1 < r_quad < 20, out
    assert r_tan > 1e4 and g_tan > 1e6 * g_quad, out
