r"""Energy terms of a cloth potential: the protocol the solvers iterate (:class:`EnergyTerm`), what a
time step gives every term (:class:`StepContext`), and the built-in terms.

A potential over positions ``x (V, 3)`` [m] is a sum of terms.  The solvers (:func:`~torchbend.solve_static`,
:func:`~torchbend.implicit_euler_step`, :func:`~torchbend.solve_static_adjoint`) and
:class:`~torchbend.ClothModel` only call the methods below, so a term of one's own plugs into all of them:

========================================  ===================================================================
``energy(x, ctx)``                        the term's energy [J], a 0-d tensor (required)
``gradient(x, ctx)``                      ``dE/dx (V, 3)`` [N]; default: autograd of ``energy``
``hvp(x, v, ctx, projection=None)``       ``H v (V, 3)``; default: double backward of ``energy`` (exact)
``hessian(x, ctx, projection=None)``      ``(3V, 3V)`` torch sparse matrix [N/m]; default: from ``vertex_blocks``
``vertex_blocks(x, ctx, projection)``     optional: ``(V, 3, 3)`` when the Hessian is block diagonal per vertex
``max_step(x, dx, ctx)``                  the largest safe fraction of a step ``dx`` in ``(0, 1]``; default 1
``inadmissible(x)``                       why a solve cannot start at ``x`` (e.g. inside a barrier), or ""
``contact_stats(x)``                      ``(min distance [m], contacts)`` of a contact term (default ``(inf, 0)``)
``begin_step(ctx)``                       stores lagged data of a time step in ``ctx.lagged[name]``
``adapt(x, ctx, start=False)``            True when the term changed its energy at a step's iterate (default False)
``force_magnitudes(x, ctx)``              ``(V, 3)`` [N] magnitudes for the stopping test; default ``|gradient|``
========================================  ===================================================================

``projection`` is ``None`` (the exact Hessian) or a :class:`~torchbend.options.Projection`; a term that has no
projection of its own returns its exact Hessian for every one (a term whose Hessian may be indefinite should
project it, or the projected solvers lose their positive definite matrix).  ``name`` keys the term in
:meth:`ClothModel.energies <torchbend.ClothModel.energies>`; ``confines`` says whether the term can hold a cloth
that has no pinned vertex in place (a collider, a spring to fixed points: True, the default; gravity and the
elastic terms, which are translation invariant or linear: False); ``contact`` marks the terms that the ``contact=``
projection of :meth:`ClothModel.hessian <torchbend.ClothModel.hessian>` applies to; ``batched`` says that
:meth:`EnergyTerm.energy` takes a batch ``x (..., V, 3)`` to ``(...,)`` (the losses then evaluate a batch in
one call; default False: sample by sample).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import torch
from torch import Tensor

from ..energies.bending import BendingEnergy
from ..energies.colliders import Collider
from ..energies.friction import friction_blocks, friction_energy, friction_gradient
from ..energies.membrane import MEMBRANE_PROJECTIONS, MembraneEnergy
from ..options import Projection

__all__ = ["EnergyTerm", "StepContext", "BendingTerm", "MembraneTerm", "GravityTerm", "ColliderTerm", "InertiaTerm",
           "TermLoss", "as_csr", "contact_stats", "softens", "sparse_from_vertex_blocks"]


@dataclass
class StepContext:
    """What a time step gives every term: the start positions ``x_prev (V, 3)`` [m] and velocities
    ``v_prev (V, 3)`` [m/s], the step ``dt`` [s], the inertial target ``x_hat = x_prev + dt v_prev`` [m],
    and ``lagged``: per-term data of the step, keyed by term name (filled by :meth:`EnergyTerm.begin_step`,
    e.g. the previous hinge angles of a viscous bending term).  ``friction_slip``: the share of a sliding pair's
    curvature along its slip that friction Hessians keep (0: exact; :func:`torchbend.energies.friction.friction_blocks`;
    a step solved again after its exact solve stopped sets it).  A static solve uses ``StepContext()``."""

    x_prev: Tensor | None = None
    v_prev: Tensor | None = None
    dt: float | None = None
    x_hat: Tensor | None = None
    lagged: dict[str, Any] = field(default_factory=dict)
    friction_slip: float = 0.0

    @property
    def dynamic(self) -> bool:
        """Whether this is a time step (``dt`` given)."""
        return self.dt is not None

    @classmethod
    def for_step(cls, terms, x_prev: Tensor, v_prev: Tensor, dt: float, friction_slip: float = 0.0) -> StepContext:
        """The context of a step of ``dt`` [s] from ``(x_prev, v_prev)``, with every term's
        :meth:`~EnergyTerm.begin_step` called."""
        ctx = cls(x_prev=x_prev, v_prev=v_prev, dt=float(dt), x_hat=x_prev + dt * v_prev, friction_slip=friction_slip)
        for t in terms:
            t.begin_step(ctx)
        return ctx


def as_csr(H: Tensor) -> Tensor:
    """A term's Hessian as a torch sparse CSR matrix (from COO, CSR or a dense ``(3V, 3V)`` tensor)."""
    if H.layout == torch.sparse_csr:
        return H
    if H.layout == torch.sparse_coo:
        H = H.coalesce()
    return H.to_sparse_csr()


def sparse_from_vertex_blocks(blocks: Tensor) -> Tensor:
    """The ``(3V, 3V)`` torch sparse CSR matrix with the ``(V, 3, 3)`` ``blocks`` on its diagonal."""
    import warnings

    V = blocks.shape[0]
    dev = blocks.device
    cols = (3 * torch.arange(V, device=dev)[:, None, None] + torch.arange(3, device=dev)).expand(V, 3, 3)
    crow = torch.arange(0, 9 * V + 1, 3, device=dev)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, cols.reshape(-1), blocks.reshape(-1), size=(3 * V, 3 * V))


class EnergyTerm:
    """A term of the potential over positions ``x (V, 3)`` [m] (module docstring): :meth:`energy` [J],
    :meth:`gradient` ``(V, 3)`` [N], :meth:`hvp` ``(V, 3)`` [N], :meth:`hessian` a ``(3V, 3V)`` sparse matrix
    [N/m].  Subclass it and define :meth:`energy`, and for the
    solvers' exact second-order steps :meth:`hessian` or :meth:`vertex_blocks`; the other methods have
    defaults (autograd for the derivatives)."""

    name: str = "term"
    confines: bool = True
    contact: bool = False
    batched: bool = False

    def energy(self, x: Tensor, ctx: StepContext) -> Tensor:
        raise NotImplementedError(f"{type(self).__name__} must define energy(x, ctx)")

    def gradient(self, x: Tensor, ctx: StepContext) -> Tensor:
        with torch.enable_grad():
            y = x.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(self.energy(y, ctx), y)
        return g

    def hvp(self, x: Tensor, v: Tensor, ctx: StepContext, projection: Projection | None = None) -> Tensor:
        blocks = self.vertex_blocks(x, ctx, projection)
        if blocks is not None:
            return (blocks @ v[..., None])[..., 0]
        with torch.enable_grad():
            y = x.detach().requires_grad_(True)
            (g,) = torch.autograd.grad(self.energy(y, ctx), y, create_graph=True)
            (hv,) = torch.autograd.grad(g, y, v, allow_unused=True)
        return torch.zeros_like(x) if hv is None else hv

    def vertex_blocks(self, x: Tensor, ctx: StepContext, projection: Projection | None = None) -> Tensor | None:
        """``(V, 3, 3)`` [N/m] when the Hessian is block diagonal per vertex, else None (the default)."""
        return None

    def hessian(self, x: Tensor, ctx: StepContext, projection: Projection | None = None) -> Tensor:
        blocks = self.vertex_blocks(x, ctx, projection)
        if blocks is None:
            raise NotImplementedError(f"{type(self).__name__} ({self.name!r}) must define hessian(x, ctx, projection) "
                                      f"or vertex_blocks(x, ctx, projection) for the solvers")
        return sparse_from_vertex_blocks(blocks)

    def block_diagonal(self, x: Tensor, ctx: StepContext, projection: Projection | None = None) -> Tensor:
        """The ``(V, 3, 3)`` diagonal blocks of :meth:`hessian` [N/m] (block-Jacobi, round-off estimates)."""
        blocks = self.vertex_blocks(x, ctx, projection)
        if blocks is not None:
            return blocks
        H = self.hessian(x, ctx, projection).to_sparse_coo().coalesce()
        (r, c), val = H.indices(), H.values()
        keep = (r // 3) == (c // 3)
        out = x.new_zeros(x.shape[0] * 9)
        return out.index_add(0, 9 * (r[keep] // 3) + 3 * (r[keep] % 3) + c[keep] % 3, val[keep].to(x.dtype)).reshape(-1, 3, 3)

    def max_step(self, x: Tensor, dx: Tensor, ctx: StepContext) -> float:
        return 1.0

    def inadmissible(self, x: Tensor) -> str:
        """Why a solve cannot start at ``x (V, 3)`` (a state where the term is infinite), or "" (the default)."""
        return ""

    def contact_stats(self, x: Tensor) -> tuple[float, int]:
        """``(the smallest contact distance [m], the number of contacts)`` at ``x`` (:class:`SolveInfo
        <torchbend.SolveInfo>`'s ``min_distance`` and ``contact_count``); ``(inf, 0)`` for a term without contact."""
        return math.inf, 0

    def begin_step(self, ctx: StepContext) -> None:
        return None

    def adapt(self, x: Tensor, ctx: StepContext, start: bool = False) -> bool:
        """Called by a time step's Newton solves (not by static solves) at the first iterate ``x (V, 3)``
        (``start``) and at every accepted one: True when the term changed its energy there (a barrier stiffened),
        so that the solve evaluates the potential again and restarts its bookkeeping from ``x``; False (the
        default): unchanged."""
        return False

    def force_magnitudes(self, x: Tensor, ctx: StepContext) -> Tensor:
        return self.gradient(x, ctx).abs()

    def softened(self, factor: float) -> EnergyTerm | None:
        """The term with its stiffness scaled by ``factor`` for the stiffness homotopy of
        :func:`~torchbend.solve_static` (``continuation``), or None (the default): not part of it."""
        return None

    # ---- a body moved between time steps (MeshCollider): a step carries out the move in stages
    def pending_move(self) -> bool:
        """Whether the term's body was moved since the last time step (a step moves it from its pose of that step
        to the assigned one); False (the default) for a term without a body."""
        return False

    def place(self, s: float) -> None:
        """Put the body at the fraction ``s`` in ``[0, 1]`` of its pending move (0: the last step's pose)."""
        return None

    def move_bound(self, x: Tensor) -> float:
        """The fraction in ``[0, 1]`` of the rest of the pending move (from the body's pose now to the assigned
        one) that the cloth at ``x (V, 3)``, held still, leaves free of contact (a conservative bound); 1.0 by
        default."""
        return 1.0

    def move_gap(self, x: Tensor) -> float:
        """The smallest distance [m] between the body and the cloth at ``x`` where the body's contact acts on it
        (within its activation distance), else ``inf`` (the default)."""
        return math.inf

    def settle(self) -> None:
        """End the pending move at the body's pose now (the next step moves it from there)."""
        return None

    def pose(self) -> Any:
        """The term's state that a step solved again starts from (:meth:`restore_pose` puts it back: the clamped retry
        and the halves of a failed step): a body's pose and pending move, an adaptive contact stiffness."""
        return None

    def restore_pose(self, pose: Any) -> None:
        return None


def contact_stats(terms, x: Tensor) -> tuple[float, int]:
    """The smallest distance and the number of contacts over ``terms`` (:meth:`EnergyTerm.contact_stats`)."""
    best, count = math.inf, 0
    for t in terms:
        d, n = t.contact_stats(x)
        best, count = min(best, d), count + n
    return best, count


def softens(term: EnergyTerm) -> bool:
    """Whether ``term`` takes part in the stiffness homotopy (defines :meth:`EnergyTerm.softened`)."""
    return type(term).softened is not EnergyTerm.softened


def _projection(projection) -> Projection:
    return Projection.NONE if projection is None else Projection.parse(projection)


class BendingTerm(EnergyTerm):
    """A :class:`~torchbend.BendingEnergy` as a term; a viscous one lags the hinge angles of the start of
    each step (``ctx.lagged["bending"]``)."""

    contact = False
    confines = False
    batched = True

    def __init__(self, energy: BendingEnergy, name: str = "bending"):
        self.module, self.name = energy, name

    def _kw(self, ctx: StepContext) -> dict:
        return ctx.lagged.get(self.name, {}) if ctx.dynamic else {}

    def begin_step(self, ctx: StepContext) -> None:
        if self.module.damping is not None and ctx.x_prev is not None:
            ctx.lagged[self.name] = {"theta_prev": self.module.angles(ctx.x_prev).detach(), "dt": ctx.dt}

    def energy(self, x, ctx):
        return self.module(x, **self._kw(ctx))

    def gradient(self, x, ctx):
        return self.module.gradient(x, **self._kw(ctx))

    def hvp(self, x, v, ctx, projection=None):
        return self.module.hvp(x, v, projection=_projection(projection), **self._kw(ctx))

    def hessian(self, x, ctx, projection=None):
        return self.module.hessian(x, projection=_projection(projection), **self._kw(ctx))

    def block_diagonal(self, x, ctx, projection=None):
        Hb = self.module.hinge_hessians(x, projection=_projection(projection), **self._kw(ctx))
        Hb = Hb.unflatten(-1, (4, 3)).unflatten(-3, (4, 3))
        diag = torch.stack([Hb[:, k, :, k, :] for k in range(4)], 1)
        return x.new_zeros(x.shape[0], 3, 3).index_add(0, self.module.hinges.reshape(-1), diag.reshape(-1, 3, 3))


class MembraneTerm(EnergyTerm):
    """A :class:`~torchbend.MembraneEnergy` as a term (a projection it does not support is mapped to the
    nearest one it does)."""

    contact = False
    confines = False
    batched = True

    def __init__(self, energy: MembraneEnergy, name: str = "membrane"):
        self.module, self.name = energy, name

    def energy(self, x, ctx):
        return self.module(x)

    def gradient(self, x, ctx):
        return self.module.gradient(x)

    def hvp(self, x, v, ctx, projection=None):
        return self.module.hvp(x, v, projection=_projection(projection).restricted(MEMBRANE_PROJECTIONS))

    def hessian(self, x, ctx, projection=None):
        return self.module.hessian(x, projection=_projection(projection).restricted(MEMBRANE_PROJECTIONS))

    def softened(self, factor: float) -> MembraneTerm:
        """The membrane with its moduli scaled by ``factor`` (a copy: the user's module keeps its own)."""
        mem = copy.copy(self.module)
        mem._buffers = dict(mem._buffers)  # noqa: SLF001 - own buffer dict: the user's module keeps its moduli
        mem.mu = mem.mu * factor
        mem.lam = mem.lam * factor
        return MembraneTerm(mem, self.name)

    def block_diagonal(self, x, ctx, projection=None):
        p = _projection(projection).restricted(MEMBRANE_PROJECTIONS)
        He = self.module.element_hessians(x, projection=p).unflatten(-1, (3, 3)).unflatten(-3, (3, 3))
        diag = torch.stack([He[:, k, :, k, :] for k in range(3)], 1)  # (T, 3, 3, 3)
        return x.new_zeros(x.shape[0], 3, 3).index_add(0, self.module.faces.reshape(-1), diag.reshape(-1, 3, 3))


class GravityTerm(EnergyTerm):
    """``-sum_i m_i g . x_i`` [J] for lumped masses ``mass (V,)`` [kg] and ``gravity (3,)`` [m/s^2]."""

    contact = False
    confines = False
    batched = True

    def __init__(self, mass: Tensor, gravity: Tensor, name: str = "gravity"):
        self.mass, self.gravity, self.name = mass, gravity, name

    def force(self, dtype=None) -> Tensor:
        """``m_i g (V, 3)`` [N]."""
        return (self.mass[:, None] * self.gravity[None, :]).to(dtype or self.mass.dtype)

    def energy(self, x, ctx):
        return -(self.force(x.dtype).to(x.device) * x).sum((-1, -2))

    def gradient(self, x, ctx):
        return -self.force(x.dtype).clone()

    def vertex_blocks(self, x, ctx, projection=None):
        return x.new_zeros(x.shape[0], 3, 3)

    def force_magnitudes(self, x, ctx):
        return self.force(x.dtype).abs()


class ColliderTerm(EnergyTerm):
    """A collider (:class:`~torchbend.Sphere`, :class:`~torchbend.Plane`, :class:`~torchbend.Capsule`) as a
    term: per-vertex Hessian blocks (the curvature term dropped for every projection), and the continuous
    step bound with penetration ``depth`` [m].  With ``friction > 0`` a time step adds the lagged smooth
    friction of :mod:`~torchbend.energies.friction` (normals and contact forces taken at the step's start by
    :meth:`begin_step`); a static solve has none.

    ``owner = (model, i)``: the term is the model's collider ``i`` (:attr:`ClothModel.colliders
    <torchbend.ClothModel.colliders>`), read from the model on every use.  A collider there replaced between
    steps by a moved one of the same kind with the ipc law is a move (:meth:`pending_move`) that the next
    time step carries out in stages, as a :class:`~torchbend.MeshCollider`'s: the collider advances as far as
    its path bound against the cloth allows (:meth:`move_bound`), and the cloth is solved where it has come
    within ``margin``, so that the cloth makes way instead of starting inside.  The friction's slip is then
    relative to the surface's move (a moving sphere or capsule drags the cloth)."""

    contact = True
    confines = True
    batched = True

    def __init__(self, collider: Collider, depth: float | Callable[[], float], name: str = "collider",
                 owner: tuple | None = None):
        self._collider, self._depth, self.name, self._owner = collider, depth, name, owner

    @property
    def collider(self) -> Collider:
        """The collider (the owner model's collider ``i`` at its pose now, where the term has an owner)."""
        if self._owner is not None:
            model, i = self._owner
            if i < len(model.colliders):  # (a term kept past an assignment of fewer colliders keeps its own)
                return model.colliders[i]
        return self._collider

    # ---- a move between steps (the owner model's collider replaced by a moved one)
    def _move(self) -> tuple:
        return self._owner[0]._collider_move(self._owner[1]) if self._owner is not None else (None, None)

    def pending_move(self) -> bool:
        return self._move()[0] is not None

    def place(self, s: float) -> None:
        start, goal = self._move()
        if start is not None and self._owner is not None:
            model, i = self._owner
            model._set_collider(i, goal if s >= 1 else start._toward(goal, s), start, goal)

    def move_bound(self, x: Tensor) -> float:
        start, goal = self._move()
        if start is None or not x.shape[0]:
            return 1.0
        c = self.collider
        s = c._sd(x.detach())[0]
        rate = c._path_rate(goal, x.detach())
        moving = rate > 0
        if not bool(moving.any()):
            return 1.0
        return min(1.0, max(0.0, float((0.9 * s[moving] / rate[moving]).min())))

    def move_gap(self, x: Tensor) -> float:
        if not x.shape[0]:
            return math.inf
        c = self.collider
        d = float(c._sd(x.detach())[0].min())
        return d if c.margin is not None and d < c.margin else math.inf

    def settle(self) -> None:
        start, _ = self._move()
        if start is not None and self._owner is not None:
            model, i = self._owner
            model._set_collider(i, self.collider, None, None)

    def pose(self) -> Any:
        return None if self._owner is None else (*self._move(), self.collider)

    def restore_pose(self, pose: Any) -> None:
        if pose is not None and self._owner is not None:
            start, goal, current = pose
            model, i = self._owner
            model._set_collider(i, current, start, goal)

    @property
    def depth(self) -> float:
        """The penetration [m] a vertex may reach in one step (a callable given is evaluated on first use)."""
        return float(self._depth() if callable(self._depth) else self._depth)

    def begin_step(self, ctx):
        # friction (a time step only): the contact normals and force magnitudes at the step's start, lagged
        c = self.collider
        if c.friction > 0 and ctx.x_prev is not None and ctx.dt is not None and ctx.x_prev.ndim == 2:
            x_prev = ctx.x_prev.detach()
            s, n, _ = c._sd(x_prev)
            lam = c.contact.slope(c.margin - s)
            lam = torch.where(torch.isfinite(lam), lam, torch.zeros_like(lam))
            start, goal = self._move()
            if start is not None:  # the slip is relative to the surface's move over the step
                x_prev = x_prev + start._surface_motion(goal, x_prev)
            ctx.lagged[self.name] = {"x_prev": x_prev, "n": n, "weight": c.friction * lam, "eps": c.eps_v * ctx.dt}

    def _friction(self, x, ctx):
        f = ctx.lagged.get(self.name) if ctx is not None else None
        return f if f is not None and x.ndim == 2 else None

    def energy(self, x, ctx):
        e = self.collider.energy(x)
        f = self._friction(x, ctx)
        return e if f is None else e + friction_energy(x, f["x_prev"], f["n"], f["weight"], f["eps"])

    def gradient(self, x, ctx):
        g = self.collider.gradient(x)
        f = self._friction(x, ctx)
        return g if f is None else g + friction_gradient(x, f["x_prev"], f["n"], f["weight"], f["eps"])

    def vertex_blocks(self, x, ctx, projection=None):
        H = self.collider.hessian_blocks(x, projection=_projection(projection))
        f = self._friction(x, ctx)
        return H if f is None else H + friction_blocks(x, f["x_prev"], f["n"], f["weight"], f["eps"], ctx.friction_slip)

    def max_step(self, x, dx, ctx):
        return float(self.collider.max_step(x, dx, depth=self.depth).min()) if x.shape[0] else 1.0

    def contact_stats(self, x):
        if not x.shape[0]:
            return math.inf, 0
        c = self.collider
        s = c._sd(x.detach())[0]
        return float(s.min()), int((s < c.margin).sum())

    def inadmissible(self, x):
        c = self.collider
        if not c.contact.bounded or not x.shape[0]:
            return ""
        s = c._sd(x.detach())[0]
        i = int(torch.argmin(s))
        if float(s[i]) > 0:
            return ""
        return (f"{self.name}: vertex {i} is {-float(s[i]):.3g} m inside the {type(c).__name__} ({int((s <= 0).sum())} "
                f"vertices on or inside it); its {type(c.contact).__name__} contact is infinite there: start outside")


class InertiaTerm(EnergyTerm):
    """The inertia of an implicit-Euler step, ``sum_i m_i |x_i - x_hat_i|^2 / (2 dt^2)`` [J] (zero in a
    static context); its force magnitudes include the inertial force ``m_i v_prev_i / dt`` of the step's start."""

    contact = False
    confines = True

    def __init__(self, mass: Tensor, name: str = "inertia"):
        self.mass, self.name = mass, name

    def _w(self, x: Tensor, ctx: StepContext) -> Tensor:
        assert ctx.dt is not None
        return self.mass.to(device=x.device, dtype=x.dtype)[:, None] / (ctx.dt * ctx.dt)

    def energy(self, x, ctx):
        if not ctx.dynamic or ctx.x_hat is None:
            return x.new_zeros(())
        return 0.5 * (self._w(x, ctx) * (x - ctx.x_hat) ** 2).sum()

    def gradient(self, x, ctx):
        if not ctx.dynamic or ctx.x_hat is None:
            return torch.zeros_like(x)
        return self._w(x, ctx) * (x - ctx.x_hat)

    def vertex_blocks(self, x, ctx, projection=None):
        if not ctx.dynamic:
            return x.new_zeros(x.shape[0], 3, 3)
        return torch.diag_embed(self._w(x, ctx).expand(-1, 3))

    def force_magnitudes(self, x, ctx):
        out = self.gradient(x, ctx).abs()
        if ctx.dynamic and ctx.v_prev is not None:
            assert ctx.dt is not None
            out = out + (self.mass.to(device=x.device, dtype=x.dtype)[:, None] * ctx.v_prev / ctx.dt).abs()
        return out


class TermLoss(torch.nn.Module):
    """An :class:`EnergyTerm` as a loss module of :class:`~torchbend.ClothLoss`: positions ``x (..., V, 3)``
    [m] to per-sample energies ``(...,)`` [J], evaluated in the step context ``ctx`` (default static), so that
    training minimises the same term objects the solver does (:meth:`ClothModel.loss
    <torchbend.ClothModel.loss>`).  A term whose ``batched`` is True (the built-in bending, membrane, gravity and
    collider terms) takes a batch at once; other terms are evaluated sample by sample."""

    def __init__(self, term: EnergyTerm, ctx: StepContext | None = None):
        super().__init__()
        self.term, self.ctx = term, ctx or StepContext()

    def forward(self, x: Tensor) -> Tensor:
        if x.dim() == 2:
            return self.term.energy(x, self.ctx)
        batch = x.shape[:-2]
        if self.term.batched:
            return self.term.energy(x, self.ctx)
        flat = x.reshape(-1, *x.shape[-2:])
        if flat.shape[0] == 0:
            return x.new_zeros(batch)
        return torch.stack([self.term.energy(xi, self.ctx) for xi in flat]).reshape(batch)

    def extra_repr(self) -> str:
        return f"term={self.term.name!r} ({type(self.term).__name__})"

