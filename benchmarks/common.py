"""Shared helpers of the benchmark scripts: timing, machine description, test scenes."""
from __future__ import annotations

import gc
import os
import platform
import statistics
import time

import torch

from torchbend.testing import median_time

timeit = median_time  # one timing helper for the demo and the benchmarks


def cpu_model() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return cpu


VECTOR_EXTENSIONS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512_fp16",
                     "amx_tile", "asimd", "sve")
"""The CPU flags the benchmarks report (the vector instruction sets the kernels can be built for)."""


def cpu_vector_extensions() -> list[str]:
    """The vector extensions of :data:`VECTOR_EXTENSIONS` this CPU has (``/proc/cpuinfo`` flags; empty elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    have = set(line.split(":", 1)[1].split())
                    return [x for x in VECTOR_EXTENSIONS if x in have]
    except OSError:
        pass
    return []


def kernel_build() -> dict:
    """How the CPU kernels in use were built: ``{"march": "native" | "x86-64-v3" | ..., "arch": its cache tag, "cflags": [...], "source": "install" | "jit",
    "module": the loaded file, "package": the torchbend directory imported}`` (:func:`torchbend.backends.native.build_info`;
    ``{}`` without the extension).  The two paths tell which tree a result measured: a script run from another
    worktree imports the editable install's torchbend, not the worktree's, unless PYTHONPATH names it."""
    import torchbend
    from torchbend.backends import native

    try:
        if native.load() is None:
            return {}
        info = dict(native.build_info())
    except Exception:  # no compiler, or a failed build: the eager path runs (the backends line says so)
        return {}
    out = {k: info[k] for k in ("arch", "cflags", "source") if k in info}
    out["module"] = info.get("path")
    out["package"] = os.path.dirname(os.path.abspath(torchbend.__file__))
    march = [f.split("=", 1)[1] for f in out.get("cflags", []) if f.startswith("-march=")]
    out["march"] = march[-1] if march else "none"  # the compiler's baseline
    return out


def machine() -> str:
    return (
        f"{cpu_model()} | {os.cpu_count()} cores | torch {torch.__version__} | threads {torch.get_num_threads()} | "
        f"python {platform.python_version()}"
    )


def machine_info(device: str = "cpu") -> dict:
    """What the results files record about the machine (CPU model, cores, threads, library versions)."""
    info = {"cpu": cpu_model(), "cores": os.cpu_count(), "threads": torch.get_num_threads(),
            "torch": torch.__version__, "python": platform.python_version(), "device": device,
            "vector_extensions": cpu_vector_extensions(), "kernels": kernel_build()}
    try:
        import numpy

        info["numpy"] = numpy.__version__
    except ImportError:
        pass
    try:
        import jax

        info["jax"] = jax.__version__
    except ImportError:
        info["jax"] = None
    if device.startswith("cuda") and torch.cuda.is_available():
        info["device"] = torch.cuda.get_device_name()
        info["cuda"] = torch.version.cuda
    return info


def sheet_for_hinges(hinges: int) -> int:
    """Side ``n`` of an ``n x n`` sheet with about ``hinges`` hinges (H ~ 3 n^2)."""
    return max(3, round((hinges / 3) ** 0.5) + 1)


def bench(fn, sync=None, budget: float = 1.0, min_repeat: int = 3, max_repeat: int = 50, warmup: int = 1) -> dict:
    """Median wall-clock seconds of ``fn()`` after ``warmup`` calls.

    Timed calls continue until they add up to about ``budget`` seconds and number at least
    ``min_repeat`` (one once the median exceeds 2 s), at most ``max_repeat``.  ``sync`` (e.g.
    ``torch.cuda.synchronize``) runs after every call, inside the timed interval.  The garbage collector
    is off while timing.  Returns ``{"median", "min", "repeats"}`` (seconds)."""
    sync = sync or (lambda: None)
    for _ in range(warmup):
        fn()
        sync()
    gc.collect()
    gc.disable()
    try:
        times = []
        while len(times) < max_repeat:
            t0 = time.perf_counter()
            fn()
            sync()
            times.append(time.perf_counter() - t0)
            need = 1 if statistics.median(times) > 2.0 else min_repeat
            if len(times) >= need and sum(times) >= budget:
                break
    finally:
        gc.enable()
    return {"median": statistics.median(times), "min": min(times), "repeats": len(times)}
