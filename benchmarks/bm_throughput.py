"""Throughput of the bending energy and its derivatives: torchbend's default path against the autodiff
a user would write (eager autograd, torch.func, torch.compile, JAX jit), ns per hinge.

    python benchmarks/bm_throughput.py --quick                         # 1e3, 1e4 hinges: harness check
    python benchmarks/bm_throughput.py --sizes 1e3 1e4 1e5 1e6 --json benchmarks/results/throughput_cpu.json
    python benchmarks/bm_throughput.py --device cuda ...               # the same on a GPU (bm_cuda.py)

Operations (one random curved sheet per size, ``tan`` model, perturbed positions ``x`` and one random
direction ``v``, the same tensors for every method):

``energy``          E(x), scalar (every method under ``torch.no_grad``)
``gradient``        dE/dx, (V, 3)
``hvp``             (d^2E/dx^2) v, (V, 3)
``hinge_hessians``  the per-hinge 12x12 blocks, (H, 12, 12)
``assembly``        the sparse (3V, 3V) Hessian (CSR)

Methods:

``torchbend``           the default path, ``BendingEnergy(...)`` with ``backend="auto"``: ``bend(x)``,
                        ``bend.gradient(x)``, ``bend.hvp(x, v)``, ``bend.hinge_hessians(x)``, ``bend.hessian(x)``
                        (compiled C++/CUDA kernels where they exist; the results name the backend that ran)
``torchbend.out``       (timed with ``torchbend``) ``hinge_hessians`` and ``assembly`` of the default path with
                        caller-owned output buffers kept between the calls: ``bend.hinge_hessians(x, out=Hb)``,
                        ``bend.hessian(x, out=values)`` (what a solver that keeps its buffers runs; fresh outputs
                        page-fault on first touch, which on large meshes costs more than the kernel)
``torchbend.backward``  the default path through torch.autograd: gradient = ``autograd.grad(bend(y), y)``,
                        HVP = double backward (what code that only knows ``bend(x)`` runs)
``torchbend.eager``     the same methods with ``backend="eager"`` (closed forms in eager PyTorch), for reference
``autograd``            eager PyTorch of the plain atan2 energy (:func:`torchbend.testing.plain_bending_energy`):
                        forward, backward, double backward
``torch.func``          ``grad``, ``jvp(grad)``, ``vmap(hessian)`` of the per-hinge energy, that + ``index_add``
                        into the same CSR pattern
``torch.compile``       the same plain energy compiled by inductor (``dynamic=False``): energy; a function
                        returning ``autograd.grad`` (dynamo ``trace_autograd_ops``), else the compiled backward;
                        double ``autograd.grad``, else ``jvp(grad)``; ``vmap(jacrev(jacrev))``.  The first call
                        (compile + run, cold cache when run through :func:`run_isolated`) is recorded as the
                        compile time; strategies that fail are recorded with their error, never raised; at the
                        end, ``vmap(hessian)`` and the double backward of ``compile(E)`` are tried (probes)
``jax``                 ``jax.jit`` of the same plain energy (x64 enabled for float64): ``grad``, ``jvp(grad)``,
                        ``vmap(hessian)``, that + scatter into the same CSR pattern; first call = compile time

Honesty: every method's first call is checked against plain-autodiff references computed beforehand,
in float64 at the same (rounded) inputs: energy, gradient and HVP by autograd; the blocks as
``H_h u_h`` for a random ``u`` per hinge, by ``jvp(grad)`` of the per-hinge energies; the assembled
matrix as its product with ``v`` against the autograd HVP.  The normwise relative error is recorded
(``inf`` for a non-finite output) and flagged above 1e-8 (float64) or 1e-3 (float32).  Then one
warm-up call (none after a checked call over 1 s), then the median of repeats (adaptive count, about
``--budget`` seconds, at least ``--min-repeat`` unless a call takes over 2 s, at most 2,000).  No assertions: this
measures and records.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import traceback

import floors
import torch
from common import bench, machine, machine_info, sheet_for_hinges

import torchbend as tb
from torchbend import backends
from torchbend.energies.sparse import HessianPattern
from torchbend.testing import autograd_gradient, autograd_hvp, plain_bending_energy

OPS = floors.OPS
METHODS = ["torchbend", "torchbend.backward", "torchbend.eager", "autograd", "torch.func", "torch.compile", "jax"]
TOL = {"float64": 1e-8, "float32": 1e-3}
MAX_REPEAT = 2000
"""At most this many timed calls per measurement: fast calls fill the budget (the harness's default of 50 gave a
thousand-hinge energy 3 ms of timed calls and a 1e5-hinge HVP 0.2 s, medians that moved by 20% from run to run)."""
NATIVE_OP = {"energy": "energy", "gradient": "gradient", "hvp": "hvp", "hinge_hessians": "hinge_hessians",
             "assembly": "hessian_triangle"}
"""The name under which :func:`torchbend.backends.select_backend` decides each op of the default path."""


# --------------------------------------------------------------------------- scene and references
def scene(target: int, dtype: torch.dtype, device: torch.device):
    """``(bend, x, v)``: a random curved sheet of about ``target`` hinges, perturbed positions, a direction."""
    n = sheet_for_hinges(target)
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3, check_finite=False).to(device)
    gen = torch.Generator().manual_seed(0)
    x = rest + (0.1 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    v = torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    return bend, x.to(device), v.to(device)


def plain_energy(bend, dtype):
    hinges, a, k, rest = bend.hinges, bend.weights.to(dtype), bend.stiffness.to(dtype), bend.rest_angles.to(dtype)
    idx = torch.arange(4, device=hinges.device)[None]

    def plain(y):
        return plain_bending_energy(y, hinges, a, k, rest, "tan")

    def hinge_e(y4, a_h, r_h):  # one hinge: y4 (4, 3)
        return plain_bending_energy(y4, idx, a_h[None], k, r_h[None], "tan")

    def stencil_sum(x4):  # sum of the per-hinge energies of stencils x4 (H, 4, 3)
        return plain_bending_energy(x4, idx, a[:, None], k, rest[:, None], "tan").sum()

    return plain, hinge_e, stencil_sum, a, rest


class Checker:
    """Plain-autodiff references and the normwise relative error of a method's output against them."""

    def __init__(self, bend, x, v, pattern: HessianPattern):
        """References in float64 whatever the dtype (at the same, rounded inputs): in float32 the plain
        autodiff's second derivatives underflow on fine meshes (the atan2 derivative divides by
        ``((nA . nB)^2 + ...)^2 ~ |e|^16``), so a float32 reference can itself be non-finite."""
        plain, _, stencil_sum, _, _ = plain_energy(bend, torch.float64)
        self.bend, self.x, self.v, self.pattern = bend, x, v, pattern
        gen = torch.Generator().manual_seed(1)
        self.u = torch.randn(bend.hinge_count, 4, 3, generator=gen, dtype=torch.float64).to(x.device)
        xd, vd = x.double(), v.double()
        with torch.no_grad():
            e = plain(xd)
        hvp = autograd_hvp(plain, xd, vd)
        x4 = xd[bend.hinges]
        blocks_u = torch.func.jvp(torch.func.grad(stencil_sum), (x4,), (self.u,))[1]
        self.ref = {"energy": e.reshape(1), "gradient": autograd_gradient(plain, xd).reshape(-1),
                    "hvp": hvp.reshape(-1), "hinge_hessians": blocks_u.reshape(-1), "assembly": hvp.reshape(-1)}

    def signature(self, op: str, out) -> torch.Tensor:
        """What is compared: the output itself; the blocks applied to ``u``; the matrix applied to ``v``."""
        if op == "assembly":
            if not out.is_sparse_csr:  # CSR values in the pattern's order (JAX)
                out = self.pattern.csr(out.to(self.x))
            return out.to(torch.float64) @ self.v.double().reshape(-1)
        out = out.double()
        if op == "hinge_hessians":
            H = self.bend.hinge_count
            return (out.reshape(H, 12, 12) @ self.u.reshape(H, 12, 1)).reshape(-1)
        return out.reshape(-1)

    def error(self, op: str, out) -> float:
        """Normwise relative error (``inf`` if the output has a non-finite entry)."""
        ref = self.ref[op]
        sig = self.signature(op, out)
        if not bool(torch.isfinite(sig).all()):
            return float("inf")
        return float((sig - ref).norm() / ref.norm().clamp_min(1e-300))


def to_torch(out):
    """JAX arrays to torch tensors (CPU)."""
    if isinstance(out, torch.Tensor):
        return out
    import numpy as np

    return torch.from_numpy(np.asarray(out).copy())


# --------------------------------------------------------------------------- methods
def device_csr(pattern: HessianPattern, device: torch.device):
    """``values -> (3V, 3V) CSR tensor`` of the pattern, its index arrays moved to ``device`` once."""
    crow, col = pattern.crow_indices.to(device), pattern.col_indices.to(device)
    return lambda values: torch.sparse_csr_tensor(crow, col, values, size=(pattern.size, pattern.size),
                                                  check_invariants=False)


def torch_methods(bend, x, v, pattern: HessianPattern) -> dict:
    """``{method: {op: fn}}`` of every eager method."""
    plain, hinge_e, _, a, rest = plain_energy(bend, x.dtype)
    hinges = bend.hinges

    def backward_grad():
        y = x.detach().requires_grad_()
        return torch.autograd.grad(bend(y), y)[0]

    def backward_hvp():
        y = x.detach().requires_grad_()
        (g,) = torch.autograd.grad(bend(y), y, create_graph=True)
        return torch.autograd.grad(g, y, v)[0]

    func_grad = torch.func.grad(plain)
    func_blocks = torch.func.vmap(torch.func.hessian(hinge_e))
    pos = pattern.hinge_pos.to(x.device).reshape(-1)
    csr = device_csr(pattern, x.device)

    def func_assembly():
        Hb = func_blocks(x[hinges], a, rest)
        return csr(x.new_zeros(pattern.nnz).index_add_(0, pos, Hb.reshape(-1)))

    kept: dict = {}  # the caller's buffers of torchbend.out, allocated on first use and kept between calls

    def kept_buffer(name: str, shape) -> torch.Tensor:
        if name not in kept:
            kept[name] = x.new_empty(shape)
        return kept[name]

    return {
        "torchbend": {
            "energy": lambda: bend(x),
            "gradient": lambda: bend.gradient(x),
            "hvp": lambda: bend.hvp(x, v),
            "hinge_hessians": lambda: bend.hinge_hessians(x),
            "assembly": lambda: bend.hessian(x),
        },
        "torchbend.out": {
            "hinge_hessians": lambda: bend.hinge_hessians(x, out=kept_buffer("blocks", (bend.hinge_count, 12, 12))),
            "assembly": lambda: bend.hessian(x, out=kept_buffer("values", (bend.hessian_nnz(),))),
        },
        "torchbend.backward": {"gradient": backward_grad, "hvp": backward_hvp},
        "torchbend.eager": {
            "energy": lambda: bend(x, backend="eager"),
            "gradient": lambda: bend.gradient(x, backend="eager"),
            "hvp": lambda: bend.hvp(x, v, backend="eager"),
            "hinge_hessians": lambda: bend.hinge_hessians(x, backend="eager"),
            "assembly": lambda: bend.hessian(x, backend="eager"),
        },
        "autograd": {
            "energy": lambda: plain(x),
            "gradient": lambda: autograd_gradient(plain, x),
            "hvp": lambda: autograd_hvp(plain, x, v),
        },
        "torch.func": {
            "gradient": lambda: func_grad(x),
            "hvp": lambda: torch.func.jvp(func_grad, (x,), (v,))[1],
            "hinge_hessians": lambda: func_blocks(x[hinges], a, rest),
            "assembly": func_assembly,
        },
    }


def compile_strategies(bend, x, v, pattern: HessianPattern) -> tuple[dict, dict]:
    """``(timed, probes)``, each ``{op: [(strategy, builder)]}``: ways to get each op from ``torch.compile`` of
    the plain energy; a builder returns the callable (its first call compiles).  ``timed``: tried in order,
    the first that works is timed.  ``probes``: the natural formulations known to fail in torch 2.13
    (``vmap(hessian)``: dynamo's fake tensors meet forward-mode AD inside vmap; double backward: AOTAutograd
    does not support it), tried after every timing, because a failed trace can leave functorch's
    transform stack in a state that breaks later compiles; their outcome is recorded, not timed."""
    plain, hinge_e, _, a, rest = plain_energy(bend, x.dtype)
    hinges = bend.hinges
    pos = pattern.hinge_pos.to(x.device).reshape(-1)
    csr = device_csr(pattern, x.device)
    C = lambda f: torch.compile(f, dynamic=False, fullgraph=True)  # noqa: E731

    def grad_fn(y):
        y = y.detach().requires_grad_()
        return torch.autograd.grad(plain(y), y)[0]

    def hvp_fn(y, w):
        y = y.detach().requires_grad_()
        (g,) = torch.autograd.grad(plain(y), y, create_graph=True)
        return torch.autograd.grad(g, y, w)[0]

    def compiled_backward():
        cp = torch.compile(plain, dynamic=False)

        def f():
            y = x.detach().requires_grad_()
            return torch.autograd.grad(cp(y), y)[0]
        return f

    def compiled_double_backward():
        cp = torch.compile(plain, dynamic=False)

        def f():
            y = x.detach().requires_grad_()
            (g,) = torch.autograd.grad(cp(y), y, create_graph=True)
            return torch.autograd.grad(g, y, v)[0]
        return f

    def jvp_grad():
        fg = torch.func.grad(plain)
        f = C(lambda y, w: torch.func.jvp(fg, (y,), (w,))[1])
        return lambda: f(x, v)

    def blocks(kind: str):
        inner = torch.func.hessian(hinge_e) if kind == "hessian" else torch.func.jacrev(torch.func.jacrev(hinge_e))
        f = C(lambda y: torch.func.vmap(inner)(y[hinges], a, rest))
        return lambda: f(x)

    def assembly(kind: str):
        inner = torch.func.hessian(hinge_e) if kind == "hessian" else torch.func.jacrev(torch.func.jacrev(hinge_e))
        f = C(lambda y: y.new_zeros(pattern.nnz).index_add_(0, pos, torch.func.vmap(inner)(y[hinges], a, rest).reshape(-1)))
        return lambda: csr(f(x))

    def compiled(f, *args):
        cf = C(f)
        return lambda: cf(*args)

    timed = {
        "energy": [("compile(E)", lambda: compiled(plain, x))],
        "gradient": [("compile(autograd.grad)", lambda: compiled(grad_fn, x)),
                     ("compiled backward", compiled_backward)],
        "hvp": [("compile(double autograd.grad)", lambda: compiled(hvp_fn, x, v)),
                ("compile(jvp(grad))", jvp_grad)],
        "hinge_hessians": [("compile(vmap(jacrev(jacrev)))", lambda: blocks("jacrev"))],
        "assembly": [("compile(vmap(jacrev(jacrev)) + index_add)", lambda: assembly("jacrev"))],
    }
    probes = {
        "hvp": [("double backward of compile(E)", compiled_double_backward)],
        "hinge_hessians": [("compile(vmap(hessian))", lambda: blocks("hessian"))],
        "assembly": [("compile(vmap(hessian) + index_add)", lambda: assembly("hessian"))],
    }
    return timed, probes


def jax_methods(bend, x, v, pattern: HessianPattern):
    """``{op: fn}`` of ``jax.jit`` of the plain energy (outputs blocked until ready), or ``None`` without JAX."""
    try:
        import jax
        import jax.numpy as jnp
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    jd = jnp.float64 if x.dtype == torch.float64 else jnp.float32
    hinges = jnp.asarray(bend.hinges.cpu().numpy())
    a = jnp.asarray(bend.weights.double().cpu().numpy(), dtype=jd)
    rest = jnp.asarray(bend.rest_angles.double().cpu().numpy(), dtype=jd)
    k = float(bend.stiffness)
    xj = jnp.asarray(x.cpu().numpy()).block_until_ready()
    vj = jnp.asarray(v.cpu().numpy()).block_until_ready()

    def hinge_energy(x4, a_h, r_h):
        x0, x1, x2, x3 = x4[0], x4[1], x4[2], x4[3]
        e = x1 - x0
        nA = jnp.cross(e, x2 - x0)
        nB = jnp.cross(x3 - x1, e)
        th = jnp.arctan2(jnp.dot(e / jnp.linalg.norm(e), jnp.cross(nA, nB)), jnp.dot(nA, nB))
        d = 2 * jnp.tan(th / 2) - 2 * jnp.tan(r_h / 2)
        return k * a_h * d * d

    def energy(y):
        return jax.vmap(hinge_energy)(y[hinges], a, rest).sum()

    ejit = jax.jit(energy)
    grad = jax.jit(jax.grad(energy))
    hvp = jax.jit(lambda y, w: jax.jvp(jax.grad(energy), (y,), (w,))[1])
    blocks = jax.jit(lambda y: jax.vmap(jax.hessian(hinge_energy))(y[hinges], a, rest))
    pos = jnp.asarray(pattern.hinge_pos.numpy().reshape(-1)).block_until_ready()
    assemble = jax.jit(lambda y: jnp.zeros(pattern.nnz, jd).at[pos].add(
        jax.vmap(jax.hessian(hinge_energy))(y[hinges], a, rest).reshape(-1)))
    ready = lambda f: (lambda: f().block_until_ready())  # noqa: E731
    return {
        "energy": ready(lambda: ejit(xj)),
        "gradient": ready(lambda: grad(xj)),
        "hvp": ready(lambda: hvp(xj, vj)),
        "hinge_hessians": ready(lambda: blocks(xj)),
        "assembly": ready(lambda: assemble(xj)),
    }


# --------------------------------------------------------------------------- one configuration
def _short(e: BaseException) -> str:
    """The exception's type, first line and, for wrapped errors (dynamo's), the inner error's message."""
    lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
    text = f"{type(e).__name__}: {lines[0][:200] if lines else ''}"
    inner = next((ln for ln in lines[1:] if "got " in ln and "Error" in ln), None)
    if inner:
        text += " ... " + inner[inner.index("got "):][:200]
    return re.sub(r' at "[^"]*":\d+', "", text)


def default_backends(bend, x) -> dict:
    """``{op: "native" | "eager (reason)"}``: what the default path runs for each op here."""
    params = tuple(t.to(x.dtype) for t in (bend.weights, bend.stiffness, bend.rest_angles))
    out = {}
    for op, name in NATIVE_OP.items():
        why = backends.native_unavailable_reason(name, x, *params)
        chosen = backends.select_backend(name, bend.backend, x, *params)
        out[op] = str(getattr(chosen, "value", chosen)) + ("" if why is None else f" ({why})")
    return out


class Measurement:
    """One size and dtype: the scene, the references, and the record the timings go into."""

    def __init__(self, target: int, dtype_name: str, device: str, budget: float, min_repeat: int, log,
                 path: str | None = None):
        self.path = path
        self.dev = dev = torch.device(device)
        self.dtype_name, self.budget, self.min_repeat, self.log = dtype_name, budget, min_repeat, log
        dtype = getattr(torch, dtype_name)
        self.sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else None
        self.bend, self.x, self.v = bend, x, v = scene(target, dtype, dev)
        self.H = H = bend.hinge_count
        self.pattern = HessianPattern(bend.topology)
        self.check = Checker(bend, x, v, self.pattern)
        fb, fx, fv = scene(10_000, dtype, dev) if H > 20_000 else (bend, x, v)
        self.rec = {"hinges": H, "vertices": bend.vertex_count, "nnz": self.pattern.nnz, "dtype": dtype_name,
                    "device": device, "target": target,
                    "param_elems": bend.weights.numel() + bend.rest_angles.numel() + bend.stiffness.numel(),
                    "backends": default_backends(bend, x), "ops_per_hinge": floors.ops_per_hinge(fb, fx, fv),
                    "rows": [], "compile": []}
        self.rec["flops_per_hinge"] = {op: sum(n.values()) for op, n in self.rec["ops_per_hinge"].items()}

    def say(self, method: str, op: str, text: str) -> None:
        self.log(f"  {self.dtype_name} {self.H:>8d} {method:>18s} {op:>15s} {text}")
        if self.path:  # the record so far: survives a process killed for memory
            with open(self.path, "w") as f:
                json.dump(self.rec, f)

    def first_call(self, op: str, fn) -> tuple[float, object]:
        with torch.no_grad() if op == "energy" else torch.enable_grad():
            t0 = time.perf_counter()
            out = fn()
            if self.sync:
                self.sync()
            return time.perf_counter() - t0, out

    def time(self, method: str, op: str, fn, strategy: str | None = None) -> None:
        """Check ``fn``'s output against the reference, then time it; a failure is recorded, not raised."""
        row = {"method": method, "op": op, "strategy": strategy}
        try:
            t_first, out = self.first_call(op, fn)
            err = self.check.error(op, to_torch(out))
            del out
            with torch.no_grad() if op == "energy" else torch.enable_grad():  # the checked call warmed up slow ones
                r = bench(fn, self.sync, budget=self.budget, min_repeat=self.min_repeat, max_repeat=MAX_REPEAT,
                          warmup=0 if t_first > 1.0 else 1)
        except Exception as e:  # an out-of-memory, a method that cannot do the op
            row.update(ns=None, note=_short(e))
            self.rec["rows"].append(row)
            self.say(method, op, f"  failed: {row['note']}")
            if self.dev.type == "cuda":
                torch.cuda.empty_cache()
            return
        H = self.H
        row.update(ns=r["median"] / H * 1e9, min_ns=r["min"] / H * 1e9, repeats=r["repeats"], first_s=t_first,
                   err=err, ok=err <= TOL[self.dtype_name])
        self.rec["rows"].append(row)
        self.say(method, op, f"{row['ns']:10.2f} ns/hinge  ({r['repeats']:2d} runs, rel. err {err:.1e})"
                 + ("" if row["ok"] else "   MISMATCH"))

    def compiled(self) -> None:
        """torch.compile: per op, the first strategy that compiles and runs; the failures before it recorded."""
        if hasattr(torch._dynamo.config, "trace_autograd_ops"):
            torch._dynamo.config.trace_autograd_ops = True  # lets dynamo trace autograd.grad
        method = "torch.compile"
        timed, self._probes = compile_strategies(self.bend, self.x, self.v, self.pattern)
        for op, strategies in timed.items():
            failures = []
            for name, build in strategies:
                t0 = time.perf_counter()
                try:
                    fn = build()
                    self.first_call(op, fn)
                except Exception as e:
                    failures.append(f"{name}: {_short(e)}")
                    self.say(method, op, f"  {name} failed: {_short(e)}")
                    torch._dynamo.reset()
                    continue
                seconds = time.perf_counter() - t0
                self.rec["compile"].append({"method": method, "op": op, "strategy": name, "seconds": seconds,
                                            "failures": failures})
                self.say(method, op, f"  {name}: first call {seconds:.1f} s")
                self.time(method, op, fn, strategy=name)
                break
            else:
                self.rec["compile"].append({"method": method, "op": op, "strategy": None, "seconds": None,
                                            "failures": failures})
                self.rec["rows"].append({"method": method, "op": op, "ns": None, "note": "; ".join(failures)})

    def compile_probes(self) -> None:
        """The strategies of :func:`compile_strategies`'s ``probes``: does each compile and run? (Recorded.)"""
        for op, strategies in getattr(self, "_probes", {}).items():
            for name, build in strategies:
                torch._dynamo.reset()
                t0 = time.perf_counter()
                try:
                    self.first_call(op, build())
                    outcome = None
                except Exception as e:
                    outcome = _short(e)
                self.rec.setdefault("compile_probes", []).append(
                    {"op": op, "strategy": name, "seconds": time.perf_counter() - t0, "error": outcome})
                self.say("torch.compile", op, f"  probe {name}: " + ("works" if outcome is None else f"fails: {outcome}"))

    def jax(self) -> None:
        """jax.jit, built only now: JAX copies its inputs in background threads, which must not overlap the
        other methods' timings."""
        ops = jax_methods(self.bend, self.x, self.v, self.pattern)
        if ops is None:
            self.log("  jax is not installed: skipped")
            return
        for op, fn in ops.items():
            t0 = time.perf_counter()
            try:
                fn()
            except Exception as e:
                self.rec["rows"].append({"method": "jax", "op": op, "ns": None, "note": _short(e)})
                self.say("jax", op, f"  failed: {_short(e)}")
                continue
            self.rec["compile"].append({"method": "jax", "op": op, "strategy": "jax.jit",
                                        "seconds": time.perf_counter() - t0, "failures": []})
            self.time("jax", op, fn, strategy="jax.jit")


def measure(target: int, dtype_name: str, device: str = "cpu", methods=None, budget: float = 1.0,
            min_repeat: int = 3, log=print, path: str | None = None) -> dict:
    """All methods and ops at one size and dtype; returns the configuration's record (JSON-serialisable),
    also written to ``path`` after every measurement if given."""
    m = Measurement(target, dtype_name, device, budget, min_repeat, log, path)
    eager = torch_methods(m.bend, m.x, m.v, m.pattern)
    for method in methods or METHODS:
        if method in eager:
            for op, fn in eager[method].items():
                m.time(method, op, fn)
            if method == "torchbend":  # beside the default rows: the same calls with caller-kept out= buffers
                for op, fn in eager["torchbend.out"].items():
                    m.time("torchbend.out", op, fn)
        elif method == "torch.compile":
            m.compiled()
        elif method == "jax" and m.dev.type == "cpu":
            m.jax()
    m.compile_probes()  # last: a failed trace may leave state behind
    return m.rec


# --------------------------------------------------------------------------- several configurations
def run_isolated(sizes, dtypes, device: str = "cpu", methods=None, budget: float = 1.0, min_repeat: int = 3,
                 log=print, threads: int | None = None, compile_once: bool = False, cold: bool = True) -> list:
    """:func:`measure` for every (size, dtype), each in a fresh process (no allocator or JAX state carried
    from one to the next) with a fresh, empty inductor cache (compile times are cold); ``threads`` sets
    torch's, OpenMP's and XLA's thread counts there (default: theirs); ``compile_once``: torch.compile
    only in the first configuration, ``cold=False``: inductor's usual on-disk cache (quick harness checks)."""
    configs = []
    methods = list(methods or METHODS)
    for i, (dt, size) in enumerate((dt, size) for dt in dtypes for size in sizes):
        ms = [m for m in methods if m != "torch.compile"] if compile_once and i > 0 else methods
        fd, path = tempfile.mkstemp(suffix=".json")
        os.close(fd)
        cache = tempfile.mkdtemp(prefix="inductor_")
        env = dict(os.environ)
        if cold:
            env.update(TORCHINDUCTOR_CACHE_DIR=cache, TRITON_CACHE_DIR=os.path.join(cache, "triton"))
        if threads:
            env["OMP_NUM_THREADS"] = str(threads)
        if threads == 1:  # XLA has no thread-count flag but this one
            env["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
        cmd = [sys.executable, os.path.abspath(__file__), "--single", "--sizes", str(size), "--dtypes", dt,
               "--device", device, "--budget", str(budget), "--min-repeat", str(min_repeat), "--json", path]
        cmd += ["--methods", *ms]
        if threads:
            cmd += ["--threads", str(threads)]
        t0 = time.perf_counter()
        with tempfile.TemporaryFile("w+") as errf:  # a file, not a pipe: a full stderr pipe would block the child
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=errf, text=True, env=env)
            assert proc.stdout is not None
            for line in proc.stdout:
                log(line.rstrip())
            proc.wait()
            errf.seek(0)
            err = errf.read()
        shutil.rmtree(cache, ignore_errors=True)
        try:
            with open(path) as f:
                rec = json.load(f)
        except (OSError, ValueError):
            rec = {"hinges": None, "target": size, "dtype": dt, "device": device, "rows": [], "compile": []}
        if proc.returncode != 0:  # what it measured before it died is kept
            rec["failed"] = f"exit {proc.returncode}: {err[-800:]}"
            log(f"  {dt} {size}: the process failed ({rec['failed']})")
        rec["wall_s"] = time.perf_counter() - t0
        log(f"  {dt} {size}: {rec['wall_s']:.0f} s")
        configs.append(rec)
        os.unlink(path)
    return configs


def measure_floors(device: str = "cpu", dtypes=("float64", "float32")) -> dict:
    """Bandwidth (STREAM copy/triad), matmul flop rate and (CPU) the one-thread op costs per dtype on ``device``."""
    out = floors.stream_bandwidth(device)
    out["flops"] = {dt: floors.matmul_flops(getattr(torch, dt), device) for dt in dtypes}
    out["op_costs"] = {dt: floors.op_costs(getattr(torch, dt), device) for dt in dtypes}
    return out


def run_all(sizes, dtypes, device: str = "cpu", methods=None, budget: float = 1.0, min_repeat: int = 3,
            log=print, threads: int | None = None, quick: bool = False) -> dict:
    """The whole record: machine, floors measured before and after (the larger bandwidth is used), configurations.
    ``quick``: torch.compile in the first configuration only, with inductor's warm on-disk cache."""
    t0 = time.perf_counter()
    load = os.getloadavg()  # other work on the machine: measured before ours starts
    if threads:
        torch.set_num_threads(threads)
    before = measure_floors(device, dtypes)
    log(f"bandwidth {before['bandwidth'] / 1e9:.1f} GB/s (copy {before['copy'] / 1e9:.1f}, triad "
        f"{before['triad'] / 1e9:.1f}); matmul " + ", ".join(f"{d} {f / 1e9:.0f} GFLOP/s" for d, f in before["flops"].items()))
    configs = run_isolated(sizes, dtypes, device, methods, budget, min_repeat, log, threads, compile_once=quick,
                           cold=not quick)
    after = measure_floors(device, dtypes)
    log(f"bandwidth after: {after['bandwidth'] / 1e9:.1f} GB/s")
    best = dict(before)
    best["bandwidth"] = max(before["bandwidth"], after["bandwidth"])
    best["flops"] = {d: max(before["flops"][d], after["flops"][d]) for d in dtypes}
    best["op_costs"] = {d: {k: min(t, after["op_costs"][d][k]) for k, t in before["op_costs"][d].items()}
                        for d in dtypes}
    return {"machine": machine_info(device), "floors": {"before": before, "after": after, "used": best},
            "configs": configs, "sizes": list(sizes), "dtypes": list(dtypes), "budget": budget,
            "min_repeat": min_repeat, "wall_s": time.perf_counter() - t0, "quick": quick, "load_before": list(load),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}


def parse_size(s: str) -> int:
    return int(float(s))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=parse_size, nargs="+", default=[1000, 10_000, 100_000, 1_000_000])
    p.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    p.add_argument("--device", default="cpu")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=None)
    p.add_argument("--budget", type=float, default=1.0, help="seconds of timed calls per measurement (about)")
    p.add_argument("--min-repeat", type=int, default=5)
    p.add_argument("--threads", type=int, default=None, help="torch/OpenMP/XLA threads (default: all cores)")
    p.add_argument("--quick", action="store_true", help="1e3 and 1e4 hinges, budget 0.1 s, 3 repeats, torch.compile "
                   "in the first configuration only and with a warm cache")
    p.add_argument("--json", help="write the record to this JSON file")
    p.add_argument("--single", action="store_true", help=argparse.SUPPRESS)  # one config, this process
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.budget, a.min_repeat = [1000, 10_000], 0.1, 3
    if a.threads:
        torch.set_num_threads(a.threads)
    if a.single:
        try:
            rec = measure(a.sizes[0], a.dtypes[0], a.device, a.methods, a.budget, a.min_repeat,
                          log=lambda s: print(s, flush=True), path=a.json)
        except Exception:
            traceback.print_exc()
            raise
        result = rec
    else:
        print("machine:", machine(), flush=True)
        result = run_all(a.sizes, a.dtypes, a.device, a.methods, a.budget, a.min_repeat,
                         log=lambda s: print(s, flush=True), threads=a.threads, quick=a.quick)
        import tables

        print("\n".join(tables.throughput_tables(result)))
        print("\n".join(tables.floor_table(result)))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(result, f)


if __name__ == "__main__":
    main()
