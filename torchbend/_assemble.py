"""Gather per-hinge stencils from vertex arrays and scatter-add per-hinge results back.

Two layouts: stencils ``(..., H, 4, 3)`` (the public kernel layout) and structure of arrays
(4 stencil vertices x 3 components, each ``(..., H)``; see :mod:`torchbend.geometry`).
"""
from __future__ import annotations

import torch
from torch import Tensor


def gather(x: Tensor, hinges: Tensor) -> Tensor:
    """``x: (..., V, 3)``, ``hinges: (H, 4)`` -> stencils ``(..., H, 4, 3)``."""
    return x[..., hinges, :]


def scatter(g4: Tensor, hinges: Tensor, vertex_count: int) -> Tensor:
    """Sum per-hinge vertex vectors ``g4: (..., H, 4, 3)`` into ``(..., V, 3)``."""
    batch = g4.shape[:-3]
    out = g4.new_zeros(batch + (vertex_count, 3))
    return out.index_add(-2, hinges.reshape(-1), g4.reshape(batch + (-1, 3)))


def gather_soa(x: Tensor, hinges: Tensor) -> tuple:
    """``x: (..., V, 3)`` -> 4 stencil vertices x 3 components, each a contiguous ``(..., H)``."""
    g = x.transpose(-1, -2)[..., hinges.t()]  # (..., 3, 4, H)
    return tuple(tuple(g[..., j, i, :] for j in range(3)) for i in range(4))


def scatter_soa(vs, hinges: Tensor, vertex_count: int) -> Tensor:
    """Sum SoA per-hinge vectors (4 x 3 components ``(..., H)``) into ``(..., V, 3)``."""
    g4 = torch.stack([c for v in vs for c in v], -1)  # (..., H, 12)
    batch = g4.shape[:-2]
    out = g4.new_zeros(batch + (vertex_count, 3))
    return out.index_add(-2, hinges.reshape(-1), g4.reshape(batch + (-1, 3)))
