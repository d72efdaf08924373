"""Scene configs (YAML): reading, validation and building of the model, initial state and robot.

Keys are documented in :mod:`torchbend.scenes.run`.  Unknown or invalid values raise ``ValueError``
naming the key.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..energies import BendingEnergy, Capsule, MembraneEnergy, Plane, Sphere, stiffness_from_material
from ..mesh import procedural
from ..robot import LinkCapsule, LinkPins, Robot, RobotScene
from ..sim import ClothModel

__all__ = ["load_config", "build_scene", "build_robot_scene", "parse_robot", "check_keyframes", "RobotConfig"]

_SECTIONS = {"scene", "mesh", "material", "bending", "membrane", "colliders", "gravity", "solver", "output", "robot"}


def load_config(path: str) -> dict:
    """Read a YAML scene config (``ValueError`` for a missing file or a malformed document)."""
    import yaml

    if not os.path.isfile(path):
        raise ValueError(f"config file not found: {path}")
    with open(path) as f:
        try:
            cfg = yaml.safe_load(f)
        except yaml.YAMLError as e:
            raise ValueError(f"config {path}: invalid YAML ({e})") from None
    if not isinstance(cfg, dict):
        raise ValueError(f"config {path}: expected a mapping at the top level")
    unknown = set(cfg) - _SECTIONS
    if unknown:
        raise ValueError(f"config {path}: unknown keys {sorted(unknown)}; allowed: {sorted(_SECTIONS)}")
    return cfg


def get_key(section: dict, key: str, where: str, default=None, *, kind=float, positive=False, required=False) -> Any:
    """``section[key]`` converted by ``kind`` (``ValueError`` naming ``where.key`` if missing, malformed or not positive)."""
    if key not in section:
        if required:
            raise ValueError(f"missing config key '{where}.{key}'")
        return default
    value = section[key]
    try:
        value = kind(value)
    except (TypeError, ValueError):
        raise ValueError(f"config key '{where}.{key}' must be a {kind.__name__}, got {value!r}") from None
    if positive and not (value > 0 and (kind is not float or math.isfinite(value))):
        raise ValueError(f"config key '{where}.{key}' must be positive, got {value!r}")
    return value


def _collider(spec: dict, i: int):
    where = f"colliders[{i}]"
    if not isinstance(spec, dict) or "type" not in spec:
        raise ValueError(f"config key '{where}' must be a mapping with a 'type'")
    kinds = {"sphere": Sphere, "plane": Plane, "capsule": Capsule}
    t = spec["type"]
    if t not in kinds:
        raise ValueError(f"config key '{where}.type' must be one of {sorted(kinds)}, got {t!r}")
    kwargs = {k: v for k, v in spec.items() if k != "type"}
    try:
        return kinds[t](**kwargs)
    except TypeError as e:
        raise ValueError(f"config key '{where}': {e}") from None
    except ValueError as e:
        raise ValueError(f"config key '{where}': {e}") from None


def build_scene(cfg: dict, *, thickness: float | None = None, resolution: tuple | None = None):
    """``(model, x0, faces)`` of a config (``thickness``/``resolution`` override the mesh/material).

    With a ``robot`` section the vertices it binds to links are pinned in the model."""
    return _build(cfg, thickness, resolution)[:3]


def build_robot_scene(cfg: dict, *, resolution: tuple | None = None):
    """``(scene, x0, faces, keyframes)`` of a config with a ``robot`` section: a
    :class:`~torchbend.robot.RobotScene` whose pins are bound at the first keyframe's joints."""
    if not cfg.get("robot"):
        raise ValueError("config has no 'robot' section")
    model, x0, faces, rc = _build(cfg, None, resolution)
    assert rc is not None  # the config has a robot section
    pins = LinkPins(rc.robot, rc.vertices, rc.links, x0[rc.vertices], rc.keyframes[0][1])
    scene = RobotScene(model, rc.robot, pins, rc.capsules)
    # the cloth starts with the held vertices exactly at their forward kinematics
    return scene, scene.place(x0, rc.keyframes[0][1]), faces, rc.keyframes


def _bending(b: dict, faces, rest, young: float, t: float, poisson: float) -> BendingEnergy:
    """The ``bending`` section: ``model``, ``stiffness`` [N m] or ``from_material: true``, ``damping``."""
    if b.get("from_material"):
        k = stiffness_from_material(young, t, poisson)
    else:
        k = get_key(b, "stiffness", "bending", required=True)
        if k < 0:
            raise ValueError(f"config key 'bending.stiffness' must be non-negative, got {k}")
    damping = b.get("damping")
    if damping is not None:
        damping = get_key(b, "damping", "bending")
        if damping < 0:
            raise ValueError(f"config key 'bending.damping' must be non-negative, got {damping}")
    try:
        return BendingEnergy(faces, rest, model=b.get("model", "tan"), stiffness=k, damping=damping or None)
    except ValueError as e:
        raise ValueError(f"config key 'bending': {e}") from None


def _pinned(pin, rest: Tensor, nx: int) -> Tensor | None:
    """The ``mesh.pin`` option: ``first_two_columns`` (a clamped beam), ``corners`` or none."""
    if pin is None:
        return None
    if pin == "first_two_columns":
        xs = rest[:, 0].unique()
        return rest[:, 0] <= xs[min(1, len(xs) - 1)] + 1e-12
    if pin == "corners":
        pinned = torch.zeros(len(rest), dtype=torch.bool, device=rest.device)
        pinned[[0, nx - 1]] = True
        return pinned
    raise ValueError(f"config key 'mesh.pin' must be 'first_two_columns' or 'corners', got {pin!r}")


def _build(cfg: dict, thickness, resolution):
    dtype = torch.float64
    mesh = cfg.get("mesh") or {}
    if mesh.get("type", "grid") != "grid":
        raise ValueError(f"config key 'mesh.type' must be 'grid', got {mesh.get('type')!r}")
    nx = get_key(mesh, "nx", "mesh", 11, kind=int, positive=True)
    ny = get_key(mesh, "ny", "mesh", nx, kind=int, positive=True)
    if resolution is not None:
        nx, ny = resolution
    size = mesh.get("size", [1.0, 1.0])
    rest, faces = procedural.grid(nx, ny, tuple(size), dtype=dtype)
    offset = torch.tensor(mesh.get("offset", [0.0, 0.0, 0.0]), dtype=dtype)
    rest = rest + offset
    mat = cfg.get("material") or {}
    young = get_key(mat, "young", "material", 1e5, positive=True)
    poisson = get_key(mat, "poisson", "material", 0.3)
    t = thickness if thickness is not None else get_key(mat, "thickness", "material", 1e-3, positive=True)
    if "volumetric_density" in mat:  # [kg/m^3] -> areal density of this thickness
        density = get_key(mat, "volumetric_density", "material", positive=True) * t
    else:
        density = get_key(mat, "density", "material", 0.2, positive=True)
    bend = None if cfg.get("bending") is None else _bending(cfg["bending"], faces, rest, young, t, poisson)
    mem = None
    if cfg.get("membrane") is not None:
        m = cfg["membrane"]
        try:
            mem = MembraneEnergy(faces, rest, model=m.get("model", "stvk"), young=young, poisson=poisson, thickness=t)
        except ValueError as e:
            raise ValueError(f"config key 'membrane': {e}") from None
    pinned = _pinned(mesh.get("pin"), rest, nx)
    rc = None
    if cfg.get("robot") is not None:
        rc = parse_robot(cfg["robot"], rest)
        if pinned is None:
            pinned = torch.zeros(len(rest), dtype=torch.bool)
        pinned = pinned.clone()
        pinned[rc.vertices] = True
    colliders = [_collider(c, i) for i, c in enumerate(cfg.get("colliders") or [])]
    gravity = cfg.get("gravity", [0.0, 0.0, -9.81])
    model = ClothModel(faces, rest, bending=bend, membrane=mem, density=density,
                       gravity=gravity, pinned=pinned, colliders=colliders)
    return model, rest.clone(), faces, rc


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
    """The ``robot`` section of a scene config, parsed (see :func:`parse_robot`)."""

    robot: Robot
    vertices: list
    links: list
    capsules: tuple
    keyframes: list


def parse_robot(section: dict, rest: Tensor, where: str = "robot") -> RobotConfig:
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
