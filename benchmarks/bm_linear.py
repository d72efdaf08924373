"""Linear solvers of the Newton directions (torchbend/sim/linear.py): factorisations, CG preconditioners,
and whole solves with ``linear_solver="direct"`` vs ``"cg"``.

    python benchmarks/bm_linear.py                     # everything (about 5 minutes on 2 cores)
    python benchmarks/bm_linear.py --sections direct   # direct, cg, solve

Matrices: the free Hessian of the stiff strip (cantilever 20x4, Y = 1e9 Pa, t = 1 mm, as in
tests/test_solver.py) at rest and at its equilibrium, and of one implicit-Euler step (dt = 0.005 s, with
the inertia m/dt^2) of the cloth-sphere drape (configs/cloth_sphere.yaml) at 41x41 after ``--warm``
steps (the cloth on the sphere) and at 81x81 at the start.

* direct: SciPy's default ``splu`` (COLAMD, partial pivoting) as the solver used before, ``splu`` in
  symmetric mode (minimum degree on A + A^T, diagonal pivots), sparse Cholesky (cholespy), seconds for
  factorisation + solve (best of 3: the machine is shared); "PD" is what direct_solve reports.
* cg: per preconditioner, setup seconds, CG iterations and seconds to a relative residual of 1e-3
  (a typical Newton forcing term) and 1e-7; "-" = not reached within 5000 iterations.
* solve: whole Newton solves with each linear solver and preconditioner: the stiff strip's static
  equilibrium, and one drape step at 41x41 from the warm state; Newton iterations, CG iterations,
  seconds, and the ratio to the direct solver (the acceptance target is CG within 3x).
No assertions on time.
"""
from __future__ import annotations

import argparse
import os
import time
from typing import Any

import numpy as np
import scipy.sparse.linalg as spla
import torch
from common import machine

import torchbend as tb
from torchbend import ClothModel, ClothState, implicit_euler_step, solve_static
from torchbend.options import Projection
from torchbend.scenes.config import build_scene, load_config
from torchbend.sim import linear
from torchbend.sim.terms import InertiaTerm

CONFIGS = os.path.join(os.path.dirname(__file__), "..", "configs")
F64 = torch.float64


def stiff_strip(nx=20, ny=4, young=1e9, t=1e-3, nu=0.3, rho=1000.0, L=0.2, W=0.05):
    rest, faces = tb.scenes.grid(nx, ny, (L, W), dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=tb.stiffness_from_material(young, t, nu))
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=young, poisson=nu, thickness=t)
    columns = rest[:, 0].unique()
    pinned = rest[:, 0] <= columns[1] + 1e-12
    return ClothModel(faces, rest, bending=bend, membrane=mem, density=rho * t, pinned=pinned), rest


def drape_state(n: int, warm: int):
    """The drape scene at ``n x n`` and its state after ``warm`` steps (cached in /tmp)."""
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    model, x0, _ = build_scene(cfg, resolution=(n, n))
    state = ClothState(x0, torch.zeros_like(x0))
    if warm:
        path = f"/tmp/bm_linear_drape{n}_{warm}.pt"
        if os.path.exists(path):
            x, v = torch.load(path)
            state = ClothState(x, v)
        else:
            for _ in range(warm):
                state, _info = implicit_euler_step(model, state, cfg["solver"]["dt"], projection="gauss_newton")
            torch.save((state.x, state.v), path)
    return model, state, cfg["solver"]["dt"]


class FreeMatrix:
    """The free Hessian of ``model``'s potential (with a time step's inertia when ``ctx`` is one) as the solvers
    assemble it: ``free_hessian(x)`` (torch sparse CSR ``(nf, nf)``) through ``hessian_op``, the model's
    :class:`~torchbend.sim.linear.FreeHessian`."""

    def __init__(self, model, x, option, ctx=None):
        self.ctx = ctx or tb.StepContext()
        self.option = Projection.parse(option)
        self.terms = model.terms + ((InertiaTerm(model.mass),) if self.ctx.dynamic else ())
        self.hessian_op = linear.FreeHessian.for_model(model, (~model.pinned).to(x.device).repeat_interleave(3))

    def free_hessian(self, x):
        return self.hessian_op.assemble(x, self.terms, self.ctx, self.option)


def best_seconds(fn, repeats=3) -> tuple[float, Any]:
    """The fastest of ``repeats`` runs (the machine is shared: the minimum is the least disturbed) and the
    last result."""
    out, times = None, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def matrices(warm: int):
    mats = []
    model, rest = stiff_strip()
    for option in ("exact", "clamp"):
        phi = FreeMatrix(model, rest, option)
        mats.append((f"strip 20x4 stiff, rest, {option}", phi.hessian_op.to_scipy(phi.free_hessian(rest)), phi, rest))
    x, info = solve_static(model, rest, projection="exact")
    phi = FreeMatrix(model, x, "exact")
    mats.append((f"strip 20x4 stiff, equilibrium ({'converged' if info.converged else 'NOT converged'}), exact",
                 phi.hessian_op.to_scipy(phi.free_hessian(x)), phi, x))
    for n, w in ((41, warm), (81, 0)):
        model, state, dt = drape_state(n, w)
        x_hat = state.x + dt * state.v
        ctx = tb.StepContext.for_step(model.terms, state.x, state.v, dt)
        for option in ("exact", "gauss_newton"):
            phi = FreeMatrix(model, x_hat, option, ctx)
            where = f"step {w}" if w else "start"
            mats.append((f"drape {n}x{n} {where}, {option}", phi.hessian_op.to_scipy(phi.free_hessian(x_hat)), phi, x_hat))
    return mats


def direct_section(mats) -> None:
    print(f"\ndirect solves (seconds: factorisation + one solve; cholespy {'installed' if linear.has_cholespy() else 'ABSENT'})")
    print(f"{'matrix':52s} {'n':>6s} {'nnz':>8s} {'PD':>5s} {'splu COLAMD':>12s} {'splu symm.':>11s} {'cholesky':>10s} {'direct_solve':>13s}")
    for name, A, _phi, _x in mats:
        rng = np.random.default_rng(0)
        b = rng.standard_normal(A.shape[0])
        t_lu, _ = best_seconds(lambda A=A, b=b: spla.splu(A.tocsc()).solve(b))
        t_sym, _ = best_seconds(lambda A=A, b=b: linear.lu_solve(A, b)[0])
        t_chol, p = best_seconds(lambda A=A, b=b: linear.cholesky_solve(A, b))
        t_all, res = best_seconds(lambda A=A, b=b: linear.direct_solve(A, b))
        chol = f"{t_chol:10.4f}" if p is not None else "    not PD"
        print(f"{name:52s} {A.shape[0]:6d} {A.nnz:8d} {str(res.positive_definite):>5s} {t_lu:12.4f} {t_sym:11.4f} {chol} "
              f"{t_all:9.4f} {res.method:>3s}", flush=True)


def cg_section(mats) -> None:
    kinds = [linear.Preconditioner.BLOCK_JACOBI, linear.Preconditioner.ILU]
    if linear.has_pyamg():
        kinds.append(linear.Preconditioner.AMG)
    print("\nCG (torch, CPU) per preconditioner: setup [s]; iterations and seconds to rtol 1e-3 | 1e-7 "
          "(T: truncated at negative curvature)")
    for name, _A, phi, x in mats:
        At = phi.free_hessian(x)
        b = torch.randn(At.shape[0], dtype=F64, generator=torch.Generator().manual_seed(0))
        row = [f"{name:52s}"]
        for kind in kinds:
            t0 = time.perf_counter()
            M, used = linear.make_preconditioner(kind, At, phi.hessian_op)
            setup = time.perf_counter() - t0
            cells = []
            for tol in (1e-3, 1e-7):
                t0 = time.perf_counter()
                res = linear.pcg(lambda d, At=At: At @ d, b, M, tol=tol, maxiter=5000)
                sec = time.perf_counter() - t0
                flag = "T" if res.negative_curvature is not None else ""
                cells.append(f"{res.iterations:4d}{flag} {sec:6.3f}" if res.converged or flag else f"   - {sec:6.3f}")
            row.append(f"{used.value:>12s} {setup:6.3f} | {' | '.join(cells)}")
        print("\n    ".join(row), flush=True)


def solve_section(warm: int) -> None:
    configs = [("direct", None), ("cg", "auto"), ("cg", "block_jacobi"), ("cg", "ilu")]
    if linear.has_pyamg():
        configs.append(("cg", "amg"))
    print("\nwhole solves (seconds: best of 3; ratio to the direct solver)")
    model, rest = stiff_strip()
    cases = []
    for h in ("exact", "clamp"):
        # the default tol stalls at the round-off floor (50 iterations, see issue 16); tol 1e-7 converges
        cases.append((f"strip 20x4 stiff, static {h}, tol 1e-9",
                      lambda ls, h=h: solve_static(model, rest, projection=h, linear_solver=ls)))
        cases.append((f"strip 20x4 stiff, static {h}, tol 1e-7",
                      lambda ls, h=h: solve_static(model, rest, projection=h, linear_solver=ls, tol=1e-7)))
    dmodel, state, dt = drape_state(41, warm)
    for h in ("exact", "gauss_newton"):
        cases.append((f"drape 41x41 step {warm} -> {warm + 1}, {h}",
                      lambda ls, h=h: implicit_euler_step(dmodel, state, dt, projection=h, linear_solver=ls, max_iters=50)))
    for name, fn in cases:
        base = None
        for ls, pre in configs:
            solver = tb.LinearSolver(ls, preconditioner=pre or "auto")
            sec, (_, info) = best_seconds(lambda fn=fn, solver=solver: fn(solver))
            base = sec if base is None else base
            label = ls if pre is None else f"cg/{pre}"
            print(f"{name:40s} {label:16s} {'ok ' if info.converged else 'NO '} {info.iterations:3d} Newton "
                  f"{info.cg_iterations:6d} CG {sec:8.3f} s  x{sec / base:5.2f}", flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sections", nargs="+", default=["direct", "cg", "solve"])
    p.add_argument("--warm", type=int, default=20, help="drape steps before the measured 41x41 step")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads (default 1: on a shared machine, intra-op threads of tiny CG operations wait on each other)")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    print("machine:", machine())
    print(f"cholespy: {'yes' if linear.has_cholespy() else 'no'}, pyamg: {'yes' if linear.has_pyamg() else 'no'}")
    if {"direct", "cg"} & set(a.sections):
        mats = matrices(a.warm)
        if "direct" in a.sections:
            direct_section(mats)
        if "cg" in a.sections:
            cg_section(mats)
    if "solve" in a.sections:
        solve_section(a.warm)


if __name__ == "__main__":
    main()
