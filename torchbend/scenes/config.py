"""Configs (YAML) for scenes and training: reading, overrides and validation against one typed schema
(:mod:`torchbend.scenes.schema`), with the builders of :mod:`torchbend.scenes.builders` and the error
wording of :mod:`torchbend.scenes.wording` (this module re-exports all three).

* :func:`load_config` reads a YAML file, applies ``KEY=VALUE`` overrides (``solver.tol=1e-8``,
  ``colliders[0].radius=0.2``), validates it against a schema and returns the validated config as a
  plain dict (defaults filled in; only numbers, strings, booleans, lists and dicts), fit for a
  ``torch.load(..., weights_only=True)`` checkpoint; :func:`read_config` returns the validated object
  itself.  :func:`validate` does the same for a dict.
* Every problem is a :class:`ConfigError` (a ``ValueError``) naming the key's full dotted path:
  ``unknown config key 'solver.tol_x' (allowed: ...)``, ``config key 'colliders[0].radius' must be
  positive, got -1``, ``missing config key 'robot.pins[1].link'``.
"""
from __future__ import annotations

import os
import re
from typing import Any, TypeVar, cast

from .._extras import missing_extra

try:
    from pydantic import BaseModel
except ModuleNotFoundError as _err:
    raise missing_extra(_err, "torchbend.scenes (configs)") from None


from .builders import (
    RobotConfig,
    build_collider,
    build_colliders,
    build_mesh,
    build_model,
    build_pins,
    build_robot_scene,
    build_scene,
    check_keyframes,
    parse_robot,
)
from .schema import (
    ASSET_PREFIX,
    MAX_GRID_VERTICES,
    SEED_LIMIT,
    BendingSection,
    CapsuleSpec,
    ColliderSpec,
    ContactSection,
    FileMesh,
    Float,
    GridMesh,
    Int,
    KeyframeSpec,
    LinearSolverSection,
    LinkCapsuleSpec,
    MaterialSection,
    MembraneSection,
    MeshField,
    MeshSection,
    MeshSpec,
    NonNegative,
    NonNegativeInt,
    OutputSection,
    PhysicsConfig,
    PinRegion,
    PinSpec,
    PlaneSpec,
    Positive,
    PositiveInt,
    RobotSection,
    SceneConfig,
    SceneSection,
    Section,
    Seed,
    SolverSection,
    SphereSpec,
    Vec3,
    check_resolution,
    mesh_file,
    mesh_shorthand,
    validate,
)
from .wording import (
    MAX_ERRORS,
    MESSAGE_LIMIT,
    QUOTE_LIMIT,
    ConfigError,
    describe,
    one_line,
    short_repr,
)

M = TypeVar("M", bound=BaseModel)

__all__ = [
    "load_config", "read_config", "build_model", "build_colliders", "PhysicsConfig", "ContactSection",
    "LinearSolverSection", "apply_overrides", "read_yaml", "Section", "SceneConfig", "validate",
    "Float", "Int", "Positive", "NonNegative", "PositiveInt", "NonNegativeInt", "Vec3", "Seed", "SEED_LIMIT",
    "GridMesh", "FileMesh", "MeshSpec", "MeshSection", "MeshField", "mesh_shorthand", "PinRegion", "mesh_file", "ASSET_PREFIX", "SphereSpec",
    "PlaneSpec", "CapsuleSpec", "ColliderSpec", "RobotSection", "MaterialSection", "BendingSection",
    "MembraneSection", "SolverSection", "OutputSection", "SceneSection", "PinSpec", "LinkCapsuleSpec",
    "KeyframeSpec", "MAX_GRID_VERTICES", "check_resolution", "build_scene", "build_mesh", "build_collider",
    "build_robot_scene", "parse_robot", "check_keyframes", "RobotConfig", "build_pins", "ConfigError",
    "short_repr", "one_line", "describe", "QUOTE_LIMIT", "MESSAGE_LIMIT", "MAX_ERRORS",
]


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
            if not _INDEX.fullmatch(index) or (rest and not rest.startswith("[")):
                raise ConfigError(f"override key {short_repr(key)}: expected name[index]")
            parts.append(int(index))
            rest = rest[1:]
    return parts


def apply_overrides(cfg: dict, overrides) -> dict:
    """``cfg`` with ``KEY=VALUE`` overrides set in place (values read as YAML: ``solver.tol=1e-8``,
    ``colliders[0].center=[0, 0, 0.1]``, or ``colliders.0.center``); missing mappings on the way are created."""
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
        node = _parent(cfg, parts, item)
        last = _list_index(node, parts[-1])
        if isinstance(last, int):
            if not isinstance(node, list) or not -len(node) <= last < len(node):
                raise ConfigError(f"override {short_repr(item)}: no list element [{last}]")
            node[last] = value
        else:
            if not isinstance(node, dict):
                raise ConfigError(f"override {short_repr(item)}: {short_repr(last)} is not inside a mapping")
            node[last] = value
    return cfg


_INDEX = re.compile(r"-?[0-9]+")
"""A list index in an override key (ASCII digits: ``str.isdigit`` also takes superscripts, which ``int`` refuses)."""


def _list_index(node: Any, part: str | int) -> str | int:
    """A dotted key's part as a list index where it names a list element (``colliders.0.friction`` as
    ``colliders[0].friction``); else the part itself."""
    if isinstance(node, list) and isinstance(part, str) and _INDEX.fullmatch(part):
        return int(part)
    return part


def _parent(cfg: dict, parts: list, item) -> Any:
    """The container of an override key's last part (``parts`` from :func:`_parse_key`), creating missing
    mappings and lists on the way; :class:`ConfigError` naming the override ``item`` where it cannot."""
    node: Any = cfg
    for i, part in enumerate(parts[:-1]):
        nxt, part = parts[i + 1], _list_index(node, part)
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
    return node


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


def read_config(path: str, schema: type[M] | None = None, overrides=()) -> M:
    """Read the YAML config ``path``, apply ``overrides`` (``["solver.tol=1e-8", ...]``) and return it
    validated against ``schema`` (default :class:`SceneConfig`): the validated object, the defaults filled
    in, to pass on as it is.  A relative ``mesh.path`` (or a body mesh collider's ``path``) becomes relative to the config's folder
    (``asset:NAME``, a shipped mesh, stays as it is).
    :class:`ConfigError` (a ``ValueError``) naming the key for anything unknown or invalid."""
    cfg = apply_overrides(read_yaml(path), overrides)
    model = validate(cfg, schema or SceneConfig, source=path)
    mesh = getattr(model, "mesh", None)
    here = os.path.dirname(os.path.abspath(path))
    if (isinstance(mesh, FileMesh) and not os.path.isabs(mesh.path) and not mesh.path.startswith(ASSET_PREFIX)):
        mesh.path = os.path.normpath(os.path.join(here, mesh.path))
    for c in getattr(model, "colliders", None) or ():  # a body mesh's file too
        p = getattr(c, "path", None)
        if isinstance(p, str) and not os.path.isabs(p) and not p.startswith(ASSET_PREFIX):
            c.path = os.path.normpath(os.path.join(here, p))
    return cast(M, model)


def load_config(path: str, schema: type[BaseModel] | None = None, overrides=()) -> dict:
    """:func:`read_config` as a plain dict (``model_dump(mode="json")``: numbers, strings, booleans, lists
    and dicts), fit for a ``torch.load(..., weights_only=True)`` checkpoint."""
    return read_config(path, schema, overrides).model_dump(mode="json")
