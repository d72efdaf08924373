"""Shared machinery of the training scripts: config sections, the cloth physics, runtime, checkpoints, plots.

Configs use torchbend's one config system (:mod:`torchbend.scenes.config`: typed sections, unknown
keys rejected with their dotted path) and CLI conventions (:mod:`torchbend.scenes.cli`: ``--config``,
``--set``, ``--seed``, ``--device``, ``--out``, ``--resume``, ``--log-level``, ``--no-progress``);
each script's schema is built from the sections below plus its own.  Scripts import torchbend;
torchbend never imports this folder.
"""
from __future__ import annotations

import math
import os
import time
from typing import Annotated, Any, cast

import torch
import torch.distributed as dist
from pydantic import Field, field_validator

import torchbend as tb
from torchbend.ops.psi import BendingModel
from torchbend.scenes import cli
from torchbend.scenes.cli import load_checkpoint, save_checkpoint, seed_everything  # noqa: F401  (re-exported)
from torchbend.scenes.config import (  # noqa: F401  (re-exported)
    MAX_GRID_VERTICES,
    ConfigError,
    Float,
    Int,
    NonNegative,
    Positive,
    PositiveInt,
    Section,
    Seed,
    load_config,
)

ENERGY_TERMS = {"membrane", "bending", "gravity", "sphere", "ground"}
MAX_SIDE = math.isqrt(MAX_GRID_VERTICES)  # the most vertices per side of a square grid cloth
MAX_BATCH = 100_000
MAX_PARAMETERS = 100_000_000  # of a network: 0.8 GB of float64 weights, three times that with Adam's state
# sizes of a batch and of a network's layers
Batch = Annotated[PositiveInt, Field(le=MAX_BATCH)]
Width = Annotated[PositiveInt, Field(le=1_000_000)]
Depth = Annotated[PositiveInt, Field(le=1000)]


# ------------------------------------------------------------------------------ config
class ClothSection(Section):
    """``cloth``: a square cloth of ``resolution`` x ``resolution`` vertices and ``size`` [m], the
    energy terms of :class:`ClothPhysics` (``energies``) and their parameters."""

    resolution: Annotated[Int, Field(ge=3, le=MAX_SIDE)] = 9
    size: Positive = 0.8
    energies: list[str] = ["membrane", "bending", "gravity", "sphere", "ground"]
    young: Positive = 2e4                # [Pa]
    poisson: Annotated[Float, Field(gt=-1.0, lt=0.5)] = 0.3
    thickness: Positive = 1e-3           # [m]
    density: Positive = 0.2              # [kg/m^2]
    bending_model: str = "tan"
    bending_stiffness: Positive = 1e-4   # [N m]
    contact_stiffness: Positive = 2e3    # [N/m]
    ground_z: Float = -0.4               # [m]

    @field_validator("energies")
    @classmethod
    def _known_terms(cls, value):
        unknown = sorted(set(value) - ENERGY_TERMS)
        if unknown:
            raise ValueError(f"has unknown energy names {unknown}; allowed: {sorted(ENERGY_TERMS)}")
        return value

    @field_validator("bending_model")
    @classmethod
    def _bending_model(cls, value):
        BendingModel.parse(value, what="bending model")
        return value


class ModelSection(Section):
    """``model``: the MLP's ``hidden`` width and number of ``layers``."""

    hidden: Width = 128
    layers: Depth = 3


def check_network_size(count: int, what: str) -> int:
    """``count`` (the parameters of a network) when at most :data:`MAX_PARAMETERS`; else a
    :class:`ConfigError` saying which sizes (``what``) make it so large."""
    if count > MAX_PARAMETERS:
        raise ConfigError(f"the network would have {count:.3g} parameters, more than the {MAX_PARAMETERS:.0e} "
                          f"allowed: make {what} smaller")
    return count


def resume_run(path: str, cfg: dict, log, *pairs, ignore=("train.steps",), map_location=None,
               hint: str = "the same config") -> int:
    """Continue a run from the checkpoint at ``path`` (``--resume``): the ``(module or optimizer,
    checkpoint key)`` ``pairs`` restored (:func:`torchbend.scenes.cli.restore`), a warning naming
    the config keys that differ from the checkpoint's (but ``ignore``); returns the step reached.
    :class:`ConfigError` for a checkpoint of another script or one that does not fit."""
    ck, changed = cli.resume_checkpoint(path, cfg, {key: dict for _, key in pairs}, ignore=ignore,
                                        map_location=map_location)
    cli.restore(path, changed, *((obj, ck[key]) for obj, key in pairs), hint=hint)
    if changed:
        log.warning("--resume: the config differs from the checkpoint's at %s", ", ".join(changed))
    log.info("resumed at step %d from %s", ck["step"], path)
    return ck["step"]


def check_positive(cfg: dict, key: str, allow_zero: bool = False) -> float:
    section, name = key.split(".")
    value = cfg[section][name]
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"config key '{key}' must be a number, got {value!r}") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"config key '{key}' must be {'non-negative' if allow_zero else 'positive'}, got {value!r}")
    return value


# ------------------------------------------------------------------------------ physics
def total(terms: dict) -> torch.Tensor:
    """Sum of the energy terms ``{name: (B,)}`` of :meth:`ClothPhysics.energies`: ``(B,)`` [J]."""
    return torch.stack(list(terms.values())).sum(0)


class ClothPhysics:
    """Potential energy of batched cloth states ``x (B, V, 3)`` with per-sample sphere colliders.

    Terms (each optional, selected by ``energies`` in the config), the loss modules of
    :mod:`torchbend.losses` in a :class:`torchbend.ClothLoss`: ``membrane`` (StVK), ``bending``
    (torchbend hinge energy, analytic first and second derivatives), ``gravity``, ``sphere``
    (one-sided quadratic penalty ``k/2 max(0, r - |x - c|)^2``, per-sample centre/radius) and ``ground``
    (the same penalty against the plane z = ground_z)."""

    def __init__(self, cfg: dict, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu", mesh=None):
        """``mesh = (rest (V, 3), faces (F, 3))`` replaces the config's square grid."""
        c = cfg["cloth"]
        terms = set(c["energies"])
        unknown = terms - ENERGY_TERMS
        if unknown:
            raise ValueError(f"config key 'cloth.energies' has unknown energy names {sorted(unknown)}; "
                             f"allowed: {sorted(ENERGY_TERMS)}")
        if mesh is None:
            n = int(c["resolution"])
            if n < 3:
                raise ValueError(f"config key 'cloth.resolution' must be >= 3, got {n}")
            size = check_positive(cfg, "cloth.size")
            rest, faces = tb.scenes.grid(n, n, (size, size), dtype=dtype, device=device)
            rest = rest - torch.tensor([size / 2, size / 2, -float(c["height"])], dtype=dtype, device=device)
        else:
            rest, faces = mesh[0].to(dtype=dtype, device=device), mesh[1].to(device)
        self.rest, self.faces, self.terms = rest, faces, terms
        density = check_positive(cfg, "cloth.density")
        modules: dict = {}
        if "membrane" in terms:
            modules["membrane"] = tb.losses.Stretch(faces, rest, young=check_positive(cfg, "cloth.young"),
                                                    poisson=float(c["poisson"]),
                                                    thickness=check_positive(cfg, "cloth.thickness"))
        if "bending" in terms:
            modules["bending"] = tb.losses.Bending(faces, rest, check_positive(cfg, "cloth.bending_stiffness"),
                                                   model=c["bending_model"])
        if "gravity" in terms:
            modules["gravity"] = tb.losses.Gravity(faces, rest, density)
        self.k_contact = check_positive(cfg, "cloth.contact_stiffness")
        self.ground_z = float(c["ground_z"])
        # k/2 max(0, -s)^2: the contact loss with power 2 and no margin
        if "sphere" in terms:
            modules["sphere"] = tb.losses.BodyContact(stiffness=0.5 * self.k_contact, eps=0.0, power=2.0)
        if "ground" in terms:
            modules["ground"] = tb.losses.BodyContact(stiffness=0.5 * self.k_contact, eps=0.0, power=2.0,
                                                      colliders=[tb.Plane(point=(0.0, 0.0, self.ground_z))])
        self.loss = tb.ClothLoss(modules, reduction="none").to(device)
        # the same energies as solver-side modules (robot_drape's reference scene, mean |theta - theta_rest|)
        self.mem = modules["membrane"].membrane if "membrane" in modules else None
        self.bend = None
        if "bending" in modules:
            self.bend = tb.BendingEnergy(faces, rest, model=c["bending_model"], stiffness=cast(Any, modules["bending"]).stiffness)
        gravity = modules.get("gravity") or tb.losses.Gravity(faces, rest, density)
        self.mass = density * gravity.areas.to(device)  # (V,) lumped masses [kg]
        self.g = torch.tensor(gravity.gravity, dtype=dtype, device=device)  # (3,) gravity [m/s^2]

    def energies(self, x: torch.Tensor, center: torch.Tensor | None, radius: torch.Tensor | None) -> dict:
        """Per-sample energy terms ``{name: (B,)}`` [J]; ``center (B, 3)`` and ``radius (B,)`` are needed
        only with the ``sphere`` term."""
        if "sphere" not in self.terms:
            return self.loss.energies(x)
        if center is None or radius is None:
            raise ValueError("the 'sphere' energy needs the sphere's center and radius")
        return self.loss.energies(x, sphere={"sphere_center": center, "sphere_radius": radius})  # (not the ground's)

    def gradient(self, x: torch.Tensor, center: torch.Tensor | None, radius: torch.Tensor | None) -> torch.Tensor:
        """``dE/dx (B, V, 3)``, differentiable: bending and membrane through their analytic
        gradient Functions (whose backward is the analytic HVP), the rest through autograd."""
        g = torch.zeros_like(x)
        modules = self.loss.terms
        if "membrane" in modules:
            g = g + cast(Any, modules["membrane"]).gradient(x)
        if "bending" in modules:
            g = g + cast(Any, modules["bending"]).gradient(x)
        if "gravity" in self.terms:
            g = g - self.mass[:, None] * self.mass.new_tensor(modules["gravity"].gravity)
        contact = []
        if "sphere" in modules:
            if center is None or radius is None:
                raise ValueError("the 'sphere' energy needs the sphere's center and radius")
            contact.append(modules["sphere"](x, sphere_center=center, sphere_radius=radius).sum())
        if "ground" in modules:
            contact.append(modules["ground"](x).sum())
        if contact:
            (gc,) = torch.autograd.grad(torch.stack(contact).sum(), x, create_graph=True)
            g = g + gc
        return g

    def residual(self, x: torch.Tensor, center: torch.Tensor | None, radius: torch.Tensor | None) -> torch.Tensor:
        """Mass-weighted squared equilibrium residual per sample ``sum_i |g_i|^2 / m_i`` ``(B,)``."""
        g = self.gradient(x, center, radius)
        return (g * g / self.mass[:, None]).sum((-1, -2))

    def mean_angle_deviation(self, x) -> float:
        if self.bend is None:
            return float("nan")
        return float((self.bend.angles(x.detach()) - self.bend.rest_angles).abs().mean())


# ------------------------------------------------------------------------------ runtime
def distributed() -> tuple[int, int]:
    """``(rank, world_size)``; initialises a gloo process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    return (dist.get_rank(), dist.get_world_size()) if dist.is_initialized() else (0, 1)


class Timer:
    """Wall-clock laps [s] (``lap``: since the previous lap; ``total``: since creation)."""

    def __init__(self):
        self.t = self.t0 = time.perf_counter()

    def total(self) -> float:
        return time.perf_counter() - self.t0

    def lap(self) -> float:
        now = time.perf_counter()
        dt, self.t = now - self.t, now
        return dt


# ------------------------------------------------------------------------------ plots
def save_drape_png(path: str, meshes, titles=None, colliders=None) -> None:
    """PNG of predicted drapes: ``meshes`` a list of ``(x (V, 3), faces)``, ``colliders`` one list of
    torchbend colliders per mesh (drawn: spheres, planes, capsules)."""
    from torchbend.scenes.plot import snapshot

    colliders = colliders or [()] * len(meshes)
    snapshot(path, [([m], c) for m, c in zip(meshes, colliders, strict=True)], titles=titles, size=4.0, dpi=90)
