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

from .._arrays import sorted_unique
from ..mesh.topology import HingeTopology

__all__ = ["StencilPattern", "HessianPattern", "to_scipy"]


class StencilPattern:
    """CSR pattern of a Hessian assembled from element stencils (built once per topology).

    ``elements: (n, m)`` vertex indices; the pattern holds every 3x3 vertex block ``(v_i, v_j)``
    with ``v_i, v_j`` in a common element.  Every scalar row of block row ``v`` has the same columns,
    ``row_len[v] = 3 * (blocks in that row)`` of them, so the entry ``(3 v_i + p, 3 v_j + q)`` sits at
    ``base + p * row_len[v_i] + q`` with ``base`` the position of the block's first entry.

    ``element_blocks (n, m * m)`` holds those bases for each element's vertex pairs ``(a, b)`` (flat
    ``m * a + b``): 8 bytes per vertex block where a map of every entry takes 72.  The compiled assembly
    reads them as they are; :meth:`expand` turns them into the positions of every entry of the local
    ``3m x 3m`` matrices (flat index ``3m * (3a + p) + 3b + q``), chunk by chunk on the values' device, for an
    ``index_add`` (:meth:`element_positions`: on the CPU the full map, built on first request and kept; on
    other devices expanded per call, which there costs less than holding it).  :meth:`blocks` does the same for
    other element lists whose vertex pairs the pattern covers.  :meth:`on` keeps the index arrays on each device
    they were asked for (a CUDA assembly copies them once, not per call).
    """

    def __init__(self, elements: np.ndarray, vertex_count: int):
        V = int(vertex_count)
        m = elements.shape[1]
        ei = np.repeat(elements, m, axis=1).reshape(-1).astype(np.int64)
        ej = np.tile(elements, (1, m)).reshape(-1).astype(np.int64)
        keys = sorted_unique(ei * V + ej)
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
        self.size = 3 * V
        self.nnz = int(crow[-1])
        self.crow_indices = torch.as_tensor(crow, dtype=torch.int64)
        self.col_indices = torch.as_tensor(col, dtype=torch.int64)
        self.row_len = torch.as_tensor(row_len, dtype=torch.int64)
        self.elements = torch.as_tensor(elements, dtype=torch.int64)
        self.element_blocks = self.blocks(elements)
        self._devices: dict[torch.device, dict[str, Tensor]] = {}

    def on(self, device: torch.device | str) -> dict[str, Tensor]:
        """The index arrays (``crow_indices``, ``col_indices``, ``row_len``, ``elements``, ``element_blocks`` and
        those a subclass adds) on ``device``, copied on first request and kept."""
        device = torch.device(device)
        if device.type == "cpu":
            return self._arrays()
        if device not in self._devices:
            self._devices[device] = {k: t.to(device) for k, t in self._arrays().items()}
        return self._devices[device]

    def _arrays(self) -> dict[str, Tensor]:
        return {"crow_indices": self.crow_indices, "col_indices": self.col_indices, "row_len": self.row_len,
                "elements": self.elements, "element_blocks": self.element_blocks}

    def blocks(self, elements: np.ndarray) -> Tensor:
        """``(n, m * m)`` positions of the first entry of each vertex block ``(a, b)`` of ``elements: (n, m)``."""
        n, m = elements.shape
        rows = np.repeat(elements, m, axis=1).astype(np.int64)
        cols = np.tile(elements, (1, m)).astype(np.int64)
        b = np.searchsorted(self._keys, rows * self._V + cols)
        return torch.as_tensor(self._base[b].reshape(n, m * m), dtype=torch.int64)

    @staticmethod
    def expand(blocks: Tensor, elements: Tensor, row_len: Tensor) -> Tensor:
        """``(n, (3m)^2)`` value positions of every entry of the local matrices of ``elements (n, m)`` from their
        block bases ``blocks (n, m * m)`` (on any one device, with ``row_len`` there too)."""
        n, m = elements.shape
        rl = row_len[elements].reshape(n, m, 1, 1, 1)
        p = torch.arange(3, dtype=torch.int64, device=blocks.device)
        return (blocks.reshape(n, m, 1, m, 1) + rl * p.reshape(1, 1, 3, 1, 1)
                + p.reshape(1, 1, 1, 1, 3)).reshape(n, (3 * m) ** 2)

    @functools.cached_property
    def element_pos(self) -> Tensor:
        """``(n, (3m)^2)`` value positions of the local matrices of the pattern's elements (CPU; built on first
        request and kept)."""
        return self.expand(self.element_blocks, self.elements, self.row_len)

    def element_positions(self, device: torch.device, sl: slice = slice(None)) -> Tensor:
        """``element_pos[sl]`` on ``device``."""
        if device.type == "cpu":
            return self.element_pos[sl]
        a = self.on(device)
        return self.expand(a["element_blocks"][sl], a["elements"][sl], a["row_len"])

    def csr(self, values: Tensor) -> Tensor:
        a = self.on(values.device)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            return torch.sparse_csr_tensor(
                a["crow_indices"],
                a["col_indices"],
                values,
                size=(self.size, self.size),
                check_invariants=False,
            )


class HessianPattern(StencilPattern):
    """The bending Hessian's pattern: blocks of vertices sharing a hinge stencil.

    ``hinge_blocks (H, 16)`` and ``face_blocks (F, 9)`` (faces with at least one hinge, listed in
    ``hinged_faces``; the others contribute nothing and hold zeros) are the block bases of
    :class:`StencilPattern`; ``hinge_pos (H, 144)`` and ``face_pos (F, 81)`` (built on request) map every local
    entry to its CSR value position."""

    def __init__(self, topo: HingeTopology):
        super().__init__(topo.hinges.numpy(), topo.vertex_count)
        self.hinge_blocks = self.element_blocks
        has_hinge = (topo.face_edge_hinges.numpy() >= 0).any(1)
        fblk = torch.zeros((topo.face_count, 9), dtype=torch.int64)
        if has_hinge.any():
            fblk[torch.as_tensor(has_hinge)] = self.blocks(topo.faces.numpy()[has_hinge])
        self.face_has_hinge = torch.as_tensor(has_hinge)
        self.hinged_faces = torch.as_tensor(np.flatnonzero(has_hinge), dtype=torch.int64)
        self.face_blocks = fblk
        self.faces = topo.faces

    def _arrays(self) -> dict[str, Tensor]:
        return {**super()._arrays(), "faces": self.faces, "face_blocks": self.face_blocks,
                "hinged_faces": self.hinged_faces}

    @property
    def hinge_pos(self) -> Tensor:
        return self.element_pos

    @property
    def face_pos(self) -> Tensor:
        return self.expand(self.face_blocks, self.faces, self.row_len)

    @functools.cached_property
    def _hinged_face_pos(self) -> Tensor:
        return self._expand_hinged_faces(self._arrays())

    def _expand_hinged_faces(self, a: dict[str, Tensor]) -> Tensor:
        keep = a["hinged_faces"]
        return self.expand(a["face_blocks"][keep], a["faces"][keep], a["row_len"])

    def hinged_face_positions(self, device: torch.device) -> Tensor:
        """``face_pos[hinged_faces]`` on ``device`` (kept on the CPU, expanded per call elsewhere)."""
        if device.type == "cpu":
            return self._hinged_face_pos
        return self._expand_hinged_faces(self.on(device))


def to_scipy(H: Tensor):
    """A torch sparse CSR matrix (e.g. a Hessian ``(3V, 3V)`` [N/m]) as ``scipy.sparse.csr_matrix`` of the same
    shape and units (float64 or float32, on the CPU)."""
    import scipy.sparse as sp

    if H.layout != torch.sparse_csr:
        raise ValueError(f"expected a sparse CSR tensor, got layout {H.layout}")
    return sp.csr_matrix(
        (H.values().detach().cpu().numpy(), H.col_indices().cpu().numpy(), H.crow_indices().cpu().numpy()),
        shape=tuple(H.shape),
    )
