"""Run a cloth scene from a YAML config: ``python -m torchbend.run configs/cloth_sphere.yaml``.

Writes into the output directory (``--out``, default ``runs/<config name>``):
``frames/frame_XXXX.obj`` (meshio), ``snapshot.png`` (matplotlib) and ``stats.json`` (per step:
Newton iterations, residual, energy per term, seconds).  Three scene kinds:

* ``dynamic`` (e.g. ``cloth_sphere``): implicit Euler steps of a cloth falling onto colliders;
* ``robot`` (e.g. ``robot_fold``): implicit Euler steps of a cloth held by a URDF robot following
  joint keyframes (``robot`` section, see :func:`torchbend.robot.parse_config`); ``stats.json``
  records the joints and the distance of the held vertices from their forward kinematics per step;
* ``static`` (e.g. ``beams``): one static solve per listed thickness (cantilevers).

Config keys (every section optional except ``mesh``): ``scene.kind``; ``mesh`` (``type: grid``,
``nx``, ``ny``, ``size``, ``offset``, ``pin``); ``material`` (``density`` [kg/m^2], ``young`` [Pa],
``poisson``, ``thickness`` [m] or ``thicknesses`` for static sweeps, or ``volumetric_density``
[kg/m^3] instead of ``density``); ``bending`` (``model``,
``stiffness`` [N m] or ``from_material: true``, ``damping``); ``membrane`` (``model``);
``colliders`` (list of ``{type: sphere|plane|capsule, ...}``); ``gravity``; ``solver`` (``dt``,
``steps``, ``hessian``, ``linear_solver``, ``tol``, ``max_iters``, ``load_steps`` for static
scenes: gravity ramped in that many equal increments); ``output`` (``every``); ``robot`` (``urdf``,
``pins``, ``capsules``, ``trajectory``).
Unknown or invalid values raise ``ValueError`` naming the key.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time

import torch

from . import scenes
from .bending import BendingEnergy
from .colliders import Capsule, Plane, Sphere
from .membrane import MembraneEnergy
from .models import stiffness_from_material
from .solver import ClothModel, ClothState, implicit_euler_step, solve_static

__all__ = ["load_config", "build_scene", "run_config", "main"]

_SECTIONS = {"scene", "mesh", "material", "bending", "membrane", "colliders", "gravity", "solver", "output", "robot"}


def load_config(path: str) -> dict:
    """Read a YAML scene config (``ValueError`` for a missing file or a malformed document)."""
    import yaml

    if not os.path.isfile(path):
        raise ValueError(f"config file not found: {path}")
    with open(path) as f:
        try:
            cfg = yaml.safe_load(f)
        except yaml.YAMLError as e:
            raise ValueError(f"config {path}: invalid YAML ({e})") from None
    if not isinstance(cfg, dict):
        raise ValueError(f"config {path}: expected a mapping at the top level")
    unknown = set(cfg) - _SECTIONS
    if unknown:
        raise ValueError(f"config {path}: unknown keys {sorted(unknown)}; allowed: {sorted(_SECTIONS)}")
    return cfg


def _get(section: dict, key: str, where: str, default=None, *, kind=float, positive=False, required=False):
    if key not in section:
        if required:
            raise ValueError(f"missing config key '{where}.{key}'")
        return default
    value = section[key]
    try:
        value = kind(value)
    except (TypeError, ValueError):
        raise ValueError(f"config key '{where}.{key}' must be a {kind.__name__}, got {value!r}") from None
    if positive and not (value > 0 and (kind is not float or math.isfinite(value))):
        raise ValueError(f"config key '{where}.{key}' must be positive, got {value!r}")
    return value


def _collider(spec: dict, i: int):
    where = f"colliders[{i}]"
    if not isinstance(spec, dict) or "type" not in spec:
        raise ValueError(f"config key '{where}' must be a mapping with a 'type'")
    kinds = {"sphere": Sphere, "plane": Plane, "capsule": Capsule}
    t = spec["type"]
    if t not in kinds:
        raise ValueError(f"config key '{where}.type' must be one of {sorted(kinds)}, got {t!r}")
    kwargs = {k: v for k, v in spec.items() if k != "type"}
    try:
        return kinds[t](**kwargs)
    except TypeError as e:
        raise ValueError(f"config key '{where}': {e}") from None
    except ValueError as e:
        raise ValueError(f"config key '{where}': {e}") from None


def build_scene(cfg: dict, *, thickness: float | None = None, resolution: tuple | None = None):
    """``(model, x0, faces)`` of a config (``thickness``/``resolution`` override the mesh/material).

    With a ``robot`` section the vertices it binds to links are pinned in the model."""
    return _build(cfg, thickness, resolution)[:3]


def build_robot_scene(cfg: dict, *, resolution: tuple | None = None):
    """``(scene, x0, faces, keyframes)`` of a config with a ``robot`` section: a
    :class:`~torchbend.robot.RobotScene` whose pins are bound at the first keyframe's joints."""
    from .robot import LinkPins, RobotScene

    if not cfg.get("robot"):
        raise ValueError("config has no 'robot' section")
    model, x0, faces, rc = _build(cfg, None, resolution)
    pins = LinkPins(rc.robot, rc.vertices, rc.links, x0[rc.vertices], rc.keyframes[0][1])
    scene = RobotScene(model, rc.robot, pins, rc.capsules)
    # the cloth starts with the held vertices exactly at their forward kinematics
    return scene, scene.place(x0, rc.keyframes[0][1]), faces, rc.keyframes


def _build(cfg: dict, thickness, resolution):
    dtype = torch.float64
    mesh = cfg.get("mesh") or {}
    if mesh.get("type", "grid") != "grid":
        raise ValueError(f"config key 'mesh.type' must be 'grid', got {mesh.get('type')!r}")
    nx = _get(mesh, "nx", "mesh", 11, kind=int, positive=True)
    ny = _get(mesh, "ny", "mesh", nx, kind=int, positive=True)
    if resolution is not None:
        nx, ny = resolution
    size = mesh.get("size", [1.0, 1.0])
    rest, faces = scenes.grid(nx, ny, tuple(size), dtype=dtype)
    offset = torch.tensor(mesh.get("offset", [0.0, 0.0, 0.0]), dtype=dtype)
    rest = rest + offset
    mat = cfg.get("material") or {}
    young = _get(mat, "young", "material", 1e5, positive=True)
    poisson = _get(mat, "poisson", "material", 0.3)
    t = thickness if thickness is not None else _get(mat, "thickness", "material", 1e-3, positive=True)
    if "volumetric_density" in mat:  # [kg/m^3] -> areal density of this thickness
        density = _get(mat, "volumetric_density", "material", positive=True) * t
    else:
        density = _get(mat, "density", "material", 0.2, positive=True)
    bend = None
    if cfg.get("bending") is not None:
        b = cfg["bending"]
        if b.get("from_material"):
            k = stiffness_from_material(young, t, poisson)
        else:
            k = _get(b, "stiffness", "bending", required=True)
            if k < 0:
                raise ValueError(f"config key 'bending.stiffness' must be non-negative, got {k}")
        damping = b.get("damping")
        if damping is not None:
            damping = _get(b, "damping", "bending")
            if damping < 0:
                raise ValueError(f"config key 'bending.damping' must be non-negative, got {damping}")
        try:
            bend = BendingEnergy(faces, rest, model=b.get("model", "tan"), stiffness=k, damping=damping or None)
        except ValueError as e:
            raise ValueError(f"config key 'bending': {e}") from None
    mem = None
    if cfg.get("membrane") is not None:
        m = cfg["membrane"]
        try:
            mem = MembraneEnergy(faces, rest, model=m.get("model", "stvk"), young=young, poisson=poisson, thickness=t)
        except ValueError as e:
            raise ValueError(f"config key 'membrane': {e}") from None
    pinned = None
    pin = mesh.get("pin")
    if pin is not None:
        if pin == "first_two_columns":
            xs = rest[:, 0].unique()
            pinned = rest[:, 0] <= xs[min(1, len(xs) - 1)] + 1e-12
        elif pin == "corners":
            pinned = torch.zeros(len(rest), dtype=torch.bool)
            pinned[[0, nx - 1]] = True
        else:
            raise ValueError(f"config key 'mesh.pin' must be 'first_two_columns' or 'corners', got {pin!r}")
    rc = None
    if cfg.get("robot") is not None:
        from .robot import parse_config

        rc = parse_config(cfg["robot"], rest)
        if pinned is None:
            pinned = torch.zeros(len(rest), dtype=torch.bool)
        pinned = pinned.clone()
        pinned[rc.vertices] = True
    colliders = [_collider(c, i) for i, c in enumerate(cfg.get("colliders") or [])]
    gravity = cfg.get("gravity", [0.0, 0.0, -9.81])
    model = ClothModel(faces, rest, bending=bend, membrane=mem, density=density,
                       gravity=gravity, pinned=pinned, colliders=colliders)
    return model, rest.clone(), faces, rc


def _write_obj(path: str, x: torch.Tensor, faces: torch.Tensor) -> None:
    import meshio

    meshio.write_points_cells(path, x.detach().cpu().numpy(), [("triangle", faces.cpu().numpy())])


def _snapshot(path: str, meshes, colliders=()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    for x, faces in meshes:
        p = x.detach().cpu().numpy()
        ax.plot_trisurf(p[:, 0], p[:, 1], p[:, 2], triangles=faces.cpu().numpy(), color="tab:blue",
                        edgecolor="k", linewidth=0.1, alpha=0.9)
    for c in colliders:
        if isinstance(c, Sphere):
            import numpy as np

            u, v = np.mgrid[0 : 2 * np.pi : 30j, 0 : np.pi : 15j]
            ax.plot_wireframe(c.center[0] + c.radius * np.cos(u) * np.sin(v), c.center[1] + c.radius * np.sin(u) * np.sin(v),
                              c.center[2] + c.radius * np.cos(v), color="tab:red", linewidth=0.3)
        if isinstance(c, Capsule):
            seg = torch.tensor([c.a, c.b]).numpy()
            ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color="tab:gray", linewidth=4, solid_capstyle="round")
    ax.set_box_aspect((1, 1, 1))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_config(cfg: dict, out_dir: str, *, steps: int | None = None, resolution: tuple | None = None,
               progress: bool = True) -> dict:
    """Run a parsed config, write frames/snapshot/stats into ``out_dir``; returns the stats dict."""
    from tqdm import tqdm

    os.makedirs(os.path.join(out_dir, "frames"), exist_ok=True)
    kind = (cfg.get("scene") or {}).get("kind", "dynamic")
    sol = cfg.get("solver") or {}
    hessian = sol.get("hessian", "exact")
    linear = sol.get("linear_solver", "direct")
    every = _get(cfg.get("output") or {}, "every", "output", 1, kind=int, positive=True)
    stats = {"config": cfg, "kind": kind, "steps": []}
    if kind in ("dynamic", "robot"):
        from .robot import trajectory

        if kind == "robot":
            scene, x0, faces, keyframes = build_robot_scene(cfg, resolution=resolution)
            model = scene.model
            stats["pin_error"] = []
        else:
            model, x0, faces = build_scene(cfg, resolution=resolution)
        dt = _get(sol, "dt", "solver", 1 / 60, positive=True)
        n_steps = steps if steps is not None else _get(sol, "steps", "solver", 60, kind=int, positive=True)
        kw = dict(hessian=hessian, linear_solver=linear, tol=_get(sol, "tol", "solver", 1e-6),
                  max_iters=_get(sol, "max_iters", "solver", 30, kind=int))
        state = ClothState(x0, torch.zeros_like(x0))
        _write_obj(os.path.join(out_dir, "frames", "frame_0000.obj"), state.x, faces)
        for i in tqdm(range(1, n_steps + 1), desc="steps", disable=not progress):
            if kind == "robot":
                q = trajectory(keyframes, i * dt)
                state, info = scene.step(state, q, dt, **kw)
                err = float((state.x[scene.pins.vertices] - scene.pins.positions(q)).norm(dim=-1).max())
                stats["pin_error"].append(err)
                extra = {"q": q.tolist(), "pin_error": err}
            else:
                state, info = implicit_euler_step(model, state, dt, **kw)
                extra = {}
            stats["steps"].append(_info_dict(info, step=i, **extra))
            if i % every == 0 or i == n_steps:
                _write_obj(os.path.join(out_dir, "frames", f"frame_{i:04d}.obj"), state.x, faces)
        colliders = scene.colliders(trajectory(keyframes, n_steps * dt)) if kind == "robot" else model.colliders
        free = ~model.pinned
        depth = max((float((c.depth(state.x[free]) - c.margin).max()) for c in colliders), default=0.0)
        stats["max_penetration"] = max(depth, 0.0)  # [m] below a collider surface (0: none)
        stats["edge_length"] = float(_mean_edge(x0, faces))
        _snapshot(os.path.join(out_dir, "snapshot.png"), [(state.x, faces)], colliders)
    elif kind == "static":
        mat = cfg.get("material") or {}
        thicknesses = mat.get("thicknesses") or [mat.get("thickness", 1e-3)]
        shown = []
        for j, t in enumerate(thicknesses):
            model, x0, faces = build_scene(cfg, thickness=float(t), resolution=resolution)
            # load stepping (continuation in gravity) for large deflections: each static solve
            # starts from the previous equilibrium
            n_load = _get(sol, "load_steps", "solver", 1, kind=int, positive=True)
            g_full = model.gravity.clone()
            x, t_solve, total_its = x0, 0.0, 0
            for k in range(1, n_load + 1):
                model.gravity = g_full * (k / n_load)
                final = k == n_load
                x, info = solve_static(model, x, hessian=hessian, linear_solver=linear,
                                       tol=_get(sol, "tol", "solver", 1e-9) if final else 1e-6,
                                       max_iters=_get(sol, "max_iters", "solver", 50, kind=int), continuation=True)
                t_solve += info.seconds
                total_its += info.iterations
            info.seconds, info.iterations = t_solve, total_its
            tip = float(-(x[:, 2] - x0[:, 2])[x0[:, 0] >= x0[:, 0].max() - 1e-12].mean())
            d = _get(mat, "young", "material", 1e5) * float(t) ** 3 / (12 * (1 - _get(mat, "poisson", "material", 0.3) ** 2))
            q = model.mass.sum().item() * 9.81 / _area(x0, faces)
            length = float(x0[:, 0].max() - x0[:, 0].min() - (x0[:, 0].unique()[1] - x0[:, 0].unique()[0]))
            kirchhoff = q * length**4 / (8 * d)
            stats["steps"].append(_info_dict(info, thickness=float(t), tip_deflection=tip,
                                             kirchhoff_tip=kirchhoff, ratio=tip / kirchhoff))
            _write_obj(os.path.join(out_dir, "frames", f"beam_{j}.obj"), x, faces)
            shown.append((x, faces))
        _snapshot(os.path.join(out_dir, "snapshot.png"), shown)
    else:
        raise ValueError(f"config key 'scene.kind' must be 'dynamic', 'robot' or 'static', got {kind!r}")
    with open(os.path.join(out_dir, "stats.json"), "w") as f:
        json.dump(stats, f, indent=1, default=str)
    return stats


def _mean_edge(x, faces):
    p = x[faces]
    return torch.cat([(p[:, i] - p[:, (i + 1) % 3]).norm(dim=-1) for i in range(3)]).mean()


def _area(x, faces):
    p = x[faces]
    return float(0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1).sum())


def _info_dict(info, **extra) -> dict:
    d = {"converged": info.converged, "iterations": info.iterations, "residual": info.residual,
         "energy": info.energy, "energies": info.energies, "seconds": info.seconds,
         "line_search_failures": info.line_search_failures, "message": info.message,
         "energy_monotone": all(b <= a + 1e-12 * max(abs(a), 1.0) for a, b in zip(info.energy_history, info.energy_history[1:]))}
    d.update(extra)
    return d


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description="Run a torchbend cloth scene from a YAML config.")
    p.add_argument("config", help="path to a YAML scene config, e.g. configs/cloth_sphere.yaml")
    p.add_argument("--out", help="output directory (default runs/<config name>)")
    p.add_argument("--steps", type=int, help="override solver.steps (dynamic scenes)")
    p.add_argument("--resolution", type=int, nargs=2, metavar=("NX", "NY"), help="override mesh.nx, mesh.ny")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    cfg = load_config(a.config)
    out = a.out or os.path.join("runs", os.path.splitext(os.path.basename(a.config))[0])
    t0 = time.perf_counter()
    stats = run_config(cfg, out, steps=a.steps, resolution=tuple(a.resolution) if a.resolution else None,
                       progress=not a.no_progress)
    its = [s["iterations"] for s in stats["steps"]]
    print(f"{len(its)} solves, Newton iterations mean {sum(its) / max(len(its), 1):.1f} max {max(its, default=0)}, "
          f"all converged: {all(s['converged'] for s in stats['steps'])}, {time.perf_counter() - t0:.1f} s -> {out}")
    if "pin_error" in stats:
        print(f"robot-held vertices vs forward kinematics: max error {max(stats['pin_error'], default=0.0):.2e} m")
    if "max_penetration" in stats:
        print(f"max penetration {stats['max_penetration']:.2e} m (mean edge {stats['edge_length']:.3e} m)")
    for s in stats["steps"]:
        if "ratio" in s:
            print(f"thickness {s['thickness']:.1e} m: tip {s['tip_deflection']:.4e} m, Kirchhoff {s['kirchhoff_tip']:.4e} m, "
                  f"ratio {s['ratio']:.3f}, {s['iterations']} Newton iterations")


if __name__ == "__main__":
    main()
