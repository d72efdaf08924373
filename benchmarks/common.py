"""Shared helpers of the benchmark scripts: timing, machine description, test scenes."""
from __future__ import annotations

import os
import platform
import statistics
import time

import torch


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (
        f"{cpu} | {os.cpu_count()} cores | torch {torch.__version__} | threads {torch.get_num_threads()} | "
        f"python {platform.python_version()}"
    )


def timeit(fn, repeat: int = 3, warmup: int = 1) -> float:
    """Median wall-clock seconds of ``fn()``."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def sheet_for_hinges(hinges: int) -> int:
    """Side ``n`` of an ``n x n`` sheet with about ``hinges`` hinges (H ~ 3 n^2)."""
    return max(3, round((hinges / 3) ** 0.5) + 1)
