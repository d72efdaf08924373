"""Shared machinery of the training scripts: config sections, the cloth physics, runtime, checkpoints, plots.

Configs use torchbend's one config dialect (:mod:`torchbend.scenes.config`: typed sections, unknown
keys rejected with their dotted path): the physics sections of :class:`PhysicsConfig` (``mesh``,
``material``, ``bending``, ``membrane``, ``colliders``, ``contact``, ``gravity``), the same as a scene
config's, and each script's own (``model``, ``train``, ``eval``, ...), validated once (:func:`read_config`)
and passed on as the validated object; and CLI conventions (:mod:`torchbend.scenes.cli`: ``--config``,
``--set``, ``--seed``, ``--device``, ``--out``, ``--resume``, ``--log-level``, ``--no-progress``);
each script's schema is built from the sections below plus its own.  Scripts import torchbend;
torchbend never imports this folder.
"""
from __future__ import annotations

import argparse
import os
import time
from typing import Annotated

import torch
import torch.distributed as dist
from pydantic import Field

import torchbend as tb
from torchbend.scenes import cli
from torchbend.scenes.cli import load_checkpoint, save_checkpoint, seed_everything  # noqa: F401  (re-exported)
from torchbend.scenes.config import (  # noqa: F401  (re-exported)
    MAX_GRID_VERTICES,
    ConfigError,
    Float,
    GridMesh,
    Int,
    MeshSpec,
    NonNegative,
    PhysicsConfig,
    Positive,
    PositiveInt,
    Section,
    Seed,
    build_mesh,
    build_model,
    build_pins,
    load_config,
    read_config,
    validate,
)
from torchbend.sim.terms import TermLoss

MAX_BATCH = 100_000
MAX_PARAMETERS = 100_000_000  # of a network: 0.8 GB of float64 weights, three times that with Adam's state
# sizes of a batch and of a network's layers
Batch = Annotated[PositiveInt, Field(le=MAX_BATCH)]
Width = Annotated[PositiveInt, Field(le=1_000_000)]
Depth = Annotated[PositiveInt, Field(le=1000)]


# ------------------------------------------------------------------------------ config
class ModelSection(Section):
    """``model``: the MLP's ``hidden`` width and number of ``layers``."""

    hidden: Width = 128
    layers: Depth = 3


def config_file(name: str) -> str:
    """The path of the shipped config ``configs/<name>`` (a script's default ``--config``)."""
    return os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "configs", name))


class TrainBase(Section):
    """The keys every script's ``train`` section has: ``steps``, ``batch``, ``lr``, ``log_every``,
    ``checkpoint_every``, ``seed`` (each script's section adds its own and sets its defaults)."""

    steps: PositiveInt = 300
    batch: Batch = 16
    lr: Positive = 1e-3
    log_every: PositiveInt = 10
    checkpoint_every: PositiveInt = 50
    seed: Seed = 0


def script_parser(doc: str | None, config: str, out: str, section: str = "train") -> argparse.ArgumentParser:
    """The argument parser of a training script: the common options of every torchbend script
    (:func:`torchbend.scenes.cli.add_common_args`) and ``--steps`` (overriding ``<section>.steps``)."""
    p = argparse.ArgumentParser(description=(doc or "").partition("\n")[0])
    cli.add_common_args(p, config=config, out=out)
    p.add_argument("--steps", type=cli.positive_int, help=f"override {section}.steps")
    return p


def flag_overrides(a: argparse.Namespace, section: str = "train", **flags) -> list[str]:
    """``--set`` overrides plus the script's own flags (``--steps``, ``--seed`` and ``flags``) as
    ``<section>.<flag>=<value>`` overrides (flags not given are left out)."""
    given = {"steps": a.steps, "seed": a.seed, **flags}
    return list(a.overrides) + [f"{section}.{k}={v}" for k, v in given.items() if v is not None]


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


# ------------------------------------------------------------------------------ physics
def total(terms: dict) -> torch.Tensor:
    """Sum of the energy terms ``{name: (B,)}`` of :meth:`ClothPhysics.energies`: ``(B,)`` [J]."""
    return torch.stack(list(terms.values())).sum(0)


SPHERE = "sphere"
"""The name of the per-sample sphere term of :class:`ClothPhysics`."""


class ClothPhysics:
    """The potential of batched cloth states ``x (B, V, 3)``, built from a config's physics sections
    (:class:`torchbend.scenes.config.PhysicsConfig`: ``mesh``, ``material``, ``bending``, ``membrane``,
    ``colliders``, ``contact``, ``gravity``) by :func:`torchbend.scenes.config.build_model`: the solver's own
    term objects (:attr:`ClothModel.terms <torchbend.ClothModel.terms>`: membrane, bending, gravity, one per
    collider) in a :class:`torchbend.ClothLoss`, and, when the config has a ``contact`` section, per-sample
    spheres (centre and radius per sample) under its contact law (``"sphere"``).  :meth:`model` is the
    :class:`~torchbend.ClothModel` of one sample, term for term the same potential, for reference solves."""

    def __init__(self, cfg, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu", mesh=None):
        """``cfg``: a validated config with the physics sections (a dict, e.g. a checkpoint's config, is
        validated as those sections); ``mesh = (rest (V, 3), faces (F, 3))`` replaces the config's mesh (its
        pins then come from the caller)."""
        if isinstance(cfg, dict):
            cfg = validate({k: cfg[k] for k in PhysicsConfig.model_fields if k in cfg}, PhysicsConfig)
        if mesh is None:
            rest, faces = build_mesh(cfg.mesh, dtype=dtype, device=device)
            self.pinned = build_pins(cfg.mesh, rest)
        else:
            rest, faces = mesh[0].to(dtype=dtype, device=device), mesh[1].to(device)
            self.pinned = None
        self.cfg, self.rest, self.faces = cfg, rest, faces
        for i, c in enumerate(cfg.colliders):
            law = getattr(c, "law", "a body mesh's barrier")
            if law != "penalty" and law != "barrier":  # a prediction may lie inside a body: a barrier is infinite
                raise ConfigError(f"config key 'colliders[{i}].law': a training loss needs a law that is finite inside "
                                  f"the collider (penalty or barrier), got {law}")
        self.solver_model = build_model(cfg, mesh=(rest, faces), pinned=self.pinned, dtype=dtype, device=device)
        modules: dict = {t.name: TermLoss(t) for t in self.solver_model.terms}
        self.contact = None
        if cfg.contact is not None:  # per-sample spheres under the config's contact law
            c = cfg.contact
            self.contact = c
            modules[SPHERE] = tb.losses.BodyContact(stiffness=c.stiffness, eps=c.margin, law=c.contact_law())
        self.terms = set(modules)
        self.loss = tb.ClothLoss(modules, reduction="none").to(device)
        self.mem, self.bend = self.solver_model.membrane, self.solver_model.bending
        self.mass = self.solver_model.mass.to(device)  # (V,) lumped masses [kg]
        self.g = self.solver_model.gravity.to(dtype=dtype, device=device)  # (3,) gravity [m/s^2]

    def _sphere(self, center, radius) -> dict:
        if SPHERE not in self.terms:
            return {}
        if center is None or radius is None:
            raise ValueError("the 'sphere' energy (the config's contact section) needs the sphere's center and radius")
        return {SPHERE: {"sphere_center": center, "sphere_radius": radius}}

    def energies(self, x: torch.Tensor, center: torch.Tensor | None, radius: torch.Tensor | None) -> dict:
        """Per-sample energy terms ``{name: (B,)}`` [J]; ``center (B, 3)`` and ``radius (B,)`` are needed
        only with the ``sphere`` term."""
        return self.loss.energies(x, **self._sphere(center, radius))

    def gradient(self, x: torch.Tensor, center: torch.Tensor | None, radius: torch.Tensor | None) -> torch.Tensor:
        """``dE/dx (B, V, 3)``, differentiable: every term's own gradient (bending and membrane through
        their analytic gradient Functions, whose backward is the analytic HVP), the spheres through autograd."""
        ctx = tb.StepContext()
        g = torch.zeros_like(x)
        for term in self.solver_model.terms:
            g = g + term.gradient(x, ctx)
        sphere = self._sphere(center, radius)
        if sphere:
            e = self.loss.terms[SPHERE](x, **sphere[SPHERE]).sum()
            (gc,) = torch.autograd.grad(e, x, create_graph=True)
            g = g + gc
        return g

    def residual(self, x: torch.Tensor, center: torch.Tensor | None, radius: torch.Tensor | None) -> torch.Tensor:
        """Mass-weighted squared equilibrium residual per sample ``sum_i |g_i|^2 / m_i`` ``(B,)``."""
        g = self.gradient(x, center, radius)
        return (g * g / self.mass[:, None]).sum((-1, -2))

    def model(self, center=None, radius: float | None = None, pinned: torch.Tensor | None = None) -> tb.ClothModel:
        """The :class:`~torchbend.ClothModel` of one sample: the same energy modules, plus the sphere (``center``
        3 numbers [m], ``radius`` [m]) under the contact law when there is one; ``pinned`` ``(V,)`` bool."""
        colliders = list(self.solver_model.colliders)
        if self.contact is not None and center is not None and radius is not None:
            c = self.contact
            colliders.append(tb.Sphere(tuple(float(v) for v in center), float(radius), stiffness=c.stiffness,
                                       margin=c.margin, law=c.law, power=c.power))
        m = self.solver_model
        return tb.ClothModel(self.faces, self.rest, bending=m.bending, membrane=m.membrane, density=m.density,
                             gravity=tuple(m.gravity.tolist()), pinned=self.pinned if pinned is None else pinned,
                             colliders=colliders)

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
