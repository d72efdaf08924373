"""Material identification: recover the bending stiffness from an observed static equilibrium.

    python train/material_id.py --config configs/train_material.yaml

A cantilever strip (quadratic bending, StVK membrane, gravity, clamped end) is solved at the true
stiffness to make a synthetic observation ``x_obs``.  Starting from a wrong guess, ``log k`` is
fitted by gradient descent on ``L(k) = |x*(k) - x_obs|^2 / |x_obs - X|^2`` where ``x*(k)`` is the
equilibrium from :func:`torchbend.solve_static`; ``dL/dk`` comes from the implicit-function adjoint
(:func:`torchbend.solve_static_adjoint`: one sparse solve with the exact Hessian, a
vector-Jacobian product through the analytic gradient), never by unrolling Newton.  Optionally the
rest angles are fitted too (``fit_rest_angles``).  TensorBoard logs, checkpoints, ``--resume``.
"""
from __future__ import annotations

import json
import logging
import math
import os
from typing import Annotated, Any

import common as tc
import torch
from pydantic import Field

import torchbend as tb
from torchbend._extras import require
from torchbend.scenes import cli
from torchbend.scenes import config as sc

log = logging.getLogger("train.material_id")
CONFIG = tc.config_file("train_material.yaml")


class IdentifySection(tc.Section):
    """``identify``: the true stiffness [N m] (default: from the beam's material), the initial guess
    (``initial_factor`` times it), L-BFGS ``steps``/``lr``, the loss ``tol`` to stop at."""

    true_stiffness: tc.Positive | None = None
    initial_factor: tc.Positive = 3.0
    steps: tc.PositiveInt = 15
    lr: tc.Positive = 1.0
    tol: Annotated[tc.Float, Field(ge=0)] = 1e-12
    fit_rest_angles: bool = False
    seed: tc.Seed = 0


class Config(sc.PhysicsConfig):
    """The material-identification config (``configs/train_material.yaml``): the physics sections of a
    scene config (:class:`~torchbend.scenes.config.PhysicsConfig`; by default a 21 x 4 strip of 0.2 x 0.03 m
    clamped at its first two columns, quadratic bending, StVK membrane) and ``identify``."""

    mesh: sc.MeshSection = sc.GridMesh(nx=21, ny=4, size=(0.2, 0.03), pin="first_two_columns")
    material: sc.MaterialSection = sc.MaterialSection(young=5e6, poisson=0.3, thickness=2e-3, density=2.0)
    bending: sc.BendingSection | None = sc.BendingSection(model="quadratic", from_material=True)
    membrane: sc.MembraneSection | None = sc.MembraneSection(model="stvk")
    identify: IdentifySection = IdentifySection()


def _config(cfg) -> Config:
    """``cfg`` as a validated :class:`Config` (a dict, e.g. a checkpoint's record, is validated)."""
    config = cfg if isinstance(cfg, Config) else sc.validate(cfg, Config)
    if config.bending is None:
        raise tc.ConfigError("config key 'bending': the bending stiffness is what this script identifies: give a "
                          "bending section")
    return config


def build(cfg, stiffness: torch.Tensor, rest_angles=None):
    """``(model, rest, bend)``: the config's model with its bending stiffness ``stiffness`` (a tensor, so that the
    adjoint differentiates with respect to it)."""
    config = _config(cfg)
    assert config.bending is not None
    model = sc.build_model(config.model_copy(update={"bending": None}))  # the bending term is this one's
    faces, rest = model.topology.faces, model.rest_positions
    model.bending = tb.BendingEnergy(faces, rest, model=config.bending.model, stiffness=stiffness,
                                     rest_angles=rest_angles)
    return model, rest, model.bending


def true_stiffness(cfg) -> float:
    """``identify.true_stiffness``, else the bending section's ``stiffness``, else the material's
    ``Y t^3 / (24 (1 - nu^2))``."""
    config = _config(cfg)
    assert config.bending is not None
    if config.identify.true_stiffness is not None:
        return config.identify.true_stiffness
    if config.bending.stiffness is not None:
        return config.bending.stiffness
    m = config.material
    return tb.stiffness_from_material(m.young, m.thickness, m.poisson)


def observe(cfg):
    k = torch.tensor(true_stiffness(cfg), dtype=torch.float64)
    model, rest, _ = build(cfg, k)
    x, info = tb.solve_static(model, rest, tol=1e-10, continuation=True)
    if not info.converged:  # the beam's or the stiffness's values: no equilibrium within the solver's limits
        raise tc.ConfigError(f"the synthetic observation (the static solve at the true stiffness {float(k):.3g} N m) did "
                          f"not converge: {info.message}; check the physics sections and 'identify.true_stiffness'")
    return x, rest, float(k)


def loss_of(cfg, log_k, rest_shift, x_obs, x_start=None):
    """``(L, x*, info)`` with ``L`` differentiable in ``log_k`` (and ``rest_shift``) via the adjoint.

    ``x_start`` warm-starts Newton (e.g. the previous equilibrium); pinned vertices are unaffected."""
    k = torch.exp(log_k)
    model, rest, bend = build(cfg, k)
    params = [bend.stiffness]
    if rest_shift is not None:
        bend.rest_angles = bend.rest_angles + rest_shift
        params.append(bend.rest_angles)
    x0 = rest if x_start is None else x_start.detach()
    x, info = tb.solve_static_adjoint(model, x0, params, tol=1e-10, continuation=True)
    scale = ((x_obs - rest) ** 2).sum()
    return ((x - x_obs) ** 2).sum() / scale, x, info


def resume(path: str, cfg: dict, log_k: torch.Tensor, shift: torch.Tensor | None, opt) -> int:
    """``--resume``: ``log_k``, the rest-angle ``shift`` (when fitted) and the optimizer restored from
    the checkpoint at ``path``; returns its step.  :class:`ConfigError` for a checkpoint of another
    script or one that does not fit (another beam resolution)."""
    ck, changed = cli.resume_checkpoint(path, cfg, {"log_k": torch.Tensor, "optimizer": dict,
                                                    "shift": (torch.Tensor, type(None))}, ignore=("identify.steps",))
    differs = f"config differs at {', '.join(changed)}" if changed else "the same config"
    if ck["log_k"].shape != log_k.shape:
        raise tc.ConfigError(f"--resume: {path} does not fit this run ({differs}): log_k of shape {tuple(ck['log_k'].shape)}")
    if shift is not None and ck.get("shift") is not None and ck["shift"].shape != shift.shape:
        raise tc.ConfigError(f"--resume: {path} does not fit this run ({differs}): {ck['shift'].numel()} rest-angle "
                          f"shifts, this beam has {shift.numel()} hinges")
    cli.restore(path, changed, (opt, ck["optimizer"]), what="run")
    with torch.no_grad():
        log_k.copy_(ck["log_k"])
        if shift is not None and ck.get("shift") is not None:
            shift.copy_(ck["shift"])
    if changed:
        log.warning("--resume: the config differs from the checkpoint's at %s", ", ".join(changed))
    log.info("resumed at step %d from %s", ck["step"], path)
    return ck["step"]


def parse_args(argv=None):
    return cli.parse_args(tc.script_parser(__doc__, CONFIG, "runs/material_id", "identify"), argv)


def main(argv=None) -> dict:
    SummaryWriter = require("torch.utils.tensorboard", "TensorBoard logs").SummaryWriter
    from tqdm import tqdm

    a = parse_args(argv)
    cli.resolve_device(a.device, supported=("cpu",), why="the sparse solves run in scipy")
    config = tc.read_config(a.config, Config, tc.flag_overrides(a, "identify"))
    _config(config)
    cfg = config.model_dump(mode="json")  # the checkpoint's record
    it = cfg["identify"]
    tc.seed_everything(int(it["seed"]))
    k_true = true_stiffness(config)
    log_k = torch.tensor(math.log(k_true * float(it["initial_factor"])), dtype=torch.float64, requires_grad=True)
    shift = None
    if it["fit_rest_angles"]:
        H = build(config, torch.tensor(1.0, dtype=torch.float64))[2].hinge_count
        shift = torch.zeros(H, dtype=torch.float64, requires_grad=True)
    params = [log_k] + ([shift] if shift is not None else [])
    # one L-BFGS iteration (with a strong-Wolfe line search) per step: each evaluation is a static
    # solve plus one adjoint solve
    opt = torch.optim.LBFGS(params, lr=float(it["lr"]), max_iter=1, line_search_fn="strong_wolfe")
    os.makedirs(a.out, exist_ok=True)
    ckpt = os.path.join(a.out, "checkpoint.pt")
    start = 0
    if a.resume:
        start = resume(ckpt, cfg, log_k, shift, opt)
    x_obs, rest, k_true = observe(config)
    writer = SummaryWriter(os.path.join(a.out, "tb"))
    timer = tc.Timer()
    history = []
    steps = int(it["steps"])
    state: dict[str, Any] = {"x": None}  # the last evaluation of the closure: x, info, L
    for step in tqdm(range(start + 1, steps + 1), desc="identify", disable=a.no_progress, initial=start, total=steps):

        def closure():
            opt.zero_grad(set_to_none=True)
            L, x, info = loss_of(config, log_k, shift, x_obs, state["x"])
            L.backward()
            state.update(x=x.detach(), info=info, L=L.detach())
            return L

        opt.step(closure)
        L, info = state["L"], state["info"]
        k_now = math.exp(float(log_k.detach()))
        history.append({"step": step, "loss": float(L.detach()), "stiffness": k_now,
                        "rel_error": abs(k_now - k_true) / k_true, "newton_iterations": info.iterations})
        writer.add_scalar("loss", float(L.detach()), step)
        writer.add_scalar("stiffness/relative_error", abs(k_now - k_true) / k_true, step)
        writer.add_scalar("residual/newton", info.residual, step)
        writer.add_scalar("time/seconds_per_step", timer.lap(), step)
        tc.save_checkpoint(ckpt, step=step, log_k=log_k.detach(), shift=None if shift is None else shift.detach(),
                        optimizer=opt.state_dict(), config=cfg)
        if float(L.detach()) < float(it["tol"]):
            break
    writer.close()
    result = {"k_true": k_true, "k_fit": math.exp(float(log_k.detach())), "history": history, "start": start}
    with open(os.path.join(a.out, "history.json"), "w") as f:
        json.dump(result, f, indent=1)
    log.info("true stiffness %.6e N m, identified %.6e N m (relative error %.2e) after %d steps -> %s", k_true,
             result["k_fit"], abs(result["k_fit"] - k_true) / k_true, start + len(history), a.out)
    return result


if __name__ == "__main__":
    cli.run_main(main)
