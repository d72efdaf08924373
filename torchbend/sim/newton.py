r"""Static and implicit-Euler cloth solvers: Newton on the (incremental) potential with exact or
projected second-order terms.

Static equilibrium minimises ``Phi(x) = E_membrane + E_bending + E_colliders - sum_i m_i g . x_i``
[J] over positions ``x (V, 3)`` [m] (:class:`~torchbend.sim.model.ClothModel`); one backward-Euler
step of size ``dt`` [s] minimises the incremental potential

    Phi(x) = 1/(2 dt^2) (x - x_hat)^T M (x - x_hat) + E(x),      x_hat = x_n + dt v_n,

then sets ``v = (x - x_n)/dt``.  The viscous bending term of the paper (``k_d/dt``,
``theta_prev`` = the angles of ``x_n``) is included when the bending module has ``damping``.

Newton iteration: pinned degrees of freedom are eliminated; the direction solves ``H p = -g`` on
the free ones with the Hessian option ``projection=``, a :class:`torchbend.options.Projection`
(``"exact"`` = ``none``, ``"clamp"``, ``"abs"``, ``"gauss_newton"``, ``"reduced"``: the bending
projection; membranes get the nearest one they support, colliders drop their concave curvature term
whenever a projection is asked for), assembled once per iteration on the positions' device, by a
sparse direct solve on the CPU (symmetric-mode LU, which also tells whether the matrix is positive
definite) or by preconditioned CG on the positions' device (an incomplete ``L |D| L^T``
factorisation on the CPU, block-Jacobi elsewhere), bounded and truncated at negative curvature (:mod:`torchbend.sim.linear`).  A direction that is not a descent direction (possible with the
indefinite exact Hessian) is replaced by a Levenberg-regularised one.  Armijo backtracking
(:mod:`torchbend.sim.line_search`) guarantees that the potential never increases beyond its round-off.

**Stopping rule.**  Two tests; ``info.stop_reason`` and ``info.message`` say which one fired.

* ``"residual"``: ``|g_free| <= tol * F`` with the force scale ``F`` [N] the 2-norm over all DOFs
  (pinned ones included: their reactions are forces of the system) of the per-DOF sum of the
  magnitudes of every force acting: gravity ``|m_i g|``, the membrane, bending and collider forces
  term by term, and for a time step the inertial forces ``|M (x - x_hat)| / dt^2`` at the iterate and
  ``|M v_n| / dt`` (the inertial force ``M (x_n - x_hat)/dt^2`` of the start of the step).  Internal
  forces make the rule scale with the stiffness (``Y t``), so that one ``tol`` serves soft and stiff
  shells; the scale is refreshed at the first iterate, every 10 iterations and whenever the
  residual comes within ``1e3 tol F`` of it.
* ``"round-off floor"``: the residual of a stiff shell cannot fall below the round-off of its
  forces (coordinates carry an absolute error ``eps |x|``; membrane forces of size ``Y t h`` turn it
  into a residual floor ``~ eps Y t |x|``), estimated as ``r_eps = eps |(|B| |x|)_free|`` (``B`` the
  per-vertex 3x3 Hessian blocks).  The iteration stops there when the predicted decrease ``-g . p``
  of the Newton direction (the Newton decrement) is below the potential's round-off
  ``64 eps (sum_terms |E_term| + sum_i F_i |x_i|)`` and ``|g_free| <= 4 r_eps``; or when, for the
  last three Newton directions, the decrement was below that round-off, the potential changed by no
  more than it, the residual made no progress (no halving of its best value) and ``|g_free| <=
  100 r_eps``; or when the line search finds no decrease along a direction whose decrement is below
  the round-off and ``|g_free| <= 100 r_eps``.  Every variant also needs ``|g_free| <= min(eps K, 1/8) F``
  (``F`` at that iterate, ``K = eps_64^(-3/4)``, about ``5.5e11``: ``eps_64^(1/4) F`` in float64): a floor far
  above that is not round-off but an ill-conditioned state (nearly collapsed triangles), where the iteration
  goes on.  ``K`` bounds the conditioning ``r_eps / (eps F)`` the same in every dtype; in float32 a crease folded
  to a radius of a fraction of its edges (a bending Hessian block of 2e5 N/m against 1e-2 N of forces) has a floor
  of 2-4% of ``F``, which ``eps_32^(1/4) F`` (1.9%) refused: the step ran to ``max_iters`` at that floor.  When the
  decrement of a step is below the round-off the full step is taken if it lowers the residual, or at ``|g_free| <=
  4 r_eps`` if it halves it (the potential cannot tell better from worse there).

**Projected Hessians** (``clamp``, ``abs``, ``gauss_newton``) converge linearly: once they reach an
apparent round-off floor, or after 5 full steps in a row that did not halve the residual once
it is below ``1e-3 F`` (near a minimum: far from one, the exact Hessian could lead to another), the
solve switches to the exact Hessian for its last iterations (quadratic convergence near the
minimum; the line search keeps the potential decreasing), and takes the first two exact steps below
the round-off whatever the residual (a soft mode's error left by the linear convergence does not
show above a stiff membrane's round-off).

**Minima, not saddles.**  With the exact Hessian (``projection="exact"``) and ``check_minimum``, a point
that passes a stopping test is checked for negative curvature: the smallest eigenvalue of the exact
Hessian on the free DOFs (:mod:`torchbend.sim.curvature`).  Below ``-1e3 eps ||H||_inf`` the solver
takes a line-searched step along the eigenvector (the sign with ``g . d <= 0``, both signs when
``g . d`` is at round-off level, the lower end state kept) and resumes Newton (at most 10 such
steps).  ``info.minimum`` is True when the returned point was verified, False when a negative
eigenvalue remains, None when not checked (projected Hessians, ``check_minimum=False``).

**Failures.**  Nothing is raised once the iteration has started: on failure (``max_iters`` reached,
line search exhausted, ``time_limit``, a stopping ``callback``, a non-finite gradient, or a
``ValueError`` raised by an energy, e.g. a ``tan`` hinge folded through) the solver returns the
best iterate it found, the one of lowest potential (ties within round-off: of lower residual; among the iterates
since a term last changed its energy, :meth:`~torchbend.sim.terms.EnergyTerm.adapt`: a contact barrier that
stiffens within the solve makes a new potential), with
``converged=False``, ``stop_reason`` and ``message`` naming the cause, and ``info`` describing the
returned state (``residual``, ``energy``, ``energies``, ``best_iteration``).  A static problem
without pinned vertices or colliders under gravity is unbounded below: diagnosed before iterating.
The input is never modified and NaN positions are never returned.

**Progress.**  The logger ``logging.getLogger("torchbend.sim")`` gets one line per Newton iteration
(iteration, residual, tolerance, potential, step length ``alpha``, CG iterations, damping) at ``DEBUG``;
once a public call has run for more than 5 s, one iteration line a second, a line per phase of
:func:`solve_static` (membrane homotopy, relaxation) and a summary at the end go out at ``INFO``.  In a
program that configured no logging they are written to stderr (a handler of that logger, active only
while the root logger has none); ``logging.getLogger("torchbend.sim").setLevel(logging.WARNING)`` silences
them.  Every call is bounded in time by default (``time_limit="auto"``, :class:`NewtonOptions`).
``callback(iteration, x, info)`` is called after every accepted iterate (``x (V, 3)``, ``info`` the
running :class:`SolveInfo`); returning True stops the solve (``stop_reason="callback"``).

Tensors are created on the device and in the dtype of the positions; the linear algebra runs in
NumPy/SciPy on the CPU and its results are moved back explicitly.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from .._checks import check_positions
from ..options import Projection
from .curvature import curvature_tolerance, smallest_eigenpair
from .damping import Damping
from .directions import NewtonDirections
from .line_search import LineSearchResult, armijo_backtracking
from .linear import FreeHessian
from .model import ClothModel, ClothState
from .options import (
    UNSET,
    Controls,
    LinearMethod,
    LinearSolver,
    NewtonOptions,
    continuation_mode,
    positive_value,
    resolve_options,
)
from .terms import InertiaTerm, StepContext, contact_stats, softens

__all__ = ["ClothModel", "ClothState", "SolveInfo", "LinearSolver", "LinearMethod", "NewtonOptions", "solve_static",
           "implicit_euler_step"]

_log = logging.getLogger("torchbend.sim")
_INFO_AFTER_S = 5.0
"""A public call running longer than this [s] logs its progress at INFO instead of DEBUG."""
_INFO_EVERY_S = 1.0
"""At most one iteration line a second at INFO."""


class _Progress(logging.StreamHandler):
    """Progress on stderr for an unconfigured program: the ``torchbend.sim`` records at INFO and above, written
    only while the root logger has no handler (a configured application's own handlers get them instead,
    by propagation).  Silence it with ``logging.getLogger("torchbend.sim").setLevel(logging.WARNING)``."""

    def emit(self, record: logging.LogRecord) -> None:
        if not logging.getLogger().handlers:
            super().emit(record)


if not any(isinstance(h, _Progress) for h in _log.handlers):
    _log.addHandler(_Progress())
    if _log.level == logging.NOTSET:
        _log.setLevel(logging.INFO)


def _level(started: float) -> int:
    """INFO once the public call begun at ``started`` has run longer than :data:`_INFO_AFTER_S`, else DEBUG."""
    return logging.INFO if time.perf_counter() - started > _INFO_AFTER_S else logging.DEBUG
_STALL_WINDOW = 3
"""Newton directions over which the round-off floor test looks for progress."""
_SLOW_STEPS = 5
"""Full steps in a row that do not halve the residual after which a projected Hessian gives way to the exact one."""
_CREDIBLE_CONDITION = torch.finfo(torch.float64).eps ** -0.75
"""The largest conditioning ``r_eps / (eps F)`` of a credible round-off floor, in every dtype (module docstring)."""
_CREDIBLE_SHARE = 0.125
"""The largest share of the force scale a credible round-off floor may have (the bound in float32)."""
_MAX_ESCAPES = 10
"""Negative-curvature steps at most per Newton solve."""


@dataclass
class SolveInfo:
    """Outcome of a solve (never raised; inspect ``converged`` and ``message``).

    Describes the returned state: ``residual`` its ``|g_free|`` [N], ``tolerance`` the one it was
    compared with [N] (``tol`` times ``force_scale`` [N], see the module docstring), ``energy`` its
    potential [J] and ``energies`` the terms, ``best_iteration`` its index among the iterates of
    the solve that produced it.  ``stop_reason``: ``"residual"`` or ``"round-off floor"`` (converged),
    ``"max_iters"``, ``"line_search"``, ``"time_limit"``, ``"callback"``, ``"non_finite"``,
    ``"evaluation_error"`` (an energy raised a ``ValueError``), ``"rigid_body_modes"`` (unbounded
    below), ``"stalled"`` (the pseudo-transient relaxation came to rest at a state the static solve does
    not converge from; repeating that solve would repeat its result), ``"body_move"`` (a time step could not carry a
    moved body all the way, :func:`implicit_euler_step`); ``message`` says it in words, with counts aggregated over sub-solves.  ``minimum``: True
    when the exact Hessian on the free DOFs was checked positive semi-definite there, False when a
    negative eigenvalue ``min_eigenvalue`` [N/m] remains, None when not checked.
    ``negative_curvature_steps``: steps taken along negative-curvature directions.
    ``iterations``: Newton iterations in all (every sub-solve); ``solves``: Newton solves in all
    (continuation and substeps make several); ``energy_history`` / ``residual_history``: one entry
    per accepted iterate; ``regularized_steps``: Newton directions that needed a Levenberg shift or
    the steepest-descent fallback; ``cg_iterations``: in all (the CG solver's, and a direct solver's on reused
    factorisations, ``LinearSolver.reuse_factorization``); ``linear_seconds``: wall time
    [s] of the linear solves of the Newton directions (factorisations and solves, or CG with its
    preconditioner; not the assembly of the matrix); ``linear_methods``: how many directions each linear method
    gave (e.g. ``{"cholmod": 12}``, ``{"cg/block_jacobi": 3}``; ``.../clamp``: the clamped Hessian's); ``substeps``:
    implicit-Euler (sub)steps making up the returned state; ``seconds``: wall time [s].  ``phase``: what
    produced the returned state: ``"newton"`` (Newton alone), ``"membrane"`` (the membrane-stiffness
    homotopy of ``continuation``), ``"relaxation"`` (pseudo-transient continuation), ``"clamped"`` (a time step
    solved again with the clamped projection after the exact Hessian's solve stopped), ``"substeps"`` (a time
    step retried as halves).  ``adaptations``: iterates of a time step's solves at which a term changed its energy
    (:meth:`~torchbend.sim.terms.EnergyTerm.adapt`, e.g. a contact barrier stiffened; the solve's best iterate
    and round-off bookkeeping start over there); ``adapted_at``: the positions in ``energy_history`` where another
    potential starts (an adaptation, or the second half of a halved step): the history is monotone between them.
    ``min_distance`` [m]: the smallest distance the contact terms report at the returned state (cloth-cloth
    between non-adjacent primitives, cloth-collider; negative: a penetration of a penalty collider; ``inf`` without
    contact; a barrier term's, exact up to 64 of its ``dhat``, ``inf`` beyond), ``contact_count``: the pairs and
    vertices in contact there (within a barrier's ``dhat`` or a collider's margin; a contact that several pairs
    find counts once for each)."""

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
    linear_seconds: float = 0.0
    linear_methods: dict = field(default_factory=dict)
    substeps: int = 1
    stop_reason: str = ""
    minimum: bool | None = None
    min_eigenvalue: float = math.nan
    negative_curvature_steps: int = 0
    force_scale: float = math.nan
    solves: int = 1
    best_iteration: int = 0
    phase: str = "newton"
    min_distance: float = math.inf
    contact_count: int = 0
    adaptations: int = 0
    adapted_at: list = field(default_factory=list)


# -------------------------------------------------------------------- Newton
class _Potential(NewtonDirections):
    """The (incremental) potential of a solve, restricted to the free DOFs: the model's terms, and for a
    time step the inertia (:class:`~torchbend.sim.terms.InertiaTerm`), evaluated in the step's
    :class:`~torchbend.sim.terms.StepContext` ``ctx`` (static: ``StepContext()``).

    ``free_mask``: ``(3V,)`` bool on the positions' device; ``free``: the same as a NumPy array
    (indexing the CPU copies of the linear algebra).  ``linear``: the :class:`LinearSolver` options.  The Newton
    matrix and its directions: :class:`~torchbend.sim.directions.NewtonDirections`."""

    def __init__(self, model: ClothModel, x: Tensor, option: Projection, ctx: StepContext | None = None,
                 soften: float | None = None, linear: LinearSolver | None = None, damping: bool = False):
        self.model, self.option = model, option
        self.linear = linear or LinearSolver()
        self.ctx = ctx or StepContext()
        terms = model.terms
        if soften is not None:
            terms = tuple((t.softened(soften) or t) if softens(t) else t for t in terms)
        self.terms = terms + (InertiaTerm(model.mass),) if self.ctx.dynamic else terms
        self.free_mask = (~model.pinned).to(x.device).repeat_interleave(3)
        self.free = self.free_mask.cpu().numpy()
        # linear algebra: the free Hessian's assembler (pattern shared per model) and what the last
        # direction found: positive definite (None: unknown), a direction of negative curvature (CG,
        # (nf,) on x's device), the factorisation / preconditioner used
        self.hessian_op = FreeHessian.for_model(model, self.free_mask)
        self.hessian_op.begin_solve()  # the pattern kept while the contact pairs change, from the terms' own
        self.positive_definite: bool | None = None
        self.negative_curvature: Tensor | None = None
        self.linear_method = ""
        self.linear_seconds = 0.0  # in the linear solves, all directions (SolveInfo.linear_seconds)
        self.reuse_cg_iterations = 0  # CG iterations on reused factorisations (SolveInfo.cg_iterations)
        self.skip_exact = False  # a time step's exact Hessian was just indefinite: the next direction is clamped's
        self.near_minimum = False  # set by the switch from a projected Hessian to the exact one
        # Levenberg-Marquardt damping by the lumped masses; in a time step only after poor steps (the far-step
        # rule is static: a step's inertia already bounds its moves, which are v dt, however far)
        mass_free = model.mass.to(x.device).repeat_interleave(3)[self.free_mask]
        self.damping = Damping(mass_free, enabled=damping)

    def value(self, y: Tensor) -> tuple[float, dict]:
        """``(Phi(y) [J], per-term energies)`` (the inertial term of a step is ``"inertia"``)."""
        e = {t.name: float(t.energy(y, self.ctx)) for t in self.terms}
        return sum(e.values()), e

    def gradient(self, y: Tensor) -> Tensor:
        """``dPhi/dy`` flat ``(3V,)`` [N]."""
        g = torch.zeros_like(y)
        for t in self.terms:
            g = g + t.gradient(y, self.ctx)
        return g.reshape(-1)

    def free_gradient(self, y: Tensor) -> np.ndarray:
        """The gradient on the free DOFs (NumPy, CPU)."""
        return self.gradient(y).cpu().numpy()[self.free]

    def force_magnitudes(self, y: Tensor) -> Tensor:
        """Per-DOF sum of the magnitudes of the forces acting at ``y``, flat ``(3V,)`` [N]: each term's
        (:meth:`EnergyTerm.force_magnitudes`: gravity, the elastic forces, the inertial forces of a time
        step; see the module docstring)."""
        out = torch.zeros_like(y)
        for t in self.terms:
            out = out + t.force_magnitudes(y, self.ctx)
        return out.reshape(-1)

    def gradient_roundoff(self, y: Tensor) -> float:
        """An estimate [N] of the round-off of ``|g_free|`` at ``y``: ``eps |(|B| |y|)_free|`` with ``B``
        the per-vertex 3x3 Hessian blocks (with the inertia's), the force error caused by rounding the
        coordinates."""
        B = torch.zeros(y.shape[0], 3, 3, dtype=y.dtype, device=y.device)
        for t in self.terms:
            B = B + t.block_diagonal(y, self.ctx, self.option).abs()
        r = (B @ y.abs()[..., None])[..., 0].reshape(-1)[self.free_mask]
        return float(torch.finfo(y.dtype).eps * r.norm())

    def max_step(self, y: Tensor, dy: Tensor) -> float:
        """The largest safe fraction of the step ``dy`` from ``y`` (the terms' :meth:`EnergyTerm.max_step`)."""
        return self.model.max_step(y, dy, self.ctx)

    def full(self, p: np.ndarray, like: Tensor) -> Tensor:
        """Free-DOF values ``p`` as a ``(V, 3)`` tensor like ``like`` (zero on pinned DOFs)."""
        out = like.new_zeros(self.free_mask.shape[0])
        out[self.free_mask] = torch.from_numpy(np.ascontiguousarray(p)).to(device=like.device, dtype=like.dtype)
        return out.reshape(-1, 3)


def _direction(phi: _Potential, x: Tensor, gf: np.ndarray, linear: LinearSolver, relative_residual: float,
               info: SolveInfo) -> tuple[np.ndarray, float]:
    """A descent direction on the free DOFs and its slope ``g . p`` [J]; a direction that is not one
    (or not finite) is replaced by the steepest-descent step ``-g min(1, 1/|g|)``.  With damping
    (:mod:`~torchbend.sim.damping`), a direction that moves a vertex farther than a tenth of the cloth's
    extent is recomputed with more damping (counted in ``info.regularized_steps``)."""
    reach = 0.1 * float((x.amax(0) - x.amin(0)).norm()) if x.shape[0] else math.inf
    while True:
        p, slope = _one_direction(phi, x, gf, linear, relative_residual, info)
        far = (phi.damping.enabled and not phi.ctx.dynamic and p.size > 0
               and float(phi.full(p, x).norm(dim=-1).max()) > reach)
        if not far or not phi.damping.increase():
            break
        info.regularized_steps += 1
    phi.damping.record_direction(p)
    return p, slope


def _one_direction(phi: _Potential, x: Tensor, gf: np.ndarray, linear: LinearSolver, relative_residual: float,
                   info: SolveInfo) -> tuple[np.ndarray, float]:
    """One direction of :func:`_direction` with the current Newton matrix."""
    before = phi.linear_seconds
    if linear.is_direct:
        reused = phi.reuse_cg_iterations
        p, shifts = phi.direct_direction(x, gf, relative_residual)
        info.regularized_steps += shifts
        info.cg_iterations += phi.reuse_cg_iterations - reused
    else:
        p, cg_it = phi.cg_direction(x, gf, relative_residual)
        info.cg_iterations += cg_it
    info.linear_seconds += phi.linear_seconds - before
    info.linear_methods[phi.linear_method] = info.linear_methods.get(phi.linear_method, 0) + 1
    slope = float(gf @ p)
    if not slope < 0 or not np.all(np.isfinite(p)):
        info.regularized_steps += 1
        gnorm = np.linalg.norm(gf)
        p = -gf / max(gnorm, 1e-300) * min(1.0, gnorm)
        slope = float(gf @ p)
    return p, slope


@dataclass
class _Iterate:
    """An evaluated iterate: positions, potential, its terms, residual, the tolerance and force scale
    it was compared with, and its index."""

    x: Tensor
    energy: float
    terms: dict
    residual: float
    tolerance: float
    scale: float
    iteration: int


def _noise(energy_terms: dict, magnitudes: Tensor | None, x: Tensor) -> float:
    """Round-off [J] of the potential at ``x``: ``64 eps (sum |E_term| + sum_i F_i |x_i|)`` (the terms'
    own rounding, and the forces times the rounding of the coordinates)."""
    s = sum(abs(v) for v in energy_terms.values())
    if magnitudes is not None:
        s += float((magnitudes * x.reshape(-1).abs()).sum())
    return 64 * torch.finfo(x.dtype).eps * s


def _stalled(info: SolveInfo, decrements: list, noise: float) -> bool:
    """The round-off floor test (module docstring) on the histories, before the gradient-round-off guard."""
    w = _STALL_WINDOW
    res, ene = info.residual_history, info.energy_history
    if len(decrements) < w or len(res) <= w or len(ene) <= w:
        return False
    if max(decrements[-w:]) > noise:
        return False
    last = ene[-w - 1:]
    if max(last) - min(last) > noise:
        return False
    return min(res[-w:]) > 0.5 * min(res[:-w])


def _better(a: _Iterate, best: _Iterate | None, noise: float) -> bool:
    """Lower potential wins; within round-off, the lower residual."""
    if best is None:
        return True
    if a.energy < best.energy - noise:
        return True
    return a.energy <= best.energy + noise and a.residual < best.residual


def _roundoff_step(phi: _Potential, x: Tensor, p: np.ndarray, energy: float, res: float,
                   noise: float) -> tuple[LineSearchResult, np.ndarray] | None:
    """The full step ``x + p`` when its decrease is below round-off: accepted if the potential stays
    within ``noise`` [J] and the residual drops, and no collider bounds the step (a step the collider
    step bound would shorten is never taken whole).  Returns ``(step, free gradient there)`` or None."""
    dx = phi.full(p, x)
    if phi.max_step(x, dx) < 1.0:
        return None
    y = x + dx
    try:
        e, terms = phi.value(y)
        gy = phi.free_gradient(y)
    except ValueError:
        return None
    r = float(np.linalg.norm(gy))
    if math.isfinite(e) and e <= energy + noise and r < res:
        return LineSearchResult(y, e, terms, 1.0), gy
    return None


def _curvature(phi: _Potential, x: Tensor) -> tuple[float, np.ndarray, float] | None:
    """``(lambda_min [N/m], unit eigenvector on the free DOFs, round-off tolerance [N/m])`` of the exact
    Hessian of the potential on the free DOFs at ``x``; None when it could not be computed."""
    Hf = phi.hessian_op.to_scipy(phi.hessian_op.assemble(x, phi.terms, phi.ctx, Projection.NONE)).tocsr()
    pair = smallest_eigenpair(Hf)
    if pair is None:
        return None
    return pair[0], pair[1], curvature_tolerance(Hf)


def _escape(phi: _Potential, x: Tensor, v: np.ndarray, gf: np.ndarray, energy: float, noise: float,
            max_steps: int = 40) -> LineSearchResult | None:
    """A step along the negative-curvature direction ``v`` (unit, free DOFs) that lowers the potential
    by more than ``noise`` [J]: the largest vertex moves by ``0.1 x`` the bounding-box diagonal at
    first (at most the collider step bound of :meth:`ClothModel.max_step`), halved until the potential
    drops, then while it keeps dropping; the sign with ``g . d <= 0`` (both when ``g . d`` is at
    round-off level, the lower end state kept).  None if neither sign helps."""
    vt = phi.full(v, x)
    vmax = float(vt.norm(dim=-1).max())
    extent = float((x.amax(0) - x.amin(0)).norm())
    if not (vmax > 0 and extent > 0):
        return None
    d = vt * (0.1 * extent / vmax)
    gd = float(gf @ (v * (0.1 * extent / vmax)))
    signs = [-1.0 if gd > 0 else 1.0]
    if abs(gd) <= noise:
        signs.append(-signs[0])
    best: LineSearchResult | None = None
    for s in signs:
        alpha, found = phi.max_step(x, s * d), None
        for _ in range(max_steps):
            y = x + (s * alpha) * d
            try:
                e, terms = phi.value(y)
            except ValueError:
                e, terms = math.inf, {}
            if math.isfinite(e) and e < energy - noise and (found is None or e < found.energy):
                found = LineSearchResult(y, e, terms, s * alpha)
            elif found is not None:
                break  # past the best point of the halving sequence
            alpha *= 0.5
        if found is not None and (best is None or found.energy < best.energy):
            best = found
    return best


def _newton(model: ClothModel, x0: Tensor, *, option: Projection, linear: LinearSolver, tol: float,
            max_iters: int, ctx: StepContext | None = None, soften: float | None = None,
            check_minimum: bool = False, callback: Callable | None = None, deadline: float | None = None,
            time_limit: float | None = None, damping: bool = False, started: float | None = None,
            max_line_search: int = 30) -> tuple[Tensor, SolveInfo]:
    """Minimise the (incremental) potential from ``x0 (V, 3)`` [m] (not modified) in the step context
    ``ctx`` (None: static), with the terms that take part in the stiffness homotopy scaled by ``soften``
    (:meth:`~torchbend.sim.terms.EnergyTerm.softened`; None: as they are).  Returns ``(x, info)``: the converged iterate, or the best one on failure
    (module docstring).  ``deadline``: a ``time.perf_counter()`` value past which the solve stops
    (``time_limit`` [s], for the message)."""
    phi = _Potential(model, x0, option, ctx, soften, linear, damping)
    run = _NewtonRun(phi, linear, tol=tol, max_iters=max_iters, check_minimum=check_minimum and option is Projection.NONE,
                     callback=callback, deadline=deadline, time_limit=time_limit, max_line_search=max_line_search)
    if started is not None:
        run.started = started
    # unbounded below: a static potential with gravity and nothing that holds the cloth in place
    unbounded = (not phi.ctx.dynamic and not bool(model.pinned.any()) and bool((model.gravity != 0).any())
                 and not any(t.confines for t in phi.terms))
    return run.solve(x0.detach().clone(), unbounded=unbounded)


class _Stop(Exception):
    """Ends a Newton run: ``reason`` (``SolveInfo.stop_reason``), ``message``, ``converged``."""

    def __init__(self, reason: str, message: str, converged: bool = False):
        super().__init__(message)
        self.reason, self.message, self.converged = reason, message, converged


class _RunRecord:
    """The state of one Newton solve (see :func:`_newton` and the module docstring): the iterates, the force
    scale, the best iterate kept, the switch from a projected to the exact Hessian and the final report;
    :class:`_NewtonRun` iterates."""

    def __init__(self, phi: _Potential, linear: LinearSolver, *, tol: float, max_iters: int, check_minimum: bool,
                 callback: Callable | None, deadline: float | None, time_limit: float | None, max_line_search: int):
        self.phi, self.linear, self.tol, self.max_iters = phi, linear, tol, max_iters
        self.check_minimum, self.callback, self.deadline, self.time_limit = check_minimum, callback, deadline, time_limit
        self.max_line_search = max_line_search
        # a stall within 100x the estimated floor ends an exact Newton run (quadratic convergence stalls only
        # there); projected Hessians converge linearly and may look stalled well above it: 4x for them
        self.floor_factor = 100.0 if phi.option is Projection.NONE else 4.0

        self.info = SolveInfo()
        self.t0 = self.started = time.perf_counter()  # started: when the public call began (progress level)
        self.last_info = -math.inf
        self.best: _Iterate | None = None
        self.current: _Iterate | None = None
        self.it = self.escapes = 0
        self.magnitudes: Tensor | None = None
        self.scale, self.scale_at = math.nan, -1
        self.decrements: list = []
        self.gf_next: np.ndarray | None = None
        self.alpha, self.cg_before = math.nan, 0
        self.polish_steps = 0  # whole exact steps still to take below round-off after :meth:`_polish`
        self.slow_steps = 0  # consecutive full steps that did not halve the residual

    def _polish(self) -> bool:
        """At an apparent round-off floor of a projected Hessian, or when it converges slowly near a minimum
        (``_SLOW_STEPS`` full steps in a row that did not halve a residual below ``1e-3 F``): switch to the
        exact one for the last iterations (a projected Newton converges linearly and its floor estimate is loose; the exact
        Newton reaches the true floor quadratically).  True when it switched (once per run)."""
        if self.phi.option is Projection.NONE:
            return False
        self.phi.option, self.floor_factor, self.polish_steps = Projection.NONE, 100.0, 2
        self.phi.near_minimum = True
        self.phi.damping.off()
        self.decrements.clear()
        return True

    def _credible_floor(self, x: Tensor, res: float) -> bool:
        """Whether a residual ``res`` [N] at an apparent round-off floor is small against the force scale at
        ``x`` (refreshed there): ``res <= min(eps K, 1/8) F`` (module docstring).  Above that the state is
        ill-conditioned (nearly collapsed elements have huge Hessian blocks, hence a huge floor estimate), not
        converged."""
        if self.scale_at != self.it:
            self._refresh_scale(x)
        return res <= min(torch.finfo(x.dtype).eps * _CREDIBLE_CONDITION, _CREDIBLE_SHARE) * self.scale

    def _refresh_scale(self, x: Tensor) -> None:
        """The per-DOF force magnitudes and the force scale ``F`` [N] at the current iterate ``x``."""
        self.magnitudes = magnitudes = self.phi.force_magnitudes(x)
        self.scale = max(float(magnitudes.norm()), torch.finfo(x.dtype).tiny)
        self.scale_at = self.it

    def _adapt(self, x: Tensor, start: bool = False) -> bool:
        """The terms' adaptation at the iterate ``x`` of a time step's solve (:meth:`EnergyTerm.adapt`, e.g. a
        barrier's stiffness; a static solve keeps its potential: it depends on its inputs alone, and its phases'
        results stay comparable).  A change makes a new potential: the iterates before it are not comparable with
        those after, so the best iterate, the decrements and the force scale start over from ``x``, and
        ``info.adapted_at`` marks where ``energy_history`` changes potential."""
        if not self.phi.ctx.dynamic:
            return False
        changed = [t.adapt(x, self.phi.ctx, start) for t in self.phi.terms]
        if not any(changed):
            return False
        self.best, self.gf_next, self.slow_steps, self.scale_at = None, None, 0, -1
        self.decrements.clear()
        self.info.adaptations += 1
        self.info.adapted_at.append(len(self.info.energy_history))
        return True

    def _where(self) -> str:
        return f"returned the best iterate (iteration {self.best.iteration if self.best else 0})"

    def _evaluate(self, x: Tensor, energy: float, terms: dict) -> tuple[np.ndarray, float]:
        """Gradient, force scale, round-off and bookkeeping at the iterate ``x``: ``(g_free, noise [J])``."""
        phi, info, it = self.phi, self.info, self.it
        try:
            gf = self.gf_next if self.gf_next is not None else phi.free_gradient(x)
        except ValueError as err:
            raise _Stop("evaluation_error", f"evaluation failed at iteration {it}: {err}; {self._where()}") from None
        self.gf_next = None
        res = float(np.linalg.norm(gf))
        if not math.isfinite(res):
            raise _Stop("non_finite", f"non-finite gradient at iteration {it}; {self._where()}")
        if self.scale_at < 0 or it - self.scale_at >= 10 or res <= 1e3 * self.tol * self.scale:
            self._refresh_scale(x)
        tolerance = self.tol * self.scale
        noise = _noise(terms, self.magnitudes, x)
        self.current = _Iterate(x, energy, terms, res, tolerance, self.scale, it)
        if _better(self.current, self.best, noise):
            self.best = self.current
        info.residual, info.energy, info.energies, info.iterations = res, energy, terms, it
        info.tolerance, info.force_scale, info.best_iteration = tolerance, self.scale, it
        info.residual_history.append(res)
        h = info.residual_history
        self.slow_steps = self.slow_steps + 1 if len(h) > 1 and self.alpha == 1.0 and h[-1] > 0.5 * h[-2] else 0
        level = _level(self.started)
        if level == logging.INFO and time.perf_counter() - self.last_info < _INFO_EVERY_S:
            level = logging.DEBUG
        if level == logging.INFO:
            self.last_info = time.perf_counter()
        if _log.isEnabledFor(level):
            _log.log(level, "newton it %d: residual %.3e N (tol %.3e N), potential %.15e J, alpha %.3g, CG %d, "
                     "damping %.2g/s^2", it, res, tolerance, energy, self.alpha, info.cg_iterations - self.cg_before,
                     phi.damping.mu)
        return gf, noise

    def _finish(self, x: Tensor, stop: _Stop) -> tuple[Tensor, SolveInfo]:
        info = self.info
        info.converged, info.stop_reason, info.message = stop.converged, stop.reason, stop.message
        ret = self.current if stop.converged or self.best is None else self.best
        if ret is not None:
            info.residual, info.energy, info.energies = ret.residual, ret.energy, ret.terms
            info.tolerance, info.force_scale, info.best_iteration = ret.tolerance, ret.scale, ret.iteration
        out = ret.x if ret is not None else x
        info.min_distance, info.contact_count = contact_stats(self.phi.terms, out)
        info.seconds = time.perf_counter() - self.t0
        _log.log(_level(self.started), "newton: %s (%d iterations, residual %.3e N, %.2f s)", info.message, info.iterations,
                 info.residual, info.seconds)
        return out, info


class _NewtonRun(_RunRecord):
    """One Newton solve: the stopping tests, the negative-curvature check and the steps."""

    # ---------------------------------------------------------------- driver
    def solve(self, x: Tensor, unbounded: bool) -> tuple[Tensor, SolveInfo]:
        info = self.info
        try:
            try:
                energy, terms = self.phi.value(x)
            except ValueError as err:
                raise _Stop("evaluation_error", f"the potential cannot be evaluated at the initial state: {err}") from None
            info.energy_history.append(energy)
            info.energy, info.energies = energy, terms
            if unbounded:
                raise _Stop("rigid_body_modes", "the cloth has free rigid-body modes (no pinned vertices and no "
                            "colliders): under gravity its potential is unbounded below; pin vertices or add a collider")
            if not math.isfinite(energy):
                raise _Stop("non_finite", "non-finite potential at the initial state")
            if self._adapt(x, start=True):
                energy, terms = self.phi.value(x)
            while True:
                gf, noise = self._evaluate(x, energy, terms)
                step = self._test(x, gf, energy, noise)
                if step is None:
                    step = self._step(x, gf, energy, terms, noise)
                x, energy, terms, self.alpha = step.x, step.energy, step.terms, step.alpha
                if self._adapt(x):
                    energy, terms = self.phi.value(x)
                    info.energy, info.energies = energy, terms
                self.it += 1
                info.iterations = self.it
                info.energy_history.append(energy)
        except _Stop as stop:
            return self._finish(x, stop)

    def _test(self, x: Tensor, gf: np.ndarray, energy: float, noise: float) -> LineSearchResult | None:
        """The stopping tests at the evaluated iterate; raises :class:`_Stop`, or returns a
        negative-curvature step (or None: iterate on)."""
        cur, info, it = self.current, self.info, self.it
        assert cur is not None and self.best is not None
        reason = None
        if self.slow_steps >= _SLOW_STEPS and cur.residual <= 1e-3 * cur.scale:
            self._polish()
        if cur.residual <= cur.tolerance:
            reason = "residual"
        elif (_stalled(info, self.decrements, noise) and cur.residual <= self.floor_factor * self.phi.gradient_roundoff(x)
              and self._credible_floor(x, cur.residual)):
            reason = None if self._polish() else "round-off floor"
        stop = bool(self.callback(it, x, info)) if (self.callback is not None and it > 0) else False
        if reason is not None:
            return self._converged(reason, x, gf, energy, noise)
        if stop:
            raise _Stop("callback", f"stopped by the callback at iteration {it}; {self._where()}")
        if it >= self.max_iters:
            raise _Stop("max_iters", f"no convergence in {self.max_iters} Newton iterations (residual "
                        f"{cur.residual:.3e} N > tolerance {cur.tolerance:.3e} N); {self._where()}")
        if self.deadline is not None and time.perf_counter() > self.deadline:
            raise _Stop("time_limit", f"time limit of {self.time_limit:g} s reached after {it} Newton iterations; "
                        f"{self._where()}")
        return None

    def _converged(self, reason: str, x: Tensor, gf: np.ndarray, energy: float, noise: float) -> LineSearchResult:
        """A stopping test fired: the negative-curvature check, then a step off the saddle or the end
        (no step when ``max_iters`` is 0, evaluation only, or after ``_MAX_ESCAPES`` of them)."""
        step = _check_minimum(self.phi, x, gf, energy, noise, self.info) if self.check_minimum else None
        why = "no descent was found along its eigenvector"
        if step is not None and self.max_iters == 0:
            step, why = None, "max_iters=0 (evaluation only)"
        elif step is not None and self.escapes >= _MAX_ESCAPES:
            step, why = None, f"{_MAX_ESCAPES} negative-curvature steps were taken"
        if step is None:
            msg = f"converged ({reason})"
            if self.info.minimum is False:
                msg += (f"; not a verified minimum: the exact Hessian has the eigenvalue {self.info.min_eigenvalue:.3e} "
                        f"N/m and {why}")
            raise _Stop(reason, msg, converged=True)
        self.escapes += 1
        self.info.negative_curvature_steps += 1
        self.decrements.append(math.inf)
        return step

    def _step(self, x: Tensor, gf: np.ndarray, energy: float, terms: dict, noise: float) -> LineSearchResult:
        """A Newton direction and an accepted step along it (or the round-off floor / a failure)."""
        phi, info, it = self.phi, self.info, self.it
        res = float(np.linalg.norm(gf))
        if res <= 1e-3 * self.scale:
            phi.damping.off()  # near the minimum: Newton's own steps (damping returns only after a failure)
        self.cg_before, shifts_before = info.cg_iterations, info.regularized_steps
        try:
            p, slope = _direction(phi, x, gf, self.linear, res / max(self.scale, 1e-300), info)
        except ValueError as err:
            raise _Stop("evaluation_error", f"evaluation failed at iteration {it}: {err}; {self._where()}") from None
        regularized = info.regularized_steps > shifts_before
        self.decrements.append(-slope)
        if -slope <= noise:
            # below the potential's round-off only the residual tells progress: a whole step that lowers it
            # is taken; at the estimated floor only if it halves the residual (the estimate is an upper
            # bound).  The first exact steps after a switch from a projected Hessian are taken whatever the
            # residual: the soft modes' error left by the linear convergence does not show above the stiff
            # modes' round-off, and the exact step removes it
            at_floor = res <= 4 * phi.gradient_roundoff(x) and self._credible_floor(x, res)
            target = math.inf if self.polish_steps > 0 else 0.5 * res if at_floor else res
            self.polish_steps = max(0, self.polish_steps - 1)
            found = _roundoff_step(phi, x, p, energy, target, noise)
            if found is not None:
                step, self.gf_next = found
                return step
            if at_floor:
                if self._polish():
                    return self._step(x, gf, energy, terms, noise)
                return self._converged("round-off floor", x, gf, energy, noise)
        dx = phi.full(p, x)
        step = armijo_backtracking(phi.value, x, dx, energy, terms, slope,
                                   lambda y: float(np.linalg.norm(phi.free_gradient(y))) < res,
                                   max_steps=self.max_line_search, alpha_max=phi.max_step(x, dx))
        if step is not None:
            phi.damping.accepted(energy - step.energy, slope, step.alpha)
            return step
        info.line_search_failures += 1
        if phi.damping.increase():  # no decrease along the damped direction: a shorter one next iteration
            return LineSearchResult(x, energy, terms, 0.0)
        if -slope <= noise and res <= 100 * phi.gradient_roundoff(x) and self._credible_floor(x, res):
            if self._polish():
                return self._step(x, gf, energy, terms, noise)
            return self._converged("round-off floor", x, gf, energy, noise)
        what = ("a regularised direction (the Hessian on the free DOFs is indefinite or singular)" if regularized
                else "the Newton direction")
        raise _Stop("line_search", f"line search exhausted at iteration {it}: no decrease along {what}; {self._where()}")


def _check_minimum(phi: _Potential, x: Tensor, gf: np.ndarray, energy: float, noise: float,
                   info: SolveInfo) -> LineSearchResult | None:
    """The negative-curvature check at a stationary point (module docstring): sets ``info.minimum`` and
    ``info.min_eigenvalue``; returns a step along the negative-curvature direction, or None (verified,
    not computable, or no descent along it)."""
    try:
        found = _curvature(phi, x)
    except ValueError:
        found = None
    if found is None:
        info.minimum, info.min_eigenvalue = None, math.nan
        return None
    lam, v, tau = found
    info.min_eigenvalue = lam
    if lam >= -tau:
        info.minimum = True
        return None
    info.minimum = False
    step = _escape(phi, x, v, gf, energy, noise)
    _log.log(logging.DEBUG, "newton: negative curvature %.3e N/m (round-off %.1e): %s", lam, tau,
             "stepping along it" if step is not None else "no descent along it")
    return step


# -------------------------------------------------------------------- public solvers
def _prepare_x(model: ClothModel, x, name: str = "x0", step: bool = False) -> Tensor:
    """``x`` as a finite floating ``(V, 3)`` tensor (on its own device), a valid start for every term (``step``: a
    time step's, where a moved body counts at its last pose if ``x`` is valid there: the step carries out the move)."""
    x = torch.as_tensor(x)
    if x.shape != (model.vertex_count, 3):
        raise ValueError(f"{name} must have shape ({model.vertex_count}, 3), got {tuple(x.shape)}")
    x = check_positions(x, model.vertex_count, name)
    if name != "state.v":
        for term in model.terms:
            why = term.inadmissible(x)
            if why and step and term.pending_move():
                pose = term.pose()
                term.place(0.0)
                why = why if term.inadmissible(x) else ""
                term.restore_pose(pose)
            if why:
                raise ValueError(f"{name}: {why}")
    return x


def _aggregate(infos: list, returned: SolveInfo) -> SolveInfo:
    """``returned`` (the info of the solve whose state is returned) with the counters of all ``infos``."""
    out = replace(returned)
    out.iterations = sum(i.iterations for i in infos)
    out.solves = sum(i.solves for i in infos)
    out.line_search_failures = sum(i.line_search_failures for i in infos)
    out.regularized_steps = sum(i.regularized_steps for i in infos)
    out.cg_iterations = sum(i.cg_iterations for i in infos)
    out.linear_seconds = sum(i.linear_seconds for i in infos)
    out.linear_methods = {}
    for i in infos:
        for method, count in i.linear_methods.items():
            out.linear_methods[method] = out.linear_methods.get(method, 0) + count
    out.negative_curvature_steps = sum(i.negative_curvature_steps for i in infos)
    out.adaptations = sum(i.adaptations for i in infos)
    return out


def solve_static(model: ClothModel, x0, options: NewtonOptions | None = None, *,
                 projection: str | Projection = UNSET, linear_solver: str | LinearSolver = UNSET,
                 tol: float = UNSET, max_iters: int = UNSET, continuation: bool | str | None = UNSET,
                 max_relax_steps: int = UNSET, check_minimum: bool = UNSET, callback: Callable | None = None,
                 time_limit: float | str | None = UNSET, max_cg_iters: int | None = UNSET,
                 damping: bool = UNSET, hessian: str | Projection | None = UNSET) -> tuple[Tensor, SolveInfo]:
    """Static equilibrium from ``x0 (V, 3)`` [m]; pinned vertices keep their ``x0`` positions.  Bodies (a
    :class:`~torchbend.MeshCollider`, an ipc collider replaced by a moved one) are where they were last given: a
    move pending for the next time step ends there.

    ``options``: a :class:`NewtonOptions` (every control below; a keyword given here overrides its field).
    ``projection``: a :class:`torchbend.options.Projection` (``"exact"``, the default, ``"clamp"``, ``"abs"``,
    ``"gauss_newton"``, ``"reduced"``) for the Newton matrix; ``linear_solver``: ``"direct"`` (sparse
    factorisation), ``"cg"``, or a :class:`LinearSolver` (``tb.LinearSolver("cg", preconditioner="amg")``:
    the preconditioner, Cholesky, the CG bound); ``hessian=``: the deprecated alias of ``projection=``
    (``DeprecationWarning``).  ``tol`` (> 0) is relative to the force scale
    (stop when ``|g_free| <= tol F`` [N], ``F`` the magnitude of all forces acting, internal ones
    included) unless the residual has reached its round-off floor: see the module docstring; the
    default suits shells from ``Y t = 1e2`` to ``1e7`` N/m.  ``max_iters``: Newton iterations per
    solve (an int >= 0; 0 evaluates ``x0`` only).  ``continuation`` globalises solves that Newton
    alone does not finish (large rotations of soft shells, where the stiff membrane limits every
    Newton step to about an edge length):

    * ``"membrane"``: a homotopy in the membrane stiffness: Newton solves with the membrane's moduli
      scaled by ``1e-3``, ``1e-1`` and then ``1`` (the problem itself), each from the previous
      equilibrium (a softer membrane lets a step rotate the shell further; the final solve is the
      unmodified potential, with every control above);
    * ``"relaxation"``: pseudo-transient continuation: implicit-Euler steps from rest (the velocity
      is reset every step, so each step is a proximal step on the potential) with a growing step
      size, retrying Newton every few steps (at most ``max_relax_steps`` steps);
    * ``"auto"`` (default, also ``True``): a first Newton solve of at most ``4 max_iters`` iterations with
      ``damping`` and a collider (the damping bounds the soft modes of a garment on a body itself, where the
      homotopy's softened membrane sags it into other contact states), else ``min(max_iters, 40)`` continued up
      to ``max_iters`` when it is converging (its last residual its lowest, a
      tenth of the lowest before its last 5 iterations and 1e-3 of its largest: softening the membrane
      there could lead to another minimum); if it fails, ``"membrane"`` from its best iterate when the model has a membrane
      (then ``"relaxation"`` if that fails too), ``"relaxation"`` otherwise;
    * ``False`` / ``None``: Newton only.

    ``info.iterations`` counts every Newton iteration of every solve.  ``check_minimum`` (with ``projection="exact"``): at a stationary
    point, check the exact Hessian for negative curvature and step off saddles (``info.minimum``).
    ``callback(iteration, x, info)``: called after every Newton iterate, True stops the solve;
    ``time_limit`` [s] (> 0): wall-time bound of the whole call (checked between Newton iterations
    and relaxation steps), after which the best state is returned with ``stop_reason="time_limit"``;
    the default ``"auto"`` is 120 s (:data:`~torchbend.sim.options.DEFAULT_TIME_LIMITS`), None lifts it.
    ``damping`` (default True; False: plain Newton): Levenberg-Marquardt damping of the Newton matrix by the lumped masses,
    driven by the agreement of the quadratic model and vanishing at convergence (:mod:`torchbend.sim.damping`:
    it bounds the steps along the soft modes of a hanging garment: sliding along a collider, turning about
    a pin, buckling).  ``max_cg_iters`` (>= 1): CG
    iterations per Newton direction (None: automatic).  Progress goes to the logger
    ``"torchbend.sim"``.

    Returns ``(x (V, 3) [m], info)``.  Nothing is raised once iterating: on failure ``x`` is the best
    iterate found (lowest potential; ``x0`` itself only when no step lowered it), ``info.converged``
    is False and ``info.stop_reason`` / ``info.message`` say why; ``info`` describes the returned
    state.  ``x0`` is never modified.  Invalid arguments raise ``ValueError`` naming them."""
    x0 = _prepare_x(model, x0)
    opts, ctl = resolve_options(options, "solve_static", "static", hessian=hessian, max_cg_iters=max_cg_iters,
                                callback=callback, projection=projection, linear_solver=linear_solver, tol=tol,
                                max_iters=max_iters, continuation=continuation, max_relax_steps=max_relax_steps,
                                check_minimum=check_minimum, time_limit=time_limit, damping=damping)
    for term in model.terms:  # the bodies are where they are given: a move pending from a step ends there
        if term.pending_move():
            term.settle()
    option, linear, max_relax_steps = opts.option, opts.linear, opts.max_relax_steps
    mode = continuation_mode(opts.continuation) if ctl.max_iters > 0 else None  # 0: evaluation only
    kw = ctl.newton_kw()
    if mode == "auto":
        kw["max_iters"] = (_DAMPED_FIRST_FACTOR * ctl.max_iters if ctl.damping and any(t.contact for t in model.terms)
                           else min(ctl.max_iters, _AUTO_FIRST_ITERS))
    x, info = _newton(model, x0, option=option, linear=linear, **kw)
    if mode == "auto" and info.stop_reason == "max_iters" and _converging(info) and ctl.max_iters > kw["max_iters"]:
        # the first attempt is on its way (a steadily falling residual): let it finish before softening anything
        first = info
        x, info = _newton(model, x, option=option, linear=linear,
                          **dict(kw, max_iters=ctl.max_iters - kw["max_iters"]))
        merged = _aggregate([first, info], info)  # its best iterate is at least the first attempt's
        merged.seconds = first.seconds + info.seconds
        info = merged
    if info.converged or mode is None or info.stop_reason in _FINAL_STOPS:
        return _done(x, info, "newton", ctl)
    if mode in ("auto", "membrane") and any(softens(t) for t in model.terms):
        _phase(ctl, "membrane-stiffness homotopy", info)
        x, info = _membrane_homotopy(model, x, info, option, linear, ctl)
        if info.converged or mode == "membrane" or info.stop_reason in _FINAL_STOPS:
            return _done(x, info, "membrane", ctl)
    _phase(ctl, "pseudo-transient relaxation", info)
    return _done(*_continuation(model, x, info, option, linear, ctl, max_relax_steps), "relaxation", ctl)


def _phase(ctl: Controls, name: str, info: SolveInfo) -> None:
    """The progress line of a phase of :func:`solve_static` that begins after a failed one."""
    _log.log(_level(ctl.started), "solve_static: %s after %d Newton iterations (%s; residual %.3e N), %.1f s so far",
             name, info.iterations, info.stop_reason, info.residual, time.perf_counter() - ctl.started)


def _done(x: Tensor, info: SolveInfo, phase: str, ctl: Controls) -> tuple[Tensor, SolveInfo]:
    """The end of a public call: ``info.phase`` set, its summary line."""
    info.phase = phase
    _log.log(_level(ctl.started), "solve_static: %s (phase %s: %d Newton iterations in %d solves, %.1f s)",
             "converged" if info.converged else f"not converged ({info.stop_reason})", phase, info.iterations,
             info.solves, time.perf_counter() - ctl.started)
    return x, info


_AUTO_FIRST_ITERS = 40
"""Newton iterations of the first attempt of ``continuation="auto"`` (undamped, or without a collider) before the
homotopy takes over (unless the attempt is converging: :func:`_converging`).  40, not 20: the damped Newton finishes
most soft strips of the solver sweep in 25-40 iterations, and a homotopy started earlier can leave the basin of the
equilibrium Newton from the rest state reaches (on an AMD Zen 4 build, Y t = 1e2 N/m, t = 1 mm, 16x4, exact/cg:
the softened membrane led to another minimum, 7% higher in energy).  Over the 288 sweep solves: 11,520 iterations
in all and at most 113 in one, against 15,478 and 209 with 20 (benchmarks/results/solver_sweep_amd_1thread.txt);
the paper beams reach the same tips in about as many iterations in all."""
_DAMPED_FIRST_FACTOR = 4
"""The first attempt of a damped ``continuation="auto"`` with a collider takes at most this many times ``max_iters``
iterations (benchmarks/results/garments_penalty_1thread.txt: the garments of benchmarks/garments.py take 50-476 Newton
iterations in all, where a 20-iteration first attempt handed every one to the homotopy and the relaxation: 200-990;
without a collider, the softest paper beam, the homotopy is the faster: 53 iterations against 93)."""
_HOMOTOPY_FACTORS = (1e-3, 1e-1)
"""Membrane stiffness factors of the homotopy stages before the unmodified potential."""
_FINAL_STOPS = ("rigid_body_modes", "time_limit", "callback")
"""Stop reasons after which no continuation is tried."""


def _converging(info: SolveInfo) -> bool:
    """Whether a Newton run that hit its iteration bound is converging: its last residual is its lowest, at
    most a tenth of the lowest before its last 5 iterations and below 1e-3 of the largest it had (the
    final approach to a minimum), so that more iterations, not a homotopy, finish it."""
    h = info.residual_history
    return len(h) > 5 and h[-1] <= min(h) and h[-1] <= 0.1 * min(h[:-5]) and h[-1] < 1e-3 * max(h)


def _membrane_homotopy(model: ClothModel, x_start: Tensor, first: SolveInfo, option: Projection,
                       linear: LinearSolver, ctl: Controls) -> tuple[Tensor, SolveInfo]:
    """The membrane-stiffness homotopy of :func:`solve_static` from ``x_start`` (the best iterate of the
    failed first solve ``first``).  Returns the final solve's state (converged or its best iterate)
    with the counters of all solves."""
    t0 = time.perf_counter()
    infos, x = [first], x_start
    stage_kw = dict(ctl.newton_kw(), tol=max(ctl.tol, 1e-6), check_minimum=False, callback=None)
    for factor in _HOMOTOPY_FACTORS:
        x, info = _newton(model, x, option=option, linear=linear, soften=factor, **stage_kw)
        infos.append(info)
        if info.stop_reason in _FINAL_STOPS:
            break
    x, info = _newton(model, x, option=option, linear=linear, **ctl.newton_kw())
    infos.append(info)
    if not info.converged and not info.energy < first.energy:  # never return a worse state than the start's
        x, info = x_start, first
    out = _aggregate(infos, info)
    out.seconds = first.seconds + (time.perf_counter() - t0)
    stages = " -> ".join(f"{f:g}" for f in (*_HOMOTOPY_FACTORS, 1.0))
    if info.converged:
        out.message = (f"{info.message} after a membrane-stiffness homotopy ({stages}): {out.iterations} Newton "
                       f"iterations in {out.solves} solves")
    else:
        out.message = (f"no convergence: {out.iterations} Newton iterations in {out.solves} solves (membrane homotopy "
                       f"{stages}); last solve: {info.message}")
    return x, out


def _continuation(model: ClothModel, x_start: Tensor, first: SolveInfo, option: Projection, linear: LinearSolver,
                  ctl: Controls, max_relax_steps: int) -> tuple[Tensor, SolveInfo]:
    """Pseudo-transient continuation after a failed static solve (see :func:`solve_static`), from that
    solve's best iterate ``x_start``.  Returns the converged state, or the best one of all static
    Newton solves and of the last relaxed state."""
    t0 = time.perf_counter()
    infos = [first]
    candidates: list = [(x_start, first)]
    xk, dt, evaluated = x_start, 1e-2, True
    static_kw = ctl.newton_kw()
    step_ctl = replace(ctl, tol=1e-6, max_iters=30, check_minimum=False, callback=None)
    converged, stopped = None, ""
    last_static: Tensor | None = None
    for k in range(max_relax_steps):
        if ctl.deadline is not None and time.perf_counter() > ctl.deadline:
            stopped = "time_limit"
            break
        state, step_info = _euler_step(model, ClothState(xk, torch.zeros_like(xk)), dt, option, linear, step_ctl, 0)
        infos.append(step_info)
        if not step_info.converged:
            dt *= 0.25
            continue
        xk, dt, evaluated = state.x, dt * 1.5, False
        if k % 5 == 4:
            if last_static is not None and torch.equal(xk, last_static):
                stopped = "stalled"  # the relaxation no longer moves: the static solve would repeat itself
                break
            last_static = xk
            x, info = _newton(model, xk, option=option, linear=linear, **static_kw)
            infos.append(info)
            candidates.append((x, info))
            evaluated = True
            if info.converged or info.stop_reason in ("time_limit", "callback"):
                converged = (x, info) if info.converged else None
                stopped = "" if info.converged else info.stop_reason
                break
    if converged is None and not evaluated:  # the last relaxed state, evaluated only
        kw = dict(static_kw, max_iters=0, check_minimum=False, callback=None, deadline=None)
        x, info = _newton(model, xk, option=option, linear=linear, **kw)
        info.solves = 0
        candidates.append((x, info))
    seconds = first.seconds + (time.perf_counter() - t0)
    if converged is not None:
        x, info = converged
        out = _aggregate(infos, info)
        out.message = (f"{info.message} after pseudo-transient continuation: {out.iterations} Newton iterations in "
                       f"{out.solves} solves")
        out.seconds = seconds
        return x, out
    x, info = min(candidates, key=lambda c: (c[1].energy if math.isfinite(c[1].energy) else math.inf))
    out = _aggregate(infos, info)
    out.converged, out.seconds, out.minimum = False, seconds, None
    if stopped:
        out.stop_reason = stopped
    elif info.stop_reason in ("residual", "round-off floor", ""):
        out.stop_reason = "max_iters"  # the relaxation budget ran out after that state
    why = (f"time limit of {ctl.time_limit} s reached" if stopped == "time_limit" else
           "stopped by the callback" if stopped == "callback" else
           "the relaxation came to rest where the static solve does not converge" if stopped == "stalled" else
           f"{max_relax_steps} relaxation steps tried")
    out.message = (f"no convergence: {out.iterations} Newton iterations in {out.solves} solves (continuation); "
                   f"{why}; returned the best state (potential {info.energy:.6e} J, residual {info.residual:.3e} N)")
    return x, out


MAX_MOVE_STAGES = 256
"""The most solves (stages) in which a time step carries out the moves of bodies (:func:`implicit_euler_step`): a
body pushing the cloth ahead of it takes a stage per fraction of the cloth's gap to it (a 10 cm sphere swept 4 cm
sideways through a hanging 15x15 sheet in one step: 60 to 175 stages, up to 6 s); the step's time limit bounds it too."""
MAX_MOVE_ADVANCES = 1024
"""The most advances (step bounds) in which a time step carries out the moves of bodies."""


def implicit_euler_step(model: ClothModel, state: ClothState, dt: float, options: NewtonOptions | None = None, *,
                        projection: str | Projection = UNSET, linear_solver: str | LinearSolver = UNSET,
                        tol: float = UNSET, max_iters: int = UNSET, max_substep_depth: int = UNSET,
                        check_minimum: bool = UNSET, callback: Callable | None = None,
                        time_limit: float | str | None = UNSET, max_cg_iters: int | None = UNSET,
                        hessian: str | Projection | None = UNSET) -> tuple[ClothState, SolveInfo]:
    """One backward-Euler step of size ``dt`` [s] from ``state`` (``x, v: (V, 3)`` [m], [m/s]):
    Newton on the incremental potential.

    ``options``, ``projection``, ``linear_solver``, ``tol`` (default ``1e-6``), ``max_iters`` (default 100),
    ``callback``, ``time_limit`` (default ``"auto"``: 30 s), ``max_cg_iters`` as for :func:`solve_static`; the force scale of ``tol`` includes the inertial
    forces ``M v_n / dt`` and ``M (x - x_hat) / dt^2``.  ``check_minimum`` is off by default here (the
    inertia term usually makes a step's potential convex; True checks as :func:`solve_static` does).
    Pinned vertices keep their positions (zero velocity).  With bending damping, the viscous term uses
    the angles of ``state.x`` as ``theta_prev``.  The Newton solve is damped after poor steps
    (``NewtonOptions(damping=)``, :mod:`~torchbend.sim.damping`).  A step whose exact-Hessian solve stops
    (``max_iters``, a failed line search) is solved again with the clamped projection (``info.phase ==
    "clamped"`` when that state is returned), and one that still fails is retried as two half steps
    (recursively, at most ``max_substep_depth`` halvings; neither with 0; ``info.substeps`` counts the
    (sub)steps of the returned state, ``info.solves`` every Newton solve).

    A body moved since the last step (a :class:`~torchbend.MeshCollider` whose ``vertices`` were assigned) moves
    from its last pose to the new one within the step: where the move would bring it into contact with the cloth
    held at ``state.x``, it advances as far as the contact's step bound allows, again and again, and the cloth is
    solved wherever the body has come within its activation distance and closed half the gap since the last solve
    (a stage; at most ``MAX_MOVE_STAGES`` solves and ``MAX_MOVE_ADVANCES`` advances), so the body pushes the cloth
    instead of passing through it.  A move the cloth cannot make way for (caught between the body and a pinned vertex or another
    body) ends where it stops: the body stays at the pose reached, the state is the solve there, and the step
    says so (``converged = False``).

    Nothing is raised once iterating: if the step fails, the best state reached at the end of the
    step is returned with ``info.converged = False`` (the halves' end state when the first half
    succeeded, else the best iterate of the full step) with the consistent velocity
    ``v = (x - x_start)/dt_step``, never the old state; ``state`` is never modified."""
    dt = positive_value(dt, "dt")
    if not isinstance(state, ClothState):
        raise ValueError(f"state must be a ClothState, got {type(state).__name__}")
    _prepare_x(model, state.x, "state.x", step=True)
    _prepare_x(model, state.v, "state.v")
    opts, ctl = resolve_options(options, "implicit_euler_step", "step", hessian=hessian, max_cg_iters=max_cg_iters,
                                callback=callback, projection=projection, linear_solver=linear_solver, tol=tol,
                                max_iters=max_iters, max_substep_depth=max_substep_depth,
                                check_minimum=check_minimum, time_limit=time_limit)
    return _euler_step(model, state, dt, opts.option, opts.linear, ctl, opts.max_substep_depth, retry=True)


RETRIED_STOPS = ("max_iters", "line_search")
"""The stop reasons of a time step's exact-Hessian solve after which the whole step is solved again with the
clamped projection before it is halved (:func:`_euler_step`)."""

def _still_converging(info: SolveInfo, window: int = 10) -> bool:
    """Whether a solve that stopped was still converging: its best residual of the last ``window`` iterates at most
    half the best before them (a time step's retry then goes on from its best state, :func:`_euler_step`)."""
    r = info.residual_history
    return len(r) > window and min(r[-window:]) <= 0.5 * min(r[:-window])


RETRY_FRICTION_SLIP = 0.5
"""The retry's ``StepContext.friction_slip``: its friction Hessians keep half the curvature along a sliding pair's
slip that the exact one removes (:func:`torchbend.energies.friction.friction_blocks`).  Stacks of three to five 11x11
to 15x15 sheets hitting a floor at 3-4 m/s with friction 1 (a mesh floor), or 0.3 in float32, failed the step after
the impact with the exact friction Hessian in the retry too; with 0.5 they converge.  In every step (not only the
retry) it slowed sliding scenes (a sphere 12 -> 25, a swing 20 -> 56 iterations at most) and failed two."""


def _euler_step(model: ClothModel, state: ClothState, dt: float, option: Projection, linear: LinearSolver,
                ctl: Controls, depth: int, retry: bool = False) -> tuple[ClothState, SolveInfo]:
    """:func:`implicit_euler_step` after validation (recursive halving).  With ``retry`` (the whole step) and halvings
    allowed (``depth > 0``: ``max_substep_depth=0`` asks for one solve), a solve with the exact Hessian that stops
    for :data:`RETRIED_STOPS` is followed by one with the per-stencil clamped projection (IPC's) before the
    halving: near a saddle of the contact potential (sheets stacked vertex above vertex,
    whose upper layer slides off its place) the exact Newton iterates wander with decrements of 1e-8 J and the
    halves fare no better, where the projected model descends (four 15 x 15 sheets hitting a floor at 3 m/s: no
    convergence in 162 iterations and 30 s, the time limit; retried: converged).  The retry's friction Hessians keep
    :data:`RETRY_FRICTION_SLIP` of the slip curvature; it is begun whatever the time taken so far (a retry left
    out on a busy machine and run on an idle one would make a step's result depend on the machine's load: the
    time limit alone cuts it, as any solve), and a callback or time-limit stop in it ends the step.  It starts over from the step's
    start, or, where the exact solve stopped (iterations, line search) while still converging (:func:`_still_converging`)
    and no body moves, goes on from that solve's best state (four 13 x 13 float32 sheets hitting a mesh floor at 3 m/s: the
    exact solve stopped at 0.006 N on its way down from 5 N; started over, the retry walked the same path to the same
    place, and the halves failed; continued, it converged in 15 iterations)."""
    t0 = time.perf_counter()
    poses = [(t, t.pose()) for t in model.terms]
    moving = any(t.pending_move() for t in model.terms)
    new, info = _euler_solve(model, state, dt, option, linear, ctl)
    if retry and depth > 0 and not info.converged and option is Projection.NONE and info.stop_reason in RETRIED_STOPS:
        after = [(t, t.pose()) for t in model.terms]
        for t, p in poses:  # the retry starts from the bodies' poses (pending moves, kappa) of the step's start
            t.restore_pose(p)
        # a solve cut off while converging goes on from its best state (the terms as they were there: kappa), no
        # body moving; else the retry starts over
        go_on = not moving and _still_converging(info)
        new2, info2 = _euler_solve(model, state, dt, Projection.CLAMP, linear, ctl, RETRY_FRICTION_SLIP,
                                   start=(new.x, after) if go_on else None)
        if info2.converged or info2.residual < info.residual:  # the better of the two (a converged one first)
            stopped = info.stop_reason
            new, info = new2, _aggregate([info, info2], info2)
            info.message = f"{info2.message}; with the clamped projection, after the exact Hessian's solve ({stopped})"
            info.phase = "clamped"
        else:
            for t, p in after:  # the exact solve's state is kept: its bodies and kappa too
                t.restore_pose(p)
            info = _aggregate([info, info2], info)
            if info2.stop_reason in ("time_limit", "callback"):
                info.stop_reason = info2.stop_reason
                info.message += f"; the clamped retry stopped: {info2.message}"
    if info.converged or depth <= 0 or info.stop_reason in ("time_limit", "callback", "body_move"):
        info.substeps, info.seconds = 1, time.perf_counter() - t0  # (a body's move the cloth cannot make way for
        return new, info  # stops the same in a half step)
    after = [(t, t.pose()) for t in model.terms]  # the bodies where the full step left them
    for t, p in poses:  # the halves start from the bodies' poses (and pending moves) of the full step
        t.restore_pose(p)
    mid, info1 = _euler_step(model, state, dt / 2, option, linear, ctl, depth - 1)
    if not info1.converged:  # the full step's best state is the one at the end of the step, its bodies' poses too
        for t, p in after:
            t.restore_pose(p)
        out = _aggregate([info, info1], info)
        out.substeps, out.seconds = 1, time.perf_counter() - t0
        if info1.stop_reason in ("time_limit", "callback"):
            out.stop_reason = info1.stop_reason
        out.message = _substep_failure(out, "the full step")
        return new, out
    end, info2 = _euler_step(model, mid, dt / 2, option, linear, ctl, depth - 1)
    out = _aggregate([info, info1, info2], info2)
    out.substeps = info1.substeps + info2.substeps
    out.seconds = time.perf_counter() - t0
    out.energy_history = info1.energy_history + info2.energy_history
    n1 = len(info1.energy_history)
    out.adapted_at = info1.adapted_at + [n1] + [n1 + i for i in info2.adapted_at]
    out.residual_history = info1.residual_history + info2.residual_history
    if not info2.converged:
        out.message = _substep_failure(out, "the second half step")
        out.phase = "substeps"
        return end, out
    out.message = f"converged in {out.substeps} substeps ({info2.message})"
    out.phase = "substeps"
    return end, out


def _substep_failure(info: SolveInfo, which: str) -> str:
    return (f"no convergence: {info.iterations} Newton iterations in {info.solves} solves (substeps); returned the "
            f"best state of {which} (stop reason {info.stop_reason!r}, residual {info.residual:.3e} N, tolerance "
            f"{info.tolerance:.3e} N)")


MOVE_RESOLUTION = 256
"""A moving body does not close in on the cloth below this many epsilons of the dtype times the coordinates' scale
(the cloth's and the moving bodies' largest coordinate; :func:`_move_bodies`): a body placed along its move is
rounded to the dtype, by about an epsilon of its coordinates, and nearer than that the rounding alone can put it
through the cloth (a float32 box pushed into a pinned sheet crept to 2e-9 m of it at 0.15 m coordinates, and its next
placement crossed the sheet).  An advance that would take the gap below it, and lower, is taken back and the move
stops there; a body that moves away from the cloth goes on."""


def _move_floor(x: Tensor, movers: list) -> float:
    """The smallest gap [m] a moving body may close in to on the cloth at ``x`` (:data:`MOVE_RESOLUTION`)."""
    scale = float(x.detach().abs().max()) if x.numel() else 0.0
    for t in movers:  # a body's own coordinates (its vertices now and at its move's end), where it has them
        for v in (getattr(t, "vertices", None), getattr(t, "_target", None)):
            if isinstance(v, Tensor) and v.numel():
                scale = max(scale, float(v.detach().abs().max()))
    return MOVE_RESOLUTION * torch.finfo(x.dtype).eps * scale


def _move_stop(alpha: float, made: list, s: float, advances: int, stages: int, ctl: Controls) -> str:
    """Why a body's move stops short of its end (:func:`_move_bodies`), or ""."""
    if alpha <= 1e-12 or (len(made) > 8 and s - made[-9] < 1e-3 * (1.0 - made[-9])):  # eight solves made no way
        return "the cloth cannot make way (caught between the body and a pinned vertex or another body?)"
    if advances >= MAX_MOVE_ADVANCES or stages >= MAX_MOVE_STAGES:
        return (f"the move needs more than {MAX_MOVE_STAGES} solves or {MAX_MOVE_ADVANCES} advances (each as far "
                f"as the step bound allows): move the body less per step (a smaller dt)")
    if ctl.deadline is not None and time.perf_counter() > ctl.deadline:
        return f"the time limit of {ctl.time_limit} s was reached"
    return ""


def _move_bodies(model: ClothModel, x_n: Tensor, movers: list, ctx: StepContext, option: Projection,
                 linear: LinearSolver, ctl: Controls) -> tuple[Tensor, list, float, str]:
    """The bodies' moves of a step (:func:`implicit_euler_step`): ``(x, the stages' infos, the fraction of the moves
    made, why they stopped short or "")``.  The bodies advance along their moves as far as the step bound against
    the cloth at ``x`` allows, again and again; where an advance has brought a body within its activation distance of the cloth and closed at
    least half the gap since the last solve, the cloth is solved there (a stage), so that it makes way; an adaptive
    barrier stiffness doubles before a stage whose advance closed the gap below its fraction of ``dhat``, as at an
    iterate of a solve that did (:meth:`~torchbend.SelfContact.adapt`).  A body that
    slides past the cloth, or away from it, takes no solve.  A body does not close in on the cloth nearer than its
    dtype resolves (:data:`MOVE_RESOLUTION`): the advance is taken back and the move stops.  The bodies end at the fraction made (their new poses
    unless stuck); a start invalid at their last poses jumps to the new ones (the step's solve judges it there)."""
    x, infos, s, stuck = x_n, [], 0.0, ""
    if movers and any(t.inadmissible(x_n) for t in movers):
        for t in movers:
            t.place(1.0)
        movers = []
    stage_ctl = replace(ctl, max_iters=4 * ctl.max_iters, check_minimum=False, callback=None)  # a stage converges
    gap, advances, made = min((t.move_gap(x) for t in movers), default=math.inf), 0, [0.0]
    now = gap  # the gap at the bodies' poses now (gap: at the last solve)
    floor = _move_floor(x_n, movers)
    while movers:
        alpha = min(t.move_bound(x) for t in movers)
        if alpha >= 1.0:
            break
        stuck = _move_stop(alpha, made, s, advances, len(infos), ctl)
        if stuck:
            break
        before, s_before = now, s
        s += alpha * (1.0 - s)
        advances += 1
        for t in movers:
            t.place(s)
        now = min(t.move_gap(x) for t in movers)
        if now < floor and now < before:  # closing in below what the dtype resolves: taken back (MOVE_RESOLUTION)
            closer, s, now = now, s_before, before
            for t in movers:
                t.place(s)
            stuck = (f"the cloth cannot make way: the body's next advance would take it to {max(closer, 0.0):.3g} m of "
                     f"the cloth, below the {floor:.3g} m its dtype resolves at these coordinates (caught between the "
                     "body and a pinned vertex or another body? float64 resolves smaller gaps)")
            break
        if now < 0.5 * gap:
            # the advance closed in on the cloth as an iterate that does: an adaptive kappa doubles where the gap is
            # below its fraction of dhat (SelfContact.adapt), or a cloth pressed by the body creeps to the dtype's floor
            grown = sum(bool(t.adapt(x, ctx)) for t in movers)
            x, info = _newton(model, x, option=option, linear=linear, ctx=ctx, **stage_ctl.newton_kw())
            info.adaptations += grown
            infos.append(info)
            made.append(s)
            gap = now = min(t.move_gap(x) for t in movers)
    if movers and not stuck:
        s = 1.0
        for t in movers:
            t.place(1.0)
    return x, infos, s, stuck


def _euler_solve(model: ClothModel, state: ClothState, dt: float, option: Projection, linear: LinearSolver,
                 ctl: Controls, friction_slip: float = 0.0,
                 start: tuple[Tensor, list] | None = None) -> tuple[ClothState, SolveInfo]:
    """One Newton solve of a step: the converged or best state, with ``v = (x - x_n)/dt`` (``friction_slip``: the
    step context's, :class:`~torchbend.sim.terms.StepContext`).  ``start = (x, poses)``: Newton starts at ``x``, an
    earlier solve's best state of this step (no body moving), with the terms' poses (kappa) of that solve there,
    set once the step's context is made, instead of at ``x_hat`` or the step bound's point."""
    x_n, v_n = state.x, state.v
    pinned = model.pinned.to(x_n.device)[:, None]
    v_n = torch.where(pinned, torch.zeros_like(v_n), v_n)
    movers = [t for t in model.terms if t.pending_move()]
    for t in movers:  # the lagged data (friction frames) at the step's start: the bodies at their last poses
        t.place(0.0)
    # the terms' lagged data (e.g. viscous hinge angles)
    ctx = StepContext.for_step(model.terms, x_n, v_n, dt, friction_slip)
    x_hat = ctx.x_hat
    assert x_hat is not None
    x, infos, s, stuck = _move_bodies(model, x_n, movers, ctx, option, linear, ctl)
    if start is not None:
        assert not movers, "a solve continued from an earlier one's state has no body to move"
        x = start[0]
        for t, p in start[1]:
            t.restore_pose(p)
    elif not infos:  # Newton starts at x_hat, or where a term's step bound (a collider's) stops it on the segment
        x = x_n + model.max_step(x_n, x_hat - x_n, ctx) * (x_hat - x_n)  # x_n -> x_hat (never through a collider)
    x, info = _newton(model, x, option=option, linear=linear, ctx=ctx, **ctl.newton_kw())  # (else: the last stage's)
    if info.stop_reason == "non_finite" and info.iterations == 0 and not infos and start is None:
        # the start on the segment rounded to a state the potential cannot evaluate (a contact at distance 0): that
        # state is no answer; Newton starts over from x_n, the step's valid start
        x, info = _newton(model, x_n, option=option, linear=linear, ctx=ctx, **ctl.newton_kw())
    for t in movers:
        t.settle()
    if infos or stuck:
        info = _aggregate(infos + [info], info)
        info.message += f" (a body's move in {len(infos) + 1} stages)"
        if stuck:
            info.converged = False
            info.stop_reason = "body_move"
            info.message = (f"a body's move stopped at {s:.3g} of the way after {len(infos)} stages: {stuck}; the "
                            f"body stays at the pose reached and the state is the solve there")
    v = torch.where(pinned, torch.zeros_like(v_n), (x - x_n) / dt)
    return ClothState(x=x, v=v), info
