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

    python benchmarks/bm_kernels.py --calls                  # per-call microseconds at 1e3 and 1e5 hinges

``--calls``: what one call costs through the public entry points (``bend(x)``, ``bend.gradient``, ``bend.hvp``
with ``backend="native"``, float64, no autograd graph) and through the registered operators
(``torch.ops.torchbend.*``), fastest of ``--repeat`` runs of a loop of calls: the per-call overhead of the
Python layers and of the dispatcher next to the kernels' work (benchmarks/results/backends_registration.txt).
``--registration``: per-call microseconds (wall clock and the thread's CPU time) of the energy, gradient and hvp
as the autograd Functions call them (``torchbend.backends.ops.run``), through the dispatcher
(``torch.ops.torchbend.<op>.default``) and through the public calls, labelled with how the operators of the
torchbend on ``sys.path`` are registered (``c++``: ``TORCH_LIBRARY`` in the CPU extension; ``python``:
``torch.library``): run it with ``PYTHONPATH`` set to a tree before and after a change, in turns
(``--json`` keeps the rows).
``--pool``: the per-hinge blocks (``hinge_hessians``) of 1e5 hinges called in a loop, with new outputs each call
and with caller-owned ``out=`` buffers kept between calls.
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


def per_call(fn, repeat: int, seconds: float = 0.05) -> float:
    """Microseconds of one call of ``fn``: the fastest of ``repeat`` loops of about ``seconds`` each."""
    fn()
    t0 = time.perf_counter()
    fn()
    n = max(1, int(seconds / max(time.perf_counter() - t0, 1e-7)))
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e6


def call_methods(bend, x, v) -> dict:
    """The public calls and the registered operators of the energy, gradient and hvp."""
    hinges, a = bend.hinges, bend.weights.to(x.dtype)
    k, rest = bend.stiffness.to(x.dtype).reshape(1), bend.rest_angles.to(x.dtype)
    ptr, idx = native.incidence(hinges, x.shape[-2])
    one = x.new_ones(1)
    ops = torch.ops.torchbend
    return {
        ("energy", "public"): lambda: bend(x),
        ("gradient", "public"): lambda: bend.gradient(x),
        ("hvp", "public"): lambda: bend.hvp(x, v),
        ("energy", "operator"): lambda: ops.bending_energy(x, hinges, a, k, rest, None, None, "tan", False),
        ("gradient", "operator"): lambda: ops.bending_gradient(x, hinges, a, k, rest, None, None, "tan", one, ptr, idx,
                                                               False, False),
        ("hvp", "operator"): lambda: ops.bending_hvp(x, v, hinges, a, k, rest, None, None, "tan", one, ptr, idx, False),
    }


def run_calls(sizes, repeat: int, log=print) -> list:
    import torchbend.backends.ops  # noqa: F401  (registers torch.ops.torchbend)

    rows = []
    for target in sizes:
        bend, x, v = scene(target, torch.float64)
        with torch.no_grad(), tb.use_backend("native"):
            for (op, path), fn in call_methods(bend, x, v).items():
                us = per_call(fn, repeat)
                rows.append((bend.hinge_count, op, path, us))
                log(f"{bend.hinge_count:>8d} {op:>9s} {path:>9s} {us:10.2f} us/call")
    return rows


def registration_label() -> str:
    """How the operators of the torchbend on ``sys.path`` are registered: ``"c++"`` (``TORCH_LIBRARY`` in the CPU
    extension) or ``"python"`` (``torch.library`` from Python: the code before the C++ registration, or no
    extension)."""
    from torchbend.backends import ops as tbops

    return "python" if getattr(tbops, "PYTHON_DEFINED", True) else "c++"


def registration_calls(bend, x, v) -> dict:
    """The energy, gradient and hvp as the autograd Functions call them (``ops.run``: in eager mode the kernel's
    Python wrapper, no dispatcher), through the dispatcher (``torch.ops.torchbend.<op>.default``: the registered
    kernel, C++ or Python), and the public calls; public API and operators only, so that the same script times
    the code before and after a change (``PYTHONPATH`` of either tree)."""
    from torchbend.backends import ops as tbops

    hinges, a = bend.hinges, bend.weights
    k, rest = bend.stiffness.reshape(1), bend.rest_angles
    ptr, idx = native.incidence(hinges, x.shape[-2])
    one = x.new_ones(1)
    args = {
        "energy": ("bending_energy", (x, hinges, a, k, rest, None, None, "tan", False)),
        "gradient": ("bending_gradient", (x, hinges, a, k, rest, None, None, "tan", one, ptr, idx, False, False)),
        "hvp": ("bending_hvp", (x, v, hinges, a, k, rest, None, None, "tan", one, ptr, idx, False)),
    }
    calls = {}
    for op, (name, a_) in args.items():
        calls[(op, "run")] = functools.partial(tbops.run, name, *a_)
        calls[(op, "dispatcher")] = functools.partial(getattr(torch.ops.torchbend, name).default, *a_)
    calls[("energy", "public")] = lambda: bend(x)
    calls[("gradient", "public")] = lambda: bend.gradient(x)
    calls[("hvp", "public")] = lambda: bend.hvp(x, v)
    return calls


def per_call_both(fn, repeat: int, seconds: float = 0.05) -> tuple[float, float]:
    """Microseconds of one call of ``fn``: ``(wall, cpu)``, each the fastest of ``repeat`` loops of about
    ``seconds``; ``cpu`` is the calling thread's CPU time (``time.thread_time``), which does not count the time
    other processes held the core."""
    fn()
    t0 = time.perf_counter()
    fn()
    n = max(1, int(seconds / max(time.perf_counter() - t0, 1e-7)))
    wall = cpu = float("inf")
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.thread_time()
        for _ in range(n):
            fn()
        wall = min(wall, (time.perf_counter() - t0) / n)
        cpu = min(cpu, (time.thread_time() - c0) / n)
    return wall * 1e6, cpu * 1e6


def run_registration(sizes, repeat: int, log=print, rounds: int = 2) -> list:
    """Per-call microseconds of :func:`registration_calls` at each size, ``rounds`` interleaved rounds."""
    label = registration_label()
    rows = []
    for target in sizes:
        bend, x, v = scene(target, torch.float64)
        calls = registration_calls(bend, x, v)
        with torch.no_grad():
            for r in range(rounds):  # interleaved rounds: drifts of a shared machine hit every call alike
                for (op, path), fn in calls.items():
                    wall, cpu = per_call_both(fn, repeat)
                    rows.append({"registration": label, "hinges": bend.hinge_count, "op": op, "path": path,
                                 "round": r, "wall_us": wall, "cpu_us": cpu})
                    log(f"{label:>6s} {bend.hinge_count:>8d} {op:>9s} {path:>10s} {wall:10.2f} us/call wall "
                        f"{cpu:10.2f} us/call CPU")
    return rows


def run_pool(hinges: int, repeat: int, log=print) -> list:
    """``hinge_hessians`` of ``hinges`` hinges in a loop: new outputs every call, and caller-owned buffers."""
    bend, x, _ = scene(hinges, torch.float64)
    args = (x, bend.hinges, bend.weights, bend.stiffness.reshape(1), bend.rest_angles, None, None, "tan")
    H = bend.hinge_count
    hb, g = x.new_empty(H, 12, 12), x.new_empty(H, 12)
    rows = []
    with torch.no_grad():
        for name, fn in (("new outputs", lambda: native.bending_hessians(*args)),
                         ("out= buffers", lambda: native.bending_hessians(*args, out=(hb, g)))):
            ms = timeit(fn, repeat) * 1e3
            rows.append((H, name, ms))
            log(f"{H:>8d} hinge_hessians {name:>13s} {ms:8.2f} ms/call {ms * 1e6 / H:7.1f} ns/hinge")
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    p.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--calls", action="store_true", help="per-call microseconds at 1e3 and 1e5 hinges")
    p.add_argument("--registration", action="store_true", help="Python against C++ operator registration")
    p.add_argument("--pool", action="store_true", help="hinge_hessians at 1e5 hinges: new outputs and out= buffers")
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds of --registration")
    p.add_argument("--json", default=None, help="write the rows of --registration here")
    a = p.parse_args(argv)
    print("machine:", machine())
    if a.calls or a.pool or a.registration:
        sizes = [1_000, 100_000] if a.sizes == p.get_default("sizes") else a.sizes
        if a.calls:
            run_calls(sizes, a.repeat)
        if a.registration:
            rows = run_registration(sizes, a.repeat, rounds=a.rounds)
            if a.json:
                import json

                with open(a.json, "w") as fh:
                    json.dump({"machine": machine(), "torch": torch.__version__, "rows": rows}, fh, indent=1)
        if a.pool:
            run_pool(100_000, a.repeat)
        return
    run(a.sizes, a.dtypes, a.repeat)


if __name__ == "__main__":
    main()
