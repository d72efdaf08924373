"""Cost of an implicit-Euler step against the mesh size: the draped square cloth of configs/cloth_sphere.yaml
(1 m x 1 m, StVK membrane, tan bending, a sphere collider) at 21x21 to 161x161 vertices, with the default
options (exact Hessian, direct solver) and each direct factorisation.

    python benchmarks/bm_scale.py                          # 21, 41, 81, 161; auto, auto:noreuse, lu (~8 minutes)
    python benchmarks/bm_scale.py --sizes 41 81 --solvers ldlt auto:noreuse

Each size is warmed by ``--warm`` steps (the cloth on the sphere; the state is cached under /tmp); then each
solver runs ``--lead`` untimed steps (as in a running simulation: the pattern analysed, a factorisation at hand
for ``reuse_factorization``) and ``--steps`` consecutive timed ones.  Printed per size and solver: vertices,
Newton iterations per step, mean and slowest seconds per step, seconds per Newton iteration, the share of the
linear solves (``SolveInfo.linear_seconds``: factorisations, solves, CG on a reused factorisation), and the
growth exponents ``log(t_161 / t_41) / log(V_161 / V_41)`` of the mean step (issue targets: a step of 161x161
at most 2 s on one thread, growth at most V^1.1).  No assertions on time.
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


def make_solver(label: str) -> tb.LinearSolver:
    """``"auto"``, ``"lu"``, ``"ldlt"``, optionally ``":noreuse"`` (``reuse_factorization=False``)."""
    fac, _, flag = label.partition(":")
    if flag not in ("", "noreuse"):
        raise SystemExit(f"unknown solver label {label!r} (e.g. auto, lu, auto:noreuse)")
    return tb.LinearSolver("direct", factorization=fac, reuse_factorization=False if flag else "auto")


def time_steps(model, state, dt, label: str, lead: int, steps: int):
    """``lead`` untimed steps from ``state`` (a running simulation: the pattern analysed, a factorisation
    at hand), then ``steps`` consecutive timed steps; ``(mean s/step, max s/step, mean Newton iterations,
    linear share, all converged)``."""
    solver = make_solver(label)
    for _ in range(lead):
        state, _info = tb.implicit_euler_step(model, state, dt, linear_solver=solver)
    times, iters, lin, conv = [], 0, 0.0, True
    for _ in range(steps):
        t0 = time.perf_counter()
        state, info = tb.implicit_euler_step(model, state, dt, linear_solver=solver)
        times.append(time.perf_counter() - t0)
        iters += info.iterations
        lin += info.linear_seconds
        conv = conv and info.converged
    return sum(times) / steps, max(times), iters / steps, lin / sum(times), conv


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[21, 41, 81, 161])
    p.add_argument("--solvers", nargs="+", default=["auto", "auto:noreuse", "lu"],
                   help="factorizations (auto, ldlt, lu), ':noreuse' for reuse_factorization=False")
    p.add_argument("--warm", type=int, default=20, help="steps before the timed ones (the cloth on the sphere)")
    p.add_argument("--lead", type=int, default=1, help="untimed steps of each solver before the timed ones")
    p.add_argument("--steps", type=int, default=5, help="consecutive timed steps")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    from torchbend.sim import pardiso

    print("machine:", machine())
    print(f"MKL PARDISO: {'yes' if pardiso.available() else 'no (auto = lu)'}; warm {a.warm} steps, then per solver "
          f"{a.lead} untimed and {a.steps} timed consecutive steps")
    print(f"{'size':>8s} {'V':>7s} {'solver':>13s} {'Newton':>6s} {'s/step':>8s} {'max':>8s} {'s/iter':>8s} {'linear':>7s}")
    rows: dict[str, dict[int, tuple]] = {f: {} for f in a.solvers}
    for n in a.sizes:
        model, state, dt = warm_state(n, a.warm)
        for label in a.solvers:
            sec, worst, its, share, conv = time_steps(model, state, dt, label, a.lead, a.steps)
            per = sec / max(its, 1)
            rows[label][n] = (model.vertex_count, sec, per)
            flag = "" if conv else "  NOT all converged"
            print(f"{n:4d}x{n:<3d} {model.vertex_count:7d} {label:>13s} {its:6.1f} {sec:8.3f} {worst:8.3f} {per:8.3f} "
                  f"{share:6.0%}{flag}", flush=True)
    for label, r in rows.items():
        sizes = sorted(r)
        if len(sizes) < 2:
            continue
        lo, hi = (41 if 41 in r else sizes[0]), sizes[-1]
        (v0, s0, i0), (v1, s1, i1) = r[lo], r[hi]
        print(f"growth {label:>13s} {lo}x{lo} -> {hi}x{hi}: per step V^{math.log(s1 / s0) / math.log(v1 / v0):.2f}, "
              f"per Newton iteration V^{math.log(i1 / i0) / math.log(v1 / v0):.2f}")


if __name__ == "__main__":
    main()
