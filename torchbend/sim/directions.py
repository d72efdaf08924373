"""The Newton matrix of a solve and the directions it gives: the free Hessian of the potential (projected, shifted
by Levenberg-Marquardt damping), a sparse direct solve (Cholesky, PARDISO LDL^T or SuperLU; optionally CG
preconditioned by a reused single-precision factorisation) or truncated preconditioned CG.  A mixin of the solver's
potential (``torchbend.sim.newton._Potential``), which owns the state named below."""
from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import Tensor

from ..options import Projection
from .damping import Damping
from .linear import (
    DirectResult,
    FreeHessian,
    Preconditioner,
    cg_iteration_bound,
    direct_solve,
    make_preconditioner,
    pcg,
    reused_factor_solve,
)
from .options import REUSE_CG_ITERS, Factorization, LinearSolver
from .terms import EnergyTerm, StepContext

__all__ = ["NewtonDirections"]


class NewtonDirections:
    """Newton directions on the free DOFs of a potential (its ``terms`` in the step context ``ctx``, projection
    ``option``): :meth:`free_hessian`, :meth:`direct_direction`, :meth:`cg_direction`.  What the last direction
    found: ``positive_definite`` (None: unknown), ``negative_curvature`` (a CG direction of negative curvature,
    ``(nf,)`` on x's device), ``linear_method``; ``linear_seconds`` and ``reuse_cg_iterations`` accumulate."""

    terms: tuple[EnergyTerm, ...]
    ctx: StepContext
    option: Projection
    linear: LinearSolver
    hessian_op: FreeHessian
    damping: Damping
    positive_definite: bool | None
    negative_curvature: Tensor | None
    linear_method: str
    linear_seconds: float
    reuse_cg_iterations: int
    skip_exact: bool
    near_minimum: bool

    @property
    def max_cg_iters(self) -> int | None:
        """The bound on CG iterations per direction (None: automatic), ``linear.max_cg_iters``."""
        return self.linear.max_cg_iters

    def free_hessian(self, x: Tensor) -> Tensor:
        """The Newton matrix at ``x``: the free Hessian of the potential (with the inertia ``m/dt^2``) in the
        projection ``option`` (``"abs"`` for an exact one while damped), plus the damping ``mu M``
        (:mod:`~torchbend.sim.damping`); torch sparse CSR ``(nf, nf)`` [N/m] on ``x``'s device."""
        damping = self.damping
        A = self.hessian_op.assemble(x, self.terms, self.ctx, damping.matrix_option(self.option))
        if damping.pending:  # the first matrix: its diagonal sets the scale (the first direction is undamped)
            damping.start(self.hessian_op.diagonal(A))
        return self._damped(A)

    def _damped(self, A: Tensor) -> Tensor:
        """``A + mu M`` while the damping is on, else ``A``."""
        return self.hessian_op.shifted(A, self.damping.shift(A.values())) if self.damping.active else A

    def _factor(self):
        """The PARDISO factorisation of the assembled pattern (``linear.factorization``: ``"auto"`` when MKL
        is installed, ``"ldlt"``), or ``None`` for SuperLU."""
        kind = self.linear.factorization
        if kind is Factorization.LU:
            return None
        factor = self.hessian_op.direct_factor()
        if factor is None and kind is Factorization.LDLT:
            raise ValueError("linear_solver: factorization='ldlt' needs MKL's PARDISO (pip install mkl, or "
                             "torchbend[solvers]); use 'auto' or 'lu'")
        return factor

    def direct_direction(self, x: Tensor, gf: np.ndarray, relative_residual: float = 1.0) -> tuple[np.ndarray, int]:
        """Newton direction by a sparse direct solve on the CPU (:func:`~torchbend.sim.linear.direct_solve`;
        sparse Cholesky first if ``linear.cholesky``); with ``linear.reuse_factorization`` first by CG
        preconditioned with a single-precision factorisation (:meth:`_preconditioned`) to the forcing term
        ``min(1e-2, sqrt(|g| / scale))`` (at least 1e-10); ``(p, Levenberg shifts)``; sets
        ``positive_definite`` (unknown after a preconditioned solve) and ``linear_method``."""
        # an indefinite exact Hessian in a time step gives way to the clamped one (below): no shifted retries
        clamp_if_indefinite = self.ctx.dynamic and self.option is Projection.NONE
        reuse = self.linear.reuses_factorization(len(gf))
        forcing = max(min(1e-2, math.sqrt(relative_residual)), 1e-10)

        def solve(A: Tensor, indefinite_stop: bool = False):  # an assembled matrix; timed in linear_seconds
            A_host, factor = self.hessian_op.to_scipy(A), self._factor()  # the factor of A's pattern
            t0 = time.perf_counter()
            out = self._preconditioned(A_host, gf, forcing) if reuse and factor is not None else None
            if out is None:
                out = direct_solve(A_host, -gf, cholesky=self.linear.cholesky, factor=factor,
                                   indefinite_stop=indefinite_stop)
            self.linear_seconds += time.perf_counter() - t0
            return out

        def clamped(after_exact: bool) -> tuple[np.ndarray, int]:
            # the clamped Hessian's direction (positive semi-definite elements plus the inertia: definite); after
            # an indefinite exact one the next direction skips the exact attempt (a buckle lasts some iterations)
            # damped as free_hessian's matrix is (the model the damping's rule judges)
            res = solve(self._damped(self.hessian_op.assemble(x, self.terms, self.ctx, Projection.CLAMP)))
            self.linear_method = f"{res.method}/clamp"
            self.skip_exact = after_exact
            return res.p, res.shifts + int(after_exact)

        if clamp_if_indefinite and self.skip_exact:
            self.positive_definite, self.negative_curvature = None, None
            return clamped(after_exact=False)
        res = solve(self.free_hessian(x), indefinite_stop=clamp_if_indefinite)
        self.positive_definite, self.negative_curvature, self.linear_method = res.positive_definite, None, res.method
        if res.positive_definite is False and clamp_if_indefinite:
            # an indefinite exact Hessian in a time step (an impact, a buckle): the clamped one's direction, not a
            # Levenberg-shifted exact one
            return clamped(after_exact=True)
        return res.p, res.shifts

    def _preconditioned(self, A, gf: np.ndarray, tol: float) -> DirectResult | None:
        """``A p = -gf`` (``A``: the assembled matrix, SciPy CSR) by CG to the relative residual ``tol``,
        preconditioned with the single-precision factorisation of the pattern: the last one (an earlier
        iterate's or step's matrix), else a new one of ``A`` (:func:`~torchbend.sim.linear.reused_factor_solve`,
        at most ``REUSE_CG_ITERS`` iterations each); ``None`` when neither converges or ``A``'s factorisation
        is not positive definite (the double-precision direct solve decides then)."""
        single = self.hessian_op.single_factor()
        if single is None:
            return None
        p, its = reused_factor_solve(A, -gf, single, tol=tol, maxiter=REUSE_CG_ITERS)
        method = "ldlt32-reused+cg"
        if p is None and single.factor(A.data) and single.positive_definite:
            p, more = reused_factor_solve(A, -gf, single, tol=tol, maxiter=REUSE_CG_ITERS)
            its, method = its + more, "ldlt32+cg"
        self.reuse_cg_iterations += its
        return None if p is None else DirectResult(p, 0, None, method)

    def cg_direction(self, x: Tensor, gf: np.ndarray, relative_residual: float) -> tuple[np.ndarray, int]:
        """Newton direction by truncated preconditioned CG (:func:`~torchbend.sim.linear.pcg`) on the
        assembled free Hessian, on ``x``'s device, to the forcing term ``min(0.1, sqrt(|g| / scale)) / 100``
        (at least 1e-10 and 100 eps of ``x``'s dtype),
        at most ``max_cg_iters`` iterations (``None``: :func:`~torchbend.sim.linear.cg_iteration_bound`).
        The preconditioner is ``linear.preconditioner`` (:class:`LinearSolver`); if its CG breaks down on a
        projected Hessian or near a minimum (``near_minimum``: the incomplete factorisation is not positive
        definite) or its direction is not a descent direction,
        block-Jacobi (SPD) is tried, and of the two descent directions the one with the lower quadratic model
        ``g.p + p.Ap/2`` is kept.  ``(p, CG iterations)``; sets ``negative_curvature``, ``positive_definite``
        (``False`` when negative curvature was met, else unknown) and ``linear_method``."""
        A = self.free_hessian(x)
        t0 = time.perf_counter()
        b = -torch.as_tensor(gf, device=x.device).to(x.dtype)
        tol = max(min(0.1, math.sqrt(relative_residual)) * 1e-2, 1e-10, 100 * torch.finfo(x.dtype).eps)
        maxiter = cg_iteration_bound(len(gf), self.max_cg_iters)
        M, used = make_preconditioner(self.linear.preconditioner, A, self.hessian_op)
        res = pcg(lambda d: A @ d, b, M, tol=tol, maxiter=maxiter)
        iterations = res.iterations
        # a breakdown on a matrix expected positive (semi-)definite (a projected Hessian, or the exact one after
        # the switch near a minimum) is the incomplete factorisation's failure; on the exact Hessian elsewhere it
        # usually reflects the matrix's own indefiniteness, and the direction is kept
        broke = res.breakdown and (self.option is not Projection.NONE or self.near_minimum)
        if used is not Preconditioner.BLOCK_JACOBI and (broke or not float(torch.dot(b, res.x)) > 0):
            retry = pcg(lambda d: A @ d, b, make_preconditioner(Preconditioner.BLOCK_JACOBI, A, self.hessian_op)[0],
                        tol=tol, maxiter=maxiter)
            iterations += retry.iterations

            def model(r) -> float:  # the quadratic model at the direction (inf: not a descent direction)
                bx = float(torch.dot(b, r.x))
                return 0.5 * float(torch.dot(r.x, A @ r.x)) - bx if bx > 0 else math.inf

            if model(retry) <= model(res):
                res, used = retry, Preconditioner.BLOCK_JACOBI
        self.negative_curvature = res.negative_curvature
        self.positive_definite = False if res.negative_curvature is not None else None
        self.linear_method = f"cg/{used.value}"
        p = res.x.detach().cpu().double().numpy()
        self.linear_seconds += time.perf_counter() - t0
        return p, iterations
