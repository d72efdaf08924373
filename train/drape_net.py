"""Self-supervised drape network: scene conditions -> cloth vertex positions, physics as the loss.

    python train/drape_net.py --config configs/train_drape.yaml                 # energy loss
    python train/drape_net.py --config configs/train_drape.yaml --loss residual # |grad E|^2 loss
    torchrun --nproc_per_node 2 train/drape_net.py --config configs/train_drape.yaml   # DDP (gloo on CPU)

A small MLP maps a sphere's position and radius to displacements of a square cloth; no ground
truth.  ``--loss energy`` minimises the total potential (membrane + bending + gravity + sphere and
ground penalties) of the prediction; ``--loss residual`` minimises the mass-weighted equilibrium
residual ``sum_i |dE/dx_i|^2 / m_i``, whose gradient needs Hessian-vector products: they run through
torchbend's analytic double backward.  Logs every energy term, residual norms, mean
``|theta - theta_rest|``, seconds per step and predicted meshes to TensorBoard; checkpoints with
``--resume``; a PNG of predicted drapes at the end.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
from typing import Literal

import torch
from common import (
    ClothPhysics,
    ClothSection,
    Float,
    Int,
    ModelSection,
    NonNegative,
    Positive,
    PositiveInt,
    Section,
    Timer,
    distributed,
    load_checkpoint,
    load_config,
    save_checkpoint,
    save_drape_png,
    seed_everything,
    total,
)
from pydantic import model_validator
from torch import nn

import torchbend as tb
from torchbend.scenes import cli
from torchbend.scenes.config import ConfigError, MeshField, build_mesh, build_pins

log = logging.getLogger("train.drape_net")
CONFIG = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "configs", "train_drape.yaml"))


class DrapeCloth(ClothSection):
    height: Float = 0.32  # initial height of the flat cloth [m]


class SceneSection(Section):
    """``scene``: sphere centres uniform in ``[-center_range, center_range]^2`` [m], radii in
    ``[radius_min, radius_max]`` [m]; ``fixed_conditions``: one batch for the whole run."""

    center_range: NonNegative = 0.1
    radius_min: Positive = 0.2
    radius_max: Positive = 0.3
    fixed_conditions: bool = False

    @model_validator(mode="after")
    def _radii(self):
        if self.radius_max < self.radius_min:
            raise ValueError(f"radius_max ({self.radius_max}) must not be below radius_min ({self.radius_min})")
        return self


class TrainSection(Section):
    """``train``: optimisation (Adam) and logging cadence."""

    steps: PositiveInt = 300
    batch: PositiveInt = 16
    lr: Positive = 1e-3
    loss: Literal["energy", "residual"] = "energy"
    log_every: PositiveInt = 10
    mesh_every: PositiveInt = 100
    checkpoint_every: PositiveInt = 50
    seed: Int = 0
    dtype: Literal["float32", "float64"] = "float64"


class Config(Section):
    """The drape network's config (``configs/train_drape.yaml``); ``mesh`` (optional, a scene-config
    mesh section such as ``mesh: garment.obj`` or ``{type: file, path: asset:skirt.obj, pin: {z_min:
    -0.001}}``) replaces the square cloth of ``cloth``; its pinned vertices stay at their rest positions
    (the network predicts no displacement there: ``configs/train_skirt.yaml``)."""

    cloth: DrapeCloth = DrapeCloth()
    mesh: MeshField = None
    scene: SceneSection = SceneSection()
    model: ModelSection = ModelSection()
    train: TrainSection = TrainSection()


class DrapeNet(nn.Module):
    """MLP: condition (``inputs`` numbers, e.g. ``(cx, cy, r)``) -> vertex displacements ``(V, 3)``
    added to a base cloth; ``pinned`` (``(V,)`` bool, optional): vertices whose displacement is zero."""

    def __init__(self, vertex_count: int, hidden: int, layers: int, inputs: int = 3,
                 pinned: torch.Tensor | None = None):
        super().__init__()
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
    s = cfg["scene"]
    c = (2 * torch.rand(batch, 2, generator=gen, dtype=torch.float64) - 1) * float(s["center_range"])
    r = float(s["radius_min"]) + torch.rand(batch, generator=gen, dtype=torch.float64) * (
        float(s["radius_max"]) - float(s["radius_min"]))
    cond = torch.cat((c, r[:, None]), 1).to(dtype=dtype, device=device)
    center = torch.cat((c, torch.zeros(batch, 1, dtype=torch.float64)), 1).to(dtype=dtype, device=device)
    return cond, center, r.to(dtype=dtype, device=device)


def loss_fn(kind: str, physics: ClothPhysics, x, center, radius):
    if kind == "energy":
        terms = physics.energies(x, center, radius)
        return total(terms).mean(), terms
    if kind == "residual":
        res = physics.residual(x, center, radius)
        return res.mean(), None
    raise ValueError(f"config key 'train.loss' must be 'energy' or 'residual', got {kind!r}")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    cli.add_common_args(p, config=CONFIG, out="runs/drape_net")
    p.add_argument("--loss", choices=["energy", "residual"], help="override train.loss")
    p.add_argument("--steps", type=int, help="override train.steps")
    p.add_argument("--lr", type=float, help="override train.lr")
    p.add_argument("--init", help="start from the network weights of this checkpoint (fresh optimizer, step 0), "
                   "e.g. residual fine-tuning of an energy-trained network")
    return cli.parse_args(p, argv)


def overrides(a: argparse.Namespace) -> list[str]:
    """``--set`` overrides plus the script's own flags (``--loss``, ``--steps``, ``--seed``, ``--lr``)."""
    flags = {"loss": a.loss, "steps": a.steps, "seed": a.seed, "lr": a.lr}
    return list(a.overrides) + [f"train.{k}={v}" for k, v in flags.items() if v is not None]


def log_step(writer, physics: ClothPhysics, step: int, x, center, radius, loss: float, seconds: float) -> None:
    """TensorBoard scalars of one step: every energy term, residual norms, mean |theta - theta_rest|."""
    with torch.no_grad():
        terms = physics.energies(x.detach(), center, radius)
    for k, v in terms.items():
        writer.add_scalar(f"energy/{k}", float(v.mean()), step)
    writer.add_scalar("energy/total", float(total(terms).mean()), step)
    xg = x.detach().requires_grad_()
    res = physics.residual(xg, center, radius).detach()
    writer.add_scalar("residual/mass_weighted_sq", float(res.mean()), step)
    writer.add_scalar("residual/norm", float(physics.gradient(xg, center, radius).detach().norm(dim=(-1, -2)).mean()), step)
    writer.add_scalar("bending/mean_abs_theta_minus_rest", physics.mean_angle_deviation(x), step)
    writer.add_scalar("loss", loss, step)
    writer.add_scalar("time/seconds_per_step", seconds, step)


def drawn_colliders(physics: ClothPhysics, center, radius: float) -> list:
    """The colliders of one sample for the PNG: its sphere and the ground plane (when in the energy)."""
    out = []
    if "sphere" in physics.terms:
        out.append(tb.Sphere(tuple(center), float(radius)))
    if "ground" in physics.terms:
        out.append(tb.Plane(point=(0.0, 0.0, physics.ground_z)))
    return out


def save_outputs(out: str, cfg: dict, net: DrapeNet, physics: ClothPhysics, result: dict, dtype, device) -> None:
    """Rank 0 at the end: a PNG of three predicted drapes (colliders drawn) and ``history.json``."""
    with torch.no_grad():
        cond, center, radius = sample_conditions(cfg, 3, torch.Generator().manual_seed(12345), dtype, device)
        x = net(cond, physics.rest)
    save_drape_png(os.path.join(out, "drapes.png"), [(xi, physics.faces) for xi in x],
                   [f"sphere ({c[0]:+.2f}, {c[1]:+.2f}), r={c[2]:.2f}" for c in cond.tolist()],
                   colliders=[drawn_colliders(physics, c, r) for c, r in zip(center.tolist(), radius.tolist())])
    with open(os.path.join(out, "history.json"), "w") as f:
        json.dump(result, f)


def main(argv=None) -> dict:
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    a = parse_args(argv)
    device = cli.resolve_device(a.device)
    cfg = load_config(a.config, Config, overrides(a))
    t = cfg["train"]
    rank, world = distributed()
    dtype = getattr(torch, t["dtype"])
    seed_everything(int(t["seed"]))
    mesh = pinned = None
    if cfg["mesh"] is not None:
        mesh = build_mesh(cfg["mesh"], dtype=dtype, device=device)
        pinned = build_pins(cfg["mesh"], mesh[0])
        if pinned is not None and t["loss"] == "residual":  # the residual would hold the pins' reaction forces
            raise ConfigError("config key 'train.loss': 'residual' does not support a pinned mesh ('mesh.pin'); "
                              "use 'energy'")
    physics = ClothPhysics(cfg, dtype=dtype, device=device, mesh=mesh)
    model = DrapeNet(len(physics.rest), int(cfg["model"]["hidden"]), int(cfg["model"]["layers"]),
                     pinned=pinned).to(dtype=dtype, device=device)
    net = nn.parallel.DistributedDataParallel(model) if world > 1 else model  # `model` holds the weights
    opt = torch.optim.Adam(net.parameters(), lr=float(t["lr"]))
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")
    start = 0
    if a.init:
        model.load_state_dict(load_checkpoint(a.init, map_location=device)["model"])
    if a.resume:
        ck = load_checkpoint(ckpt_path, map_location=device)
        changed = cli.changed_keys(ck.get("config"), cfg, ignore=("train.steps",))
        if changed:
            log.warning("--resume: the config differs from the checkpoint's at %s", ", ".join(changed))
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start = int(ck["step"])
        log.info("resumed at step %d from %s", start, ckpt_path)
    gen = torch.Generator().manual_seed(int(t["seed"]) * 1000 + rank + 7919 * start)
    writer = SummaryWriter(os.path.join(a.out, "tb")) if rank == 0 else None
    history = []
    timer = Timer()
    steps = int(t["steps"])
    cond, center, radius = sample_conditions(cfg, int(t["batch"]), gen, dtype, device)
    for step in tqdm(range(start + 1, steps + 1), desc=f"train ({t['loss']})", disable=a.no_progress or rank != 0,
                     initial=start, total=steps):
        if step > start + 1 and not cfg["scene"]["fixed_conditions"]:
            cond, center, radius = sample_conditions(cfg, int(t["batch"]), gen, dtype, device)
        x = net(cond, physics.rest)
        loss, _ = loss_fn(t["loss"], physics, x, center, radius)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        seconds = timer.lap()
        history.append(float(loss.detach()))
        if writer is not None and (step % int(t["log_every"]) == 0 or step == steps):
            log_step(writer, physics, step, x, center, radius, history[-1], seconds)
        if writer is not None and step % int(t["mesh_every"]) == 0:
            writer.add_mesh("prediction", vertices=x.detach()[:1].float(), faces=physics.faces[None].int(), global_step=step)
        if rank == 0 and (step % int(t["checkpoint_every"]) == 0 or step == steps):
            save_checkpoint(ckpt_path, step=step, model=model.state_dict(), optimizer=opt.state_dict(), config=cfg)
    result = {"losses": history, "start": start, "steps": steps}
    if writer is not None:
        save_outputs(a.out, cfg, model, physics, result, dtype, device)
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
                 history[-1], steps, timer.total() / len(history), a.out)
    return result


if __name__ == "__main__":
    cli.run_main(main)
