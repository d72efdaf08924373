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
``--registration``: the operators as the autograd Functions call them (``torchbend.backends.ops.run``: registered
from Python with ``torch.library``, called directly in eager mode) against the same kernels registered in C++
(``TORCH_LIBRARY`` / ``TORCH_LIBRARY_IMPL(..., CPU)`` in a JIT build of the CPU sources with a registration unit,
called through ``torch.ops``, the status word checked in Python): the per-call cost of each registration.
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


_REGISTRATION = r"""
#include <torch/library.h>
#include "cpu_ops.h"
TORCH_LIBRARY(torchbend_cxx, m) {
  m.def("bending_energy(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, int model, "
        "bool check) -> (Tensor, Tensor, int)");
  m.def("bending_gradient(Tensor x, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, int model, "
        "Tensor weight, Tensor inc_ptr, Tensor inc_idx, bool params, bool check) -> (Tensor, Tensor, Tensor, int)");
  m.def("bending_hvp(Tensor x, Tensor v, Tensor hinges, Tensor a, Tensor k, Tensor rest, Tensor? c, Tensor? prev, "
        "int model, Tensor weight, Tensor inc_ptr, Tensor inc_idx, bool check) -> (Tensor, Tensor, int)");
}
TORCH_LIBRARY_IMPL(torchbend_cxx, CPU, m) {
  m.impl("bending_energy", &torchbend::cpu::bending_energy);
  m.impl("bending_gradient", &torchbend::cpu::bending_gradient);
  m.impl("bending_hvp", &torchbend::cpu::bending_hvp);
}
"""


def load_cxx_registration() -> None:
    """The CPU kernels with the energy, gradient and hvp registered in C++ as ``torch.ops.torchbend_cxx.*`` (a JIT
    build of the sources with a registration unit in place of the bindings; a few minutes, then cached)."""
    import os
    import tempfile

    from torch.utils.cpp_extension import load

    from torchbend.backends import _build_config as cfg

    src = os.path.join(tempfile.mkdtemp(prefix="torchbend_registration_"), "registration.cpp")
    with open(src, "w") as fh:
        fh.write(_REGISTRATION)
    sources = [os.path.join(cfg.CSRC, f) for f in cfg.NATIVE_SOURCES if f != "bending_cpu.cpp"] + [src]
    load(name=native.extension_name() + "_cxx_registration", sources=sources, extra_include_paths=[cfg.CSRC],
         extra_cflags=native.jit_cflags(), extra_ldflags=["-fopenmp"], is_python_module=False, verbose=False)


def registration_calls(bend, x, v, cxx) -> dict:
    """The energy, gradient and hvp operators registered from Python (``ops.run``) and in C++ (``cxx``)."""
    from torchbend.backends import ops as tbops

    hinges, a = bend.hinges, bend.weights
    k, rest = bend.stiffness.reshape(1), bend.rest_angles
    ptr, idx = native.incidence(hinges, x.shape[-2])
    one = x.new_ones(1)

    def checked(out):
        if out[-1]:
            raise ValueError(out[-1])
        return out

    return {
        ("energy", "python"): lambda: tbops.run("bending_energy", x, hinges, a, k, rest, None, None, "tan", False),
        ("energy", "c++"): lambda: checked(cxx.bending_energy(x, hinges, a, k, rest, None, None, 1, False)),
        ("gradient", "python"): lambda: tbops.run("bending_gradient", x, hinges, a, k, rest, None, None, "tan", one,
                                                  ptr, idx, False, False),
        ("gradient", "c++"): lambda: checked(cxx.bending_gradient(x, hinges, a, k, rest, None, None, 1, one, ptr, idx,
                                                                  False, False)),
        ("hvp", "python"): lambda: tbops.run("bending_hvp", x, v, hinges, a, k, rest, None, None, "tan", one, ptr, idx,
                                             False),
        ("hvp", "c++"): lambda: checked(cxx.bending_hvp(x, v, hinges, a, k, rest, None, None, 1, one, ptr, idx, False)),
    }


def run_registration(sizes, repeat: int, log=print) -> list:
    load_cxx_registration()
    rows = []
    for target in sizes:
        bend, x, v = scene(target, torch.float64)
        calls = registration_calls(bend, x, v, torch.ops.torchbend_cxx)
        with torch.no_grad():
            for _ in range(2):  # interleaved rounds: drifts of a shared machine hit both registrations
                for (op, reg), fn in calls.items():
                    us = per_call(fn, repeat)
                    rows.append((bend.hinge_count, op, reg, us))
                    log(f"{bend.hinge_count:>8d} {op:>9s} {reg:>7s} {us:10.2f} us/call")
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
    a = p.parse_args(argv)
    print("machine:", machine())
    if a.calls or a.pool or a.registration:
        sizes = [1_000, 100_000] if a.sizes == p.get_default("sizes") else a.sizes
        if a.calls:
            run_calls(sizes, a.repeat)
        if a.registration:
            run_registration(sizes, a.repeat)
        if a.pool:
            run_pool(100_000, a.repeat)
        return
    run(a.sizes, a.dtypes, a.repeat)


if __name__ == "__main__":
    main()
