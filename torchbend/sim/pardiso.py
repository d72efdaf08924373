r"""Sparse symmetric factorisation by Intel MKL's PARDISO (the optional ``mkl`` wheel, extra
``torchbend[solvers]``): a supernodal ``L D L^T`` with Bunch-Kaufman pivoting inside the supernodes and a
nested-dissection ordering (METIS), called through MKL's C interface (``pardiso`` of ``libmkl_rt``).

:class:`SymmetricFactor` is bound to one sparsity pattern: the ordering and the symbolic factorisation
(PARDISO's phase 11) run once, every new matrix of that pattern is a numeric factorisation (phase 22) and
each right-hand side a solve (phase 33).  The factorisation reports the inertia of the matrix
(Sylvester: the signs of ``D``), which is what the Newton solvers need to know whether a matrix is
positive definite.  MKL runs sequentially here (its threading layer is set to ``SEQUENTIAL`` before
first use: no second OpenMP runtime beside PyTorch's).

:func:`available` says whether MKL was found: ``ctypes.util.find_library("mkl_rt")``, then
``libmkl_rt.so*`` under ``sys.prefix`` (where the ``mkl`` wheel puts it), or the path in the
environment variable ``TORCHBEND_MKL_RT``.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
import sys
import weakref

import numpy as np

__all__ = ["SymmetricFactor", "available"]

_REAL_SYMMETRIC_INDEFINITE = -2
_SEQUENTIAL = 1  # MKL_THREADING_SEQUENTIAL


def _candidates() -> list[str]:
    env = os.environ.get("TORCHBEND_MKL_RT")
    if env:
        return [env]
    found = ctypes.util.find_library("mkl_rt")
    names = [found] if found else []
    for root in {sys.prefix, sys.base_prefix}:
        names += sorted(glob.glob(os.path.join(root, "lib", "libmkl_rt.so*")), key=len)
        names += sorted(glob.glob(os.path.join(root, "Library", "bin", "mkl_rt*.dll")), key=len)
    return names


_LIB: ctypes.CDLL | None = None
_LOOKED = False


def _library() -> ctypes.CDLL | None:
    global _LIB, _LOOKED
    if not _LOOKED:
        _LOOKED = True
        for name in _candidates():
            try:
                lib = ctypes.CDLL(name)
                lib.pardiso  # noqa: B018 - the symbol must exist
            except (OSError, AttributeError):
                continue
            try:
                lib.MKL_Set_Threading_Layer.argtypes = [ctypes.c_int]
                lib.MKL_Set_Threading_Layer(_SEQUENTIAL)
            except AttributeError:
                pass
            _p, _i = ctypes.POINTER(ctypes.c_int64), ctypes.POINTER(ctypes.c_int32)
            lib.pardiso.argtypes = [_p, _i, _i, _i, _i, _i, ctypes.c_void_p, _i, _i, _i, _i, _i, _i,
                                    ctypes.c_void_p, ctypes.c_void_p, _i]
            lib.pardiso.restype = None
            _LIB = lib
            break
    return _LIB


def available() -> bool:
    """Whether MKL's PARDISO can be loaded (``pip install torchbend[solvers]`` installs it on x86-64)."""
    return _library() is not None


class PardisoError(RuntimeError):
    """An error code of PARDISO other than a singular or indefinite matrix (e.g. out of memory)."""


def _release(lib, pt: np.ndarray, iparm: np.ndarray, n: int) -> None:
    """Phase -1: free every buffer PARDISO holds for the handle ``pt`` (with the ``iparm`` it was analysed with)."""
    if not pt.any():  # never analysed: nothing allocated
        return
    i32 = ctypes.c_int32
    P = ctypes.POINTER(i32)
    dummy = np.zeros(1)
    idx = np.zeros(1, dtype=np.int32)
    err = i32(0)
    c = lambda v: ctypes.byref(i32(v))
    lib.pardiso(pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), c(1), c(1), c(_REAL_SYMMETRIC_INDEFINITE), c(-1),
                c(n), dummy.ctypes.data, idx.ctypes.data_as(P), idx.ctypes.data_as(P), idx.ctypes.data_as(P), c(1),
                iparm.ctypes.data_as(P), c(0), dummy.ctypes.data, dummy.ctypes.data, ctypes.byref(err))
    pt[:] = 0


class SymmetricFactor:
    """``L D L^T`` factorisations of symmetric ``(n, n)`` matrices of one CSR pattern (``indptr``,
    ``indices``: the full symmetric pattern, sorted columns, every diagonal entry present).

    :meth:`factor` takes the CSR values of a matrix (optionally ``+ shift I``) and returns whether the
    factorisation succeeded; then :attr:`inertia` is ``(positive, negative)`` pivots, :attr:`perturbed`
    the pivots PARDISO perturbed (a singular or nearly singular matrix), and :meth:`solve` solves with it.
    Raises ``RuntimeError`` if MKL is not available.

    ``single=True``: the factorisation and the solves in single precision (PARDISO's ``iparm(28)``; the values
    and right-hand sides are rounded to float32, solutions come back as float64): 1.6x faster to factorise and
    1.4x to solve on the 161x161 drape, accurate to about ``cond(A) * 6e-8``: a preconditioner (CG on the
    float64 matrix recovers the digits), not a solver."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, *, single: bool = False):
        lib = _library()
        if lib is None:
            raise RuntimeError("SymmetricFactor needs MKL's PARDISO: pip install mkl (or torchbend[solvers])")
        self._lib = lib
        n = int(indptr.shape[0]) - 1
        rows = np.repeat(np.arange(n), np.diff(indptr))
        upper = indices >= rows
        self.n, self.nnz = n, int(indices.shape[0])
        self._upper = np.flatnonzero(upper)
        counts = np.bincount(rows[upper], minlength=n)
        self._ia = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(counts, out=self._ia[1:])
        self._ja = np.ascontiguousarray(indices[upper], dtype=np.int32)
        cols_upper = indices[upper]
        self._diag = np.flatnonzero(cols_upper == rows[upper])  # positions of the diagonal in the upper values
        if self._diag.shape[0] != n:
            raise ValueError(f"SymmetricFactor: the pattern must hold every diagonal entry ({self._diag.shape[0]} of {n})")
        self._pt = np.zeros(64, dtype=np.int64)
        self._iparm = np.zeros(64, dtype=np.int32)
        ip = self._iparm
        ip[0] = 1    # iparm(1): no solver defaults, the values below
        ip[1] = 2    # iparm(2): nested dissection (METIS)
        ip[7] = 0    # iparm(8): iterative refinement (two steps) only when pivots were perturbed
        ip[9] = 8    # iparm(10): pivots below 1e-8 ||A|| perturbed
        ip[10] = 0   # iparm(11): no scaling (the analysis depends on the pattern only)
        ip[12] = 0   # iparm(13): no weighted matching (idem)
        ip[20] = 0   # iparm(21): 1x1 diagonal pivots (as SuperLU's symmetric mode; 1.4x faster than Bunch-Kaufman here)
        ip[34] = 1   # iparm(35): zero-based indices
        self.single = bool(single)
        self._dtype = np.float32 if self.single else np.float64
        ip[27] = 1 if self.single else 0  # iparm(28): single precision
        self._values = np.zeros(self._ja.shape[0], dtype=self._dtype)
        self._analysed = False
        self._factored = False
        self.inertia: tuple[int, int] = (0, 0)
        self.perturbed = 0
        self._finalizer = weakref.finalize(self, _release, lib, self._pt, self._iparm, n)

    def _call(self, phase: int, b: np.ndarray | None = None) -> tuple[int, np.ndarray | None]:
        i32 = ctypes.c_int32
        P = ctypes.POINTER(i32)
        c = lambda v: ctypes.byref(i32(v))
        err = i32(0)
        nrhs = 1
        if b is None:
            bb = xx = np.zeros(1, dtype=self._dtype)
        else:
            bb = np.asfortranarray(b, dtype=self._dtype)
            nrhs = 1 if bb.ndim == 1 else bb.shape[1]
            xx = np.zeros_like(bb)
        perm = np.zeros(1, dtype=np.int32)
        self._lib.pardiso(self._pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), c(1), c(1),
                          c(_REAL_SYMMETRIC_INDEFINITE), c(phase), c(self.n), self._values.ctypes.data,
                          self._ia.ctypes.data_as(P), self._ja.ctypes.data_as(P), perm.ctypes.data_as(P), c(nrhs),
                          self._iparm.ctypes.data_as(P), c(0), bb.ctypes.data, xx.ctypes.data, ctypes.byref(err))
        return err.value, (None if b is None else np.ascontiguousarray(xx, dtype=np.float64))

    def factor(self, values: np.ndarray, shift: float = 0.0) -> bool:
        """Numeric factorisation of the matrix with CSR ``values`` (of the full pattern) plus ``shift I``
        (the symbolic one first, once).  False if PARDISO reports the matrix singular (then :meth:`solve`
        must not be called); other errors raise :class:`PardisoError`."""
        np.take(np.asarray(values, dtype=self._dtype), self._upper, out=self._values)
        if shift:
            self._values[self._diag] += shift
        self._factored = False
        if not self._analysed:
            err, _ = self._call(11)
            if err:
                raise PardisoError(f"PARDISO analysis failed with error {err}")
            self._analysed = True
        err, _ = self._call(22)
        if err in (-4, -7):  # zero pivot / singular matrix
            return False
        if err:
            raise PardisoError(f"PARDISO factorisation failed with error {err}")
        self.inertia = (int(self._iparm[21]), int(self._iparm[22]))
        self.perturbed = int(self._iparm[13])
        self._factored = True
        return True

    @property
    def positive_definite(self) -> bool:
        """Whether the last factored matrix has ``n`` positive pivots and none perturbed."""
        return self._factored and self.inertia[0] == self.n and self.perturbed == 0

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^{-1} rhs`` with the last factorisation (``rhs``: ``(n,)`` or ``(n, k)``)."""
        if not self._factored:
            raise RuntimeError("SymmetricFactor.solve: no factorisation (factor() first, and it must succeed)")
        err, x = self._call(33, rhs)
        if err:
            raise PardisoError(f"PARDISO solve failed with error {err}")
        assert x is not None
        return x
