"""Throughput of the bending energy and its derivatives: torchbend vs autograd, torch.func and JAX.

    python benchmarks/bm_throughput.py --sizes 1000 10000 100000 --dtypes float64

Operations (one mesh, random curved sheet, tan model): ``energy``, ``gradient``, ``hvp``,
``hinge_hessians`` (12x12 blocks) and ``assembly`` (sparse CSR).  Methods:
``torchbend`` (closed forms, eager PyTorch: ``backend="eager"``, the path whose numbers
BENCHMARKS.md records; the compiled kernels that ``"auto"`` picks for ``hinge_hessians`` and
``assembly`` are measured by ``benchmarks/bm_hessian.py``), ``autograd`` (eager PyTorch of the plain atan2 energy: backward and
double backward), ``torch.func`` (``grad``, ``jvp(grad)``, ``vmap(hessian)``), ``jax`` (``jit`` of
the same plain energy; optional, skipped when JAX is missing).  Reported as ns per hinge (median).
"""
from __future__ import annotations

import argparse
import functools
import os
import sys

import torch
from common import machine, sheet_for_hinges, timeit

import torchbend as tb
from torchbend.energies.sparse import HessianPattern
from torchbend.testing import autograd_gradient, autograd_hvp, plain_bending_energy

OPS = ["energy", "gradient", "hvp", "hinge_hessians", "assembly"]


def _jax_methods(bend, x, v, dtype):
    try:
        import jax
        import jax.numpy as jnp
    except ImportError:
        return None
    jax.config.update("jax_enable_x64", True)
    jd = jnp.float64 if dtype == torch.float64 else jnp.float32
    hinges = jnp.asarray(bend.hinges.numpy())
    a = jnp.asarray(bend.weights.double().numpy(), dtype=jd)
    rest = jnp.asarray(bend.rest_angles.double().numpy(), dtype=jd)
    k = float(bend.stiffness)
    xj = jnp.asarray(x.double().numpy(), dtype=jd).block_until_ready()
    vj = jnp.asarray(v.double().numpy(), dtype=jd).block_until_ready()

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

    grad = jax.jit(jax.grad(energy))
    hvp = jax.jit(lambda y, w: jax.jvp(jax.grad(energy), (y,), (w,))[1])
    blocks = jax.jit(lambda y: jax.vmap(jax.hessian(hinge_energy))(y[hinges], a, rest))
    pat = HessianPattern(bend.topology)
    pos = jnp.asarray(pat.hinge_pos.numpy().reshape(-1)).block_until_ready()
    assemble = jax.jit(lambda y: jnp.zeros(pat.nnz, jd).at[pos].add(blocks(y).reshape(-1)))
    ejit = jax.jit(energy)
    run = lambda f: (lambda: f().block_until_ready())  # noqa: E731
    return {
        "energy": run(lambda: ejit(xj)),
        "gradient": run(lambda: grad(xj)),
        "hvp": run(lambda: hvp(xj, vj)),
        "hinge_hessians": run(lambda: blocks(xj)),
        "assembly": run(lambda: assemble(xj)),
    }


def methods(bend, x, v):
    hinges, a, k, rest = bend.hinges, bend.weights.to(x.dtype), bend.stiffness.to(x.dtype), bend.rest_angles.to(x.dtype)

    def plain(y):
        return plain_bending_energy(y, hinges, a, k, rest, "tan")

    ag_grad = functools.partial(autograd_gradient, plain, x)
    ag_hvp = functools.partial(autograd_hvp, plain, x, v)

    idx = torch.arange(4)[None]

    def hinge_e(y4, a_h, r_h):
        return plain_bending_energy(y4, idx, a_h[None], k, r_h[None], "tan")

    func_blocks = torch.func.vmap(torch.func.hessian(hinge_e))
    pat = HessianPattern(bend.topology)

    def func_assembly():
        Hb = func_blocks(x[hinges], a, rest).reshape(-1, 144)
        return pat.csr(x.new_zeros(pat.nnz).index_add_(0, pat.hinge_pos.reshape(-1), Hb.reshape(-1)))

    func_grad = torch.func.grad(plain)
    out = {
        "torchbend": {
            "energy": lambda: bend(x),
            "gradient": lambda: bend.gradient(x),
            "hvp": lambda: bend.hvp(x, v),
            "hinge_hessians": lambda: bend.hinge_hessians(x),
            "assembly": lambda: bend.hessian(x, assembly="triangle"),
        },
        "autograd": {"energy": lambda: plain(x), "gradient": ag_grad, "hvp": ag_hvp},
        "torch.func": {
            "gradient": lambda: func_grad(x),
            "hvp": lambda: torch.func.jvp(func_grad, (x,), (v,))[1],
            "hinge_hessians": lambda: func_blocks(x[hinges], a, rest),
            "assembly": func_assembly,
        },
    }
    return out


def run(sizes, dtypes, repeat: int, with_jax: bool = True, log=print):
    """Returns rows ``{(method, op, dtype, hinges): ns_per_hinge}``."""
    rows = {}
    for dt_name in dtypes:
        dtype = getattr(torch, dt_name)
        for target in sizes:
            n = sheet_for_hinges(target)
            rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
            bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3, check_finite=False, backend="eager")
            gen = torch.Generator().manual_seed(0)
            x = rest + (0.1 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
            v = torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
            H = bend.hinge_count
            ms = methods(bend, x, v)
            r = repeat if H <= 200_000 else 1
            for method in list(ms) + (["jax"] if with_jax else []):
                if method == "jax":
                    # built only now: JAX copies its inputs in background threads, which must not
                    # overlap the other methods' timings
                    ops = _jax_methods(bend, x, v, dtype)
                    if ops is None:
                        continue
                else:
                    ops = ms[method]
                for op, fn in ops.items():
                    with torch.no_grad() if op == "energy" else torch.enable_grad():
                        t = timeit(fn, r)
                    rows[(method, op, dt_name, H)] = t / H * 1e9
                    log(f"  {dt_name} {H:>8d} hinges {method:>11s} {op:>15s} {t / H * 1e9:10.1f} ns/hinge")
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    p.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-jax", action="store_true")
    p.add_argument("--json", help="also write the rows to this JSON file")
    a = p.parse_args(argv)
    print("machine:", machine())
    rows = run(a.sizes, a.dtypes, a.repeat, with_jax=not a.no_jax)
    if a.json:
        import json

        with open(a.json, "w") as f:
            json.dump([[m, op, d, h, v] for (m, op, d, h), v in rows.items()], f)


def run_isolated(sizes, dtypes, repeat: int, with_jax: bool = True, log=print) -> dict:
    """:func:`run` with every (size, dtype) in a fresh process, so that one method's memory
    (allocator state, JAX buffers) does not slow the next size down."""
    import json
    import subprocess
    import tempfile

    rows = {}
    for dt in dtypes:
        for size in sizes:
            with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
                path = f.name
            cmd = [sys.executable, os.path.abspath(__file__), "--sizes", str(size), "--dtypes", dt,
                   "--repeat", str(repeat), "--json", path] + ([] if with_jax else ["--no-jax"])
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                log(f"  {dt} {size}: failed: {proc.stderr[-500:]}")
                continue
            for line in proc.stdout.splitlines()[1:]:
                log(line)
            with open(path) as f:
                for m, op, d, h, v in json.load(f):
                    rows[(m, op, d, h)] = v
            os.unlink(path)
    return rows


if __name__ == "__main__":
    main()
