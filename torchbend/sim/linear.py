r"""Linear solves for Newton directions on the free degrees of freedom.

* :class:`FreeHessian`: the Hessian of a :class:`~torchbend.sim.model.ClothModel` restricted to the
  free DOFs (plus an optional diagonal, the inertia ``M/dt^2``), assembled once per Newton iteration
  into one torch sparse CSR matrix on the positions' device (its pattern is kept per model and pinned set
  while the terms' patterns stay, and within a Newton solve while the contact pairs change:
  :meth:`FreeHessian.begin_solve`); :meth:`FreeHessian.to_scipy` gives the same matrix as ``scipy.sparse`` on the
  CPU.
* :func:`direct_solve`: MKL PARDISO's supernodal ``L D L^T`` when the optional ``mkl`` is installed
  (``pip install torchbend[solvers]``; :mod:`~torchbend.sim.pardiso`, the ordering and symbolic analysis
  kept per pattern by :meth:`FreeHessian.direct_factor`), else sparse LU (``scipy.sparse.linalg.splu`` in
  symmetric mode: minimum degree on ``A + A^T``, diagonal pivots), or on request a sparse Cholesky
  (CHOLMOD through the optional ``cholespy``) with the factorisation as fallback for indefinite matrices;
  Levenberg shifts when the direction is not a descent direction.  It reports whether the matrix was
  found positive definite (the inertia of the factorisation, or the Cholesky's success).
* :func:`pcg`: preconditioned conjugate gradients in torch on any device, truncated at negative
  curvature (Steihaug), bounded, with no host round trip per iteration on a GPU.
* Preconditioners (:class:`Preconditioner`): block-Jacobi (torch, any device, SPD by construction),
  an incomplete ``L |D| L^T`` factorisation (from ``scipy.sparse.linalg.spilu``, CPU; symmetric positive
  definite by construction, see :func:`ilu`) and smoothed-aggregation AMG (the optional ``pyamg``, CPU);
  ``"auto"`` is the incomplete factorisation for CPU tensors and block-Jacobi on other devices.

The direct solver works on the CPU (the matrix is copied there); CG runs on the device of the
positions, and only the CPU preconditioners (``ilu``, ``amg``) copy vectors to the host, once per
CG iteration (so ``"auto"`` never does on a GPU).  Benchmarks: ``benchmarks/bm_linear.py``.
"""
from __future__ import annotations

import contextlib
import math
import os
import sys
import weakref
from typing import Callable, NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from .._arrays import sorted_unique
from ..options import Option, Projection
from . import pardiso
from .terms import as_csr

__all__ = ["Preconditioner", "DirectResult", "CGResult", "FreeHessian", "direct_solve", "lu_solve", "cholesky_solve",
           "pcg", "block_jacobi", "ilu", "amg", "make_preconditioner", "cg_iteration_bound", "has_cholespy", "has_pyamg"]

Apply = Callable[[Tensor], Tensor]


# -------------------------------------------------------------------- optional dependencies
def _optional(name: str):
    try:
        return __import__(name)
    except ImportError:
        return None


_cholespy = _optional("cholespy")
_pyamg = _optional("pyamg")


def has_cholespy() -> bool:
    """Whether the sparse Cholesky (``cholespy``, extra ``torchbend[solvers]``) is installed."""
    return _cholespy is not None


def has_pyamg() -> bool:
    """Whether the AMG preconditioner (``pyamg``, extra ``torchbend[solvers]``) is installed."""
    return _pyamg is not None


class Preconditioner(Option):
    """CG preconditioner: ``auto`` (incomplete LU for CPU tensors, block-Jacobi on other devices),
    ``block_jacobi`` (3x3 vertex blocks, torch, any device), ``ilu`` (incomplete ``L |D| L^T`` from
    ``scipy`` ``spilu``, CPU) or
    ``amg`` (``pyamg`` smoothed aggregation, CPU; needs ``pyamg``)."""

    __label__ = "preconditioner"

    AUTO = "auto"
    BLOCK_JACOBI = "block_jacobi"
    ILU = "ilu"
    AMG = "amg"


# -------------------------------------------------------------------- assembled free Hessian
class _Pattern:
    """The CSR pattern of a free Hessian and where each term's values go (built on the CPU, then moved to
    ``device``).  ``extra``: keys (``row * nf + col``) kept in the pattern beyond the terms' own, e.g. the entries
    of the contact pairs of earlier iterates (:meth:`FreeHessian.assemble`)."""

    def __init__(self, free: np.ndarray, terms: list[tuple[np.ndarray, np.ndarray]], device: torch.device,
                 extra: np.ndarray | None = None):
        n_full = free.shape[0]
        index = np.full(n_full, -1, dtype=np.int64)
        index[free] = np.arange(int(free.sum()))
        nf = int(free.sum())
        vf = nf // 3
        self._free, self._index = free, index
        # every free vertex's 3x3 diagonal block is in the pattern (colliders, inertia, block-Jacobi)
        bi = np.repeat(np.arange(nf), 3)
        bj = (3 * (np.arange(nf) // 3))[:, None].repeat(3, 1) + np.arange(3)[None, :]
        placed = [self._term_keys(rows, cols, nf) for rows, cols in terms]
        block_keys = bi * nf + bj.reshape(-1)
        own = sorted_unique(np.concatenate([block_keys, *(k for _, k in placed)]))
        keys = own if extra is None else sorted_unique(np.concatenate([own, extra]))  # (np.union1d hashes: slow)
        rows = keys // nf
        crow = np.zeros(nf + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows, minlength=nf), out=crow[1:])
        self.n, self.nnz, self.device, self.keys = nf, int(keys.shape[0]), device, keys
        self.crow, self.col = self._dev(crow), self._dev(keys % nf)
        self.term_keep, self.term_pos, self.term_whole, self._term_pos_np = [], [], [], []
        for (keep, k), (t_rows, _) in zip(placed, terms):
            self._set_term(len(self.term_pos), keep, k, np.searchsorted(keys, k), t_rows.shape[0])
        self._block_pos_np = np.searchsorted(keys, block_keys)
        self.block_pos = self._dev(self._block_pos_np.reshape(vf, 3, 3))
        self.used = int(own.shape[0])  # the entries the current terms fill (the rest: kept from earlier ones)
        self.free_vertices = self._dev(np.flatnonzero(free.reshape(-1, 3)[:, 0]))
        self.scipy_indices = (keys % nf, crow)
        # the same as 32-bit integers where they fit: scipy then takes them as they are (with 64-bit ones it scans
        # both arrays for their range on every matrix it wraps)
        small = self.nnz < 2**31 - 1
        self.wrap_indices = tuple(a.astype(np.int32) if small else a for a in self.scipy_indices)
        self.factor: pardiso.SymmetricFactor | None = None  # built on first use (direct solves with MKL)
        self.single_factor: pardiso.SymmetricFactor | None = None  # idem, single precision (reused factorisations)

    def _dev(self, a: np.ndarray) -> Tensor:
        return torch.as_tensor(a, dtype=torch.int64, device=self.device)

    def _term_keys(self, rows: np.ndarray, cols: np.ndarray, nf: int) -> tuple[np.ndarray, np.ndarray]:
        """The entries of a term's ``(rows, cols)`` (full DOFs) between free DOFs, and their keys."""
        keep = self._free[rows] & self._free[cols]
        return np.flatnonzero(keep), self._index[rows[keep]] * nf + self._index[cols[keep]]

    def _set_term(self, i: int, keep: np.ndarray, keys: np.ndarray, pos: np.ndarray, count: int) -> None:
        # a term whose every entry is kept (no pinned vertex in it) needs no gather; one whose entries are the
        # whole pattern in order (the bending's 2-ring pattern usually) starts the values as a copy
        entry = (None if keep.shape[0] == count else self._dev(keep), self._dev(pos),
                 pos.shape[0] == self.nnz and bool(np.all(pos == np.arange(self.nnz))))
        if i == len(self.term_pos):
            self.term_keep.append(None)
            self.term_pos.append(entry[1])
            self.term_whole.append(False)
            self._term_pos_np.append(pos)
        self.term_keep[i], self.term_pos[i], self.term_whole[i] = entry
        self._term_pos_np[i] = pos

    def place(self, i: int, rows: np.ndarray, cols: np.ndarray) -> bool:
        """Term ``i``'s new entries ``(rows, cols)`` placed in this pattern, if every one of them is in it (then
        the pattern, and a factorisation analysed on it, serve on); False (nothing changed) otherwise."""
        keep, k = self._term_keys(rows, cols, self.n)
        pos = np.searchsorted(self.keys, k)
        if k.shape[0] and (int(pos.max()) >= self.nnz or not np.array_equal(self.keys[pos], k)):
            return False
        self._set_term(i, keep, k, pos, rows.shape[0])
        used = np.zeros(self.nnz, dtype=bool)
        used[self._block_pos_np] = True
        for q in self._term_pos_np:
            used[q] = True
        self.used = int(used.sum())
        return True


def _update_pattern(fh: FreeHessian, matrices: list[Tensor], device: torch.device) -> _Pattern:
    """The pattern for the terms' CSR ``matrices`` of ``fh`` (kept, placed in, grown or rebuilt: :meth:`FreeHessian.begin_solve`)."""
    index = tuple((H.crow_indices(), H.col_indices()) for H in matrices)
    pat, old_index = fh._pattern, fh._term_index
    # forgotten while it changes: an exception part way (an interrupt, out of memory) leaves no pattern whose
    # positions disagree with the recorded term patterns
    fh._pattern, fh._term_index = None, ()
    own = lambda: _Pattern(fh._free, [_csr_indices(H) for H in matrices], device)  # noqa: E731
    unchanged = pat is not None and len(index) == len(old_index) and _same_patterns(index, old_index)
    if pat is None or pat.device != device or len(index) != len(old_index):
        pat = own()
    elif fh._trim:  # a solve's first assembly: the terms' own pattern
        pat = pat if unchanged and pat.used == pat.nnz else own()
    elif not unchanged:
        # a term's pattern changed (the contact pairs of a new iterate): with keep_pattern placed in the kept
        # pattern where all its entries are there; else a new pattern that keeps the old entries too, unless
        # they would make up more than a third of it (then the terms' own)
        changed = [i for i, (a, b) in enumerate(zip(index, old_index)) if not _same_patterns((a,), (b,))]
        if not fh.keep_pattern:
            pat = own()
        elif not all(pat.place(i, *_csr_indices(matrices[i])) for i in changed) or pat.nnz > 1.5 * pat.used:
            bloated = pat.nnz > 1.5 * pat.used
            grown = _Pattern(fh._free, [_csr_indices(H) for H in matrices], device,
                             extra=None if bloated else pat.keys)
            pat = grown if grown.nnz <= 1.5 * grown.used else own()
    fh._trim = False
    fh._pattern, fh._term_index = pat, index
    return pat


def _same_patterns(a: tuple, b: tuple) -> bool:
    """Whether two tuples of CSR ``(crow, col)`` index pairs are equal (``torch.equal`` returns at once for
    views of one storage: the energies' cached patterns)."""
    return len(a) == len(b) and all(torch.equal(ra, rb) and torch.equal(ca, cb) for (ra, ca), (rb, cb) in zip(a, b))


def _csr_indices(H: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Row and column index of every stored value of a torch sparse CSR matrix (NumPy, CPU)."""
    crow = H.crow_indices().cpu().numpy()
    return np.repeat(np.arange(crow.shape[0] - 1), np.diff(crow)), H.col_indices().cpu().numpy()


_FREE_HESSIANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class FreeHessian:
    """The Hessian of a model's potential on its free DOFs, one torch sparse CSR ``(nf, nf)`` [N/m].

    ``free_mask``: ``(3V,)`` bool, whole vertices (pinned vertices drop their three DOFs).  The terms
    are :class:`~torchbend.sim.terms.EnergyTerm` objects (sparse matrices, or per-vertex 3x3 blocks);
    the summed pattern (every free vertex keeps its diagonal
    block) and the scatter positions of each term are built on first use and rebuilt when a term's pattern
    changes (the energies keep their CSR patterns per topology), or, after :meth:`begin_solve`, kept while the
    new entries fit in it.  Use :meth:`for_model` to share one per model and pinned set."""

    def __init__(self, model, free_mask: Tensor):
        self._model = weakref.ref(model)  # weak: the per-model cache must not keep its key alive
        self.free_mask = free_mask
        self._free = free_mask.cpu().numpy().astype(bool)
        if self._free.ndim != 1 or self._free.shape[0] % 3 or (self._free.reshape(-1, 3) != self._free[::3, None]).any():
            raise ValueError(f"FreeHessian: free_mask must be a (3V,) bool mask of whole vertices, got shape "
                             f"{tuple(free_mask.shape)}")
        self._pattern: _Pattern | None = None
        self._term_index: tuple = ()
        self.keep_pattern = False  # see begin_solve
        self._trim = False

    def begin_solve(self) -> None:
        """From now on keep the pattern while the terms' patterns change (the Newton solver's, whose contact pairs
        change from one iterate to the next): a term's new entries that are all in it are placed there, so that
        the pattern and PARDISO's analysis on it serve on; new entries give a pattern that keeps the old ones too.
        A pattern whose kept entries are over a third of it is rebuilt from the terms' own, and so is one with any
        kept entry at the first assembly after this call: every solve starts from the terms' own pattern (its
        pattern does not depend on earlier solves; a factorisation kept with an unchanged pattern, as
        ``LinearSolver.reuse_factorization`` keeps one, may).  An instance on which this was never called
        (:meth:`ClothModel.hessian`'s) keeps exactly the terms' pattern; one shared through :meth:`for_model`
        keeps patterns for every later user once a solve has called it."""
        self.keep_pattern = True
        self._trim = True

    @classmethod
    def for_model(cls, model, free_mask: Tensor) -> FreeHessian:
        """The cached instance of ``model`` for this ``free_mask`` and device (a new one otherwise)."""
        cached = _FREE_HESSIANS.get(model)
        if (cached is not None and cached.free_mask.device == free_mask.device
                and cached.free_mask.shape == free_mask.shape and bool((cached.free_mask == free_mask).all())):
            return cached
        fh = cls(model, free_mask)
        _FREE_HESSIANS[model] = fh
        return fh

    @property
    def model(self):
        """The :class:`~torchbend.sim.model.ClothModel` (held weakly)."""
        model = self._model()
        if model is None:
            raise ReferenceError("the model of this FreeHessian no longer exists")
        return model

    @property
    def size(self) -> int:
        """The number of free DOFs ``nf``."""
        return int(self._free.sum())

    def assemble(self, x: Tensor, terms, ctx, option: Projection) -> Tensor:
        """The free Hessian at ``x (V, 3)`` [m] of the sum of ``terms`` (:class:`~torchbend.sim.terms.EnergyTerm`,
        e.g. the model's and a time step's inertia) in the step context ``ctx``, each with the projection
        ``option``: a torch sparse CSR ``(nf, nf)`` on ``x``'s device in ``x``'s dtype.  Terms with per-vertex
        blocks (:meth:`~torchbend.sim.terms.EnergyTerm.vertex_blocks`: colliders, inertia) go to the diagonal
        blocks; the others' sparse matrices are scattered through the summed pattern."""
        matrices, blocks = [], None
        for t in terms:
            b = t.vertex_blocks(x, ctx, option)
            if b is None:
                matrices.append(as_csr(t.hessian(x, ctx, option)))
            else:
                blocks = b if blocks is None else blocks + b
        pat = _update_pattern(self, matrices, x.device)
        values = None
        # a term whose values fill the whole pattern first: a copy of them is the sum's start (one pass less)
        order = sorted(range(len(matrices)), key=lambda i: not pat.term_whole[i])
        for H, keep, pos, whole in ((matrices[i], pat.term_keep[i], pat.term_pos[i], pat.term_whole[i]) for i in order):
            v = H.values().detach().to(x.dtype)
            v = v if keep is None else v[keep]
            if values is None and whole:
                values = v.clone()  # (the term's own values stay untouched)
                continue
            if values is None:
                values = x.new_zeros(pat.nnz)
            values.index_add_(0, pos, v)
        if values is None:
            values = x.new_zeros(pat.nnz)
        if blocks is not None:
            values.index_add_(0, pat.block_pos.reshape(-1), blocks.detach().to(x.dtype)[pat.free_vertices].reshape(-1))
        return _csr(pat.crow, pat.col, values, pat.n)

    def diagonal(self, A: Tensor) -> Tensor:
        """The diagonal ``(nf,)`` of an assembled free Hessian ``A`` (on its device)."""
        return self.diagonal_blocks(A).diagonal(dim1=-2, dim2=-1).reshape(-1)

    def shifted(self, A: Tensor, d: Tensor) -> Tensor:
        """``A + diag(d)`` for an assembled free Hessian ``A`` and ``d (nf,)``, a new torch sparse CSR on
        ``A``'s device (``A`` is not modified)."""
        assert self._pattern is not None, "assemble() first"
        pat = self._pattern
        values = A.values().clone()
        diag_pos = pat.block_pos.diagonal(dim1=-2, dim2=-1).reshape(-1)
        values[diag_pos] += d.to(dtype=values.dtype, device=values.device)
        return _csr(pat.crow, pat.col, values, pat.n)

    def diagonal_blocks(self, A: Tensor) -> Tensor:
        """The ``(Vf, 3, 3)`` diagonal blocks of an assembled free Hessian ``A`` (on its device)."""
        assert self._pattern is not None, "assemble() first"
        return A.values()[self._pattern.block_pos]

    def direct_factor(self) -> pardiso.SymmetricFactor | None:
        """The sparse ``L D L^T`` factorisation (:class:`~torchbend.sim.pardiso.SymmetricFactor`) bound to the
        current pattern, or ``None`` without MKL.  Kept with the pattern: PARDISO's ordering and symbolic
        analysis run once per model and pinned set, every Newton matrix after that is a numeric
        factorisation only."""
        assert self._pattern is not None, "assemble() first"
        pat = self._pattern
        if pat.factor is None and pardiso.available():
            col, crow = pat.scipy_indices
            pat.factor = pardiso.SymmetricFactor(crow, col)
        return pat.factor

    def single_factor(self) -> pardiso.SymmetricFactor | None:
        """A single-precision factorisation bound to the current pattern (``SymmetricFactor(single=True)``), kept
        with it as :meth:`direct_factor` is, or ``None`` without MKL: the preconditioner of the direct solver's
        CG when it reuses factorisations (``LinearSolver.reuse_factorization``)."""
        assert self._pattern is not None, "assemble() first"
        pat = self._pattern
        if pat.single_factor is None and pardiso.available():
            col, crow = pat.scipy_indices
            pat.single_factor = pardiso.SymmetricFactor(crow, col, single=True)
        return pat.single_factor

    def to_scipy(self, A: Tensor) -> sp.csr_matrix:
        """An assembled free Hessian as ``scipy.sparse`` CSR float64 (copied to the CPU)."""
        assert self._pattern is not None, "assemble() first"
        col, crow = self._pattern.wrap_indices
        n = self._pattern.n
        return sp.csr_matrix((A.values().detach().cpu().double().numpy(), col, crow), shape=(n, n))


def _csr(crow: Tensor, col: Tensor, values: Tensor, n: int) -> Tensor:
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, col, values, size=(n, n), check_invariants=False)


# -------------------------------------------------------------------- direct solves
class DirectResult(NamedTuple):
    """A direct solve: the direction ``p (n,)``, the Levenberg ``shifts`` it took (0: the matrix as
    given), whether the unshifted matrix was found positive definite (``None``: not determined, e.g.
    an LU with off-diagonal pivots) and the factorisation used (``"cholesky"`` / ``"lu"``, or
    ``"steepest"`` when every shift failed)."""

    p: np.ndarray
    shifts: int
    positive_definite: bool | None
    method: str


@contextlib.contextmanager
def _quiet_stdout():
    """Silence file descriptor 1 (CHOLMOD prints "not positive definite" warnings with C stdio).

    Python's and C's buffers are flushed on both sides; output other threads write meanwhile is lost."""
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError, AttributeError):
        yield
        return
    libc = _libc()
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        if libc is not None:
            libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)


def _libc():
    try:
        import ctypes

        return ctypes.CDLL(None)
    except (OSError, TypeError):  # e.g. Windows: no process-wide C library handle
        return None


def cholesky_solve(A: sp.spmatrix, rhs: np.ndarray) -> np.ndarray | None:
    """``A^{-1} rhs`` by a sparse Cholesky factorisation (``cholespy``; ``A`` symmetric, its lower
    triangle is used), or ``None`` when ``A`` is not positive definite or ``cholespy`` is absent."""
    if _cholespy is None:
        return None
    A = sp.csr_matrix(A)
    n = int(rhs.shape[0])
    try:
        with _quiet_stdout():
            solver = _cholespy.CholeskySolverD(n, A.indptr.astype(np.int32), A.indices.astype(np.int32),
                                               np.ascontiguousarray(A.data, dtype=np.float64),
                                               _cholespy.MatrixType.CSR)
    except ValueError:  # "Matrix is not positive definite!"
        return None
    out = np.zeros(n)
    solver.solve(np.ascontiguousarray(rhs, dtype=np.float64), out)
    return out


def lu_solve(A: sp.spmatrix, rhs: np.ndarray) -> tuple[np.ndarray | None, bool | None]:
    """``(A^{-1} rhs, positive definite?)`` by sparse LU; ``(None, definite)`` when ``A`` is singular.

    First SuperLU in symmetric mode: minimum degree on ``A + A^T`` and diagonal pivots only
    (``diag_pivot_thresh=0``), i.e. ``P^T L D L^T P`` whose pivot signs are ``A``'s inertia (Sylvester):
    1.4-2.3x faster than SciPy's default (COLAMD, partial pivoting) on these matrices
    (benchmarks/results/linear_cpu_1thread.txt).  A zero pivot (then ``A`` is not positive definite) or a
    non-finite solution (pivot growth on an indefinite matrix) is retried with the default partial
    pivoting.  ``definite``: all pivots positive, or ``None`` if the symmetric factorisation failed."""
    A = sp.csc_matrix(A)
    try:
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:  # a zero pivot
        p, definite = None, False
    else:
        p = lu.solve(rhs)
        definite = bool((lu.U.diagonal() > 0).all()) if np.array_equal(lu.perm_r, lu.perm_c) else None
        if np.all(np.isfinite(p)):
            return p, definite
    try:
        return spla.splu(A).solve(rhs), definite
    except RuntimeError:  # exactly singular
        return None, definite


def _ldlt_solve(factor: pardiso.SymmetricFactor, A: sp.csr_matrix, rhs: np.ndarray,
                shift: float) -> tuple[np.ndarray | None, bool]:
    """``((A + shift I)^{-1} rhs, positive definite?)`` by the PARDISO factorisation bound to ``A``'s pattern;
    ``(None, False)`` when the matrix is singular."""
    if not factor.factor(A.data, shift):
        return None, False
    return factor.solve(rhs), factor.positive_definite


def reused_factor_solve(A: sp.csr_matrix, rhs: np.ndarray, factor: pardiso.SymmetricFactor, *, tol: float,
                        maxiter: int) -> tuple[np.ndarray | None, int]:
    """``A^{-1} rhs`` to the relative residual ``tol`` by CG preconditioned with the numeric factorisation that
    ``factor`` holds of an earlier matrix of ``A``'s pattern (an earlier Newton iterate's, or the previous time
    step's: nearby matrices, so that CG converges in a few iterations at the cost of triangular solves).
    ``A``: ``scipy.sparse`` CSR ``(n, n)``, ``rhs``: ``(n,)``.  Returns ``(p, CG iterations)``, with ``p = None``
    when there is no positive definite factorisation to use, or CG did not reach ``tol`` within ``maxiter``,
    met a direction of non-positive curvature or broke down, or ``p`` is not a descent direction
    (``rhs . p > 0``): the caller factorises ``A`` then."""
    n = int(A.get_shape()[0])
    if not factor.positive_definite or factor.n != n:
        return None, 0
    b = torch.from_numpy(np.ascontiguousarray(rhs, dtype=np.float64))
    res = pcg(lambda d: torch.from_numpy(A @ d.numpy()), b, lambda r: torch.from_numpy(factor.solve(r.numpy())),
              tol=tol, maxiter=maxiter)
    p = res.x.numpy()
    if not res.converged or res.negative_curvature is not None or res.breakdown \
            or not np.all(np.isfinite(p)) or not float(rhs @ p) > 0:
        return None, res.iterations
    return p, res.iterations


def direct_solve(A, rhs: np.ndarray, max_shifts: int = 12, *, cholesky: bool = False,
                 factor: pardiso.SymmetricFactor | None = None, indefinite_stop: bool = False) -> DirectResult:
    """Solve ``A p = rhs`` for a descent direction (``rhs . p > 0``, ``rhs = -gradient``).

    ``A``: ``scipy.sparse`` ``(n, n)`` symmetric, ``rhs``: ``(n,)``.  With ``factor`` (a
    :class:`~torchbend.sim.pardiso.SymmetricFactor` of ``A``'s CSR pattern, e.g.
    :meth:`FreeHessian.direct_factor`) by MKL PARDISO's supernodal ``L D L^T`` (its pivots give the
    inertia; 5-7x faster than the LU on the cloth matrices, benchmarks/bm_scale.py), else by
    :func:`lu_solve` (symmetric sparse LU, which also gives the inertia); with ``cholesky=True`` and
    ``cholespy`` installed by a sparse Cholesky first (CHOLMOD), the factorisation above when ``A`` is not
    positive definite.  The direction of an indefinite matrix is kept if it is a descent direction.  A
    singular matrix, a non-finite solution or one that is not a descent direction is retried with the
    Levenberg shift ``A + mu I``, ``mu = 1e-8 max|diag A|`` growing tenfold (at most ``max_shifts`` tries;
    then the steepest-descent direction ``rhs`` itself).  Returns a :class:`DirectResult`; its
    ``positive_definite`` is that of the unshifted ``A``.  ``indefinite_stop``: return at once (the first
    solution, unshifted, or ``rhs``) when the first factorisation finds ``A`` not positive definite, for a
    caller that then takes another matrix's direction (no shifted retries spent on it)."""
    n = A.shape[0]
    use_chol = bool(cholesky) and has_cholespy()
    if factor is not None:
        A = sp.csr_matrix(A)
        if factor.n != n or factor.nnz != A.nnz:
            raise ValueError(f"direct_solve: factor is bound to a pattern of {factor.n} rows and {factor.nnz} "
                             f"values, A has {n} and {A.nnz}")
    diag_scale = float(abs(A.diagonal()).max()) if n else 1.0
    diag_scale = diag_scale if diag_scale > 0 and math.isfinite(diag_scale) else 1.0
    shift, definite = 0.0, None
    for tries in range(max_shifts):
        # the shifted matrix for the Cholesky and the LU (the factor takes the shift itself)
        M = A if shift == 0 or not (use_chol or factor is None) else A + sp.identity(n, format="csr") * shift
        p, method, pd = (cholesky_solve(M, rhs), "cholesky", True) if use_chol else (None, "lu", None)
        if p is None and factor is not None:
            p, fac_pd = _ldlt_solve(factor, A, rhs, shift)
            method, pd = "ldlt", (False if use_chol else fac_pd)
        elif p is None:
            p, lu_pd = lu_solve(M, rhs)
            method, pd = "lu", (False if use_chol else lu_pd)
        if tries == 0:
            definite = pd
            if indefinite_stop and pd is False:
                return DirectResult(rhs.copy() if p is None else p, 0, False, method)
        if p is not None and np.all(np.isfinite(p)) and float(rhs @ p) > 0:
            return DirectResult(p, tries, definite, method)
        shift = max(shift * 10, 1e-8 * diag_scale)
    return DirectResult(rhs.copy(), max_shifts, definite, "steepest")


# -------------------------------------------------------------------- conjugate gradients
class CGResult(NamedTuple):
    """A CG solve: the iterate ``x``, the ``iterations`` (operator applications), whether the
    relative residual reached the tolerance, ``negative_curvature``: the search direction
    ``d`` with ``d . A d <= 0`` that truncated it (``None`` if none did), and ``breakdown``: whether
    it stopped because ``r . precond(r) <= 0`` for a nonzero residual (the preconditioner is not
    positive definite there: an incomplete factorisation of an ill-conditioned matrix)."""

    x: Tensor
    iterations: int
    converged: bool
    negative_curvature: Tensor | None
    breakdown: bool = False


def pcg(apply: Apply, b: Tensor, precond: Apply, *, tol: float, maxiter: int, check_every: int | None = None) -> CGResult:
    """Preconditioned CG for ``A x = b`` (``apply(d) = A d``, ``precond(r) ~ A^{-1} r``, SPD), all in
    torch on ``b``'s device; stopped at ``|r| <= tol |b|``, after ``maxiter`` iterations, or
    truncated at the first direction of non-positive curvature (Steihaug: the iterate so far, or
    ``precond(b)`` at the first iteration) or when ``r . precond(r) <= 0`` (a preconditioner that is not
    positive definite).  From ``x = 0`` every iterate before a truncation is a descent direction for
    ``1/2 x.Ax - b.x`` (``b . x > 0``) in exact arithmetic, whatever ``A``'s inertia.

    The stopping tests are evaluated on the device and read by the host only every ``check_every``
    iterations (default: 1 on the CPU, 8 elsewhere); iterations past a stop change nothing."""
    if check_every is None:
        check_every = 1 if b.device.type == "cpu" else 8
    x = torch.zeros_like(b)
    r = b.clone()
    z = precond(r)
    d = z.clone()
    rz = torch.dot(r, z)
    bnorm = torch.linalg.vector_norm(b)
    done = rz <= 0  # a zero right-hand side, or a preconditioner that is not positive definite
    converged = bnorm == 0
    breakdown = done & ~converged
    negative = torch.zeros_like(done)
    neg_d = torch.zeros_like(b)
    iterations = torch.zeros((), dtype=torch.int64, device=b.device)
    limit = tol * bnorm
    for k in range(maxiter):
        if k % check_every == 0 and bool(done):
            break
        Ad = apply(d)
        curv = torch.dot(d, Ad)
        active = ~done
        iterations = iterations + active.to(torch.int64)
        neg = active & (curv <= 0)
        negative = negative | neg
        neg_d = torch.where(neg, d, neg_d)
        if k == 0:  # negative curvature at once: the preconditioned steepest-descent direction
            x = torch.where(neg, d, x)
        step = active & ~neg
        alpha = torch.where(step, rz / torch.where(step, curv, torch.ones_like(curv)), torch.zeros_like(curv))
        x = x + alpha * d
        r = r - alpha * Ad
        conv = step & (torch.linalg.vector_norm(r) <= limit)
        converged = converged | conv
        done = done | neg | conv
        z = precond(r)
        rz_new = torch.dot(r, z)
        go = ~done & (rz_new > 0)
        breakdown = breakdown | (~done & ~go)
        done = done | ~go
        beta = torch.where(go, rz_new / torch.where(go, rz, torch.ones_like(rz)), torch.zeros_like(rz))
        d = torch.where(go, z + beta * d, d)
        rz = torch.where(go, rz_new, rz)
    return CGResult(x, int(iterations), bool(converged), neg_d if bool(negative) else None, bool(breakdown))


def cg_iteration_bound(n: int, max_cg_iters: int | None = None) -> int:
    """The CG iteration bound: ``max_cg_iters`` if given (>= 1), else ``min(2 n, max(100, 20 sqrt(n)))``
    (CG is exact after ``n`` steps in exact arithmetic; a truncated CG still returns a descent
    direction, so the bound trades Newton iterations for CG iterations)."""
    if max_cg_iters is not None:
        return max(1, int(max_cg_iters))
    return max(1, min(2 * n, max(100, int(20 * math.sqrt(n)))))


# -------------------------------------------------------------------- preconditioners
def block_jacobi(blocks: Tensor) -> Apply:
    """Block-Jacobi preconditioner from the ``(Vf, 3, 3)`` diagonal blocks of the free Hessian (torch,
    on the blocks' device): each block is replaced by ``Q |L| Q^T`` (eigenvalues in absolute value,
    floored at ``1e-12`` times the largest) so that the preconditioner is SPD even for an indefinite
    Hessian; applies to flat ``(3 Vf,)`` vectors."""
    blocks = 0.5 * (blocks + blocks.transpose(-1, -2))
    lam, Q = torch.linalg.eigh(blocks)
    mag = lam.abs()
    floor = 1e-12 * mag.amax().clamp_min(torch.finfo(blocks.dtype).tiny)
    inv = (Q / torch.maximum(mag, floor)[..., None, :]) @ Q.transpose(-1, -2)

    def precond(r: Tensor) -> Tensor:
        return (inv @ r.reshape(-1, 3, 1)).reshape(-1)

    return precond


def _host(fn: Callable[[np.ndarray], np.ndarray], like: Tensor) -> Apply:
    """A NumPy operator applied to torch vectors (a host copy unless ``like`` is on the CPU)."""

    def apply(r: Tensor) -> Tensor:
        out = fn(r.detach().cpu().double().numpy())
        return torch.as_tensor(out, device=like.device).to(like.dtype)

    return apply


def ilu_solver(A: sp.spmatrix, *, drop_tol: float = 1e-4,
               fill_factor: float = 10.0) -> Callable[[np.ndarray], np.ndarray] | None:
    """Incomplete ``L |D| L^T`` factorisation of the free Hessian ``A`` as a symmetric positive definite
    preconditioner on NumPy vectors; ``None`` if the factorisation fails.

    ``scipy.sparse.linalg.spilu`` (symmetric ordering, no pivoting: ``P A P^T ~ L U``) supplies the unit lower
    factor ``L`` and the pivots ``D = diag(U)``; the preconditioner is ``P^T (L |D| L^T)^-1 P``.  The
    incomplete LU's own inverse ``U^-1 L^-1`` is not symmetric once entries are dropped (on a thin stiff
    sheet its preconditioned spectrum has imaginary parts near 1), and CG, whose recurrences assume a
    symmetric preconditioner, can then stall for thousands of iterations; ``L |D| L^T`` is symmetric and
    positive definite by construction, also on an indefinite Hessian (negative pivots enter as ``|d|``)."""
    try:
        fac = spla.spilu(sp.csc_matrix(A), drop_tol=drop_tol, fill_factor=fill_factor,
                         permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError:
        return None
    perm = np.asarray(fac.perm_c)
    d = np.abs(fac.U.diagonal())
    if not np.array_equal(np.asarray(fac.perm_r), perm) or not (np.all(np.isfinite(d)) and d.min(initial=1.0) > 0):
        return None  # a row interchange or a zero pivot: not a symmetric factorisation
    lower = sp.csr_matrix(fac.L)
    upper = sp.csr_matrix(lower.T)

    def solve(r: np.ndarray) -> np.ndarray:
        y = np.empty_like(r)
        y[perm] = r  # P r
        y = spla.spsolve_triangular(lower, y, lower=True, unit_diagonal=True) / d
        w = spla.spsolve_triangular(upper, y, lower=False, unit_diagonal=True)
        return w[perm]  # P^T w

    return solve


def ilu(A: sp.spmatrix, like: Tensor, *, drop_tol: float = 1e-4, fill_factor: float = 10.0) -> Apply | None:
    """:func:`ilu_solver` on torch vectors like ``like`` (CPU work); ``None`` if the factorisation fails."""
    solve = ilu_solver(A, drop_tol=drop_tol, fill_factor=fill_factor)
    return None if solve is None else _host(solve, like)


def amg_cycle(A: sp.spmatrix) -> Callable[[np.ndarray], np.ndarray] | None:
    """Smoothed-aggregation AMG (``pyamg``; one V-cycle per application, 3x3 vertex blocks) of the free
    Hessian ``A`` as a preconditioner on NumPy vectors; ``None`` without ``pyamg`` or if the setup fails."""
    if _pyamg is None:
        return None
    try:
        ml = _pyamg.smoothed_aggregation_solver(sp.bsr_matrix(sp.csr_matrix(A), blocksize=(3, 3)), symmetry="symmetric")
    except (ValueError, RuntimeError, np.linalg.LinAlgError):
        return None
    M = ml.aspreconditioner(cycle="V")
    return lambda r: M @ r


def amg(A: sp.spmatrix, like: Tensor) -> Apply | None:
    """:func:`amg_cycle` on torch vectors like ``like`` (CPU work); ``None`` without ``pyamg`` or if the setup
    fails."""
    cycle = amg_cycle(A)
    return None if cycle is None else _host(cycle, like)


def diagonal_blocks(A: sp.spmatrix) -> np.ndarray:
    """The ``(n / 3, 3, 3)`` diagonal vertex blocks of a SciPy matrix ``A (n, n)`` (zero where a block is absent)."""
    bsr = sp.bsr_matrix(sp.csr_matrix(A), blocksize=(3, 3))
    bsr.sum_duplicates()
    indptr, indices, data = np.asarray(bsr.indptr), np.asarray(bsr.indices), np.asarray(bsr.data)
    n = A.shape[0] // 3  # pyright: ignore[reportOptionalSubscript]
    rows = np.repeat(np.arange(n), np.diff(indptr))
    on = indices == rows
    out = np.zeros((n, 3, 3), dtype=data.dtype)
    out[rows[on]] = data[on]
    return out


def make_preconditioner(kind: Preconditioner | str, A: Tensor, fh: FreeHessian) -> tuple[Apply, Preconditioner]:
    """The preconditioner ``kind`` (:class:`Preconditioner`) for the assembled free Hessian ``A`` (torch
    sparse CSR) of ``fh``; falls back to block-Jacobi when ``ilu``/``amg`` are unavailable or fail.
    Returns ``(apply, the kind used)``."""
    kind = Preconditioner.parse(kind)
    if kind is Preconditioner.AUTO:
        kind = Preconditioner.ILU if A.device.type == "cpu" else Preconditioner.BLOCK_JACOBI
    like = A.values()
    if kind is Preconditioner.ILU:
        M = ilu(fh.to_scipy(A), like)
        if M is not None:
            return M, kind
    elif kind is Preconditioner.AMG:
        M = amg(fh.to_scipy(A), like)
        if M is not None:
            return M, kind
    return block_jacobi(fh.diagonal_blocks(A)), Preconditioner.BLOCK_JACOBI
