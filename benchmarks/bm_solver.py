"""Solver-level speed/accuracy trade: Hessian options on the paper's scenes.

    python benchmarks/bm_solver.py                          # drape 11..41, beams at 3 resolutions
    python benchmarks/bm_solver.py --drape 11 21 41 81 --steps 60

Drape (configs/cloth_sphere.yaml): per resolution and Hessian option (exact, clamp, abs,
gauss_newton): mean/max Newton iterations per step, seconds per step, final energy, max penetration.
Beams (configs/beams.yaml): tip deflection and its ratio to Kirchhoff plate theory per thickness
and resolution, with Newton iterations.  No assertions on time.
"""
from __future__ import annotations

import argparse
import os
import time

import torch
from common import machine

from torchbend import ClothState, implicit_euler_step
from torchbend.scenes.config import build_scene, load_config
from torchbend.scenes.run import run_config

CONFIGS = os.path.join(os.path.dirname(__file__), "..", "configs")


def drape(n: int, hessian: str, steps: int) -> str:
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    model, x0, _ = build_scene(cfg, resolution=(n, n))
    state = ClothState(x0, torch.zeros_like(x0))
    its, secs, ok = [], [], True
    for _ in range(steps):
        t0 = time.perf_counter()
        state, info = implicit_euler_step(model, state, cfg["solver"]["dt"], hessian=hessian,
                                          max_iters=cfg["solver"]["max_iters"])
        secs.append(time.perf_counter() - t0)
        its.append(info.iterations)
        ok &= info.converged
    pen = float(model.colliders[0].depth(state.x).max())
    energy = model.potential(state.x)
    return (f"{n:>3d}x{n:<3d} {hessian:>13s} {sum(its) / len(its):8.2f} {max(its):5d} {sum(secs) / len(secs) * 1e3:10.1f}ms "
            f"{energy:13.6e} {pen / (1.0 / (n - 1)):12.2e}  {'yes' if ok else 'NO'}")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--drape", type=int, nargs="*", default=[11, 21, 41])
    p.add_argument("--steps", type=int, default=120)
    p.add_argument("--hessians", nargs="+", default=["exact", "clamp", "abs", "gauss_newton"])
    p.add_argument("--beams", type=str, nargs="*", default=["61x6", "131x6", "196x7"])
    a = p.parse_args(argv)
    print("machine:", machine())
    if a.drape:
        print(f"\ndrape: square cloth falling onto a sphere, {a.steps} implicit Euler steps of 0.005 s")
        print(f"{'mesh':>7s} {'hessian':>13s} {'its/step':>8s} {'max':>5s} {'s/step':>12s} {'final energy':>13s} "
              f"{'pen./edge':>12s}  converged")
        for n in a.drape:
            for h in a.hessians:
                print(drape(n, h, a.steps), flush=True)
    if a.beams:
        print("\nbeams: cantilevers, static equilibrium (exact Hessian, direct solver)")
        cfg = load_config(os.path.join(CONFIGS, "beams.yaml"))
        for res in a.beams:
            nx, ny = (int(v) for v in res.split("x"))
            stats = run_config(cfg, os.path.join("runs", "bm_beams", res), resolution=(nx, ny), progress=False)
            for s in stats["steps"]:
                print(f"  {nx * ny:5d} vertices  t={s['thickness']:.1e} m  tip {s['tip_deflection']:.4e} m  "
                      f"Kirchhoff {s['kirchhoff_tip']:.4e} m  ratio {s['ratio']:.3f}  {s['iterations']:4d} Newton its  "
                      f"{s['seconds']:.2f} s  {'converged' if s['converged'] else 'NOT converged'}", flush=True)


if __name__ == "__main__":
    main()
