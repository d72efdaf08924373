"""Regenerate BENCHMARKS.md and the plots in benchmarks/plots/ on this machine (one command).

    python benchmarks/report.py            # full (30-45 min): 1e3..1e6 hinges, float64+float32, all methods, accuracy, solver
    python benchmarks/report.py --quick    # harness check: 1e3 and 1e4 hinges, short repeats, no accuracy/solver
    python benchmarks/report.py --from-json benchmarks/results/throughput_cpu.json   # re-render a saved run

On x86-64 the default path is measured a second time with its kernels built for ``-march=x86-64-v3`` (AVX2 +
FMA: the narrowest vectors of the x86-64 machines in use, on whatever CPU runs the report; a JIT build,
``TORCHBEND_PREBUILT=0 TORCHBEND_CPU_ARCH=x86-64-v3``), float64, rows ``torchbend[x86-64-v3]`` and
``torchbend.backward[x86-64-v3]``, and every CPU target is evaluated for both builds (``--arch-rows``).

Throughput (:mod:`bm_throughput`: torchbend's default path against eager autograd, torch.func,
torch.compile and JAX jit; ns per hinge), the machine's floors (:mod:`floors`: STREAM bandwidth, matmul
flop rate, the measured costs of divisions, square roots and transcendentals, bytes and operations per hinge) and
the ratio to them, compile times, the acceptance targets
(each computed from the measured numbers, marked met or not), a GPU section read from
``benchmarks/results/cuda_*.json`` (written by ``benchmarks/bm_cuda.py`` on a GPU machine), accuracy in
ulps against a 40-digit mpmath reference and the solver-level trade.  No assertions: this only measures
and reports.  The measured record is saved as JSON next to the results (``--raw``).
"""
from __future__ import annotations

import argparse
import glob
import importlib.util
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time

import bm_throughput
import numpy as np
import tables

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")
PLOTS = os.path.join(ROOT, "benchmarks", "plots")
COLORS = {"torchbend": "tab:blue", "torchbend.backward": "tab:cyan", "torchbend.eager": "tab:purple",
          "autograd": "tab:orange", "torch.func": "tab:green", "torch.compile": "tab:brown", "jax": "tab:red"}
FULL_SIZES = [1000, 10_000, 100_000, 1_000_000]
QUICK_SIZES = [1000, 10_000]


DEFAULT_ARCH_ROWS = ["x86-64-v3"] if platform.machine() in ("x86_64", "AMD64") else []


def arch_rows(result: dict, arch: str, sizes, threads, budget: float, min_repeat: int, log=print) -> None:
    """Measure the default path (``torchbend``, ``torchbend.backward``; float64) with the CPU kernels built for
    ``-march=<arch>`` in a child process (JIT build, ``TORCHBEND_PREBUILT=0``) and add its rows to ``result``
    as ``torchbend[<arch>]`` and ``torchbend.backward[<arch>]``, next to the same sizes' other methods; the
    child's kernel build is recorded in ``result["arch_rows"]``.  A child that did not run kernels built for
    ``arch`` is an error (its rows would be the other build's)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "rows.json")
        cmd = [sys.executable, os.path.join(ROOT, "benchmarks", "bm_throughput.py"), "--sizes", *map(str, sizes),
               "--dtypes", "float64", "--methods", "torchbend", "torchbend.backward", "--budget", str(budget),
               "--min-repeat", str(min_repeat), "--json", out] + ([] if threads is None else ["--threads", str(threads)])
        env = dict(os.environ, TORCHBEND_PREBUILT="0", TORCHBEND_CPU_ARCH=arch)
        log(f"default path with the kernels built for -march={arch}: {' '.join(cmd[1:])}")
        subprocess.run(cmd, env=env, check=True)
        with open(out) as f:
            sub = json.load(f)
    built = sub["machine"].get("kernels", {})
    if built.get("march") != arch:
        raise RuntimeError(f"the -march={arch} measurement ran kernels built for {built or 'nothing'}")
    here = os.path.dirname(os.path.abspath(bm_throughput.tb.__file__))
    if built.get("package") not in (None, here):
        raise RuntimeError(f"the -march={arch} measurement imported torchbend from {built['package']}, not {here}")
    shown = ["python", "benchmarks/bm_throughput.py", *cmd[2:cmd.index("--json")], *cmd[cmd.index("--json") + 2:]]
    result.setdefault("arch_rows", {})[arch] = {"kernels": built, "command": " ".join(shown)}
    by_key = {(c["dtype"], c.get("hinges")): c for c in result["configs"]}
    for c in sub["configs"]:
        into = by_key.get((c["dtype"], c.get("hinges")))
        if into is None:  # a size the main run did not measure: keep it as a configuration of its own
            into = dict(c, rows=[])
            result["configs"].append(into)
        for r in c.get("rows", []):
            if r["method"] in ("torchbend", "torchbend.backward"):
                into["rows"].append(dict(r, method=f"{r['method']}[{arch}]"))


# --------------------------------------------------------------------------- plots
def plot_throughput(result: dict, dtype: str, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = tables.index(result)
    ops = tables.OPS
    fig, axes = plt.subplots(1, len(ops), figsize=(4 * len(ops), 3.6))
    for ax, op in zip(axes, ops, strict=True):
        for m in tables.METHODS + [b for b, _ in tables.builds(result)[1:]]:
            pts = sorted((h, r["ns"]) for (mm, o, d, h), r in rows.items()
                         if mm == m and o == op and d == dtype and r.get("ns") is not None)
            if pts:  # another build of the default path: its colour, dashed
                ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-" if m in COLORS else "s--", label=m,
                          color=COLORS.get(m, "tab:blue"), lw=2.5 if m == "torchbend" else 1.2)
        cs = tables.configs(result, dtype)
        if cs:
            fl = [max(tables.floor_ns(result, c, op)[2:]) for c in cs]
            ax.loglog([c["hinges"] for c in cs], fl, "k--", lw=1, label="floor")
        ax.set_title(f"{op} ({dtype})")
        ax.set_xlabel("hinges")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("ns per hinge")
    handles = {}
    for ax in axes:
        for hd, lb in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lb, hd)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=len(handles), fontsize=8)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_accuracy(errs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for ax, q in zip(axes, ["energy", "gradient", "hessian"], strict=True):
        for (m, d, qq), v in sorted(errs.items()):
            if qq != q or d != "float64":
                continue
            v = np.sort(np.maximum(np.array(v), 1e-3))
            ax.semilogx(v, np.linspace(0, 1, len(v)), label=f"{m}")
        ax.set_title(f"{q}, float64: CDF of error")
        ax.set_xlabel("normwise relative error [ulp]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("fraction of hinges")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --------------------------------------------------------------------------- other sections
def accuracy_section() -> tuple[list, dict]:
    if importlib.util.find_spec("mpmath") is None:
        return ["\nmpmath is not installed (`pip install mpmath`): accuracy section skipped.\n"], {}
    import accuracy

    lines, errs_all = [], {}
    for model in ("tan", "quadratic"):
        errs, names = accuracy.errors(model)
        names = np.array(names)
        errs_all[model] = errs
        lines += [f"\n#### model `{model}` ({len(names)} hinges: "
                  + ", ".join(f"{c} {int((names == c).sum())}" for c in dict.fromkeys(names)) + ")\n",
                  "| method | dtype | quantity | median | 90% | max | max per case |", "|---|---|---|---|---|---|---|"]
        for key, v in sorted(errs.items()):
            v = np.array(v)
            per = ", ".join(f"{c} {v[names == c].max():.1f}" for c in dict.fromkeys(names))
            lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {np.median(v):.2f} | {np.quantile(v, 0.9):.2f} | "
                         f"{v.max():.1f} | {per} |")
    plot_accuracy(errs_all["tan"], os.path.join(PLOTS, "accuracy_float64.png"))
    return lines, errs_all


def solver_section(sizes, steps) -> list:
    import bm_solver

    lines = ["\n| mesh | hessian | Newton its/step | max | time/step | final energy [J] | penetration/edge | all converged |",
             "|---|---|---|---|---|---|---|---|"]
    for n in sizes:
        for h in ["exact", "clamp", "abs", "gauss_newton"]:
            r = bm_solver.drape_run(n, h, steps)
            cells = [r["mesh"], h, f"{r['its']:.2f}", str(r["max_its"]), f"{r['seconds'] * 1e3:.1f} ms",
                     f"{r['energy']:.6e}", f"{r['penetration']:.2e}", "yes" if r["converged"] else "NO"]
            lines.append("| " + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
    return lines


def gpu_section(results: str = RESULTS) -> list:
    """Every ``cuda_*.json`` in ``results`` (bm_cuda.py's format); without one, older ``cuda_*.txt`` files verbatim."""
    lines = ["", "## GPU", ""]
    jsons = sorted(glob.glob(os.path.join(results, "cuda_*.json")))
    txts = [] if jsons else sorted(glob.glob(os.path.join(results, "cuda_*.txt")))
    if not jsons and not txts:
        return lines + ["No GPU results yet: on a machine with a CUDA device run `python benchmarks/bm_cuda.py`, "
                        "which writes `benchmarks/results/cuda_<device>.json`, then this report."]
    lines.append("Written by `python benchmarks/bm_cuda.py` (same harness, methods and floors as the CPU tables, "
                 "timed with `torch.cuda.synchronize()`; bandwidth by the same STREAM copy/triad on the device).")
    for path in jsons:
        with open(path) as f:
            res = json.load(f)
        name = os.path.relpath(path, ROOT)
        lines += ["", f"### {res['machine']['device']} (`{name}`, {res.get('date', '?')})", "",
                  f"- {tables.machine_line(res)}", "- default path: " + ", ".join(
                      f"{op} {b}" for op, b in (res["configs"][0].get("backends", {}) if res["configs"] else {}).items()),
                  "", "Targets (float32 and float64 at 1e6 hinges): every op >= 20x the plain autodiff on the same GPU "
                  "and within 3x of the bandwidth floor.", ""]
        lines += tables.targets_table(tables.gpu_targets(res))
        lines += tables.throughput_tables(res) + tables.speedup_tables(res)
        lines += ["", "#### Floors"] + tables.floor_table(res)
        if any(c.get("compile") for c in res["configs"]):
            lines += ["", "#### Compile times"] + tables.compile_table(res)
    for path in txts:
        with open(path) as f:
            text = f.read().rstrip()
        lines += ["", f"### Earlier run, older format (`{os.path.relpath(path, ROOT)}`)", "", "```", text, "```"]
    return lines


def garments_section(results: str = RESULTS) -> list:
    """Every ``garments_*.txt`` in ``results`` (``python benchmarks/garments.py > ...``), verbatim."""
    lines = ["", "## Garments (static solves and 30 implicit steps, one thread)", ""]
    paths = sorted(glob.glob(os.path.join(results, "garments_*.txt")))
    if not paths:
        return lines + ["No garment run recorded: `python benchmarks/garments.py > benchmarks/results/garments_cpu.txt`."]
    lines.append("Written by `python benchmarks/garments.py` (a sleeve on an arm with and without a pin, the skirt scene, "
                 "a towel on a rail; the documented API only), recorded in:")
    for path in paths:
        with open(path) as f:
            text = f.read().rstrip()
        lines += ["", f"### `{os.path.relpath(path, ROOT)}`", "", "```", text, "```"]
    return lines


def recorded(path: str, pattern: str = r"\((\d{4}-\d{2}-\d{2} \d{2}:\d{2}) UTC") -> str:
    """When a results file was run: ``pattern``'s first group in its header (default: "(YYYY-MM-DD HH:MM UTC");
    "" if none: sorted first)."""
    with open(path) as f:
        m = re.search(pattern, f.read(600))
    return m.group(1) if m else ""


def ratios_section(results: str = RESULTS) -> list:
    """The newest ``ratios_*.txt`` in ``results`` (``python benchmarks/bm_ratios.py > ...``: the targets' ratios with
    both sides timed in one process, in turns), verbatim, under the acceptance table (which this run's figures fill)."""
    paths = sorted(glob.glob(os.path.join(results, "ratios_*.txt")),
                   key=lambda p: recorded(p, r"(\d{4}-\d{2}-\d{2} \d{2}:\d{2})"))
    if not paths:
        return []
    with open(paths[-1]) as f:
        text = f.read().rstrip()
    return ["", "### The same ratios timed side by side (`python benchmarks/bm_ratios.py`)", "",
            "The table above divides medians measured one after the other (the x86-64-v3 rows' by a reference measured "
            "in another process, earlier); `bm_ratios.py` times both sides of each ratio in one process, in alternated "
            f"turns.  Its newest record, `{os.path.relpath(paths[-1], ROOT)}` (recorded separately, not by this run):",
            "", "```", text, "```"]


def contact_section(results: str = RESULTS) -> list:
    """The newest ``self_contact_*.txt`` in ``results`` (``python benchmarks/bm_contact.py > ...``), verbatim, and the
    names of the earlier ones."""
    lines = ["", "## Self-contact against the IPC toolkit (one thread)", ""]
    paths = sorted(glob.glob(os.path.join(results, "self_contact_*.txt")), key=recorded)
    if not paths:
        return lines + ["No contact run recorded: `python benchmarks/bm_contact.py --scene half --sizes 12 20 50 100 > "
                        "benchmarks/results/self_contact_<machine>.txt`."]
    lines.append("Written by `python benchmarks/bm_contact.py` (a grid folded onto itself: the pairs' barrier energy, "
                 "gradient and clamp-projected Hessian against `ipctk` on the same scene, a Newton iteration's contact "
                 "work, the broad phase, the cost per pair from 1e3 to 1e5 pairs).  The newest record:")
    with open(paths[-1]) as f:
        text = f.read().rstrip()
    lines += ["", f"### `{os.path.relpath(paths[-1], ROOT)}`", "", "```", text, "```"]
    if len(paths) > 1:
        lines += ["", "Earlier records: " + ", ".join(f"`{os.path.relpath(q, ROOT)}`" for q in reversed(paths[:-1])) + "."]
    return lines


# --------------------------------------------------------------------------- discussion
def _against_floor_and_fastest(result: dict, rows: dict) -> list:
    out = []
    for dt in result["dtypes"]:
        cs = tables.configs(result, dt)
        if not cs:
            continue
        big = cs[-1]
        h = big["hinges"]
        parts, best = [], []
        for op in tables.OPS:
            t = tables.ns(rows, "torchbend", op, dt, h)
            if t is None:
                continue
            parts.append(f"{op} {t / max(tables.floor_ns(result, big, op)[2:]):.1f}x")
            alts = [(tables.ns(rows, m, op, dt, h), m) for m in ("autograd", "torch.func", "torch.compile", "jax")]
            alts = [(ta, m) for ta, m in alts if ta is not None]
            if alts:
                tm, m = min(alts)
                best.append(f"{op} {tm / t:.1f}x over {m}")
        out.append(f"- Default path against its floor at {h:,} hinges ({dt}): " + ", ".join(parts) + ".")
        if best:
            out.append(f"- Against the fastest autodiff for each op at {h:,} hinges ({dt}): " + ", ".join(best) + ".")
    return out


def discussion(result: dict) -> list:
    """Short findings written from the numbers."""
    rows = tables.index(result)
    out = []
    load = result.get("load_before")
    cores = result["machine"].get("cores") or 1
    if load and load[0] > 0.25 * cores:
        out.append(f"- The machine was busy when the run started (load average {load[0]:.1f} over 1 min, {load[2]:.1f} "
                   f"over 15 min, {cores} cores): other processes shared the cores, and multi-threaded eager PyTorch "
                   "(one OpenMP barrier per op) suffers most from that; the numbers are not reference numbers.")
    fl = result["floors"]
    b0, b1 = fl["before"]["bandwidth"], fl["after"]["bandwidth"]
    if abs(b0 - b1) / max(b0, b1) > 0.15:
        out.append(f"- The bandwidth measured before and after the run differs by {abs(b0 - b1) / max(b0, b1):.0%} "
                   f"({b0 / 1e9:.1f} vs {b1 / 1e9:.1f} GB/s): the machine was not quiet; treat the ratios with care.")
    out += _against_floor_and_fastest(result, rows)
    dt = result["dtypes"][0]
    for h in [c["hinges"] for c in tables.configs(result, dt)][-1:]:
        a, b = tables.ns(rows, "torchbend", "hvp", dt, h), tables.ns(rows, "torchbend.backward", "hvp", dt, h)
        if a is not None and b is not None and b > 2 * a:
            out.append(f"- The HVP through torch.autograd (double backward of `bend(x)`) costs {b / a:.1f}x "
                       f"`bend.hvp` at {h:,} hinges ({dt}): code that wants the fast HVP should call `hvp`.")
    fails = {}
    for c in result["configs"]:
        for e in c.get("compile", []):
            for f in e["failures"]:
                fails.setdefault(f.split(":")[0], f.split(":", 1)[1].strip())
        for p in c.get("compile_probes", []):
            if p["error"]:
                fails.setdefault(p["strategy"], p["error"])
    for name, f in fails.items():
        out.append(f"- torch.compile of `{name}` fails ({f[:260]}...); see the compile tables for what is timed instead.")
    bad = [(k, r["err"]) for k, r in rows.items() if r.get("ns") is not None and not r.get("ok", True)]
    if bad:
        out.append(f"- {len(bad)} timed results disagree with the float64 autodiff reference beyond the tolerance "
                   "(marked (!); their timings compare with a wrong result): " + "; ".join(
                       f"{m} {op} {dt} {h:,} ({'non-finite' if err == float('inf') else f'rel. err {err:.1e}'})"
                       for (m, op, dt, h), err in bad[:8]) + ("; ..." if len(bad) > 8 else "") + ".")
    return out


# --------------------------------------------------------------------------- the document
def render(result: dict, quick: bool, acc_lines: list | None, sol_lines: list | None, command: str) -> list:
    cpu = tables.cpu_targets(result, at=(10_000,) if quick else (100_000, 1_000_000))
    met = sum(1 for t in cpu if t[2])
    known = sum(1 for t in cpu if t[2] is not None)
    threads = result["machine"]["threads"]
    md = ["# torchbend benchmarks", ""]
    if quick:
        md += ["> **Quick validation run** (`--quick`: 1e3 and 1e4 hinges, short repeats, no accuracy or solver",
               "> sections). Not the reference numbers: regenerate with `python benchmarks/report.py` on a quiet machine.", ""]
    measured = result.get("command", command)
    md += [f"Generated by `{measured}` on {result.get('date', '?')} (throughput run: {result.get('wall_s', 0) / 60:.1f} min)"
           + ("." if measured == command else f"; rendered by `{command}`."), "",
           f"- machine: {tables.machine_line(result)}",
           f"- bandwidth (STREAM, threads: {threads}, 256 MiB arrays): copy {result['floors']['used']['copy'] / 1e9:.1f} GB/s, "
           f"triad {result['floors']['used']['triad'] / 1e9:.1f} GB/s; matmul flop rate "
           + ", ".join(f"{d} {v / 1e9:.0f} GFLOP/s" for d, v in result["floors"]["used"]["flops"].items()),
           f"- sizes: {', '.join(f'{s:,}' for s in result['sizes'])} target hinges (random curved sheets, `tan` model), "
           f"{', '.join(result['dtypes'])}; median of repeats (about {result['budget']} s of timed calls per "
           f"measurement, at least {result['min_repeat']} and at most 2,000, one for calls over 2 s) after a checked call and a warm-up "
           "call (the checked call is the warm-up of calls over 1 s)",
           "- what the default path (`backend=\"auto\"`) ran:"] + [f"  {line}" for line in tables.backends_line(result)]
    for arch, info in result.get("arch_rows", {}).items():
        md += [f"- `torchbend[{arch}]`, `torchbend.backward[{arch}]`: the same default path with the CPU kernels built "
               f"for `-march={arch}` ({' '.join(info['kernels'].get('cflags', []))}; {info['kernels'].get('source', '?')} "
               f"build), measured on the same machine after the main run: `{info['command']}` with "
               f"`TORCHBEND_PREBUILT=0 TORCHBEND_CPU_ARCH={arch}`"]
    md += ["", "Methods: `torchbend` = the default path's methods (`bend(x)`, `.gradient`, `.hvp`, `.hinge_hessians`, "
           "`.hessian`); `torchbend.backward` = the default path through `torch.autograd` (backward, double backward); "
           "`torchbend.eager` = `backend=\"eager\"`; `autograd` = eager PyTorch of the plain atan2 energy (forward, "
           "backward, double backward); `torch.func` = `grad`, `jvp(grad)`, `vmap(hessian)` (+ `index_add` into the "
           "CSR pattern); `torch.compile` = inductor on the plain energy (strategy per op in the compile table); "
           "`jax` = `jax.jit` of the same energy (`grad`, `jvp(grad)`, `vmap(hessian)`, scatter). Every result is "
           "checked against plain autodiff before it is timed (`benchmarks/bm_throughput.py`).", "",
           "## Acceptance targets (CPU, default path, float64)", "",
           f"{met} of {known} measured targets met. Ratios are the other method's ns per hinge over the default path's, "
           "from the tables below; 'flat' compares each size's ns per hinge with the 1e5 figure."
           + (" **Quick run: the speed-up targets are evaluated at 1e4 hinges, to check the harness only.**"
              if quick else ""), ""]
    md += tables.targets_table(cpu)
    md += ratios_section()
    md += ["", "## Findings", ""] + discussion(result)
    md += ["", "## Throughput", "", "![float64](benchmarks/plots/throughput_float64.png)",
           "![float32](benchmarks/plots/throughput_float32.png)"]
    md += tables.throughput_tables(result) + tables.speedup_tables(result)
    md += ["", "## Floors", "", (floors_doc()), ""] + tables.floor_table(result)
    md += ["", "## Compile times (first call: trace, compile, run; one process per size and dtype, "
           + ("inductor's warm on-disk cache, torch.compile in the first configuration only)" if quick else
              "cold caches)")]
    md += tables.compile_table(result)
    probes = tables.probe_table(result)
    if probes:
        md += ["", "Other formulations, tried after all timings (a failed trace can leave functorch state behind that "
               "breaks later compiles in the same process):"] + probes
    md += gpu_section()
    md += ["", "## Accuracy against a 40-digit reference", ""]
    if acc_lines is None:
        md += ["Not part of this run (`--quick` or `--from-json`); `python benchmarks/accuracy.py` measures it, recorded "
               "runs are in `benchmarks/results/accuracy_*.txt`."]
    else:
        md += ["Normwise relative error `|a - r| / |r|` in units of the dtype's epsilon; the reference (mpmath,",
               "second-order Taylor arithmetic, `benchmarks/accuracy.py`) is evaluated at the inputs as rounded to",
               "each dtype, so the numbers measure the evaluation, not the rounding of the data.", "",
               "![accuracy](benchmarks/plots/accuracy_float64.png)"] + acc_lines
    md += ["", "## Solver-level trade (drape, 0.005 s implicit Euler steps, direct solver)", ""]
    md += (["Not part of this run (`--quick` or `--from-json`); `python benchmarks/bm_solver.py`."]
           if sol_lines is None else sol_lines)
    md += garments_section()
    md += contact_section()
    md += ["", "## Regenerating", "",
           "- `python benchmarks/report.py`: everything above (CPU throughput 1e3..1e6 hinges, float64 and float32, all",
           "  methods; accuracy; solver), roughly 30 to 45 minutes on the 2-core machine when it is quiet (the header",
           "  gives the measured time; the 1e6 configurations, where torch.func and JAX take seconds per call,",
           "  dominate); `--quick` checks the harness in 2 to 5 minutes; `--from-json FILE` re-renders a saved run.",
           "- `python benchmarks/bm_throughput.py --sizes 1e5 --dtypes float64 --methods torchbend autograd`: any subset.",
           "- `python benchmarks/bm_cuda.py` on a GPU machine: the GPU section (`benchmarks/results/cuda_<device>.json`).",
           "- `python benchmarks/bm_hessian.py`, `bm_membrane.py`, `bm_solver.py`: more detail; recorded runs in "
           "`benchmarks/results/`.",
           "- `python benchmarks/bm_lanes.py [--csrc OTHER_TREE]`: the lane functions (bend angle, psi, atan2) compiled "
           "alone for `-march=native` and `x86-64-v3`, timed in turns, with a bitwise checksum across the builds.",
           "- `python benchmarks/bm_ratios.py`: the kernels issue's ratios (energy, gradient, HVP against eager autograd, "
           "the blocks against torch.func) with both sides timed in one process in alternated turns, for this build and "
           "an `x86-64-v3` build (about 15 minutes)."]
    return md


def floors_doc() -> str:
    """The model of :mod:`floors` (its docstring), in Markdown."""
    import re

    import floors

    doc = (floors.__doc__ or "").split("\n\n", 1)[-1].strip()
    doc = re.sub(r":(?:func|mod):`([^`]+)`", r"`floors.\1`", doc)
    return doc.replace("``", "`")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--quick", action="store_true", help="1e3 and 1e4 hinges, short repeats, throughput only")
    p.add_argument("--sizes", type=bm_throughput.parse_size, nargs="+", default=None)
    p.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    p.add_argument("--methods", nargs="+", choices=bm_throughput.METHODS, default=None)
    p.add_argument("--threads", type=int, default=None, help="torch/OpenMP/XLA threads (default: all cores)")
    p.add_argument("--budget", type=float, default=None, help="seconds of timed calls per measurement")
    p.add_argument("--out", default=os.path.join(ROOT, "BENCHMARKS.md"))
    p.add_argument("--raw", default=None, help="where the measured record is saved (default: "
                   "benchmarks/results/throughput_cpu.json, or throughput_cpu_quick.json with --quick)")
    p.add_argument("--from-json", help="render this saved record instead of measuring")
    p.add_argument("--no-accuracy", action="store_true")
    p.add_argument("--no-solver", action="store_true")
    p.add_argument("--arch-rows", nargs="*", default=DEFAULT_ARCH_ROWS, metavar="ARCH",
                   help="also measure the default path with the CPU kernels built for these -march values "
                        f"(default: {' '.join(DEFAULT_ARCH_ROWS) or 'none'}; no value: none)")
    a = p.parse_args(argv)
    os.makedirs(PLOTS, exist_ok=True)
    command = " ".join(["python benchmarks/report.py", *(sys.argv[1:] if argv is None else argv)])
    if a.from_json:
        with open(a.from_json) as f:
            result = json.load(f)
        quick = bool(result.get("quick"))
    else:
        quick = a.quick
        sizes = a.sizes or (QUICK_SIZES if quick else FULL_SIZES)
        budget = a.budget or (0.1 if quick else 1.0)
        print("machine:", tables.machine_line({"machine": __import__("common").machine_info()}), flush=True)
        result = bm_throughput.run_all(sizes, a.dtypes, "cpu", a.methods, budget, 3 if quick else 5,
                                       log=lambda s: print(s, flush=True), threads=a.threads, quick=quick)
        for arch in a.arch_rows:
            arch_rows(result, arch, sizes, a.threads, budget, 3 if quick else 5, log=lambda s: print(s, flush=True))
        result["command"] = command
        raw = a.raw or os.path.join(RESULTS, "throughput_cpu_quick.json" if quick else "throughput_cpu.json")
        os.makedirs(os.path.dirname(raw), exist_ok=True)
        with open(raw, "w") as f:
            json.dump(result, f, indent=0)
        print(f"wrote {raw}", flush=True)
    for dt in result["dtypes"]:
        plot_throughput(result, dt, os.path.join(PLOTS, f"throughput_{dt}.png"))
    acc = sol = None
    if not quick and not a.from_json:
        t0 = time.perf_counter()
        acc = None if a.no_accuracy else accuracy_section()[0]
        sol = None if a.no_solver else solver_section([11, 21], 120)
        print(f"accuracy and solver sections: {time.perf_counter() - t0:.0f} s", flush=True)
    md = render(result, quick, acc, sol, command)
    with open(a.out, "w") as f:
        f.write("\n".join(md) + "\n")
    print(f"wrote {a.out} and plots in {PLOTS}")


if __name__ == "__main__":
    main()
