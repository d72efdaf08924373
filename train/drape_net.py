"""Self-supervised drape network: scene conditions -> cloth vertex positions, physics as the loss.

    python train/drape_net.py                                                   # the quick start
    python train/drape_net.py --config configs/train_drape.yaml --loss residual # |grad E|^2 loss
    torchrun --nproc_per_node 2 train/drape_net.py --config configs/train_drape.yaml   # DDP (gloo on CPU)

A small MLP maps a sphere's position and radius to displacements of a square cloth whose middle
vertex is held at the top of the sphere; no ground truth.  ``--loss energy`` minimises the total
potential (membrane + bending + gravity + sphere and ground penalties) of the prediction; ``--loss
residual`` minimises the mass-weighted equilibrium residual ``sum_i |dE/dx_i|^2 / m_i``, whose
gradient needs Hessian-vector products: they run through torchbend's analytic double backward.
Logs every energy term, residual norms, mean ``|theta - theta_rest|``, the cap gap, seconds per step
and predicted meshes to TensorBoard; checkpoints with ``--resume``.

At the end, on held-out spheres: the cap gap (:func:`cap_gap`, how far the drapes rest from their
spheres) and, for three of them, Newton from the prediction (:meth:`SphereDrape.check`: how far the
prediction's energy lies above the equilibrium it settles into, and how far it moves); a PNG of those
three drapes with their colliders, ``history.json`` and one summary line on stdout.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import time
from typing import Annotated, Literal

import common as tc
import torch
from pydantic import Field, model_validator
from torch import nn

import torchbend as tb
from torchbend._extras import require
from torchbend.scenes import cli
from torchbend.scenes import config as sc

log = logging.getLogger("train.drape_net")
CONFIG = tc.config_file("train_drape.yaml")


class SceneSection(tc.Section):
    """``scene``: sphere centres uniform in ``[-center_range, center_range]^2`` [m], radii in
    ``[radius_min, radius_max]`` [m]; ``fixed_conditions``: one batch for the whole run.

    ``hold_center``: the cloth's middle vertex (the one nearest the centre of its rest bounding box)
    is held at the top of the sphere, and the flat rest cloth is moved there before the network's
    displacements are added.  Without it the drape is not a resting state: a frictionless sphere
    cannot hold a free cloth, whose potential is lowest once it has slid off onto the ground (Newton
    from a drape over the sphere ends there), so an energy-trained network drifts towards that."""

    center_range: tc.NonNegative = 0.1
    radius_min: tc.Positive = 0.2
    radius_max: tc.Positive = 0.3
    fixed_conditions: bool = False
    hold_center: bool = True

    @model_validator(mode="after")
    def _radii(self):
        if self.radius_max < self.radius_min:
            raise ValueError(f"radius_max ({self.radius_max}) must not be below radius_min ({self.radius_min})")
        return self


class TrainSection(tc.TrainBase):
    """``train``: optimisation (Adam), logging cadence, torch's intra-op CPU ``threads``.

    ``lr_schedule: cosine`` decays the learning rate from ``lr`` to ``lr * lr_final`` over the run
    (:func:`learning_rate`): large steps carry the cloth down the sphere, small ones settle it against
    the stiff contact and membrane terms (at a constant 1e-3 the default run stalled about 20% above
    the Newton equilibria in energy).  One thread suits these small tensors: two, on a shared 2-core
    machine, ran 10-20x slower per step (0: torch's default)."""

    steps: tc.PositiveInt = 1000
    lr: tc.Positive = 3e-3
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    lr_final: Annotated[tc.Float, Field(gt=0, le=1)] = 0.01  # cosine: the last step's lr relative to lr
    loss: Literal["energy", "residual"] = "energy"
    mesh_every: tc.PositiveInt = 100
    dtype: Literal["float32", "float64"] = "float64"
    threads: Annotated[tc.Int, Field(ge=0)] = 1


class EvalSection(tc.Section):
    """``eval``: checks at the end of a run, on held-out conditions drawn with ``seed`` (apart from
    training's): the cap gap (:func:`cap_gap`) of the predictions for ``conditions`` of them, and
    Newton from the predictions for the first ``newton`` (also drawn in ``drapes.png``), at most
    ``time_limit`` [s] each (:meth:`SphereDrape.check`)."""

    conditions: tc.Batch = 32
    newton: Annotated[tc.Int, Field(ge=0)] = 3
    time_limit: tc.Positive = 20.0
    seed: tc.Seed = 12345


class Config(sc.PhysicsConfig):
    """The drape network's config (``configs/train_drape.yaml``): the physics sections of a scene config
    (:class:`~torchbend.scenes.config.PhysicsConfig`; by default a 9 x 9 cloth of 0.8 m at a height of
    0.32 m, membrane, bending, gravity, the ground plane z = -0.4 m as a collider and the spheres under the
    ``contact`` law) and the script's own.  A file mesh (``mesh: garment.obj`` or ``{type: file, path:
    asset:skirt.obj, pin: {z_min: -0.001}}``) replaces the square cloth; its pinned vertices stay at their
    rest positions (the network predicts no displacement there: ``configs/train_skirt.yaml``)."""

    mesh: sc.MeshSection = sc.GridMesh(nx=9, size=(0.8, 0.8), offset=(-0.4, -0.4, 0.32))
    material: sc.MaterialSection = sc.MaterialSection(young=2e4, poisson=0.3, thickness=1e-3, density=0.2)
    bending: sc.BendingSection | None = sc.BendingSection(model="tan", stiffness=1e-4)
    membrane: sc.MembraneSection | None = sc.MembraneSection()
    colliders: list[sc.ColliderSpec] = [sc.PlaneSpec(type="plane", point=(0.0, 0.0, -0.4), stiffness=2e3, law="penalty")]
    contact: sc.ContactSection | None = sc.ContactSection(stiffness=2e3)
    scene: SceneSection = SceneSection()
    model: tc.ModelSection = tc.ModelSection()
    train: TrainSection = TrainSection()
    eval: EvalSection = EvalSection()


class DrapeNet(nn.Module):
    """MLP: condition (``inputs`` numbers, e.g. ``(cx, cy, r)``) -> vertex displacements ``(V, 3)``
    added to a base cloth; ``pinned`` (``(V,)`` bool, optional): vertices whose displacement is zero."""

    def __init__(self, vertex_count: int, hidden: int, layers: int, inputs: int = 3,
                 pinned: torch.Tensor | None = None):
        super().__init__()
        tc.check_network_size(inputs * hidden + (layers - 1) * hidden * (hidden + 1) + (hidden + 1) * 3 * vertex_count,
                           f"model.hidden ({hidden}), model.layers ({layers}) or the cloth ({vertex_count} vertices)")
        free = torch.ones(vertex_count, 1) if pinned is None else (~pinned.reshape(-1, 1).bool()).float()
        self.register_buffer("free", free, persistent=False)  # (V, 1): 0 at pinned vertices
        dims = [inputs] + [hidden] * layers
        mods = []
        for a, b in zip(dims[:-1], dims[1:], strict=True):
            mods += [nn.Linear(a, b), nn.Tanh()]
        mods.append(nn.Linear(hidden, 3 * vertex_count))
        nn.init.zeros_(mods[-1].weight)
        nn.init.zeros_(mods[-1].bias)
        self.net = nn.Sequential(*mods)
        self.vertex_count = vertex_count

    def forward(self, cond: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
        return rest + 0.1 * self.net(cond).reshape(-1, self.vertex_count, 3) * self.free


def sample_conditions(cfg, batch: int, gen: torch.Generator, dtype, device):
    """``batch`` sphere conditions: ``cond (B, 3)`` = ``(cx, cy, r)``, ``center (B, 3)`` [m] (z = 0),
    ``radius (B,)`` [m]."""
    s = cfg["scene"]
    c = (2 * torch.rand(batch, 2, generator=gen, dtype=torch.float64) - 1) * float(s["center_range"])
    r = float(s["radius_min"]) + torch.rand(batch, generator=gen, dtype=torch.float64) * (
        float(s["radius_max"]) - float(s["radius_min"]))
    cond = torch.cat((c, r[:, None]), 1).to(dtype=dtype, device=device)
    center = torch.cat((c, torch.zeros(batch, 1, dtype=torch.float64)), 1).to(dtype=dtype, device=device)
    return cond, center, r.to(dtype=dtype, device=device)


def mean_edge_length(rest: torch.Tensor, faces: torch.Tensor) -> float:
    """Mean length [m] of the distinct edges of the mesh ``rest (V, 3)``, ``faces (F, 3)``."""
    e = tb.mesh.HingeTopology.from_faces(faces, len(rest)).edges.to(rest.device)
    return float((rest[e[:, 1]] - rest[e[:, 0]]).norm(dim=-1).mean())


CAP = math.sqrt(0.5)
"""Horizontal distance from the sphere's vertical axis, relative to its radius, below which a vertex
lies over the cap measured by :func:`cap_gap` (the cap above 45 degrees latitude)."""


def cap_gap(x: torch.Tensor, center: torch.Tensor, radius: torch.Tensor, free: torch.Tensor | None = None) -> torch.Tensor:
    """How far a drape rests from its sphere: per sample ``(B,)`` [m], the mean of ``| |x_i - c| - r |``
    over the vertices ``i`` over the sphere's cap: above its centre and closer to its vertical axis than
    ``CAP * r`` (``CAP`` = 1/sqrt(2): the cap above 45 degrees latitude, where a cloth draped from the top
    lies on the sphere).  ``x (B, V, 3)``, ``center (B, 3)``, ``radius (B,)``; ``free (V,)`` bool keeps
    only those vertices (e.g. leaves out a held one).  NaN for a sample with no vertex over its cap."""
    p = x - center[:, None, :]
    over = (p[..., :2].norm(dim=-1) < CAP * radius[:, None]) & (p[..., 2] > 0)
    if free is not None:
        over = over & free
    d = (p.norm(dim=-1) - radius[:, None]).abs()
    return (d * over).sum(-1) / over.sum(-1)


def turned_onto(q: torch.Tensor, p: torch.Tensor, pivot: torch.Tensor) -> torch.Tensor:
    """``q (V, 3)`` turned about the vertical through ``pivot (3,)`` by the angle that brings it
    closest to ``p (V, 3)`` (least squares; closed form ``atan2(sum q x p . z, sum q . p)`` in xy)."""
    a, b = q[:, :2] - pivot[:2], p[:, :2] - pivot[:2]
    angle = torch.atan2((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum(), (a * b).sum())
    c, s = torch.cos(angle), torch.sin(angle)
    xy = torch.stack((c * a[:, 0] - s * a[:, 1], s * a[:, 0] + c * a[:, 1]), -1) + pivot[:2]
    return torch.cat((xy, q[:, 2:]), -1)


class SphereDrape:
    """The cloth of ``physics`` over per-sample spheres: where predictions start, the held vertex, and
    the same potential as a :class:`torchbend.ClothModel` for reference (Newton) solves."""

    def __init__(self, cfg: dict, physics: tc.ClothPhysics):
        self.physics = physics
        rest = physics.rest
        self.hold = bool(cfg["scene"]["hold_center"])
        middle = (rest.amin(0) + rest.amax(0)) / 2
        self.held = int((rest - middle).norm(dim=-1).argmin())
        self.free = torch.ones(len(rest), dtype=torch.bool, device=rest.device)
        if self.hold:
            self.free[self.held] = False
        self.edge_length = mean_edge_length(rest, physics.faces)

    def top(self, center: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
        """The tops of the spheres ``(B, 3)`` [m]."""
        return center + radius[:, None] * torch.tensor([0.0, 0.0, 1.0], dtype=center.dtype, device=center.device)

    def base(self, center: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
        """Where predictions start, ``(B, V, 3)`` [m]: the rest cloth, moved so its held vertex is at
        the top of the sphere (``hold_center``), or as it is."""
        rest = self.physics.rest
        if not self.hold:
            return rest.expand(len(center), -1, -1)
        return rest + (self.top(center, radius) - rest[self.held])[:, None, :]

    def predict(self, net, cond: torch.Tensor, center: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
        """The drapes ``(B, V, 3)`` [m]: the network's displacements added to :meth:`base`, the held
        vertex at the top of the sphere."""
        x = net(cond, self.base(center, radius))
        if self.hold:
            index = torch.tensor([self.held], device=x.device)
            x = x.index_copy(-2, index, self.top(center, radius)[:, None, :])
        return x

    def model(self, center, radius: float) -> tb.ClothModel:
        """The potential of one sample as a solver model (``center`` 3 numbers [m], ``radius`` [m]),
        term for term that of :class:`ClothPhysics`, with the held vertex pinned."""
        pinned = ~self.free if self.physics.pinned is None else (~self.free | self.physics.pinned)
        return self.physics.model(center, radius, pinned=pinned)

    def residual(self, x: torch.Tensor, center: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
        """Mass-weighted squared equilibrium residual of the free vertices per sample,
        ``sum_i |dE/dx_i|^2 / m_i`` ``(B,)`` [N^2/kg] (differentiable: its gradient runs the analytic HVP)."""
        g = self.physics.gradient(x, center, radius)
        return (g * g / self.physics.mass[:, None] * self.free[:, None]).sum((-1, -2))

    def check(self, x: torch.Tensor, center: torch.Tensor, radius: torch.Tensor, time_limit: float = 30.0) -> list[dict]:
        """Each prediction ``x (B, V, 3)`` against the Newton equilibrium started from it
        (:func:`torchbend.solve_static`, exact Hessian, at most ``time_limit`` [s] each): ``energy_gap``
        [J] (prediction minus equilibrium: >= 0 when the solve converged to the minimum it slid into),
        ``rms_distance`` [m] (with ``hold_center``, after turning the equilibrium about the vertical
        through the held vertex to fit the prediction: that turn costs no energy), ``relative_residual`` (``|dE/dx|`` of the free vertices at the prediction
        over the weight of the cloth: 0 at an equilibrium; the stiff contact penalty dominates it: with
        the default 2e3 N/m a vertex 0.5 mm inside the sphere pushes back with about the cloth's weight), the
        equilibrium's ``cap_gap`` [m] and the solve's ``converged``, ``iterations``, ``seconds``."""
        out = []
        for xi, ci, ri in zip(x.detach(), center, radius, strict=True):
            m = self.model(ci.tolist(), float(ri))
            g = m.gradient(xi)[self.free]
            weight = float(m.external_force(xi.dtype).sum(0).norm())
            x_eq, info = tb.solve_static(m, xi, time_limit=time_limit)
            e_pred = m.potential(xi)
            if self.hold:  # the turn about the vertical through the held vertex costs no energy: not a miss
                x_eq = turned_onto(x_eq, xi, xi[self.held])
            out.append({"energy_gap": e_pred - m.potential(x_eq), "energy_prediction": e_pred,
                        "rms_distance": float((xi - x_eq).norm(dim=-1).pow(2).mean().sqrt()),
                        "relative_residual": float(g.norm()) / weight if weight > 0 else math.nan,
                        "cap_gap_equilibrium": float(cap_gap(x_eq[None], ci[None], ri[None], self.free)[0]),
                        "converged": bool(info.converged), "iterations": info.iterations, "seconds": info.seconds})
        return out


def init_weights(path: str, cfg: dict, model: nn.Module, device) -> None:
    """``--init``: the network weights (``model``) of the checkpoint at ``path`` loaded into ``model``;
    :class:`ConfigError` naming the path when it holds none or they do not fit."""
    ck = tc.load_checkpoint(path, map_location=device)
    if not isinstance(ck.get("model"), dict):
        raise sc.ConfigError(f"--init: {path} holds no network weights ('model')")
    changed = cli.changed_keys(ck["config"], cfg) if isinstance(ck.get("config"), dict) else []
    cli.restore(path, changed, (model, ck["model"]), flag="--init")


def learning_rate(t: dict, step: int) -> float:
    """The learning rate of step ``step`` (1-based) of the ``train`` section ``t``: ``lr`` throughout
    (``constant``) or a cosine from ``lr`` at the first step to ``lr * lr_final`` at the last."""
    lr = float(t["lr"])
    if t["lr_schedule"] == "constant":
        return lr
    f = float(t["lr_final"])
    u = min(max(step - 1, 0) / max(int(t["steps"]) - 1, 1), 1.0)
    return lr * (f + (1 - f) * 0.5 * (1 + math.cos(math.pi * u)))


def loss_fn(kind: str, scene: SphereDrape, x, center, radius):
    physics = scene.physics
    if kind == "energy":
        terms = physics.energies(x, center, radius)
        return tc.total(terms).mean(), terms
    if kind == "residual":
        return scene.residual(x, center, radius).mean(), None
    raise ValueError(f"config key 'train.loss' must be 'energy' or 'residual', got {kind!r}")


def parse_args(argv=None):
    p = tc.script_parser(__doc__, CONFIG, "runs/drape_net")
    p.add_argument("--loss", choices=["energy", "residual"], help="override train.loss")
    p.add_argument("--lr", type=cli.positive_float, help="override train.lr")
    p.add_argument("--init", help="start from the network weights of this checkpoint (fresh optimizer, step 0), "
                   "e.g. residual fine-tuning of an energy-trained network")
    return cli.parse_args(p, argv)


def overrides(a: argparse.Namespace) -> list[str]:
    """``--set`` overrides plus the script's own flags (``--loss``, ``--steps``, ``--seed``, ``--lr``)."""
    return tc.flag_overrides(a, loss=a.loss, lr=a.lr)


def log_step(writer, scene: SphereDrape, step: int, x, center, radius, loss: float, seconds: float) -> None:
    """TensorBoard scalars of one step: every energy term, residual norms, mean |theta - theta_rest|,
    the cap gap."""
    physics = scene.physics
    with torch.no_grad():
        terms = physics.energies(x.detach(), center, radius)
    for k, v in terms.items():
        writer.add_scalar(f"energy/{k}", float(v.mean()), step)
    writer.add_scalar("energy/total", float(tc.total(terms).mean()), step)
    xg = x.detach().requires_grad_()
    writer.add_scalar("residual/mass_weighted_sq", float(scene.residual(xg, center, radius).detach().mean()), step)
    g = physics.gradient(xg, center, radius).detach() * scene.free[:, None]
    writer.add_scalar("residual/norm", float(g.norm(dim=(-1, -2)).mean()), step)
    writer.add_scalar("bending/mean_abs_theta_minus_rest", physics.mean_angle_deviation(x), step)
    if "sphere" in physics.terms:
        gap = cap_gap(x.detach(), center, radius, scene.free)
        if not bool(gap.isnan().all()):  # no vertex over any cap (a garment around its body): nothing to log
            writer.add_scalar("contact/cap_gap", float(gap.nanmean()), step)
    writer.add_scalar("loss", loss, step)
    writer.add_scalar("time/seconds_per_step", seconds, step)


def drawn_colliders(physics: tc.ClothPhysics, center, radius: float) -> list:
    """The colliders of one sample for the PNG: its sphere (when the physics has one) and the config's colliders."""
    out = list(physics.solver_model.colliders)
    if "sphere" in physics.terms:
        out.append(tb.Sphere(tuple(center), float(radius)))
    return out


def evaluate(cfg: dict, net: nn.Module, scene: SphereDrape, dtype, device) -> tuple[dict, list]:
    """Held-out conditions (``eval.seed``, apart from training's): the cap gap of the predictions for
    ``eval.conditions`` of them [m], and :meth:`SphereDrape.check` of the first ``eval.newton`` (on the
    CPU in float64).  Returns the summary numbers and the
    first three conditions' ``(x, center, radius, cond)`` to draw."""
    e = cfg["eval"]
    n = max(int(e["conditions"]), 3)
    with torch.no_grad():
        cond, center, radius = sample_conditions(cfg, n, torch.Generator().manual_seed(int(e["seed"])), dtype, device)
        x = scene.predict(net, cond, center, radius)
    out: dict = {"edge_length": scene.edge_length, "conditions": n}
    if "sphere" in scene.physics.terms:
        gap = cap_gap(x, center, radius, scene.free)
        out["cap_gap"] = float(gap.nanmean()) if not gap.isnan().all() else None  # None: no vertex over a cap
    k = min(int(e["newton"]), n)
    if k:
        level = logging.getLogger("torchbend.sim").level
        logging.getLogger("torchbend.sim").setLevel(max(level, logging.WARNING))  # no per-iteration INFO lines
        ref = scene
        if scene.physics.rest.dtype != torch.float64 or scene.physics.rest.device.type != "cpu":
            ref = SphereDrape(cfg, tc.ClothPhysics(scene.physics.cfg, dtype=torch.float64, device="cpu"))
        try:
            checks = ref.check(*(v[:k].detach().cpu().double() for v in (x, center, radius)), time_limit=float(e["time_limit"]))
        finally:
            logging.getLogger("torchbend.sim").setLevel(level)
        out["newton"] = checks
        out.update(_newton_summary(checks))
    return out, [x[:3], center[:3], radius[:3], cond[:3]]


def _newton_summary(checks: list[dict]) -> dict:
    """Means of the Newton checks over the solves that converged (an unconverged solve's best iterate is no
    equilibrium: its distance and energy say nothing of the prediction); None where none converged."""
    done = [c for c in checks if c["converged"]]
    n = len(done)

    def mean(f):
        return sum(f(c) for c in done) / n if n else None

    return {"newton_converged": n,
            "energy_gap": mean(lambda c: c["energy_gap"]),
            "relative_energy_gap": mean(lambda c: c["energy_gap"] / abs(c["energy_prediction"] - c["energy_gap"])),
            "rms_distance": mean(lambda c: c["rms_distance"]),
            "relative_residual": sum(c["relative_residual"] for c in checks) / len(checks)}


def summary_line(result: dict, out: str) -> str:
    """The one line printed at the end of a run (stdout)."""
    s = result["summary"]
    unit = {"energy": "J", "residual": "N^2/kg"}[result["loss_kind"]]
    parts = [f"drape_net: {result['loss_kind']} loss {s['final_loss']:.4g} {unit} (mean of the last {s['final_window']} steps)"]
    if s.get("cap_gap") is not None:
        parts.append(f"cap gap {1e3 * s['cap_gap']:.2g} mm = {s['cap_gap'] / s['edge_length']:.2g} edge lengths "
                     f"({s['conditions']} held-out spheres)")
    if "newton" in s:
        k = len(s["newton"])
        if s["newton_converged"]:
            parts.append(f"vs Newton from {k} predictions ({s['newton_converged']}/{k} converged; means over those): "
                         f"energy +{1e3 * s['energy_gap']:.2g} mJ ({100 * s['relative_energy_gap']:.2g}%), RMS "
                         f"{1e3 * s['rms_distance']:.2g} mm")
        else:
            parts.append(f"vs Newton from {k} predictions: not converged from any (no equilibrium to compare with)")
    parts.append(f"{s['train_seconds']:.0f} s training ({s['steps_run']} steps) + {s['eval_seconds']:.0f} s checks")
    parts.append(f"-> {os.path.join(out, 'drapes.png')}, checkpoint.pt, TensorBoard: tensorboard --logdir {os.path.join(out, 'tb')}")
    return " | ".join(parts)


def save_outputs(out: str, physics: tc.ClothPhysics, result: dict, drawn: list) -> None:
    """Rank 0 at the end: ``drapes.png`` (three held-out drapes with their colliders, from above and
    from the side) and ``history.json``."""
    from torchbend.scenes.plot import snapshot

    x, center, radius, cond = drawn
    panels = [([(xi, physics.faces)], drawn_colliders(physics, c, r))
              for xi, c, r in zip(x, center.tolist(), radius.tolist(), strict=True)]
    snapshot(os.path.join(out, "drapes.png"), panels, titles=[f"sphere ({c[0]:+.2f}, {c[1]:+.2f}), r={c[2]:.2f}"
                                                              for c in cond.tolist()],
             size=4.0, dpi=80, views=(None, (5.0, -60.0)), alpha=0.6)
    with open(os.path.join(out, "history.json"), "w") as f:
        json.dump(result, f)


@contextlib.contextmanager
def intra_op_threads(threads: int):
    """Run the block with ``threads`` intra-op CPU threads in torch (0: leave them), restored after."""
    previous = torch.get_num_threads()
    if threads > 0:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def main(argv=None) -> dict:
    a = parse_args(argv)
    device = cli.resolve_device(a.device)
    config = tc.read_config(a.config, Config, overrides(a))
    with intra_op_threads(config.train.threads):
        return train(a, config, device)


def _check_pins(physics: tc.ClothPhysics, loss: str) -> torch.Tensor | None:
    """The mesh's pins; the residual loss refuses them (it would hold the pins' reaction forces)."""
    if physics.pinned is not None and loss == "residual":
        raise sc.ConfigError("config key 'train.loss': 'residual' does not support a pinned mesh ('mesh.pin'); "
                          "use 'energy'")
    return physics.pinned


def train(a: argparse.Namespace, config: Config, device: torch.device) -> dict:
    """The run of :func:`main` (parsed options ``a``, the validated ``config``; its plain-dict form is the
    checkpoint's record)."""
    SummaryWriter = require("torch.utils.tensorboard", "TensorBoard logs").SummaryWriter
    from tqdm import tqdm

    cfg = config.model_dump(mode="json")
    t = cfg["train"]
    rank, world = tc.distributed()
    dtype = getattr(torch, t["dtype"])
    tc.seed_everything(int(t["seed"]))
    physics = tc.ClothPhysics(config, dtype=dtype, device=device)
    pinned = _check_pins(physics, t["loss"])
    scene = SphereDrape(cfg, physics)
    model = DrapeNet(len(physics.rest), int(cfg["model"]["hidden"]), int(cfg["model"]["layers"]),
                     pinned=pinned).to(dtype=dtype, device=device)
    net = nn.parallel.DistributedDataParallel(model) if world > 1 else model  # `model` holds the weights
    opt = torch.optim.Adam(net.parameters(), lr=float(t["lr"]))
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")
    start = 0
    if a.init:
        init_weights(a.init, cfg, model, device)
    if a.resume:
        start = tc.resume_run(ckpt_path, cfg, log, (model, "model"), (opt, "optimizer"), map_location=device)
    gen = torch.Generator().manual_seed(int(t["seed"]) * 1000 + rank + 7919 * start)
    writer = SummaryWriter(os.path.join(a.out, "tb")) if rank == 0 else None
    history = []
    timer = tc.Timer()
    steps = int(t["steps"])
    cond, center, radius = sample_conditions(cfg, int(t["batch"]), gen, dtype, device)
    for step in tqdm(range(start + 1, steps + 1), desc=f"train ({t['loss']})", disable=a.no_progress or rank != 0,
                     initial=start, total=steps):
        if step > start + 1 and not cfg["scene"]["fixed_conditions"]:
            cond, center, radius = sample_conditions(cfg, int(t["batch"]), gen, dtype, device)
        for group in opt.param_groups:
            group["lr"] = learning_rate(t, step)
        x = scene.predict(net, cond, center, radius)
        loss, _ = loss_fn(t["loss"], scene, x, center, radius)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        seconds = timer.lap()
        history.append(float(loss.detach()))
        if writer is not None and (step % int(t["log_every"]) == 0 or step == steps):
            log_step(writer, scene, step, x, center, radius, history[-1], seconds)
        if writer is not None and step % int(t["mesh_every"]) == 0:
            writer.add_mesh("prediction", vertices=x.detach()[:1].float(), faces=physics.faces[None].int(), global_step=step)
        if rank == 0 and (step % int(t["checkpoint_every"]) == 0 or step == steps):
            tc.save_checkpoint(ckpt_path, step=step, model=model.state_dict(), optimizer=opt.state_dict(), config=cfg)
    train_seconds = timer.total()
    result: dict = {"losses": history, "start": start, "steps": steps, "loss_kind": t["loss"]}
    if writer is not None:
        t0 = time.perf_counter()
        summary, drawn = evaluate(cfg, model, scene, dtype, device)
        window = min(10, len(history))
        summary.update(final_loss=sum(history[-window:]) / window if window else math.nan, final_window=window,
                       train_seconds=train_seconds, steps_run=len(history), eval_seconds=time.perf_counter() - t0)
        result["summary"] = summary
        save_outputs(a.out, physics, result, drawn)
        writer.close()
    # every rank writes its parameters (the DDP test checks they stay identical)
    flat = torch.cat([p.detach().reshape(-1) for p in model.parameters()])
    torch.save(flat, os.path.join(a.out, f"params_rank{rank}.pt"))
    if world > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()
    if rank == 0 and history:
        log.info("%s loss: %.6g at step %d -> %.6g at step %d, %.3f s/step -> %s", t["loss"], history[0], start + 1,
                 history[-1], steps, train_seconds / len(history), a.out)
        print(summary_line(result, a.out), flush=True)
    return result


if __name__ == "__main__":
    cli.run_main(main)
