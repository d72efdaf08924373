"""Cost of an implicit-Euler step against the mesh size: the draped square cloth of configs/cloth_sphere.yaml
(1 m x 1 m, StVK membrane, tan bending, a sphere collider) at 21x21 to 161x161 vertices, with the default
options (exact Hessian, direct solver) and each direct factorisation.

    python benchmarks/bm_scale.py                          # 21, 41, 81, 161; 'auto' and 'lu' (~4 minutes)
    python benchmarks/bm_scale.py --sizes 41 81 --factorizations ldlt

Each size is warmed by ``--warm`` steps (the cloth on the sphere; the state is cached under /tmp), then the
next step is timed ``--repeats`` times from that state (the fastest is printed: the machine may be shared).
Printed per size: vertices, Newton iterations, seconds per step and per Newton iteration, the share of
the linear solves (``SolveInfo.linear_seconds``: factorisation and solve), and the growth exponents
``log(t_161 / t_41) / log(V_161 / V_41)`` (issue targets: a step of 161x161 at most 2 s on one thread, growth
at most V^1.1).  No assertions on time.
"""
from __future__ import annotations

import argparse
import hashlib
import math
import os
import time

import torch
from common import machine

import torchbend as tb
from torchbend.scenes.config import build_scene, load_config

CONFIG = os.path.join(os.path.dirname(__file__), "..", "configs", "cloth_sphere.yaml")


def warm_state(n: int, warm: int):
    """The scene at ``n x n``, its state after ``warm`` steps (default options; cached in /tmp) and ``dt``."""
    cfg = load_config(CONFIG)
    model, x0, _ = build_scene(cfg, resolution=(n, n))
    dt = cfg["solver"]["dt"]
    key = hashlib.sha1(open(CONFIG, "rb").read()).hexdigest()[:10]  # a changed scene is warmed again
    path = f"/tmp/torchbend_bm_scale_{n}_{warm}_{key}.pt"
    if os.path.exists(path):
        x, v = torch.load(path)
        return model, tb.ClothState(x, v), dt
    state = tb.ClothState(x0, torch.zeros_like(x0))
    for _ in range(warm):
        state, _info = tb.implicit_euler_step(model, state, dt)
    torch.save((state.x, state.v), path)
    return model, state, dt


def time_step(model, state, dt, factorization: str, repeats: int):
    solver = tb.LinearSolver("direct", factorization=factorization)
    best, info = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        _s, info = tb.implicit_euler_step(model, state, dt, linear_solver=solver)
        best = min(best, time.perf_counter() - t0)
    return best, info


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[21, 41, 81, 161])
    p.add_argument("--factorizations", nargs="+", default=["auto", "lu"])
    p.add_argument("--warm", type=int, default=20, help="steps before the timed one (the cloth on the sphere)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    from torchbend.sim import pardiso

    print("machine:", machine())
    print(f"MKL PARDISO: {'yes' if pardiso.available() else 'no (auto = lu)'}; warm {a.warm} steps, best of {a.repeats}")
    print(f"{'size':>8s} {'V':>7s} {'factorization':>14s} {'Newton':>6s} {'s/step':>8s} {'s/iter':>8s} {'linear':>7s}")
    rows: dict[str, dict[int, tuple]] = {f: {} for f in a.factorizations}
    for n in a.sizes:
        model, state, dt = warm_state(n, a.warm)
        for fac in a.factorizations:
            sec, info = time_step(model, state, dt, fac, a.repeats)
            assert info is not None
            per = sec / max(info.iterations, 1)
            rows[fac][n] = (model.vertex_count, sec, per)
            flag = "" if info.converged else f"  NOT converged ({info.stop_reason})"
            print(f"{n:4d}x{n:<3d} {model.vertex_count:7d} {fac:>14s} {info.iterations:6d} {sec:8.3f} {per:8.3f} "
                  f"{info.linear_seconds / max(info.seconds, 1e-12):6.0%}{flag}", flush=True)
    for fac, r in rows.items():
        sizes = sorted(r)
        if len(sizes) < 2:
            continue
        lo, hi = (41 if 41 in r else sizes[0]), sizes[-1]
        (v0, s0, i0), (v1, s1, i1) = r[lo], r[hi]
        print(f"growth {fac:>5s} {lo}x{lo} -> {hi}x{hi}: per step V^{math.log(s1 / s0) / math.log(v1 / v0):.2f}, "
              f"per Newton iteration V^{math.log(i1 / i0) / math.log(v1 / v0):.2f}")


if __name__ == "__main__":
    main()
