"""Garment benchmark: the solver on garments a user brings, through the documented API only.

Cases (each loaded as a user would: an OBJ with unwelded UV seams read by ``tb.mesh.load``, or a shipped scene):

* ``sleeve``: a 408-vertex tube (24 around x 17 along, radius 6 cm, 50 cm, two panels sewn along two seams)
  hanging on a capsule arm (radius 4 cm, 70 cm), quadratic bending from
  ``stiffness_from_material(2e5, 5e-4, 0.3)``, StVK membrane (Y = 2e5 Pa, t = 0.5 mm), 0.2 kg/m^2;
  ``sleeve+pin``: the same with the seam vertex at the top of the shoulder pinned (no free slide along the
  arm); both start from the rest shape, coaxial with the arm (the sleeve drops 2 cm onto it);
* ``skirt``: ``configs/skirt_drape.yaml`` (384 vertices, waist pinned, hips and legs);
* ``towel``: a 31 x 31 sheet (0.5 m, 961 vertices) hanging over a capsule rail, its centre vertex pinned
  (frictionless, a towel over a rail slides off either side).

The colliders' contact law is the default (``--contact default``: the log barrier of Incremental Potential
Contact, ``law="ipc"``, margin 1 mm, stiffness chosen from the garment's weight; C2 where a vertex comes within
the margin, infinite on the surface, never reached).  ``--contact penalty`` gives the sleeves' arm and the
towel's rail the penalty ``k/2 max(0, d)^2`` (``stiffness=1e4`` N/m, the default before), whose curvature jumps
from 0 to ``k`` where a vertex touches (the Newton model changes under every vertex that touches or leaves the
surface); ``--contact cubic`` the C2 law ``k max(0, d)^3`` (``law="barrier", power=3, stiffness=1e8`` J/m^3);
``--contact ipc-fixed`` the ipc law with ``stiffness=1.0`` J/m^2 and ``margin=2e-3`` m.  The skirt keeps its
config's colliders (the default law).  ``--continuation off`` runs the static solves with ``continuation=False``.

For each: a static solve from the rest shape with the default options (damped) and with ``damping=False``
(plain Newton, the default before the damping), and 30
implicit-Euler steps of 0.01 s from rest (default options).  One thread (``torch.set_num_threads(1)``).

    python benchmarks/garments.py                 # every case, the table on stdout
    python benchmarks/garments.py --cases sleeve  # some of them
    python benchmarks/garments.py --cases sleeve sleeve+pin --contact cubic --continuation off
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
import time

import torch
from common import machine

import torchbend as tb
from torchbend.scenes.builders import build_scene
from torchbend.scenes.config import load_config

CONTACT = {"default": {}, "penalty": {"law": "penalty", "stiffness": 1e4},
           "cubic": {"law": "barrier", "power": 3.0, "stiffness": 1e8},
           "ipc-fixed": {"law": "ipc", "stiffness": 1.0, "margin": 2e-3}}
"""The contact laws of ``--contact``: the colliders' keyword arguments."""

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _loaded(positions, faces, uvs) -> tuple[torch.Tensor, torch.Tensor]:
    """Write an OBJ with its seams unwelded and read it back with ``tb.mesh.load`` (welds them)."""
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "garment.obj")
        tb.mesh.save_obj(path, positions, faces, uvs)
        rest, faces = tb.mesh.load(path)
    return rest, faces


def sleeve(pin: bool, contact: dict) -> tuple[tb.ClothModel, torch.Tensor]:
    p, f, uv = tb.mesh.skirt(24, 17, waist_radius=0.06, hem_radius=0.06, length=0.5, dtype=torch.float64)
    p = torch.stack((-p[:, 2], p[:, 1], p[:, 0]), -1)  # axis along +x, the shoulder at x = 0, a seam on top
    rest, faces = _loaded(p, f, uv)
    k = tb.stiffness_from_material(2e5, 5e-4, 0.3)
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=k)
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=2e5, poisson=0.3, thickness=5e-4)
    arm = tb.Capsule((-0.1, 0.0, 0.0), (0.6, 0.0, 0.0), radius=0.04, **contact)
    pinned = None
    if pin:  # the seam vertex at the top of the shoulder (z = 0.06: angle 0, where the two panels meet)
        pinned = [int(torch.argmin((rest - torch.tensor([0.0, 0.0, 0.06], dtype=rest.dtype)).norm(dim=-1)))]
    return tb.ClothModel(faces, rest, bending=bend, membrane=mem, colliders=[arm], density=0.2, pinned=pinned), rest


def skirt() -> tuple[tb.ClothModel, torch.Tensor]:
    model, x0, _ = build_scene(load_config(os.path.join(ROOT, "configs", "skirt_drape.yaml")))
    return model, x0


def towel(contact: dict) -> tuple[tb.ClothModel, torch.Tensor]:
    rest, faces = tb.scenes.grid(31, 31, (0.5, 0.5), dtype=torch.float64)
    rest = rest - torch.tensor([0.25, 0.25, -0.03], dtype=torch.float64)  # centred 3 cm above the rail's top
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=tb.stiffness_from_material(1e5, 1e-3, 0.3))
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=1e5, poisson=0.3, thickness=1e-3)
    rail = tb.Capsule((-0.4, 0.0, -0.02), (0.4, 0.0, -0.02), radius=0.02, **contact)
    centre = int(torch.argmin(rest[:, :2].norm(dim=-1)))
    return tb.ClothModel(faces, rest, bending=bend, membrane=mem, colliders=[rail], density=0.3,
                         pinned=[centre]), rest


CASES = {"sleeve": lambda contact: sleeve(False, contact), "sleeve+pin": lambda contact: sleeve(True, contact),
         "skirt": lambda contact: skirt(), "towel": towel}
"""Each case from the colliders' contact keyword arguments (:data:`CONTACT`; the skirt keeps its config's)."""


def static_row(model, x0, **kw) -> dict:
    t = time.perf_counter()
    x, info = tb.solve_static(model, x0, **kw)
    return {"converged": info.converged, "iterations": info.iterations, "solves": info.solves,
            "seconds": time.perf_counter() - t, "stop": info.stop_reason, "energy": info.energy,
            "drop": float((x0[:, 2] - x[:, 2]).max())}


def steps_row(model, x0, steps: int = 30, dt: float = 0.01) -> dict:
    state = tb.ClothState(x0.clone(), torch.zeros_like(x0))
    times, iters, ok = [], [], 0
    for _ in range(steps):
        t = time.perf_counter()
        state, info = tb.implicit_euler_step(model, state, dt)
        times.append(time.perf_counter() - t)
        iters.append(info.iterations)
        ok += int(info.converged)
    return {"total": sum(times), "max": max(times), "iterations": sum(iters), "max_iterations": max(iters),
            "converged": ok, "steps": steps}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--contact", choices=list(CONTACT), default="default",
                    help="the sleeves' and the towel's contact law (the skirt keeps its config's)")
    ap.add_argument("--continuation", choices=["auto", "off"], default="auto", help="of the static solves")
    ap.add_argument("--max-iters", type=int, default=None, help="of the static solves (default: the solver's)")
    args = ap.parse_args(argv)
    cont = {} if args.continuation == "auto" else {"continuation": False}
    if args.max_iters is not None:
        cont["max_iters"] = args.max_iters
    torch.set_num_threads(1)
    flags = [f for f in ("avx512f", "avx2", "fma") if f in open("/proc/cpuinfo").read().split()] if os.path.exists("/proc/cpuinfo") else []
    print(machine(), "|", " ".join(flags))
    print(f"threads: 1; float64; direct solver; static solves from the rest shape (continuation {args.continuation}, "
          f"max_iters {args.max_iters or 'default'}), "
          f"steps of 0.01 s from rest; contact law: {args.contact} {CONTACT[args.contact] or '(default)'}\n")
    head = (f"{'case':<11} {'V':>5}  {'static (defaults)':<34} {'static (damping=False)':<34} "
            f"{'30 steps: total / slowest step / iterations':<44}")
    print(head)
    print("-" * len(head))
    for name in args.cases:
        model, x0 = CASES[name](CONTACT[args.contact])
        rows = [static_row(model, x0, **cont), static_row(model, x0, damping=False, **cont)]
        cells = [f"{'ok ' if r['converged'] else 'FAIL'} {r['iterations']:4d} it {r['solves']:3d} solves {r['seconds']:6.1f} s"
                 for r in rows]
        st = steps_row(model, x0, args.steps) if args.steps else None
        step_cell = (f"{st['total']:6.1f} s / {st['max']:5.2f} s / {st['iterations']:4d} (max {st['max_iterations']}),"
                     f" {st['converged']}/{st['steps']} conv." if st else "")
        print(f"{name:<11} {model.vertex_count:5d}  {cells[0]:<34} {cells[1]:<34} {step_cell}", flush=True)
        for label, r in zip(("defaults", "damping=False"), rows):
            if not r["converged"] or not math.isfinite(r["energy"]):
                print(f"{'':<18}{label}: stop {r['stop']!r}, potential {r['energy']:.6e} J, largest drop {r['drop']:.3g} m")


if __name__ == "__main__":
    main()
