"""Drapes conditioned on robot joint angles: a towel held by the two finger tips of the shipped arm.

    python train/robot_drape.py --config configs/train_robot.yaml

A batch of joint configurations ``q (B, J)`` is sampled around a nominal pose every step; an MLP
maps ``q`` to vertex displacements added to the rest towel moved with the finger tips (kept
vertical); the two corner vertices are placed exactly at the finger tips by batched forward
kinematics (``LinkPins``, pytorch-kinematics).  The loss is the
total potential (membrane + bending + gravity + table penalty), no ground truth.  Gradients reach
the network through torchbend's analytic bending gradient; the pins are differentiable in ``q``.

At the end the predictions for three held-out joint vectors are compared with Newton equilibria
(:meth:`RobotScene.solve_static` from the prediction): RMS vertex distance and energy gap are
printed and saved in ``history.json``.  TensorBoard logs, checkpoints (``--resume``), ``drapes.png``.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
from typing import Annotated

import common as tc
import torch
from drape_net import DrapeNet, intra_op_threads
from pydantic import Field

import torchbend as tb
from torchbend._extras import require
from torchbend.robot import LinkPins, Robot, RobotScene
from torchbend.scenes import cli
from torchbend.scenes import config as sc

log = logging.getLogger("train.robot_drape")
CONFIG = tc.config_file("train_robot.yaml")


class PoseSection(tc.Section):
    """``robot``: the ``urdf``; joints sampled uniformly in ``nominal +- spread`` (one entry per joint)."""

    urdf: str = "folding_arm.urdf"
    nominal: list[sc.Float] = [0.0, -1.0, 1.2, -0.2, -0.1, -0.1]
    spread: list[sc.Float] = [0.5, 0.1, 0.1, 0.3, 0.03, 0.03]


class TrainSection(tc.TrainBase):
    """``train``: optimisation (Adam), logging cadence, torch's intra-op CPU ``threads`` (0: torch's
    default; one suits these small tensors, and two on a shared 2-core machine ran 10-20x slower)."""

    threads: Annotated[sc.Int, Field(ge=0)] = 1


class Config(sc.PhysicsConfig):
    """The robot-drape config (``configs/train_robot.yaml``): the physics sections of a scene config
    (:class:`~torchbend.scenes.config.PhysicsConfig`; ``mesh`` a grid whose ``nx`` x ``ny`` vertices and
    ``size`` the towel takes, hung below the finger tips; the table top z = 0 a collider) and the script's own."""

    mesh: sc.MeshSection = sc.GridMesh(nx=9, size=(0.3, 0.3))
    material: sc.MaterialSection = sc.MaterialSection(young=1e5, poisson=0.3, thickness=1e-3, density=0.2)
    bending: sc.BendingSection | None = sc.BendingSection(model="sin", stiffness=1e-4)
    membrane: sc.MembraneSection | None = sc.MembraneSection()
    colliders: list[sc.ColliderSpec] = [sc.PlaneSpec(type="plane", point=(0.0, 0.0, 0.0), stiffness=1e3, law="penalty")]
    robot: PoseSection = PoseSection()
    model: tc.ModelSection = tc.ModelSection()
    train: TrainSection = TrainSection()


class HeldTowel:
    """The towel, its physics and the robot: ``drape(net, q)`` -> positions ``(B, V, 3)``."""

    def __init__(self, config: Config, dtype=torch.float64, device=None):
        r = config.robot
        device = torch.device(device or "cpu")
        self.robot = Robot(r.urdf, dtype=dtype, device=device)
        self.nominal = self.robot.check_joints(torch.tensor(r.nominal, dtype=dtype, device=device), "robot.nominal")
        self.spread = self.robot.check_joints(torch.tensor(r.spread, dtype=dtype, device=device), "robot.spread")
        mesh = config.mesh
        if not isinstance(mesh, sc.GridMesh):
            raise sc.ConfigError("config key 'mesh': the towel is a grid (type: grid), not a file mesh")
        nx, ny = mesh.nx, mesh.ny or mesh.nx
        if nx < 3:
            raise sc.ConfigError(f"config key 'mesh.nx' must be >= 3, got {nx}")
        # rest: a flat towel hanging vertically below the line between the finger tips at the nominal pose
        tips = self.robot.link_transforms(self.nominal, ["finger_left", "finger_right"])[:, :3, 3]
        flat, faces = tb.scenes.grid(nx, ny, mesh.size, dtype=dtype, device=device)
        u = (tips[0] - tips[1]) / (tips[0] - tips[1]).norm()
        rest = tips[1] + flat[:, :1] * u - flat[:, 1:2] * torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
        self.physics = tc.ClothPhysics(config, dtype=dtype, device=device, mesh=(rest, faces))
        self.rest, self.faces = rest, faces
        corners = [nx - 1, 0]
        self.pins = LinkPins(self.robot, corners, ["finger_left", "finger_right"], rest[corners], self.nominal)
        self._tips0 = rest[self.pins.vertices]  # the order pins.positions returns

    def sample(self, batch: int, gen: torch.Generator) -> torch.Tensor:
        u = 2 * torch.rand(batch, self.robot.joint_count, generator=gen, dtype=self.nominal.dtype).to(self.nominal.device) - 1
        return self.nominal + u * self.spread

    def base(self, tips: torch.Tensor) -> torch.Tensor:
        """The rest towel moved with the finger tips ``(B, 2, 3)`` and kept vertical: rotation about z
        by the turn of the tip line, translation by the move of its midpoint."""
        def frame(t):
            d = t[..., 0, :] - t[..., 1, :]
            return t.mean(-2), torch.atan2(d[..., 1], d[..., 0])
        mid0, phi0 = frame(self._tips0)
        mid, phi = frame(tips)
        c, s = torch.cos(phi - phi0)[..., None], torch.sin(phi - phi0)[..., None]
        p = self.rest - mid0
        rotated = torch.stack((c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2].expand_as(c * p[:, 0])), -1)
        return rotated + mid[..., None, :]

    def drape(self, net, q: torch.Tensor) -> torch.Tensor:
        tips = self.pins.positions(q)  # (B, 2, 3), vertex order of pins.vertices
        x = self.base(tips) + net((q - self.nominal) / self.spread, torch.zeros_like(self.rest))
        return x.index_copy(-2, self.pins.vertices, tips)

    def scene(self) -> RobotScene:
        """The same cloth as a solver scene (reference equilibria)."""
        pinned = torch.zeros(len(self.rest), dtype=torch.bool, device=self.rest.device)
        pinned[self.pins.vertices] = True
        return RobotScene(self.physics.model(pinned=pinned), self.robot, self.pins)


def parse_args(argv=None):
    return cli.parse_args(tc.script_parser(__doc__, CONFIG, "runs/robot_drape"), argv)


def main(argv=None) -> dict:
    a = parse_args(argv)
    device = cli.resolve_device(a.device)
    config = tc.read_config(a.config, Config, tc.flag_overrides(a))
    with intra_op_threads(config.train.threads):
        return train(a, config, device)


def train(a: argparse.Namespace, config: Config, device: torch.device) -> dict:
    """The run of :func:`main` (parsed options ``a``, the validated ``config``; its plain-dict form is the
    checkpoint's record)."""
    SummaryWriter = require("torch.utils.tensorboard", "TensorBoard logs").SummaryWriter
    from tqdm import tqdm

    cfg = config.model_dump(mode="json")
    t = cfg["train"]
    tc.seed_everything(int(t["seed"]))
    towel = HeldTowel(config, device=device)
    net = DrapeNet(len(towel.rest), int(cfg["model"]["hidden"]), int(cfg["model"]["layers"]),
                   inputs=towel.robot.joint_count).to(dtype=torch.float64, device=device)
    opt = torch.optim.Adam(net.parameters(), lr=float(t["lr"]))
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")
    start = 0
    if a.resume:
        start = tc.resume_run(ckpt_path, cfg, log, (net, "model"), (opt, "optimizer"), map_location=device)
    gen = torch.Generator().manual_seed(int(t["seed"]) * 1000 + 7919 * start)
    writer = SummaryWriter(os.path.join(a.out, "tb"))
    history, timer, steps = [], tc.Timer(), int(t["steps"])
    for step in tqdm(range(start + 1, steps + 1), desc="train", disable=a.no_progress, initial=start, total=steps):
        q = towel.sample(int(t["batch"]), gen)
        x = towel.drape(net, q)
        terms = towel.physics.energies(x, None, None)
        loss = tc.total(terms).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
        if step % int(t["log_every"]) == 0 or step == steps:
            for k, v in terms.items():
                writer.add_scalar(f"energy/{k}", float(v.detach().mean()), step)
            writer.add_scalar("loss", history[-1], step)
            writer.add_scalar("time/seconds_per_step", timer.lap() / int(t["log_every"]), step)
        if step % int(t["checkpoint_every"]) == 0 or step == steps:
            tc.save_checkpoint(ckpt_path, step=step, model=net.state_dict(), optimizer=opt.state_dict(), config=cfg)
    # held-out joint vectors: prediction vs Newton equilibrium started from it
    q_eval = towel.sample(3, torch.Generator().manual_seed(12345))
    with torch.no_grad():
        x_pred = towel.drape(net, q_eval)
    scene, evals = towel.scene(), []
    for qi, xi in zip(q_eval, x_pred, strict=True):
        x_eq, info = scene.solve_static(qi, xi, tol=1e-8, continuation=True)
        e_pred = float(tc.total(towel.physics.energies(xi[None], None, None)))
        e_eq = float(tc.total(towel.physics.energies(x_eq[None].detach(), None, None)))
        evals.append({"q": qi.tolist(), "converged": info.converged,
                      "rms_distance_to_equilibrium": float((xi - x_eq).norm(dim=-1).pow(2).mean().sqrt()),
                      "energy_gap": e_pred - e_eq, "energy_equilibrium": e_eq,
                      "pin_error": float((xi[towel.pins.vertices] - towel.pins.positions(qi)).norm(dim=-1).max())})
    table = list(towel.physics.solver_model.colliders)
    tc.save_drape_png(os.path.join(a.out, "drapes.png"), [(xi, towel.faces) for xi in x_pred],
                   [f"yaw {qi[0]:+.2f} wrist {qi[3]:+.2f} rad" for qi in q_eval.tolist()], colliders=[table] * len(x_pred))
    result = {"losses": history, "start": start, "steps": steps, "eval": evals}
    with open(os.path.join(a.out, "history.json"), "w") as f:
        json.dump(result, f)
    writer.close()
    if history:
        log.info("loss %.6g at step %d -> %.6g at step %d -> %s", history[0], start + 1, history[-1], steps, a.out)
    for e in evals:
        log.info("held-out q: RMS distance to the Newton equilibrium %.2e m, energy %.4f J vs %.4f J, pins vs FK %.1e m%s",
                 e["rms_distance_to_equilibrium"], e["energy_equilibrium"] + e["energy_gap"], e["energy_equilibrium"],
                 e["pin_error"], "" if e["converged"] else " (Newton did not converge)")
    return result


if __name__ == "__main__":
    cli.run_main(main)
