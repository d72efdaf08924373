r"""Static data of a cloth scene and its potential: :class:`ClothModel` and :class:`ClothState`.

The potential of a static equilibrium is

    Phi(x) = E_membrane(x) + E_bending(x) + sum_c E_c(x) - sum_i m_i g . x_i + sum_t E_t(x)      [J]

over positions ``x (V, 3)`` [m], a sum of :class:`~torchbend.sim.terms.EnergyTerm` objects
(:attr:`ClothModel.terms`): only the terms a model declares are built and evaluated, and a term of
one's own is one more entry of ``terms=``.  Lumped
masses ``m_i`` [kg] are a third of the rest-area mass of each incident triangle.  Every tensor the
model creates (masses, the pinned mask, gravity, Hessian blocks) lives on the device and in the
dtype of the rest positions (or of the positions ``x`` it is evaluated at); the ``scipy.sparse``
Hessian is assembled on the CPU.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from .._checks import positive, vec3
from ..energies.bending import BendingEnergy
from ..energies.colliders import Collider
from ..energies.membrane import MembraneEnergy
from ..energies.sparse import to_scipy
from ..losses.cloth_loss import ClothLoss
from ..mesh.topology import lumped_areas, mesh_and_rest
from ..options import Projection
from .linearized import LinearizedHessian
from .terms import (
    BendingTerm,
    ColliderTerm,
    EnergyTerm,
    GravityTerm,
    MembraneTerm,
    StepContext,
    TermLoss,
    as_csr,
)

__all__ = ["ClothModel", "ClothState", "TermSum"]


@dataclass
class ClothState:
    """Dynamic state: positions ``x (V, 3)`` [m] and velocities ``v (V, 3)`` [m/s]."""

    x: Tensor
    v: Tensor


class TermSum:
    """A potential that is the sum of energy terms (:class:`~torchbend.EnergyTerm`): its energies, gradient,
    Hessian, Hessian-vector products, diagonal blocks and step bound, each the sum (or minimum) over
    :attr:`terms`, which a subclass provides (with ``vertex_count``).  :class:`ClothModel` is one."""

    vertex_count: int

    @property
    def terms(self) -> tuple[EnergyTerm, ...]:  # pragma: no cover - abstract
        raise NotImplementedError

    def loss(self, weights=None, *, reduction: str = "mean", ctx: StepContext | None = None) -> ClothLoss:
        """The model's potential as a :class:`~torchbend.ClothLoss` over batches of positions ``(B, V, 3)``:
        one :class:`~torchbend.sim.terms.TermLoss` per term of :attr:`terms`, named as the terms, so that
        training and the solvers minimise the same term objects (for one state, ``loss(x)`` with
        ``reduction="sum"`` equals :meth:`potential` to round-off).  ``weights``, ``reduction`` as in
        ``ClothLoss``; ``ctx``: a time step's :class:`StepContext` (default static)."""
        return ClothLoss({t.name: TermLoss(t, ctx) for t in self.terms}, weights, reduction=reduction)

    def max_step(self, x: Tensor, dx: Tensor, ctx: StepContext | None = None) -> float:
        """The largest fraction ``alpha`` in ``(0, 1]`` of the step ``dx (V, 3)`` [m] from ``x (V, 3)`` [m]
        that no term forbids (:meth:`EnergyTerm.max_step`): for the colliders, the minimum over colliders
        and vertices of :meth:`Collider.max_step <torchbend.energies.colliders.Collider.max_step>` with
        ``depth = contact_depth`` (continuous, closed form: no vertex tunnels through a collider on the
        segment ``x + t alpha dx``, ``t`` in ``[0, 1]``; a vertex outside sinks at most
        ``contact_depth`` below the surface, one inside at most doubles its depth).  ``1.0`` when no term
        bounds steps (nothing is evaluated for the built-in elastic terms and gravity)."""
        if x.shape[0] == 0:
            return 1.0
        ctx = ctx or StepContext()
        alpha = 1.0
        for t in self.terms:
            if type(t).max_step is not EnergyTerm.max_step:
                alpha = min(alpha, float(t.max_step(x, dx, ctx)))
        return alpha

    # ---------------------------------------------------------------- potential and derivatives
    def energies(self, x: Tensor, ctx: StepContext | None = None) -> dict:
        """Per-term energies [J] at ``x (V, 3)`` [m], keyed by term name: ``membrane``, ``bending``,
        ``gravity``, ``collider0``, ..., then one's own terms.  ``ctx``: the :class:`StepContext` of a
        time step (the viscous bending term's lagged angles), default static."""
        ctx = ctx or StepContext()
        return {t.name: float(t.energy(x, ctx)) for t in self.terms}

    def potential(self, x: Tensor, ctx: StepContext | None = None) -> float:
        """The potential ``Phi(x)`` [J]: the sum of :meth:`energies`."""
        return sum(self.energies(x, ctx).values())

    def gradient(self, x: Tensor, ctx: StepContext | None = None) -> Tensor:
        """``dPhi/dx`` ``(V, 3)`` [N] (minus the net force on each vertex)."""
        ctx = ctx or StepContext()
        g = torch.zeros_like(x)
        for t in self.terms:
            g = g + t.gradient(x, ctx)
        return g

    def _projection(self, term: EnergyTerm, option: Projection, contact) -> Projection:
        return Projection.parse(contact) if (term.contact and contact is not None) else option

    def hessian(self, x: Tensor, option: Projection | str, ctx: StepContext | None = None, *,
                contact=None) -> sp.csr_matrix:
        """``scipy.sparse`` CSR Hessian ``(3V, 3V)`` [N/m] of the potential (without inertia) at ``x (V, 3)``.

        ``option``: a :class:`torchbend.options.Projection` (or its name) for every term (the membrane gets the
        nearest one it supports, colliders drop their curvature term for every member but ``NONE``).
        ``contact``: a projection for the contact terms alone (default: ``option``), e.g. ``"clamp"`` for
        PSD contact blocks (as IPC projects every contact Hessian) under an otherwise exact Hessian:
        the exact penalty curvature ``-k d Hess s`` is negative definite in the tangent plane of a
        curved collider and grows with the penetration ``d``."""
        option = Projection.parse(option)
        ctx = ctx or StepContext()
        n = 3 * self.vertex_count
        if contact is None and isinstance(x, Tensor) and x.shape == (self.vertex_count, 3):
            # the solver's assembly (one pattern analysed per model and device, values scattered into it)
            fh = _full_hessian(self, x.device)
            return fh.to_scipy(fh.assemble(x, self.terms, ctx, option))
        H = sp.csr_matrix((n, n))
        for t in self.terms:
            projection = self._projection(t, option, contact)
            blocks = t.vertex_blocks(x, ctx, projection)
            if blocks is not None:
                H = H + _block_diagonal_csr(blocks.detach().cpu().numpy())
            else:
                H = H + to_scipy(as_csr(t.hessian(x, ctx, projection)))
        return H.tocsr()

    def linearize(self, x: Tensor, projection: Projection | str = "exact", ctx: StepContext | None = None, *,
                  contact=None) -> LinearizedHessian:
        """The Hessian at ``x (V, 3)`` evaluated, projected (``projection``, ``contact`` as ``option`` and
        ``contact`` of :meth:`hessian`) and assembled once, as an operator applied at the cost of a sparse matvec
        (:class:`~torchbend.sim.linearized.LinearizedHessian`: ``op @ v``, ``op.as_linear_operator()``); pinned
        vertices are known to it (``op.free``)."""
        H = self.hessian(x, Projection.parse(projection), ctx, contact=contact)
        return LinearizedHessian(H, self.vertex_count, getattr(self, "pinned", None))

    def contact_blocks(self, x: Tensor, project) -> Tensor:
        """The contact terms' per-vertex 3x3 Hessian blocks ``(V, 3, 3)`` [N/m] summed (zeros without
        them); ``project`` as in :meth:`Collider.hessian_blocks
        <torchbend.energies.colliders.Collider.hessian_blocks>`."""
        out = x.new_zeros(x.shape[0], 3, 3)
        ctx = StepContext()
        for t in self.terms:
            if t.contact:
                out = out + t.block_diagonal(x, ctx, Projection.parse(project))
        return out

    def hvp(self, x: Tensor, v: Tensor, option: Projection | str, ctx: StepContext | None = None, *,
            contact=None) -> Tensor:
        """Hessian-vector product ``H(x) v`` ``(V, 3)`` [N] for a direction ``v (V, 3)`` [m] (``option``,
        ``contact`` as in :meth:`hessian`)."""
        option = Projection.parse(option)
        ctx = ctx or StepContext()
        out = torch.zeros_like(x)
        for t in self.terms:
            out = out + t.hvp(x, v, ctx, self._projection(t, option, contact))
        return out

    def block_diagonal(self, x: Tensor, option: Projection | str, ctx: StepContext | None = None, *,
                       contact=None) -> Tensor:
        """Per-vertex 3x3 diagonal blocks of the Hessian ``(V, 3, 3)`` [N/m] (block-Jacobi
        preconditioner; ``option``, ``contact`` as in :meth:`hessian`)."""
        option = Projection.parse(option)
        ctx = ctx or StepContext()
        out = x.new_zeros(self.vertex_count, 3, 3)
        for t in self.terms:
            out = out + t.block_diagonal(x, ctx, self._projection(t, option, contact))
        return out


class ClothModel(TermSum):
    """Static data of a cloth scene: only the terms it declares are built and evaluated.

    Args:
        faces: ``(F, 3)`` int triangles (or a :class:`~torchbend.mesh.HingeTopology`).
        rest_positions: ``(V, 3)`` [m]; its device and dtype are those of every tensor of the model.
        terms: energy terms: :class:`~torchbend.EnergyTerm` instances (one's own, see the README's "Adding an
            energy term"), and for the built-in ones a :class:`~torchbend.BendingEnergy`,
            :class:`~torchbend.MembraneEnergy` or collider, which is the same as passing it by keyword.
        bending: a :class:`~torchbend.BendingEnergy` over the same mesh, or ``None``.
        membrane: a :class:`~torchbend.MembraneEnergy` over the same mesh, or ``None``.
        density: areal density [kg/m^2] (> 0): lumped masses, 1/3 of each triangle's rest-area mass per vertex.
        gravity: ``(3,)`` acceleration [m/s^2].
        pinned: ``(V,)`` bool mask of vertices held at their given positions, integer vertex indices
            (a tensor, array or list, of any length: ``V`` indices are indices, not a mask), or ``None``
            (nothing pinned).
        colliders: :class:`~torchbend.Sphere`, :class:`~torchbend.Plane`, :class:`~torchbend.Capsule` instances.
        contact_depth: the penetration [m] (> 0) a vertex may reach below a collider surface in one
            Newton step (:meth:`max_step`); default ``CONTACT_DEPTH`` times the mean rest edge length.

    Attributes:
        topology: the :class:`~torchbend.mesh.HingeTopology` (integer connectivity, CPU).
        rest_positions: ``(V, 3)`` [m].
        mass: ``(V,)`` lumped vertex masses [kg].
        gravity: ``(3,)`` [m/s^2].
        pinned: ``(V,)`` bool.
        colliders: tuple of colliders.
        terms: every term of the potential, in evaluation order: membrane, bending, gravity, the colliders,
            then the ``EnergyTerm`` instances given (built from the attributes above on each access, so that
            assigning e.g. ``colliders`` or ``gravity`` changes them).
        contact_depth: see above [m] (computed from the rest edges on first use when not given).

    A model may be built on the ``meta`` device (shapes only): the checks that need values are
    then skipped, and it cannot be solved.
    """

    def __init__(self, faces, rest_positions, *, terms=(), bending: BendingEnergy | None = None,
                 membrane: MembraneEnergy | None = None, density: float = 0.1,
                 gravity=(0.0, 0.0, -9.81), pinned=None, colliders=(), contact_depth: float | None = None):
        topo, rest = mesh_and_rest(faces, rest_positions)
        V = topo.vertex_count
        density = positive(density, "density")
        bending, membrane, colliders, extra = _split_terms(terms, bending, membrane, colliders)
        _check_terms(V, bending, membrane)
        self.extra_terms = extra
        self.topology = topo
        self.rest_positions = rest
        self.bending, self.membrane = bending, membrane
        self.density = density
        self.gravity = torch.tensor(_gravity(gravity), dtype=rest.dtype, device=rest.device)
        self.pinned = _pinned_mask(pinned, V, rest.device)
        self.mass = density * lumped_areas(topo.faces.to(rest.device), rest)
        self.colliders = colliders
        for t in extra:  # terms over the mesh itself (self-contact) take it from the model
            bind = getattr(t, "bind", None)
            if callable(bind):
                bind(topo, rest, self.mass)
        self._contact_depth = None if contact_depth is None else positive(contact_depth, "contact_depth")

    @property
    def colliders(self) -> tuple:
        """The colliders (class docstring), an ipc collider's ``stiffness=None`` replaced by the one chosen from
        :meth:`vertex_weight` (:meth:`Collider.with_weight <torchbend.energies.colliders.Collider.with_weight>`)."""
        return self._colliders

    @colliders.setter
    def colliders(self, colliders) -> None:
        colliders = _check_colliders(colliders)
        if any(c.stiffness is None for c in colliders) and self.mass.device.type != "meta":
            w = self.vertex_weight()
            colliders = tuple(c.with_weight(w) for c in colliders)
        # a collider replaced by a moved one of the same kind (ipc law) is a move the next time step carries out in
        # stages (ColliderTerm.pending_move): from the pose of the last step, kept until then
        # (matched by place: collider i of the new tuple moves from collider i of the old one, where both exist)
        old = getattr(self, "_colliders", None) or ()
        starts = getattr(self, "_collider_starts", None) or ()
        moves = []
        for i, c in enumerate(colliders):
            start = None
            if i < len(old):
                start = starts[i] if i < len(starts) and starts[i] is not None else old[i]
                if not start._moves_to(c):
                    start = None
            moves.append(start)
        self._colliders = colliders
        self._collider_starts = tuple(moves)
        self._collider_goals: dict = {}

    def _collider_move(self, i: int):
        """``(start, goal)`` of collider ``i``'s pending move (``start`` None: none)."""
        starts = getattr(self, "_collider_starts", ())
        return (starts[i] if i < len(starts) else None), getattr(self, "_collider_goals", {}).get(i, self._colliders[i])

    def _set_collider(self, i: int, collider, start, goal) -> None:
        """Collider ``i`` placed at ``collider`` on its move from ``start`` to ``goal`` (``start`` None: settled)."""
        colliders = list(self._colliders)
        colliders[i] = collider
        self._colliders = tuple(colliders)
        starts = list(getattr(self, "_collider_starts", None) or (None,) * len(colliders))
        starts[i] = start
        self._collider_starts = tuple(starts)
        goals = dict(getattr(self, "_collider_goals", {}))
        if start is None:
            goals.pop(i, None)
        else:
            goals[i] = goal
        self._collider_goals = goals

    def vertex_weight(self) -> float:
        """The mean vertex weight ``|g| mean(m)`` [N] (with ``|g| = 9.81`` m/s^2 under no gravity): the scale the
        contact terms choose their default stiffness from."""
        g = float(self.gravity.norm())
        m = float(self.mass.mean()) if self.mass.numel() else 0.0
        w = (g if g > 0 else 9.81) * m
        return w if w > 0 else 1.0

    CONTACT_DEPTH = 0.01
    """Default :attr:`contact_depth` relative to the mean rest edge length."""

    @property
    def vertex_count(self) -> int:
        return self.topology.vertex_count

    @property
    def contact_depth(self) -> float:
        """The penetration [m] a vertex outside a collider may reach in one Newton step (:meth:`max_step`)."""
        if self._contact_depth is None:
            e = self.topology.edges.to(self.rest_positions.device)
            length = float((self.rest_positions[e[:, 1]] - self.rest_positions[e[:, 0]]).norm(dim=-1).mean())
            self._contact_depth = self.CONTACT_DEPTH * length if length > 0 else 1.0
        return self._contact_depth

    def external_force(self, dtype=None) -> Tensor:
        """Gravity force ``m_i g`` ``(V, 3)`` [N] (in ``dtype``, default the masses'): the gravity term's."""
        return GravityTerm(self.mass, self.gravity).force(dtype)

    @property
    def terms(self) -> tuple[EnergyTerm, ...]:
        """The terms of the potential (class docstring)."""
        out: list[EnergyTerm] = []
        if self.membrane is not None:
            out.append(MembraneTerm(self.membrane))
        if self.bending is not None:
            out.append(BendingTerm(self.bending))
        out.append(GravityTerm(self.mass, self.gravity))
        if self.colliders:
            depth = lambda: self.contact_depth  # noqa: E731 - evaluated by a step bound only
            out.extend(ColliderTerm(c, depth, name=f"collider{i}", owner=(self, i)) for i, c in enumerate(self.colliders))
        out.extend(self.extra_terms)
        return tuple(out)

# -------------------------------------------------------------------- construction helpers
def _gravity(gravity) -> tuple[float, float, float]:
    """``gravity`` [m/s^2] as a finite 3-tuple (a tensor is read on its device)."""
    if isinstance(gravity, Tensor):
        gravity = gravity.detach().reshape(-1).tolist()
    return vec3(gravity, "gravity")


def _split_terms(terms, bending, membrane, colliders) -> tuple:
    """``terms=`` sorted into the shorthands (a bending or membrane energy, colliders) and one's own
    :class:`EnergyTerm` instances; a second bending or membrane energy is a ``ValueError``."""
    if isinstance(terms, (EnergyTerm, BendingEnergy, MembraneEnergy, Collider)):
        terms = (terms,)
    extra = [c for c in colliders if isinstance(c, EnergyTerm)]  # a body mesh collider is a term of its own
    colliders = [c for c in colliders if not isinstance(c, EnergyTerm)]
    for i, t in enumerate(terms):
        if isinstance(t, BendingEnergy):
            if bending is not None:
                raise ValueError(f"terms[{i}] is a second bending energy (one BendingEnergy per model)")
            bending = t
        elif isinstance(t, MembraneEnergy):
            if membrane is not None:
                raise ValueError(f"terms[{i}] is a second membrane energy (one MembraneEnergy per model)")
            membrane = t
        elif isinstance(t, Collider):
            colliders.append(t)
        elif isinstance(t, EnergyTerm):
            extra.append(t)
        else:
            raise ValueError(f"terms[{i}] must be an EnergyTerm, a BendingEnergy, a MembraneEnergy or a collider, "
                             f"got {type(t).__name__}")
    _name_terms(extra, len(colliders))
    return bending, membrane, tuple(colliders), tuple(extra)


def _name_terms(extra: list, n_colliders: int) -> None:
    """Check the names of one's own terms (unique, not the model's own); a second body mesh left at the default name
    'mesh_collider' after another is named 'mesh_collider_2', then '_3', ... (set once every check has passed)."""
    from .self_contact import MeshCollider

    default = "mesh_collider"
    names = [t.name for t in extra]
    reserved = {"membrane", "bending", "gravity", "inertia"} | {f"collider{i}" for i in range(n_colliders)}
    for i, name in enumerate(names):
        t = extra[i]
        if not isinstance(name, str) or not name:
            raise ValueError(f"terms: an EnergyTerm needs a non-empty string name, got {name!r}")
        if any(t is u for u in extra[:i]):
            raise ValueError(f"terms: the {type(t).__name__} {name!r} is given twice")
        if name in reserved or name in names[:i]:
            first = extra[names.index(name)] if name in names[:i] else None
            if not (name == default and isinstance(t, MeshCollider) and isinstance(first, MeshCollider)):
                raise ValueError(f"terms: the name {name!r} of {type(t).__name__} is already taken "
                                 f"(set its `name` attribute to a unique one)")
            k = 2
            while f"{default}_{k}" in reserved or f"{default}_{k}" in names:
                k += 1
            names[i] = f"{default}_{k}"
    for t, name in zip(extra, names):
        t.name = name


def _check_terms(V: int, bending, membrane) -> None:
    if bending is not None and not isinstance(bending, BendingEnergy):
        raise ValueError(f"bending must be a BendingEnergy or None, got {type(bending).__name__}")
    if membrane is not None and not isinstance(membrane, MembraneEnergy):
        raise ValueError(f"membrane must be a MembraneEnergy or None, got {type(membrane).__name__}")
    for name, term in (("bending", bending), ("membrane", membrane)):
        if term is not None and term.vertex_count != V:
            raise ValueError(f"{name} has {term.vertex_count} vertices but the mesh has {V}")


def _check_colliders(colliders) -> tuple:
    colliders = tuple(colliders)
    for i, c in enumerate(colliders):
        if not isinstance(c, Collider):
            raise ValueError(f"colliders[{i}] must be a Sphere, Plane, Capsule or MeshCollider, got {type(c).__name__}")
    return colliders


def _pinned_mask(pinned, V: int, device: torch.device) -> Tensor:
    """``(V,)`` bool mask on ``device`` from a mask, vertex indices or ``None``.

    A boolean tensor, array or list is a mask (it must have length ``V``); integers are vertex indices,
    whatever their count (a list of ``V`` indices is not mistaken for a mask; repeated indices are
    allowed); an empty list pins nothing.  Index values are checked where they are given (a list: on the
    CPU), then the mask is built on ``device``; values on the ``meta`` device are not checked."""
    if pinned is None:
        return torch.zeros(V, dtype=torch.bool, device=device)
    if not isinstance(pinned, Tensor):
        try:
            pinned = torch.as_tensor(pinned, device="cpu")  # user data (a list): checked on the host
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(f"pinned must be a ({V},) bool mask or a list of vertex indices, got {pinned!r}") from None
        if pinned.numel() == 0 and pinned.ndim == 1:
            pinned = pinned.long()  # [] reads as float32: no index
    if pinned.dtype == torch.bool:
        if pinned.shape != (V,):
            raise ValueError(f"pinned must have shape ({V},) (a bool mask, one per vertex), got {tuple(pinned.shape)}")
        return pinned.to(device)
    if pinned.ndim != 1 or pinned.is_floating_point() or pinned.is_complex():
        raise ValueError(f"pinned must be a ({V},) bool mask or a (P,) tensor/list of integer vertex indices, got "
                         f"shape {tuple(pinned.shape)} dtype {pinned.dtype}")
    if pinned.numel() and pinned.device.type != "meta" and (int(pinned.min()) < 0 or int(pinned.max()) >= V):
        raise ValueError(f"pinned indices must lie in [0, {V}), got range "
                         f"[{int(pinned.min())}, {int(pinned.max())}]")
    mask = torch.zeros(V, dtype=torch.bool, device=device)
    mask[pinned.long().to(device)] = True
    return mask


_FULL_HESSIANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _full_hessian(model, device: torch.device):
    """The :class:`~torchbend.sim.linear.FreeHessian` of every DOF of ``model`` on ``device`` (kept per model, apart
    from the solver's, whose free DOFs leave the pinned vertices out)."""
    from .linear import FreeHessian

    fh = _FULL_HESSIANS.get(model)
    if fh is None or fh.free_mask.device != device or fh.free_mask.shape[0] != 3 * model.vertex_count:
        fh = FreeHessian(model, torch.ones(3 * model.vertex_count, dtype=torch.bool, device=device))
        _FULL_HESSIANS[model] = fh
    return fh


def _block_diagonal_csr(blocks: np.ndarray):
    """``scipy.sparse`` CSR matrix ``(3V, 3V)`` with the ``(V, 3, 3)`` ``blocks`` on its diagonal
    (one construction: every row ``3v + i`` holds columns ``3v, 3v + 1, 3v + 2``)."""
    V = blocks.shape[0]
    cols = (3 * np.arange(V)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)  # (V, 3, 3)
    indptr = np.arange(0, 9 * V + 1, 3)
    return sp.csr_matrix((blocks.reshape(-1), cols.reshape(-1), indptr), shape=(3 * V, 3 * V))
