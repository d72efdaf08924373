"""HOOD-style self-supervised cloth dynamics: a network steps the cloth in time, physics is the loss.

    python train/hood_style.py                                   # script defaults
    python train/hood_style.py --config configs/train_hood.yaml --steps 2000 --device cuda

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

The network is a plain MLP on the flattened state (no graph network, so it is tied to one mesh; the
mesh is pluggable: ``main(argv, mesh=(rest, faces))``, default a square grid).  TensorBoard logs
every loss term (``loss/<name>``, unweighted, joules), the total and seconds per step; checkpoints
with ``--resume`` (a resumed run starts new sequences).
"""
from __future__ import annotations

import argparse
import json
import math
import os

import torch
from common import Timer, check_positive, load_checkpoint, load_config, save_checkpoint, seed_everything
from torch import nn

import torchbend as tb

TERMS = ("stretch", "bending", "gravity", "inertia", "contact")

DEFAULTS = {
    "cloth": {"resolution": 9, "size": 0.8, "height": 0.32, "thickness": 4.7e-4},
    # HOOD's coefficients, sampled per sequence: log-uniform in [lo, hi] (density: uniform);
    # lame_lambda = ratio * lame_mu with the ratio uniform in lame_lambda_ratio (Poisson ratio (-1, 0.5) needs < 2)
    "material": {"lame_mu": [1.5e4, 6.0e4], "lame_lambda_ratio": [0.2, 1.8], "bending_coeff": [1.0e-6, 1.0e-4],
                 "density": [0.1, 0.4]},
    "body": {"subdivisions": 2, "radius": [0.15, 0.25], "offset": 0.1, "speed": 0.2},
    "loss": {"dt": 1.0 / 30.0, "contact_stiffness": 1.0e4, "contact_eps": 4.0e-3, "normalize": True,
             "weights": {name: 1.0 for name in TERMS}},
    "model": {"hidden": 256, "layers": 3, "output_scale": 10.0},  # output_scale: acceleration [m/s^2]
    "train": {"steps": 500, "batch": 8, "rollout": 20, "lr": 1.0e-4, "clip_grad": 1.0, "log_every": 10, "checkpoint_every": 100,
              "seed": 0, "dtype": "float32"},
}


def grid_cloth(cfg: dict, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The default cloth: a flat square grid centred above the origin (the body's mean position)."""
    c = cfg["cloth"]
    n = int(c["resolution"])
    if n < 3:
        raise ValueError(f"config key 'cloth.resolution' must be >= 3, got {n}")
    size = check_positive(cfg, "cloth.size")
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=dtype)
    return rest - torch.tensor([size / 2, size / 2, -float(c["height"])], dtype=dtype), faces


def _range(cfg: dict, key: str, positive: bool = True) -> tuple[float, float]:
    section, name = key.split(".")
    v = cfg[section][name]
    try:
        lo, hi = (float(t) for t in v)
    except (TypeError, ValueError):
        raise ValueError(f"config key '{key}' must be a pair [lo, hi], got {v!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi and (lo > 0 or not positive)):
        raise ValueError(f"config key '{key}' must be finite with {'0 < ' if positive else ''}lo <= hi, got {v!r}")
    return lo, hi


class Sequences:
    """Per-sequence conditions of a batch: HOOD materials (and ours), body radius, start and velocity."""

    def __init__(self, cfg: dict, batch: int, gen: torch.Generator, dtype, device):
        m, b = cfg["material"], cfg["body"]

        def uniform(lo, hi, log=False):
            u = torch.rand(batch, generator=gen, dtype=torch.float64)
            out = math.log(lo) + u * (math.log(hi) - math.log(lo)) if log else lo + u * (hi - lo)
            return (out.exp() if log else out).to(dtype=dtype, device=device)

        lo, hi = _range(cfg, "material.lame_lambda_ratio", positive=False)
        if not (-1 < lo and hi < 2):
            raise ValueError(f"config key 'material.lame_lambda_ratio' must lie in (-1, 2), got {m['lame_lambda_ratio']!r}")
        self.lame_mu = uniform(*_range(cfg, "material.lame_mu"), log=True)
        self.lame_lambda = self.lame_mu * uniform(lo, hi)
        self.bending_coeff = uniform(*_range(cfg, "material.bending_coeff"), log=True)
        self.density = uniform(*_range(cfg, "material.density"))
        self.young, self.poisson = tb.material_from_lame(self.lame_mu, self.lame_lambda)
        self.bending_stiffness = tb.bending_stiffness_from_hood(self.bending_coeff)
        self.radius = uniform(*_range(cfg, "body.radius"))
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
        dims = [6 * vertex_count + 3 + features] + [hidden] * layers
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
    """The ClothLoss of stretch, bending, gravity, inertia and body contact (materials per call)."""
    lc = cfg["loss"]
    weights = lc["weights"]
    if not isinstance(weights, dict) or set(weights) - set(TERMS):
        raise ValueError(f"config key 'loss.weights' must map a subset of {list(TERMS)} to numbers, got {weights!r}")
    weights = {name: float(weights.get(name, 1.0)) for name in TERMS}
    # the stored materials are placeholders: every call passes the sampled per-sample ones
    young, poisson = tb.material_from_lame(3e4, 3e4)
    thickness = check_positive(cfg, "cloth.thickness")
    terms = {
        "stretch": tb.losses.Stretch(faces, rest, young=young, poisson=poisson, thickness=thickness),
        "bending": tb.losses.Bending(faces, rest, 1e-6),  # quadratic: see torchbend.losses.elastic
        "gravity": tb.losses.Gravity(faces, rest, 0.2),
        "inertia": tb.losses.Inertia(faces, rest, 0.2, check_positive(cfg, "loss.dt")),
        "contact": tb.losses.BodyContact(stiffness=check_positive(cfg, "loss.contact_stiffness"),
                                         eps=check_positive(cfg, "loss.contact_eps", allow_zero=True),
                                         body_faces=body_faces),
    }
    if lc["normalize"]:  # joules -> O(1): divide by M g L of a mid-range density (torchbend.losses.cloth_loss)
        scale = tb.losses.energy_scale(faces, rest, sum(_range(cfg, "material.density")) / 2)
        weights = {k: w / scale for k, w in weights.items()}
    return tb.ClothLoss(terms, weights)


def resolve_device(name: str) -> torch.device:
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
    return device


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--config", help="YAML config over the script's defaults (e.g. configs/train_hood.yaml)")
    p.add_argument("--out", default="runs/hood_style", help="output directory (logs, checkpoint, history)")
    p.add_argument("--steps", type=int, help="override train.steps")
    p.add_argument("--seed", type=int, help="override train.seed")
    p.add_argument("--device", default="cpu")
    p.add_argument("--resume", action="store_true", help="continue from <out>/checkpoint.pt")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def main(argv=None, mesh: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict:
    """Train; ``mesh = (rest (V, 3), faces (F, 3))`` replaces the default grid cloth (placed above the
    body, which moves about the origin).  Returns ``{"losses", "terms", "start", "steps"}``."""
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    a = parse_args(argv)
    cfg = load_config(a.config, DEFAULTS) if a.config else {k: dict(v) for k, v in DEFAULTS.items()}
    t = cfg["train"]
    for key in ("steps", "seed"):
        if getattr(a, key) is not None:
            t[key] = getattr(a, key)
    if t["dtype"] not in ("float32", "float64"):
        raise ValueError(f"config key 'train.dtype' must be float32 or float64, got {t['dtype']!r}")
    dtype, device = getattr(torch, t["dtype"]), resolve_device(a.device)
    check_positive(cfg, "train.lr")
    check_positive(cfg, "train.clip_grad")
    seed_everything(int(t["seed"]))
    rest, faces = grid_cloth(cfg, dtype) if mesh is None else (mesh[0].to(dtype), mesh[1])
    sphere, body_faces = tb.scenes.icosphere(int(cfg["body"]["subdivisions"]), 1.0, dtype=dtype)
    loss_fn = build_loss(cfg, rest, faces, body_faces).to(device)
    rest, sphere = rest.to(device), sphere.to(device)
    dt = float(cfg["loss"]["dt"])
    m = cfg["model"]
    net = StepNet(len(rest), 9, int(m["hidden"]), int(m["layers"]), float(m["output_scale"])).to(dtype=dtype, device=device)
    opt = torch.optim.Adam(net.parameters(), lr=float(t["lr"]))
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")
    start = 0
    if a.resume:
        ck = load_checkpoint(ckpt_path)
        net.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start = int(ck["step"])
    gen = torch.Generator().manual_seed(int(t["seed"]) * 1000 + 7919 * start)
    writer = SummaryWriter(os.path.join(a.out, "tb"))
    batch, rollout, steps = int(t["batch"]), int(t["rollout"]), int(t["steps"])
    if batch < 1 or rollout < 1:
        raise ValueError(f"config keys 'train.batch' and 'train.rollout' must be >= 1, got {batch}, {rollout}")
    history: list[float] = []
    terms: dict[str, list[float]] = {}  # per evaluated term (weight != 0), unweighted [J]
    timer = Timer()
    seq = x = v = None
    frame = 0
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
        if step % int(t["log_every"]) == 0 or step == steps:
            for name, value in values.items():
                writer.add_scalar(f"loss/{name}", float(value), step)
            writer.add_scalar("loss/total", history[-1], step)
            writer.add_scalar("time/seconds_per_step", timer.lap() / int(t["log_every"]), step)
        if step % int(t["checkpoint_every"]) == 0 or step == steps:
            save_checkpoint(ckpt_path, step=step, model=net.state_dict(), optimizer=opt.state_dict(), config=cfg)
    writer.close()
    result = {"losses": history, "terms": terms, "start": start, "steps": steps}
    with open(os.path.join(a.out, "history.json"), "w") as f:
        json.dump(result, f)
    if history:
        print(f"hood_style: {len(history)} steps, final loss {history[-1]:.4g} "
              + " ".join(f"{k}={vals[-1]:.3g} J" for k, vals in terms.items() if vals))
    return result


if __name__ == "__main__":
    main()
