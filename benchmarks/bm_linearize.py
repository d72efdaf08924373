"""Linearise once, apply many (issue: the whole cloth model fast, item 3): on the draped cloth of
configs/cloth_sphere.yaml (StVK membrane, tan bending, the sphere), at one state, one thread:

- ``hvp``: the matrix-free ``model.hvp(x, v, projection)`` per product;
- ``linearize``: ``model.linearize(x, projection)`` once (evaluate, project, assemble);
- ``op @ v``: a product of the linearised operator (tensor in, tensor out);
- ``csr @ v``: SciPy's CSR matvec of the same matrix (NumPy in, NumPy out), the floor of ``op @ v``;
- break-even: the number of products after which linearising costs less than the HVPs;
- two CG Newtons a user writes on ``linearize`` against ``solve_static(linear_solver="cg")`` from the same start
  (a cantilever of configs/beams.yaml: the free drape on a frictionless sphere has no static equilibrium): the
  plain one (clamped Hessian, SciPy CG, backtracking), linear near the answer, and a damped one (the exact Hessian
  with a Levenberg-Marquardt shift, SciPy CG to a forcing term preconditioned by ``op.preconditioner()``, the step
  bound, Armijo), as the solver globalises.

    python benchmarks/bm_linearize.py                 # 21, 41, 81 vertices a side
    python benchmarks/bm_linearize.py --sizes 41 --projections clamp

No assertions on time (tests/test_linearize.py checks the results)."""
from __future__ import annotations

import argparse
import os
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from common import bench, machine

import torchbend as tb
from torchbend.scenes.config import build_scene, load_config

CONFIG = os.path.join(os.path.dirname(__file__), "..", "configs", "cloth_sphere.yaml")
BEAMS = os.path.join(os.path.dirname(__file__), "..", "configs", "beams.yaml")


def cg_newton(model, x0, max_iters: int = 200):
    """A user's Newton loop on linearize (the test's, tests/test_linearize.py): returns (x, iterations)."""
    x, free = x0.clone(), ~model.pinned
    scale = float(model.external_force(x0.dtype).norm())
    for it in range(max_iters):
        g = model.gradient(x)[free].reshape(-1).numpy()
        if np.linalg.norm(g) <= 1e-8 * scale:
            return x, it
        op = model.linearize(x, "clamp")
        p, _ = spla.cg(op.as_linear_operator(free=True), -g, rtol=1e-8, maxiter=1000)
        step = torch.zeros_like(x)
        step[free] = torch.as_tensor(p).reshape(-1, 3)
        alpha = min(1.0, model.max_step(x, step))
        e0 = model.potential(x)
        while model.potential(x + alpha * step) > e0 + 1e-4 * alpha * float(g @ p) and alpha > 1e-10:
            alpha *= 0.5
        x = x + alpha * step
        if float((alpha * step).norm()) <= 1e-9 * float((x - x0).norm()):  # the residual's round-off floor
            return x, it + 1
    return x, max_iters


def damped_newton(model, x0, max_iters: int = 200):
    """A damped Newton a user writes on linearize: the exact Hessian plus a Levenberg-Marquardt shift (x10 while a
    step is not a descent direction or fails Armijo's test, /10 after an accepted one), SciPy CG to the forcing term
    min(1e-2, sqrt(|g| / F)) preconditioned by the operator's (the solver's) incomplete factorisation, the model's
    step bound; returns (x, iterations)."""
    x, free = x0.clone(), ~model.pinned
    scale = float(model.external_force(x0.dtype).norm())
    lam, e = 0.0, float(model.potential(x))
    for it in range(max_iters):
        g = model.gradient(x)[free].reshape(-1).numpy()
        gn = float(np.linalg.norm(g))
        if gn <= 1e-8 * scale:
            return x, it
        op = model.linearize(x, "exact")
        A, pre = op.free, op.preconditioner()  # the solver's incomplete L |D| L^T, once per iteration
        floor = 1e-8 * float(abs(A.diagonal()).max())
        while True:
            M = A + lam * sp.identity(A.shape[0], format="csr") if lam else A
            p, _ = spla.cg(M, -g, rtol=min(1e-2, (gn / scale) ** 0.5), maxiter=2000, M=pre)
            slope = float(g @ p)
            if slope < 0:
                step = torch.zeros_like(x)
                step[free] = torch.as_tensor(p).reshape(-1, 3)
                alpha = min(1.0, model.max_step(x, step))
                e1 = float(model.potential(x + alpha * step))
                if e1 <= e + 1e-4 * alpha * slope:
                    x, e = x + alpha * step, e1
                    lam = lam / 10 if lam > floor else 0.0
                    break
            lam = max(10 * lam, floor)
    return x, max_iters


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[21, 41, 81])
    p.add_argument("--projections", nargs="+", default=["exact", "clamp"])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--beam-thickness", type=float, default=5e-3, help="of the CG Newton comparison [m]")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    print(machine())
    print(f"{'size':>8s} {'V':>6s} {'projection':>10s} {'hvp ms':>8s} {'linearize ms':>12s} {'op@v ms':>8s} "
          f"{'csr@v ms':>8s} {'op/csr':>6s} {'break-even':>10s}")
    cfg = load_config(CONFIG)
    for n in a.sizes:
        model, x0, _ = build_scene(cfg, resolution=(n, n))
        gen = torch.Generator().manual_seed(0)
        x = x0 + 1e-3 * torch.randn(x0.shape, generator=gen, dtype=x0.dtype)  # a deformed state above the sphere
        v = torch.randn(x.shape, generator=gen, dtype=x.dtype)
        for proj in a.projections:
            t_hvp = bench(lambda m=model, y=x, d=v, proj=proj: m.hvp(y, d, proj))["median"]
            t_lin = bench(lambda m=model, y=x, proj=proj: m.linearize(y, proj))["median"]
            op = model.linearize(x, proj)
            vn = v.reshape(-1).numpy()
            t_op = bench(lambda op=op, d=v: op @ d, budget=0.3, max_repeat=20000)["median"]  # microseconds: many calls
            t_csr = bench(lambda op=op, d=vn: op.matrix @ d, budget=0.3, max_repeat=20000)["median"]
            even = t_lin / max(t_hvp - t_op, 1e-12)
            print(f"{n:>4d}x{n:<3d} {len(x):6d} {proj:>10s} {1e3 * t_hvp:8.2f} {1e3 * t_lin:12.2f} {1e3 * t_op:8.3f} "
                  f"{1e3 * t_csr:8.3f} {t_op / t_csr:6.2f} {even:10.1f}")
    model, x0, _ = build_scene(load_config(BEAMS), thickness=a.beam_thickness, resolution=(61, 6))
    t0 = time.perf_counter()
    x_ref, info = tb.solve_static(model, x0, linear_solver="cg")
    t_ref = time.perf_counter() - t0
    print(f"\nstatic cantilever (configs/beams.yaml, 61x6, t={a.beam_thickness:g} m) from rest: "
          f"solve_static(linear_solver='cg') {info.iterations} Newton its {t_ref:.2f} s (converged {info.converged})")
    for name, loop in (("plain (clamped, backtracking)", cg_newton), ("damped (exact, Levenberg-Marquardt)", damped_newton)):
        t0 = time.perf_counter()
        x_user, its = loop(model, x0)
        t_user = time.perf_counter() - t0
        err = float((x_user - x_ref).norm() / (x_ref - x0).norm())
        print(f"  a CG Newton on linearize, {name}: {its} its {t_user:.2f} s (ratio {t_user / t_ref:.2f}), "
              f"relative difference of the displacements {err:.1e}")


if __name__ == "__main__":
    main()
