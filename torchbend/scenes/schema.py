"""The config schema (pydantic) shared by scenes and training scripts: the field types, :class:`Section`
(the base of every section: unknown keys rejected, numbers finite and not booleans) and the sections
``mesh``, ``material``, ``bending``, ``membrane``, ``colliders``, ``solver`` (one to one with
:class:`~torchbend.NewtonOptions`), ``output``, ``robot`` of :class:`SceneConfig`.  Training scripts
(``train/``) compose the physics sections with their own (``network``, ``train``, ``eval``)."""
from __future__ import annotations

import operator
import warnings
from collections.abc import Mapping
from typing import Annotated, Literal, Optional, TypeVar, Union

from .._extras import missing_extra

try:
    from pydantic import (
        BaseModel,
        BeforeValidator,
        ConfigDict,
        Discriminator,
        Field,
        StrictBool,
        Tag,
        ValidationError,
        field_validator,
        model_validator,
    )
except ModuleNotFoundError as _err:
    raise missing_extra(_err, "torchbend.scenes (configs)") from None

from ..energies.contact import ContactLaw, contact_law
from ..ops.membrane import MembraneModel
from ..ops.psi import BendingModel
from ..options import Projection
from ..sim.linear import Preconditioner
from ..sim.options import Factorization, LinearMethod, LinearSolver, NewtonOptions
from .wording import MAX_ERRORS, ConfigError, describe, short_repr

__all__ = [
    "Section", "PhysicsConfig", "SceneConfig", "ContactSection", "validate", "Float", "Int", "Positive", "NonNegative", "PositiveInt",
    "NonNegativeInt", "Vec3", "Seed", "SEED_LIMIT", "GridMesh", "FileMesh", "MeshSpec", "MeshSection", "MeshField", "mesh_shorthand",
    "PinRegion", "mesh_file", "ASSET_PREFIX", "SphereSpec", "PlaneSpec", "CapsuleSpec", "ColliderSpec",
    "RobotSection", "MaterialSection", "BendingSection", "MembraneSection", "SolverSection", "LinearSolverSection", "OutputSection",
    "SceneSection", "PinSpec", "LinkCapsuleSpec", "KeyframeSpec", "MAX_GRID_VERTICES", "check_resolution",
]

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
        if value is None:  # an optional option left out
            return value
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
    two corners of the first row), a list of vertex indices or a region (:class:`PinRegion`).  ``layers``
    (>= 1): a stack of that many separate sheets, ``layer_gap`` [m] apart in z, each turned by ``layer_twist``
    [degrees] about its centre from the one below (a pile; the named pins need one layer)."""

    type: Literal["grid"] = "grid"
    nx: Annotated[int, Field(ge=2), BeforeValidator(_number)] = 11
    ny: Annotated[int, Field(ge=2), BeforeValidator(_number)] | None = None  # default: nx
    size: Annotated[tuple[Positive, Positive], BeforeValidator(_pair)] = (1.0, 1.0)
    offset: Vec3 = (0.0, 0.0, 0.0)
    pin: GridPin = None
    layers: Annotated[int, Field(ge=1), BeforeValidator(_number)] = 1
    layer_gap: Positive = 0.01
    layer_twist: Annotated[float, BeforeValidator(_number)] = 0.0

    @model_validator(mode="after")
    def _size(self):
        n, m = self.nx, self.ny or self.nx
        if n * m * self.layers > MAX_GRID_VERTICES:
            raise ValueError(f"nx x ny x layers = {n} x {m} x {self.layers} vertices is more than the "
                             f"{MAX_GRID_VERTICES} a grid may have")
        if self.layers > 1 and isinstance(self.pin, str):
            raise ValueError(f"pin: {self.pin} names vertices of one sheet: give vertex indices or a region for "
                             f"{self.layers} layers")
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


class ContactSection(Section):
    """``contact``: a contact law (:mod:`torchbend.energies.contact`): ``law`` (``penalty``: ``k/2 max(0, d)^2``,
    ``k`` [N/m]; ``barrier``: ``k max(0, d)^p``, ``k`` [J/m^p]; ``ipc``: ``-k d^2 log(1 - d / margin)``, ``k``
    [J/m^2], infinite on the surface), ``stiffness`` ``k``, ``margin`` [m] (the depth ``d`` is ``margin`` minus
    the signed distance; the ``ipc`` law's activation distance, > 0), ``power`` ``p`` (the barrier's, default 3).  Every
    collider has these keys; the training scripts' ``contact`` section is the law of the bodies they draw
    per sample (spheres, a body mesh)."""

    stiffness: Positive = 1e4
    margin: NonNegative = 0.0
    law: Literal["penalty", "barrier", "ipc"] = "penalty"
    power: Annotated[float, Field(gt=1), BeforeValidator(_number)] | None = None

    @model_validator(mode="after")
    def _power_of_law(self):
        if self.law == "penalty" and self.power is not None and self.power != 2:
            raise ValueError("the penalty law has power 2: give law: barrier for another power")
        if self.law == "ipc" and self.power is not None:
            raise ValueError("the ipc law has no power (it is C2 where a point comes within margin)")
        if self.law == "ipc" and self.margin is not None and not self.margin > 0:
            raise ValueError("the ipc law needs margin > 0 (its activation distance) [m]")
        return self

    def contact_law(self) -> ContactLaw:
        """The :class:`~torchbend.energies.contact.ContactLaw` of this section."""
        return contact_law(self.law, self.stiffness, self.power, margin=self.margin)


class SelfContactSection(Section):
    """``self_contact``: the cloth's own contact (:class:`~torchbend.SelfContact`): ``dhat`` [m] the activation
    distance of the barrier, ``stiffness`` its ``kappa`` [J/m^4] (absent: chosen from the cloth's weight),
    ``friction`` Coulomb's ``mu`` between the layers (time steps) smoothed below ``eps_v`` [m/s]."""

    dhat: Positive = 1e-3
    stiffness: Positive | None = None
    friction: NonNegative = 0.0
    eps_v: Positive = 1e-3


class _ColliderSpec(ContactSection):
    """A collider's contact law and its ``friction`` (Coulomb's ``mu`` >= 0, time steps only) smoothed below the
    sliding speed ``eps_v`` [m/s] (:mod:`torchbend.energies.friction`).  The solver's colliders default to the
    ``ipc`` law (:class:`~torchbend.energies.colliders.Collider`): ``margin`` absent is 1 mm, ``stiffness`` absent
    is chosen from the cloth's weight (for ``penalty`` and ``barrier``: 0 and 1e4)."""

    stiffness: Positive | None = None  # pyright: ignore[reportIncompatibleVariableOverride]
    margin: NonNegative | None = None  # pyright: ignore[reportIncompatibleVariableOverride]
    law: Literal["penalty", "barrier", "ipc"] = "ipc"
    friction: NonNegative = 0.0
    eps_v: Positive = 1e-3


class SphereSpec(_ColliderSpec):
    """``{type: sphere, center, radius, stiffness, margin, law, power, friction, eps_v}`` (:class:`~torchbend.Sphere`)."""

    type: Literal["sphere"]
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: Positive = 1.0


class PlaneSpec(_ColliderSpec):
    """``{type: plane, point, normal, stiffness, margin, law, power, friction, eps_v}`` (:class:`~torchbend.Plane`)."""

    type: Literal["plane"]
    point: Vec3 = (0.0, 0.0, 0.0)
    normal: Vec3 = (0.0, 0.0, 1.0)


class CapsuleSpec(_ColliderSpec):
    """``{type: capsule, a, b, radius, stiffness, margin, law, power, friction, eps_v}`` (:class:`~torchbend.Capsule`)."""

    type: Literal["capsule"]
    a: Vec3 = (0.0, 0.0, 0.0)
    b: Vec3 = (1.0, 0.0, 0.0)
    radius: Positive = 0.1


class MeshColliderSpec(Section):
    """``{type: mesh, shape: mannequin, offset, dhat, stiffness, friction, eps_v}``: a rigid body of triangles
    (:class:`~torchbend.MeshCollider`, the barrier of self-contact between the cloth and the body): ``shape`` a
    procedural body (``mannequin``: :func:`torchbend.scenes.mannequin`, hips and legs) or ``path`` a mesh file
    (``asset:NAME`` or a path), moved by ``offset`` [m]; ``dhat`` [m] the activation distance, ``stiffness`` its
    ``kappa`` [J/m^4] (absent: from the cloth's weight), ``friction`` Coulomb's ``mu`` on the body (time steps)
    smoothed below ``eps_v`` [m/s]."""

    type: Literal["mesh"]
    shape: Literal["mannequin"] | None = None
    path: str | None = None
    offset: Vec3 = (0.0, 0.0, 0.0)
    dhat: Positive = 1e-3
    stiffness: Positive | None = None
    friction: NonNegative = 0.0
    eps_v: Positive = 1e-3

    @model_validator(mode="after")
    def _one_source(self):
        if (self.shape is None) == (self.path is None):
            raise ValueError("give either 'shape: mannequin' or 'path: <mesh file>'")
        if self.path is not None:
            mesh_file(self.path)  # an unknown asset name: ValueError listing the shipped meshes
        return self


ColliderSpec = Annotated[Union[SphereSpec, PlaneSpec, CapsuleSpec, MeshColliderSpec], Field(discriminator="type")]
MeshSpec = Annotated[Union[GridMesh, FileMesh], Field(discriminator="type")]


class LinearSolverSection(Section):
    """``solver.linear_solver`` as a mapping, one to one with :class:`~torchbend.LinearSolver`: ``method``
    (``direct``, ``cg``), ``preconditioner`` (``auto``, ``block_jacobi``, ``ilu``, ``amg``), ``cholesky``,
    ``max_cg_iters``, ``factorization`` (``auto``, ``ldlt``, ``lu``), ``reuse_factorization`` (``auto``, true,
    false); a string is the ``method``."""

    method: str = "direct"
    preconditioner: str = "auto"
    cholesky: bool = False
    max_cg_iters: PositiveInt | None = None
    factorization: str = "auto"
    reuse_factorization: Union[StrictBool, Literal["auto"]] = "auto"

    _check_method = field_validator("method")(_option(LinearMethod, "linear solver"))
    _check_preconditioner = field_validator("preconditioner")(_option(Preconditioner, "preconditioner"))
    _check_factorization = field_validator("factorization")(_option(Factorization, "factorization"))

    def linear_solver(self) -> LinearSolver:
        return LinearSolver(self.method, self.preconditioner, self.cholesky, self.max_cg_iters, self.factorization,
                            self.reuse_factorization)


def _linear_shorthand(value):
    return {"method": value} if isinstance(value, str) else value


class SolverSection(Section):
    """``solver``: the scene's ``dt`` [s], ``steps`` and ``load_steps`` (static scenes: gravity ramped in that
    many equal increments), and the fields of :class:`~torchbend.NewtonOptions`, one to one: ``projection``,
    ``linear_solver`` (a method name or a mapping, :class:`LinearSolverSection`), ``tol``, ``max_iters``,
    ``check_minimum`` (null: the solver's defaults, 1e-6, 30, false for steps, 1e-9, 50, true for static
    solves), ``time_limit`` [s] (``auto``: the solver's default budget, null: none), ``damping``,
    ``continuation``, ``max_relax_steps``, ``max_substep_depth``.  ``hessian``:
    the deprecated alias of ``projection`` (a ``DeprecationWarning``)."""

    dt: Positive = 1 / 60
    steps: PositiveInt = 60
    load_steps: PositiveInt = 1
    projection: str = "exact"
    hessian: str | None = None
    linear_solver: Annotated[LinearSolverSection, BeforeValidator(_linear_shorthand)] = LinearSolverSection()
    tol: Positive | None = None
    max_iters: NonNegativeInt | None = None
    check_minimum: bool | None = None
    time_limit: Positive | Literal["auto"] | None = "auto"
    damping: bool = True
    continuation: bool | Literal["auto", "membrane", "relaxation"] | None = "auto"
    max_relax_steps: NonNegativeInt = 200
    max_substep_depth: NonNegativeInt = 3

    _check_projection = field_validator("projection", "hessian")(_option(Projection, "Hessian projection"))

    @model_validator(mode="after")
    def _deprecated_hessian(self):
        if self.hessian is not None:
            warnings.warn("config key 'solver.hessian' is deprecated: write 'solver.projection'",
                          DeprecationWarning, stacklevel=2)
            if "projection" in self.model_fields_set and Projection.parse(self.projection) is not Projection.parse(self.hessian):
                raise ValueError(f"give 'projection' or its deprecated alias 'hessian', not both with different values "
                                 f"({self.projection!r}, {self.hessian!r})")
            self.projection, self.hessian = self.hessian, None
        return self

    def newton_options(self) -> NewtonOptions:
        """The :class:`~torchbend.NewtonOptions` of this section (field by field)."""
        return NewtonOptions(projection=self.projection, linear_solver=self.linear_solver.linear_solver(),
                             tol=self.tol, max_iters=self.max_iters, check_minimum=self.check_minimum,
                             time_limit=self.time_limit, damping=self.damping, continuation=self.continuation,
                             max_relax_steps=self.max_relax_steps, max_substep_depth=self.max_substep_depth)


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
    stiffness: Positive = 1e4  # the penalty's [N/m]: a moving link keeps the penalty law (LinkCapsule)
    margin: NonNegative = 1e-3  # [m]: the penalty acts from this far outside the surface (LinkCapsule)


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


def mesh_shorthand(value):
    if value is None:
        return {"type": "grid"}
    if isinstance(value, str):
        return {"type": "file", "path": value}
    if isinstance(value, dict) and "type" not in value:
        return {"type": "grid", **value}
    return value


def _optional_mesh(value):
    return None if value is None else mesh_shorthand(value)


MeshSection = Annotated[MeshSpec, BeforeValidator(mesh_shorthand)]
"""A ``mesh`` key: a grid or a file (``mesh: path.obj`` for short, a mapping without ``type`` a grid)."""

# a ``mesh`` key that may be absent (the training scripts): null, a path (``mesh: garment.obj``), a grid or a file
MeshField = Annotated[MeshSpec | None, BeforeValidator(_optional_mesh)]


class PhysicsConfig(Section):
    """The physics sections shared by scene configs and every training script: ``mesh``, ``material``,
    ``bending`` and ``membrane`` (a term each, absent: no such term), ``colliders``, ``contact`` (the law of
    the bodies a training script draws), ``self_contact`` (absent: none) and ``gravity``; :func:`~torchbend.scenes.builders.build_model` builds
    their :class:`~torchbend.ClothModel`."""

    mesh: MeshSection = GridMesh()
    material: MaterialSection = MaterialSection()
    bending: BendingSection | None = None
    membrane: MembraneSection | None = None
    colliders: list[ColliderSpec] = []
    contact: ContactSection | None = None
    self_contact: SelfContactSection | None = None
    gravity: Vec3 = (0.0, 0.0, -9.81)

    @field_validator("material", "colliders", mode="before")
    @classmethod
    def _null_is_default(cls, value, info):
        """``material:`` with nothing under it (YAML null) means the defaults."""
        if value is None:
            field = cls.model_fields[info.field_name]
            return field.get_default(call_default_factory=True)
        return value


class SceneConfig(PhysicsConfig):
    """A scene config (every section optional): the physics sections of :class:`PhysicsConfig` and
    ``scene``, ``solver``, ``output``, ``robot``."""

    scene: SceneSection = SceneSection()
    solver: SolverSection = SolverSection()
    output: OutputSection = OutputSection()
    robot: RobotSection | None = None

    @field_validator("scene", "material", "solver", "output", "colliders", mode="before")
    @classmethod
    def _null_is_default(cls, value, info):  # pyright: ignore[reportIncompatibleMethodOverride]
        """``solver:`` with nothing under it (YAML null) means the defaults."""
        if value is None:
            field = cls.model_fields[info.field_name]
            return field.get_default(call_default_factory=True)
        return value


M = TypeVar("M", bound=BaseModel)


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
        msgs = list(dict.fromkeys(describe(err, schema, prefix) for err in e.errors(include_url=False)))
        more = f"; ... and {len(msgs) - MAX_ERRORS} more" if len(msgs) > MAX_ERRORS else ""
        where = f"config {source}: " if source else ""
        raise ConfigError(where + "; ".join(msgs[:MAX_ERRORS]) + more) from None
