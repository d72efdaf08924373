r"""The solvers' options as objects: :class:`LinearSolver` (how a Newton direction is solved) and
:class:`NewtonOptions` (everything else a solve is controlled by), accepted by
:func:`~torchbend.solve_static`, :func:`~torchbend.implicit_euler_step` and
:func:`~torchbend.solve_static_adjoint` as ``options=``; the config's ``solver`` section maps to them one to
one (:mod:`torchbend.scenes.schema`).

A solver's keyword arguments (``tol=``, ``projection=``, ...) override the fields of ``options``; a field
left ``None`` takes the solver's own default (``tol``: ``1e-9`` for a static solve, ``1e-6`` for a step;
``max_iters``: 50 / 100; ``check_minimum``: True / False).  Every value is validated where it is given: a
``ValueError`` names the field.
"""
from __future__ import annotations

import operator
import time
from dataclasses import dataclass, field, fields, replace
from typing import Any, Callable, ClassVar

from .._checks import positive
from ..options import Option, Projection, projection_argument
from .linear import Preconditioner

__all__ = ["Factorization", "LinearMethod", "LinearSolver", "NewtonOptions", "SOLVER_PROJECTIONS"]


def int_at_least(value, name: str, minimum: int) -> int:
    """``value`` as an ``int >= minimum`` (a bool or a float is a ``ValueError`` naming ``name``)."""
    if isinstance(value, bool):
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}") from None
    if v < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {v}")
    return v


def positive_value(value, name: str) -> float:
    """``value`` as a positive finite float (``ValueError`` naming ``name`` otherwise)."""
    try:
        return positive(value, name)
    except TypeError:
        raise ValueError(f"{name} must be positive and finite, got {value!r}") from None


class Factorization(Option):
    """The sparse factorisation of ``linear_solver="direct"``: ``"auto"`` (PARDISO when MKL is installed,
    else SuperLU), ``"ldlt"`` (MKL PARDISO's supernodal ``L D L^T``, symbolic analysis once per pattern;
    needs ``mkl``), ``"lu"`` (SciPy's SuperLU in symmetric mode)."""

    __label__ = "factorization"

    AUTO = "auto"
    LDLT = "ldlt"
    LU = "lu"


class LinearMethod(Option):
    """How Newton directions are solved: sparse direct factorisation or matrix-free CG."""

    __label__ = "linear_solver"

    DIRECT = "direct"
    CG = "cg"


REUSE_MIN_UNKNOWNS = 15_000
"""``reuse_factorization="auto"``: the free unknowns from which a direct solve first tries CG preconditioned with
a single-precision factorisation (a 71x71 cloth; benchmarks/bm_scale.py: at 81x81 steps take 25% less time with
it, at 41x41 about 10%, within the noise)."""

REUSE_CG_ITERS = 8
"""CG iterations a reused factorisation gets before the matrix is factorised anew."""


@dataclass(frozen=True)
class LinearSolver:
    """The linear solves of the Newton directions, ``linear_solver=`` of :func:`~torchbend.solve_static`,
    :func:`~torchbend.implicit_euler_step` and :func:`~torchbend.solve_static_adjoint` (a string is the ``method``):

    * ``method``: ``"direct"`` (sparse factorisation on the CPU) or ``"cg"`` (truncated preconditioned CG on
      the positions' device);
    * ``preconditioner`` (CG): ``"auto"`` (the incomplete ``L |D| L^T`` factorisation on the CPU,
      block-Jacobi elsewhere), ``"block_jacobi"``, ``"ilu"`` or ``"amg"`` (needs ``pyamg``);
    * ``factorization`` (direct): ``"auto"`` (default: MKL PARDISO's supernodal ``L D L^T`` when ``mkl`` is
      installed, ``pip install torchbend[solvers]``, else SciPy's SuperLU), ``"ldlt"`` or ``"lu"``
      (see :class:`Factorization`);
    * ``cholesky`` (direct): try a sparse Cholesky first (needs ``cholespy``; the factorisation above when it fails);
    * ``max_cg_iters`` (CG): iterations per direction at most (``None``: ``min(2 n, max(100, 20 sqrt(n)))``).
    * ``reuse_factorization`` (direct, PARDISO): solve a Newton system by CG (in float64) preconditioned with
      a single-precision factorisation: the last one (of an earlier iterate's matrix, or the previous time
      step's), else a new one of this matrix; when neither reaches the forcing tolerance within
      :data:`REUSE_CG_ITERS` iterations (or the matrix is not positive definite), the double-precision
      factorisation decides as without it.  ``"auto"`` (default) does so from :data:`REUSE_MIN_UNKNOWNS` free
      unknowns on (where a factorisation costs 10x and more a triangular solve), ``True`` always,
      ``False`` never.  The directions are Newton's to the forcing tolerance; the stopping test is the same.

    ``tb.LinearSolver("cg", preconditioner="amg")``; invalid values are a ``ValueError`` naming the field."""

    method: LinearMethod | str = "direct"
    preconditioner: Preconditioner | str = "auto"
    cholesky: bool = False
    max_cg_iters: int | None = None
    factorization: Factorization | str = "auto"
    reuse_factorization: bool | str = "auto"

    DIRECT: ClassVar[LinearMethod] = LinearMethod.DIRECT
    CG: ClassVar[LinearMethod] = LinearMethod.CG

    def __post_init__(self):
        object.__setattr__(self, "method", LinearMethod.parse(self.method))
        object.__setattr__(self, "preconditioner", Preconditioner.parse(self.preconditioner))
        object.__setattr__(self, "factorization", Factorization.parse(self.factorization))
        if not isinstance(self.cholesky, bool):
            raise ValueError(f"LinearSolver: cholesky must be True or False, got {self.cholesky!r}")
        if self.max_cg_iters is not None:
            object.__setattr__(self, "max_cg_iters", int_at_least(self.max_cg_iters, "LinearSolver: max_cg_iters", 1))
        if not (isinstance(self.reuse_factorization, bool) or self.reuse_factorization == "auto"):
            raise ValueError(f"LinearSolver: reuse_factorization must be 'auto', True or False, "
                             f"got {self.reuse_factorization!r}")

    def reuses_factorization(self, unknowns: int) -> bool:
        """Whether a direct solve of ``unknowns`` free DOFs tries the last factorisation first."""
        if self.reuse_factorization == "auto":
            return unknowns >= REUSE_MIN_UNKNOWNS
        return bool(self.reuse_factorization)

    @classmethod
    def parse(cls, value) -> LinearSolver:
        """A :class:`LinearSolver` from one, or from a method name (``"direct"``, ``"cg"``)."""
        if isinstance(value, LinearSolver):
            return value
        return cls(method=value)

    @property
    def is_direct(self) -> bool:
        return self.method is LinearMethod.DIRECT


SOLVER_PROJECTIONS = frozenset({Projection.NONE, Projection.CLAMP, Projection.ABS, Projection.GAUSS_NEWTON,
                                Projection.REDUCED})
"""``projection=`` options of the solvers (``"exact"`` is ``none``): the bending projection; membranes get
the nearest one they support (:meth:`Projection.restricted`), colliders drop their curvature term."""

CONTINUATIONS = ("auto", "membrane", "relaxation")


def continuation_mode(continuation) -> str | None:
    """``continuation`` as ``"auto"``, ``"membrane"``, ``"relaxation"`` or None (Newton only)."""
    if continuation is None or continuation is False:
        return None
    if continuation is True:
        return "auto"
    if continuation in CONTINUATIONS:
        return continuation
    raise ValueError(f"continuation must be 'auto', 'membrane', 'relaxation', True, False or None, got {continuation!r}")


@dataclass(frozen=True, kw_only=True)
class NewtonOptions:
    """The controls of a Newton solve, ``options=`` of :func:`~torchbend.solve_static`,
    :func:`~torchbend.implicit_euler_step` and :func:`~torchbend.solve_static_adjoint`.

    * ``projection``: the Newton matrix, a :class:`~torchbend.options.Projection` (``"exact"``, ``"clamp"``,
      ``"abs"``, ``"gauss_newton"``, ``"reduced"``);
    * ``linear_solver``: a :class:`LinearSolver` or its method name (``"direct"``, ``"cg"``);
    * ``tol`` (> 0), ``max_iters`` (int >= 0), ``check_minimum``: ``None`` takes the solver's default
      (static: ``1e-9``, 50, True; a time step: ``1e-6``, 100, False);
    * ``time_limit`` [s] (> 0, ``"auto"`` or None): the wall-time bound of a whole call, after which the best
      state is returned with ``stop_reason="time_limit"``; ``"auto"`` (default) is :data:`DEFAULT_TIME_LIMITS`
      (a static solve 120 s, a time step 30 s), None lifts it;
    * ``damping``: Levenberg-Marquardt damping by the lumped masses, vanishing at convergence
      (:mod:`torchbend.sim.damping`; default True: it bounds the steps along the soft modes of a hanging
      garment, benchmarks/garments.py, and in a time step the steps that overshoot, as along a sliding friction
      pair; False: plain Newton);
    * ``continuation`` (static solves): ``"auto"``, ``"membrane"``, ``"relaxation"``, True (= ``"auto"``),
      False/None; ``max_relax_steps`` (int >= 0): the pseudo-transient steps at most;
    * ``max_substep_depth`` (time steps, int >= 0): halvings of a failed step at most; above 0 an exact-Hessian
      step that stops is first solved again with the clamped projection (``SolveInfo.phase`` ``"clamped"``), from
      the stopped solve's best state where that solve was still converging and no body moves.

    ``tb.NewtonOptions(projection="gauss_newton", linear_solver=tb.LinearSolver("cg"), tol=1e-8)``;
    :meth:`replace` gives a copy with some fields changed.  Invalid values are a ``ValueError`` naming the
    field."""

    projection: Projection | str = Projection.NONE
    linear_solver: LinearSolver | str = "direct"
    tol: float | None = None
    max_iters: int | None = None
    check_minimum: bool | None = None
    time_limit: float | str | None = "auto"
    damping: bool = True
    continuation: bool | str | None = "auto"
    max_relax_steps: int = 200
    max_substep_depth: int = 3

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "projection", Projection.parse(self.projection, what="projection", supported=SOLVER_PROJECTIONS))
        set_(self, "linear_solver", LinearSolver.parse(self.linear_solver))
        if self.tol is not None:
            set_(self, "tol", positive_value(self.tol, "tol"))
        if self.max_iters is not None:
            set_(self, "max_iters", int_at_least(self.max_iters, "max_iters", 0))
        if self.check_minimum is not None and not isinstance(self.check_minimum, bool):
            raise ValueError(f"check_minimum must be True, False or None, got {self.check_minimum!r}")
        if isinstance(self.time_limit, str) and self.time_limit != "auto":
            raise ValueError(f"time_limit must be a positive number of seconds, 'auto' or None, got {self.time_limit!r}")
        if self.time_limit is not None and self.time_limit != "auto":
            set_(self, "time_limit", positive_value(self.time_limit, "time_limit"))
        if not isinstance(self.damping, bool):
            raise ValueError(f"damping must be True or False, got {self.damping!r}")
        continuation_mode(self.continuation)
        set_(self, "max_relax_steps", int_at_least(self.max_relax_steps, "max_relax_steps", 0))
        set_(self, "max_substep_depth", int_at_least(self.max_substep_depth, "max_substep_depth", 0))

    def replace(self, **changes) -> NewtonOptions:
        """A copy with ``changes`` (validated as in the constructor)."""
        return replace(self, **changes)

    @property
    def linear(self) -> LinearSolver:
        """:attr:`linear_solver` (always a :class:`LinearSolver` after construction)."""
        assert isinstance(self.linear_solver, LinearSolver)
        return self.linear_solver

    @property
    def option(self) -> Projection:
        """:attr:`projection` (always a :class:`~torchbend.options.Projection` after construction)."""
        assert isinstance(self.projection, Projection)
        return self.projection


class _Unset:
    """The default of a solver keyword that was not given (``None`` is a value: ``continuation=None``)."""

    def __repr__(self) -> str:
        return "<default>"


UNSET: Any = _Unset()
"""The default of every solver keyword: the value of ``options`` (or the solver's default) applies."""

_FIELDS = tuple(f.name for f in fields(NewtonOptions))


@dataclass
class Controls:
    """The validated controls shared by every sub-solve of a public call."""

    tol: float
    max_iters: int
    time_limit: float | None
    deadline: float | None
    callback: Callable | None
    check_minimum: bool
    damping: bool = True
    started: float = field(default_factory=time.perf_counter)
    """When the public call began (``time.perf_counter()``): its progress lines go out at INFO after 5 s."""

    def newton_kw(self) -> dict[str, Any]:
        return {"tol": self.tol, "max_iters": self.max_iters, "callback": self.callback, "deadline": self.deadline,
                "time_limit": self.time_limit, "check_minimum": self.check_minimum, "damping": self.damping,
                "started": self.started}


DEFAULT_TIME_LIMITS = {"static": 120.0, "step": 30.0}
"""The wall-time bound [s] of a call with ``time_limit="auto"``: a static solve, a time step."""

_DEFAULTS = {"static": {"tol": 1e-9, "max_iters": 50, "check_minimum": True},
             "step": {"tol": 1e-6, "max_iters": 100, "check_minimum": False}}
"""A time step's 100 iterations (30, then 60 before): a contact-rich impact may need 30-60 before its iterates settle
(two sheets stacked vertex above vertex hitting a floor at 3 m/s: 43 and 53 in its first two steps), and 30 failed
such a step and halved it, several times over (configs/pile.yaml with six sheets twisted by 90 degrees dropped
from 0.1 m: 2 of 20 steps failed, 311 iterations and 19 s; with 60 every step converged, 157 iterations, 9 s).  Ten
sheets twisted by 36 degrees falling at 3 m/s onto a sphere mesh take 56-93 a step: with 60 the third step failed
(300 iterations in five solves, the clamped retry and the halves no better), with 100 every step converges."""


def resolve_options(options, where: str, kind: str, *, hessian=UNSET, max_cg_iters=UNSET, callback=None,
                    **given) -> tuple[NewtonOptions, Controls]:
    """The :class:`NewtonOptions` of a solver call (``options`` with the keywords ``given`` that are not
    :data:`UNSET`; ``hessian=``: the deprecated alias of ``projection=``; ``max_cg_iters=`` replaces the
    linear solver's bound) with the solver's defaults (``kind``: ``"static"`` or ``"step"``) filled in, and
    the :class:`Controls` of the call (its deadline starts now)."""
    if options is None:
        options = NewtonOptions()
    elif not isinstance(options, NewtonOptions):
        raise ValueError(f"{where}: options must be a torchbend.NewtonOptions, got {type(options).__name__}")
    changes = {k: v for k, v in given.items() if v is not UNSET}
    unknown = set(changes) - set(_FIELDS)
    assert not unknown, unknown
    if hessian is not UNSET and hessian is not None:
        changes["projection"] = projection_argument(changes.get("projection"), hessian, where, old="hessian")
    if "tol" in changes and changes["tol"] is None:
        raise ValueError("tol must be positive and finite, got None")
    if "max_iters" in changes and changes["max_iters"] is None:
        raise ValueError("max_iters must be an int >= 0, got None")
    opts = options.replace(**changes) if changes else options
    if max_cg_iters is not UNSET and max_cg_iters is not None:
        opts = opts.replace(linear_solver=replace(opts.linear, max_cg_iters=int_at_least(max_cg_iters, "max_cg_iters", 1)))
    defaults = _DEFAULTS[kind]
    filled = {k: v for k, v in defaults.items() if getattr(opts, k) is None}
    if filled:
        opts = opts.replace(**filled)
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable or None, got {type(callback).__name__}")
    assert opts.tol is not None and opts.max_iters is not None and opts.check_minimum is not None
    time_limit = DEFAULT_TIME_LIMITS[kind] if opts.time_limit == "auto" else opts.time_limit
    assert time_limit is None or isinstance(time_limit, float)
    deadline = None if time_limit is None else time.perf_counter() + time_limit
    ctl = Controls(opts.tol, opts.max_iters, time_limit, deadline, callback, opts.check_minimum, opts.damping)
    return opts, ctl
