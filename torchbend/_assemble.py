"""Gather per-hinge stencils from vertex arrays and scatter-add per-hinge results back."""
from __future__ import annotations

from torch import Tensor


def gather(x: Tensor, hinges: Tensor) -> Tensor:
    """``x: (..., V, 3)``, ``hinges: (H, 4)`` -> stencils ``(..., H, 4, 3)``."""
    return x[..., hinges, :]


def scatter(g4: Tensor, hinges: Tensor, vertex_count: int) -> Tensor:
    """Sum per-hinge vertex vectors ``g4: (..., H, 4, 3)`` into ``(..., V, 3)``."""
    batch = g4.shape[:-3]
    out = g4.new_zeros(batch + (vertex_count, 3))
    return out.index_add(-2, hinges.reshape(-1), g4.reshape(batch + (-1, 3)))
