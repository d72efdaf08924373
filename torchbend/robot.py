r"""Robot-driven cloth: pins bound to link frames and capsule colliders on links, through the
batched, differentiable forward kinematics of pytorch-kinematics (URDF).

* :class:`Robot` loads a URDF (a file, an XML string, or the name of an asset shipped in
  ``torchbend/assets``, e.g. ``"folding_arm.urdf"``) in float64 and evaluates link transforms for
  joint vectors ``q (..., J)`` (``J`` = number of movable joints, in :attr:`Robot.joint_names` order).
* :class:`LinkPins` binds cloth vertices to links: at bind time each vertex is stored in its
  link's local frame; its position for joints ``q`` is ``T_link(q) p_local``, differentiable in ``q``.
* :class:`LinkCapsule` is a capsule fixed in a link's frame; :meth:`LinkCapsule.collider` gives the
  world-space :class:`~torchbend.colliders.Capsule` for ``q`` (tensor end points, differentiable).
* :class:`RobotScene` ties a :class:`~torchbend.solver.ClothModel` to a robot: implicit-Euler steps
  with the pins moved to the forward kinematics of the next joint vector, and a static solve that is
  differentiable with respect to the joint angles (implicit-function adjoint: the equilibrium
  depends on ``q`` through the pinned positions and through the link capsules).

Units: metres, radians (prismatic joints: metres).  Bad input raises ``ValueError`` naming it.
"""
from __future__ import annotations

import copy
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import torch
from torch import Tensor

from .colliders import Capsule, _TensorCapsule
from .implicit import solve_static_adjoint
from .solver import ClothModel, ClothState, SolveInfo, implicit_euler_step

__all__ = ["Robot", "LinkPins", "LinkCapsule", "RobotScene", "asset_path"]

_ASSETS = os.path.join(os.path.dirname(__file__), "assets")
_JOINT_TYPES = {"revolute", "continuous", "prismatic", "fixed"}


def asset_path(name: str) -> str:
    """Path of a file shipped in ``torchbend/assets`` (``ValueError`` listing them if absent)."""
    path = os.path.join(_ASSETS, name)
    if not os.path.isfile(path):
        raise ValueError(f"no asset named {name!r}; shipped assets: {sorted(os.listdir(_ASSETS))}")
    return path


def _read_urdf(urdf: str) -> tuple[str, str]:
    """``(xml text, where)`` from an XML string, a file path or an asset name."""
    if not isinstance(urdf, str):
        raise ValueError(f"urdf must be a path, an asset name or an XML string, got {type(urdf).__name__}")
    if urdf.lstrip().startswith("<"):
        return urdf, "URDF string"
    path = urdf if os.path.isfile(urdf) else os.path.join(_ASSETS, urdf)
    if not os.path.isfile(path):
        raise ValueError(f"URDF file not found: {urdf!r} (neither a file nor one of the shipped assets "
                         f"{sorted(os.listdir(_ASSETS))})")
    with open(path) as f:
        return f.read(), path


def _names(elements, kind: str, where: str) -> list:
    """The ``name`` attributes of URDF elements (``ValueError`` for a missing or repeated one)."""
    names: list = []
    for i, el in enumerate(elements):
        name = el.get("name")
        if not name:
            raise ValueError(f"malformed URDF ({where}): <{kind}> number {i} has no name")
        if name in names:
            raise ValueError(f"malformed URDF ({where}): {kind} {name!r} is declared twice")
        names.append(name)
    return names


def _validate_urdf(text: str, where: str) -> None:
    """Structural checks with messages naming the bad element (pytorch-kinematics fails obscurely)."""
    try:
        root = ET.fromstring(text.encode() if text.lstrip().startswith("<?xml") else text)
    except ET.ParseError as e:
        raise ValueError(f"malformed URDF ({where}): XML syntax error: {e}") from None
    if root.tag != "robot":
        raise ValueError(f"malformed URDF ({where}): the root element must be <robot>, got <{root.tag}>")
    links = _names(root.findall("link"), "link", where)
    joints = root.findall("joint")
    if not joints:
        raise ValueError(f"malformed URDF ({where}): no <joint> elements (a robot needs at least one)")
    children: dict[str, str] = {}
    for name, joint in zip(_names(joints, "joint", where), joints):
        jtype = joint.get("type")
        if jtype not in _JOINT_TYPES:
            raise ValueError(f"malformed URDF ({where}): joint {name!r} has type {jtype!r}; supported: "
                             f"{sorted(_JOINT_TYPES)}")
        for tag in ("parent", "child"):
            el = joint.find(tag)
            link = None if el is None else el.get("link")
            if link is None:
                raise ValueError(f"malformed URDF ({where}): joint {name!r} has no <{tag} link=...>")
            if link not in links:
                raise ValueError(f"malformed URDF ({where}): joint {name!r} names {tag} link {link!r}, "
                                 f"which is not declared")
        child = joint.find("child").get("link")
        if child in children:
            raise ValueError(f"malformed URDF ({where}): link {child!r} is the child of two joints "
                             f"({children[child]!r} and {name!r})")
        children[child] = name
        for tag in ("origin", "axis"):
            el = joint.find(tag)
            for attr in ("xyz", "rpy") if tag == "origin" else ("xyz",):
                value = None if el is None else el.get(attr)
                if value is None:
                    continue
                try:
                    ok = len([float(v) for v in value.split()]) == 3
                except ValueError:
                    ok = False
                if not ok:
                    raise ValueError(f"malformed URDF ({where}): joint {name!r} <{tag} {attr}={value!r}> "
                                     f"must be three numbers")
    roots = [link for link in links if link not in children]
    if len(roots) != 1:
        raise ValueError(f"malformed URDF ({where}): expected one root link (a tree), found {roots}")


def _float64_chain(text: str, device):
    """pytorch-kinematics chain with float64 joint offsets and axes (its URDF reader rounds to float32)."""
    import pytorch_kinematics as pk
    import pytorch_kinematics.transforms as tf
    from pytorch_kinematics.urdf_parser_py.urdf import URDF

    chain = pk.build_chain_from_urdf(text)
    model = URDF.from_xml_string(text)
    joints = {j.name: j for j in model.joints}
    links = {link.name: link for link in model.links}

    def transform(origin):
        if origin is None:
            return tf.Transform3d(dtype=torch.float64)
        rpy = torch.tensor(origin.rpy, dtype=torch.float64)
        return tf.Transform3d(rot=tf.quaternion_from_euler(rpy, "sxyz"), pos=list(origin.xyz), dtype=torch.float64)

    def visit(frame):
        j = joints.get(frame.joint.name)
        if j is not None:
            frame.joint.offset = transform(j.origin)
            axis = torch.tensor(j.axis if j.axis is not None else (0.0, 0.0, 1.0), dtype=torch.float64)
            frame.joint.axis = axis / axis.norm()
        link = links.get(frame.link.name)
        frame.link.offset = transform(link.origin if link is not None else None)
        for child in frame.children:
            visit(child)

    visit(chain._root)
    return pk.Chain(chain._root, dtype=torch.float64, device=device)


class Robot:
    """A URDF robot with batched forward kinematics (pytorch-kinematics), float64 by default.

    Args:
        urdf: a URDF file path, an XML string, or an asset name (``"folding_arm.urdf"``).
        dtype, device: of the transforms returned (joint vectors are cast to them).
    """

    def __init__(self, urdf: str = "folding_arm.urdf", *, dtype=torch.float64, device=None):
        text, where = _read_urdf(urdf)
        _validate_urdf(text, where)
        try:
            chain = _float64_chain(text, device or "cpu")
        except Exception as e:  # the parser's errors are not ValueErrors
            raise ValueError(f"malformed URDF ({where}): {type(e).__name__}: {e}") from None
        self.chain = chain.to(dtype=dtype, device=device or "cpu")
        self.source = where
        self.name = ET.fromstring(text.encode() if text.lstrip().startswith("<?xml") else text).get("name", "robot")
        self.joint_names: list[str] = list(self.chain.get_joint_parameter_names())
        self.link_names: list[str] = list(self.chain.get_frame_names(exclude_fixed=False))
        self.dtype = dtype

    @property
    def joint_count(self) -> int:
        return len(self.joint_names)

    def __repr__(self) -> str:
        return f"Robot({self.name!r}, joints={self.joint_names}, links={self.link_names})"

    def joint_limits(self) -> tuple[Tensor, Tensor]:
        """``(lower, upper)`` ``(J,)`` from the URDF."""
        low, high = self.chain.get_joint_limits()
        return torch.as_tensor(low, dtype=self.dtype), torch.as_tensor(high, dtype=self.dtype)

    def check_joints(self, q, name: str = "q") -> Tensor:
        """``q`` as a floating tensor ``(..., J)`` (``ValueError`` naming a wrong length or bad values)."""
        q = torch.as_tensor(q)
        if not q.is_floating_point():
            q = q.to(self.dtype)
        if q.ndim == 0 or q.shape[-1] != self.joint_count:
            got = "a scalar" if q.ndim == 0 else f"length {q.shape[-1]}"
            raise ValueError(f"joint vector {name} has {got} but robot {self.name!r} has {self.joint_count} "
                             f"movable joints {self.joint_names}")
        if not bool(torch.isfinite(q).all()):
            raise ValueError(f"joint vector {name} holds non-finite values")
        return q

    def check_link(self, link: str, where: str = "link") -> str:
        if link not in self.link_names:
            raise ValueError(f"{where}: robot {self.name!r} has no link {link!r}; links: {self.link_names}")
        return link

    def link_transforms(self, q, links) -> Tensor:
        """World transforms of ``links`` (a list of names) for joints ``q (..., J)``: ``(..., L, 4, 4)``.

        Differentiable in ``q`` (first order; pytorch-kinematics' analytic Jacobian)."""
        q = self.check_joints(q)
        idx = torch.tensor([self.chain.frame_to_idx[self.check_link(n)] for n in links], dtype=torch.long)
        batch = q.shape[:-1]
        qb = q.reshape(-1, self.joint_count).to(dtype=self.chain.dtype, device=self.chain.device)
        T = self.chain.forward_kinematics_tensor(qb)  # (frames, B, 4, 4)
        T = T[idx.to(T.device)].transpose(0, 1)  # (B, L, 4, 4)
        return T.reshape(*batch, len(links), 4, 4).to(dtype=q.dtype)


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


@dataclass(frozen=True)
class LinkCapsule:
    """A capsule fixed in the frame of ``link``: end points ``a``, ``b`` [m] in link coordinates."""

    link: str
    a: tuple = (0.0, 0.0, 0.0)
    b: tuple = (0.1, 0.0, 0.0)
    radius: float = 0.02
    stiffness: float = 1e4
    margin: float = 0.0

    def __post_init__(self):
        c = Capsule(a=self.a, b=self.b, radius=self.radius, stiffness=self.stiffness, margin=self.margin)
        for k in ("a", "b", "radius", "stiffness", "margin"):
            object.__setattr__(self, k, getattr(c, k))

    def endpoints(self, robot: Robot, q) -> Tensor:
        """World end points ``(..., 2, 3)`` [m] for joints ``q (..., J)``."""
        T = robot.link_transforms(q, [robot.check_link(self.link, "LinkCapsule")])[..., 0, None, :, :]
        return _apply(T, torch.tensor([self.a, self.b], dtype=T.dtype, device=T.device))

    def collider(self, robot: Robot, q) -> Capsule:
        """The world-space :class:`Capsule` for one joint vector ``q (J,)`` (tensor end points)."""
        ends = self.endpoints(robot, q)
        if ends.ndim != 2:
            raise ValueError("LinkCapsule.collider takes one joint vector (J,), not a batch")
        return _TensorCapsule(ends[0], ends[1], radius=self.radius, stiffness=self.stiffness, margin=self.margin)


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

    def step(self, state: ClothState, q_next, dt: float, **kw) -> tuple[ClothState, SolveInfo]:
        """One implicit-Euler step to the joint vector ``q_next`` at the end of the step."""
        q_next = self.robot.check_joints(q_next, "q_next").detach()
        x = self.place(state.x, q_next)
        return implicit_euler_step(self.model_at(q_next), ClothState(x, state.v), dt, **kw)

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
        return solve_static_adjoint(model, x0, list(params) + ends, pin_positions=pin_pos, **solve_kw)


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


def check_keyframes(keyframes, robot: Robot, where: str = "trajectory") -> list:
    """Validated ``[(t, q (J,)), ...]`` with strictly increasing times."""
    if not keyframes:
        raise ValueError(f"{where} must list at least one keyframe")
    out = []
    for i, k in enumerate(keyframes):
        if isinstance(k, dict):
            if set(k) != {"t", "q"}:
                raise ValueError(f"{where}[{i}] must be a mapping {{t: seconds, q: [joints]}}, got keys {sorted(k)}")
            t, q = k["t"], k["q"]
        else:
            t, q = k
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise ValueError(f"{where}[{i}].t must be a number, got {t!r}") from None
        if not math.isfinite(t) or (out and t <= out[-1][0]):
            raise ValueError(f"{where}[{i}].t must be finite and larger than the previous keyframe's, got {t}")
        out.append((t, robot.check_joints(torch.as_tensor(q, dtype=torch.float64), f"{where}[{i}].q")))
    return out


@dataclass
class RobotConfig:
    """The ``robot`` section of a scene config, parsed (see :func:`parse_config`)."""

    robot: Robot
    vertices: list
    links: list
    capsules: tuple
    keyframes: list


def parse_config(section: dict, rest: Tensor, where: str = "robot") -> RobotConfig:
    """Parse a scene config's ``robot`` section against the rest mesh ``rest (V, 3)``.

    Keys: ``urdf`` (asset name or path, default ``folding_arm.urdf``); ``pins``: a list of
    ``{link: name, vertices: [indices]}`` or ``{link: name, nearest: [[x, y, z], ...]}`` (the rest
    vertex nearest each point); ``capsules``: a list of ``{link, a, b, radius, stiffness, margin}``
    (end points in link coordinates [m]); ``trajectory``: joint keyframes ``[{t: s, q: [...]}, ...]``.
    """
    if not isinstance(section, dict):
        raise ValueError(f"config key '{where}' must be a mapping")
    unknown = set(section) - {"urdf", "pins", "capsules", "trajectory"}
    if unknown:
        raise ValueError(f"unknown config keys {[f'{where}.{k}' for k in sorted(unknown)]}")
    urdf = section.get("urdf", "folding_arm.urdf")
    if not isinstance(urdf, str):
        raise ValueError(f"config key '{where}.urdf' must be a string, got {urdf!r}")
    robot = Robot(urdf)
    vertices, links = [], []
    for i, pin in enumerate(section.get("pins") or []):
        w = f"{where}.pins[{i}]"
        if not isinstance(pin, dict) or "link" not in pin or len(set(pin) & {"vertices", "nearest"}) != 1 \
                or set(pin) - {"link", "vertices", "nearest"}:
            raise ValueError(f"config key '{w}' must be {{link: name, vertices: [...]}} or {{link: name, nearest: [[x, y, z], ...]}}")
        robot.check_link(str(pin["link"]), f"config key '{w}.link'")
        if "vertices" in pin:
            try:
                idx = [int(v) for v in pin["vertices"]]
            except (TypeError, ValueError):
                raise ValueError(f"config key '{w}.vertices' must be a list of vertex indices") from None
            bad = [v for v in idx if not 0 <= v < len(rest)]
            if bad:
                raise ValueError(f"config key '{w}.vertices': indices {bad} out of range [0, {len(rest)})")
        else:
            try:
                pts = torch.as_tensor(pin["nearest"], dtype=rest.dtype).reshape(-1, 3)
            except (TypeError, ValueError, RuntimeError):
                raise ValueError(f"config key '{w}.nearest' must be a list of [x, y, z] points") from None
            idx = torch.cdist(pts, rest).argmin(-1).tolist()
        vertices += idx
        links += [str(pin["link"])] * len(idx)
    if len(set(vertices)) != len(vertices):
        raise ValueError(f"config key '{where}.pins' binds a vertex twice")
    capsules = []
    for i, c in enumerate(section.get("capsules") or []):
        w = f"{where}.capsules[{i}]"
        if not isinstance(c, dict) or "link" not in c:
            raise ValueError(f"config key '{w}' must be a mapping with a 'link'")
        robot.check_link(str(c["link"]), f"config key '{w}.link'")
        try:
            capsules.append(LinkCapsule(**c))
        except (TypeError, ValueError) as e:
            raise ValueError(f"config key '{w}': {e}") from None
    keyframes = check_keyframes(section.get("trajectory"), robot, f"{where}.trajectory")
    return RobotConfig(robot, vertices, links, tuple(capsules), keyframes)
