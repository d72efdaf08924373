"""Linearise once, apply many: the Hessian of a potential evaluated, projected and assembled once, then applied to
any number of directions at the cost of a sparse matrix-vector product.

A matrix-free :meth:`~torchbend.sim.model.TermSum.hvp` recomputes every element's derivatives (and, projected,
every eigensystem) on each call; :meth:`~torchbend.sim.model.TermSum.linearize` pays that once.  Use the HVPs for
a handful of products at one state (or a batch of states); use the linearised operator for the tens to hundreds
of products of a Krylov solve at one state (``benchmarks/bm_linearize.py`` measures both)."""
from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import LinearOperator, aslinearoperator
from torch import Tensor

from .linear import Preconditioner, amg_cycle, block_jacobi, diagonal_blocks, ilu_solver

__all__ = ["LinearizedHessian"]


class LinearizedHessian:
    """The Hessian ``H (3V, 3V)`` [N/m] of a potential at one state, assembled once (a ``scipy.sparse`` CSR
    matrix, :attr:`matrix`), as an operator.

    ``op @ v`` and :meth:`matvec` take ``v`` as a tensor ``(V, 3)`` or ``(3V,)`` (the result has the same shape,
    dtype and device) or a NumPy array ``(3V,)``/``(3V, k)``; :meth:`as_linear_operator` gives a
    ``scipy.sparse.linalg.LinearOperator`` for SciPy's Krylov solvers; :attr:`free` restricts to the free DOFs
    (pinned vertices removed) as the solvers do."""

    def __init__(self, matrix: sp.spmatrix, vertex_count: int, pinned: Tensor | None = None):
        self.matrix: sp.csr_matrix = sp.csr_matrix(matrix)
        n = 3 * vertex_count
        if self.matrix.shape != (n, n):
            raise ValueError(f"the matrix must be ({n}, {n}) for {vertex_count} vertices, got {self.matrix.shape}")
        self.vertex_count = vertex_count
        self._pinned = None if pinned is None else pinned.detach().cpu().numpy().astype(bool)

    @property
    def shape(self) -> tuple[int, int]:
        return self.matrix.shape  # pyright: ignore[reportReturnType]

    @property
    def free_dofs(self) -> np.ndarray:
        """The indices of the free DOFs ``(3 V_free,)`` (every DOF when nothing is pinned)."""
        if self._pinned is None:
            return np.arange(3 * self.vertex_count)
        return np.nonzero(np.repeat(~self._pinned, 3))[0]

    @property
    def free(self) -> sp.csr_matrix:
        """The Hessian on the free DOFs ``(3 V_free, 3 V_free)`` (CSR), the matrix a solve with pins works on."""
        idx = self.free_dofs
        return self.matrix[idx][:, idx].tocsr()

    def matvec(self, v):
        """``H v`` for ``v (V, 3)`` or ``(3V,)`` (tensor: same shape, dtype and device back) or a NumPy array."""
        if isinstance(v, Tensor):
            if v.shape not in ((self.vertex_count, 3), (3 * self.vertex_count,)):
                raise ValueError(f"v must have shape ({self.vertex_count}, 3) or ({3 * self.vertex_count},), "
                                 f"got {tuple(v.shape)}")
            out = self.matrix @ v.detach().reshape(-1).cpu().to(torch.float64).numpy()
            return torch.as_tensor(out, dtype=v.dtype, device=v.device).reshape(v.shape)
        return self.matrix @ np.asarray(v)

    def __matmul__(self, v):
        return self.matvec(v)

    def as_linear_operator(self, free: bool = False) -> LinearOperator:
        """A SciPy ``LinearOperator`` over all DOFs (``free=True``: the free DOFs only)."""
        return aslinearoperator(self.free if free else self.matrix)

    def preconditioner(self, kind: str = "auto", free: bool = True) -> LinearOperator:
        """A preconditioner for SciPy's Krylov solvers on this matrix (``free=True``: on the free DOFs), built once,
        symmetric positive definite also for an indefinite Hessian: ``M=`` of ``scipy.sparse.linalg.cg``.  ``kind``
        as the solver's ``preconditioner`` option (:class:`torchbend.sim.linear.Preconditioner`): ``auto`` and
        ``ilu`` the incomplete ``L |D| L^T`` the solver's CG uses, ``amg`` (needs ``pyamg``), ``block_jacobi`` (the
        inverted 3x3 vertex blocks, eigenvalues in absolute value); ``ilu``/``amg`` fall back to block-Jacobi where
        they fail, as in the solver.  Rebuild it when the matrix changes much (each Newton iteration, say); a
        Levenberg-Marquardt shift of the matrix can keep the unshifted one's."""
        A = self.free if free else self.matrix
        choice = Preconditioner.parse(kind)
        solve: Callable[[np.ndarray], np.ndarray] | None = None
        if choice in (Preconditioner.AUTO, Preconditioner.ILU):
            solve = ilu_solver(A)
        elif choice is Preconditioner.AMG:
            solve = amg_cycle(A)
        if solve is None:
            apply = block_jacobi(torch.from_numpy(diagonal_blocks(A)))

            def jacobi(r: np.ndarray) -> np.ndarray:
                return apply(torch.from_numpy(np.ascontiguousarray(r, dtype=np.float64))).numpy()

            solve = jacobi

        def matvec(r: np.ndarray, solve=solve) -> np.ndarray:
            return solve(np.asarray(r).reshape(-1)).reshape(np.shape(r))

        return LinearOperator(A.shape, matvec=matvec, dtype=A.dtype)  # pyright: ignore[reportCallIssue]

    def __repr__(self) -> str:
        return f"LinearizedHessian({self.shape[0]}x{self.shape[1]}, nnz={self.matrix.nnz})"
