"""The edges of the envelope: the ``tan`` difference across +-pi, float32 bend angles at every scale and
offset, and the ARAP element Hessian of strongly compressed triangles, each against a high-precision
reference (mpmath, or float64 for float32 results), eager and compiled."""
from __future__ import annotations

import math

import pytest
import torch

import torchbend as tb
from torchbend.backends import native
from torchbend.ops.hinge import hinge_angle
from torchbend.ops.psi import BendingModel, phi_difference

mpmath = pytest.importorskip("mpmath")



def _native():
    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")
    return native


def _stencils(b: torch.Tensor, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions ``(4n, 3)`` and hinges ``(n, 4)`` of hinges with bend angles ``b`` (float64, before rounding)."""
    n = b.numel()
    x = torch.zeros(n, 4, 3, dtype=torch.float64)
    x[:, 1, 0] = 1.0
    x[:, 2] = torch.tensor([0.3, 1.0, 0.0], dtype=torch.float64)
    x[:, 3, 0] = 0.6
    x[:, 3, 1] = -torch.cos(b)
    x[:, 3, 2] = -torch.sin(b)
    return x.reshape(-1, 3).to(dtype), torch.arange(4 * n).reshape(n, 4)


def _angle_pairs(dtype, n: int = 300) -> tuple[torch.Tensor, torch.Tensor]:
    """``(theta, rest)``: a third on opposite sides of +-pi (distances to pi from 1e-7.5 (float32: 1e-6) to 0.3),
    a third on one side, close to each other and far, a third anywhere in (-pi, pi)."""
    g = torch.Generator().manual_seed(11)
    lo = 7.5 if dtype == torch.float64 else 6.0

    def near_pi(k):
        return 10 ** -(0.5 + (lo - 0.5) * torch.rand(k, generator=g, dtype=torch.float64))

    k = n // 3
    sign = (torch.randint(0, 2, (k,), generator=g) * 2 - 1).double()
    t1, r1 = sign * (math.pi - near_pi(k)), -sign * (math.pi - near_pi(k))
    t2 = sign * (math.pi - near_pi(k))
    r2 = torch.where(torch.rand(k, generator=g) < 0.5, sign * (math.pi - near_pi(k)), sign * 3 * torch.rand(k, generator=g, dtype=torch.float64))
    t3 = (torch.rand(k, generator=g, dtype=torch.float64) * 2 - 1) * 3.14
    r3 = (torch.rand(k, generator=g, dtype=torch.float64) * 2 - 1) * 3.14
    return torch.cat([t1, t2, t3]), torch.cat([r1, r2, r3])


def _tan_difference(t: float, r: float):
    mpmath.mp.dps = 40
    t, r = mpmath.mpf(t), mpmath.mpf(r)
    return 2 * mpmath.tan(t / 2) - 2 * mpmath.tan(r / 2)


def _ulps(value: torch.Tensor, ref: list, eps: float) -> list[float]:
    return [float(abs((mpmath.mpf(float(v)) - r) / r)) / eps if r != 0 else float(v != 0) for v, r in zip(value.tolist(), ref, strict=True)]


# A few roundings each of the half-angle sines and cosines, a product, a sum and a quotient: a worst case
# of ~6 ulps (measured: 1.8 in float64, 1.4 in float32); before, opposite sides of +-pi lost up to 2e7 ulps.
TAN_ULPS = 6.0


def test_tan_difference_eager_matches_mpmath_across_pi(dtype):
    theta, rest = (v.to(dtype) for v in _angle_pairs(dtype))
    keep = (theta.abs() < math.pi) & (rest.abs() < math.pi) & (theta != rest)
    theta, rest = theta[keep], rest[keep]
    d = phi_difference(BendingModel.TAN, theta, rest)[0]
    ref = [_tan_difference(t, r) for t, r in zip(theta.tolist(), rest.tolist(), strict=True)]
    err = _ulps(d, ref, torch.finfo(dtype).eps)
    assert max(err) <= TAN_ULPS, f"max {max(err):.3g} ulps"


def test_tan_energy_compiled_matches_mpmath_across_pi(dtype):
    """The compiled per-hinge energy psi = (phi(theta) - phi(rest))^2 (a = k = 1) at the compiled theta."""
    nat = _native()
    theta0, rest = _angle_pairs(dtype)
    x, hinges = _stencils(theta0, dtype)
    rest = rest.to(dtype)
    theta = nat.hinge_angles(x, hinges)
    keep = (theta.abs() < math.pi) & (rest.abs() < math.pi) & (theta != rest)
    x, hinges = x.reshape(-1, 4, 3)[keep].reshape(-1, 3), torch.arange(4 * int(keep.sum())).reshape(-1, 4)
    theta, rest = theta[keep], rest[keep]
    one = torch.ones(1, dtype=dtype)
    psi = nat.bending_energy(x, hinges, one, one, rest, None, None, "tan")
    ref = [_tan_difference(t, r) ** 2 for t, r in zip(theta.tolist(), rest.tolist(), strict=True)]
    err = _ulps(psi, ref, torch.finfo(dtype).eps)
    assert max(err) <= 2 * TAN_ULPS + 1, f"max {max(err):.3g} ulps (psi is a square)"
    # the eager energy of the same angles agrees
    d = phi_difference(BendingModel.TAN, theta, rest)[0]
    assert torch.allclose(psi, d * d, rtol=4 * (2 * TAN_ULPS + 1) * torch.finfo(dtype).eps, atol=0.0)


def _random_hinges(n: int, seed: int) -> torch.Tensor:
    """``(n, 4, 3)`` well-shaped stencils (edge ~1, angles in (-3, 3)) in a random orientation."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(n, 4, 3, dtype=torch.float64)
    x[:, 1, 0] = 1.0
    x[:, 2] = torch.tensor([0.4, 0.9, 0.0], dtype=torch.float64) + 0.2 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    b = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * 3.0
    x[:, 3, 0] = 0.5
    x[:, 3, 1] = -0.9 * torch.cos(b)
    x[:, 3, 2] = -0.9 * torch.sin(b)
    rot = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0]
    return x @ rot


# float32 positions of edge lengths 1e-12 .. 1e12 (the README's range is 1e-9 .. 1e9), with and without an
# offset of 1e3 edge lengths: the angle (evaluated in float64 from the float32 positions) is within an ulp
# or so of the float64 angle of the same float32 positions; before, 1e-9 lost 1.3e7 ulps and 1e9 gave NaN.
@pytest.mark.parametrize("scale", [1e-12, 1e-9, 1e-6, 1.0, 1e6, 1e9, 1e12])
@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_float32_angles_at_every_scale(scale, offset):
    x4 = _random_hinges(500, 3)
    x32 = (x4 * scale + offset * scale).to(torch.float32)
    ref = hinge_angle(x32.double())  # float64 is exact enough for a float32 result
    eps = torch.finfo(torch.float32).eps
    theta = hinge_angle(x32)
    assert theta.dtype == torch.float32
    assert float((theta.double() - ref).abs().max()) <= 2 * eps
    V = x32.reshape(-1, 3)
    topo_angles = tb.hinge_angles(V, _topology_of(x32.shape[0]))
    assert torch.equal(topo_angles, theta)
    if native.load() is not None:
        tn = native.hinge_angles(V, torch.arange(V.shape[0]).reshape(-1, 4))
        assert float((tn.double() - ref).abs().max()) <= 2 * eps


def _topology_of(n: int):
    """A topology whose hinges are the ``n`` separate stencils ``(4i, 4i+1, 4i+2, 4i+3)``."""
    faces = []
    for i in range(n):
        a, b, c, d = 4 * i, 4 * i + 1, 4 * i + 2, 4 * i + 3
        faces += [[a, b, c], [b, a, d]]
    topo = tb.HingeTopology.from_faces(torch.tensor(faces))
    assert torch.equal(topo.hinges, torch.arange(4 * n).reshape(n, 4))
    return topo


@pytest.mark.parametrize("scale", [1e-70, 1e-30, 1e30, 1e70])
def test_float64_angles_at_extreme_scales(scale):
    """float64: the scaled products keep the angle exact (bit for bit the unit-scale one for power-of-two scales)."""
    x4 = _random_hinges(200, 5)
    p = 2.0 ** round(math.log2(scale))
    ref = hinge_angle(x4)
    assert torch.equal(hinge_angle(x4 * p), ref)
    assert float((hinge_angle(x4 * scale) - ref).abs().max()) <= 64 * torch.finfo(torch.float64).eps
    if native.load() is not None:
        V = (x4 * p).reshape(-1, 3)
        tn = native.hinge_angles(V, torch.arange(V.shape[0]).reshape(-1, 4))
        assert float((tn - ref).abs().max()) <= 4 * torch.finfo(torch.float64).eps


# ---- ARAP element Hessians of strongly compressed triangles ---------------------------------------
_THICK = 1e-3


def _arap(faces, rest) -> tb.MembraneEnergy:
    return tb.MembraneEnergy(faces, rest, model="arap", young=1e5, poisson=0.3, thickness=_THICK)
_REST = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.4, 0.9, 0.0]]


def _arap_exact_hessian(rest: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """float64 autograd Hessian (9x9) of the plain ARAP energy ``A t mu sum_i (s_i - 1)^2`` of one triangle
    (the float64 module of the same, possibly float32-rounded, rest and deformed positions)."""
    ref = _arap(torch.tensor([[0, 1, 2]]), rest.double())
    D = ref.shape_matrices[0]
    coef = float(ref.rest_areas[0]) * _THICK * float(ref.mu)

    def energy(xf):
        s = torch.linalg.svdvals(xf.reshape(3, 3).T @ D)
        return coef * ((s - 1) ** 2).sum()

    return torch.func.hessian(energy)(x.double().reshape(-1))


@pytest.mark.parametrize("dtype,ratio,tol", [(torch.float64, 1e-9, 1e-6), (torch.float64, 1e-12, 1e-6),
                                             (torch.float32, 1e-4, 1e-6), (torch.float32, 1e-6, 1e-6)])
def test_arap_hessian_of_compressed_triangle_is_exact(dtype, ratio, tol):
    """A triangle squashed to ``ratio`` times its base: the unprojected element Hessian matches the exact one
    (before: the stretch floor at sqrt(eps) made it 93% (float64, 1e-9) and 68% (float32, 1e-4) wrong)."""
    faces = torch.tensor([[0, 1, 2]])
    rest = torch.tensor(_REST, dtype=dtype)
    mem = _arap(faces, rest)
    eps = torch.finfo(dtype).eps
    for angle in (0.0, 0.3, 0.7, 1.1):  # along the axes, and turned about the z axis
        c, s = math.cos(angle), math.sin(angle)
        rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        x = (torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, ratio, 0.0]], dtype=torch.float64) @ rot.T).to(dtype)
        H = mem.element_hessians(x)[0].double()
        Hx = _arap_exact_hessian(rest, x)
        # along the axes the products of the edges are exact; turned, the cross product of the nearly
        # parallel edges is known to ~eps |e1| |e2|, and so s2, the stiffest eigenvalue 2 mu (1 - 1/s2), and
        # the Hessian to ~eps / ratio (its relative condition) -- in float64; float32 edges get their cross
        # product in float64 (exact products, one rounding), so float32 keeps tol (before: 7e-5 at 1e-4)
        bound = tol if angle == 0.0 or dtype == torch.float32 else max(tol, 16 * eps / ratio)
        err = float((H - Hx).norm() / Hx.norm())
        assert err <= bound, (angle, err)


def test_arap_hessian_finite_at_collapse(dtype):
    """Zero area (collinear vertices, a collapsed edge, one point): finite Hessians, projected ones PSD."""
    faces = torch.tensor([[0, 1, 2]])
    mem = _arap(faces, torch.tensor(_REST, dtype=dtype))
    for pts in ([[0.0, 0, 0], [1.0, 0, 0], [0.3, 0, 0]], [[0.0, 0, 0], [0.0, 0, 0], [0.3, 0.2, 0]],
                [[0.5, 0.5, 0.5]] * 3):
        x = torch.tensor(pts, dtype=dtype)
        H = mem.element_hessians(x)
        assert torch.isfinite(H).all()
        for project in ("clamp", "abs"):
            Hp = mem.element_hessians(x, projection=project)[0].double()
            assert torch.isfinite(Hp).all()
            assert float(torch.linalg.eigvalsh(Hp).min()) >= -1e-6 * float(Hp.abs().max())
        assert torch.isfinite(mem.hessian(x).to_dense()).all()
