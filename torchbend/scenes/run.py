"""Run a cloth scene from a YAML config: ``python -m torchbend.scenes configs/cloth_sphere.yaml``.

Writes into the output directory (``--out``, default ``runs/<config name>``):
``frames/frame_XXXX.obj`` (meshio), ``snapshot.png`` (matplotlib: the cloth and every collider,
including a robot's link capsules) and ``stats.json`` (the validated config and, per step: Newton
iterations, residual, energy per term, seconds, the smallest contact distance and the contact count).  Three
scene kinds:

* ``dynamic`` (e.g. ``cloth_sphere``): implicit Euler steps of a cloth falling onto colliders;
* ``robot`` (e.g. ``robot_fold``): implicit Euler steps of a cloth held by a URDF robot following
  joint keyframes (``robot`` section, see :func:`torchbend.scenes.config.parse_robot`); ``stats.json``
  records the joints and the distance of the held vertices from their forward kinematics per step;
* ``static`` (e.g. ``beams``): one static solve per listed thickness (cantilevers).

Dynamic and robot scenes write ``checkpoint.pt`` (step, positions, velocities, statistics so far)
with every frame; ``--resume`` continues from it (a checkpoint of another scene kind or mesh is an
error; other config changes are logged as a warning).  Options shared with the training scripts
(:mod:`torchbend.scenes.cli`): ``--config``, ``--set KEY=VALUE``, ``--seed``, ``--device``, ``--out``,
``--resume``, ``--log-level``, ``--no-progress``; and ``--steps``, ``--resolution NX NY``.

Config keys (every section optional; schema and defaults: :class:`torchbend.scenes.config.SceneConfig`):
``scene.kind``; ``mesh`` (``type: grid`` with ``nx``, ``ny``, ``size``, ``offset``, ``pin``, or
``type: file`` with ``path`` (a file, or ``asset:NAME`` for a mesh shipped with torchbend), ``weld_tol``,
``offset``, ``pin``; ``mesh: path.obj`` for short; ``pin``: vertex indices or a region
``{x_min, ..., z_max, nearest}`` of rest coordinates before the offset, e.g. ``configs/skirt_drape.yaml``);
``material`` (``density`` [kg/m^2], ``young`` [Pa], ``poisson``, ``thickness`` [m] or
``thicknesses`` for static sweeps, or ``volumetric_density`` [kg/m^3] instead of ``density``);
``bending`` (``model``, ``stiffness`` [N m] or ``from_material: true``, ``damping``); ``membrane``
(``model``); ``colliders`` (list of ``{type: sphere|plane|capsule, ...}``); ``gravity``; ``solver``
(``dt``, ``steps``, ``load_steps`` for static scenes: gravity ramped in that many equal increments, and
the fields of :class:`torchbend.NewtonOptions` one to one: ``projection``, ``linear_solver``, ``tol``,
``max_iters``, ``check_minimum``, ``time_limit``, ``continuation``, ``max_relax_steps``, ``max_substep_depth``); ``output`` (``every``); ``robot`` (``urdf``,
``pins``, ``capsules``, ``trajectory``).  Unknown keys and invalid values raise ``ValueError``
naming the key's path (``unknown config key 'solver.tol_x'``).

**The beams report** compares each tip deflection with Kirchhoff plate theory,
``w = q L^4 / (8 D)``, ``D = Y t^3 / (12 (1 - nu^2))``, ``q`` the weight per area, ``L`` the free
length, and splits the ratio into two factors: ``tip / linear`` with ``linear`` the same mesh's
small-load response (a solve at 1e-4 of the load, scaled back), and ``linear / Kirchhoff``.

* ``tip / linear`` < 1 measures geometric nonlinearity: where Kirchhoff's deflection is comparable
  to or larger than the beam (the thin beams: 8 m for a 0.3 m beam at t = 0.5 mm), linear theory
  does not apply and the beam, which cannot deflect more than its length, is far stiffer.
* ``linear / Kirchhoff`` is the same at every thickness (0.42 on the 61 x 6 grid): the discrete
  hinge energy's own linear stiffness against plate theory.  With the stiffness
  ``k = Y t^3 / (24 (1 - nu^2)) = D / 2`` the hinge energy matches Kirchhoff for doubly curved
  (sphere-like) bending, ``k (2H)^2`` per area, but stores about ``3 k kappa^2`` per area, three
  times the plate's ``D kappa^2 / 2``, when a flat regular triangle mesh (grid or equilateral) is
  bent into a cylinder of curvature ``kappa``; the grid's one-way diagonals let the strip relax part
  of that.  The factor depends on the cell shape and not on refinement: 0.42 with square cells
  (61 x 6, 121 x 11, 241 x 21), 0.37 at 31 x 6, 0.56 at 131 x 6, 0.59 at 196 x 7.  So the stiff
  beams' 0.42 is the discretisation's known mesh dependence, not a solver error.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import time

import torch

from .._extras import require
from ..robot import trajectory
from ..sim import ClothState, implicit_euler_step, solve_static
from . import cli
from .config import (
    ConfigError,
    SceneConfig,
    build_collider,
    build_robot_scene,
    build_scene,
    check_resolution,
    load_config,
    validate,
)
from .plot import snapshot

__all__ = ["run_config", "main"]

log = logging.getLogger("torchbend.scenes")

LINEAR_LOAD = 1e-4  # load fraction of the small-load (linear response) solve of static scenes


def _write_obj(path: str, x: torch.Tensor, faces: torch.Tensor) -> None:
    meshio = require("meshio", "writing scene frames")

    meshio.write_points_cells(path, x.detach().cpu().numpy(), [("triangle", faces.cpu().numpy())])


def run_config(cfg, out_dir: str, *, steps: int | None = None, resolution: tuple | None = None,
               progress: bool = True, device=None, resume: bool = False, name: str | None = None) -> dict:
    """Run a scene config (a dict or :class:`~torchbend.scenes.config.SceneConfig`), write
    frames/snapshot/stats into ``out_dir``; returns the stats dict.

    ``steps``/``resolution`` override ``solver.steps`` and the grid size, ``device`` places the
    tensors (robot scenes: CPU only), ``resume`` continues a dynamic or robot run from
    ``out_dir/checkpoint.pt``, ``name`` titles the snapshot."""
    cfg = validate(cfg, SceneConfig)
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise ConfigError(f"--steps must be a positive integer, got {steps!r}")
    kind = cfg.scene.kind
    sol = cfg.solver
    stats = {"config": cfg.model_dump(mode="json"), "kind": kind, "steps": []}
    if kind in ("dynamic", "robot"):
        _run_dynamic(cfg, out_dir, stats, steps, resolution, progress, device, resume, name)
    else:
        if resume:
            log.warning("--resume: a static scene has nothing to resume; solving from the start")
        _run_static(cfg, out_dir, stats, sol, resolution, device, name)
    with open(os.path.join(out_dir, "stats.json"), "w") as f:
        json.dump(stats, f, indent=1, default=str)
    return stats


def _run_dynamic(cfg: SceneConfig, out_dir, stats, steps, resolution, progress, device, resume, name) -> None:
    tqdm = require("tqdm", "the scene runner's progress bar").tqdm

    sol, kind = cfg.solver, cfg.scene.kind
    ckpt = os.path.join(out_dir, "checkpoint.pt")
    ck, changed = _checkpoint(ckpt, stats["config"]) if resume else ({}, [])  # checked before the scene is built
    if kind == "robot":
        if device is not None and torch.device(device).type != "cpu":
            raise ValueError("robot scenes run on the CPU (--device cpu)")
        scene, x0, faces, keyframes = build_robot_scene(cfg, resolution=resolution)
        model = scene.model
        stats["pin_error"] = []
    else:
        model, x0, faces = build_scene(cfg, resolution=resolution, device=device)
    os.makedirs(os.path.join(out_dir, "frames"), exist_ok=True)
    dt, n_steps = sol.dt, steps if steps is not None else sol.steps
    options = sol.newton_options()  # the solver section, field by field (defaults: those of a time step)
    state, start = ClothState(x0, torch.zeros_like(x0)), 0
    if resume:
        for key in ("x", "v"):
            if tuple(ck[key].shape) != tuple(x0.shape):
                raise ConfigError(f"--resume: {ckpt} holds {key} of shape {tuple(ck[key].shape)}, this scene "
                                  f"{tuple(x0.shape)} (another --resolution?)")
        if changed:
            log.warning("--resume: the config differs from the checkpoint's at %s", ", ".join(changed))
        state = ClothState(ck["x"].to(x0), ck["v"].to(x0))
        start = int(ck["step"])
        stats["steps"] = list(ck["steps"])
        if kind == "robot":
            stats["pin_error"] = list(ck["pin_error"])
        log.info("resumed at step %d from %s", start, ckpt)
    else:
        _write_obj(os.path.join(out_dir, "frames", "frame_0000.obj"), state.x, faces)
    for i in tqdm(range(start + 1, n_steps + 1), desc="steps", disable=not progress, initial=start, total=n_steps):
        if kind == "robot":
            q = trajectory(keyframes, i * dt)
            state, info = scene.step(state, q, dt, options)
            err = float((state.x[scene.pins.vertices] - scene.pins.positions(q)).norm(dim=-1).max())
            stats["pin_error"].append(err)
            extra = {"q": q.tolist(), "pin_error": err}
        else:
            state, info = implicit_euler_step(model, state, dt, options)
            extra = {}
        stats["steps"].append(_info_dict(info, step=i, **extra))
        if not info.converged:
            log.warning("step %d did not converge: %s", i, info.message)
        if i % cfg.output.every == 0 or i == n_steps:
            _write_obj(os.path.join(out_dir, "frames", f"frame_{i:04d}.obj"), state.x, faces)
            cli.save_checkpoint(ckpt, step=i, x=state.x.detach().cpu(), v=state.v.detach().cpu(), steps=stats["steps"],
                                pin_error=stats.get("pin_error", []), config=stats["config"])
    colliders = scene.colliders(trajectory(keyframes, n_steps * dt)) if kind == "robot" else model.colliders
    free = ~model.pinned
    depth = max((float((c.depth(state.x[free]) - c.margin).max()) for c in colliders), default=0.0)
    stats["max_penetration"] = max(depth, 0.0)  # [m] below a collider surface (0: none)
    stats["edge_length"] = float(_mean_edge(x0, faces))
    title = f"{name or kind}: step {n_steps}, t = {n_steps * dt:.3g} s"
    snapshot(os.path.join(out_dir, "snapshot.png"), [([(state.x, faces)], colliders)], titles=[title])


def _checkpoint(path: str, config: dict) -> tuple[dict, list[str]]:
    """The checkpoint ``--resume`` continues a scene of ``config`` from, and the config keys that
    differ; :class:`ConfigError` for a checkpoint of another script, scene kind or mesh."""
    ck, changed = cli.resume_checkpoint(path, config, {"x": torch.Tensor, "v": torch.Tensor, "steps": list,
                                                       "pin_error": list}, ignore=("solver.steps",))
    other = [k for k in changed if k == "scene.kind" or k == "mesh" or k.startswith("mesh.")]
    if other:
        raise ConfigError(f"--resume: {path} is of another scene (config differs at {', '.join(other)})")
    return ck, changed


def _tip(x, x0) -> float:
    """Mean downward deflection [m] of the free end (the vertices of largest rest x)."""
    return float(-(x[:, 2] - x0[:, 2])[x0[:, 0] >= x0[:, 0].max() - 1e-12].mean())


def _run_static(cfg: SceneConfig, out_dir, stats, sol, resolution, device, name) -> None:
    mat = cfg.material
    thicknesses = mat.thicknesses or [mat.thickness]
    options = sol.newton_options()  # the solver section, field by field (defaults: those of a static solve)
    # the intermediate load steps need no more than an approximate equilibrium to start the next one from
    intermediate = options.replace(tol=1e-6)
    shown = []
    for j, t in enumerate(thicknesses):
        model, x0, faces = build_scene(cfg, thickness=float(t), resolution=resolution, device=device)
        os.makedirs(os.path.join(out_dir, "frames"), exist_ok=True)
        # load stepping (continuation in gravity) for large deflections: each static solve
        # starts from the previous equilibrium
        n_load = sol.load_steps
        g_full = model.gravity.clone()
        x, t_solve, total_its = x0, 0.0, 0
        for k in range(1, n_load + 1):
            model.gravity = g_full * (k / n_load)
            final = k == n_load
            x, info = solve_static(model, x, options if final else intermediate)
            t_solve += info.seconds
            total_its += info.iterations
        info.seconds, info.iterations = t_solve, total_its
        if not info.converged:
            log.warning("thickness %.1e m: the static solve did not converge: %s", t, info.message)
        tip = _tip(x, x0)
        # the same mesh's linear response: a small load, scaled back (tip / linear: geometric nonlinearity)
        model.gravity = g_full * LINEAR_LOAD
        x_lin, info_lin = solve_static(model, x0, options)
        linear = _tip(x_lin, x0) / LINEAR_LOAD if info_lin.converged else float("nan")
        model.gravity = g_full
        d = mat.young * float(t) ** 3 / (12 * (1 - mat.poisson ** 2))
        q = model.mass.sum().item() * float(g_full.norm()) / _area(x0, faces)  # load per area [Pa]
        cols = x0[:, 0].unique()
        length = float(cols[-1] - cols[0] - (cols[1] - cols[0]))  # free length: from the second column
        kirchhoff = q * length**4 / (8 * d)
        stats["steps"].append(_info_dict(info, thickness=float(t), tip_deflection=tip, linear_tip=linear,
                                         kirchhoff_tip=kirchhoff, ratio=tip / kirchhoff, nonlinearity=tip / linear,
                                         linear_to_kirchhoff=linear / kirchhoff))
        _write_obj(os.path.join(out_dir, "frames", f"beam_{j}.obj"), x, faces)
        shown.append((x, faces))
    snapshot(os.path.join(out_dir, "snapshot.png"), [(shown, [build_collider(c) for c in cfg.colliders])],
             titles=[f"{name or 'static'}: thicknesses {', '.join(f'{t:g}' for t in thicknesses)} m"])


def _mean_edge(x, faces):
    p = x[faces]
    return torch.cat([(p[:, i] - p[:, (i + 1) % 3]).norm(dim=-1) for i in range(3)]).mean()


def _area(x, faces):
    p = x[faces]
    return float(0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1).sum())


def _monotone(history: list, starts: list) -> bool:
    """Whether the potential never rose between the positions ``starts`` where another potential begins (a
    barrier's adapted stiffness, a halved step's second half: ``SolveInfo.adapted_at``)."""
    cuts = [0, *sorted(starts), len(history)]
    return all(b <= a + 1e-12 * max(abs(a), 1.0) for lo, hi in zip(cuts, cuts[1:])
               for a, b in zip(history[lo:hi], history[lo + 1:hi]))


def _info_dict(info, **extra) -> dict:
    d = {"converged": info.converged, "iterations": info.iterations, "residual": info.residual,
         "energy": info.energy, "energies": info.energies, "seconds": info.seconds,
         "line_search_failures": info.line_search_failures, "message": info.message,
         "min_distance": info.min_distance, "contact_count": info.contact_count,
         "energy_monotone": _monotone(info.energy_history, info.adapted_at)}
    d.update(extra)
    return d


def summary(stats: dict, seconds: float, out: str) -> list[str]:
    """The lines of the end-of-run report."""
    its = [s["iterations"] for s in stats["steps"]]
    converged = sum(bool(s["converged"]) for s in stats["steps"])
    lines = [f"{len(its)} solves ({converged} converged), Newton iterations mean {sum(its) / max(len(its), 1):.1f} "
             f"max {max(its, default=0)}, {seconds:.1f} s -> {out}"]
    if "pin_error" in stats:
        lines.append(f"robot-held vertices vs forward kinematics: max error {max(stats['pin_error'], default=0.0):.2e} m")
    if "max_penetration" in stats:
        lines.append(f"max penetration {stats['max_penetration']:.2e} m (mean edge {stats['edge_length']:.3e} m)")
    touching = [s for s in stats["steps"] if s.get("contact_count")]
    if touching:
        lines.append(f"contact: {len(touching)} solves with contacts, smallest distance "
                     f"{min(s['min_distance'] for s in touching):.2e} m, at most "
                     f"{max(s['contact_count'] for s in touching)} contacts")
    beams = [s for s in stats["steps"] if "ratio" in s]
    if beams:
        lines.append("beams: tip/Kirchhoff = (tip/linear) x (linear/Kirchhoff); Kirchhoff = q L^4 / (8 D), linear plate "
                     "theory; linear = this mesh's small-load response")
        lines.append("  tip/linear < 1: large deflection (geometric stiffening; Kirchhoff out of range); linear/Kirchhoff: "
                     "the hinge energy's mesh-dependent stiffness vs plate theory (same at every thickness; "
                     "see torchbend.scenes.run)")
    for s in beams:
        lines.append(f"thickness {s['thickness']:.1e} m: tip {s['tip_deflection']:.4e} m, linear {s['linear_tip']:.4e} m, "
                     f"Kirchhoff {s['kirchhoff_tip']:.4e} m, tip/Kirchhoff {s['ratio']:.3f} = "
                     f"{s['nonlinearity']:.3f} x {s['linear_to_kirchhoff']:.3f}, {s['iterations']} Newton iterations")
    return lines


def parser() -> argparse.ArgumentParser:
    """The options of ``python -m torchbend.scenes``."""
    p = argparse.ArgumentParser(prog="python -m torchbend.scenes",
                                description="Run a torchbend cloth scene from a YAML config.")
    cli.add_common_args(p, config_positional=True)
    p.add_argument("--steps", type=cli.positive_int, help="override solver.steps (dynamic scenes)")
    p.add_argument("--resolution", type=cli.positive_int, nargs=2, metavar=("NX", "NY"),
                   help="override mesh.nx, mesh.ny (grid meshes)")
    return p


def main(argv=None) -> dict:
    p = parser()
    a = cli.parse_args(p, argv)
    if a.resolution:
        try:
            check_resolution(*a.resolution, where="argument --resolution")
        except ConfigError as e:
            p.error(str(e))
    device = cli.resolve_device(a.device, prog=p.prog)
    cfg = load_config(a.config, SceneConfig, a.overrides)
    if cfg["scene"]["kind"] == "robot" and device.type != "cpu":
        raise SystemExit(f"{p.prog}: error: --device {a.device}: robot scenes run on the CPU only")
    if a.seed is not None:
        cli.seed_everything(a.seed)
    name = os.path.splitext(os.path.basename(a.config))[0]
    out = a.out or os.path.join("runs", name)
    t0 = time.perf_counter()
    stats = run_config(cfg, out, steps=a.steps, resolution=tuple(a.resolution) if a.resolution else None,
                       progress=not a.no_progress, device=device, resume=a.resume, name=name)
    for line in summary(stats, time.perf_counter() - t0, out):
        log.info(line)
    return stats


if __name__ == "__main__":
    cli.run_main(main, "python -m torchbend.scenes")
