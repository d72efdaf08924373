r"""Negative-curvature check at a stationary point: the smallest eigenpair of a sparse symmetric matrix.

A Newton iteration on a non-convex potential stops wherever the gradient vanishes, saddles included
(a strip clamped upright beyond its buckling length stays straight).  :func:`smallest_eigenpair`
finds the smallest eigenvalue of the exact Hessian on the free degrees of freedom and its unit
eigenvector, so that the solver can step along it; :func:`curvature_tolerance` is the round-off
level below which a negative eigenvalue is not trusted.

* Up to ``dense_limit`` unknowns: a dense LAPACK eigensolver (exact to round-off).
* Larger: Sylvester's law of inertia and shift-invert Lanczos.  :func:`count_below` factorises
  ``A - sigma I`` as ``L D L^T`` (SuperLU in symmetric mode with diagonal pivoting: ``U = D L^T``)
  and counts the negative pivots, i.e. the eigenvalues below ``sigma``.  With ``sigma = -2 tau``
  (``tau`` the round-off tolerance) a count of 0 proves that no eigenvalue is below it; then
  ``scipy.sparse.linalg.eigsh`` in shift-invert mode about ``sigma`` returns the smallest eigenvalue
  (the nearest one above the shift).  Otherwise a negative eigenvalue near zero found by Lanczos
  (``k`` nearest the shift) is confirmed or a lower shift bracketing the smallest eigenvalue is
  found by counting (shifts growing fourfold), and Lanczos about it returns the smallest.  When the
  count finds eigenvalues below the shift that Lanczos near it does not reach (many eigenvalues near
  zero), the bracketing starts from the shift itself.  When a
  factorisation fails (an exactly singular shifted matrix, off-diagonal pivots) the shift-invert
  estimate alone is used; when Lanczos fails, ``None`` is returned: not checked.

Matrices are ``scipy.sparse`` (any format) in float64 on the CPU.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["smallest_eigenpair", "curvature_tolerance", "count_below"]


def curvature_tolerance(A) -> float:
    """Round-off level of the eigenvalues of ``A`` (``scipy.sparse`` ``(n, n)``): ``1e3 eps ||A||_inf``
    (eigenvalues computed in float64 carry an absolute error of a few ``eps ||A||_2``)."""
    return 1e3 * float(np.finfo(np.float64).eps) * _inf_norm(sp.csr_matrix(A))


def _inf_norm(A: sp.csr_matrix) -> float:
    """``||A||_inf``: the largest absolute row sum (0 for an empty matrix)."""
    if A.nnz == 0:
        return 0.0
    return float(np.max(np.asarray(abs(A).sum(axis=1))))


def count_below(A, sigma: float) -> int | None:
    """The number of eigenvalues of the symmetric ``A`` (``scipy.sparse`` ``(n, n)``) below ``sigma``, from
    the inertia of ``A - sigma I`` (an ``L D L^T`` factorisation with symmetric pivoting); ``None``
    when that factorisation is not available (singular, or SuperLU left the diagonal)."""
    n = int(A.get_shape()[0])
    M = sp.csc_matrix(A - sigma * sp.identity(n, format="csc"))
    try:
        lu = spla.splu(M, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:
        return None
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return None
    d = lu.U.diagonal()
    if not np.all(np.isfinite(d)) or np.any(d == 0):
        return None
    return int((d < 0).sum())


def _nearest(A, sigma: float, k: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``k`` eigenpairs of ``A`` nearest ``sigma`` (shift-invert Lanczos), or None if that fails.  The start
    vector is fixed (ARPACK's default is drawn from a generator whose state persists between calls, which made a
    solve's negative-curvature steps depend on the solves run before it in the process)."""
    n = int(A.get_shape()[0])
    v0 = np.random.default_rng(0).standard_normal(n)
    try:
        w, V = spla.eigsh(sp.csc_matrix(A), k=max(1, min(k, n - 2)), sigma=sigma, which="LM", maxiter=50 * n, v0=v0)
    except RuntimeError:  # a singular shifted matrix, or ArpackError / ArpackNoConvergence
        return None
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(V))):
        return None
    return w, V


def _pair(found: tuple[np.ndarray, np.ndarray] | None) -> tuple[float, np.ndarray] | None:
    """The smallest of the eigenpairs ``found``, with a unit vector."""
    if found is None:
        return None
    w, V = found
    i = int(np.argmin(w))
    v = V[:, i]
    return float(w[i]), v / max(float(np.linalg.norm(v)), 1e-300)


def smallest_eigenpair(A, *, dense_limit: int = 64, k: int = 6,
                       max_brackets: int = 40) -> tuple[float, np.ndarray] | None:
    """``(lambda_min, v)`` of the symmetric ``A`` (``scipy.sparse`` ``(n, n)``, float64): the smallest
    eigenvalue and a unit eigenvector ``(n,)``; ``None`` when it could not be computed (see the module
    docstring).  ``dense_limit``: the largest ``n`` solved densely; ``k``: eigenvalues asked of the
    first Lanczos run; ``max_brackets``: shifts tried at most to bracket a negative eigenvalue."""
    A = sp.csr_matrix(A, dtype=np.float64)
    n = int(A.get_shape()[0])
    if n == 0:
        return None
    A = sp.csr_matrix((A + A.T) * 0.5)  # symmetric to the last bit
    if n <= dense_limit:
        w, V = np.linalg.eigh(A.toarray())
        return float(w[0]), V[:, 0]
    norm = _inf_norm(A)
    tau = max(curvature_tolerance(A), np.finfo(np.float64).tiny)
    sigma = -2 * tau
    below = count_below(A, sigma)
    if below == 0:  # all eigenvalues >= sigma: the nearest one above the shift is the smallest
        return _pair(_nearest(A, sigma, 1))
    near = _pair(_nearest(A, sigma, k))
    if below is None:
        return near  # no inertia to go by: the estimate nearest zero
    if near is not None and near[0] < sigma:
        lo = near[0] * 1.5  # a negative eigenvalue near[0]: is it the smallest?  Bracket with counts below it.
    else:
        # the count says an eigenvalue lies below sigma, but the k nearest the shift are all above it (many
        # eigenvalues near zero, as a soft strip has): bracket downwards from the shift.  Should that fail,
        # nothing is claimed (None) rather than the positive estimate the count contradicts.
        near, lo = None, 4 * sigma
    for _ in range(max_brackets):
        c = count_below(A, lo)
        if c is None:
            return near
        if c == 0:
            return _pair(_nearest(A, lo, 1)) or near
        if lo < -4 * norm:  # beyond the Gershgorin bound: the counts are not trustworthy
            return near
        lo *= 4
    return near
