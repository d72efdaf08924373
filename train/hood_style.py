"""HOOD-style self-supervised cloth dynamics: a network steps the cloth in time, physics is the loss.

    python train/hood_style.py                                   # configs/train_hood.yaml
    python train/hood_style.py --steps 2000 --set train.batch=16 --device cuda
    python train/hood_style.py --set "mesh={type: file, path: 'asset:skirt.obj', offset: [0, 0, 0.65]}"
                                                                 # the shipped skirt instead of the grid

As in HOOD (Grigorev et al. 2023) and SNUG (Santesteban et al. 2022), without ground truth: a
network maps the cloth's current state (positions, velocities), the body's next state and the
sequence's material to the next positions; the loss of each predicted step is the incremental
potential of one backward-Euler step, a :class:`torchbend.ClothLoss` of

    stretch (StVK) + bending (quadratic hinges) + gravity + inertia (x_hat = x + dt v) + body contact

with materials sampled per sequence in HOOD's own coefficients (``lame_mu``, ``lame_lambda``,
``bending_coeff``, areal ``density``) and converted to torchbend's
(:func:`torchbend.material_from_lame`, :func:`torchbend.bending_stiffness_from_hood`).  The body is
a triangle mesh (an icosphere of per-sample radius moving at a per-sample velocity) with HOOD's
contact penalty (nearest body vertex, its normal, ``k max(0, eps - d)^3``).  Training runs
autoregressive rollouts: each step continues every sequence of the batch from the network's own
previous prediction, and a new batch of sequences (materials, bodies, cloth at rest) starts every
``train.rollout`` steps.

The network is a plain MLP on the flattened state (no graph network, so it is tied to one mesh).
The cloth is the config's ``mesh`` (a scene-config mesh section: the default square grid, ``mesh:
garment.obj`` or ``{type: file, path, weld_tol, offset}``, read with :func:`torchbend.mesh.load`) unless
``main(argv, mesh=(rest, faces))`` passes one (placed by the caller;
the body moves about the origin).  Common options of every torchbend script (``--config``, ``--set``,
``--seed``, ``--device``, ``--out``, ``--resume``, ``--log-level``, ``--no-progress``) plus
``--steps``.  TensorBoard logs every loss term (``loss/<name>``, unweighted, joules), the total and
seconds per step; checkpoints (weights only, the validated config as plain values) with ``--resume``
(a resumed run starts new sequences).
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
from torchbend.scenes import cli
from torchbend.scenes import config as sc

log = logging.getLogger("train.hood_style")
CONFIG = tc.config_file("train_hood.yaml")
TERMS = ("stretch", "bending", "gravity", "inertia", "contact")


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


class SamplingSection(tc.Section):
    """``sampling``: HOOD's material coefficients, sampled per sequence in ``[lo, hi]``: ``lame_mu`` [Pa] and
    ``bending_coeff`` [N m] log-uniform, ``lame_lambda = ratio * lame_mu`` with the ratio uniform in
    ``lame_lambda_ratio`` (within (-1, 2): a Poisson ratio in (-1, 0.5)), areal ``density`` [kg/m^2]
    uniform."""

    lame_mu: PositiveRange = (1.5e4, 6.0e4)
    lame_lambda_ratio: RatioRange = (0.2, 1.8)
    bending_coeff: PositiveRange = (1.0e-6, 1.0e-4)
    density: PositiveRange = (0.1, 0.4)


class BodySection(tc.Section):
    """``body``: an icosphere of ``subdivisions`` with a per-sequence radius uniform in ``radius`` [m],
    start uniform in ``[-offset, offset]^2`` [m] (z = 0) and a horizontal velocity of ``speed`` [m/s]
    in a uniform direction."""

    subdivisions: Annotated[tc.Int, Field(ge=0, le=8)] = 2  # 20 * 4**s faces: 1.3 million at 8
    radius: PositiveRange = (0.15, 0.25)
    offset: tc.NonNegative = 0.1
    speed: tc.NonNegative = 0.2


class WeightsSection(tc.Section):
    """``loss.weights``: the weight of each term (0 leaves it out)."""

    stretch: tc.NonNegative = 1.0
    bending: tc.NonNegative = 1.0
    gravity: tc.NonNegative = 1.0
    inertia: tc.NonNegative = 1.0
    contact: tc.NonNegative = 1.0


class LossSection(tc.Section):
    """``loss``: time step ``dt`` [s], ``normalize`` (divide by ``M g L``, :func:`torchbend.losses.energy_scale`,
    at the mid-range density) and the term ``weights``; the body contact's law is the ``contact`` section."""

    dt: tc.Positive = 1.0 / 30.0
    normalize: bool = True
    weights: WeightsSection = WeightsSection()


class StepModel(tc.ModelSection):
    """``model``: the MLP's ``hidden`` width, ``layers`` and ``output_scale`` [m/s^2] (the
    acceleration of a raw output of 1)."""

    hidden: tc.PositiveInt = 256
    output_scale: tc.Positive = 10.0


class TrainSection(tc.TrainBase):
    """``train``: optimisation (Adam, gradient norm clipped at ``clip_grad``), sequences of ``rollout``
    steps, logging cadence."""

    steps: tc.PositiveInt = 500
    batch: tc.Batch = 8
    rollout: tc.PositiveInt = 20
    lr: tc.Positive = 1.0e-4
    clip_grad: tc.Positive = 1.0
    checkpoint_every: tc.PositiveInt = 100
    dtype: Literal["float32", "float64"] = "float32"


class Config(sc.PhysicsConfig):
    """The HOOD-style config (``configs/train_hood.yaml``): the physics sections of a scene config
    (:class:`~torchbend.scenes.config.PhysicsConfig`: ``mesh``, by default a 9 x 9 square of 0.8 m flat at
    0.32 m above the body's mean position; ``material.thickness`` [m], that of the stretch energy ``A t Psi``
    (the moduli and the density are sampled per sequence: ``sampling``); ``contact``, the law of the body
    contact, HOOD's ``k max(0, eps - d)^3``) and the script's own."""

    mesh: sc.MeshSection = sc.GridMesh(nx=9, size=(0.8, 0.8), offset=(-0.4, -0.4, 0.32))
    material: sc.MaterialSection = sc.MaterialSection(thickness=4.7e-4)
    contact: sc.ContactSection | None = sc.ContactSection(law="barrier", stiffness=1.0e4, margin=4.0e-3, power=3.0)
    sampling: SamplingSection = SamplingSection()
    body: BodySection = BodySection()
    loss: LossSection = LossSection()
    model: StepModel = StepModel()
    train: TrainSection = TrainSection()


def cloth_mesh(cfg: dict, dtype, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rest (V, 3) [m], faces (F, 3))``: the config's ``mesh`` (offset applied)."""
    if cfg["mesh"].get("pin") is not None:
        raise sc.ConfigError("config key 'mesh.pin': hood_style pins no vertices (the cloth moves freely over the body)")
    return sc.build_mesh(cfg["mesh"], dtype=dtype, device=device)


class Sequences:
    """Per-sequence conditions of a batch: HOOD materials (and ours), body radius, start and velocity
    (``cfg``: a validated config, :func:`load_config` with :class:`Config`)."""

    def __init__(self, cfg: dict, batch: int, gen: torch.Generator, dtype, device):
        m, b = cfg["sampling"], cfg["body"]

        def uniform(lo_hi, log=False):
            lo, hi = (float(v) for v in lo_hi)
            u = torch.rand(batch, generator=gen, dtype=torch.float64)
            out = math.log(lo) + u * (math.log(hi) - math.log(lo)) if log else lo + u * (hi - lo)
            return (out.exp() if log else out).to(dtype=dtype, device=device)

        self.lame_mu = uniform(m["lame_mu"], log=True)
        self.lame_lambda = self.lame_mu * uniform(m["lame_lambda_ratio"])
        self.bending_coeff = uniform(m["bending_coeff"], log=True)
        self.density = uniform(m["density"])
        self.young, self.poisson = tb.material_from_lame(self.lame_mu, self.lame_lambda)
        self.bending_stiffness = tb.bending_stiffness_from_hood(self.bending_coeff)
        self.radius = uniform(b["radius"])
        offset = float(b["offset"])
        self.center = torch.cat(((2 * torch.rand(batch, 2, generator=gen, dtype=torch.float64) - 1) * offset,
                                 torch.zeros(batch, 1, dtype=torch.float64)), 1).to(dtype=dtype, device=device)
        angle = 2 * math.pi * torch.rand(batch, generator=gen, dtype=torch.float64)
        self.velocity = (float(b["speed"]) * torch.stack((angle.cos(), angle.sin(), torch.zeros_like(angle)), 1)).to(
            dtype=dtype, device=device)

    def features(self) -> torch.Tensor:
        """``(B, 9)``: log-materials (normalised to O(1)), body radius and velocity."""
        return torch.stack((self.lame_mu.log() - math.log(3e4), self.lame_lambda.log() - math.log(3e4),
                            self.bending_coeff.log() - math.log(1e-5), self.density * 5, self.radius * 5,
                            *(self.velocity * 5).unbind(-1), torch.ones_like(self.radius)), -1)
class StepNet(nn.Module):
    """MLP: (state relative to the body, sequence features) -> next positions ``x + dt v + dt^2 a``, with the
    accelerations ``a_i = s (net_i(...) + net_0(...))`` [m/s^2]: one per vertex and one shared by all
    (``s = output_scale``, about g: a raw output of O(1) is a physical acceleration).  The shared one
    moves the centre of mass, which gravity and contact drive coherently while the internal (stretch,
    bending) forces sum to zero over the vertices: without it the optimiser sees gravity only through
    per-vertex outputs, where the elastic forces of an untrained prediction drown it and the cloth
    learns to hover."""

    def __init__(self, vertex_count: int, features: int, hidden: int, layers: int, output_scale: float):
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

    def forward(self, x, v, dt: float, body_center, features):
        rel = x - body_center[:, None, :]
        inp = torch.cat((rel.flatten(1), (v * dt).flatten(1) * 10, body_center, features), 1)
        out = self.net(inp)
        a = out[:, 3:].reshape(x.shape) + out[:, None, :3]
        return x + dt * v + (dt * dt * self.output_scale) * a


def build_loss(cfg: dict, rest, faces, body_faces) -> tb.ClothLoss:
    """The ClothLoss of stretch, bending, gravity, inertia and body contact (materials per call;
    ``cfg``: a validated config)."""
    lc = cfg["loss"]
    contact = sc.ContactSection.model_validate(cfg["contact"]) if cfg["contact"] is not None else None
    if contact is None:
        raise sc.ConfigError("config key 'contact': the body contact needs a contact law (e.g. {law: barrier, "
                          "stiffness: 1.0e+4, margin: 4.0e-3, power: 3})")
    weights = {name: float(lc["weights"][name]) for name in TERMS}
    # the stored materials are placeholders: every call passes the sampled per-sample ones
    young, poisson = tb.material_from_lame(3e4, 3e4)
    terms = {
        "stretch": tb.losses.Stretch(faces, rest, young=young, poisson=poisson, thickness=float(cfg["material"]["thickness"])),
        "bending": tb.losses.Bending(faces, rest, 1e-6),  # quadratic: see torchbend.losses.elastic
        "gravity": tb.losses.Gravity(faces, rest, 0.2),
        "inertia": tb.losses.Inertia(faces, rest, 0.2, float(lc["dt"])),
        "contact": tb.losses.BodyContact(stiffness=contact.stiffness, eps=contact.margin, law=contact.contact_law(),
                                         body_faces=body_faces),
    }
    if lc["normalize"]:  # joules -> O(1): divide by M g L of a mid-range density (torchbend.losses.cloth_loss)
        scale = tb.losses.energy_scale(faces, rest, sum(float(v) for v in cfg["sampling"]["density"]) / 2)
        weights = {k: w / scale for k, w in weights.items()}
    return tb.ClothLoss(terms, weights)


def parse_args(argv=None) -> argparse.Namespace:
    return cli.parse_args(tc.script_parser(__doc__, CONFIG, "runs/hood_style"), argv)


def overrides(a: argparse.Namespace) -> list[str]:
    """``--set`` overrides plus the script's own flags (``--steps``, ``--seed``)."""
    return tc.flag_overrides(a)


def main(argv=None, mesh: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict:
    """Train; ``mesh = (rest (V, 3), faces (F, 3))`` replaces the config's cloth (grid or ``mesh``
    section; placed as given, the body moves about the origin).  Returns ``{"losses", "terms",
    "start", "steps"}``."""
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
    sphere, body_faces = tb.scenes.icosphere(int(cfg["body"]["subdivisions"]), 1.0, dtype=dtype, device=device)
    loss_fn = build_loss(cfg, rest, faces, body_faces).to(device)
    dt = float(cfg["loss"]["dt"])
    m = cfg["model"]
    net = StepNet(len(rest), 9, int(m["hidden"]), int(m["layers"]), float(m["output_scale"])).to(dtype=dtype, device=device)
    opt = torch.optim.Adam(net.parameters(), lr=float(t["lr"]))
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")
    start = 0
    if a.resume:
        start = tc.resume_run(ckpt_path, cfg, log, (net, "model"), (opt, "optimizer"), map_location=device,
                           hint="the same config: another mesh passed to main?")
    gen = torch.Generator().manual_seed(int(t["seed"]) * 1000 + 7919 * start)
    writer = SummaryWriter(os.path.join(a.out, "tb"))
    batch, rollout, steps, log_every = int(t["batch"]), int(t["rollout"]), int(t["steps"]), int(t["log_every"])
    history: list[float] = []
    terms: dict[str, list[float]] = {}  # per evaluated term (weight != 0), unweighted [J]
    timer, lap = tc.Timer(), tc.Timer()
    seq = x = v = None
    frame, logged = 0, start
    for step in tqdm(range(start + 1, steps + 1), desc="train (hood-style)", disable=a.no_progress,
                     initial=start, total=steps):
        if seq is None or frame == rollout:  # new sequences: materials, bodies, cloth at rest
            seq = Sequences(cfg, batch, gen, dtype, device)
            x, v, frame = rest.expand(batch, -1, -1).clone(), torch.zeros(batch, *rest.shape, dtype=dtype, device=device), 0
        assert x is not None and v is not None
        frame += 1
        center = seq.center + (frame * dt) * seq.velocity  # the body at the predicted time
        body = center[:, None, :] + seq.radius[:, None, None] * sphere
        x_next = net(x, v, dt, center, seq.features())
        total, values = loss_fn(x_next, x_prev=x, v_prev=v, body=body, density=seq.density, young=seq.young,
                                poisson=seq.poisson, bending_stiffness=seq.bending_stiffness)
        opt.zero_grad(set_to_none=True)
        total.backward()
        nn.utils.clip_grad_norm_(net.parameters(), float(t["clip_grad"]))  # early rollouts can reach large losses
        opt.step()
        x_next = x_next.detach()
        x, v = x_next, (x_next - x) / dt
        history.append(float(total.detach()))
        for name, value in values.items():
            terms.setdefault(name, []).append(float(value))
        if step % log_every == 0 or step == steps:
            for name, value in values.items():
                writer.add_scalar(f"loss/{name}", float(value), step)
            writer.add_scalar("loss/total", history[-1], step)
            writer.add_scalar("time/seconds_per_step", lap.lap() / (step - logged), step)
            logged = step
        if step % int(t["checkpoint_every"]) == 0 or step == steps:
            tc.save_checkpoint(ckpt_path, step=step, model=net.state_dict(), optimizer=opt.state_dict(), config=cfg)
    writer.close()
    result = {"losses": history, "terms": terms, "start": start, "steps": steps}
    with open(os.path.join(a.out, "history.json"), "w") as f:
        json.dump(result, f)
    if history:
        log.info("loss %.4g at step %d -> %.4g at step %d (%s), %.3f s/step -> %s", history[0], start + 1, history[-1],
                 steps, ", ".join(f"{k} {vals[-1]:.3g} J" for k, vals in terms.items() if vals),
                 timer.total() / len(history), a.out)
    return result


if __name__ == "__main__":
    cli.run_main(main)
