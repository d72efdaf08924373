"""Shared machinery of the training scripts: configs, the cloth physics, logging, checkpoints, DDP.

Scripts import torchbend; torchbend never imports this folder.
"""
from __future__ import annotations

import math
import os
import random
import time

import numpy as np
import torch
import torch.distributed as dist

import torchbend as tb

ENERGY_TERMS = {"membrane", "bending", "gravity", "sphere", "ground"}


# ------------------------------------------------------------------------------ config
def load_config(path: str, defaults: dict) -> dict:
    """YAML config merged over ``defaults``; ``ValueError`` naming the key for unknown or bad values."""
    import yaml

    if not os.path.isfile(path):
        raise ValueError(f"config file not found: {path}")
    with open(path) as f:
        try:
            cfg = yaml.safe_load(f) or {}
        except yaml.YAMLError as e:
            raise ValueError(f"config {path}: invalid YAML ({e})") from None
    if not isinstance(cfg, dict):
        raise ValueError(f"config {path}: expected a mapping at the top level")
    out = {}
    for section, values in defaults.items():
        given = cfg.pop(section, {}) or {}
        if not isinstance(given, dict):
            raise ValueError(f"config key '{section}' must be a mapping")
        unknown = set(given) - set(values)
        if unknown:
            raise ValueError(f"unknown config keys {[f'{section}.{k}' for k in sorted(unknown)]}")
        out[section] = {**values, **given}
    if cfg:
        raise ValueError(f"unknown config keys {sorted(cfg)}; allowed sections: {sorted(defaults)}")
    return out


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
            self.bend = tb.BendingEnergy(faces, rest, model=c["bending_model"], stiffness=modules["bending"].stiffness)
        gravity = modules.get("gravity") or tb.losses.Gravity(faces, rest, density)
        self.mass = density * gravity.areas.to(device)  # (V,) lumped masses [kg]

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
            g = g + modules["membrane"].gradient(x)
        if "bending" in modules:
            g = g + modules["bending"].gradient(x)
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
def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def distributed() -> tuple[int, int]:
    """``(rank, world_size)``; initialises a gloo process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    return (dist.get_rank(), dist.get_world_size()) if dist.is_initialized() else (0, 1)


def save_checkpoint(path: str, **state) -> None:
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str) -> dict:
    if not os.path.isfile(path):
        raise ValueError(f"--resume: no checkpoint at {path}")
    return torch.load(path, weights_only=False)


class Timer:
    def __init__(self):
        self.t = time.perf_counter()

    def lap(self) -> float:
        now = time.perf_counter()
        dt, self.t = now - self.t, now
        return dt


def save_drape_png(path: str, meshes, titles=None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(4 * len(meshes), 4))
    for i, (x, faces) in enumerate(meshes):
        ax = fig.add_subplot(1, len(meshes), i + 1, projection="3d")
        p = x.detach().cpu().numpy()
        ax.plot_trisurf(p[:, 0], p[:, 1], p[:, 2], triangles=faces.cpu().numpy(), color="tab:blue",
                        edgecolor="k", linewidth=0.1)
        if titles:
            ax.set_title(titles[i], fontsize=8)
        ax.set_box_aspect((1, 1, 0.6))
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
