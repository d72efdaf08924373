"""Configs (YAML) for scenes and training: one typed, validated schema (pydantic), reading, and the
builders of the model, initial state and robot of a scene config.

* :class:`Section` is the base of every config section: unknown keys are rejected, numbers must be
  finite and not booleans.  :class:`SceneConfig` is the scene schema (sections ``scene``, ``mesh``,
  ``material``, ``bending``, ``membrane``, ``colliders``, ``gravity``, ``solver``, ``output``,
  ``robot``; keys documented on each section and in :mod:`torchbend.scenes.run`).  The training
  scripts (``train/``) subclass :class:`Section` for their own sections.
* :func:`load_config` reads a YAML file, applies ``KEY=VALUE`` overrides (``solver.tol=1e-8``,
  ``colliders[0].radius=0.2``), validates it against a schema and returns the validated config as a
  plain dict (defaults filled in; only numbers, strings, booleans, lists and dicts), fit for a
  ``torch.load(..., weights_only=True)`` checkpoint.  :func:`validate` does the same for a dict.
* Every problem is a :class:`ConfigError` (a ``ValueError``) naming the key's full dotted path:
  ``unknown config key 'solver.tol_x' (allowed: ...)``, ``config key 'colliders[0].radius' must be
  positive, got -1``, ``missing config key 'robot.pins[1].link'``.
"""
from __future__ import annotations

import math
import operator
import os
import re
import reprlib
import types
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Optional, TypeGuard, TypeVar, Union, get_args, get_origin

import torch
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)
from torch import Tensor

from ..energies import BendingEnergy, Capsule, MembraneEnergy, Plane, Sphere, stiffness_from_material
from ..mesh import procedural
from ..ops.membrane import MembraneModel
from ..ops.psi import BendingModel
from ..options import Projection
from ..robot import LinkCapsule, LinkPins, Robot, RobotScene
from ..sim import ClothModel
from ..sim.newton import LinearMethod

__all__ = [
    "ConfigError", "Section", "SceneConfig", "load_config", "validate", "apply_overrides", "build_scene",
    "build_mesh", "build_collider", "build_robot_scene", "parse_robot", "check_keyframes", "RobotConfig",
    "Float", "Int", "Positive", "NonNegative", "PositiveInt", "Vec3", "GridMesh", "FileMesh", "MeshSpec", "MeshField",
    "PinRegion", "build_pins", "mesh_file", "ASSET_PREFIX", "SphereSpec", "PlaneSpec", "CapsuleSpec", "RobotSection",
    "Seed", "short_repr", "one_line", "QUOTE_LIMIT", "MAX_GRID_VERTICES", "check_resolution", "read_yaml",
]


M = TypeVar("M", bound=BaseModel)


QUOTE_LIMIT = 200
"""The most characters of an offending value (or of any one quoted run or word) a message shows."""
MESSAGE_LIMIT = 1000
"""The most characters of a whole error message (longer ones keep their start and end)."""
MAX_ERRORS = 5
"""The most validation errors one :class:`ConfigError` lists (then ``... and N more``)."""

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = QUOTE_LIMIT
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 8
_REPR.maxlevel = 4


def _clip(text: str, limit: int) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def short_repr(value: Any, limit: int = QUOTE_LIMIT) -> str:
    """``repr(value)`` in at most about ``limit`` characters (long strings and deep or long
    containers elided with ``...``), for quoting a user's value in an error message."""
    try:
        text = _REPR.repr(value)
    except Exception:  # a value whose repr fails is quoted by its type
        text = f"<{type(value).__name__}>"
    return _clip(text, limit)


# a quoted run (the closing quote kept) or a word, longer than QUOTE_LIMIT
_LONG = re.compile("('[^'\n]{N,})'|(\"[^\"\n]{N,})\"|(\\S{N,})".replace("N", str(QUOTE_LIMIT)))


def _clip_match(m: re.Match) -> str:
    if m.group(3) is not None:
        return _clip(m.group(3), QUOTE_LIMIT)
    quoted = m.group(1) if m.group(1) is not None else m.group(2)
    return _clip(quoted, QUOTE_LIMIT) + quoted[0]


def one_line(message: Any, limit: int = MESSAGE_LIMIT) -> str:
    """``message`` as one line of at most about ``limit`` characters: line breaks become spaces, a
    quoted run or a word longer than :data:`QUOTE_LIMIT` keeps its first :data:`QUOTE_LIMIT`
    characters (then ``... (N characters)``), an overlong whole keeps its start and end."""
    text = re.sub(r"\s*[\r\n]+\s*", " ", str(message)).strip()
    text = _LONG.sub(_clip_match, text)
    if len(text) > limit:
        text = f"{text[:limit * 3 // 4]} ... {text[-(limit // 4):]}"
    return text


class ConfigError(ValueError):
    """A config problem: the message names the key's dotted path (``solver.tol``, ``colliders[0].radius``).

    The message is kept to one line and quotes at most about :data:`QUOTE_LIMIT` characters of any
    value (:func:`one_line`)."""

    def __init__(self, message: Any = ""):
        super().__init__(one_line(message))


# ------------------------------------------------------------------------------ field types
def _number(value):
    """Numbers only: YAML's ``true``/``false`` are not 0/1 (pydantic's lax mode would take them)."""
    if isinstance(value, bool):
        raise ValueError(f"must be a number, got {short_repr(value)}")
    return value


def _vec3(value):
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 3:
        raise ValueError(f"must be a list of 3 numbers [x, y, z], got {short_repr(value)}")
    return [_number(v) for v in value]


def _pair(value):
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ValueError(f"must be a list of 2 numbers, got {short_repr(value)}")
    return [_number(v) for v in value]


Float = Annotated[float, BeforeValidator(_number)]
Int = Annotated[int, BeforeValidator(_number)]
Positive = Annotated[float, Field(gt=0), BeforeValidator(_number)]
NonNegative = Annotated[float, Field(ge=0), BeforeValidator(_number)]
PositiveInt = Annotated[int, Field(gt=0), BeforeValidator(_number)]
NonNegativeInt = Annotated[int, Field(ge=0), BeforeValidator(_number)]
Vec3 = Annotated[tuple[float, float, float], BeforeValidator(_vec3)]
SEED_LIMIT = 2**32
Seed = Annotated[int, Field(ge=0, lt=SEED_LIMIT), BeforeValidator(_number)]
"""A random seed: an integer in [0, 2**32) (every generator seeded with it accepts it)."""

MAX_GRID_VERTICES = 10_000_000
"""The most vertices of a grid mesh (``nx * ny``): beyond, memory runs out long before a step."""


def check_resolution(nx, ny, where: str = "mesh.nx x mesh.ny") -> tuple[int, int]:
    """``(nx, ny)`` of a grid when both are integers >= 2 with ``nx * ny <= MAX_GRID_VERTICES``;
    :class:`ConfigError` naming ``where`` otherwise."""
    sides = []
    for n in (nx, ny):
        try:
            side = operator.index(n)
        except TypeError:
            side = None
        if side is None or isinstance(n, bool) or side < 2:
            raise ConfigError(f"{where}: a grid needs an integer >= 2 of vertices per side, got {short_repr(n)}")
        sides.append(side)
    if sides[0] * sides[1] > MAX_GRID_VERTICES:
        raise ConfigError(f"{where}: a grid of {sides[0]} x {sides[1]} vertices is more than the "
                          f"{MAX_GRID_VERTICES} allowed")
    return sides[0], sides[1]


class Section(BaseModel):
    """Base of every config section: unknown keys rejected, numbers finite."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def _option(cls, what: str):
    """A field validator: the value must name a member of the option enum ``cls`` (stored as its string)."""
    def check(value):
        member = cls.parse(value, what=what)
        return value if isinstance(value, str) else member.value  # the user's spelling
    return check


# ------------------------------------------------------------------------------ scene schema
class SceneSection(Section):
    """``scene``: ``kind`` = ``dynamic`` (implicit Euler steps), ``robot`` (steps of a robot-held cloth)
    or ``static`` (one static solve per thickness)."""

    kind: Literal["dynamic", "robot", "static"] = "dynamic"


_AXES = ("x", "y", "z")


class PinRegion(Section):
    """``mesh.pin`` as a region: the vertices whose rest position, in the mesh's own coordinates
    (before ``offset``), lies within every bound given (``x_min`` ... ``z_max`` [m], inclusive), plus
    the vertex nearest each point of ``nearest`` ([[x, y, z], ...] [m], same coordinates).  At least
    one key; e.g. ``pin: {z_min: -0.001}`` pins the skirt's waist ring (z = 0)."""

    x_min: Float | None = None
    x_max: Float | None = None
    y_min: Float | None = None
    y_max: Float | None = None
    z_min: Float | None = None
    z_max: Float | None = None
    nearest: Annotated[list[Vec3], Field(min_length=1)] | None = None

    @model_validator(mode="after")
    def _bounds(self):
        keys = [f"{a}_{m}" for a in _AXES for m in ("min", "max")]
        if self.nearest is None and all(getattr(self, k) is None for k in keys):
            raise ValueError(f"a pin region needs at least one of {', '.join(keys)}, nearest")
        for a in _AXES:
            lo, hi = getattr(self, f"{a}_min"), getattr(self, f"{a}_max")
            if lo is not None and hi is not None and lo > hi:
                raise ValueError(f"{a}_min ({lo}) must not exceed {a}_max ({hi})")
        return self


def _pin_kind(value) -> str:
    """Which form of ``mesh.pin`` a value is (the discriminator of ``GridPin`` and ``FilePin``)."""
    if isinstance(value, (Mapping, BaseModel)):
        return "region"
    if isinstance(value, (list, tuple)):
        return "vertices"
    return "name"


def _pin_name(names: tuple[str, ...]) -> BeforeValidator:
    """The validator of ``mesh.pin`` given as a string: one of ``names``; the message lists every form."""
    forms = "".join(f"'{k}', " for k in names) + "a list of vertex indices, a region {x_min: ..., z_max: ..., nearest: ...}"

    def name(value):
        if isinstance(value, str) and value in names:
            return value
        raise ValueError(f"must be {forms} or null, got {short_repr(value)}")

    return BeforeValidator(name)


# ``mesh.pin``: a region, vertex indices, a name (grids: first_two_columns, corners) or null
GridPin = Optional[Annotated[Union[
    Annotated[PinRegion, Tag("region")],
    Annotated[list[NonNegativeInt], Tag("vertices")],
    Annotated[str, _pin_name(("first_two_columns", "corners")), Tag("name")],
], Discriminator(_pin_kind)]]
FilePin = Optional[Annotated[Union[
    Annotated[PinRegion, Tag("region")],
    Annotated[list[NonNegativeInt], Tag("vertices")],
    Annotated[str, _pin_name(()), Tag("name")],
], Discriminator(_pin_kind)]]


class GridMesh(Section):
    """``mesh`` of ``type: grid`` (the default): ``nx * ny`` vertices on ``size`` [m] in the z = 0
    plane, moved by ``offset`` [m]; ``pin``: ``first_two_columns`` (a clamped beam), ``corners`` (the
    two corners of the first row), a list of vertex indices or a region (:class:`PinRegion`)."""

    type: Literal["grid"] = "grid"
    nx: Annotated[int, Field(ge=2), BeforeValidator(_number)] = 11
    ny: Annotated[int, Field(ge=2), BeforeValidator(_number)] | None = None  # default: nx
    size: Annotated[tuple[Positive, Positive], BeforeValidator(_pair)] = (1.0, 1.0)
    offset: Vec3 = (0.0, 0.0, 0.0)
    pin: GridPin = None

    @model_validator(mode="after")
    def _size(self):
        n, m = self.nx, self.ny or self.nx
        if n * m > MAX_GRID_VERTICES:
            raise ValueError(f"nx x ny = {n} x {m} vertices is more than the {MAX_GRID_VERTICES} a grid may have")
        return self


ASSET_PREFIX = "asset:"


def mesh_file(path: str) -> str:
    """The file of a ``mesh.path``: ``asset:NAME`` is the mesh ``NAME`` shipped with torchbend
    (:func:`torchbend.mesh.asset_path`, e.g. ``asset:skirt.obj``), anything else a file path."""
    if path.startswith(ASSET_PREFIX):
        from ..mesh import asset_path

        return asset_path(path[len(ASSET_PREFIX):])
    return path


class FileMesh(Section):
    """``mesh`` read from a file (``mesh: path.obj`` is short for ``{type: file, path: path.obj}``):
    :func:`torchbend.mesh.load` with vertex welding within ``weld_tol`` (relative to the mesh size).
    ``path``: a file (a relative path is relative to the config file's folder) or ``asset:NAME``, a
    mesh shipped with torchbend (``asset:skirt.obj``).  ``offset`` [m]; ``pin``: a list of vertex
    indices (of the welded mesh) or a region (:class:`PinRegion`, e.g. ``{z_min: -0.001}``)."""

    type: Literal["file"]
    path: str
    weld_tol: NonNegative = 1e-6
    offset: Vec3 = (0.0, 0.0, 0.0)
    pin: FilePin = None

    @field_validator("path")
    @classmethod
    def _shipped(cls, value: str):
        mesh_file(value)  # an unknown asset name: ValueError listing the shipped meshes
        return value


class MaterialSection(Section):
    """``material``: ``young`` [Pa], ``poisson``, ``thickness`` [m] (or ``thicknesses`` for a static
    sweep), ``density`` [kg/m^2] or ``volumetric_density`` [kg/m^3] (times the thickness)."""

    young: Positive = 1e5
    poisson: Annotated[float, Field(gt=-1.0, le=0.5), BeforeValidator(_number)] = 0.3
    thickness: Positive = 1e-3
    thicknesses: Annotated[list[Positive], Field(min_length=1)] | None = None
    density: Positive = 0.2
    volumetric_density: Positive | None = None


class BendingSection(Section):
    """``bending``: ``model`` (``quadratic``, ``tan``, ``sin``), ``stiffness`` [N m] or
    ``from_material: true`` (``Y t^3 / (24 (1 - nu^2))``), ``damping`` [N m s]."""

    model: str = "tan"
    stiffness: NonNegative | None = None
    from_material: bool = False
    damping: NonNegative | None = None

    _check_model = field_validator("model")(_option(BendingModel, "bending model"))

    @model_validator(mode="after")
    def _stiffness_or_material(self):
        if (self.stiffness is None) == (not self.from_material):
            raise ValueError("give either 'stiffness' [N m] or 'from_material: true'" +
                             (", not both" if self.from_material else ""))
        return self


class MembraneSection(Section):
    """``membrane``: ``model`` (``stvk``, ``arap``, ``symmetric_dirichlet``, ``neohookean``); the
    moduli and thickness come from ``material``."""

    model: str = "stvk"

    _check_model = field_validator("model")(_option(MembraneModel, "membrane model"))


class _ColliderSpec(Section):
    stiffness: Positive = 1e4  # [N/m]
    margin: NonNegative = 0.0  # [m]


class SphereSpec(_ColliderSpec):
    """``{type: sphere, center, radius, stiffness, margin}`` (:class:`~torchbend.Sphere`)."""

    type: Literal["sphere"]
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: Positive = 1.0


class PlaneSpec(_ColliderSpec):
    """``{type: plane, point, normal, stiffness, margin}`` (:class:`~torchbend.Plane`)."""

    type: Literal["plane"]
    point: Vec3 = (0.0, 0.0, 0.0)
    normal: Vec3 = (0.0, 0.0, 1.0)


class CapsuleSpec(_ColliderSpec):
    """``{type: capsule, a, b, radius, stiffness, margin}`` (:class:`~torchbend.Capsule`)."""

    type: Literal["capsule"]
    a: Vec3 = (0.0, 0.0, 0.0)
    b: Vec3 = (1.0, 0.0, 0.0)
    radius: Positive = 0.1


ColliderSpec = Annotated[Union[SphereSpec, PlaneSpec, CapsuleSpec], Field(discriminator="type")]
MeshSpec = Annotated[Union[GridMesh, FileMesh], Field(discriminator="type")]


class SolverSection(Section):
    """``solver``: ``dt`` [s], ``steps``, ``hessian`` (projection), ``linear_solver``, ``tol``,
    ``max_iters`` (defaults per scene kind: 1e-6 and 30 for steps, 1e-9 and 50 for static solves),
    ``load_steps`` (static scenes: gravity ramped in that many equal increments)."""

    dt: Positive = 1 / 60
    steps: PositiveInt = 60
    hessian: str = "exact"
    linear_solver: str = "direct"
    tol: Positive | None = None
    max_iters: PositiveInt | None = None
    load_steps: PositiveInt = 1

    _check_hessian = field_validator("hessian")(_option(Projection, "Hessian projection"))
    _check_linear = field_validator("linear_solver")(_option(LinearMethod, "linear solver"))


class OutputSection(Section):
    """``output``: ``every`` (write a frame every that many steps)."""

    every: PositiveInt = 1


def _keyframe(value):
    if isinstance(value, (list, tuple)) and len(value) == 2:  # [t, q]
        return {"t": value[0], "q": value[1]}
    return value


class PinSpec(Section):
    """``robot.pins[i]``: ``{link: name, vertices: [indices]}`` or ``{link: name, nearest: [[x, y, z], ...]}``
    (the rest vertex nearest each point)."""

    link: str
    vertices: list[NonNegativeInt] | None = None
    nearest: list[Vec3] | None = None

    @model_validator(mode="after")
    def _one_of(self):
        if (self.vertices is None) == (self.nearest is None):
            raise ValueError("give either 'vertices: [indices]' or 'nearest: [[x, y, z], ...]'")
        return self


class LinkCapsuleSpec(Section):
    """``robot.capsules[i]``: a capsule fixed in ``link``'s frame (:class:`~torchbend.robot.LinkCapsule`),
    end points ``a``, ``b`` [m] in link coordinates."""

    link: str
    a: Vec3 = (0.0, 0.0, 0.0)
    b: Vec3 = (0.1, 0.0, 0.0)
    radius: Positive = 0.02
    stiffness: Positive = 1e4
    margin: NonNegative = 0.0


class KeyframeSpec(Section):
    """``robot.trajectory[i]``: ``{t: seconds, q: [joints]}`` (or ``[t, q]``)."""

    t: Float
    q: list[Float]


class RobotSection(Section):
    """``robot``: ``urdf`` (asset name or path), ``pins``, ``capsules``, ``trajectory`` (joint keyframes)."""

    urdf: str = "folding_arm.urdf"
    pins: list[PinSpec] = []
    capsules: list[LinkCapsuleSpec] = []
    trajectory: list[Annotated[KeyframeSpec, BeforeValidator(_keyframe)]] = []


def _mesh_shorthand(value):
    if value is None:
        return {"type": "grid"}
    if isinstance(value, str):
        return {"type": "file", "path": value}
    if isinstance(value, dict) and "type" not in value:
        return {"type": "grid", **value}
    return value


def _optional_mesh(value):
    return None if value is None else _mesh_shorthand(value)


# a ``mesh`` key that may be absent (the training scripts): null, a path (``mesh: garment.obj``), a grid or a file
MeshField = Annotated[MeshSpec | None, BeforeValidator(_optional_mesh)]


class SceneConfig(Section):
    """A scene config (every section optional)."""

    scene: SceneSection = SceneSection()
    mesh: Annotated[MeshSpec, BeforeValidator(_mesh_shorthand)] = GridMesh()
    material: MaterialSection = MaterialSection()
    bending: BendingSection | None = None
    membrane: MembraneSection | None = None
    colliders: list[ColliderSpec] = []
    gravity: Vec3 = (0.0, 0.0, -9.81)
    solver: SolverSection = SolverSection()
    output: OutputSection = OutputSection()
    robot: RobotSection | None = None

    @field_validator("scene", "material", "solver", "output", "colliders", mode="before")
    @classmethod
    def _null_is_default(cls, value, info):
        """``solver:`` with nothing under it (YAML null) means the defaults."""
        if value is None:
            field = cls.model_fields[info.field_name]
            return field.get_default(call_default_factory=True)
        return value


# ------------------------------------------------------------------------------ errors
def _strip(tp):
    """``tp`` without ``Annotated`` and ``Optional``."""
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            tp = get_args(tp)[0]
        elif origin in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return tp
            tp = args[0]
        else:
            return tp


def _is_model(tp) -> TypeGuard[type[BaseModel]]:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _walk(schema, loc, prefix: str = ""):
    """``(dotted path, type at the end)`` of a pydantic error location; drops the tags that
    discriminated unions put into locations (``colliders.0.sphere.radius`` -> ``colliders[0].radius``)."""
    path, tp = prefix, schema
    for part in loc:
        tp = _strip(tp) if tp is not None else None
        if get_origin(tp) in (Union, types.UnionType) and isinstance(part, str):
            members = [m for m in get_args(tp) if _is_model(m) and "type" in m.model_fields
                       and part in get_args(m.model_fields["type"].annotation)]
            if members:
                tp = members[0]
                continue
            tagged = [m for m in get_args(tp) if get_origin(m) is Annotated
                      and any(isinstance(meta, Tag) and meta.tag == part for meta in m.__metadata__)]
            if tagged:  # a union discriminated by a function (``mesh.pin``): the tag is no key either
                tp = tagged[0]
                continue
        if isinstance(part, int):
            path += f"[{part}]"
            args = get_args(tp) if get_origin(tp) in (list, tuple) else ()
            tp = args[0] if args else None
        else:
            path += f".{part}" if path else str(part)
            field = tp.model_fields.get(part) if _is_model(tp) else None
            tp = field.annotation if field is not None else None
    return path, tp


def _describe(error: Mapping[str, Any], schema, prefix: str) -> str:
    kind, loc, ctx = error["type"], error["loc"], error.get("ctx") or {}
    value = error.get("input")
    path, _ = _walk(schema, loc, prefix)
    key = f"config key '{path}'" if path else "the config"
    if kind == "extra_forbidden":
        _, parent = _walk(schema, loc[:-1], prefix)
        parent = _strip(parent)
        allowed = f" (allowed: {', '.join(parent.model_fields)})" if _is_model(parent) else ""
        return f"unknown config key '{path}'{allowed}"
    if kind == "missing":
        return f"missing config key '{path}'"
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        bound = next(iter(ctx.values()))
        words = {("greater_than", 0): "positive", ("greater_than_equal", 0): "non-negative"}
        ops = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
        return f"{key} must be {words.get((kind, bound)) or f'{ops[kind]} {bound}'}, got {short_repr(value)}"
    if kind == "union_tag_invalid":
        disc = ctx["discriminator"].strip("'")
        return f"{key[:-1]}.{disc}' must be one of {ctx['expected_tags']}, got {short_repr(ctx['tag'])}"
    if kind == "union_tag_not_found":
        return f"{key} needs a {ctx['discriminator']} key, got {short_repr(value)}"
    if kind == "literal_error":
        return f"{key} must be one of {ctx['expected'].replace(' or ', ', ')}, got {short_repr(value)}"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return f"{key} must be a mapping, got {short_repr(value)}"
    if kind in ("list_type", "tuple_type"):
        return f"{key} must be a list, got {short_repr(value)}"
    if kind in ("float_parsing", "float_type", "int_parsing", "int_type", "finite_number"):
        what = "an integer" if kind.startswith("int") else "a finite number"
        return f"{key} must be {what}, got {short_repr(value)}"
    if kind in ("int_from_float",):
        return f"{key} must be an integer, got {short_repr(value)}"
    if kind in ("bool_parsing", "bool_type"):
        return f"{key} must be true or false, got {short_repr(value)}"
    if kind in ("string_type",):
        return f"{key} must be a string, got {short_repr(value)}"
    if kind == "value_error":
        msg = str(ctx.get("error", error["msg"]))
        return f"{key} {msg}" if msg.startswith("must ") else f"{key}: {msg}"
    return f"{key}: {error['msg']}, got {short_repr(value)}"


def validate(data, schema: type[M], *, prefix: str = "", source: str | None = None) -> M:
    """``data`` (a dict, or an instance of ``schema``) validated against the schema (e.g.
    :class:`SceneConfig`); :class:`ConfigError` naming every offending key's path (below ``prefix``)."""
    if isinstance(data, schema):
        return data
    if isinstance(data, BaseModel):
        data = data.model_dump()
    try:
        return schema.model_validate({} if data is None and not prefix else data)
    except ValidationError as e:
        msgs = list(dict.fromkeys(_describe(err, schema, prefix) for err in e.errors(include_url=False)))
        more = f"; ... and {len(msgs) - MAX_ERRORS} more" if len(msgs) > MAX_ERRORS else ""
        where = f"config {source}: " if source else ""
        raise ConfigError(where + "; ".join(msgs[:MAX_ERRORS]) + more) from None


# ------------------------------------------------------------------------------ reading
def _parse_key(key: str) -> list:
    parts: list = []
    for name in key.split("."):
        base, _, rest = name.partition("[")
        if not base:
            raise ConfigError(f"override key {short_repr(key)}: empty name")
        parts.append(base)
        while rest:
            index, _, rest = rest.partition("]")
            if not index.lstrip("-").isdigit() or (rest and not rest.startswith("[")):
                raise ConfigError(f"override key {short_repr(key)}: expected name[index]")
            parts.append(int(index))
            rest = rest[1:]
    return parts


def apply_overrides(cfg: dict, overrides) -> dict:
    """``cfg`` with ``KEY=VALUE`` overrides set in place (values read as YAML: ``solver.tol=1e-8``,
    ``colliders[0].center=[0, 0, 0.1]``); missing mappings on the way are created."""
    import yaml

    for item in overrides or ():
        key, sep, text = str(item).partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {short_repr(item)} must be KEY=VALUE, e.g. solver.tol=1e-8")
        parts = _parse_key(key.strip())
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            raise ConfigError(f"override {short_repr(item)}: the value is not valid YAML") from None
        except RecursionError:
            raise ConfigError(f"override {short_repr(item)}: the value is nested too deeply") from None
        node: Any = cfg
        for i, part in enumerate(parts[:-1]):
            nxt = parts[i + 1]
            if isinstance(part, int):
                if not isinstance(node, list) or not -len(node) <= part < len(node):
                    raise ConfigError(f"override {short_repr(item)}: no list element [{part}]")
                node = node[part]
            else:
                if not isinstance(node, dict):
                    raise ConfigError(f"override {short_repr(item)}: {short_repr(part)} is not inside a mapping")
                if node.get(part) is None:
                    node[part] = [] if isinstance(nxt, int) else {}
                node = node[part]
        last = parts[-1]
        if isinstance(last, int):
            if not isinstance(node, list) or not -len(node) <= last < len(node):
                raise ConfigError(f"override {short_repr(item)}: no list element [{last}]")
        elif not isinstance(node, dict):
            raise ConfigError(f"override {short_repr(item)}: {short_repr(last)} is not inside a mapping")
        node[last] = value
    return cfg


def read_yaml(path: str) -> dict:
    """The mapping in a YAML file (UTF-8 text; ``{}`` for a file holding ``{}``); :class:`ConfigError`
    for a missing or unreadable file, a directory, text that is not UTF-8, invalid YAML, an empty
    file (no YAML document: write ``{}`` for every default) and anything but a mapping."""
    import yaml

    shown = short_repr(str(path)) if len(str(path)) > QUOTE_LIMIT else str(path)
    if os.path.isdir(path):
        raise ConfigError(f"config {shown} is a directory, not a YAML file")
    if not os.path.isfile(path):
        raise ConfigError(f"config file not found: {shown}")
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise ConfigError(f"config {shown} cannot be read: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise ConfigError(f"config {shown} is not UTF-8 text (byte 0x{data[e.start]:02x} on line {line}); "
                          "save it as UTF-8") from None
    try:
        cfg = yaml.safe_load(text)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"config {shown}: invalid YAML{at}: {e.problem or e.context or type(e).__name__}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"config {shown}: invalid YAML: {e}") from None
    except RecursionError:
        raise ConfigError(f"config {shown}: invalid YAML: nested too deeply") from None
    if cfg is None:
        raise ConfigError(f"config {shown} is empty (no YAML mapping; write {{}} for every default)")
    if not isinstance(cfg, dict):
        raise ConfigError(f"config {shown}: expected a mapping (key: value lines) at the top level, "
                          f"got {_yaml_kind(cfg)}")
    return cfg


def _yaml_kind(value) -> str:
    if isinstance(value, list):
        return "a list"
    if isinstance(value, str):
        return f"the string {short_repr(value)}"
    return f"{type(value).__name__} {short_repr(value)}"


def load_config(path: str, schema: type[BaseModel] | None = None, overrides=()) -> dict:
    """Read the YAML config ``path``, apply ``overrides`` (``["solver.tol=1e-8", ...]``), validate
    against ``schema`` (default :class:`SceneConfig`) and return the validated config as a plain dict
    with the defaults filled in.  A relative ``mesh.path`` becomes relative to the config's folder
    (``asset:NAME``, a shipped mesh, stays as it is).
    :class:`ConfigError` (a ``ValueError``) naming the key for anything unknown or invalid."""
    schema = schema or SceneConfig
    cfg = apply_overrides(read_yaml(path), overrides)
    model = validate(cfg, schema, source=path)
    out = model.model_dump(mode="json")
    mesh = out.get("mesh")
    if (isinstance(mesh, dict) and mesh.get("type") == "file" and not os.path.isabs(mesh["path"])
            and not mesh["path"].startswith(ASSET_PREFIX)):
        mesh["path"] = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(path)), mesh["path"]))
    return out


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
        local = rest - torch.tensor(mesh.offset, dtype=rest.dtype, device=rest.device)  # the mesh's own coordinates
        bounded = False
        inside = torch.ones(len(rest), dtype=torch.bool, device=rest.device)
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
            pts = torch.tensor(pin.nearest, dtype=rest.dtype, device=rest.device).reshape(-1, 3)
            mask[torch.cdist(pts, local).argmin(-1)] = True
        if not mask.any():
            lo, hi = local.amin(0).tolist(), local.amax(0).tolist()
            span = ", ".join(f"{a} [{lo[j]:.4g}, {hi[j]:.4g}]" for j, a in enumerate(_AXES))
            raise ConfigError(f"config key 'mesh.pin': the region holds no vertex (the mesh spans {span} m, "
                              "before offset)")
        return mask
    bad = [v for v in pin if v >= len(rest)]
    if bad:
        raise ConfigError(f"config key 'mesh.pin': vertex indices {bad} out of range [0, {len(rest)})")
    mask[pin] = True
    return mask


def build_collider(spec):
    """The :class:`~torchbend.Sphere`, :class:`~torchbend.Plane` or :class:`~torchbend.Capsule` of a
    ``colliders`` entry (a validated spec)."""
    kinds = {"sphere": Sphere, "plane": Plane, "capsule": Capsule}
    return kinds[spec.type](**spec.model_dump(exclude={"type"}))


def _build(cfg: SceneConfig, thickness, resolution, device):
    dtype = torch.float64
    rest, faces = build_mesh(cfg.mesh, resolution=resolution, dtype=dtype, device=device)
    # the cheap checks (pins, robot, colliders) before the energies are built
    pinned = build_pins(cfg.mesh, rest, resolution=resolution)
    rc = None
    if cfg.robot is not None:
        rc = parse_robot(cfg.robot, rest)
        if pinned is None:
            pinned = torch.zeros(len(rest), dtype=torch.bool, device=rest.device)
        pinned = pinned.clone()
        pinned[rc.vertices] = True
    colliders = []
    for i, c in enumerate(cfg.colliders):
        try:
            colliders.append(build_collider(c))
        except ValueError as e:
            raise ConfigError(f"config key 'colliders[{i}]': {e}") from None
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
    model = ClothModel(faces, rest, bending=bend, membrane=mem, density=density,
                       gravity=cfg.gravity, pinned=pinned, colliders=colliders)
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
