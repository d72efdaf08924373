"""The cost of the operators' argument checks (torchbend/csrc/checks.h) against the operators themselves.

    python benchmarks/bm_checks.py                       # 1e5 hinges, float64 and float32, 1 and 2 threads
    python benchmarks/bm_checks.py --hinges 1000000 --threads 1

Every operator ``torch.ops.torchbend.*`` checks its arguments before it returns anything: shapes, dtypes and
devices, every index value (hinges in [0, V); the incidence lists of the gradient operators where they are read;
the sparsity pattern, faces and face-edge maps of ``assemble``), the viscous pair.  Some checks are passes of
their own (hinge_hessians' and assemble's hinge indices, assemble's faces and pattern rows), others ride on a pass
that reads the integers anyway (the energy's gather, the gradient operators' scatter plan, assemble's scatter), so
their cost is only visible against a build without them: this script compiles the same sources with
``-DTORCHBEND_UNCHECKED`` (every check of index values off; about a minute, then cached) and times each kernel
in both builds on the same inputs, interleaved, fastest of ``--repeat`` (with one thread the calling thread's CPU
time, with more the wall time).  Reported: both times and the checks'
share of the checked operator's time (the target: at most 3% at 1e5 hinges).
"""
from __future__ import annotations

import argparse
import functools
import os
import time

import torch
from common import machine, sheet_for_hinges

import torchbend as tb
from torchbend.backends import native
from torchbend.energies.sparse import HessianPattern


def cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return " ".join(f for f in ("sse4_2", "avx", "avx2", "fma", "avx512f") if f in flags)
    except OSError:
        pass
    return "?"


def unchecked_module():
    """The kernels compiled with -DTORCHBEND_UNCHECKED (same sources and flags otherwise)."""
    from torch.utils.cpp_extension import load

    from torchbend.backends import _build_config as cfg

    return load(name=native.extension_name() + "_unchecked", sources=[os.path.join(cfg.CSRC, f) for f in cfg.NATIVE_SOURCES],
                extra_include_paths=[cfg.CSRC], extra_cflags=[*native.jit_cflags(), "-DTORCHBEND_UNCHECKED"],
                extra_ldflags=list(cfg.NATIVE_LDFLAGS), verbose=False)


def cases(hinges: int, dtype):
    n = sheet_for_hinges(hinges)
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3, check_finite=False)
    topo = bend.topology
    gen = torch.Generator().manual_seed(0)
    x = rest + (0.1 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    v = torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    h = bend.hinges
    H, V = h.shape[0], x.shape[0]
    a, k, r = bend.weights.to(dtype), bend.stiffness.to(dtype).reshape(1), bend.rest_angles.to(dtype)
    ptr, idx = native.incidence(h, V)
    one = x.new_ones(1)
    t = torch.randn(H, 4, dtype=dtype, generator=gen)
    pat = HessianPattern(topo)
    return H, {
        "bending_energy": lambda m: m.bending_energy(x, h, a, k, r, None, None, 1, False),
        "bending_gradient": lambda m: m.bending_gradient(x, h, a, k, r, None, None, 1, one, ptr, idx, False, False),
        "bending_energy_gradient": lambda m: m.bending_energy_gradient(x, h, a, k, r, None, None, 1, ptr, idx, False,
                                                                       False),
        "bending_hvp": lambda m: m.bending_hvp(x, v, h, a, k, r, None, None, 1, one, ptr, idx, False),
        "bending_second_order": lambda m: m.bending_second_order(x, v, t, h, a, k, r, None, None, 1, one, ptr, idx),
        "hinge_hessians": lambda m: m.bending_hessians(x, h, a, k, r, None, None, 1, None, None, False),
        "assemble": lambda m: m.assemble(x, h, a, k, r, None, None, 1, pat.hinge_blocks, topo.faces,
                                         topo.face_edge_hinges, topo.face_edge_signs, pat.face_blocks, pat.row_len,
                                         pat.nnz, True),
    }


def interleaved(fa, fb, repeat: int, clock=time.perf_counter) -> tuple[float, float]:
    """Fastest of ``repeat`` calls of each, alternating (load from other processes hits both alike)."""
    fa(); fb()  # noqa: E702
    ta = tb_ = float("inf")
    for _ in range(repeat):
        t0 = clock(); fa(); t1 = clock(); fb(); t2 = clock()  # noqa: E702
        ta, tb_ = min(ta, t1 - t0), min(tb_, t2 - t1)
    return ta, tb_


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--hinges", type=int, default=100_000)
    p.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--repeat", type=int, default=20)
    a = p.parse_args(argv)
    print("machine:", machine(), "|", cpu_flags(), "| kernels:", native.build_info().get("source"))
    checked, unchecked = native.load(), unchecked_module()
    worst = 0.0
    for threads in a.threads:
        torch.set_num_threads(threads)
        for dt in a.dtypes:
            H, ops = cases(a.hinges, getattr(torch, dt))
            for name, op in ops.items():
                with torch.no_grad():
                    # one thread: the calling thread's CPU time (what other processes on the machine add least to)
                    clock = time.thread_time if threads == 1 else time.perf_counter
                    t_on, t_off = interleaved(functools.partial(op, checked), functools.partial(op, unchecked),
                                              a.repeat, clock)
                share = 100 * (t_on - t_off) / t_on
                worst = max(worst, share)
                print(f"threads {threads} {dt:>8s} H {H:>7d} {name:>24s}  checked {t_on * 1e3:8.3f} ms  "
                      f"unchecked {t_off * 1e3:8.3f} ms  checks {share:+6.2f}%")
    print(f"largest share: {worst:.2f}%")


if __name__ == "__main__":
    main()
