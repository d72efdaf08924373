"""Linear solves for Newton directions on the free degrees of freedom.

* :func:`direct_solve`: sparse LU (``scipy.sparse.linalg.splu``) with a Levenberg fallback.
* :func:`truncated_pcg`: preconditioned conjugate gradients, truncated at negative curvature
  (Steihaug), on a matrix-free operator.
* :func:`block_jacobi`: the block-Jacobi preconditioner from per-vertex 3x3 Hessian blocks.

Vectors here are float64 NumPy arrays over the free DOFs (flat ``3V`` coordinates with the pinned
ones removed by a ``(3V,)`` bool mask ``free``); the tensors they come from are moved to the CPU
explicitly and back to their own device by the caller.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

__all__ = ["direct_solve", "truncated_pcg", "block_jacobi"]

Operator = Callable[[np.ndarray], np.ndarray]


def direct_solve(A, rhs: np.ndarray, max_shifts: int = 12) -> tuple[np.ndarray, int]:
    """Solve ``A p = rhs`` for a descent direction (``rhs . p > 0``, ``rhs = -gradient``) by sparse LU.

    ``A``: ``scipy.sparse`` ``(n, n)`` (CSC) symmetric, ``rhs``: ``(n,)``.  A singular factorisation,
    a non-finite solution or one that is not a descent direction is retried with the Levenberg shift
    ``A + mu I``, ``mu = 1e-8 max|diag A|`` growing tenfold (at most ``max_shifts`` tries; then the
    steepest-descent direction ``rhs`` itself).  Returns ``(p, shifts)``: the number of regularised tries."""
    n = A.shape[0]
    diag_scale = float(abs(A.diagonal()).max()) if n else 1.0
    shift = 0.0
    for tries in range(max_shifts):
        try:
            M = A if shift == 0 else A + sp.identity(n, format="csc") * shift
            p = spla.splu(M).solve(rhs)
        except RuntimeError:  # singular
            p = None
        if p is not None and np.all(np.isfinite(p)) and float(rhs @ p) > 0:
            return p, tries
        shift = max(shift * 10, 1e-8 * diag_scale)
    return rhs.copy(), max_shifts


def truncated_pcg(apply: Operator, b: np.ndarray, precond: Operator, tol: float, maxiter: int) -> tuple[np.ndarray, int]:
    """Preconditioned CG for ``A p = b`` (``apply(d) = A d``, ``precond(r) ~ A^{-1} r``), stopped at
    ``|r| <= tol |b|`` or truncated at the first direction of non-positive curvature (Steihaug: the
    iterate so far, or ``b`` at the first iteration).  Returns ``(p, iterations)``."""
    x = np.zeros_like(b)
    r = b.copy()
    z = precond(r)
    d = z.copy()
    rz = r @ z
    bnorm = np.linalg.norm(b)
    for it in range(1, maxiter + 1):
        Ad = apply(d)
        curv = d @ Ad
        if curv <= 0:
            return (x if it > 1 else b.copy()), it
        alpha = rz / curv
        x += alpha * d
        r -= alpha * Ad
        if np.linalg.norm(r) <= tol * bnorm:
            return x, it
        z = precond(r)
        rz_new = r @ z
        d = z + (rz_new / rz) * d
        rz = rz_new
    return x, maxiter


def block_jacobi(blocks: Tensor, free: np.ndarray) -> Operator:
    """Block-Jacobi preconditioner on the free DOFs from the per-vertex Hessian blocks ``(V, 3, 3)``.

    Each block gets ``1e-12 max|diag|`` added to its diagonal (identity on the blocks' device) and is
    pseudo-inverted; rows and columns of pinned DOFs are dropped (``free``: ``(3V,)`` bool)."""
    eye = torch.eye(3, dtype=blocks.dtype, device=blocks.device)
    blocks = blocks + 1e-12 * blocks.diagonal(dim1=-2, dim2=-1).abs().amax() * eye
    inv = torch.linalg.pinv(blocks.cpu().double()).numpy()
    mask3 = free.reshape(-1, 3)

    def precond(r: np.ndarray) -> np.ndarray:
        full = np.zeros(free.shape[0])
        full[free] = r
        out = np.einsum("vij,vj->vi", inv, full.reshape(-1, 3)) * mask3
        return out.reshape(-1)[free]

    return precond
