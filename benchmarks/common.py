"""Shared helpers of the benchmark scripts: timing, machine description, test scenes."""
from __future__ import annotations

import os
import platform

import torch

from torchbend.testing import median_time

timeit = median_time  # one timing helper for the demo and the benchmarks


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


def sheet_for_hinges(hinges: int) -> int:
    """Side ``n`` of an ``n x n`` sheet with about ``hinges`` hinges (H ~ 3 n^2)."""
    return max(3, round((hinges / 3) ** 0.5) + 1)
