"""Solver-level speed/accuracy trade: Hessian options on the paper's scenes.

    python benchmarks/bm_solver.py                          # drape 11..41, beams at 3 resolutions
    python benchmarks/bm_solver.py --drape 11 21 41 81 --steps 60
    python benchmarks/bm_solver.py --drape --split-beams --beams --sweep full   # the acceptance sweep table only

Drape (configs/cloth_sphere.yaml): per resolution, Hessian option (exact, clamp, abs,
gauss_newton) and linear solver (direct, cg): mean/max Newton iterations per step, seconds per step,
final energy, max penetration.  Beams (configs/beams.yaml): tip deflection and its ratio to Kirchhoff
plate theory per thickness and resolution, with Newton iterations.

Time split (the paper's Table 1 reports the bending share: 4-6 % of the total time on the cloth-sphere,
9-12 % on the beams): ``bend %`` is every call into the bending energy (energy, gradient, HVP, Hessian blocks
and their assembly: the paper's "bending force evaluation and stiffness matrix assembly"), ``mem %`` every
call into the membrane energy; the rest of a step is gravity, the colliders, inertia, the scatter of the
free Hessian and the linear solve.  Measured through the public API: the scene's energies are replaced by
subclasses of :class:`~torchbend.BendingEnergy` and :class:`~torchbend.MembraneEnergy` with the same
parameters whose public methods time themselves (nested calls counted once).  No assertions on time.

Sweep (``--sweep full|corners``): the cantilever strips of ``tests/test_solver_sweep.py`` (Y t, t,
resolution, triangulation pattern) for every Hessian option and linear solver with default solver options:
converged, Newton iterations, seconds, and the relative displacement error against that test's dense
reference (run from the repository root: it imports the test module).
"""
from __future__ import annotations

import argparse
import os
import time

import torch
from common import machine

from torchbend import BendingEnergy, ClothModel, ClothState, MembraneEnergy, implicit_euler_step, solve_static
from torchbend.scenes.config import build_scene, load_config
from torchbend.scenes.run import run_config

CONFIGS = os.path.join(os.path.dirname(__file__), "..", "configs")


class Stopwatch:
    """Seconds spent inside ``with watch:`` blocks; a block nested in another of the same watch counts once."""

    def __init__(self):
        self.seconds, self._depth, self._t0 = 0.0, 0, 0.0

    def __enter__(self):
        if self._depth == 0:
            self._t0 = time.perf_counter()
        self._depth += 1

    def __exit__(self, *exc):
        self._depth -= 1
        if self._depth == 0:
            self.seconds += time.perf_counter() - self._t0


def _timed(cls, methods):
    """A subclass of the energy class ``cls`` whose ``methods`` run inside ``self.watch`` (a :class:`Stopwatch`)."""

    def timing(name):
        def method(self, *args, **kwargs):
            with self.watch:
                return getattr(super(sub, self), name)(*args, **kwargs)

        method.__name__ = name
        return method

    sub = type(f"Timed{cls.__name__}", (cls,), {name: timing(name) for name in methods})
    return sub


TimedBending = _timed(BendingEnergy, ("forward", "gradient", "hvp", "hessian", "hinge_hessians"))
TimedMembrane = _timed(MembraneEnergy, ("forward", "gradient", "hvp", "hessian", "element_hessians"))


class TimeShares:
    """The shares of a solve's time spent in the bending and membrane energies of a model (module docstring):
    :meth:`timed` gives the model with its energies replaced by timed copies (same parameters)."""

    GROUPS = ("bend", "mem")

    def __init__(self):
        self.watches = {g: Stopwatch() for g in self.GROUPS}

    def timed(self, model: ClothModel) -> ClothModel:
        rest, b, m = model.rest_positions, model.bending, model.membrane
        if b is not None:
            model.bending = TimedBending(model.topology, rest, model=b.model, stiffness=b.stiffness,
                                         rest_angles=b.rest_angles, damping=b.damping, backend=b.backend,
                                         check_finite=b.check_finite)
            model.bending.watch = self.watches["bend"]
        if m is not None:
            model.membrane = TimedMembrane(model.topology, rest, model=m.model, young=m.young, poisson=m.poisson,
                                           thickness=m.thickness, backend=m.backend, check_finite=m.check_finite)
            model.membrane.watch = self.watches["mem"]
        return model

    def percent(self, total: float) -> str:
        return " ".join(f"{100 * self.watches[g].seconds / total:5.1f}" for g in self.GROUPS)


def drape_run(n: int, hessian: str, steps: int, linear_solver: str = "direct") -> dict:
    """``steps`` implicit Euler steps of the drape at ``n x n``: Newton iterations per step (mean, max), seconds
    per step, the time shares (:class:`TimeShares`), the final potential [J], the penetration per edge length,
    and whether every step converged."""
    cfg = load_config(os.path.join(CONFIGS, "cloth_sphere.yaml"))
    model, x0, _ = build_scene(cfg, resolution=(n, n))
    shares = TimeShares()
    model = shares.timed(model)
    state = ClothState(x0, torch.zeros_like(x0))
    its, secs, ok = [], [], True
    for _ in range(steps):
        t0 = time.perf_counter()
        state, info = implicit_euler_step(model, state, cfg["solver"]["dt"], projection=hessian,
                                          linear_solver=linear_solver, max_iters=cfg["solver"]["max_iters"])
        secs.append(time.perf_counter() - t0)
        its.append(info.iterations)
        ok &= info.converged
    pen = float(model.colliders[0].depth(state.x).max())
    return {"mesh": f"{n}x{n}", "hessian": hessian, "linear": linear_solver, "its": sum(its) / len(its),
            "max_its": max(its), "seconds": sum(secs) / len(secs), "shares": shares.percent(sum(secs)),
            "energy": float(model.potential(state.x)), "penetration": pen / (1.0 / (n - 1)), "converged": ok}


def drape(n: int, hessian: str, steps: int, linear_solver: str = "direct") -> str:
    """One row of the drape table (:func:`drape_run`)."""
    r = drape_run(n, hessian, steps, linear_solver)
    return (f"{r['mesh']:>7s} {hessian:>13s} {linear_solver:>6s} {r['its']:8.2f} {r['max_its']:5d} "
            f"{r['seconds'] * 1e3:10.1f}ms {r['shares']} "
            f"{r['energy']:13.6e} {r['penetration']:12.2e}  {'yes' if r['converged'] else 'NO'}")


def beam(nx: int, ny: int, thickness: float, hessian: str, linear_solver: str, time_limit: float = 60.0) -> str:
    """One cantilever of configs/beams.yaml solved with default solver options (tolerance and
    globalisation as a user gets them), stopped after ``time_limit`` seconds."""
    cfg = load_config(os.path.join(CONFIGS, "beams.yaml"))
    model, x0, _ = build_scene(cfg, thickness=thickness, resolution=(nx, ny))
    shares = TimeShares()
    model = shares.timed(model)
    t0 = time.perf_counter()
    _, info = solve_static(model, x0, projection=hessian, linear_solver=linear_solver, time_limit=time_limit)
    secs = time.perf_counter() - t0
    return (f"{nx:>3d}x{ny:<2d} t={thickness:.1e} {hessian:>13s} {linear_solver:>6s} {info.iterations:5d} "
            f"{secs:9.2f}s {shares.percent(secs)}  {'yes' if info.converged else 'NO: ' + info.stop_reason}")


def sweep(cases: str) -> None:
    """The table of the solver acceptance sweep (module docstring); ``cases``: ``"full"`` or ``"corners"``."""
    import sys

    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from tests import test_solver_sweep as sw

    print(f"\nsweep: cantilever strips ({cases}), default solver options; error = relative displacement error "
          "against the dense autograd reference")
    print(f"{'Y t':>6s} {'t':>6s} {'mesh':>5s} {'pattern':>7s} {'hessian':>13s} {'linear':>6s} {'its':>5s} "
          f"{'seconds':>8s} {'error':>8s}  converged")
    total = ok = 0
    for yt, t, res, pattern in (sw.FULL if cases == "full" else sw.CORNERS):
        model, rest, _ = sw.scene(yt, t, *res, pattern)
        x_ref = sw.reference(yt, t, *res, pattern)
        for hessian in sw.HESSIANS:
            for lin in sw.SOLVERS:
                t0 = time.perf_counter()
                x, info = solve_static(model, rest, projection=hessian, linear_solver=lin)
                secs = time.perf_counter() - t0
                err = float((x - x_ref).norm() / (x_ref - rest).norm())
                good = info.converged and err <= 1e-6
                total, ok = total + 1, ok + good
                print(f"{yt:6.0e} {t:6.0e} {res[0]:>2d}x{res[1]:<2d} {pattern:>7s} {hessian:>13s} {lin:>6s} "
                      f"{info.iterations:5d} {secs:8.2f} {err:8.1e}  {'yes' if info.converged else 'NO'}"
                      f"{'' if good else '  <- fails the acceptance'}", flush=True)
    print(f"{ok} of {total} solves converged within 1e-6 of the reference")


def drape_table(a) -> None:
    print(f"\ndrape: square cloth falling onto a sphere, {a.steps} implicit Euler steps of 0.005 s")
    print(f"{'mesh':>7s} {'hessian':>13s} {'linear':>6s} {'its/step':>8s} {'max':>5s} {'s/step':>12s} "
          f"{'bend%':>5s} {'mem %':>5s} {'final energy':>13s} {'pen./edge':>12s}  converged")
    for n in a.drape:
        for h in a.hessians:
            for lin in a.linear:
                print(drape(n, h, a.steps, lin), flush=True)


def split_table(a) -> None:
    cfg = load_config(os.path.join(CONFIGS, "beams.yaml"))
    print("\nbeams: static equilibrium per option, default solver options (time split)")
    print(f"{'mesh':>6s} {'thickness':>9s} {'hessian':>13s} {'linear':>6s} {'its':>5s} {'seconds':>10s} "
          f"{'bend%':>5s} {'mem %':>5s}  converged")
    for res in a.split_beams:
        nx, ny = (int(v) for v in res.split("x"))
        for t in cfg["material"]["thicknesses"]:
            for h in a.hessians:
                for lin in a.linear:
                    print(beam(nx, ny, float(t), h, lin, a.time_limit), flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--drape", type=int, nargs="*", default=[11, 21, 41])
    p.add_argument("--steps", type=int, default=120)
    p.add_argument("--hessians", nargs="+", default=["exact", "clamp", "abs", "gauss_newton"])
    p.add_argument("--linear", nargs="+", default=["direct", "cg"], help="linear solvers of the drape and beam rows")
    p.add_argument("--beams", type=str, nargs="*", default=["61x6", "131x6", "196x7"])
    p.add_argument("--split-beams", type=str, nargs="*", default=["61x6"],
                   help="beam resolutions of the per-option time split table (default solver options)")
    p.add_argument("--time-limit", type=float, default=60.0, help="seconds per beam solve of the time split table")
    p.add_argument("--sweep", choices=["full", "corners"], default=None,
                   help="the acceptance sweep table of tests/test_solver_sweep.py")
    a = p.parse_args(argv)
    print("machine:", machine())
    if a.sweep:
        sweep(a.sweep)
    if a.drape:
        drape_table(a)
    if a.split_beams:
        split_table(a)
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
