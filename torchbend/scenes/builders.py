"""Builders: the cloth model, its rest mesh, pins, colliders and robot from a validated config
(:mod:`torchbend.scenes.schema`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..energies import BendingEnergy, Capsule, MembraneEnergy, Plane, Sphere, stiffness_from_material
from ..mesh import procedural
from ..robot import LinkCapsule, LinkPins, Robot, RobotScene
from ..sim import ClothModel, MeshCollider, SelfContact
from .schema import (
    _AXES,
    BendingSection,
    FileMesh,
    GridMesh,
    KeyframeSpec,
    PhysicsConfig,
    PinRegion,
    RobotSection,
    SceneConfig,
    check_resolution,
    mesh_file,
    validate,
)
from .wording import ConfigError, short_repr

__all__ = [
    "build_model", "build_colliders", "build_scene", "build_mesh", "build_collider", "build_robot_scene", "parse_robot", "check_keyframes",
    "RobotConfig", "build_pins",
]

# ------------------------------------------------------------------------------ building scenes
def build_scene(cfg, *, thickness: float | None = None, resolution: tuple | None = None, device=None):
    """``(model, x0, faces)`` of a scene config (a dict or :class:`SceneConfig`; ``thickness`` and
    ``resolution`` override the material and the grid; tensors on ``device``, default CPU).

    With a ``robot`` section the vertices it binds to links are pinned in the model."""
    return _build(validate(cfg, SceneConfig), thickness, resolution, device)[:3]


def build_robot_scene(cfg, *, resolution: tuple | None = None):
    """``(scene, x0, faces, keyframes)`` of a config with a ``robot`` section: a
    :class:`~torchbend.robot.RobotScene` whose pins are bound at the first keyframe's joints."""
    cfg = validate(cfg, SceneConfig)
    if cfg.robot is None:
        raise ConfigError("config has no 'robot' section")
    model, x0, faces, rc = _build(cfg, None, resolution, None)
    assert rc is not None  # the config has a robot section
    pins = LinkPins(rc.robot, rc.vertices, rc.links, x0[rc.vertices], rc.keyframes[0][1])
    scene = RobotScene(model, rc.robot, pins, rc.capsules)
    # the cloth starts with the held vertices exactly at their forward kinematics
    return scene, scene.place(x0, rc.keyframes[0][1]), faces, rc.keyframes


def build_mesh(mesh, *, resolution: tuple | None = None, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor]:
    """``(rest (V, 3) [m], faces (F, 3))`` of a ``mesh`` section (dict, :class:`GridMesh` or
    :class:`FileMesh`), offset applied; ``resolution = (nx, ny)`` overrides a grid's size."""
    if not isinstance(mesh, (GridMesh, FileMesh)):
        mesh = validate({"mesh": mesh}, SceneConfig).mesh
    if isinstance(mesh, GridMesh):
        nx, ny = (check_resolution(*resolution, where="--resolution") if resolution is not None
                  else (mesh.nx, mesh.ny or mesh.nx))
        rest, faces = procedural.grid(nx, ny, mesh.size, dtype=dtype, device=device)
        if mesh.layers > 1:  # a stack of sheets, each turned about its centre from the one below
            centre = rest.mean(0)
            sheets, tris = [], []
            for k in range(mesh.layers):
                a = math.radians(k * mesh.layer_twist)
                R = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
                                 dtype=dtype, device=rest.device)
                sheets.append((rest - centre) @ R.T + centre + torch.tensor([0.0, 0.0, k * mesh.layer_gap], dtype=dtype,
                                                                             device=rest.device))
                tris.append(faces + k * rest.shape[0])
            rest, faces = torch.cat(sheets), torch.cat(tris)
    else:
        from ..mesh import load  # pyright: ignore[reportAttributeAccessIssue]

        if resolution is not None:
            raise ConfigError("--resolution applies to grid meshes only, not to 'mesh.path' files")
        try:
            rest, faces = load(mesh_file(mesh.path), weld_tol=mesh.weld_tol, dtype=dtype, device=device)
        except ValueError as e:
            raise ConfigError(f"config key 'mesh.path': {e}") from None
        except OSError as e:  # a directory, no permission to read, ...
            raise ConfigError(f"config key 'mesh.path': cannot read {mesh.path}: {e.strerror or e}") from None
    return rest + torch.tensor(mesh.offset, dtype=dtype, device=rest.device), faces


def _bending(b: BendingSection, faces, rest, young: float, t: float, poisson: float) -> BendingEnergy:
    k = stiffness_from_material(young, t, poisson) if b.from_material else b.stiffness
    if k is None:
        raise ConfigError("config key 'bending.stiffness' is required unless 'bending.from_material' is true")
    try:
        return BendingEnergy(faces, rest, model=b.model, stiffness=k, damping=b.damping or None)
    except ValueError as e:
        raise ConfigError(f"config key 'bending': {e}") from None


def build_pins(mesh, rest: Tensor, *, resolution: tuple | None = None) -> Tensor | None:
    """The ``(V,)`` bool mask of a mesh section's ``pin`` (``None`` when it pins nothing) for the rest
    positions ``rest (V, 3)`` [m] of :func:`build_mesh` (offset applied).

    ``pin``: ``first_two_columns`` (a clamped beam), ``corners`` (the first row's two corners: the
    grid's ``nx`` or ``resolution[0]`` vertices apart), vertex indices, or a :class:`PinRegion`
    (bounds and nearest points in the mesh's own coordinates, before ``offset``).
    :class:`ConfigError` naming ``mesh.pin`` for indices out of range or a region without vertices."""
    if not isinstance(mesh, (GridMesh, FileMesh)):
        mesh = validate({"mesh": mesh}, SceneConfig).mesh
    pin = mesh.pin
    if pin is None:
        return None
    mask = torch.zeros(len(rest), dtype=torch.bool, device=rest.device)
    if isinstance(pin, str):  # the schema allows only these two, and only for grids
        if pin == "first_two_columns":
            xs = rest[:, 0].unique()
            return rest[:, 0] <= xs[min(1, len(xs) - 1)] + 1e-12
        nx = resolution[0] if resolution is not None else getattr(mesh, "nx", 0)
        mask[[0, nx - 1]] = True  # corners
        return mask
    if isinstance(pin, PinRegion):
        return _region_mask(pin, rest - torch.tensor(mesh.offset, dtype=rest.dtype, device=rest.device))
    bad = [v for v in pin if v >= len(rest)]
    if bad:
        raise ConfigError(f"config key 'mesh.pin': vertex indices {bad} out of range [0, {len(rest)})")
    mask[pin] = True
    return mask


def _region_mask(pin: PinRegion, local: Tensor) -> Tensor:
    """The ``(V,)`` mask of a pin region for rest positions ``local (V, 3)`` in the mesh's own coordinates."""
    mask = torch.zeros(len(local), dtype=torch.bool, device=local.device)
    bounded = False
    inside = torch.ones(len(local), dtype=torch.bool, device=local.device)
    for j, a in enumerate(_AXES):
        lo, hi = getattr(pin, f"{a}_min"), getattr(pin, f"{a}_max")
        if lo is not None:
            inside &= local[:, j] >= lo
        if hi is not None:
            inside &= local[:, j] <= hi
        bounded |= lo is not None or hi is not None
    if bounded:
        mask |= inside
    if pin.nearest is not None:
        pts = torch.tensor(pin.nearest, dtype=local.dtype, device=local.device).reshape(-1, 3)
        mask[torch.cdist(pts, local).argmin(-1)] = True
    if not mask.any():
        lo, hi = local.amin(0).tolist(), local.amax(0).tolist()
        span = ", ".join(f"{a} [{lo[j]:.4g}, {hi[j]:.4g}]" for j, a in enumerate(_AXES))
        raise ConfigError(f"config key 'mesh.pin': the region holds no vertex (the mesh spans {span} m, "
                          "before offset)")
    return mask


def build_collider(spec):
    """The :class:`~torchbend.Sphere`, :class:`~torchbend.Plane`, :class:`~torchbend.Capsule` or
    :class:`~torchbend.MeshCollider` of a ``colliders`` entry (a validated spec)."""
    if spec.type == "mesh":
        if spec.shape == "mannequin":
            vertices, faces = procedural.mannequin(dtype=torch.float64)
        else:
            from ..mesh import load  # pyright: ignore[reportAttributeAccessIssue]

            vertices, faces = load(mesh_file(spec.path))
            vertices = vertices.to(torch.float64)
        vertices = vertices + torch.tensor(spec.offset, dtype=vertices.dtype)
        return MeshCollider(vertices, faces, dhat=spec.dhat, stiffness=spec.stiffness, friction=spec.friction,
                            eps_v=spec.eps_v)
    kinds = {"sphere": Sphere, "plane": Plane, "capsule": Capsule}
    return kinds[spec.type](**spec.model_dump(exclude={"type"}))


def build_colliders(specs, where: str = "colliders") -> list:
    """The colliders of a ``colliders`` list (validated specs); :class:`ConfigError` naming the entry."""
    out = []
    for i, c in enumerate(specs):
        try:
            out.append(build_collider(c))
        except ValueError as e:
            raise ConfigError(f"config key '{where}[{i}]': {e}") from None
    return out


def build_model(cfg, *, mesh: tuple[Tensor, Tensor] | None = None, pinned: Tensor | None = None,
                thickness: float | None = None, resolution: tuple | None = None, dtype=torch.float64,
                device=None, colliders=None) -> ClothModel:
    """The :class:`~torchbend.ClothModel` of the physics sections of a config (a :class:`PhysicsConfig`
    or any config that has them, a dict or validated): ``bending`` and ``membrane`` (each term only when
    its section is given), ``material`` (``thickness`` overrides its own), ``colliders`` (``colliders``, a
    list, replaces them), ``gravity``, the pins of ``mesh.pin`` or ``pinned`` ``(V,)`` bool.  ``mesh =
    (rest (V, 3), faces (F, 3))`` replaces the config's mesh (offset applied); tensors in ``dtype`` on
    ``device``.  :class:`ConfigError` naming the key for anything that does not fit."""
    if not isinstance(cfg, PhysicsConfig):
        cfg = validate(cfg, PhysicsConfig if isinstance(cfg, dict) and "scene" not in cfg else SceneConfig)
    if mesh is None:
        rest, faces = build_mesh(cfg.mesh, resolution=resolution, dtype=dtype, device=device)
        if pinned is None:
            pinned = build_pins(cfg.mesh, rest, resolution=resolution)
    else:
        rest, faces = mesh[0].to(dtype=dtype, device=device), mesh[1].to(device)
    built = build_colliders(cfg.colliders) if colliders is None else list(colliders)
    mat = cfg.material
    t = thickness if thickness is not None else mat.thickness
    density = mat.volumetric_density * t if mat.volumetric_density is not None else mat.density
    bend = None if cfg.bending is None else _bending(cfg.bending, faces, rest, mat.young, t, mat.poisson)
    mem = None
    if cfg.membrane is not None:
        try:
            mem = MembraneEnergy(faces, rest, model=cfg.membrane.model, young=mat.young, poisson=mat.poisson, thickness=t)
        except ValueError as e:
            raise ConfigError(f"config key 'membrane': {e}") from None
    terms = [] if cfg.self_contact is None else [SelfContact(**cfg.self_contact.model_dump())]
    return ClothModel(faces, rest, bending=bend, membrane=mem, density=density, gravity=cfg.gravity, pinned=pinned,
                      colliders=built, terms=terms)


def _build(cfg: SceneConfig, thickness, resolution, device):
    rest, faces = build_mesh(cfg.mesh, resolution=resolution, dtype=torch.float64, device=device)
    # the cheap checks (pins, robot, colliders) before the energies are built
    pinned = build_pins(cfg.mesh, rest, resolution=resolution)
    rc = None
    if cfg.robot is not None:
        rc = parse_robot(cfg.robot, rest)
        if pinned is None:
            pinned = torch.zeros(len(rest), dtype=torch.bool, device=rest.device)
        pinned = pinned.clone()
        pinned[rc.vertices] = True
    colliders = build_colliders(cfg.colliders)
    model = build_model(cfg, mesh=(rest, faces), pinned=pinned, thickness=thickness, device=device, colliders=colliders)
    return model, rest.clone(), faces, rc


def check_keyframes(keyframes, robot: Robot, where: str = "trajectory") -> list:
    """Validated ``[(t, q (J,)), ...]`` with strictly increasing times."""
    if not keyframes:
        raise ConfigError(f"{where} must list at least one keyframe")
    out = []
    for i, k in enumerate(keyframes):
        if isinstance(k, KeyframeSpec):
            t, q = k.t, k.q
        elif isinstance(k, dict):
            if set(k) != {"t", "q"}:
                raise ConfigError(f"{where}[{i}] must be a mapping {{t: seconds, q: [joints]}}, got keys {sorted(k)}")
            t, q = k["t"], k["q"]
        else:
            t, q = k
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}[{i}].t must be a number, got {short_repr(t)}") from None
        if not math.isfinite(t) or (out and t <= out[-1][0]):
            raise ConfigError(f"{where}[{i}].t must be finite and larger than the previous keyframe's, got {t}")
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


def parse_robot(section, rest: Tensor, where: str = "robot") -> RobotConfig:
    """Parse a scene config's ``robot`` section (a dict or :class:`RobotSection`) against the rest
    mesh ``rest (V, 3)``.

    Keys: ``urdf`` (asset name or path, default ``folding_arm.urdf``); ``pins``: a list of
    ``{link: name, vertices: [indices]}`` or ``{link: name, nearest: [[x, y, z], ...]}`` (the rest
    vertex nearest each point); ``capsules``: a list of ``{link, a, b, radius, stiffness, margin}``
    (end points in link coordinates [m]); ``trajectory``: joint keyframes ``[{t: s, q: [...]}, ...]``.
    """
    section = validate(section, RobotSection, prefix=where)
    robot = Robot(section.urdf)
    vertices, links = [], []
    for i, pin in enumerate(section.pins):
        w = f"{where}.pins[{i}]"
        robot.check_link(pin.link, f"config key '{w}.link'")
        if pin.vertices is not None:
            idx = list(pin.vertices)
            bad = [v for v in idx if not 0 <= v < len(rest)]
            if bad:
                raise ConfigError(f"config key '{w}.vertices': indices {bad} out of range [0, {len(rest)})")
        else:
            pts = torch.tensor(pin.nearest, dtype=rest.dtype, device=rest.device).reshape(-1, 3)
            idx = torch.cdist(pts, rest).argmin(-1).tolist()
        vertices += idx
        links += [pin.link] * len(idx)
    if len(set(vertices)) != len(vertices):
        raise ConfigError(f"config key '{where}.pins' binds a vertex twice")
    capsules = []
    for i, c in enumerate(section.capsules):
        w = f"{where}.capsules[{i}]"
        robot.check_link(c.link, f"config key '{w}.link'")
        try:
            capsules.append(LinkCapsule(**c.model_dump()))
        except ValueError as e:
            raise ConfigError(f"config key '{w}': {e}") from None
    keyframes = check_keyframes(section.trajectory, robot, f"{where}.trajectory")
    return RobotConfig(robot, vertices, links, tuple(capsules), keyframes)
