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

__all__ = ["plain_hinge_angles", "plain_bending_energy", "autograd_gradient", "autograd_hvp", "median_time"]


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
    (SPEC sec. 1, continuity through +-pi), ``theta`` for tan."""
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


def median_time(fn, repeat: int = 3, warmup: int = 1) -> float:
    """Median wall-clock seconds of ``fn()`` over ``repeat`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def autograd_gradient(energy, x: Tensor) -> Tensor:
    """``dE/dx`` of a scalar ``energy(x)`` by reverse-mode autograd (what a user would write)."""
    y = x.detach().requires_grad_()
    return torch.autograd.grad(energy(y), y)[0]


def autograd_hvp(energy, x: Tensor, v: Tensor) -> Tensor:
    """``(d^2E/dx^2) v`` of a scalar ``energy(x)`` by double backward (what a user would write)."""
    y = x.detach().requires_grad_()
    (g,) = torch.autograd.grad(energy(y), y, create_graph=True)
    return torch.autograd.grad(g, y, v)[0]
