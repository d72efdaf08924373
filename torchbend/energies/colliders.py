r"""Rigid colliders with a smooth one-sided contact potential (analytic gradient and Hessian).

Each collider has a signed distance ``s(x)`` (positive outside) and acts on every vertex closer than
``margin`` by a contact law of :mod:`torchbend.energies.contact`: ``law="ipc"``, the default, the log
barrier of Incremental Potential Contact, infinite on the surface, so that the cloth never touches it;
``"penalty"`` or ``"barrier"`` (with ``power``), which let a vertex sink into the collider::

    E = sum_i  phi(d_i),   d_i = margin - s(x_i)
    ipc:      phi = -k d^2 log(1 - d / margin)  [J],  k = stiffness [J/m^2],  margin = dhat (default 1 mm)
    penalty:  phi = k/2 max(0, d)^2             [J],  k = stiffness [N/m]    (default 1e4; margin default 0)

    grad_i = -phi'(d_i) grad s,          Hess_i = phi''(d_i) grad s grad s^T  -  phi'(d_i) Hess s

The ipc law's default ``stiffness=None`` is chosen by the :class:`~torchbend.ClothModel` the collider is
given to (:meth:`Collider.with_weight`): ten times the cloth's mean vertex weight is held at the gap
``margin / 2``, i.e. ``k = 10 m g / ((1/2 + ln 2) margin)``; a cloth resting on the collider then keeps a
gap of about ``0.8 margin``, a vertex pressed harder comes closer (the barrier's force grows without bound
as the gap closes), and a collider used on its own needs a ``stiffness``.  The ipc law is C2 where a vertex
comes within ``margin``, so the Newton model sees a contact before it is made (the penalty's curvature jumps
from 0 to ``k`` at the surface, which makes a damped Newton solve chatter on an active set).  A law that
lets a vertex inside (``penalty``, ``barrier``) is what the training losses need, where a network's
prediction may lie inside a body.

The colliders act on the cloth's vertices only: an edge between two vertices outside a sphere or capsule can cut
into it by its sagitta, ``l^2 / (8 R)`` for an edge of length ``l`` over a radius ``R`` (4 mm for 15 cm edges on a
0.7 m sphere); a :class:`~torchbend.MeshCollider` keeps the cloth's edges and triangles off the body's too.

``grad s`` is the unit contact normal.  For convex colliders ``Hess s`` is PSD, so the curvature
term ``-phi'(d) Hess s`` is negative semi-definite; every projection but ``none``
(:class:`~torchbend.options.Projection`) drops it.  Units: positions [m].

**Continuous step bound** (:meth:`Collider.max_step`, used by the solvers' line search against
tunnelling): the penalty is evaluated at points only, so a step may carry a vertex through a collider
unseen.  ``max_step(x, dx, depth=tau)`` gives per vertex the largest fraction ``alpha`` in ``(0, 1]``
of the step ``dx`` such that, on the whole segment ``x + t alpha dx`` (``t`` in ``[0, 1]``), the
vertex stays above its *allowed depth* ``D`` below the surface, with the safety fraction of IPC:
``alpha = min(1, safety * t*)``, ``t*`` the exact (closed-form) first time of impact of the ray with
the level set ``s = -D``.  The allowed depth is

    D = max(tau, 2 d),        d = max(0, -s(x))   (current depth below the surface)

and, for the sphere and the capsule, at most ``(R + d)/2`` (half way from the current depth to the
centre or the axis, ``R`` the radius): a vertex outside the surface may sink at most ``tau`` below it
in one step, one inside may at most double its depth (plus ``tau``) and never reaches the centre or
the axis, where the penalty's normal flips and a vertex would be pushed out through the far side.
For the ipc law (infinite on the surface) ``tau`` is zero: a step
carries no vertex beyond ``safety`` of the way to the surface.  For a penalty a zero ``tau`` is not
offered: a penalty acts only below ``s = margin``, and with ``margin = 0`` a vertex that may never
cross the surface never feels the collider, so the solver would stall above it.  The doubling lets a vertex reach any
equilibrium depth in a few steps while no step can tunnel.  Plane: a linear equation; sphere: a
quadratic; capsule: the union of an infinite-cylinder quadratic (hits whose axial coordinate lies on
the segment) and the two end-sphere quadratics, exact.  Roots use the cancellation-free form
``c / (-b + sqrt(b^2 - a c))``: no NaN for ``dx = 0``, tangent motion or a vertex on the surface.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from .._checks import nonnegative, positive, vec3
from ..options import Projection, projection_argument
from .contact import ContactLaw, contact_law

__all__ = ["Sphere", "Plane", "Capsule", "Collider"]


@dataclass(frozen=True, kw_only=True)
class Collider:
    """Base of the rigid colliders: a signed distance and the one-sided contact potential on it, with
    ``stiffness`` (> 0; [N/m] for the penalty, [J/m^p] for the barrier, [J/m^2] for ipc; None: 1e4 for the penalty
    and the barrier, chosen from the cloth's weight by a model for ipc), ``margin`` [m] (>= 0; ipc's activation
    distance, > 0; None: ``DEFAULT_MARGIN`` for ipc, 0 otherwise), ``law`` (``"ipc"``, the default, ``"penalty"`` or
    ``"barrier"``, :mod:`torchbend.energies.contact`), ``power`` (the barrier's, default 3), ``friction`` (the
    Coulomb coefficient ``mu`` >= 0 of time steps, lagged and smoothed below the sliding speed ``eps_v`` [m/s],
    :mod:`torchbend.energies.friction`) as keyword arguments of every collider."""

    stiffness: float | None = None
    margin: float | None = None
    law: str = "ipc"
    power: float | None = None
    friction: float = 0.0
    eps_v: float = 1e-3
    _contact: ClassVar[ContactLaw | None]  # set by _check_penalty (not a field)

    DEFAULT_MARGIN: ClassVar[float] = 1e-3
    """The ipc law's default activation distance ``margin`` [m]."""
    DEFAULT_STIFFNESS: ClassVar[float] = 1e4
    """The penalty's and the barrier's default stiffness ([N/m], [J/m^p])."""
    WEIGHT_FACTOR: ClassVar[float] = 10.0
    """The ipc law's chosen stiffness holds this many mean vertex weights at the gap ``margin / 2``."""

    def _check_penalty(self) -> None:
        """Validate (and store as floats) ``stiffness`` (> 0), ``margin`` (>= 0), ``law`` and ``power``; fill the
        law's defaults (an ipc stiffness None stays None until :meth:`with_weight`)."""
        name = type(self).__name__
        ipc = self.law == "ipc"
        margin = (self.DEFAULT_MARGIN if ipc else 0.0) if self.margin is None else self.margin
        object.__setattr__(self, "margin", nonnegative(margin, f"{name}.margin"))
        stiffness = self.stiffness
        if stiffness is None and not ipc:
            stiffness = self.DEFAULT_STIFFNESS
        if stiffness is not None:
            object.__setattr__(self, "stiffness", positive(stiffness, f"{name}.stiffness"))
        object.__setattr__(self, "friction", nonnegative(self.friction, f"{name}.friction"))
        object.__setattr__(self, "eps_v", positive(self.eps_v, f"{name}.eps_v"))
        try:  # the law is checked even before its stiffness is known
            law = contact_law(self.law, 1.0 if stiffness is None else stiffness, self.power, margin=self.margin)
        except ValueError as e:
            raise ValueError(f"{name}: {e}") from None
        object.__setattr__(self, "power", law.power)
        # built once: every energy, gradient and Hessian uses it
        object.__setattr__(self, "_contact", None if stiffness is None else law)

    @property
    def contact(self) -> ContactLaw:
        """The collider's contact law (:mod:`torchbend.energies.contact`); a ``ValueError`` for an ipc collider
        whose stiffness is still to be chosen by a model."""
        if self._contact is None:
            raise ValueError(f"{type(self).__name__}: stiffness=None: the ipc law's stiffness is chosen from the "
                             f"cloth's weight by the ClothModel the collider is given to (model.colliders holds the "
                             f"chosen one); give stiffness= [J/m^2] to use the collider on its own")
        return self._contact

    def stiffness_for(self, weight: float) -> float:
        """The ipc stiffness [J/m^2] that holds ``WEIGHT_FACTOR * weight`` [N] at the gap ``margin / 2``
        (``-phi'`` there is ``(1/2 + ln 2) k margin``)."""
        assert self.margin is not None
        return self.WEIGHT_FACTOR * weight / ((0.5 + math.log(2.0)) * self.margin)

    def with_weight(self, weight: float) -> Collider:
        """This collider, with its stiffness chosen for a mean vertex weight ``weight`` [N] (> 0) when it is None
        (the ipc law's default; :meth:`stiffness_for`), else itself."""
        if self.stiffness is not None:
            return self
        return self._replace(stiffness=self.stiffness_for(positive(weight, "weight")))

    def _replace(self, **changes) -> Collider:
        return dataclasses.replace(self, **changes)

    # ---- a move between time steps (a model's collider replaced by a moved one: ClothModel.colliders)
    _GEOMETRY: ClassVar[tuple[str, ...]] = ()  # the fields a move changes; the others must stay

    def _moves_to(self, goal: Collider) -> bool:
        """Whether replacing this collider by ``goal`` is a move a time step carries out in stages: the same
        kind with a bounded law (ipc: no cloth may start inside it), only its geometry changed."""
        if type(goal) is not type(self) or goal == self or self._contact is None or not self._contact.bounded:
            return False
        return all(getattr(self, f.name) == getattr(goal, f.name) for f in dataclasses.fields(self)
                   if f.name not in self._GEOMETRY)

    def _toward(self, goal: Collider, s: float) -> Collider:  # pragma: no cover - abstract
        """The collider a fraction ``s`` in ``[0, 1]`` of the way from this one to ``goal``."""
        raise NotImplementedError

    def _path_rate(self, goal: Collider, x: Tensor) -> Tensor:  # pragma: no cover - abstract
        """``(V,)``: how far the signed distance of ``x (V, 3)`` falls at most on the way to ``goal`` (a fraction
        ``s`` of the way: ``s`` times as far)."""
        raise NotImplementedError

    def _surface_motion(self, goal: Collider, x: Tensor) -> Tensor:
        """``(V, 3)``: the surface's move nearest ``x`` on the way to ``goal`` (the friction's slip is relative to it)."""
        return torch.zeros_like(x)

    def _sd(self, x: Tensor):  # pragma: no cover - abstract
        """``(s, n, curv)``: signed distance ``(V,)``, unit normal ``(V, 3)``, ``Hess s`` ``(V, 3, 3)`` or None."""
        raise NotImplementedError

    def depth(self, x: Tensor) -> Tensor:
        """Penetration depth ``margin - s(x)`` ``(V,)`` [m] (positive = inside the margin)."""
        assert self.margin is not None  # filled by the validation
        return self.margin - self._sd(x)[0]

    def signed_distance(self, x: Tensor) -> Tensor:
        """The signed distance ``s(x)`` [m] of ``x (..., 3)`` from the surface (positive outside): ``(...,)``."""
        return self._sd(x.reshape(-1, 3))[0].reshape(x.shape[:-1])

    def energy(self, x: Tensor) -> Tensor:
        """The contact energy [J] of ``x (..., V, 3)`` [m]: ``(...,)``."""
        d = self.margin - self._sd(x.reshape(-1, 3))[0]
        return self.contact.value(d).reshape(x.shape[:-1]).sum(-1)

    def gradient(self, x: Tensor) -> Tensor:
        """``dE/dx`` ``(..., V, 3)`` [N]."""
        s, n, _ = self._sd(x.reshape(-1, 3))
        return (-self.contact.slope(self.margin - s)[:, None] * n).reshape(x.shape)

    def max_step(self, x: Tensor, dx: Tensor, *, depth: float, safety: float = 0.9) -> Tensor:
        """Per-vertex largest step fractions ``(V,)`` in ``(0, 1]`` (dtype and device of ``x``) along
        ``dx (V, 3)`` [m] from ``x (V, 3)`` [m] that keep every vertex above its allowed depth (module
        docstring): ``depth`` [m] (> 0) is ``tau``, the penetration a vertex outside may reach in one
        step; ``safety`` in ``(0, 1)`` the fraction of the time of impact that may be taken."""
        name = type(self).__name__
        if not isinstance(x, Tensor) or x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"{name}.max_step: x must be a (V, 3) tensor, got {getattr(x, 'shape', type(x))}")
        if not isinstance(dx, Tensor) or dx.shape != x.shape:
            raise ValueError(f"{name}.max_step: dx must have the shape of x {tuple(x.shape)}, got "
                             f"{getattr(dx, 'shape', type(dx))}")
        # a bounded law (ipc) is infinite on the surface: the vertices may come close to it, never reach it
        depth = 0.0 if self.contact.bounded else positive(depth, f"{name}.max_step depth")
        if not 0 < safety < 1:
            raise ValueError(f"{name}.max_step: safety must lie in (0, 1), got {safety!r}")
        x, dx = x.detach(), dx.detach().to(x.dtype)
        t = self._impact_time(x, dx, depth)
        return (safety * t).clamp(max=1.0)

    def _impact_time(self, x: Tensor, dx: Tensor, tau: float) -> Tensor:  # pragma: no cover - abstract
        """First ``t >= 0`` with ``s(x + t dx) = -D`` ``(V,)`` (``inf`` if never); ``D`` as in the module docstring."""
        raise NotImplementedError

    def hessian_blocks(self, x: Tensor, projection=None, *, project=None) -> Tensor:
        """Per-vertex 3x3 Hessian blocks ``(V, 3, 3)`` [N/m]; any ``projection`` but ``None``/``"none"``
        drops the curvature term (PSD for convex colliders); ``project=``: its deprecated alias."""
        if project is not None:
            projection = projection_argument(projection, project, "Collider.hessian_blocks")
        exact = Projection.parse(projection, what="collider projection") is Projection.NONE
        s, n, curv = self._sd(x)
        return self.contact.vertex_terms(self.margin - s, n, curv, exact)


def _lerp(p: tuple, q: tuple, s: float) -> tuple:
    return tuple(a + s * (b - a) for a, b in zip(p, q))


def _lerp1(p: float, q: float, s: float) -> float:
    return p + s * (q - p)


def _radial(p: Tensor, radius: float):
    """Distance to a point (``p`` relative to it) minus ``radius``: ``(s, n, Hess s)``."""
    r = p.norm(dim=-1)
    safe = torch.where(r > 0, r, torch.ones_like(r))
    n = torch.where((r > 0)[:, None], p / safe[:, None], torch.zeros_like(p))
    eye = torch.eye(3, dtype=p.dtype, device=p.device)
    curv = (eye - n[:, :, None] * n[:, None, :]) / safe[:, None, None]
    return r - radius, n, curv


def _allowed_radius(r: Tensor, radius: float, tau: float) -> Tensor:
    """Radius ``rho = R - D`` of the level set ``s = -D`` around a point or an axis, for vertices at
    distance ``r (V,)`` from it: ``D = max(tau, 2 d)``, at most ``(R + d) / 2`` (``rho >= min(r, R) / 2``)."""
    d = (radius - r).clamp_min(0)
    return torch.maximum(radius - torch.clamp(2 * d, min=tau), 0.5 * r.clamp_max(radius))


def _ray_ball(p: Tensor, dx: Tensor, rho: Tensor) -> Tensor:
    """First time ``t >= 0`` ``(V,)`` at which ``|p + t dx| = rho`` for ``p`` outside the ball
    (``|p| > rho``; ``inf`` when the ray misses it, moves away, starts inside or on it, or ``rho = 0``).

    ``|p + t dx|^2 = rho^2`` is ``a t^2 + 2 b t + c = 0`` with ``a = |dx|^2``, ``b = p . dx``,
    ``c = |p|^2 - rho^2 > 0``; the entry root is ``c / (-b + sqrt(b^2 - a c))`` (no cancellation)."""
    a = (dx * dx).sum(-1)
    b = (p * dx).sum(-1)
    c = (p * p).sum(-1) - rho * rho
    disc = b * b - a * c
    hit = (c > 0) & (b < 0) & (disc >= 0) & (rho > 0)
    den = torch.where(hit, -b + disc.clamp_min(0).sqrt(), torch.ones_like(b))
    return torch.where(hit, c / den, torch.full_like(b, math.inf))


@dataclass(frozen=True)
class Sphere(Collider):
    """Solid sphere ``|x - center| <= radius``: ``center`` a 3-vector [m], ``radius`` [m]; acts on cloth positions
    ``(..., V, 3)`` [m] (the contact law and its parameters: :class:`Collider`)."""

    center: tuple = (0.0, 0.0, 0.0)
    radius: float = 1.0
    def __post_init__(self):
        object.__setattr__(self, "center", vec3(self.center, "Sphere.center"))
        object.__setattr__(self, "radius", positive(self.radius, "Sphere.radius"))
        self._check_penalty()

    def _sd(self, x: Tensor):
        return _radial(x - x.new_tensor(self.center), self.radius)

    _GEOMETRY = ("center", "radius")

    def _toward(self, goal: Collider, s: float) -> Collider:
        assert isinstance(goal, Sphere)
        return self._replace(center=_lerp(self.center, goal.center, s), radius=_lerp1(self.radius, goal.radius, s))

    def _path_rate(self, goal: Collider, x: Tensor) -> Tensor:
        assert isinstance(goal, Sphere)
        return x.new_full(x.shape[:1], math.dist(self.center, goal.center) + abs(goal.radius - self.radius))

    def _surface_motion(self, goal: Collider, x: Tensor) -> Tensor:
        assert isinstance(goal, Sphere)
        return x.new_tensor(goal.center).sub(x.new_tensor(self.center)).expand_as(x)

    def _impact_time(self, x: Tensor, dx: Tensor, tau: float) -> Tensor:
        p = x - x.new_tensor(self.center)
        return _ray_ball(p, dx, _allowed_radius(p.norm(dim=-1), self.radius, tau))


@dataclass(frozen=True)
class Plane(Collider):
    """Half-space below the plane through ``point`` (a 3-vector [m]) with outward ``normal`` (a 3-vector,
    normalised); acts on cloth positions ``(..., V, 3)`` [m] (the contact law: :class:`Collider`)."""

    point: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, 1.0)
    def __post_init__(self):
        object.__setattr__(self, "point", vec3(self.point, "Plane.point"))
        n = vec3(self.normal, "Plane.normal")
        norm = math.sqrt(sum(v * v for v in n))
        if norm == 0:
            raise ValueError("Plane.normal must be non-zero")
        object.__setattr__(self, "normal", tuple(v / norm for v in n))
        self._check_penalty()

    def _sd(self, x: Tensor):
        n = x.new_tensor(self.normal)
        s = (x - x.new_tensor(self.point)) @ n
        return s, n.expand_as(x), None

    _GEOMETRY = ("point", "normal")

    def _moves_to(self, goal: Collider) -> bool:  # a turn of less than 90 degrees
        return super()._moves_to(goal) and sum(a * b for a, b in zip(self.normal, goal.normal)) > 0  # type: ignore[attr-defined]

    def _toward(self, goal: Collider, s: float) -> Collider:
        assert isinstance(goal, Plane)
        return self._replace(point=_lerp(self.point, goal.point, s), normal=_lerp(self.normal, goal.normal, s))

    def _path_rate(self, goal: Collider, x: Tensor) -> Tensor:
        # s_t(x) - s(x) = (x - p) . (n_t - n) - (p_t - p) . n_t, and the normalized chord's normal moves at most
        # twice as far as the chord: |n_t - n| <= 2 t |n' - n|
        assert isinstance(goal, Plane)
        turn = math.dist(self.normal, goal.normal)
        return 2 * turn * (x - x.new_tensor(self.point)).norm(dim=-1) + math.dist(self.point, goal.point)

    def _impact_time(self, x: Tensor, dx: Tensor, tau: float) -> Tensor:
        # s(x + t dx) = s + t (dx . n) reaches -D (D = max(tau, 2 d) > -s) only when moving inwards
        s = self._sd(x)[0]
        gap = s + torch.clamp(2 * (-s).clamp_min(0), min=tau)
        rate = -(dx @ x.new_tensor(self.normal))
        inwards = rate > 0
        return torch.where(inwards, gap / torch.where(inwards, rate, torch.ones_like(rate)),
                           torch.full_like(rate, math.inf))


@dataclass(frozen=True)
class Capsule(Collider):
    """Solid capsule: points within ``radius`` [m] of the segment ``a -> b`` (3-vectors [m]); acts on cloth
    positions ``(..., V, 3)`` [m] (the contact law: :class:`Collider`)."""

    a: tuple = (0.0, 0.0, 0.0)
    b: tuple = (1.0, 0.0, 0.0)
    radius: float = 0.1
    def __post_init__(self):
        a, b = vec3(self.a, "Capsule.a"), vec3(self.b, "Capsule.b")
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "b", b)
        length = math.dist(a, b)
        if length == 0:
            raise ValueError("Capsule.a and Capsule.b must differ (use a Sphere for a point)")
        object.__setattr__(self, "radius", positive(self.radius, "Capsule.radius"))
        self._check_penalty()

    def transformed(self, a, b) -> Capsule:
        """The same capsule with new end points ``a``, ``b`` [m] (e.g. attached to a moving link).

        Tensor end points are kept as tensors: the collider's energy and gradient are then
        differentiable with respect to them (used to differentiate through contacts with robot links)."""
        if isinstance(a, Tensor) or isinstance(b, Tensor):
            return _TensorCapsule(a, b, radius=self.radius, stiffness=self.stiffness, margin=self.margin, law=self.law,
                                  power=self.power, friction=self.friction, eps_v=self.eps_v)
        return Capsule(a=a, b=b, radius=self.radius, stiffness=self.stiffness, margin=self.margin, law=self.law,
                       power=self.power, friction=self.friction, eps_v=self.eps_v)

    def _ends(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return x.new_tensor(self.a), x.new_tensor(self.b)

    def _sd(self, x: Tensor):
        a, b = self._ends(x)
        return _capsule_sd(x, a, b, self.radius)

    _GEOMETRY = ("a", "b", "radius")

    def _goal_ends(self, goal: Collider) -> tuple[tuple, tuple]:
        """The goal's ends in the order nearer this capsule's ``(a, b)`` (``a`` and ``b`` swapped are one shape)."""
        assert isinstance(goal, Capsule)
        ga, gb = tuple(goal.a), tuple(goal.b)
        if math.dist(self.a, gb) + math.dist(self.b, ga) < math.dist(self.a, ga) + math.dist(self.b, gb):
            ga, gb = gb, ga
        return ga, gb

    def _moves_to(self, goal: Collider) -> bool:  # (not a robot link's tensor ends; not the same ends swapped)
        if isinstance(self, _TensorCapsule) or isinstance(goal, _TensorCapsule) or not super()._moves_to(goal):
            return False
        assert isinstance(goal, Capsule)
        return self._goal_ends(goal) != (tuple(self.a), tuple(self.b)) or goal.radius != self.radius

    def _toward(self, goal: Collider, s: float) -> Collider:
        assert isinstance(goal, Capsule)
        ga, gb = self._goal_ends(goal)
        return self._replace(a=_lerp(self.a, ga, s), b=_lerp(self.b, gb, s), radius=_lerp1(self.radius, goal.radius, s))

    def _path_rate(self, goal: Collider, x: Tensor) -> Tensor:
        # each point of the axis moves on a chord between the ends' moves: at most the longer of them
        assert isinstance(goal, Capsule)
        ga, gb = self._goal_ends(goal)
        move = max(math.dist(self.a, ga), math.dist(self.b, gb)) + abs(goal.radius - self.radius)
        return x.new_full(x.shape[:1], move)

    def _surface_motion(self, goal: Collider, x: Tensor) -> Tensor:
        a, b = self._ends(x)
        ga, gb = self._goal_ends(goal)
        length = (b - a).norm()
        u = (((x - a) @ ((b - a) / length)).clamp_min(0.0).clamp_max(length) / length)[:, None]
        da, db = x.new_tensor(ga) - a, x.new_tensor(gb) - b
        return (1 - u) * da + u * db

    def _impact_time(self, x: Tensor, dx: Tensor, tau: float) -> Tensor:
        a, b = (e.detach() for e in self._ends(x))
        return _capsule_impact(x, dx, a, b, self.radius, tau)


class _TensorCapsule(Capsule):
    """A :class:`Capsule` whose end points are tensors ``(3,)`` (possibly requiring grad)."""

    ends: tuple[Tensor, Tensor]

    def __init__(self, a: Tensor, b: Tensor, *, radius: float, stiffness: float | None, margin: float | None,
                 law: str = "ipc",
                 power: float | None = None, friction: float = 0.0, eps_v: float = 1e-3):
        # an end point given as Python numbers is kept in float64 (cast to the positions' dtype per call)
        a, b = (e if isinstance(e, Tensor) else torch.as_tensor(e, dtype=torch.float64) for e in (a, b))
        super().__init__(a=tuple(a.detach().tolist()), b=tuple(b.detach().tolist()), radius=radius, stiffness=stiffness,
                         margin=margin, law=law, power=power, friction=friction, eps_v=eps_v)
        object.__setattr__(self, "ends", (a, b))

    def _replace(self, **changes) -> Collider:
        kw = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("a", "b")}
        return _TensorCapsule(*self.ends, **{**kw, **changes})

    def _ends(self, x: Tensor) -> tuple[Tensor, Tensor]:
        a, b = self.ends
        return a.to(dtype=x.dtype, device=x.device), b.to(dtype=x.dtype, device=x.device)


def _capsule_sd(x: Tensor, a: Tensor, b: Tensor, radius: float):
    """Signed distance of ``x (V, 3)`` to the capsule ``a -> b`` (tensors ``(3,)``): ``(s, n, Hess s)``."""
    length = (b - a).norm()
    t_hat = (b - a) / length
    tau = torch.minimum(((x - a) @ t_hat).clamp_min(0.0), length)
    s, n, curv = _radial(x - (a + tau[:, None] * t_hat), radius)
    interior = ((tau > 0) & (tau < length)).to(x.dtype)
    # along the segment's interior the distance is constant in the axis direction
    tt = t_hat[:, None] * t_hat[None, :]
    r = (s + radius).clamp_min(torch.finfo(x.dtype).tiny)
    curv = curv - interior[:, None, None] * tt / r[:, None, None]
    return s, n, curv


def _capsule_impact(x: Tensor, dx: Tensor, a: Tensor, b: Tensor, radius: float, tau: float) -> Tensor:
    """First time ``(V,)`` the rays ``x + t dx`` enter the capsule ``a -> b`` of the allowed radius
    ``rho`` (:func:`_allowed_radius`): the earliest of the lateral entry into the infinite cylinder
    (kept when its axial coordinate lies on the segment) and the entries into the two end balls.  A
    capsule is the union of these three convex pieces, and a ray entering the finite cylinder
    through an end disk is already inside that end's ball, so the minimum is exact."""
    length = (b - a).norm()
    u = (b - a) / length
    q = x - a
    axial = q @ u
    tau_c = torch.minimum(axial.clamp_min(0.0), length)
    rho = _allowed_radius((q - tau_c[:, None] * u).norm(dim=-1), radius, tau)
    du = dx @ u
    t_side = _ray_ball(q - axial[:, None] * u, dx - du[:, None] * u, rho)
    ax_hit = axial + torch.where(torch.isfinite(t_side), t_side, torch.zeros_like(t_side)) * du
    t_side = torch.where((ax_hit >= 0) & (ax_hit <= length), t_side, torch.full_like(t_side, math.inf))
    return torch.minimum(t_side, torch.minimum(_ray_ball(q, dx, rho), _ray_ball(x - b, dx, rho)))
