"""Self-contact cost per contact: torchbend's SelfContact against the IPC toolkit (``ipctk``) on the same scene.

A square grid folded onto itself: the lower half flat, the upper half 1 mm above it (shifted by a third of an
edge so every distance type occurs), ``dhat`` 2 mm: every vertex of one layer is in contact with the other.
For each: the contacts' barrier energy, gradient and PSD-projected Hessian (ipctk: ``NormalCollisions.build``
with its default broad phase, ``BarrierPotential`` with clamp projection; torchbend: the term's ``energy``,
``gradient`` and ``hessian(projection="clamp")``, which find their own pairs), one thread, best of
``--repeats``, and the microseconds per contact.  The ratio is given per pair (each code's time over its own count)
and in total (the same scene's work): ipctk counts a contact found by several stencils as one collision of that
weight, torchbend each stencil as a pair (about 1.45x as many on the half fold), so the per-pair ratio flatters
torchbend by that factor and the total is the like-for-like one.  Beside: the broad phase alone (the candidate pairs within
``dhat``), the step bound (``max_step``) of a step of 1 mm, and a Newton iteration's contact work (energy,
gradient and Hessian at a new iterate, the step bound of its step, and the energy at two trial points of its line
search).  Then the work the issue names alone (gradient, clamp-projected Hessian and its assembly of the pairs
found beforehand: ipctk's ``BarrierPotential.gradient`` and ``hessian`` of a built ``NormalCollisions``, torchbend's
``gradient`` and ``hessian`` at the positions whose pairs it kept).  Then a static solve per size: the upper layer, held at its corners, sags under its weight onto the
pinned lower one, and the contact term's time per Newton iteration of it (whatever its steps and line searches
asked for).

    python benchmarks/bm_contact.py                      # 20x20 and 50x50 grids
    python benchmarks/bm_contact.py --sizes 20 50 80 --repeats 3
    python benchmarks/bm_contact.py --scene half --sizes 50 --repeats 5   # the issue's grid folded in half
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import machine  # noqa: E402

import torchbend as tb  # noqa: E402
from torchbend.sim.self_contact import vertex_boxes  # noqa: E402
from torchbend.testing import call_times  # noqa: E402


def folded(n: int, size: float = 0.5):
    """Two layers of an ``n x n``-vertex grid ``size`` wide, 1 mm apart (one mesh of two components)."""
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=torch.float64)
    h = size / (n - 1)
    upper = rest + torch.tensor([h / 3, h / 5, 1e-3], dtype=torch.float64)
    x = torch.cat([rest, upper])
    f = torch.cat([faces, faces + rest.shape[0]])
    return x, f


def folded_in_half(n: int, size: float = 0.5):
    """One ``n x n``-vertex grid ``size`` wide folded in half onto itself (the issue's scene: 2,500 vertices at
    ``n = 50``): the rows beyond the middle turned over onto the others, 1 mm above them and shifted by a third of an
    edge along the crease (every distance type occurs; the crease's edges rise 1 mm)."""
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=torch.float64)
    h, mid = size / (n - 1), size / 2
    x = rest.clone()
    up = rest[:, 1] > mid
    x[up, 1] = 2 * mid - rest[up, 1]
    x[up, 2] = 1e-3
    x[up, 0] += h / 3
    return x, faces


SCENES = {"layers": folded, "half": folded_in_half}


def best(fn, repeats: int) -> float:
    return min(call_times(fn, repeats))


def run_torchbend(x, f, dhat, repeats):
    sc = tb.SelfContact(dhat=dhat, stiffness=1.0)
    tb.ClothModel(f, x, terms=[sc])  # binds the mesh
    ctx = tb.StepContext()
    _, count = sc.min_distance(x)

    # each call at positions of its own (a picometre apart, as a new Newton iterate is): the term finds its pairs
    shifted = (x + 1e-12 * k for k in range(1, 10 * repeats + 10))

    def work():
        y = next(shifted)
        sc._cache = None  # its own broad phase, as ipctk's build
        sc.energy(y, ctx)
        sc.gradient(y, ctx)
        sc.hessian(y, ctx, tb.Projection.CLAMP)

    dx = torch.zeros_like(x)
    dx[x[:, 2] > 0, 2] = -1e-3  # the upper layer (and the crease) down by 1 mm
    seconds = best(work, repeats)

    def bound_fresh():
        sc._cache = None  # a new step's bound searches its pairs
        sc.max_step(x, dx, ctx)

    bound = best(bound_fresh, repeats)
    broad = best(lambda: sc._candidates(*vertex_boxes(x), dhat), repeats)

    def iteration():
        y = next(shifted)
        sc.energy(y, ctx)
        sc.gradient(y, ctx)
        sc.hessian(y, ctx, tb.Projection.CLAMP)
        sc._cache = None
        sc.max_step(y, 0.1 * dx, ctx)
        sc.energy(y + 0.1 * dx, ctx)
        sc.energy(y + 0.05 * dx, ctx)

    newton = best(iteration, repeats)

    def gradient_hessian():  # the pairs found (kept from the last call at x): their work alone
        sc.gradient(x, ctx)
        sc.hessian(x, ctx, tb.Projection.CLAMP)

    sc.energy(x, ctx)
    alone = best(gradient_hessian, repeats)
    return count, seconds, bound, broad, newton, alone


def run_solve(x, f, dhat):
    """A static solve of the folded grid: the upper layer, held at its corners, sags under its weight onto the
    pinned lower one (StVK membrane, bending, adaptive barrier stiffness).  Returns (Newton iterations, the contact term's seconds
    per iteration, the solve's seconds, the contacts at the end)."""
    import time

    n = x.shape[0] // 2
    sc = tb.SelfContact(dhat=dhat)
    spent = [0.0]
    for name in ("energy", "gradient", "hessian", "max_step"):
        method = getattr(sc, name)

        def timed(*a, _m=method, **k):
            t0 = time.perf_counter()
            try:
                return _m(*a, **k)
            finally:
                spent[0] += time.perf_counter() - t0
        setattr(sc, name, timed)
    pinned = torch.arange(2 * n) < n
    side = round(n ** 0.5)
    pinned[n + torch.tensor([0, side - 1, n - side, n - 1])] = True  # the upper layer's corners: no sliding mode
    model = tb.ClothModel(f, x, bending=tb.BendingEnergy(f, x, stiffness=1e-6), density=0.2, pinned=pinned,
                          membrane=tb.MembraneEnergy(f, x, model="stvk", young=1e5, poisson=0.3, thickness=5e-4),
                          terms=[sc])
    t0 = time.perf_counter()
    _, info = tb.solve_static(model, x)
    total = time.perf_counter() - t0
    if not info.converged:
        raise RuntimeError(f"the benchmark's solve did not converge: {info.message}")
    return info.iterations, spent[0] / max(info.iterations, 1), total, info.contact_count


def run_ipctk(x, f, dhat, repeats):
    import ipctk
    import numpy as np
    if hasattr(ipctk, "set_num_threads"):  # one thread, as torchbend here (ipctk's default: every core)
        ipctk.set_num_threads(1)
    else:
        print(f"warning: ipctk {getattr(ipctk, '__version__', '?')} has no set_num_threads: it runs on its default "
              "threads, not one", file=sys.stderr)
    V = x.numpy()
    F = f.numpy().astype(np.int32)
    E = ipctk.edges(F)
    mesh = ipctk.CollisionMesh(V, E, F)
    B = ipctk.BarrierPotential(dhat, 1.0)
    holder = {}

    def work():
        c = ipctk.NormalCollisions()
        c.build(mesh, V, dhat)
        B(c, mesh, V)
        B.gradient(c, mesh, V)
        B.hessian(c, mesh, V, ipctk.PSDProjectionMethod.CLAMP)
        holder["n"] = len(c)

    seconds = best(work, repeats)
    found = ipctk.NormalCollisions()
    found.build(mesh, V, dhat)

    def gradient_hessian():
        B.gradient(found, mesh, V)
        B.hessian(found, mesh, V, ipctk.PSDProjectionMethod.CLAMP)

    return holder["n"], seconds, best(gradient_hessian, repeats)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=[20, 50], help="grid sizes n (about 13 n^2 contacts)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dhat", type=float, default=2e-3)
    ap.add_argument("--no-solve", dest="solve", action="store_false", help="skip the static solves")
    ap.add_argument("--scene", choices=sorted(SCENES), default="layers",
                    help="layers: two n x n layers 1 mm apart (2 n^2 vertices); half: one n x n grid folded in half "
                         "onto itself (n^2 vertices; no static solve)")
    args = ap.parse_args(argv)
    build = SCENES[args.scene]
    torch.set_num_threads(1)
    print(machine())
    label = {"layers": "two n x n layers 1 mm apart", "half": "one n x n grid folded in half onto itself"}[args.scene]
    print(f"scene {args.scene} ({label}); one thread, float64, dhat {args.dhat:g} m, best of {args.repeats}; energy + "
          f"gradient + clamp-projected Hessian with each code's own pair search\n")
    print(f"{'grid':>6} {'V':>6} | {'torchbend pairs':>15} {'s':>8} {'us/pair':>8} {'broad s':>8} {'max_step s':>10} "
          f"{'newton it s':>11} | {'ipctk pairs':>11} {'s':>8} {'us/pair':>8} | ratio")
    work_rows = []
    for n in args.sizes:
        x, f = build(n)
        count, sec, bound, broad, newton, alone = run_torchbend(x, f, args.dhat, args.repeats)
        try:
            ic, isec, iwork = run_ipctk(x, f, args.dhat, args.repeats)
            tail = (f"{ic:>11} {isec:8.3f} {1e6 * isec / max(ic, 1):8.1f} | {sec / isec * ic / max(count, 1):5.2f}x per "
                    f"pair, {sec / isec:5.2f}x in total (torchbend / ipctk)")
            work_rows.append(f"{n:>4}^2 {x.shape[0]:>6} | {count:>15} {alone:8.4f} {1e6 * alone / max(count, 1):8.2f} | "
                             f"{ic:>11} {iwork:8.4f} {1e6 * iwork / max(ic, 1):8.2f} | "
                             f"{alone / iwork * ic / max(count, 1):5.2f}x per pair, {alone / iwork:5.2f}x in total")
        except ImportError:
            tail = "ipctk not installed (pip install ipctk)"
        print(f"{n:>4}^2 {x.shape[0]:>6} | {count:>15} {sec:8.4f} {1e6 * sec / max(count, 1):8.2f} {broad:8.4f} "
              f"{bound:10.4f} {newton:11.4f} | {tail}")
    if work_rows:
        print("\nthe issue's per-contact work alone: gradient + clamp-projected Hessian + its assembly of the pairs "
              "found beforehand (no pair search, no energy)")
        print(f"{'grid':>6} {'V':>6} | {'torchbend pairs':>15} {'s':>8} {'us/pair':>8} | {'ipctk pairs':>11} {'s':>8} "
              f"{'us/pair':>8} | ratio (torchbend / ipctk)")
        print("\n".join(work_rows))
    if args.solve and args.scene == "layers":
        print("\nstatic solve: the upper layer, held at its corners, sags onto the pinned lower one (gravity, adaptive"
              " stiffness); the contact term's time per Newton iteration")
        print(f"{'grid':>6} {'V':>6} | {'iterations':>10} {'contact s/it':>12} {'solve s':>8} {'contacts':>9}")
        for n in args.sizes:
            x, f = folded(n)
            its, per, total, contacts = run_solve(x, f, args.dhat)
            print(f"{n:>4}^2 {x.shape[0]:>6} | {its:>10} {per:12.4f} {total:8.2f} {contacts:>9}")


if __name__ == "__main__":
    main()
