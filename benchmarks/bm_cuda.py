"""GPU benchmark: torchbend's default path (the CUDA kernels) against the autodiff a user would write, on the
same GPU, in the same format as the CPU tables of BENCHMARKS.md.

    python benchmarks/bm_cuda.py                       # 1e3..1e6 hinges, float32 and float64 (a few minutes)
    python benchmarks/bm_cuda.py --sizes 1e6 --compile # only 1e6, with torch.compile (inductor/triton) as well

It runs :func:`bm_throughput.run_all` with ``device="cuda"`` (each size and dtype in a fresh process, every
result checked against plain autodiff before it is timed, timings with ``torch.cuda.synchronize()``):
methods ``torchbend`` (default path), ``torchbend.backward``, ``torchbend.eager``, ``autograd`` (eager
PyTorch of the plain energy: forward, backward, double backward), ``torch.func`` (``grad``,
``jvp(grad)``, ``vmap(hessian)``, + ``index_add``) and, with ``--compile``, ``torch.compile``; floors from
the device's STREAM copy/triad bandwidth and matmul flop rate (:mod:`floors`).  Writes
``benchmarks/results/cuda_<device>.json`` (read by ``benchmarks/report.py``, which puts it in the GPU
section of BENCHMARKS.md) and prints the tables and the GPU targets (float32 and float64 at 1e6 hinges:
every op >= 20x the plain autodiff on the same GPU and within 3x of the bandwidth floor).
With ``--merge``, configurations already in the file and not re-measured are kept (a run split into
several commands).
"""
from __future__ import annotations

import argparse
import json
import os
import re

import bm_throughput
import tables
import torch

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def slug(name: str) -> str:
    """``NVIDIA H100 80GB HBM3`` -> ``h100_80gb_hbm3``."""
    name = re.sub(r"^nvidia\s+", "", name.strip(), flags=re.I)
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    ap.add_argument("--sizes", type=bm_throughput.parse_size, nargs="+", default=[1000, 10_000, 100_000, 1_000_000])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--compile", action="store_true", help="also torch.compile of the plain energy (slow to compile)")
    ap.add_argument("--budget", type=float, default=0.5)
    ap.add_argument("--out", default=None, help="default: benchmarks/results/cuda_<device>.json")
    ap.add_argument("--merge", action="store_true", help="keep the file's other configurations")
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("bm_cuda.py needs a CUDA device")
    methods = ["torchbend", "torchbend.backward", "torchbend.eager", "autograd", "torch.func"]
    methods += ["torch.compile"] if a.compile else []
    out = a.out or os.path.join(RESULTS, f"cuda_{slug(torch.cuda.get_device_name())}.json")
    print(f"device: {torch.cuda.get_device_name()}; torch {torch.__version__}", flush=True)
    result = bm_throughput.run_all(a.sizes, a.dtypes, "cuda", methods, a.budget, 5, log=lambda s: print(s, flush=True))
    if a.merge and os.path.exists(out):
        with open(out) as f:
            old = json.load(f)
        new = {(c["dtype"], c.get("target")) for c in result["configs"]}
        result["configs"] = [c for c in old["configs"] if (c["dtype"], c.get("target")) not in new] + result["configs"]
        result["sizes"] = sorted(set(old["sizes"]) | set(result["sizes"]))
        result["dtypes"] = [d for d in ("float32", "float64") if d in set(old["dtypes"]) | set(result["dtypes"])]
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        json.dump(result, f, indent=0)
    lines = [f"device: {tables.machine_line(result)}", ""] + tables.targets_table(tables.gpu_targets(result))
    lines += tables.throughput_tables(result) + tables.speedup_tables(result) + tables.floor_table(result)
    if a.compile:
        lines += tables.compile_table(result)
    text = "\n".join(lines)
    print(text)
    with open(os.path.splitext(out)[0] + ".md", "w") as f:
        f.write(text + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
