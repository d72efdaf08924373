"""Markdown tables from a throughput record (:func:`bm_throughput.run_all`): ns per hinge, speed-ups,
floors, compile times and the acceptance targets, every number computed from the record."""
from __future__ import annotations

import math

import floors

OPS = floors.OPS
METHODS = ["torchbend", "torchbend.backward", "torchbend.eager", "autograd", "torch.func", "torch.compile", "jax"]
REFERENCE = {"energy": "autograd", "gradient": "autograd", "hvp": "autograd", "hinge_hessians": "torch.func",
             "assembly": "torch.func"}
"""The plain-autodiff method a user would otherwise run for each op (the GPU targets' baseline)."""


def index(result: dict) -> dict:
    """``{(method, op, dtype, hinges): row}`` of the measured rows (failed ones included, ``ns`` None)."""
    out = {}
    for c in result["configs"]:
        if not c.get("hinges"):
            continue
        for r in c["rows"]:
            out[(r["method"], r["op"], c["dtype"], c["hinges"])] = r
    return out


def configs(result: dict, dtype: str) -> list:
    return sorted((c for c in result["configs"] if c["dtype"] == dtype and c.get("hinges")), key=lambda c: c["hinges"])


def ns(rows: dict, method: str, op: str, dtype: str, h: int) -> float | None:
    r = rows.get((method, op, dtype, h))
    return None if r is None else r.get("ns")


def nearest(result: dict, dtype: str, target: int) -> int | None:
    """The measured hinge count nearest (in log) to ``target``, if within a factor 2."""
    hs = [c["hinges"] for c in configs(result, dtype)]
    if not hs:
        return None
    h = min(hs, key=lambda h: abs(math.log(h / target)))
    return h if abs(math.log(h / target)) < math.log(2) else None


def _cell(r: dict | None) -> str:
    if r is None:
        return "—"
    if r.get("ns") is None:
        return "fail"
    v = r["ns"]
    s = f"{v:,.0f}" if v >= 100 else f"{v:.1f}" if v >= 1 else f"{v:.3f}"
    return s if r.get("ok", True) else s + " (!)"


def _op_tables(result: dict, title: str, column: str, methods, cells_of) -> list:
    """Per dtype a table ``| op | <column> | one cell per size |``; ``cells_of(rows, method, op, dtype, hinges)``
    gives a row's cells, or ``None`` for no row."""
    rows = index(result)
    lines = []
    for dt in result["dtypes"]:
        cs = configs(result, dt)
        if not cs:
            continue
        hs = [c["hinges"] for c in cs]
        lines += [f"\n### {dt}: {title}\n",
                  f"| op | {column} | " + " | ".join(f"{h:,}" for h in hs) + " |", "|" + "---|" * (2 + len(hs))]
        for op in OPS:
            for m in methods:
                cells = cells_of(rows, m, op, dt, hs)
                if cells is not None:
                    name = f"**{m}**" if m == "torchbend" else m
                    lines.append(f"| {op} | {name} | " + " | ".join(cells) + " |")
    return lines


def _time_cells(rows, m, op, dt, hs) -> list | None:
    cells = [rows.get((m, op, dt, h)) for h in hs]
    return None if all(c is None for c in cells) else [_cell(c) for c in cells]


def _speedup_cells(rows, m, op, dt, hs) -> list | None:
    vals = [(ns(rows, m, op, dt, h), ns(rows, "torchbend", op, dt, h)) for h in hs]
    if all(a is None for a, _ in vals):
        return None
    return ["—" if a is None or b is None else f"{a / b:,.1f}" for a, b in vals]


def throughput_tables(result: dict) -> list:
    rows = index(result)
    methods = METHODS + [m for m, _ in builds(result)[1:]] + [_backward_of(m) for m, _ in builds(result)[1:]]
    lines = _op_tables(result, "ns per hinge (median wall clock, lower is better)", "method", methods, _time_cells)
    bad = [(k, r) for k, r in rows.items() if r.get("ns") is not None and not r.get("ok", True)]
    if bad:
        lines += ["", "(!) disagrees with the plain-autodiff reference beyond the tolerance: "
                  + "; ".join(f"{m} {op} {dt} {h:,}: {r['err']:.1e}" for (m, op, dt, h), r in bad)]
    dead = [c for c in result["configs"] if c.get("failed")]
    if dead:
        lines += ["", "Measurement processes that died (their earlier measurements are kept): "
                  + "; ".join(f"{c['dtype']} ~{c.get('target', 0):,} hinges: {c['failed'][:300]}" for c in dead)]
    failed = [(k, r) for k, r in rows.items() if r.get("ns") is None]
    if failed:
        lines += ["", "fail: " + "; ".join(f"{m} {op} {dt} {h:,}: {r.get('note', '')[:160]}"
                                            for (m, op, dt, h), r in failed)]
    return lines


def speedup_tables(result: dict) -> list:
    """Default path's speed-up over every other method (their ns / its ns)."""
    return _op_tables(result, "speed-up of the default path (`torchbend`) over each method (x, higher is better)",
                      "over", METHODS[1:], _speedup_cells)


def floor_ns(result: dict, c: dict, op: str) -> tuple[float, float, float, float]:
    """``(bytes per hinge, flops per hinge, bandwidth floor ns, compute floor ns)`` of ``op`` in config ``c``
    (records written before the op costs were measured: every op one flop at the matmul rate)."""
    used = result["floors"]["used"]
    s = 8 if c["dtype"] == "float64" else 4
    b = floors.bytes_per_hinge(op, s, c["hinges"], c["vertices"], c["nnz"], c["param_elems"])
    f = c["flops_per_hinge"][op]
    counts = c.get("ops_per_hinge", {}).get(op, {"flops": f})
    costs = used.get("op_costs", {}).get(c["dtype"])
    threads = used.get("threads") or 1
    return (b, f, b / used["bandwidth"] * 1e9,
            floors.compute_floor_ns(counts, used["flops"][c["dtype"]], costs, threads))


def _costs_text(used: dict) -> str:
    costs = {d: c for d, c in used.get("op_costs", {}).items() if c}  # none measured on a GPU
    if not costs:
        return ""
    return (f"; op costs beyond a multiplication's pass [ns per element, one thread; divided by the run's "
            f"{used.get('threads') or 1} thread(s)]: "
            + "; ".join(f"{d} " + ", ".join(f"{k} {v:.2f}" for k, v in c.items()) for d, c in costs.items()))


def floor_table(result: dict) -> list:
    rows = index(result)
    used = result["floors"]["used"]
    lines = ["\n| dtype | op | bytes/hinge | flops/hinge | bandwidth floor [ns] | compute floor [ns] | "
             + " | ".join(f"`torchbend` / floor at {c['hinges']:,}" for c in configs(result, result["dtypes"][0]))
             + " |", "|" + "---|" * (6 + len(configs(result, result["dtypes"][0])))]
    for dt in result["dtypes"]:
        cs = configs(result, dt)
        if not cs:
            continue
        big = cs[-1]
        for op in OPS:
            b, f, tb_, tf = floor_ns(result, big, op)
            ratios = []
            for c in cs:
                t = ns(rows, "torchbend", op, dt, c["hinges"])
                fl = max(floor_ns(result, c, op)[2:])
                ratios.append("—" if t is None else f"{t / fl:,.1f}")
            lines.append(f"| {dt} | {op} | {b:,.0f} | {f:,.0f} | {tb_:.2f} | {tf:.2f} | " + " | ".join(ratios) + " |")
    lines += ["", f"Bandwidth used: {used['bandwidth'] / 1e9:.1f} GB/s (best of STREAM copy and triad, measured before "
              f"and after the run: {result['floors']['before']['bandwidth'] / 1e9:.1f} and "
              f"{result['floors']['after']['bandwidth'] / 1e9:.1f} GB/s); flop rate (matmul): "
              + ", ".join(f"{d} {v / 1e9:.0f} GFLOP/s" for d, v in used["flops"].items())
              + _costs_text(used)
              + ". Bytes and flops per hinge are those of the largest mesh; the ratios use each mesh's own floor "
              "`max(bandwidth floor, compute floor)`."]
    return lines


def compile_table(result: dict) -> list:
    lines = ["\n| method | op | dtype | hinges | strategy | first call [s] | strategies that failed |",
             "|---|---|---|---|---|---|---|"]
    order = {d: i for i, d in enumerate(result["dtypes"])}
    for c in sorted(result["configs"], key=lambda c: (order.get(c["dtype"], 9), c.get("hinges") or 0)):
        for e in c.get("compile", []):
            sec = "—" if e["seconds"] is None else f"{e['seconds']:.1f}"
            fails = "<br>".join(f.replace("|", "\\|")[:200] for f in e["failures"]) or ""
            lines.append(f"| {e['method']} | {e['op']} | {c['dtype']} | {c['hinges'] or 0:,} | {e['strategy'] or '**none**'} "
                         f"| {sec} | {fails} |")
    return lines


def probe_table(result: dict) -> list:
    """Other torch.compile formulations tried after the timings: do they compile and run?"""
    seen = {}
    for c in result["configs"]:
        for p in c.get("compile_probes", []):
            seen.setdefault((p["op"], p["strategy"], p["error"]), []).append(f"{c['dtype']} {c['hinges']:,}")
    if not seen:
        return []
    lines = ["\n| op | strategy | outcome | where |", "|---|---|---|---|"]
    for (op, name, err), where in seen.items():
        outcome = "compiles and runs" if err is None else "fails: " + err.replace("|", "\\|")[:300]
        lines.append(f"| {op} | {name} | {outcome} | {', '.join(where)} |")
    return lines


def backends_line(result: dict) -> list:
    seen = {}
    for c in result["configs"]:
        for op, b in c.get("backends", {}).items():
            seen.setdefault((op, b), []).append(f"{c['dtype']} {c['hinges']:,}")
    return [f"- `{op}`: {b}" + ("" if len(v) == len(result["configs"]) else f" ({', '.join(v)})")
            for (op, b), v in seen.items()]


# --------------------------------------------------------------------------- targets
def _ratio(rows, slow: str, op: str, dt: str, h: int | None, fast: str = "torchbend") -> float | None:
    if h is None:
        return None
    a, b = ns(rows, slow, op, dt, h), ns(rows, fast, op, dt, h)
    return None if a is None or b is None else a / b


def builds(result: dict) -> list[tuple[str, str]]:
    """``(method, label)`` of the default path's builds in the record: ``torchbend`` (the kernels of the record's
    header) and ``torchbend[<arch>]`` (the same operators with the kernels built for ``-march=<arch>``, measured
    on the same machine: ``report.py --arch-rows``)."""
    found = {r["method"] for c in result["configs"] for r in c.get("rows", [])}
    extra = sorted(m for m in found if m.startswith("torchbend[") and m.endswith("]"))
    return [("torchbend", "")] + [(m, f" ({m[len('torchbend['):-1]} build)") for m in extra]


def _backward_of(method: str) -> str:
    """The through-torch.autograd method that goes with a default-path method (``torchbend[a]`` ->
    ``torchbend.backward[a]``)."""
    return method.replace("torchbend", "torchbend.backward", 1)


CPU_SPEEDUPS = [  # (label, op, the method it is compared with, required ratio, through torch.autograd: required)
    ("HVP >= 20x eager autograd double backward (through torch.autograd: >= 10x)", "hvp", "autograd", 20.0, 10.0),
    ("HVP >= 5x JAX jit", "hvp", "jax", 5.0, None),
    ("gradient >= 8x autograd", "gradient", "autograd", 8.0, None),
    ("energy >= 5x autograd", "energy", "autograd", 5.0, None),
    ("energy >= 2x torch.compile", "energy", "torch.compile", 2.0, None),
    ("gradient >= 2x torch.compile", "gradient", "torch.compile", 2.0, None),
    ("HVP >= 2x torch.compile", "hvp", "torch.compile", 2.0, None),
    ("per-hinge blocks >= 100x torch.func", "hinge_hessians", "torch.func", 100.0, None),
    ("sparse assembly >= 10x torch.func + scatter", "assembly", "torch.func", 10.0, None),
]
"""The CPU acceptance ratios (float64, one thread), for every build of :func:`builds`."""

FLOOR_OPS = ("energy", "gradient", "hvp")
"""Ops whose time must be within 3x of their floor (``max(bandwidth floor, compute floor)``)."""


def cpu_targets(result: dict, at=(100_000, 1_000_000)) -> list:
    """``(target, size label, met: bool | None, measured text)`` for the CPU acceptance criteria (float64);
    the speed-up targets at the sizes ``at``; each target once per build in the record (:func:`builds`)."""
    rows = index(result)
    out = []
    for fast, tag in builds(result):
        out += _speedup_rows(result, rows, fast, tag, at)
        out += _floor_rows(result, rows, fast, tag, at)
        out += _flatness_rows(result, rows, fast, tag)
    return out


def _speedup_rows(result: dict, rows, fast: str, tag: str, at) -> list:
    """The speed-up targets of one build (``fast``: its method) at the sizes ``at``."""
    dt, out = "float64", []
    for label, op, slow, need, need_back in CPU_SPEEDUPS:
        for target in at:
            h = nearest(result, dt, target)
            r = _ratio(rows, slow, op, dt, h, fast=fast)
            extra, ok = "", None if r is None else r >= need
            if op in ("gradient", "hvp") and slow == "autograd":
                rb = _ratio(rows, slow, op, dt, h, fast=_backward_of(fast))
                if rb is not None:
                    extra = f" (through torch.autograd: {rb:.1f}x)"
                    if need_back is not None and ok is not None:
                        ok = ok and rb >= need_back
            text = "not measured" if r is None else f"{r:.1f}x{extra}"
            out.append((label + tag, f"{h:,}" if h else f"~{target:,}", ok, text))
    return out


def _floor_rows(result: dict, rows, fast: str, tag: str, at) -> list:
    """Each op of :data:`FLOOR_OPS` within 3x of its floor, one build, at the sizes ``at``."""
    dt, out = "float64", []
    for op in FLOOR_OPS:
        for target in at:
            h = nearest(result, dt, target)
            c = next((c for c in configs(result, dt) if c["hinges"] == h), None)
            t = ns(rows, fast, op, dt, h) if h else None
            label = f"{op} within 3x of its floor" + tag
            if c is None or t is None:
                out.append((label, f"~{target:,}", None, "not measured"))
                continue
            fl = max(floor_ns(result, c, op)[2:])
            out.append((label, f"{h:,}", t / fl <= 3.0, f"{t:.1f} ns vs floor {fl:.2f} ns: {t / fl:.1f}x"))
    return out


def _flatness_rows(result: dict, rows, fast: str, tag: str) -> list:
    """ns per hinge flat from 1e4 to 1e6 and at 1e3 at most 2x the 1e5 figure, one build."""
    dt, out = "float64", []
    h3, h4, h5, h6 = (nearest(result, dt, t) for t in (1000, 10_000, 100_000, 1_000_000))
    for op in OPS:
        ref = ns(rows, fast, op, dt, h5) if h5 else None
        vals = [(h, ns(rows, fast, op, dt, h)) for h in (h4, h5, h6) if h]
        vals = [(h, t) for h, t in vals if t is not None]
        label = f"{op}: ns per hinge flat within +-20% from 1e4 to 1e6" + tag
        if ref is None or len(vals) < 2:
            out.append((label, "", None, "not measured"))
        else:
            rel = [t / ref for _, t in vals]
            out.append((label, ", ".join(f"{h:,}" for h, _ in vals), all(0.8 <= q <= 1.2 for q in rel) and len(vals) == 3,
                        "relative to 1e5: " + ", ".join(f"{q:.2f}" for q in rel)))
        t3 = ns(rows, fast, op, dt, h3) if h3 else None
        label = f"{op}: at 1e3 at most 2x the 1e5 figure" + tag
        if ref is None or t3 is None:
            out.append((label, "", None, "not measured"))
        else:
            out.append((label, f"{h3:,}", t3 / ref <= 2.0, f"{t3:.1f} vs {ref:.1f} ns/hinge: {t3 / ref:.2f}x"))
    return out


def gpu_targets(result: dict) -> list:
    """GPU criteria at 1e6 hinges, float32 and float64: every op >= 20x the plain autodiff on the same GPU
    (eager autograd; torch.func for the blocks and the assembly) and within 3x of the bandwidth floor."""
    rows = index(result)
    out = []
    for dt in ("float32", "float64"):
        h = nearest(result, dt, 1_000_000)
        c = next((c for c in configs(result, dt) if c["hinges"] == h), None)
        for op in OPS:
            r = _ratio(rows, REFERENCE[op], op, dt, h)
            out.append((f"{op} >= 20x {REFERENCE[op]}", f"{dt} {h:,}" if h else dt, None if r is None else r >= 20,
                        "not measured" if r is None else f"{r:.1f}x"))
            t = ns(rows, "torchbend", op, dt, h) if h else None
            if c is None or t is None:
                out.append((f"{op} within 3x of the bandwidth floor", dt, None, "not measured"))
            else:
                fl = floor_ns(result, c, op)[2]
                out.append((f"{op} within 3x of the bandwidth floor", f"{dt} {h:,}", t / fl <= 3.0,
                            f"{t:.3f} ns vs floor {fl:.3f} ns: {t / fl:.1f}x"))
    return out


def targets_table(targets: list) -> list:
    lines = ["| target | hinges | met | measured |", "|---|---|---|---|"]
    for label, where, ok, text in targets:
        met = "n/a" if ok is None else "yes" if ok else "**no**"
        lines.append(f"| {label} | {where} | {met} | {text} |")
    return lines


def machine_line(result: dict) -> str:
    m = result["machine"]
    s = (f"{m['cpu']}, {m['cores']} cores, torch threads: {m['threads']}; torch {m['torch']}, "
         f"jax {m.get('jax') or 'not installed'}, numpy {m.get('numpy', '?')}, python {m['python']}")
    if m.get("vector_extensions") is not None:
        s += f"; vector extensions: {', '.join(m['vector_extensions']) or 'none reported'}"
    k = m.get("kernels")
    if k is not None:
        s += (f"; CPU kernels built for -march={k.get('march', '?')} ({k.get('source', '?')} build)" if k.get("arch")
              else "; CPU kernels: not available (eager path)")
    if m.get("device", "cpu") != "cpu":
        s = f"device: {m['device']} (CUDA {m.get('cuda')}); host " + s
    return s
