r"""Static and implicit-Euler cloth solvers: Newton on the (incremental) potential with exact or
projected second-order terms.

Static equilibrium minimises ``Phi(x) = E_membrane + E_bending + E_colliders - sum_i m_i g . x_i``
[J] over positions ``x (V, 3)`` [m] (:class:`~torchbend.sim.model.ClothModel`); one backward-Euler
step of size ``dt`` [s] minimises the incremental potential

    Phi(x) = 1/(2 dt^2) (x - x_hat)^T M (x - x_hat) + E(x),      x_hat = x_n + dt v_n,

then sets ``v = (x - x_n)/dt``.  The viscous bending term of the paper (``k_d/dt``,
``theta_prev`` = the angles of ``x_n``) is included when the bending module has ``damping``.

Newton iteration: pinned degrees of freedom are eliminated; the direction solves ``H p = -g`` on
the free ones with the Hessian option ``hessian=``, a :class:`torchbend.options.Projection`
(``"exact"`` = ``none``, ``"clamp"``, ``"abs"``, ``"gauss_newton"``, ``"reduced"``: the bending
projection; membranes get the nearest one they support, colliders drop their concave curvature term
whenever a projection is asked for), by a sparse direct solve (scipy) or matrix-free CG on
Hessian-vector products with a block-Jacobi preconditioner, truncated at negative curvature
(:mod:`torchbend.sim.linear`).  A direction that is not a descent direction (possible with the
indefinite exact Hessian) is replaced by a Levenberg-regularised one.  Armijo backtracking
(:mod:`torchbend.sim.line_search`) guarantees that the potential never increases.

The iteration stops when ``|g_free| <= tol * scale`` with ``scale`` the magnitude of the resultant
gravity force ``|sum_i m_i g|`` [N] plus, for a time step, the norm of the inertial force
``M (x_n - x_hat)/dt^2`` (a scale-aware, unit-consistent rule; without gravity, the initial
residual).  In float64 the attainable residual is limited by coordinate round-off: the bend angles
carry an absolute error of about ``eps |x| / h``, so very stiff shells on fine meshes far from the
origin have a floor; ``info.residual_history`` shows it.  Failures are reported in
:class:`SolveInfo`; the input is never modified and NaN positions are never returned.  Tensors are
created on the device and in the dtype of the positions; the linear algebra runs in NumPy/SciPy on
the CPU and its results are moved back explicitly.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from .._checks import check_positions, positive
from ..options import Option, Projection
from .line_search import armijo_backtracking
from .linear import block_jacobi, direct_solve, truncated_pcg
from .model import ClothModel, ClothState

__all__ = ["ClothModel", "ClothState", "SolveInfo", "LinearSolver", "solve_static", "implicit_euler_step"]


class LinearSolver(Option):
    """How Newton directions are solved: sparse direct factorisation or matrix-free CG."""

    __label__ = "linear_solver"

    DIRECT = "direct"
    CG = "cg"


SOLVER_PROJECTIONS = frozenset({Projection.NONE, Projection.CLAMP, Projection.ABS, Projection.GAUSS_NEWTON,
                                Projection.REDUCED})
"""``hessian=`` options of the solvers (``"exact"`` is ``none``): the bending projection; membranes get
the nearest one they support (:meth:`Projection.restricted`), colliders drop their curvature term."""


@dataclass
class SolveInfo:
    """Outcome of a solve (never raised; inspect ``converged`` and ``message``).

    ``residual``: the last ``|g_free|`` [N], ``tolerance``: the one it was compared with [N];
    ``energy``: the last potential [J] and ``energies`` its terms; ``energy_history`` /
    ``residual_history``: one entry per accepted iterate; ``regularized_steps``: Newton directions
    that needed a Levenberg shift or the steepest-descent fallback; ``cg_iterations``: in all (CG
    solver); ``substeps``: implicit-Euler solves a step took; ``seconds``: wall time [s]."""

    converged: bool = False
    iterations: int = 0
    residual: float = math.nan
    energy: float = math.nan
    line_search_failures: int = 0
    seconds: float = 0.0
    message: str = ""
    tolerance: float = math.nan
    energies: dict = field(default_factory=dict)
    energy_history: list = field(default_factory=list)
    residual_history: list = field(default_factory=list)
    regularized_steps: int = 0
    cg_iterations: int = 0
    substeps: int = 1


# -------------------------------------------------------------------- Newton
class _Potential:
    """The (incremental) potential of a solve, restricted to the free DOFs.

    ``inertia``: ``None`` (static) or ``(x_hat (V, 3) [m], dt [s])``; ``w`` is then the per-DOF
    ``m / dt^2`` ``(3V,)`` [kg/s^2].  ``free_mask``: ``(3V,)`` bool on the positions' device;
    ``free``: the same as a NumPy array (indexing the CPU copies of the linear algebra)."""

    def __init__(self, model: ClothModel, x: Tensor, option: Projection, inertia: tuple | None, bend_kw: dict):
        self.model, self.option, self.bend_kw = model, option, bend_kw
        self.free_mask = (~model.pinned).to(x.device).repeat_interleave(3)
        self.free = self.free_mask.cpu().numpy()
        self.w: Tensor | None = None
        if inertia is not None:
            self.x_hat, dt = inertia
            self.w = model.mass.to(device=x.device, dtype=x.dtype).repeat_interleave(3) / (dt * dt)

    def value(self, y: Tensor) -> tuple[float, dict]:
        """``(Phi(y) [J], per-term energies)``; the inertial term is ``"inertia"``."""
        e = self.model.energies(y, self.bend_kw)
        if self.w is not None:
            e["inertia"] = float(0.5 * (self.w * ((y - self.x_hat).reshape(-1)) ** 2).sum())
        return sum(e.values()), e

    def gradient(self, y: Tensor) -> Tensor:
        """``dPhi/dy`` flat ``(3V,)`` [N]."""
        g = self.model.gradient(y, self.bend_kw).reshape(-1)
        if self.w is not None:
            g = g + self.w * (y - self.x_hat).reshape(-1)
        return g

    def free_gradient(self, y: Tensor) -> np.ndarray:
        """The gradient on the free DOFs (NumPy, CPU)."""
        return self.gradient(y).cpu().numpy()[self.free]

    def force_scale(self, x: Tensor) -> float:
        """The force scale [N] of the stopping test (see the module docstring)."""
        scale = float(self.model.external_force(x.dtype).sum(0).norm())
        if self.w is not None:
            scale += float((self.w * (x - self.x_hat).reshape(-1)).norm())
        if scale == 0:
            scale = float(self.gradient(x).norm())
        return max(scale, torch.finfo(x.dtype).tiny)

    def full(self, p: np.ndarray, like: Tensor) -> Tensor:
        """Free-DOF values ``p`` as a ``(V, 3)`` tensor like ``like`` (zero on pinned DOFs)."""
        out = like.new_zeros(self.free_mask.shape[0])
        out[self.free_mask] = torch.from_numpy(np.ascontiguousarray(p)).to(device=like.device, dtype=like.dtype)
        return out.reshape(-1, 3)

    def direct_direction(self, x: Tensor, gf: np.ndarray) -> tuple[np.ndarray, int]:
        """Newton direction by a sparse direct solve; ``(p, Levenberg shifts)``."""
        H = self.model.hessian(x, self.option, self.bend_kw)
        if self.w is not None:
            H = H + sp.diags(self.w.cpu().numpy())
        Hf = H.tocsr()[self.free][:, self.free].tocsc()
        return direct_solve(Hf, -gf)

    def cg_direction(self, x: Tensor, gf: np.ndarray, relative_residual: float) -> tuple[np.ndarray, int]:
        """Newton direction by truncated block-Jacobi PCG on Hessian-vector products, to the forcing
        term ``min(0.1, sqrt(|g| / scale)) / 100``; ``(p, CG iterations)``."""
        blocks = self.model.block_diagonal(x, self.option, self.bend_kw)
        if self.w is not None:
            blocks = blocks + torch.diag_embed(self.w.reshape(-1, 3))
        precond = block_jacobi(blocks, self.free)
        zero = np.zeros(self.free.shape[0])

        def apply(d: np.ndarray) -> np.ndarray:
            full = zero.copy()
            full[self.free] = d
            v = torch.from_numpy(full).to(device=x.device, dtype=x.dtype).reshape(-1, 3)
            out = self.model.hvp(x, v, self.option, self.bend_kw).reshape(-1)
            if self.w is not None:
                out = out + self.w * v.reshape(-1)
            return out.cpu().double().numpy()[self.free]

        forcing = min(0.1, math.sqrt(relative_residual)) * 1e-2
        return truncated_pcg(apply, -gf, precond, tol=max(forcing, 1e-14), maxiter=10 * len(gf))


def _direction(phi: _Potential, x: Tensor, gf: np.ndarray, linear: LinearSolver, relative_residual: float,
               info: SolveInfo) -> tuple[np.ndarray, float]:
    """A descent direction on the free DOFs and its slope ``g . p`` [J]; a direction that is not one
    (or not finite) is replaced by the steepest-descent step ``-g min(1, 1/|g|)``."""
    if linear is LinearSolver.DIRECT:
        p, shifts = phi.direct_direction(x, gf)
        info.regularized_steps += shifts
    else:
        p, cg_it = phi.cg_direction(x, gf, relative_residual)
        info.cg_iterations += cg_it
    slope = float(gf @ p)
    if not slope < 0 or not np.all(np.isfinite(p)):
        info.regularized_steps += 1
        gnorm = np.linalg.norm(gf)
        p = -gf / max(gnorm, 1e-300) * min(1.0, gnorm)
        slope = float(gf @ p)
    return p, slope


def _stop(info: SolveInfo, it: int, max_iters: int) -> bool:
    """The stopping test on ``info.residual``; sets ``converged`` and ``message`` when it stops."""
    if info.residual <= info.tolerance:
        info.converged, info.message = True, "converged"
        return True
    if it == max_iters:
        info.message = f"no convergence in {max_iters} Newton iterations"
        return True
    return False


def _failed(x0: Tensor, info: SolveInfo, t0: float, message: str) -> tuple[Tensor, SolveInfo]:
    info.converged, info.message = False, message
    info.seconds = time.perf_counter() - t0
    return x0, info


def _newton(model: ClothModel, x0: Tensor, *, option: Projection, linear: LinearSolver, tol: float,
            max_iters: int, inertia: tuple | None, bend_kw: dict, max_line_search: int = 30):
    """Minimise the (incremental) potential from ``x0 (V, 3)`` [m] (not modified).  Returns ``(x, info)``."""
    t0 = time.perf_counter()
    info = SolveInfo()
    x = x0.detach().clone()
    phi = _Potential(model, x, option, inertia, bend_kw)
    scale = phi.force_scale(x)
    info.tolerance = tol * scale
    energy, terms = phi.value(x)
    info.energy_history.append(energy)
    if not math.isfinite(energy):
        return _failed(x0, info, t0, "non-finite potential at the initial state")
    for it in range(max_iters + 1):
        gf = phi.free_gradient(x)
        res = float(np.linalg.norm(gf))
        info.residual, info.energy, info.energies, info.iterations = res, energy, terms, it
        info.residual_history.append(res)
        if not math.isfinite(res):
            return _failed(x0, info, t0, "non-finite gradient")
        if _stop(info, it, max_iters):
            break
        p, slope = _direction(phi, x, gf, linear, res / max(scale, 1e-300), info)
        dx = phi.full(p, x)
        step = armijo_backtracking(phi.value, x, dx, energy, terms, slope,
                                   lambda y, res=res: float(np.linalg.norm(phi.free_gradient(y))) < res,
                                   max_steps=max_line_search, alpha_max=model.max_step(x, dx))
        if step is None:
            info.line_search_failures += 1
            info.message = "line search exhausted (no decrease along the Newton direction)"
            break
        x, energy, terms = step.x, step.energy, step.terms
        info.energy_history.append(energy)
    info.seconds = time.perf_counter() - t0
    if not bool(torch.isfinite(x).all()):
        return _failed(x0, info, t0, "non-finite positions")
    return x, info


# -------------------------------------------------------------------- public solvers
def _prepare_x(model: ClothModel, x, name: str = "x0") -> Tensor:
    """``x`` as a finite floating ``(V, 3)`` tensor (on its own device)."""
    x = torch.as_tensor(x)
    if x.shape != (model.vertex_count, 3):
        raise ValueError(f"{name} must have shape ({model.vertex_count}, 3), got {tuple(x.shape)}")
    return check_positions(x, model.vertex_count, name)


def _parse_options(hessian, linear_solver) -> tuple[Projection, LinearSolver]:
    return (Projection.parse(hessian, what="hessian", supported=SOLVER_PROJECTIONS),
            LinearSolver.parse(linear_solver))


def solve_static(model: ClothModel, x0, *, hessian: str = "exact", linear_solver: str = "direct",
                 tol: float = 1e-9, max_iters: int = 50, continuation: bool = False,
                 max_relax_steps: int = 200) -> tuple[Tensor, SolveInfo]:
    """Static equilibrium from ``x0 (V, 3)`` [m]; pinned vertices keep their ``x0`` positions.

    ``hessian``: a :class:`torchbend.options.Projection` (``"exact"``, ``"clamp"``, ``"abs"``,
    ``"gauss_newton"``, ``"reduced"``) for the Newton matrix; ``linear_solver``: ``"direct"`` (sparse
    LU) or ``"cg"`` (:class:`LinearSolver`).  ``tol`` is relative to the resultant gravity force
    (stop when ``|g_free| <= tol |sum_i m_i g|`` [N]).  With ``continuation=True``, a Newton solve
    that fails from ``x0`` (large rotations of soft shells) is globalised by pseudo-transient
    continuation: implicit-Euler steps from rest (the velocity is reset every step, so each step is a
    proximal step on the potential) with a growing step size, retrying Newton every few steps (at most
    ``max_relax_steps`` steps).  ``info.iterations`` counts all Newton iterations.
    Returns ``(x (V, 3) [m], info)``; on failure ``x`` is ``x0`` unchanged and ``info.converged`` is False."""
    x0 = _prepare_x(model, x0)
    option, linear = _parse_options(hessian, linear_solver)
    tol = positive(tol, "tol")
    x, info = _newton(model, x0, option=option, linear=linear, tol=tol, max_iters=int(max_iters),
                      inertia=None, bend_kw={})
    if info.converged or not continuation:
        return (x, info) if info.converged else (x0, info)
    return _continuation(model, x0, info, option, linear, hessian, tol, int(max_iters), max_relax_steps)


def _continuation(model: ClothModel, x0: Tensor, info: SolveInfo, option: Projection, linear: LinearSolver,
                  hessian, tol: float, max_iters: int, max_relax_steps: int) -> tuple[Tensor, SolveInfo]:
    """Pseudo-transient continuation after a failed static solve (see :func:`solve_static`)."""
    t0 = time.perf_counter()
    total = info.iterations
    x, xk, dt = x0, x0, 1e-2
    for k in range(max_relax_steps):
        state, step_info = implicit_euler_step(model, ClothState(xk, torch.zeros_like(xk)), dt,
                                               hessian=hessian, linear_solver=linear, tol=1e-6, max_iters=30)
        total += step_info.iterations
        if not step_info.converged:
            dt *= 0.25
            continue
        xk, dt = state.x, dt * 1.5
        if k % 5 == 4:
            x, info = _newton(model, xk, option=option, linear=linear, tol=tol, max_iters=max_iters,
                              inertia=None, bend_kw={})
            total += info.iterations
            if info.converged:
                break
    info.iterations = total
    info.seconds = time.perf_counter() - t0
    if info.converged:
        info.message = "converged (after pseudo-transient continuation)"
        return x, info
    return x0, info


def implicit_euler_step(model: ClothModel, state: ClothState, dt: float, *, hessian: str = "exact",
                        linear_solver: str = "direct", tol: float = 1e-6, max_iters: int = 30,
                        max_substep_depth: int = 3) -> tuple[ClothState, SolveInfo]:
    """One backward-Euler step of size ``dt`` [s] from ``state`` (``x, v: (V, 3)`` [m], [m/s]):
    Newton on the incremental potential.

    ``hessian``, ``linear_solver`` as for :func:`solve_static` (``hessian``: a
    :class:`torchbend.options.Projection`); ``tol`` is relative to the resultant gravity plus inertial
    force.  Pinned vertices keep their positions (zero velocity).  With bending damping, the viscous
    term uses the angles of ``state.x`` as ``theta_prev``.  A step whose Newton solve fails is retried
    as two half steps (recursively, at most ``max_substep_depth`` halvings; ``info.substeps`` counts
    the solves).  If that fails too, the input state is returned unchanged with ``info.converged = False``."""
    dt = positive(dt, "dt")
    if not isinstance(state, ClothState):
        raise ValueError(f"state must be a ClothState, got {type(state).__name__}")
    _prepare_x(model, state.x, "state.x")
    _prepare_x(model, state.v, "state.v")
    option, linear = _parse_options(hessian, linear_solver)
    new, info = _euler_solve(model, state, dt, option, linear, positive(tol, "tol"), int(max_iters))
    if info.converged or max_substep_depth <= 0:
        info.substeps = 1
        return new, info
    t0 = time.perf_counter()
    half = lambda s: implicit_euler_step(model, s, dt / 2, hessian=hessian, linear_solver=linear_solver, tol=tol,
                                         max_iters=max_iters, max_substep_depth=max_substep_depth - 1)
    mid, info1 = half(state)
    if not info1.converged:
        info1.seconds += info.seconds
        return state, info1
    end, info2 = half(mid)
    info2.iterations += info1.iterations + info.iterations
    info2.substeps = info1.substeps + info2.substeps
    info2.seconds = info.seconds + (time.perf_counter() - t0)
    info2.energy_history = info1.energy_history + info2.energy_history
    if not info2.converged:
        return state, info2
    info2.message = f"converged in {info2.substeps} substeps"
    return end, info2


def _euler_solve(model: ClothModel, state: ClothState, dt: float, option: Projection, linear: LinearSolver,
                 tol: float, max_iters: int) -> tuple[ClothState, SolveInfo]:
    x_n, v_n = state.x, state.v
    pinned = model.pinned.to(x_n.device)[:, None]
    v_n = torch.where(pinned, torch.zeros_like(v_n), v_n)
    x_hat = x_n + dt * v_n
    bend_kw = {}
    if model.bending is not None and model.bending.damping is not None:
        bend_kw = {"theta_prev": model.bending.angles(x_n).detach(), "dt": dt}
    # Newton starts at x_hat, or with colliders at the point of the segment x_n -> x_hat where the
    # step bound stops it (x_hat of a large step may lie through a collider: never start there)
    x0 = x_n + model.max_step(x_n, x_hat - x_n) * (x_hat - x_n) if model.colliders else x_hat.clone()
    x, info = _newton(model, x0, option=option, linear=linear, tol=tol, max_iters=max_iters,
                      inertia=(x_hat, dt), bend_kw=bend_kw)
    if not info.converged:
        return state, info
    v = torch.where(pinned, torch.zeros_like(v_n), (x - x_n) / dt)
    return ClothState(x=x, v=v), info
