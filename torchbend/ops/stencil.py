"""Gather per-element stencils from vertex arrays, scatter-add per-element results back, chunking,
and the one degenerate-triangle test.

Two layouts: stencils ``(..., H, 4, 3)`` (the public kernel layout) and structure of arrays
(4 stencil vertices x 3 components, each ``(..., H)``; see :mod:`torchbend.geometry`).
"""
from __future__ import annotations

from collections.abc import Iterator

import torch
from torch import Tensor

__all__ = ["CHUNK", "nondegenerate", "chunks", "sliced", "cat_or_none", "gather", "scatter", "gather_soa", "scatter_soa"]

CHUNK = 1 << 16
"""Hinges per pass of the per-hinge kernels.  The kernels are sequences of elementwise passes; in
chunks of this size their intermediates stay in the CPU caches, which keeps the cost per hinge
flat as meshes grow (a single pass over 10^6 hinges spills every intermediate to memory)."""


def chunks(n: int) -> Iterator[slice]:
    """Slices covering ``range(n)`` in pieces of at most :data:`CHUNK` (one ``slice(None)`` if it fits)."""
    if n <= CHUNK:
        yield slice(None)
        return
    for s in range(0, n, CHUNK):
        yield slice(s, min(s + CHUNK, n))


def sliced(t: Tensor | None, sl: slice) -> Tensor | None:
    """``t[..., sl]`` for a per-element tensor; a 0-dim (scalar) tensor or ``None`` is returned as is."""
    if t is None or t.ndim == 0:
        return t
    return t[..., sl]


def cat_or_none(parts: list) -> Tensor | None:
    """Concatenate per-chunk results along the last dimension (``None`` if any part is ``None``)."""
    if any(p is None for p in parts):
        return None
    return parts[0] if len(parts) == 1 else torch.cat(parts, -1)


def gather(x: Tensor, hinges: Tensor) -> Tensor:
    """``x: (..., V, 3)``, ``hinges: (H, 4)`` -> stencils ``(..., H, 4, 3)``."""
    return x[..., hinges, :]


def scatter(g4: Tensor, elements: Tensor, vertex_count: int) -> Tensor:
    """Sum per-element vertex vectors ``g4: (..., n, m, 3)`` (``elements: (n, m)``, e.g. hinges
    ``m = 4`` or faces ``m = 3``) into ``(..., V, 3)``."""
    batch = g4.shape[:-3]
    out = g4.new_zeros(batch + (vertex_count, 3))
    return out.index_add(-2, elements.reshape(-1), g4.flatten(-3, -2))  # (..., n m, 3), also for n m = 0


def gather_soa(x: Tensor, hinges: Tensor) -> tuple:
    """``x: (..., V, 3)`` -> 4 stencil vertices x 3 components, each a contiguous ``(..., H)``."""
    g = x.transpose(-1, -2)[..., hinges.t()]  # (..., 3, 4, H)
    return tuple(tuple(g[..., j, i, :] for j in range(3)) for i in range(4))


def scatter_soa(vs, hinges: Tensor, vertex_count: int) -> Tensor:
    """Sum SoA per-hinge vectors (4 x 3 components ``(..., H)``) into ``(..., V, 3)``."""
    g4 = torch.stack([c for v in vs for c in v], -1)  # (..., H, 12)
    return scatter(g4.unflatten(-1, (4, 3)), hinges, vertex_count)


def nondegenerate(area2: Tensor, longest_sq: Tensor, eps: float | None = None) -> Tensor:
    """The degenerate-triangle test used everywhere: a triangle is numerically collinear unless
    twice its area ``|N|`` exceeds ``eps * longest_edge^2`` (``eps`` of the dtype by default).

    Relative to the triangle's own size, so it does not depend on the units or the mesh's scale;
    a collapsed edge (length 0) makes the triangle degenerate too."""
    eps = torch.finfo(area2.dtype).eps if eps is None else eps
    return area2 > eps * longest_sq
