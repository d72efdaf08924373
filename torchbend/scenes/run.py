"""Run a cloth scene from a YAML config: ``python -m torchbend.scenes configs/cloth_sphere.yaml``.

Writes into the output directory (``--out``, default ``runs/<config name>``):
``frames/frame_XXXX.obj`` (meshio), ``snapshot.png`` (matplotlib) and ``stats.json`` (per step:
Newton iterations, residual, energy per term, seconds).  Three scene kinds:

* ``dynamic`` (e.g. ``cloth_sphere``): implicit Euler steps of a cloth falling onto colliders;
* ``robot`` (e.g. ``robot_fold``): implicit Euler steps of a cloth held by a URDF robot following
  joint keyframes (``robot`` section, see :func:`torchbend.scenes.config.parse_robot`); ``stats.json``
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
import os
import time

import torch

from ..energies import Capsule, Sphere
from ..robot import trajectory
from ..sim import ClothState, implicit_euler_step, solve_static
from .config import build_robot_scene, build_scene, get_key, load_config

__all__ = ["run_config", "main"]


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
    every = get_key(cfg.get("output") or {}, "every", "output", 1, kind=int, positive=True)
    stats = {"config": cfg, "kind": kind, "steps": []}
    if kind in ("dynamic", "robot"):

        if kind == "robot":
            scene, x0, faces, keyframes = build_robot_scene(cfg, resolution=resolution)
            model = scene.model
            stats["pin_error"] = []
        else:
            model, x0, faces = build_scene(cfg, resolution=resolution)
        dt = get_key(sol, "dt", "solver", 1 / 60, positive=True)
        n_steps = steps if steps is not None else get_key(sol, "steps", "solver", 60, kind=int, positive=True)
        kw = dict(hessian=hessian, linear_solver=linear, tol=get_key(sol, "tol", "solver", 1e-6),
                  max_iters=get_key(sol, "max_iters", "solver", 30, kind=int))
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
            n_load = get_key(sol, "load_steps", "solver", 1, kind=int, positive=True)
            g_full = model.gravity.clone()
            x, t_solve, total_its = x0, 0.0, 0
            for k in range(1, n_load + 1):
                model.gravity = g_full * (k / n_load)
                final = k == n_load
                x, info = solve_static(model, x, hessian=hessian, linear_solver=linear,
                                       tol=get_key(sol, "tol", "solver", 1e-9) if final else 1e-6,
                                       max_iters=get_key(sol, "max_iters", "solver", 50, kind=int), continuation=True)
                t_solve += info.seconds
                total_its += info.iterations
            info.seconds, info.iterations = t_solve, total_its
            tip = float(-(x[:, 2] - x0[:, 2])[x0[:, 0] >= x0[:, 0].max() - 1e-12].mean())
            d = get_key(mat, "young", "material", 1e5) * float(t) ** 3 / (12 * (1 - get_key(mat, "poisson", "material", 0.3) ** 2))
            q = model.mass.sum().item() * float(model.gravity.norm()) / _area(x0, faces)  # load per area [Pa]
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
