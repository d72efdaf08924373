"""Test and benchmark helpers: plain autograd reference energies (what a user would write without
torchbend) and a timing helper.

Used by the tests, the demo and the benchmarks as the independent reference: the bend angle is
the defining ``atan2`` formula of the angle written with ordinary tensor operations, and every derivative of it
comes from PyTorch's autograd (or ``torch.func``), never from torchbend's closed forms.
"""
from __future__ import annotations

import statistics
import time

import torch
from torch import Tensor

__all__ = ["plain_hinge_angles", "plain_bending_energy", "autograd_gradient", "autograd_hvp", "call_times", "median_time",
           "hood_reference_loss", "HoodReference"]


def plain_hinge_angles(x: Tensor, hinges: Tensor) -> Tensor:
    """``theta: (..., H)`` of ``x: (..., V, 3)`` by the defining atan2 formula, autograd-differentiable."""
    x0, x1, x2, x3 = (x[..., hinges[:, i], :] for i in range(4))
    e = x1 - x0
    nA = torch.linalg.cross(e, x2 - x0, dim=-1)
    nB = torch.linalg.cross(x3 - x1, e, dim=-1)
    e_hat = e / torch.linalg.vector_norm(e, dim=-1, keepdim=True)
    sin = (e_hat * torch.linalg.cross(nA, nB, dim=-1)).sum(-1)
    cos = (nA * nB).sum(-1)
    return torch.atan2(sin, cos)


def _phi(model: str, t: Tensor) -> Tensor:
    if model == "quadratic":
        return t
    if model == "tan":
        return 2.0 * torch.tan(0.5 * t)
    if model == "sin":
        return 2.0 * torch.sin(0.5 * t)
    raise ValueError(f"unknown bending model {model!r}")


def _term(model: str, theta: Tensor, ref) -> Tensor:
    """``(phi(theta') - phi(ref))^2`` with ``theta' = ref + wrap(theta - ref)`` for quadratic and sin
    (continuity through +-pi, as :func:`torchbend.ops.psi.phi_difference`), ``theta`` for tan."""
    if model != "tan":
        d = theta - ref
        theta = ref + (d - 2.0 * torch.pi * torch.ceil((d - torch.pi) / (2.0 * torch.pi)).detach())
    return (_phi(model, theta) - _phi(model, torch.as_tensor(ref))) ** 2


def plain_bending_energy(
    x: Tensor, hinges: Tensor, a: Tensor, k, rest: Tensor, model: str = "tan", c=None, prev=None
) -> Tensor:
    """``E: (...,)`` = sum_h a [k (phi - phi_rest)^2 + c (phi - phi_prev)^2], plain autograd ops."""
    model = getattr(model, "value", model)
    theta = plain_hinge_angles(x, hinges)
    psi = a * k * _term(model, theta, rest)
    if c is not None:
        if prev is None:
            raise ValueError("the viscous term needs both c and prev")
        psi = psi + a * c * _term(model, theta, prev)
    return psi.sum(-1)


def call_times(fn, repeat: int = 3, warmup: int = 1) -> list[float]:
    """Wall-clock seconds of ``repeat`` calls of ``fn()``, after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def median_time(fn, repeat: int = 3, warmup: int = 1) -> float:
    """Median wall-clock seconds of ``fn()`` over ``repeat`` calls after ``warmup`` calls."""
    return statistics.median(call_times(fn, repeat, warmup))


def autograd_gradient(energy, x: Tensor) -> Tensor:
    """``dE/dx`` of a scalar ``energy(x)`` by reverse-mode autograd (what a user would write)."""
    y = x.detach().requires_grad_()
    return torch.autograd.grad(energy(y), y)[0]


def autograd_hvp(energy, x: Tensor, v: Tensor) -> Tensor:
    """``(d^2E/dx^2) v`` of a scalar ``energy(x)`` by double backward (what a user would write)."""
    y = x.detach().requires_grad_()
    (g,) = torch.autograd.grad(energy(y), y, create_graph=True)
    return torch.autograd.grad(g, y, v)[0]


def _hood_hinges(faces: Tensor):
    """HOOD's ``f_connectivity`` (pairs of faces sharing an edge) and ``f_connectivity_edges`` (that edge)."""
    seen: dict = {}
    pairs, edges = [], []
    for f, tri in enumerate(faces.tolist()):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            key = (min(a, b), max(a, b))
            if key in seen:
                pairs.append((seen[key], f))
                edges.append(key)
            else:
                seen[key] = f
    return torch.tensor(pairs, dtype=torch.int64), torch.tensor(edges, dtype=torch.int64)


def _unit_face_normals(p: Tensor, faces: Tensor) -> Tensor:
    n = torch.linalg.cross(p[..., faces[:, 1], :] - p[..., faces[:, 0], :], p[..., faces[:, 2], :] - p[..., faces[:, 0], :],
                           dim=-1)
    return n / n.norm(dim=-1, keepdim=True)


def _knn(points: Tensor, targets: Tensor) -> tuple[Tensor, Tensor]:
    """Brute force, sample by sample: squared distance and index of the nearest target per point (no gradient)."""
    out = [(torch.cdist(p, t) ** 2).min(-1) for p, t in zip(points.detach(), targets.detach(), strict=True)]
    return torch.stack([m.values for m in out]), torch.stack([m.indices for m in out])


def _pick(values: Tensor, idx: Tensor) -> Tensor:
    return torch.stack([values[b][idx[b]] for b in range(idx.shape[0])])


def _per(v, B: int, like: Tensor) -> Tensor:
    return torch.as_tensor(v, dtype=like.dtype).expand(B).clone()


class HoodReference:
    """HOOD's six criteria in plain PyTorch (autograd for every derivative), per sample ``(B,)`` [J]: a
    transcription of the formulas of :mod:`torchbend.losses.hood`'s docstrings written without torchbend
    (hinges from a dict of edges, ``D_m`` in HOOD's ``(x0 - x2, x1 - x2)`` frame with a matrix inverse,
    normals and angles as HOOD computes them, nearest centroids by brute force).  The rest data (hinges,
    areas, ``D_m^-1``, masses per unit density) is computed once here, as a user's module would.

    ``__call__(x, *, x_curr, x_prev, body_prev, body_curr, body_next, terms=None, **material)``: ``x``,
    ``x_curr``, ``x_prev`` ``(B, V, 3)``; bodies ``(B, Vb, 3)``; materials floats or ``(B,)``; ``dt`` the step
    of every sample; ``collision_weight`` the ramp's current value; ``terms`` the names to evaluate (all)."""

    def __init__(self, faces: Tensor, rest: Tensor, body_faces: Tensor):
        self.faces, self.body_faces = faces, body_faces
        r0, r1, r2 = rest[faces[:, 0]], rest[faces[:, 1]], rest[faces[:, 2]]
        self.area = 0.5 * torch.linalg.cross(r1 - r0, r2 - r0, dim=-1).norm(dim=-1)
        self.v_area = torch.zeros(rest.shape[0], dtype=rest.dtype).index_add(0, faces.reshape(-1),
                                                                            (self.area / 3).repeat_interleave(3))
        a, b = r0 - r2, r1 - r2
        ex = a / a.norm(dim=-1, keepdim=True)
        ey = torch.linalg.cross(torch.linalg.cross(a, b, dim=-1), a, dim=-1)
        ey = ey / ey.norm(dim=-1, keepdim=True)
        Dm = torch.stack([torch.stack([(a * ex).sum(-1), (b * ex).sum(-1)], -1),
                          torch.stack([(a * ey).sum(-1), (b * ey).sum(-1)], -1)], -2)
        self.Dm_inv = torch.linalg.inv(Dm)
        self.pairs, self.edges = _hood_hinges(faces)

    def stretching(self, x, lame_mu, lame_lambda, thickness):
        B, eye = x.shape[0], torch.eye(2, dtype=x.dtype)
        tri = x[:, self.faces]  # (B, F, 3, 3)
        Ds = torch.stack([tri[:, :, 0] - tri[:, :, 2], tri[:, :, 1] - tri[:, :, 2]], dim=-1)
        F = Ds @ self.Dm_inv.to(x.dtype)
        G = 0.5 * (F.transpose(-1, -2) @ F - eye)
        trG = G.diagonal(dim1=-1, dim2=-2).sum(-1)
        lmu, llam = _per(lame_mu, B, x)[:, None, None, None], _per(lame_lambda, B, x)[:, None, None, None]
        S = lmu * G + 0.5 * llam * trG[..., None, None] * eye
        w = (S.transpose(-1, -2) @ G).diagonal(dim1=-1, dim2=-2).sum(-1)
        return (self.area.to(x.dtype) * thickness * w).sum(-1)

    def bending(self, x, bending_coeff):
        fn = _unit_face_normals(x, self.faces)
        n0, n1 = fn[:, self.pairs[:, 0]], fn[:, self.pairs[:, 1]]
        e = x[:, self.edges[:, 1]] - x[:, self.edges[:, 0]]
        l = e.norm(dim=-1, keepdim=True)
        theta = torch.atan2(((e / l) * torch.linalg.cross(n0, n1, dim=-1)).sum(-1), (n0 * n1).sum(-1))
        scale = l[..., 0] ** 2 / (4 * self.area.to(x.dtype)[self.pairs].sum(-1))
        return (_per(bending_coeff, x.shape[0], x)[:, None] * scale * theta**2 / 2).sum(-1)

    def _centroids(self, p):
        return p[:, self.body_faces].mean(dim=2)

    def collision(self, x, x_curr, body_curr, body_next, eps, weight):
        _, j = _knn(x_curr, self._centroids(body_curr))
        c, n = _pick(self._centroids(body_next), j), _pick(_unit_face_normals(body_next, self.body_faces), j)
        d = ((x - c) * n).sum(-1)
        return weight * torch.clamp(eps - d, min=0).pow(3).sum(-1)

    def friction(self, x, x_curr, body_prev, body_curr, mass, mu, radius, g, floor_normal):
        d2_prev, jp = _knn(x_curr, self._centroids(body_prev))
        d2_curr, jc = _knn(x, self._centroids(body_curr))
        n_mean = (_pick(_unit_face_normals(body_prev, self.body_faces), jp)
                  + _pick(_unit_face_normals(body_curr, self.body_faces), jc)) / 2
        delta = x - (x_curr + _pick(self._centroids(body_curr), jp) - _pick(self._centroids(body_prev), jp))
        t = delta - (delta * n_mean).sum(-1, keepdim=True) * n_mean
        floor = torch.tensor(floor_normal, dtype=x.dtype)[None, None]
        cos = torch.nn.functional.cosine_similarity(floor, t, dim=-1).abs()
        s = ((1 - cos.pow(2)).abs() + 1e-4).sqrt()
        mask = (d2_prev < radius) & (d2_curr < radius)
        return (mass * s * g * t.norm(dim=-1) * mask * mu).sum(-1)

    def __call__(self, x: Tensor, *, x_curr: Tensor, x_prev: Tensor, body_prev: Tensor, body_curr: Tensor,
                 body_next: Tensor, density: float | Tensor = 0.20022, lame_mu: float | Tensor = 23600.0,
                 lame_lambda: float | Tensor = 44400.0, bending_coeff: float | Tensor = 3.9625778333333325e-05,
                 thickness: float = 4.7e-4, dt: float | Tensor = 1 / 30, eps: float = 2e-3,
                 collision_weight: float = 5e3, mu: float = 0.5, radius: float = 3e-3, g: float = 9.81, axis: int = 1,
                 floor_normal=(0.0, 0.0, 1.0), terms=None) -> dict[str, Tensor]:
        B = x.shape[0]
        mass = _per(density, B, x)[:, None] * self.v_area.to(x.dtype)  # (B, V)
        every = {
            "stretching": lambda: self.stretching(x, lame_mu, lame_lambda, thickness),
            "bending": lambda: self.bending(x, bending_coeff),
            "inertia": lambda: (((x - (2 * x_curr - x_prev)) ** 2).sum(-1) * mass).sum(-1) / (2 * _per(dt, B, x) ** 2),
            "gravity": lambda: g * (mass * x[..., axis]).sum(-1),
            "collision": lambda: self.collision(x, x_curr, body_curr, body_next, eps, collision_weight),
            "friction": lambda: self.friction(x, x_curr, body_prev, body_curr, mass, mu, radius, g, floor_normal),
        }
        return {name: every[name]() for name in (terms or every)}


def hood_reference_loss(x: Tensor, faces: Tensor, rest: Tensor, *, body_faces: Tensor, **inputs) -> dict[str, Tensor]:
    """:class:`HoodReference` of ``(faces, rest, body_faces)`` applied once (keywords as its ``__call__``)."""
    return HoodReference(faces, rest.to(x.dtype), body_faces)(x, **inputs)
