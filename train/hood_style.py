"""HOOD-style self-supervised cloth dynamics: a network steps the cloth in time, physics is the loss.

    python train/hood_style.py                                   # configs/train_hood.yaml: HOOD's convention
    python train/hood_style.py --steps 2000 --set train.batch=16 --device cuda
    python train/hood_style.py --set convention=torchbend        # torchbend's own loss terms instead

As in HOOD (Grigorev et al. 2023) and SNUG (Santesteban et al. 2022), without ground truth: a network maps
the cloth's current state (positions, velocities), the body's next state and the sequence's material to the
next positions; the loss of each predicted step is the incremental potential of one backward-Euler step.

``convention: hood`` (the default) is HOOD's training loss formula by formula
(:func:`torchbend.losses.hood.criteria`: StVK stretching with HOOD's Lame parameters, HOOD's bending with the
current edge length, inertia with the first step's ``dt = 1/3`` s, gravity along ``-y``, the collision
penalty against the nearest body face centroids with its weight ramp, friction), on HOOD's kind of scene:
the shipped skirt (``asset:skirt.obj``) on a body of hips and legs (:func:`torchbend.mesh.procedural.mannequin`),
both turned y-up as HOOD's data is, the body walking at a per-sequence velocity; materials drawn as HOOD draws
them (:func:`torchbend.losses.hood.sample_materials`: independent ``lame_mu``, ``lame_lambda``,
``bending_coeff``, ``density`` over HOOD's ranges), the network fed their normalised values.
``convention: torchbend`` is torchbend's terms (:mod:`torchbend.losses`: ``Stretch``, ``Bending``,
``Gravity``, ``Inertia``, ``BodyContact``) on a square cloth over a moving sphere, z-up.

Training runs autoregressive rollouts: each step continues every sequence of the batch from the network's own
previous prediction, and a new batch of sequences starts every ``train.rollout`` steps.  Every
``eval.every`` steps (and at the end) the network rolls out ``eval.sequences`` held-out sequences (their own
seed): TensorBoard gets their mean loss per step, the RMS of the potential's gradient at the predictions
(the residual, [N]), the mean ``|theta - theta_rest|`` and the predicted meshes; the run ends with a picture
(``<out>/eval.png``) of the last held-out predictions on their bodies.

The network is a plain MLP on the flattened state (no graph network, so it is tied to one mesh).  The cloth
is the config's ``mesh`` unless ``main(argv, mesh=(rest, faces))`` passes one (placed by the caller).  Common
options of every torchbend script (``--config``, ``--set``, ``--seed``, ``--device``, ``--out``, ``--resume``,
``--log-level``, ``--no-progress``) plus ``--steps``.  TensorBoard logs every loss term (``loss/<name>``,
unweighted, joules), the total and seconds per step; checkpoints (weights only, the validated config as plain
values) with ``--resume`` (a resumed run starts new sequences).
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
from typing import Annotated, Literal

import common as tc
import torch
from pydantic import AfterValidator, BeforeValidator, Field
from torch import nn

import torchbend as tb
from torchbend._extras import require
from torchbend.losses import hood
from torchbend.mesh.procedural import mannequin
from torchbend.scenes import cli
from torchbend.scenes import config as sc

log = logging.getLogger("train.hood_style")
CONFIG = tc.config_file("train_hood.yaml")
TERMS = {"hood": ("stretching", "bending", "inertia", "gravity", "collision", "friction"),
         "torchbend": ("stretch", "bending", "gravity", "inertia", "contact")}
"""The loss terms of each convention (their TensorBoard tags ``loss/<name>``)."""


# ------------------------------------------------------------------------------ config
def _pair(value):
    if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ValueError(f"must be a pair [lo, hi], got {value!r}")
    if any(isinstance(v, bool) for v in value):
        raise ValueError(f"must be a pair of numbers [lo, hi], got {value!r}")
    return value


def _ordered(value):
    if value[0] > value[1]:
        raise ValueError(f"must be a pair [lo, hi] with lo <= hi, got {list(value)}")
    return value


Ratio = Annotated[float, Field(gt=-1.0, lt=2.0)]
# a sampling range [lo, hi] (lo <= hi), of positive numbers or of Lame ratios in (-1, 2)
PositiveRange = Annotated[tuple[tc.Positive, tc.Positive], BeforeValidator(_pair), AfterValidator(_ordered)]
RatioRange = Annotated[tuple[Ratio, Ratio], BeforeValidator(_pair), AfterValidator(_ordered)]
_H = hood.HOOD_RANGES


class SamplingSection(tc.Section):
    """``sampling``: HOOD's material coefficients, sampled per sequence in ``[lo, hi]`` (defaults: HOOD's
    training ranges): ``lame_mu`` [Pa] and ``bending_coeff`` [N m] log-uniform, areal ``density`` [kg/m^2]
    uniform; ``lame_lambda`` [Pa] uniform and independent (``convention: hood``, as HOOD) or ``lame_mu``
    times a ratio uniform in ``lame_lambda_ratio`` (``convention: torchbend``: within (-1, 2), a Poisson ratio
    below 0.5)."""

    lame_mu: PositiveRange = _H["lame_mu"]
    lame_lambda: PositiveRange = _H["lame_lambda"]
    lame_lambda_ratio: RatioRange = (0.2, 1.8)
    bending_coeff: PositiveRange = _H["bending_coeff"]
    density: PositiveRange = _H["density"]


class BodySection(tc.Section):
    """``body``: ``convention: hood``: the mannequin (hips, an icosphere of ``subdivisions``, and legs) walking
    from the origin; ``torchbend``: an icosphere of ``subdivisions`` with a per-sequence radius uniform in
    ``radius`` [m], starting uniform in ``[-offset, offset]^2`` [m].  Both move horizontally at ``speed``
    [m/s] in a uniform direction."""

    subdivisions: Annotated[tc.Int, Field(ge=0, le=8)] = 2  # 20 * 4**s faces: 1.3 million at 8
    radius: PositiveRange = (0.15, 0.25)
    offset: tc.NonNegative = 0.1
    speed: tc.NonNegative = 0.2


class WeightsSection(tc.Section):
    """``loss.weights``: the weight of each term (0 leaves it out); each convention uses its own names
    (:data:`TERMS`)."""

    stretch: tc.NonNegative = 1.0
    stretching: tc.NonNegative = 1.0
    bending: tc.NonNegative = 1.0
    gravity: tc.NonNegative = 1.0
    inertia: tc.NonNegative = 1.0
    contact: tc.NonNegative = 1.0
    collision: tc.NonNegative = 1.0
    friction: tc.NonNegative = 1.0


class HoodSection(tc.Section):
    """``hood``: HOOD's collision margin ``eps`` [m], the collision weight ramp ``collision_weight`` [start, max]
    over ``rampup`` [first iteration, iterations], friction coefficient and its (squared-distance) radius."""

    eps: tc.NonNegative = 2e-3
    collision_weight: PositiveRange = (5e3, 5e5)
    rampup: tuple[sc.NonNegativeInt, tc.PositiveInt] = (50000, 100000)
    friction: tc.NonNegative = 0.5
    radius: tc.Positive = 3e-3


class LossSection(tc.Section):
    """``loss``: time step ``dt`` [s], ``normalize`` (divide by ``M g L``, :func:`torchbend.losses.energy_scale`,
    at the mid-range density) and the term ``weights``; the body contact's law of ``convention: torchbend`` is
    the ``contact`` section, HOOD's terms are set by the ``hood`` section."""

    dt: tc.Positive = hood.REGULAR_DT
    normalize: bool = True
    weights: WeightsSection = WeightsSection()


class EvalSection(tc.Section):
    """``eval``: every ``every`` steps (and at the end) roll out ``sequences`` held-out sequences of
    ``train.rollout`` steps drawn with ``seed`` (never trained on)."""

    every: tc.PositiveInt = 100
    sequences: tc.PositiveInt = 4
    seed: tc.Seed = 12345


class StepModel(tc.ModelSection):
    """``model``: the MLP's ``hidden`` width, ``layers``, ``output_scale`` [m/s^2] (the acceleration of a raw
    output of 1 shared by all vertices: about g) and ``vertex_scale`` [m/s^2] (that of a raw output of 1 of
    one vertex: small, so that an untrained network's outputs do not tear the cloth)."""

    hidden: tc.PositiveInt = 256
    output_scale: tc.Positive = 10.0
    vertex_scale: tc.Positive = 1.0


class TrainSection(tc.TrainBase):
    """``train``: optimisation (Adam, learning rate ``lr`` decaying exponentially to ``lr * lr_decay`` at the last
    step, as HOOD's; gradient norm clipped at ``clip_grad``), sequences of ``rollout`` steps, logging cadence."""

    steps: tc.PositiveInt = 500
    batch: tc.Batch = 8
    rollout: tc.PositiveInt = 20
    lr: tc.Positive = 1.0e-4
    lr_decay: Annotated[float, Field(gt=0.0, le=1.0)] = 0.1
    clip_grad: tc.Positive = 1.0
    checkpoint_every: tc.PositiveInt = 100
    dtype: Literal["float32", "float64"] = "float32"


class Config(sc.PhysicsConfig):
    """The HOOD-style config (``configs/train_hood.yaml``): the physics sections of a scene config
    (:class:`~torchbend.scenes.config.PhysicsConfig`: ``mesh``, by default the shipped skirt (its waist ring on
    the mannequin's hips); ``material.thickness`` [m], that of the stretch energy ``A t Psi`` (the moduli and the
    density are sampled per sequence: ``sampling``); ``contact``, the law of ``convention: torchbend``'s body
    contact) and the script's own: ``convention`` (``hood``: HOOD's loss, y-up; ``torchbend``: torchbend's)."""

    convention: Literal["hood", "torchbend"] = "hood"
    mesh: sc.MeshSection = sc.FileMesh(type="file", path="asset:skirt.obj")
    material: sc.MaterialSection = sc.MaterialSection(thickness=hood.DEFAULT_MATERIAL["thickness"])
    contact: sc.ContactSection | None = sc.ContactSection(law="barrier", stiffness=1.0e4, margin=4.0e-3, power=3.0)
    sampling: SamplingSection = SamplingSection()
    body: BodySection = BodySection()
    hood: HoodSection = HoodSection()
    loss: LossSection = LossSection()
    eval: EvalSection = EvalSection()
    model: StepModel = StepModel()
    train: TrainSection = TrainSection()


def y_up(p: torch.Tensor) -> torch.Tensor:
    """z-up positions turned y-up (a rotation about x: ``(x, y, z) -> (x, z, -y)``), as HOOD's data is."""
    return torch.stack((p[..., 0], p[..., 2], -p[..., 1]), -1)


def z_up(p: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`y_up` (for pictures)."""
    return torch.stack((p[..., 0], -p[..., 2], p[..., 1]), -1)


def cloth_mesh(cfg: dict, dtype, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rest (V, 3) [m], faces (F, 3))``: the config's ``mesh`` (offset applied; turned y-up in HOOD's
    convention)."""
    if cfg["mesh"].get("pin") is not None:
        raise sc.ConfigError("config key 'mesh.pin': hood_style pins no vertices (the cloth moves freely over the body)")
    rest, faces = sc.build_mesh(cfg["mesh"], dtype=dtype, device=device)
    return (y_up(rest) if cfg["convention"] == "hood" else rest), faces


def body_mesh(cfg: dict, dtype, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The body's template ``(vertices, faces)``: the y-up mannequin (HOOD) or the unit icosphere (torchbend)."""
    s = int(cfg["body"]["subdivisions"])
    if cfg["convention"] == "hood":
        v, f = mannequin(s, dtype=dtype, device=device)
        return y_up(v), f
    return tb.scenes.icosphere(s, 1.0, dtype=dtype, device=device)


class Sequences:
    """Per-sequence conditions of a batch: HOOD materials (and ours), the body's start, velocity and (sphere)
    radius (``cfg``: a validated config, :func:`load_config` with :class:`Config`)."""

    def __init__(self, cfg: dict, batch: int, gen: torch.Generator, dtype, device):
        m, b = cfg["sampling"], cfg["body"]
        self.convention = cfg["convention"]
        ranges = {k: tuple(float(v) for v in m[k]) for k in ("lame_mu", "lame_lambda", "bending_coeff", "density")}
        mats = hood.sample_materials(batch, generator=gen, ranges=ranges, dtype=dtype, device=device)
        self.lame_mu, self.bending_coeff, self.density = mats["lame_mu"], mats["bending_coeff"], mats["density"]
        if self.convention == "hood":
            self.lame_lambda = mats["lame_lambda"]
            self.inputs = torch.stack([mats[f"{k}_input"] for k in ranges], -1)
        else:
            lo, hi = (float(v) for v in m["lame_lambda_ratio"])
            self.lame_lambda = self.lame_mu * (lo + (hi - lo) * mats["lame_lambda_input"])
            self.young, self.poisson = tb.material_from_lame(self.lame_mu, self.lame_lambda)
            self.bending_stiffness = tb.bending_stiffness_from_hood(self.bending_coeff)
        u = torch.rand(batch, generator=gen, dtype=torch.float64)
        lo, hi = (float(v) for v in b["radius"])
        self.radius = (lo + u * (hi - lo)).to(dtype=dtype, device=device)
        angle = 2 * math.pi * torch.rand(batch, generator=gen, dtype=torch.float64)
        start = (2 * torch.rand(batch, 2, generator=gen, dtype=torch.float64) - 1) * float(b["offset"])
        c, s_ = angle.cos(), angle.sin()
        zero = torch.zeros_like(angle)
        if self.convention == "hood":  # y-up: walking in the x-z plane from the origin
            self.start = torch.zeros(batch, 3, dtype=dtype, device=device)
            direction = torch.stack((c, zero, s_), 1)
        else:
            self.start = torch.cat((start, torch.zeros(batch, 1, dtype=torch.float64)), 1).to(dtype=dtype, device=device)
            direction = torch.stack((c, s_, zero), 1)
        self.velocity = (float(b["speed"]) * direction).to(dtype=dtype, device=device)

    def center(self, t: float) -> torch.Tensor:
        """The body's translation ``(B, 3)`` [m] at time ``t`` [s]."""
        return self.start + t * self.velocity

    def body(self, template: torch.Tensor, t: float) -> torch.Tensor:
        """The body's vertices ``(B, Vb, 3)`` at time ``t`` [s]."""
        if self.convention == "hood":
            return template + self.center(t)[:, None, :]
        return self.center(t)[:, None, :] + self.radius[:, None, None] * template

    def features(self) -> torch.Tensor:
        """HOOD: ``(B, 8)``, its normalised material inputs, the body's velocity and a constant; torchbend:
        ``(B, 9)``, log-materials (normalised to O(1)), body radius and velocity."""
        if self.convention == "hood":
            return torch.cat((self.inputs, self.velocity * 5, torch.ones_like(self.radius)[:, None]), -1)
        return torch.stack((self.lame_mu.log() - math.log(3e4), self.lame_lambda.log() - math.log(3e4),
                            self.bending_coeff.log() - math.log(1e-5), self.density * 5, self.radius * 5,
                            *(self.velocity * 5).unbind(-1), torch.ones_like(self.radius)), -1)

    def materials(self) -> dict:
        """The per-sample loss inputs of the materials, by the convention's names."""
        if self.convention == "hood":
            return {"density": self.density, "lame_mu": self.lame_mu, "lame_lambda": self.lame_lambda,
                    "bending_coeff": self.bending_coeff}
        return {"density": self.density, "young": self.young, "poisson": self.poisson,
                "bending_stiffness": self.bending_stiffness}


class StepNet(nn.Module):
    """MLP: (state relative to the body, sequence features) -> next positions ``x + dt v + dt^2 a``, with the
    accelerations ``a_i = s_v net_i(...) + s net_0(...)`` [m/s^2]: one per vertex and one shared by all
    (``s = output_scale``, about g; ``s_v = vertex_scale``, smaller).  The shared one
    moves the centre of mass, which gravity and contact drive coherently while the internal (stretch,
    bending) forces sum to zero over the vertices: without it the optimiser sees gravity only through
    per-vertex outputs, where the elastic forces of an untrained prediction drown it and the cloth
    learns to hover."""

    def __init__(self, vertex_count: int, features: int, hidden: int, layers: int, output_scale: float,
                 vertex_scale: float | None = None):
        super().__init__()
        dims = [6 * vertex_count + 3 + features] + [hidden] * layers + [3 * vertex_count + 3]
        tc.check_network_size(sum((a + 1) * b for a, b in zip(dims[:-1], dims[1:])),
                           f"model.hidden ({hidden}), model.layers ({layers}) or the cloth ({vertex_count} vertices)")
        dims = dims[:-1]
        mods: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:], strict=True):
            mods += [nn.Linear(a, b), nn.Tanh()]
        last = nn.Linear(hidden, 3 * vertex_count + 3)
        nn.init.zeros_(last.weight)  # the untrained network predicts free flight: x + dt v
        nn.init.zeros_(last.bias)
        self.net = nn.Sequential(*mods, last)
        self.vertex_count, self.output_scale = vertex_count, float(output_scale)
        self.vertex_scale = float(output_scale if vertex_scale is None else vertex_scale)

    def forward(self, x, v, dt: float, body_center, features):
        rel = x - body_center[:, None, :]
        inp = torch.cat((rel.flatten(1), (v * dt).flatten(1) * 10, body_center, features), 1)
        out = self.net(inp)
        a = self.vertex_scale * out[:, 3:].reshape(x.shape) + self.output_scale * out[:, None, :3]
        return x + dt * v + (dt * dt) * a


def _torchbend_terms(cfg: dict, rest, faces, body_faces) -> dict:
    contact = sc.ContactSection.model_validate(cfg["contact"]) if cfg["contact"] is not None else None
    if contact is None:
        raise sc.ConfigError("config key 'contact': the body contact needs a contact law (e.g. {law: barrier, "
                             "stiffness: 1.0e+4, margin: 4.0e-3, power: 3})")
    # the stored materials are placeholders: every call passes the sampled per-sample ones
    young, poisson = tb.material_from_lame(3e4, 3e4)
    dt = float(cfg["loss"]["dt"])
    return {
        "stretch": tb.losses.Stretch(faces, rest, young=young, poisson=poisson, thickness=float(cfg["material"]["thickness"])),
        "bending": tb.losses.Bending(faces, rest, 1e-6),  # quadratic: see torchbend.losses.elastic
        "gravity": tb.losses.Gravity(faces, rest, 0.2),
        "inertia": tb.losses.Inertia(faces, rest, 0.2, dt),
        "contact": tb.losses.BodyContact(stiffness=contact.stiffness, eps=contact.margin, law=contact.contact_law(),
                                         body_faces=body_faces),
    }


def _hood_terms(cfg: dict, rest, faces, body_faces) -> dict:
    h = cfg["hood"]
    start, ramp = (int(v) for v in h["rampup"])
    w0, w1 = (float(v) for v in h["collision_weight"])
    return {
        "stretching": hood.Stretching(faces, rest, thickness=float(cfg["material"]["thickness"])),
        "bending": hood.Bending(faces, rest),
        "inertia": hood.Inertia(faces, rest, dt=float(cfg["loss"]["dt"])),
        "gravity": hood.Gravity(faces, rest, axis=1),
        "collision": hood.Collision(body_faces, eps=float(h["eps"]), weight_start=w0, weight_max=w1,
                                    start_rampup_iteration=start, n_rampup_iterations=ramp),
        "friction": hood.Friction(faces, rest, body_faces, mu=float(h["friction"]), radius=float(h["radius"])),
    }


def build_loss(cfg: dict, rest, faces, body_faces) -> tb.ClothLoss:
    """The ClothLoss of the convention's terms (materials per call; ``cfg``: a validated config)."""
    lc = cfg["loss"]
    build = _hood_terms if cfg["convention"] == "hood" else _torchbend_terms
    terms = build(cfg, rest, faces, body_faces)
    weights = {name: float(lc["weights"][name]) for name in terms}
    if lc["normalize"]:  # joules -> O(1): divide by M g L of a mid-range density (torchbend.losses.cloth_loss)
        scale = tb.losses.energy_scale(faces, rest, sum(float(v) for v in cfg["sampling"]["density"]) / 2)
        weights = {k: w / scale for k, w in weights.items()}
    return tb.ClothLoss(terms, weights)


class Rollout:
    """The state of a batch of sequences: the cloth at the current and previous frames, the frame number,
    and the keyword inputs of the loss for the next prediction."""

    def __init__(self, seq: Sequences, rest: torch.Tensor, template: torch.Tensor, dt: float):
        self.seq, self.template, self.dt = seq, template, dt
        self.x = rest.expand(len(seq.density), -1, -1).clone()
        self.x_prev, self.frame = self.x, 0

    def inputs(self, iteration: int) -> dict:
        """The loss inputs of the prediction of frame ``frame + 1`` (bodies at frames ``frame - 1 .. frame + 1``)."""
        f, dt, seq = self.frame, self.dt, self.seq
        if seq.convention == "hood":
            return {"x_curr": self.x, "x_prev": self.x_prev, "body_prev": seq.body(self.template, (f - 1) * dt),
                    "body_curr": seq.body(self.template, f * dt), "body_next": seq.body(self.template, (f + 1) * dt),
                    "first_step": f == 0, "iteration": iteration, **seq.materials()}
        return {"x_prev": self.x, "v_prev": (self.x - self.x_prev) / dt, "body": seq.body(self.template, (f + 1) * dt),
                **seq.materials()}

    def predict(self, net: nn.Module) -> torch.Tensor:
        dt, seq = self.dt, self.seq
        return net(self.x, (self.x - self.x_prev) / dt, dt, seq.center((self.frame + 1) * dt), seq.features())

    def advance(self, x_next: torch.Tensor) -> None:
        self.x_prev, self.x, self.frame = self.x, x_next.detach(), self.frame + 1


def evaluate(cfg: dict, net: nn.Module, loss_fn: tb.ClothLoss, rest, faces, template, dtype, device) -> dict:
    """Roll out the held-out sequences (``eval`` section) with the network: the mean loss per step, the RMS of
    the potential's gradient at the predictions [N] (the residual of each step's incremental potential), the
    mean ``|theta - theta_rest|`` [rad], and the last predictions and bodies."""
    e, dt = cfg["eval"], float(cfg["loss"]["dt"])
    seq = Sequences(cfg, int(e["sequences"]), torch.Generator().manual_seed(int(e["seed"])), dtype, device)
    roll = Rollout(seq, rest, template, dt)
    topo = tb.HingeTopology.from_faces(faces.cpu())
    theta_rest = tb.hinge_angles(rest, topo.to(device))
    scale = {k: float(w) for k, w in loss_fn.weights.items()}
    losses, residuals, angles = [], [], []
    for _ in range(int(cfg["train"]["rollout"])):
        kw = roll.inputs(0)
        with torch.no_grad():
            x_next = roll.predict(net)
        x = x_next.detach().requires_grad_()
        with torch.enable_grad():
            total, _ = loss_fn(x, **kw)
            energies = loss_fn.energies(x, **kw)  # unweighted, per sample [J]
            energy = torch.stack([v.sum() for k, v in energies.items() if scale[k] != 0]).sum()
            (g,) = torch.autograd.grad(energy, x)
        losses.append(float(total.detach()))
        residuals.append(float(g.pow(2).sum(-1).mean().sqrt()))
        angles.append(float((tb.hinge_angles(x.detach(), topo.to(device)) - theta_rest).abs().mean()))
        roll.advance(x_next)
    body = seq.body(template, roll.frame * dt)
    return {"loss": sum(losses) / len(losses), "residual_rms": sum(residuals) / len(residuals),
            "mean_abs_theta_minus_rest": sum(angles) / len(angles), "x": roll.x, "body": body}


def log_eval(writer, result: dict, faces, body_faces, step: int) -> None:
    writer.add_scalar("eval/loss", result["loss"], step)
    writer.add_scalar("eval/residual_rms", result["residual_rms"], step)
    writer.add_scalar("eval/mean_abs_theta_minus_rest", result["mean_abs_theta_minus_rest"], step)
    writer.add_mesh("eval/prediction", vertices=result["x"][:1].float().cpu(), faces=faces[None].int().cpu(),
                    global_step=step)


def save_picture(path: str, cfg: dict, result: dict, faces, body_faces, count: int = 2) -> None:
    """PNG of the last held-out predictions on their bodies (z-up for the view)."""
    up = z_up if cfg["convention"] == "hood" else (lambda p: p)
    n = min(count, result["x"].shape[0])
    from torchbend.scenes.plot import snapshot

    panels = [([(up(result["x"][b]).cpu(), faces.cpu()), (up(result["body"][b]).cpu(), body_faces.cpu())], ())
              for b in range(n)]
    snapshot(path, panels, titles=[f"held-out sequence {b}" for b in range(n)], size=4.0, dpi=90)


def parse_args(argv=None) -> argparse.Namespace:
    return cli.parse_args(tc.script_parser(__doc__, CONFIG, "runs/hood_style"), argv)


def overrides(a: argparse.Namespace) -> list[str]:
    """``--set`` overrides plus the script's own flags (``--steps``, ``--seed``)."""
    return tc.flag_overrides(a)


def log_losses(writer, values: dict, total: float, step: int, seconds_per_step: float) -> None:
    """The step's unweighted term values, total loss and time per step to TensorBoard."""
    for name, value in values.items():
        writer.add_scalar(f"loss/{name}", float(value), step)
    writer.add_scalar("loss/total", total, step)
    writer.add_scalar("time/seconds_per_step", seconds_per_step, step)


def main(argv=None, mesh: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict:
    """Train; ``mesh = (rest (V, 3), faces (F, 3))`` replaces the config's cloth (placed as given).  Returns
    ``{"losses", "terms", "eval", "start", "steps"}`` (``eval``: ``{step: held-out mean loss per step}``)."""
    SummaryWriter = require("torch.utils.tensorboard", "TensorBoard logs").SummaryWriter
    from tqdm import tqdm

    a = parse_args(argv)
    device = cli.resolve_device(a.device)
    cfg = tc.load_config(a.config, Config, overrides(a))
    t = cfg["train"]
    dtype = getattr(torch, t["dtype"])
    tc.seed_everything(int(t["seed"]))
    if mesh is None:
        rest, faces = cloth_mesh(cfg, dtype, device)
    else:
        rest, faces = mesh[0].to(dtype=dtype, device=device), mesh[1].to(device)
    template, body_faces = body_mesh(cfg, dtype, device)
    loss_fn = build_loss(cfg, rest, faces, body_faces).to(device)
    dt = float(cfg["loss"]["dt"])
    m = cfg["model"]
    features = Sequences(cfg, 1, torch.Generator().manual_seed(0), dtype, device).features().shape[1]
    net = StepNet(len(rest), features, int(m["hidden"]), int(m["layers"]), float(m["output_scale"]),
                  float(m["vertex_scale"])).to(dtype=dtype, device=device)
    opt = torch.optim.Adam(net.parameters(), lr=float(t["lr"]))
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")
    start = 0
    if a.resume:
        start = tc.resume_run(ckpt_path, cfg, log, (net, "model"), (opt, "optimizer"), map_location=device,
                              hint="the same config: another mesh passed to main?")
    decay = float(t["lr_decay"]) ** (1.0 / max(1, int(t["steps"])))
    schedule = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: decay ** (k + start))
    gen = torch.Generator().manual_seed(int(t["seed"]) * 1000 + 7919 * start)
    writer = SummaryWriter(os.path.join(a.out, "tb"))
    batch, rollout, steps, log_every = int(t["batch"]), int(t["rollout"]), int(t["steps"]), int(t["log_every"])
    history: list[float] = []
    terms: dict[str, list[float]] = {}  # per evaluated term (weight != 0), unweighted [J]
    evals: dict[int, float] = {}
    timer, lap = tc.Timer(), tc.Timer()
    roll = None
    logged = start

    def run_eval(step: int) -> dict:
        result = evaluate(cfg, net, loss_fn, rest, faces, template, dtype, device)
        log_eval(writer, result, faces, body_faces, step)
        evals[step] = result["loss"]
        return result

    if start == 0:
        run_eval(0)  # the untrained network: free flight
    for step in tqdm(range(start + 1, steps + 1), desc="train (hood-style)", disable=a.no_progress,
                     initial=start, total=steps):
        if roll is None or roll.frame == rollout:  # new sequences: materials, bodies, cloth at rest
            roll = Rollout(Sequences(cfg, batch, gen, dtype, device), rest, template, dt)
        x_next = roll.predict(net)
        total, values = loss_fn(x_next, **roll.inputs(step))
        opt.zero_grad(set_to_none=True)
        total.backward()
        nn.utils.clip_grad_norm_(net.parameters(), float(t["clip_grad"]))  # early rollouts can reach large losses
        opt.step()
        schedule.step()
        roll.advance(x_next)
        history.append(float(total.detach()))
        for name, value in values.items():
            terms.setdefault(name, []).append(float(value))
        if step % log_every == 0 or step == steps:
            log_losses(writer, values, history[-1], step, lap.lap() / (step - logged))
            logged = step
        if step % int(cfg["eval"]["every"]) == 0 and step != steps:
            run_eval(step)
        if step % int(t["checkpoint_every"]) == 0 or step == steps:
            tc.save_checkpoint(ckpt_path, step=step, model=net.state_dict(), optimizer=opt.state_dict(), config=cfg)
    final = run_eval(steps)
    save_picture(os.path.join(a.out, "eval.png"), cfg, final, faces, body_faces)
    writer.close()
    result = {"losses": history, "terms": terms, "eval": evals, "start": start, "steps": steps}
    with open(os.path.join(a.out, "history.json"), "w") as f:
        json.dump(result, f)
    if history:
        first = evals[min(evals)]
        log.info("held-out loss per step %.4g (step %d) -> %.4g (step %d); training loss %.4g -> %.4g (%s); "
                 "%.3f s/step -> %s", first, min(evals), evals[steps], steps, history[0], history[-1],
                 ", ".join(f"{k} {vals[-1]:.3g} J" for k, vals in terms.items() if vals),
                 timer.total() / len(history), a.out)
    return result


if __name__ == "__main__":
    cli.run_main(main)
