"""The implicit adjoint (``tb.solve_static_adjoint``) through contact: the derivative of a cloth's equilibrium
resting on an ipc collider (with respect to the collider's position and the bending stiffness) and on a body mesh
(with respect to the body's vertices) against central differences of converged solves."""
import torch

import torchbend as tb

F64 = torch.float64
TOL = 1e-13  # the solves' residual tolerance (relative to the forces): differences far below the derivatives


def hanging(n: int = 7):
    rest, faces = tb.scenes.grid(n, n, (0.3, 0.3), dtype=F64)
    rest = rest - torch.tensor([0.15, 0.15, 0.0], dtype=F64)
    return rest, faces, [0, n - 1]


def weights(x: torch.Tensor) -> torch.Tensor:
    return torch.linspace(0.5, 1.5, x.numel(), dtype=F64).reshape(x.shape)  # a loss that sees every coordinate


def test_adjoint_through_an_ipc_rail_matches_central_differences():
    rest, faces, pins = hanging()
    bend = lambda k: tb.BendingEnergy(faces, rest, stiffness=k)  # noqa: E731
    mem = tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4)

    def model(z, k):  # the rail 3 cm below the cloth's plane, raised by z
        a = torch.stack([torch.tensor(-0.3, dtype=F64), torch.tensor(0.0, dtype=F64), -0.03 + z])
        b = torch.stack([torch.tensor(0.3, dtype=F64), torch.tensor(0.0, dtype=F64), -0.03 + z])
        rail = tb.Capsule(radius=0.02, stiffness=1.0, margin=2e-3).transformed(a, b)
        return tb.ClothModel(faces, rest, bending=bend(k), membrane=mem, colliders=[rail], density=0.2, pinned=pins)

    z = torch.tensor(0.0, dtype=F64, requires_grad=True)
    k = torch.tensor(1e-4, dtype=F64, requires_grad=True)
    m = model(z, k)
    x, info = tb.solve_static_adjoint(m, rest, [z, k], tol=TOL)
    assert info.converged and info.contact_count > 0 and info.min_distance > 0  # on the rail
    gz, gk = torch.autograd.grad((weights(x) * x).sum(), [z, k])

    def loss(zv, kv):
        xs, inf = tb.solve_static(model(torch.tensor(zv, dtype=F64), torch.tensor(kv, dtype=F64)), x.detach(), tol=TOL)
        assert inf.converged
        return float((weights(xs) * xs).sum())

    hz, hk = 1e-6, 1e-8
    fz = (loss(hz, 1e-4) - loss(-hz, 1e-4)) / (2 * hz)
    fk = (loss(0.0, 1e-4 + hk) - loss(0.0, 1e-4 - hk)) / (2 * hk)
    assert abs(float(gz) - fz) <= 1e-6 * abs(fz), (float(gz), fz)
    assert abs(float(gk) - fk) <= 1e-6 * abs(fk), (float(gk), fk)
    assert abs(fz) > 1  # the rail carries the cloth: raising it raises the cloth


def test_adjoint_through_a_body_mesh_matches_central_differences():
    rest, faces, pins = hanging()
    # a tent-shaped body mesh under the cloth: its ridge along y, 1.5 cm below the cloth's plane
    body = torch.tensor([[-0.3, -0.3, -0.06], [0.3, -0.3, -0.06], [0.0, -0.3, -0.015],
                         [-0.3, 0.3, -0.06], [0.3, 0.3, -0.06], [0.0, 0.3, -0.015]], dtype=F64)
    body_faces = torch.tensor([[0, 2, 5], [0, 5, 3], [2, 1, 4], [2, 4, 5]])
    bend = tb.BendingEnergy(faces, rest, stiffness=1e-4)
    mem = tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4)

    def model(vertices):
        tent = tb.MeshCollider(vertices, body_faces, dhat=2e-3, stiffness=1e6)
        return tb.ClothModel(faces, rest, bending=bend, membrane=mem, colliders=[tent], density=0.2,
                             pinned=[0, 6, 42, 48])  # the four corners, above the tent's feet

    verts = body.clone().requires_grad_(True)
    x, info = tb.solve_static_adjoint(model(verts), rest, [verts], tol=TOL)
    assert info.converged and info.contact_count > 0 and info.min_distance > 0
    (g,) = torch.autograd.grad((weights(x) * x).sum(), [verts])
    lift = torch.zeros_like(body)
    lift[[2, 5], 2] = 1.0  # raising the ridge

    def loss(h):
        xs, inf = tb.solve_static(model(body + h * lift), x.detach(), tol=TOL)
        assert inf.converged
        return float((weights(xs) * xs).sum())

    h = 1e-6
    fd = (loss(h) - loss(-h)) / (2 * h)
    adj = float((g * lift).sum())
    assert abs(adj - fd) <= 1e-6 * abs(fd), (adj, fd)
    assert abs(fd) > 1


def free_sheet_on_floor(k):
    """A sheet without pinned vertices resting on a two-triangle floor (a MeshCollider): it can slide along the
    floor's diagonal edge without changing its potential (across it, the diagonal's edge pairs hold it)."""
    rest, faces = tb.scenes.grid(6, 6, (0.1, 0.1), dtype=F64)
    rest = rest + torch.tensor([-0.05, -0.05, 5e-4], dtype=F64)
    floor = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]], dtype=F64)
    body = tb.MeshCollider(floor, torch.tensor([[0, 1, 2], [0, 2, 3]]), dhat=1e-3)
    model = tb.ClothModel(faces, rest, colliders=[body], density=0.2,
                          membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(faces, rest, stiffness=k))
    return model, rest


def test_adjoint_of_an_equilibrium_that_can_slide_refuses_a_loss_that_sees_the_slide():
    """The free sheet's position along the floor is not determined (the Hessian is singular along the slide): a loss
    that changes along it has no derivative, and the backward pass says so (it used to return an arbitrary number);
    a loss that ignores the slide (the heights) gets its derivative, as central differences give it."""
    import pytest

    k = torch.tensor(1e-5, dtype=F64, requires_grad=True)
    model, rest = free_sheet_on_floor(k)
    x, info = tb.solve_static_adjoint(model, rest, [k], tol=TOL)
    assert info.converged
    with pytest.raises(RuntimeError, match="the equilibrium is not isolated: the exact Hessian on the free "
                                           "coordinates has 1 zero eigenvalues"):
        (x[:, 0] + x[:, 1]).sum().backward()
    x, info = tb.solve_static_adjoint(model, rest, [k], tol=TOL)
    (grad,) = torch.autograd.grad(x[:, 2].sum(), [k])

    def heights(kv: float) -> float:
        m, r = free_sheet_on_floor(kv)
        y, inf = tb.solve_static(m, r, tol=TOL)
        assert inf.converged
        return float(y[:, 2].sum())

    h = 1e-3
    fd = (heights(1e-5 * (1 + h)) - heights(1e-5 * (1 - h))) / (2e-5 * h)
    assert abs(float(grad) - fd) <= 1e-6 * abs(fd)
