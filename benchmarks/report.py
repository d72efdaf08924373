"""Regenerate BENCHMARKS.md and the plots in benchmarks/plots/ on this machine (one command).

    python benchmarks/report.py              # full: 1e3..1e6 hinges, float64 and float32 (~15 min on 2 cores)
    python benchmarks/report.py --quick      # 1e3..1e5 hinges (a few minutes)

Sections: throughput (ns per hinge, torchbend vs autograd, torch.func and JAX jit), scaling fits
``t(n) = a n^k``, accuracy in ulps against a 40-digit mpmath reference, the solver-level trade
(Hessian options on the drape scene), and the targets of the benchmark issue, each marked met or
missed.  No assertions anywhere: this only measures and reports.
"""
from __future__ import annotations

import argparse
import datetime
import importlib.util
import os

import bm_throughput
import numpy as np
import torch
from common import machine

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLOTS = os.path.join(ROOT, "benchmarks", "plots")
METHODS = ["torchbend", "autograd", "torch.func", "jax"]
COLORS = {"torchbend": "tab:blue", "autograd": "tab:orange", "torch.func": "tab:green", "jax": "tab:red"}


def fit(ns, ts):
    """Least-squares fit of ``t = a n^k`` in log-log; returns ``(a, k)``."""
    k, loga = np.polyfit(np.log(ns), np.log(ts), 1)
    return float(np.exp(loga)), float(k)


def throughput_tables(rows, dtypes):
    lines = []
    for dt in dtypes:
        sizes = sorted({h for (_, _, d, h) in rows if d == dt})
        lines.append(f"\n### {dt}: ns per hinge (median wall clock; lower is better)\n")
        head = "| operation | method | " + " | ".join(f"{h:,}" for h in sizes) + " |"
        lines += [head, "|" + "---|" * (2 + len(sizes))]
        for op in bm_throughput.OPS:
            for m in METHODS:
                vals = [rows.get((m, op, dt, h)) for h in sizes]
                if all(v is None for v in vals):
                    continue
                cells = " | ".join("—" if v is None else f"{v:,.0f}" for v in vals)
                lines.append(f"| {op} | {m} | {cells} |")
    return lines


def scaling_table(rows, dtype="float64"):
    lines = ["\n| operation | method | a [ns] | k | sizes fitted |", "|---|---|---|---|---|"]
    fits = {}
    for op in bm_throughput.OPS:
        for m in METHODS:
            pts = sorted((h, rows[(m, op, dtype, h)] * h) for (mm, o, d, h) in rows
                         if mm == m and o == op and d == dtype and h >= 5000)
            if len(pts) < 2:
                continue
            a, k = fit([p[0] for p in pts], [p[1] for p in pts])
            fits[(m, op)] = (a, k)
            lines.append(f"| {op} | {m} | {a:.3g} | {k:.3f} | {', '.join(f'{p[0]:,}' for p in pts)} |")
    return lines, fits


def plot_throughput(rows, dtype, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(1, len(bm_throughput.OPS), figsize=(4 * len(bm_throughput.OPS), 3.4), sharey=False)
    for ax, op in zip(axes, bm_throughput.OPS, strict=True):
        for m in METHODS:
            pts = sorted((h, v) for (mm, o, d, h), v in rows.items() if mm == m and o == op and d == dtype)
            if pts:
                ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-", label=m, color=COLORS[m])
        ax.set_title(f"{op} ({dtype})")
        ax.set_xlabel("hinges")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("ns per hinge")
    handles = [Line2D([], [], color=COLORS[m], marker="o", label=m) for m in METHODS]
    axes[-1].legend(handles=handles, fontsize=8)
    fig.tight_layout()
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


def solver_table(sizes, steps):
    import bm_solver

    lines = ["\n| mesh | hessian | Newton its/step | max | time/step | final energy [J] | penetration/edge | all converged |",
             "|---|---|---|---|---|---|---|---|"]
    for n in sizes:
        for h in ["exact", "clamp", "abs", "gauss_newton"]:
            parts = bm_solver.drape(n, h, steps).split()
            lines.append("| " + " | ".join([parts[0], parts[1], parts[2], parts[3], parts[4], parts[5], parts[6], parts[7]]) + " |")
            print(lines[-1], flush=True)
    return lines


def why_text(rows, errs_all) -> list:
    """The explanation under the targets, written from the measured rows."""
    hs = sorted({h for (_, _, d, h) in rows if d == "float64"})
    big = hs[-1]
    faster_jax = [op for op in bm_throughput.OPS if ("jax", op, "float64", big) in rows
                  and rows[("jax", op, "float64", big)] < rows[("torchbend", op, "float64", big)]]
    slower_jax = [op for op in bm_throughput.OPS if ("jax", op, "float64", big) in rows and op not in faster_jax]
    out = [
        "Why speed targets are missed, and what would reach them: torchbend's kernels run as eager PyTorch,",
        "one pass over memory per elementwise operation (a few hundred per hinge for the HVP); the closed",
        "forms save operations and autograd bookkeeping, not passes, so on 2 CPU cores both torchbend and",
        "autograd are memory-bound and the ratios stay small. The kernels process hinges in cache-sized",
        "chunks (`torchbend.ops.stencil.CHUNK`), which keeps their cost per hinge nearly flat.",
        f"At {big:,} hinges (float64) `jax.jit`, which fuses the whole per-hinge computation into one loop, is "
        f"faster than torchbend for: {', '.join(faster_jax) or 'none'}; torchbend is faster for: {', '.join(slower_jax) or 'none'}.",
        "Reaching 10x/50x needs the same fusion for torchbend: compiling the pure per-hinge kernels",
        "(`torchbend/ops/hinge.py`, structure-of-arrays, written for it). The compiled C++ kernels",
        "(`torchbend/csrc`, the default `backend=\"auto\"` on the CPU) do this for the per-hinge Hessians and",
        "the sparse assembly; the `torchbend` rows here are the eager path (`backend=\"eager\"`), the compiled",
        "one is measured by `benchmarks/bm_hessian.py`.",
    ]
    if errs_all:
        out += [
            "Accuracy: the maxima come from the random hinges, several of which are ill-conditioned (nearly",
            "degenerate triangles, theta close to the rest angle); autograd of the plain energy shows maxima of the",
            "same size on the same hinges (per-case column below), so they measure the problem's conditioning,",
            "not the formulas. The adversarial families (flat, near pi, slivers, curved rest) stay within a few ulps.",
        ]
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--quick", action="store_true", help="sizes 1e3..1e5 only, fewer solver steps")
    p.add_argument("--no-jax", action="store_true")
    p.add_argument("--out", default=os.path.join(ROOT, "BENCHMARKS.md"))
    p.add_argument("--raw", default=os.path.join(ROOT, "benchmarks", "results", "throughput_raw.json"),
                   help="where the measured throughput rows are saved")
    p.add_argument("--replot", action="store_true", help="only redraw the throughput plots from --raw")
    a = p.parse_args(argv)
    os.makedirs(PLOTS, exist_ok=True)
    if a.replot:
        import json

        with open(a.raw) as f:
            rows = {(m, op, d, h): v for m, op, d, h, v in json.load(f)}
        for dt in sorted({d for (_, _, d, _) in rows}):
            plot_throughput(rows, dt, os.path.join(PLOTS, f"throughput_{dt}.png"))
        return
    sizes = [1000, 10000, 100000] if a.quick else [1000, 10000, 100000, 1000000]
    dtypes = ["float64", "float32"]
    print("machine:", machine(), flush=True)
    rows = bm_throughput.run_isolated(sizes, dtypes, repeat=3, with_jax=not a.no_jax,
                                      log=lambda s: print(s, flush=True))
    import json

    os.makedirs(os.path.dirname(a.raw), exist_ok=True)
    with open(a.raw, "w") as f:
        json.dump([[m, op, d, h, v] for (m, op, d, h), v in rows.items()], f)
    scal, fits = scaling_table(rows)
    for dt in dtypes:
        plot_throughput(rows, dt, os.path.join(PLOTS, f"throughput_{dt}.png"))
    acc_lines = []
    errs_all = {}
    if importlib.util.find_spec("mpmath") is not None:
        import accuracy

        for model in ("tan", "quadratic"):
            errs, names = accuracy.errors(model)
            names = np.array(names)
            errs_all[model] = errs
            acc_lines += [f"\n#### model `{model}` ({len(names)} hinges: "
                          + ", ".join(f"{c} {int((names == c).sum())}" for c in dict.fromkeys(names)) + ")\n",
                          "| method | dtype | quantity | median | 90% | max | max per case |", "|---|---|---|---|---|---|---|"]
            for key, v in sorted(errs.items()):
                v = np.array(v)
                per = ", ".join(f"{c} {v[names == c].max():.1f}" for c in dict.fromkeys(names))
                acc_lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {np.median(v):.2f} | {np.quantile(v, 0.9):.2f} | "
                                 f"{v.max():.1f} | {per} |")
        plot_accuracy(errs_all["tan"], os.path.join(PLOTS, "accuracy_float64.png"))
    else:
        acc_lines.append("\nmpmath is not installed (`pip install mpmath`): accuracy section skipped.\n")
    sol = solver_table([11, 21], 60 if a.quick else 120)

    # ---------------------------------------------------------------- targets
    big = max(h for (_, _, d, h) in rows if d == "float64" and h <= 1_000_000)
    h5 = min((h for (_, _, d, h) in rows if d == "float64" and h >= 100000), default=big)

    def r(m, op, h=h5, dt="float64") -> float:
        return rows[(m, op, dt, h)]

    targets = []
    hvp_ratio = r("autograd", "hvp") / r("torchbend", "hvp")
    targets.append(("HVP >= 10x faster than autograd double backward (>= 1e5 hinges, float64)", hvp_ratio >= 10,
                    f"{hvp_ratio:.2f}x at {h5:,} hinges"))
    hh_ratio = r("torch.func", "hinge_hessians") / r("torchbend", "hinge_hessians")
    targets.append(("per-hinge Hessians >= 50x faster than torch.func", hh_ratio >= 50, f"{hh_ratio:.1f}x at {h5:,} hinges"))
    g_ratio = r("autograd", "gradient") / r("torchbend", "gradient")
    targets.append(("gradient no slower than autograd", g_ratio >= 1.0, f"{g_ratio:.2f}x at {h5:,} hinges"))
    flat = []
    for op in bm_throughput.OPS:
        vals = [rows[("torchbend", op, "float64", h)] for h in sorted({h for (_, _, d, h) in rows if d == "float64"})
                if h >= 5000 and ("torchbend", op, "float64", h) in rows]
        if len(vals) >= 2:
            flat.append((op, max(vals) / min(vals)))
    worst = max(flat, key=lambda t: t[1]) if flat else ("-", 1.0)
    targets.append(("cost per hinge flat within +-20% from 1e4 to 1e6", worst[1] <= 1.2 / 0.8,
                    "max/min ns per hinge over sizes: " + ", ".join(f"{o} {v:.2f}" for o, v in flat)))
    if errs_all:
        hv = np.array(errs_all["tan"][("torchbend", "float64", "hessian")])
        targets.append(("float64 Hessian error median <= 2 ulp", float(np.median(hv)) <= 2, f"median {np.median(hv):.2f} ulp"))
        targets.append(("float64 Hessian error max <= 8 ulp", float(hv.max()) <= 8, f"max {hv.max():.1f} ulp"))

    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    md = [
        "# torchbend benchmarks",
        "",
        f"Generated by `python benchmarks/report.py{' --quick' if a.quick else ''}` on {now}.",
        "",
        f"- machine: {machine()}",
        f"- torch {torch.__version__}, threads {torch.get_num_threads()}, CUDA: {'yes' if torch.cuda.is_available() else 'no (CPU rows only)'}",
        f"- sizes: {', '.join(f'{s:,}' for s in sizes)} target hinges (random curved sheets, `tan` model)",
        "- methods: `torchbend` (closed forms, eager PyTorch), `autograd` (eager PyTorch of the plain atan2 energy;",
        "  gradient = backward, HVP = double backward), `torch.func` (`grad`, `jvp(grad)`, `vmap(hessian)`),",
        "  `jax` (`jit` of the same plain energy; `jvp(grad)`, `vmap(hessian)`, scatter into the same CSR pattern).",
        "",
        "## Targets",
        "",
        "| target | met | measured |",
        "|---|---|---|",
    ]
    md += [f"| {t} | {'yes' if ok else '**no**'} | {m} |" for t, ok, m in targets]
    md += [
        "",
    ] + why_text(rows, errs_all) + [
        "",
        "## Throughput",
        "",
        "![float64](benchmarks/plots/throughput_float64.png)",
        "![float32](benchmarks/plots/throughput_float32.png)",
    ]
    md += throughput_tables(rows, dtypes)
    md += ["", "## Scaling fits `t(n) = a n^k` (float64, total time in ns, sizes >= 5k hinges)"] + scal
    md += ["", "## Accuracy against a 40-digit reference",
           "",
           "Normwise relative error `|a - r| / |r|` in units of the dtype's epsilon; the reference (mpmath,",
           "second-order Taylor arithmetic, `benchmarks/accuracy.py`) is evaluated at the inputs as rounded to",
           "each dtype, so the numbers measure the evaluation, not the rounding of the data.",
           "",
           "![accuracy](benchmarks/plots/accuracy_float64.png)"] + acc_lines
    md += ["", "## Solver-level trade (drape, 0.005 s implicit Euler steps, direct solver)"] + sol
    md += ["", "Beams (cantilever tip deflection vs Kirchhoff plate theory) and more sizes: `python benchmarks/bm_solver.py`;",
           "results of a full run are in `benchmarks/results/`."]
    with open(a.out, "w") as f:
        f.write("\n".join(md) + "\n")
    print(f"wrote {a.out} and plots in {PLOTS}")


if __name__ == "__main__":
    main()
