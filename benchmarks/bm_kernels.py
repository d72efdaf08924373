"""The compiled CPU kernels against eager autograd of the plain atan2 energy, ns per hinge.

    python benchmarks/bm_kernels.py                          # 1e4, 1e5, 1e6 hinges, float64 and float32
    python benchmarks/bm_kernels.py --sizes 100000 --dtypes float64 --repeat 5

Operations (one mesh, random curved sheet, tan model, scalar stiffness, per-hinge rest angles):
``energy`` (native: per-hinge psi, summed; autograd: the plain energy's forward), ``gradient`` (native:
the gradient kernel; autograd: forward + backward), ``hvp`` (native: the HVP kernel; autograd: forward,
backward with ``create_graph`` and double backward) and ``second_order`` (native: the general double
backward with parameter tangents, ``bending_second_order``, compared with autograd's double backward).
Each kernel is called directly (no input checks, no autograd Function), as the Functions call it.
Reported: ns per hinge (fastest of ``--repeat``) and the speedup over autograd.
"""
from __future__ import annotations

import argparse
import functools
import time

import torch
from common import machine, sheet_for_hinges

import torchbend as tb
from torchbend.backends import native
from torchbend.testing import autograd_gradient, autograd_hvp, plain_bending_energy


def timeit(fn, repeat: int) -> float:
    """The fastest of ``repeat`` calls after one warm-up (on a shared machine the minimum is the stable
    statistic: other processes only ever add time)."""
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def scene(hinges: int, dtype):
    n = sheet_for_hinges(hinges)
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3, check_finite=False)
    gen = torch.Generator().manual_seed(0)
    x = rest + (0.1 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    v = torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    return bend, x, v


def methods(bend, x, v):
    hinges, a = bend.hinges, bend.weights.to(x.dtype)
    k, rest = bend.stiffness.to(x.dtype).reshape(1), bend.rest_angles.to(x.dtype)
    inc = native.incidence(hinges, x.shape[-2])
    one = x.new_ones(1)
    t = torch.randn(hinges.shape[0], 4, dtype=x.dtype, generator=torch.Generator().manual_seed(1))

    def plain(y):
        return plain_bending_energy(y, hinges, a, k, rest, "tan")

    nat = {
        "energy": lambda: native.bending_energy(x, hinges, a, k, rest, None, None, "tan").sum(-1),
        "gradient": lambda: native.bending_gradient(x, hinges, a, k, rest, None, None, "tan", one, inc, False),
        "hvp": lambda: native.bending_hvp(x, v, hinges, a, k, rest, None, None, "tan", one, inc),
    }
    if hasattr(native, "bending_second_order"):
        nat["second_order"] = lambda: native.bending_second_order(x, v, t, hinges, a, k, rest, None, None, "tan", one,
                                                                  inc)
    ag_hvp = functools.partial(autograd_hvp, plain, x, v)
    ag = {
        "energy": lambda: plain(x),
        "gradient": functools.partial(autograd_gradient, plain, x),
        "hvp": ag_hvp,
        "second_order": ag_hvp,
    }
    return nat, ag


def run(sizes, dtypes, repeat: int, log=print):
    rows = []
    for dt_name in dtypes:
        dtype = getattr(torch, dt_name)
        for target in sizes:
            bend, x, v = scene(target, dtype)
            H = bend.hinge_count
            nat, ag = methods(bend, x, v)
            for op, fn in nat.items():
                with torch.no_grad():
                    tn = timeit(fn, repeat) / H * 1e9
                with torch.no_grad() if op == "energy" else torch.enable_grad():
                    ta = timeit(ag[op], repeat) / H * 1e9
                rows.append((dt_name, H, op, tn, ta))
                log(f"{dt_name:>8s} {H:>8d} {op:>13s}  native {tn:8.1f}  autograd {ta:8.1f} ns/hinge  "
                    f"x{ta / tn:5.1f}")
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    p.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    p.add_argument("--repeat", type=int, default=5)
    a = p.parse_args(argv)
    print("machine:", machine())
    run(a.sizes, a.dtypes, a.repeat)


if __name__ == "__main__":
    main()
