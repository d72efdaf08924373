r"""Per-triangle refactoring of the bending Hessian (Tamstorf & Grinspun 2013, sec. 4.1, eq. 7).

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

Evaluated, as the per-hinge kernels (:mod:`torchbend.ops.hinge`, "Accuracy"), without normalizing ``N``,
which is the cross product of the two shortest edges:

    mh_k = (e_k x N) / |N|^2,     d_i n = D_i N  with  D_i = -(sum_k (c_k / |e_k|) e_i . e_k) / |N|^2,
    H_ij = mh_j G_i^T + G_j mh_i^T  (G_i = D_i N),     R_k = (c_k / |e_k|^3) N mh_k^T

(``cos(alpha_{i+2}) |e_i| = -(e_i . e_{i+1}) / |e_{i+1}|``, so ``D_i = d_i / |N|``).
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..mesh.topology import HingeTopology
from .stencil import nondegenerate

__all__ = ["triangle_hessian_blocks"]


def triangle_hessian_blocks(x: Tensor, topo: HingeTopology, d1: Tensor) -> Tensor:
    """``sum_h psi'_h Hess(theta_h)`` as per-triangle 9x9 blocks ``(F, 9, 9)`` (paper eq. 7).

    ``x: (V, 3)``, ``d1 = psi'`` per hinge ``(H,)``.  See the module docstring for the formulas."""
    F = topo.faces.to(x.device)
    p = x[F]  # (F, 3, 3) [vertex k, axis]
    e = p[:, [2, 0, 1]] - p[:, [1, 2, 0]]  # e_k = p_{k+2} - p_{k+1}, (F, 3, 3)
    ee = (e * e).sum(-1)  # (F, 3) |e_k|^2
    # N = e_{k+1} x e_{k+2} for any k: from the two shortest edges (k the longest, ties as the compiled
    # tri_frame: 2, then 0; see hinge._normal)
    Ns = torch.linalg.cross(e[:, [1, 2, 0]], e[:, [2, 0, 1]], dim=-1)  # (F, k, 3): N without edge k
    m2 = (ee[:, 2] >= ee[:, 1]) & (ee[:, 2] >= ee[:, 0])
    longest = torch.where(m2, 2, torch.where(ee[:, 0] >= ee[:, 1], 0, 1))
    N = Ns.gather(1, longest[:, None, None].expand(-1, 1, 3))[:, 0]  # (F, 3)
    nn = (N * N).sum(-1)  # |N|^2
    valid = nondegenerate(nn.sqrt(), ee.amax(-1))
    one = torch.ones_like(nn)
    vf = valid.to(x.dtype)
    nn_s = torch.where(valid, nn, one)
    ee_s = torch.where(valid[:, None], ee, 1.0)
    elen = ee_s.sqrt()
    mh = torch.linalg.cross(e, N[:, None, :].expand_as(e), dim=-1) * (vf / nn_s)[:, None, None]  # (e_k x N)/|N|^2
    fh = topo.face_edge_hinges.to(x.device)
    c = torch.where(fh >= 0, d1[fh.clamp_min(0)], 0.0)  # (F, 3)
    # D_i = d_i / |N| = -(sum_k (c_k / |e_k|) e_i . e_k) / |N|^2   (d_i n = D_i N)
    gram = e @ e.transpose(-1, -2)  # (F, i, k) e_i . e_k
    D = -(gram @ (c / elen)[:, :, None])[:, :, 0] / nn_s[:, None] * vf[:, None]  # (F, 3)
    G = D[:, :, None] * N[:, None, :]  # (F, i, 3)
    # H_ij = mh_j G_i^T + G_j mh_i^T
    Hl = mh[:, None, :, :, None] * G[:, :, None, None, :]  # (F, i, j, 3, 3)
    Hl = Hl + Hl.permute(0, 2, 1, 4, 3)
    # R_k = c_k n (e_k x n)^T / |e_k|^3 = (c_k / |e_k|^3) N mh_k^T on the endpoints (p, q) = (k+1, k+2) of edge k
    R = (c / (ee_s * elen))[:, :, None, None] * (N[:, None, :, None] * mh[:, :, None, :])  # (F, k, 3, 3)
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
