"""Sparse assembly of per-element Hessian blocks: CSR patterns built once per topology, and
conversion to SciPy.

A pattern is built on first use by the energy that needs it and kept on that energy (never on the
topology, which stays an immutable value)."""
from __future__ import annotations

import functools
import warnings

import numpy as np
import torch
from torch import Tensor

from ..mesh.topology import HingeTopology

__all__ = ["StencilPattern", "HessianPattern", "to_scipy"]


class StencilPattern:
    """CSR pattern of a Hessian assembled from element stencils (built once per topology).

    ``elements: (n, m)`` vertex indices; the pattern holds every 3x3 vertex block ``(v_i, v_j)``
    with ``v_i, v_j`` in a common element.  Every scalar row of block row ``v`` has the same columns,
    ``row_len[v] = 3 * (blocks in that row)`` of them, so the entry ``(3 v_i + p, 3 v_j + q)`` sits at
    ``base + p * row_len[v_i] + q`` with ``base`` the position of the block's first entry.

    ``element_blocks (n, m * m)`` holds those bases for each element's vertex pairs ``(a, b)`` (flat
    ``m * a + b``): the compiled assembly reads these (8 bytes per vertex block instead of 72).
    ``element_pos (n, (3m)^2)`` (built on first use) maps every entry of each element's local
    ``3m x 3m`` matrix (flat index ``3m * (3a + p) + 3b + q``) to its position in the CSR value array, so
    that assembling is one ``index_add`` into it.  :meth:`blocks` and :meth:`positions` do the same for
    other element lists whose vertex pairs the pattern covers.
    """

    def __init__(self, elements: np.ndarray, vertex_count: int):
        V = int(vertex_count)
        m = elements.shape[1]
        ei = np.repeat(elements, m, axis=1).reshape(-1).astype(np.int64)
        ej = np.tile(elements, (1, m)).reshape(-1).astype(np.int64)
        keys = np.unique(ei * V + ej)
        bi, bj = keys // V, keys % V
        deg = np.bincount(bi, minlength=V)  # blocks per block row
        first = np.concatenate([[0], np.cumsum(deg)])
        rank = np.arange(keys.shape[0]) - first[bi]  # position of each block within its block row
        crow = np.concatenate([[0], np.cumsum(np.repeat(3 * deg, 3))])
        p = np.arange(3)
        base = crow[3 * bi] + 3 * rank  # (nb,): position of each block's first entry
        row_len = 3 * deg
        pos = base[:, None, None] + row_len[bi][:, None, None] * p[None, :, None] + p[None, None, :]  # (nb, 3, 3)
        col = np.empty(int(crow[-1]), dtype=np.int64)
        col[pos.reshape(-1)] = np.broadcast_to(3 * bj[:, None, None] + p[None, None, :], pos.shape).reshape(-1)
        self._keys, self._base, self._V = keys, base, V
        self._elements = elements
        self.size = 3 * V
        self.nnz = int(crow[-1])
        self.crow_indices = torch.as_tensor(crow, dtype=torch.int64)
        self.col_indices = torch.as_tensor(col, dtype=torch.int64)
        self.row_len = torch.as_tensor(row_len, dtype=torch.int64)
        self.element_blocks = self.blocks(elements)

    @functools.cached_property
    def element_pos(self) -> Tensor:
        return self.positions(self._elements)

    def blocks(self, elements: np.ndarray) -> Tensor:
        """``(n, m * m)`` positions of the first entry of each vertex block ``(a, b)`` of ``elements: (n, m)``."""
        n, m = elements.shape
        rows = np.repeat(elements, m, axis=1).astype(np.int64)
        cols = np.tile(elements, (1, m)).astype(np.int64)
        b = np.searchsorted(self._keys, rows * self._V + cols)
        return torch.as_tensor(self._base[b].reshape(n, m * m), dtype=torch.int64)

    def positions(self, elements: np.ndarray, blocks: Tensor | None = None) -> Tensor:
        """``(n, (3m)^2)`` value positions of the local matrices of ``elements: (n, m)`` (their :meth:`blocks`
        if already at hand)."""
        n, m = elements.shape
        base = (self.blocks(elements) if blocks is None else blocks).reshape(n, m, 1, m, 1)
        rl = self.row_len[torch.as_tensor(elements, dtype=torch.int64)].reshape(n, m, 1, 1, 1)
        p = torch.arange(3, dtype=torch.int64)
        return (base + rl * p.reshape(1, 1, 3, 1, 1) + p.reshape(1, 1, 1, 1, 3)).reshape(n, (3 * m) ** 2)

    def csr(self, values: Tensor) -> Tensor:
        dev = values.device
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            return torch.sparse_csr_tensor(
                self.crow_indices.to(dev),
                self.col_indices.to(dev),
                values,
                size=(self.size, self.size),
                check_invariants=False,
            )


class HessianPattern(StencilPattern):
    """The bending Hessian's pattern: blocks of vertices sharing a hinge stencil.

    ``hinge_blocks (H, 16)`` and ``face_blocks (F, 9)`` (faces with at least one hinge; the others
    contribute nothing and hold zeros) are the block bases of :class:`StencilPattern`; ``hinge_pos (H, 144)``
    and ``face_pos (F, 81)`` (built on first use, for the eager assembly) map every local entry to its CSR
    value position."""

    def __init__(self, topo: HingeTopology):
        super().__init__(topo.hinges.numpy(), topo.vertex_count)
        self.hinge_blocks = self.element_blocks
        has_hinge = (topo.face_edge_hinges.numpy() >= 0).any(1)
        fblk = torch.zeros((topo.face_count, 9), dtype=torch.int64)
        if has_hinge.any():
            fblk[torch.as_tensor(has_hinge)] = self.blocks(topo.faces.numpy()[has_hinge])
        self.face_has_hinge = torch.as_tensor(has_hinge)
        self.face_blocks = fblk
        self._faces = topo.faces.numpy()

    @property
    def hinge_pos(self) -> Tensor:
        return self.element_pos

    @functools.cached_property
    def face_pos(self) -> Tensor:
        fpos = torch.zeros((self._faces.shape[0], 81), dtype=torch.int64)
        keep = self.face_has_hinge
        if keep.any():
            fpos[keep] = self.positions(self._faces[keep.numpy()], self.face_blocks[keep])
        return fpos


def to_scipy(H: Tensor):
    """A torch sparse CSR matrix as ``scipy.sparse.csr_matrix`` (float64 or float32, on the CPU)."""
    import scipy.sparse as sp

    if H.layout != torch.sparse_csr:
        raise ValueError(f"expected a sparse CSR tensor, got layout {H.layout}")
    return sp.csr_matrix(
        (H.values().detach().cpu().numpy(), H.col_indices().cpu().numpy(), H.crow_indices().cpu().numpy()),
        shape=tuple(H.shape),
    )
