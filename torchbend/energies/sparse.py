"""Sparse assembly of per-element Hessian blocks: CSR patterns built once per topology, and
conversion to SciPy.

A pattern is built on first use by the energy that needs it and kept on that energy (never on the
topology, which stays an immutable value)."""
from __future__ import annotations

import warnings

import numpy as np
import torch
from torch import Tensor

from ..mesh.topology import HingeTopology

__all__ = ["StencilPattern", "HessianPattern", "to_scipy"]


class StencilPattern:
    """CSR pattern of a Hessian assembled from element stencils (built once per topology).

    ``elements: (n, m)`` vertex indices; the pattern holds every 3x3 vertex block ``(v_i, v_j)``
    with ``v_i, v_j`` in a common element.  ``element_pos (n, (3m)^2)`` maps the entries of each
    element's local ``3m x 3m`` matrix (flat index ``3*k + j``) to positions in the CSR value array,
    so that assembling is one ``index_add`` into it.  :meth:`positions` does the same for other
    element lists whose vertex pairs the pattern covers.
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
        base = crow[3 * bi[:, None] + p[None, :]] + 3 * rank[:, None]  # (nb, 3): scalar row starts
        pos = base[:, :, None] + p[None, None, :]  # (nb, 3, 3)
        col = np.empty(int(crow[-1]), dtype=np.int64)
        col[pos.reshape(-1)] = np.broadcast_to(3 * bj[:, None, None] + p[None, None, :], pos.shape).reshape(-1)
        self._keys, self._pos, self._V = keys, pos, V
        self.size = 3 * V
        self.nnz = int(crow[-1])
        self.crow_indices = torch.as_tensor(crow, dtype=torch.int64)
        self.col_indices = torch.as_tensor(col, dtype=torch.int64)
        self.element_pos = self.positions(elements)

    def positions(self, elements: np.ndarray) -> Tensor:
        """``(n, (3m)^2)`` value positions of the local matrices of ``elements: (n, m)``."""
        n, m = elements.shape
        rows = np.repeat(elements, m, axis=1).astype(np.int64)
        cols = np.tile(elements, (1, m)).astype(np.int64)
        b = np.searchsorted(self._keys, rows * self._V + cols).reshape(n, m, m)
        P = self._pos[b]  # (n, m, m, 3, 3) [a, b, p, q]
        return torch.as_tensor(P.transpose(0, 1, 3, 2, 4).reshape(n, (3 * m) ** 2), dtype=torch.int64)

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

    ``hinge_pos (H, 144)`` and ``face_pos (F, 81)`` (faces with at least one hinge; the others
    contribute nothing) map local entries to CSR value positions."""

    def __init__(self, topo: HingeTopology):
        super().__init__(topo.hinges.numpy(), topo.vertex_count)
        self.hinge_pos = self.element_pos
        has_hinge = (topo.face_edge_hinges.numpy() >= 0).any(1)
        fpos = torch.zeros((topo.face_count, 81), dtype=torch.int64)
        if has_hinge.any():
            fpos[torch.as_tensor(has_hinge)] = self.positions(topo.faces.numpy()[has_hinge])
        self.face_has_hinge = torch.as_tensor(has_hinge)
        self.face_pos = fpos


def to_scipy(H: Tensor):
    """A torch sparse CSR matrix as ``scipy.sparse.csr_matrix`` (float64 or float32, on the CPU)."""
    import scipy.sparse as sp

    if H.layout != torch.sparse_csr:
        raise ValueError(f"expected a sparse CSR tensor, got layout {H.layout}")
    return sp.csr_matrix(
        (H.values().detach().cpu().numpy(), H.col_indices().cpu().numpy(), H.crow_indices().cpu().numpy()),
        shape=tuple(H.shape),
    )
