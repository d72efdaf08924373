r"""Exact bending Hessians: per-hinge 12x12 blocks, sparse assembly (per hinge or per triangle),
and PSD projections for Newton-type solvers.

Per hinge (paper eq. 3) the energy Hessian is

    H_h = psi'' grad(theta) grad(theta)^T + psi' Hess(theta)                       (12 x 12)

with ``psi' = d psi/d theta``, ``psi''`` its derivative (:mod:`torchbend.models`) and the closed-form
``Hess(theta)`` of :mod:`torchbend.geometry`.  Flat index ``3*k + j`` (stencil vertex k, axis j).

Per-triangle assembly (paper sec. 4.1, eq. 7)
---------------------------------------------
``sum_h psi'_h Hess(theta_h)`` splits into half-hinges, and the (up to) three half-hinges of a
triangle share its local quantities.  For a triangle ``(p0, p1, p2)`` (CCW, unit normal ``n``,
twice the area ``|N|``), edge ``k`` opposite vertex ``k`` running ``p_{k+1} -> p_{k+2}`` with
vector ``e_k``, altitude ``h_k = |N|/|e_k|``, interior angles ``alpha_k`` and
``c_k = psi'`` of the hinge on edge ``k`` (0 on the boundary, the paper's ``sigma_k``):

    mh_k = (e_k x n) / |N|                 (outward edge normal / altitude, "M_k" of eq. 7)
    d_i  = (c_{i+1} cos(alpha_{i+2}) + c_{i+2} cos(alpha_{i+1}) - c_i) / h_i
    R_k  = c_k n (e_k x n)^T / |e_k|^3

    H_ij = d_i mh_j n^T + d_j n mh_i^T  +  { -R_{i+1} - R_{i+2}      i = j
                                            { R_{i+2}^dagger         j = i + 1   (and H_ji = H_ij^T)

where ``R^dagger`` is ``R`` when the triangle traverses edge ``i+2`` in its global direction
(``i0 -> i1``; it is the hinge's triangle A) and ``R^T`` otherwise: the paper's conditional
transpose.  The rank-one term ``psi'' g g^T`` couples both triangles of a hinge and is added per
hinge (sec. 4.2).

With :mod:`torchbend.native` enabled, both assemblies (unprojected) run as one C++ pass each: the
per-triangle one is then about 1.1x faster than the per-hinge one (both are bound by scattering
~200 resp. 144 values per hinge into the CSR array, not by arithmetic; see
``benchmarks/results/hessian_native_cpu_2core.txt``).

Projections (:class:`HessianProjection`)
----------------------------------------
``clamp``/``abs`` replace the eigenvalues of each 12x12 hinge block by ``max(l, 0)``/``|l|``;
``gauss_newton`` keeps ``max(psi'', 0) g g^T`` and drops ``psi' Hess(theta)``; ``reduced`` is the
structured projection described in :func:`project_blocks`.
"""
from __future__ import annotations

import enum
import warnings
import numpy as np
import torch
from torch import Tensor

from . import geometry
from .models import psi_theta_derivatives  # noqa: F401  (re-exported)
from .topology import HingeTopology

__all__ = [
    "HessianProjection",
    "hinge_hessian_blocks",
    "project_blocks",
    "triangle_hessian_blocks",
    "HessianPattern",
    "StencilPattern",
    "pattern_of",
    "psi_theta_derivatives",
    "to_scipy",
]


class HessianProjection(str, enum.Enum):
    """How a Hessian is made positive semi-definite (``None`` = exact, indefinite)."""

    CLAMP = "clamp"  # per-hinge eigenvalues clamped at 0
    ABS = "abs"  # per-hinge absolute eigenvalues
    GAUSS_NEWTON = "gauss_newton"  # max(psi'', 0) g g^T only
    REDUCED = "reduced"  # eigenvalues clamped in the 9-dim translation-free coordinates

    @classmethod
    def parse(cls, value) -> "HessianProjection | None":
        if value is None or value == "none":
            return None
        try:
            return cls(value)
        except ValueError:
            names = ", ".join(["None"] + [repr(m.value) for m in cls])
            raise ValueError(f"unknown Hessian projection {value!r}; expected one of {names}") from None


class Assembly(str, enum.Enum):
    HINGE = "hinge"
    TRIANGLE = "triangle"

    @classmethod
    def parse(cls, value) -> "Assembly":
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"unknown assembly {value!r}; expected 'hinge' or 'triangle'") from None


# ------------------------------------------------------------------------------ per-hinge blocks
def hinge_hessian_blocks(x4: Tensor, d1: Tensor, d2: Tensor) -> tuple[Tensor, Tensor]:
    """Per-hinge energy Hessians ``(..., H, 12, 12)`` and angle gradients ``(..., H, 12)``.

    ``x4: (..., H, 4, 3)`` stencils, ``d1 = psi'``, ``d2 = psi''``: ``(..., H)``.  Uses the fused
    C++ kernel of :mod:`torchbend.native` when it is enabled and applies."""
    from . import native
    from .autograd import _chunks

    fused = native.hinge_hessian_blocks(x4, d1, d2)
    if fused is not None:
        return fused

    blocks, grads = [], []
    for sl in _chunks(x4.shape[-3]):
        Hb, g = geometry.hinge_energy_hessian_soa(geometry.to_soa(x4[..., sl, :, :]), d1[..., sl], d2[..., sl])
        blocks.append(Hb)
        grads.append(g)
    if len(blocks) == 1:
        return blocks[0], grads[0]
    return torch.cat(blocks, -3), torch.cat(grads, -2)


def _reduce_translation(Hb: Tensor) -> Tensor:
    """The 9x9 Hessian in relative coordinates ``y_k = x_k - x0`` (k = 1..3): the lower-right block."""
    return Hb[..., 3:, 3:]


def _expand_translation(R: Tensor) -> Tensor:
    """``D^T R D`` with ``y = D x`` (``y_k = x_k - x0``): 9x9 -> 12x12 (translations in the null space)."""
    shape = R.shape[:-2]
    R4 = R.reshape(shape + (3, 3, 3, 3))  # [k, p, l, q]
    col = R4.sum(-4, keepdim=True)  # sum over rows k
    top = -col  # block row 0: -sum_k R_kl
    out_rows = torch.cat((top, R4), -4)  # (4, 3, 3, 3)
    left = -out_rows.sum(-2, keepdim=True)  # column 0: -sum_l
    full = torch.cat((left, out_rows), -2)  # (4, 3, 4, 3)
    return full.reshape(shape + (12, 12))


def project_blocks(Hb: Tensor, projection: HessianProjection, g: Tensor | None = None, d2: Tensor | None = None) -> Tensor:
    """PSD projection of symmetric hinge blocks ``(..., 12, 12)``.

    * ``clamp`` / ``abs``: ``Q max(L, 0) Q^T`` / ``Q |L| Q^T`` from ``torch.linalg.eigh``.
    * ``gauss_newton``: ``max(psi'', 0) g g^T`` (needs ``g`` and ``d2``).
    * ``reduced`` (structured): the hinge energy depends on positions only through the relative
      coordinates ``y_k = x_k - x0`` (translation invariance), so ``H = D^T H_y D`` with the fixed
      map ``D`` and ``H_y`` the lower-right 9x9 block of ``H``.  We clamp the eigenvalues of ``H_y``
      (a 9x9 instead of a 12x12 eigendecomposition: ``(9/12)^3 ~ 0.42`` of the flops) and map back.
      ``D^T P D`` is PSD whenever ``P`` is, keeps the three translations in the null space exactly
      (zero net force of every Newton step), and equals ``H`` whenever ``H`` is already PSD (then
      ``H_y`` is PSD and is left unchanged).  It is not the Frobenius-nearest PSD matrix (``clamp``
      is), since ``D`` is not orthogonal.
    """
    if projection is HessianProjection.GAUSS_NEWTON:
        if g is None or d2 is None:
            raise ValueError("gauss_newton projection needs the angle gradients and psi''")
        gg = d2.clamp_min(0)[..., None] * g
        return gg[..., :, None] * g[..., None, :]
    if projection is HessianProjection.REDUCED:
        return _expand_translation(_eig_project(_reduce_translation(Hb), HessianProjection.CLAMP))
    return _eig_project(Hb, projection)


def _eig_project(M: Tensor, projection: HessianProjection) -> Tensor:
    M = 0.5 * (M + M.transpose(-1, -2))
    if M.numel() == 0:
        return M
    L, Q = torch.linalg.eigh(M)
    L = L.clamp_min(0) if projection is not HessianProjection.ABS else L.abs()
    return (Q * L[..., None, :]) @ Q.transpose(-1, -2)


# ------------------------------------------------------------------------------ per-triangle blocks
def triangle_hessian_blocks(x: Tensor, topo: HingeTopology, d1: Tensor) -> Tensor:
    """``sum_h psi'_h Hess(theta_h)`` as per-triangle 9x9 blocks ``(F, 9, 9)`` (paper eq. 7).

    ``x: (V, 3)``, ``d1 = psi'`` per hinge ``(H,)``.  See the module docstring for the formulas."""
    F = topo.faces.to(x.device)
    p = x[F]  # (F, 3, 3) [vertex k, axis]
    e = p[:, [2, 0, 1]] - p[:, [1, 2, 0]]  # e_k = p_{k+2} - p_{k+1}, (F, 3, 3)
    N = torch.linalg.cross(e[:, 2], -e[:, 1], dim=-1)  # (p1 - p0) x (p2 - p0)
    area2 = N.norm(dim=-1)  # (F,)
    ee = (e * e).sum(-1)  # (F, 3) |e_k|^2
    valid = area2 > torch.finfo(x.dtype).eps * ee.amax(-1)
    one = torch.ones_like(area2)
    inv_area2 = torch.where(valid, torch.where(valid, area2, one).reciprocal(), 0.0)
    n = N * inv_area2[:, None]  # (F, 3)
    elen = ee.sqrt()
    inv_elen = torch.where(valid[:, None], torch.where(valid[:, None], elen, 1.0).reciprocal(), 0.0)
    en = torch.linalg.cross(e, n[:, None, :].expand_as(e), dim=-1)  # e_k x n  (|e_k| * outward normal)
    mh = en * inv_area2[:, None, None]  # (F, 3, 3)
    # cos(alpha_k) = -(e_{k+1} . e_{k+2}) / (|e_{k+1}| |e_{k+2}|)
    e1, e2 = e[:, [1, 2, 0]], e[:, [2, 0, 1]]
    cos = -(e1 * e2).sum(-1) * inv_elen[:, [1, 2, 0]] * inv_elen[:, [2, 0, 1]]  # (F, 3)
    h_inv = elen * inv_area2[:, None]  # 1 / h_k = |e_k| / |N|
    fh = topo.face_edge_hinges.to(x.device)
    c = torch.where(fh >= 0, d1[fh.clamp_min(0)], 0.0)  # (F, 3)
    c1, c2 = c[:, [1, 2, 0]], c[:, [2, 0, 1]]
    cos1, cos2 = cos[:, [1, 2, 0]], cos[:, [2, 0, 1]]
    d = (c1 * cos2 + c2 * cos1 - c) * h_inv  # (F, 3)
    # H_ij = d_i mh_j n^T + d_j n mh_i^T
    mhn = mh[:, :, :, None] * n[:, None, None, :]  # (F, j, 3, 3) = mh_j n^T
    Hl = d[:, :, None, None, None] * mhn[:, None]  # (F, i, j, 3, 3)
    Hl = Hl + Hl.permute(0, 2, 1, 4, 3)
    # R_k = c_k n (e_k x n)^T / |e_k|^3 on the endpoints (p, q) = (k+1, k+2) of edge k
    R = (c * inv_elen**3)[:, :, None, None] * (n[:, None, :, None] * en[:, :, None, :])  # (F, k, 3, 3)
    signs = topo.face_edge_signs.to(x.device)
    RT = R.transpose(-1, -2)
    fwd = (signs > 0)[:, :, None, None]
    Rpq = torch.where(fwd, R, RT)  # block (p, q)
    rows = []
    for i in range(3):
        row = []
        for j in range(3):
            blk = Hl[:, i, j]
            if i == j:
                blk = blk - R[:, (i + 1) % 3] - R[:, (i + 2) % 3]
            elif j == (i + 1) % 3:  # edge k = i + 2 runs p = i -> q = i + 1
                blk = blk + Rpq[:, (i + 2) % 3]
            else:  # j = i - 1: block (q, p) of edge k = i + 1 (p = j, q = i) is the transpose
                blk = blk + Rpq[:, (i + 1) % 3].transpose(-1, -2)
            row.append(blk)
        rows.append(torch.stack(row, 1))  # (F, j, 3, 3)
    Hf = torch.stack(rows, 1)  # (F, i, j, 3, 3)
    return Hf.permute(0, 1, 3, 2, 4).reshape(-1, 9, 9)


# ------------------------------------------------------------------------------ sparse pattern
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
        return torch.as_tensor(P.transpose(0, 1, 3, 2, 4).reshape(n, -1), dtype=torch.int64)

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


def pattern_of(topo: HingeTopology) -> HessianPattern:
    """The (cached) CSR pattern of ``topo``: built on first use and stored on the topology."""
    pat = topo.__dict__.get("_hessian_pattern")
    if pat is None:
        pat = HessianPattern(topo)
        object.__setattr__(topo, "_hessian_pattern", pat)
    return pat


def to_scipy(H: Tensor):
    """A torch sparse CSR matrix as ``scipy.sparse.csr_matrix`` (float64 or float32, on the CPU)."""
    import scipy.sparse as sp

    if H.layout != torch.sparse_csr:
        raise ValueError(f"expected a sparse CSR tensor, got layout {H.layout}")
    return sp.csr_matrix(
        (H.values().detach().cpu().numpy(), H.col_indices().cpu().numpy(), H.crow_indices().cpu().numpy()),
        shape=tuple(H.shape),
    )
