r"""Robot-driven cloth: pins bound to link frames and capsule colliders on links, through the
batched, differentiable forward kinematics of pytorch-kinematics (URDF).

* :class:`Robot` loads a URDF (a file, an XML string, or the name of an asset shipped in
  ``torchbend/robot/assets``, e.g. ``"folding_arm.urdf"``) in float64 and evaluates link transforms for
  joint vectors ``q (..., J)`` (``J`` = number of movable joints, in :attr:`Robot.joint_names` order).
* :class:`LinkPins` binds cloth vertices to links: at bind time each vertex is stored in its
  link's local frame; its position for joints ``q`` is ``T_link(q) p_local``, differentiable in ``q``.
* :class:`LinkCapsule` is a capsule fixed in a link's frame; :meth:`LinkCapsule.collider` gives the
  world-space :class:`~torchbend.Capsule` for ``q`` (tensor end points, differentiable).
* :class:`RobotScene` ties a :class:`~torchbend.ClothModel` to a robot: implicit-Euler steps
  with the pins moved to the forward kinematics of the next joint vector, and a static solve that is
  differentiable with respect to the joint angles (implicit-function adjoint: the equilibrium
  depends on ``q`` through the pinned positions and through the link capsules).

Units: metres, radians (prismatic joints: metres).  Bad input raises ``ValueError`` naming it.
"""
from __future__ import annotations

import copy

import torch
from torch import Tensor

from ..energies.colliders import Capsule
from ..sim.adjoint import solve_static_adjoint
from ..sim.model import ClothModel, ClothState
from ..sim.newton import SolveInfo, implicit_euler_step
from .urdf import Robot

__all__ = ["LinkPins", "LinkCapsule", "RobotScene", "trajectory"]


def _apply(T: Tensor, p: Tensor) -> Tensor:
    """``T (..., N, 4, 4)`` applied to points ``p (N, 3)`` -> ``(..., N, 3)``."""
    return (T[..., :3, :3] @ p[..., None].to(T.dtype))[..., 0] + T[..., :3, 3]


class LinkPins:
    """Cloth vertices rigidly attached to robot links (bound at joints ``q_bind``).

    Args:
        robot: the :class:`Robot`.
        vertices: ``(P,)`` vertex indices.
        links: one link name per vertex (or one name for all).
        positions: ``(P, 3)`` [m] world positions of the vertices at bind time.
        q_bind: ``(J,)`` joints at bind time.
    """

    def __init__(self, robot: Robot, vertices, links, positions, q_bind):
        self.robot = robot
        vertices = torch.as_tensor(vertices, dtype=torch.long).reshape(-1)
        if isinstance(links, str):
            links = [links] * len(vertices)
        links = list(links)
        if len(links) != len(vertices):
            raise ValueError(f"links must name one link per pinned vertex ({len(vertices)}), got {len(links)}")
        if len(set(vertices.tolist())) != len(vertices):
            raise ValueError("a vertex is bound to the robot twice")
        for i, link in enumerate(links):
            robot.check_link(link, f"pin {i} (vertex {int(vertices[i])})")
        positions = torch.as_tensor(positions)
        if positions.shape != (len(vertices), 3) or not positions.is_floating_point():
            raise ValueError(f"positions must be a ({len(vertices)}, 3) float tensor, got {tuple(positions.shape)}")
        q_bind = robot.check_joints(q_bind, "q_bind")
        if q_bind.ndim != 1:
            raise ValueError(f"q_bind must be a single joint vector ({robot.joint_count},), got {tuple(q_bind.shape)}")
        order = torch.argsort(vertices)  # increasing vertex order, as ClothModel.pinned lists them
        self.vertices = vertices[order]
        self.links = [links[i] for i in order.tolist()]
        self._unique = sorted(set(self.links))
        self._which = torch.tensor([self._unique.index(n) for n in self.links], dtype=torch.long)
        T = robot.link_transforms(q_bind.detach(), self._unique)[self._which]  # (P, 4, 4)
        p = positions[order].detach().to(T.dtype)
        R, t = T[:, :3, :3], T[:, :3, 3]
        self.local = (R.transpose(-1, -2) @ (p - t)[..., None])[..., 0]  # (P, 3) in link frames

    def __len__(self) -> int:
        return len(self.vertices)

    def positions(self, q) -> Tensor:
        """World positions ``(..., P, 3)`` [m] of the pinned vertices for joints ``q (..., J)``."""
        T = self.robot.link_transforms(q, self._unique)[..., self._which, :, :]
        return _apply(T, self.local)


class LinkCapsule:
    """A capsule fixed in the frame of ``link``: end points ``a``, ``b`` [m] in link coordinates; the
    other arguments (validated) are those of :class:`~torchbend.Capsule` with the ``"penalty"`` law
    (``stiffness`` [N/m]): a link moves between time steps and may start a step on the cloth, where the ipc
    law's barrier would be infinite (a penalty pushes the cloth back out).  The penalty acts from ``margin`` [m]
    (default 1 mm) outside the capsule's surface, so that the cloth it pushes (up to ``stiffness * margin`` per
    vertex) stays outside the capsule: a penalty needs some depth to push, and with ``margin=0`` that depth is
    inside the link."""

    def __init__(self, link: str, a=(0.0, 0.0, 0.0), b=(0.1, 0.0, 0.0), radius: float = 0.02, stiffness: float = 1e4,
                 margin: float = 1e-3):
        self.link = str(link)
        self.local = Capsule(a=a, b=b, radius=radius, stiffness=stiffness, margin=margin,  # in link coordinates
                             law="penalty")

    a = property(lambda self: self.local.a)
    b = property(lambda self: self.local.b)
    radius = property(lambda self: self.local.radius)

    def __repr__(self) -> str:
        return f"LinkCapsule({self.link!r}, {self.local!r})"

    def endpoints(self, robot: Robot, q) -> Tensor:
        """World end points ``(..., 2, 3)`` [m] for joints ``q (..., J)``."""
        T = robot.link_transforms(q, [robot.check_link(self.link, "LinkCapsule")])[..., 0, None, :, :]
        return _apply(T, torch.tensor([self.a, self.b], dtype=T.dtype, device=T.device))

    def collider(self, robot: Robot, q) -> Capsule:
        """The world-space :class:`Capsule` for one joint vector ``q (J,)`` (tensor end points)."""
        ends = self.endpoints(robot, q)
        if ends.ndim != 2:
            raise ValueError("LinkCapsule.collider takes one joint vector (J,), not a batch")
        return self.local.transformed(ends[0], ends[1])


class RobotScene:
    """A cloth model driven by a robot: pinned vertices follow links, capsules move with links.

    ``model.pinned`` must contain every vertex of ``pins`` (other pinned vertices stay where they
    are); ``model.colliders`` are the static ones (table, ...); ``capsules`` are added per joint vector.
    """

    def __init__(self, model: ClothModel, robot: Robot, pins: LinkPins, capsules=()):
        if not isinstance(model, ClothModel):
            raise ValueError(f"model must be a ClothModel, got {type(model).__name__}")
        if not isinstance(pins, LinkPins) or pins.robot is not robot:
            raise ValueError("pins must be LinkPins bound to this robot")
        if len(pins) and not bool(model.pinned[pins.vertices].all()):
            missing = pins.vertices[~model.pinned[pins.vertices]].tolist()
            raise ValueError(f"vertices {missing} are bound to the robot but not pinned in the model")
        if len(pins) and int(pins.vertices.max()) >= model.vertex_count:
            raise ValueError(f"pinned vertex {int(pins.vertices.max())} is out of range (V = {model.vertex_count})")
        capsules = tuple(capsules)
        for i, c in enumerate(capsules):
            if not isinstance(c, LinkCapsule):
                raise ValueError(f"capsules[{i}] must be a LinkCapsule, got {type(c).__name__}")
            robot.check_link(c.link, f"capsules[{i}]")
        self.model, self.robot, self.pins, self.capsules = model, robot, pins, capsules
        # position of each robot pin among model.pinned (increasing vertex order)
        pinned_idx = model.pinned.nonzero()[:, 0]
        self._slot = torch.searchsorted(pinned_idx, pins.vertices.to(pinned_idx.device))

    def colliders(self, q) -> tuple:
        """Static colliders plus the link capsules at joints ``q (J,)``."""
        return tuple(self.model.colliders) + tuple(c.collider(self.robot, q) for c in self.capsules)

    def model_at(self, q) -> ClothModel:
        """The cloth model with the link capsules placed for joints ``q (J,)``."""
        m = copy.copy(self.model)
        m.colliders = self.colliders(q)
        return m

    def place(self, x: Tensor, q) -> Tensor:
        """``x (V, 3)`` with the robot-held vertices moved to their forward kinematics at ``q``."""
        x = x.clone()
        x[self.pins.vertices] = self.pins.positions(q).to(x.dtype)
        return x

    def step(self, state: ClothState, q_next, dt: float, options=None, **kw) -> tuple[ClothState, SolveInfo]:
        """One implicit-Euler step to the joint vector ``q_next`` at the end of the step (``options``, ``kw``:
        those of :func:`~torchbend.implicit_euler_step`)."""
        q_next = self.robot.check_joints(q_next, "q_next").detach()
        x = self.place(state.x, q_next)
        model = self.model_at(q_next)
        try:
            return implicit_euler_step(model, ClothState(x, state.v), dt, options, **kw)
        finally:
            self._settle_static(model)

    def _settle_static(self, model: ClothModel) -> None:
        """The static colliders' moves that ``model`` (a :meth:`model_at` copy) carried out, ended on
        :attr:`model` too, at the poses the copy left them."""
        for i in range(len(self.model.colliders)):
            if self.model._collider_move(i)[0] is not None and model._collider_move(i)[0] is None:
                self.model._set_collider(i, model.colliders[i], None, None)

    def solve_static(self, q, x0: Tensor, params=(), **solve_kw) -> tuple[Tensor, SolveInfo]:
        """Static equilibrium ``(V, 3)`` with the robot at ``q (J,)``, differentiable with respect to
        ``q`` (and ``params``) by the implicit-function adjoint: one sparse solve in the backward.

        Pinned vertices bound to the robot sit at their forward kinematics; ``solve_kw`` go to
        :func:`~torchbend.solver.solve_static`."""
        q = self.robot.check_joints(q)
        if q.ndim != 1:
            raise ValueError(f"solve_static takes one joint vector ({self.robot.joint_count},), got {tuple(q.shape)}")
        model = self.model_at(q)
        x0 = torch.as_tensor(x0)
        pin_pos = x0[self.model.pinned].to(x0.dtype)
        robot_pos = self.pins.positions(q).to(x0.dtype)
        index = self._slot.to(x0.device)[:, None].expand(-1, 3)
        pin_pos = pin_pos.scatter(0, index, robot_pos)  # differentiable in q
        ends = [t for c in model.colliders[len(self.model.colliders):] for t in c.ends]
        try:
            return solve_static_adjoint(model, x0, list(params) + ends, pin_positions=pin_pos, **solve_kw)
        finally:
            self._settle_static(model)


def trajectory(keyframes, t: float) -> Tensor:
    """Joint vector at time ``t`` [s] from ``keyframes = [(t_k, q_k), ...]`` (increasing ``t_k``):
    smoothstep interpolation between neighbouring keyframes (zero joint velocity at each keyframe),
    held constant outside the keyframe range."""
    times = [float(k[0]) for k in keyframes]
    if t <= times[0]:
        return torch.as_tensor(keyframes[0][1], dtype=torch.float64)
    for (t0, q0), (t1, q1) in zip(keyframes, keyframes[1:]):
        if t <= t1:
            s = (t - t0) / (t1 - t0)
            s = s * s * (3 - 2 * s)
            q0, q1 = torch.as_tensor(q0, dtype=torch.float64), torch.as_tensor(q1, dtype=torch.float64)
            return q0 + s * (q1 - q0)
    return torch.as_tensor(keyframes[-1][1], dtype=torch.float64)
