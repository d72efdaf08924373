"""Membrane benchmark: projected element Hessians and operators, compiled vs eager, autograd and torch.func.

    python benchmarks/bm_membrane.py                # projected blocks, 1e3, 1e4, 1e5 triangles, float64
    python benchmarks/bm_membrane.py --model-hessian  # the drape's Newton matrix, membrane blocks eager vs compiled
    python benchmarks/bm_membrane.py --operators      # energy, gradient, HVP vs autograd, torch.func (1e3-1e6)
    python benchmarks/bm_membrane.py --operators --with-compile --sizes 100000   # and vs torch.compile
    python benchmarks/bm_membrane.py --compile        # bending + membrane under torch.compile(fullgraph) vs eager

Per size and model, the time to produce PSD-projected element Hessians (T, 9, 9):
  torchbend    : MembraneEnergy.element_hessians(x, projection="clamp") (the compiled kernel on the CPU:
                 closed-form eigensystem, eigenvalues clamped in F-space);
  eager        : the same with backend="eager" (the closed form in PyTorch operations);
  func + eigh  : what a user writes without this library: torch.func.hessian of the plain per-triangle energy
                 (vmap over triangles), torch.linalg.eigh (9x9), clamp (a different, position-space projection);
  check        : the unprojected compiled blocks against torch.func.hessian of the plain energy in float64.
The plain energies are written in the invariants I2 = |F|^2 and J = |f0 x f1| (as a user would), independent of
the library's singular values.  No assertions on time.
"""
from __future__ import annotations

import argparse

import torch
from common import machine, timeit

import torchbend as tb
from torchbend import MembraneEnergy
from torchbend.ops.membrane import deformation_gradient


def plain_density(model: str, F: torch.Tensor, mu, lam) -> torch.Tensor:
    """The energy density of ``F (..., 3, 2)`` as a user writes it, in ``I2 = |F|^2`` and ``J = |f0 x f1|``."""
    f0, f1 = F[..., 0], F[..., 1]
    if model == "stvk":
        G = 0.5 * (F.transpose(-1, -2) @ F - torch.eye(2, dtype=F.dtype))
        tr = G[..., 0, 0] + G[..., 1, 1]
        return mu * (G * G).sum((-1, -2)) + 0.5 * lam * tr * tr
    I2 = (F * F).sum((-1, -2))
    J = torch.linalg.cross(f0, f1, dim=-1).norm(dim=-1)
    if model == "arap":  # sum (s_i - 1)^2 with s1 + s2 = sqrt(I2 + 2 J)
        return mu * (I2 - 2 * torch.sqrt(I2 + 2 * J) + 2)
    if model == "symmetric_dirichlet":  # |F|^2 + |F^+|^2 - 4, |F^+|^2 = I2 / J^2
        return mu * (I2 + I2 / (J * J) - 4)
    lj = torch.log(J)  # neo-Hookean
    return 0.5 * mu * (I2 - 2) - mu * lj + 0.5 * lam * lj * lj


def plain_energy(mem: MembraneEnergy, x: torch.Tensor) -> torch.Tensor:
    """The membrane energy as a user writes it in PyTorch (the reference of the operator rows)."""
    D = mem.shape_matrices.to(x.dtype)
    psi = plain_density(mem.model.value, deformation_gradient(x, mem.faces, D), mem.mu.to(x.dtype), mem.lam.to(x.dtype))
    return (psi * (mem.rest_areas * mem.thickness).to(x.dtype)).sum(-1)


def func_hessians(mem: MembraneEnergy, x: torch.Tensor) -> torch.Tensor:
    """Per-triangle Hessians ``(T, 9, 9)`` by ``torch.func.hessian`` of the plain energy, vmapped over triangles."""
    D = mem.shape_matrices.to(x.dtype)
    coef = (mem.rest_areas * mem.thickness).to(x.dtype)
    mu, lam, model = mem.mu.to(x.dtype), mem.lam.to(x.dtype), mem.model.value

    def one(X, Dk, c):  # X (3 vertices, 3 axes), Dk (3, 2): F = X^T Dk
        return c * plain_density(model, X.transpose(0, 1) @ Dk, mu, lam)

    return torch.func.vmap(torch.func.hessian(one))(x[mem.faces], D, coef).reshape(-1, 9, 9)


def func_eigh_projection(mem: MembraneEnergy, x: torch.Tensor) -> torch.Tensor:
    """torch.func Hessians, eigh, eigenvalues clamped: the generic PSD projection a user writes."""
    L, R = torch.linalg.eigh(func_hessians(mem, x))
    return (R * L.clamp_min(0)[..., None, :]) @ R.transpose(-1, -2)


def measure(mem: MembraneEnergy, x: torch.Tensor, repeat: int) -> str:
    """One row: the projected blocks compiled, eager and by torch.func + eigh; the unprojected ones checked."""
    t_c = timeit(lambda: mem.element_hessians(x, projection="clamp"), repeat)
    t_e = timeit(lambda: mem.element_hessians(x, projection="clamp", backend="eager"), repeat)
    t_f = timeit(lambda: func_eigh_projection(mem, x), repeat)
    ref = func_hessians(mem.double(), x.double())  # the reference in float64 (a float32 one loses digits itself)
    err = float((mem.to(x.dtype).element_hessians(x).double() - ref).abs().max() / ref.abs().max())
    return (f"{mem.face_count:>10d} {mem.model.value:>20s} {t_c * 1e3:10.2f}ms {t_e * 1e3:8.2f}ms {t_f * 1e3:9.2f}ms "
            f"{t_e / t_c:8.1f}x {t_f / t_c:8.1f}x  unprojected vs torch.func max rel. diff {err:.1e}")


def model_hessians(sizes: list[int], repeat: int) -> None:
    """The solver's Newton matrix on the drape of configs/cloth_sphere.yaml (membrane, bending, gravity, the
    sphere): ``ClothModel.hessian(x, "exact")`` with the membrane's unprojected StVK blocks eager (the code
    before they were compiled) and compiled (``backend="auto"``), and the StVK element Hessians alone."""
    import os

    from torchbend.scenes.config import build_scene, load_config

    cfg = load_config(os.path.join(os.path.dirname(__file__), "..", "configs", "cloth_sphere.yaml"))
    print(f"{'size':>8s} {'faces':>7s} {'blocks eager':>13s} {'compiled':>9s} {'ratio':>6s} | "
          f"{'model.hessian eager membrane':>28s} {'compiled':>9s} {'ratio':>6s}  check")
    for n in sizes:
        model, x0, _ = build_scene(cfg, resolution=(n, n))
        gen = torch.Generator().manual_seed(0)
        x = x0 + 0.2 / n * torch.randn(x0.shape, generator=gen, dtype=x0.dtype)
        mem = model.membrane
        assert mem is not None, "the drape has a membrane"
        rows = {}
        for backend in ("eager", "auto"):
            mem.backend = tb.Backend.parse(backend)
            rows[backend] = (timeit(lambda mem=mem, x=x: mem.element_hessians(x), repeat),
                             timeit(lambda model=model, x=x: model.hessian(x, "exact"), repeat),
                             model.hessian(x, "exact"))
        mem.backend = tb.Backend.AUTO
        (be, he, He), (bc, hc, Hc) = rows["eager"], rows["auto"]
        err = float(abs(Hc - He).max() / abs(He).max())
        print(f"{n:4d}x{n:<3d} {mem.face_count:7d} {be * 1e3:11.2f}ms {bc * 1e3:7.2f}ms {be / bc:5.1f}x | "
              f"{he * 1e3:26.2f}ms {hc * 1e3:7.2f}ms {he / hc:5.1f}x  max rel. diff {err:.1e}", flush=True)


def operators(sizes: list[int], dtype: torch.dtype, repeat: int, models: list[str], with_compile: bool = False) -> None:
    """Energy, gradient and HVP of MembraneEnergy (compiled on the CPU) against eager autograd of
    :func:`plain_energy` (its backward, its double backward), torch.func (grad, jvp of grad) and, with
    ``with_compile``, ``torch.compile`` of the plain energy (:func:`compiled_plain`), one mesh."""
    extra = f" {'compile':>10s} {'x compile':>9s}" if with_compile else ""
    print(f"{'triangles':>10s} {'model':>20s} {'op':>9s} {'torchbend':>11s} {'autograd':>10s} {'torch.func':>11s} "
          f"{'x autograd':>10s} {'x func':>8s}{extra}  check")
    for T in sizes:
        n = max(3, round((T / 2) ** 0.5) + 1)
        rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
        gen = torch.Generator().manual_seed(0)
        x = rest * 1.05 + (0.3 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
        v = torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
        for model in models:
            mem = MembraneEnergy(faces, rest, model=model, young=1e5, poisson=0.3, thickness=1e-3).to(dtype)
            operator_rows(mem, x, v, repeat, with_compile)


def compiled_plain(f, x: torch.Tensor, v: torch.Tensor) -> dict:
    """``{op: (strategy, callable) or (error, None)}``: the energy, gradient and HVP of the plain energy ``f`` by
    ``torch.compile`` (inductor, ``dynamic=False``), the first strategy that compiles (as bm_throughput.py: a
    compiled ``autograd.grad``, else the compiled backward; a compiled double ``autograd.grad``, else a compiled
    ``jvp(grad)``); each callable has run once (compiled)."""
    torch._dynamo.reset()  # a fresh cache per mesh and model: no recompile limit reached, no stale guards
    C = lambda g: torch.compile(g, dynamic=False, fullgraph=True)  # noqa: E731

    def grad_fn(y):
        y = y.detach().requires_grad_()
        return torch.autograd.grad(f(y), y)[0]

    def hvp_fn(y, w):
        y = y.detach().requires_grad_()
        (g,) = torch.autograd.grad(f(y), y, create_graph=True)
        return torch.autograd.grad(g, y, w)[0]

    def compiled_backward():
        cp = torch.compile(f, dynamic=False)

        def run():
            y = x.detach().requires_grad_()
            return torch.autograd.grad(cp(y), y)[0]
        return run

    def jvp_grad():
        cf = C(lambda y, w: torch.func.jvp(torch.func.grad(f), (y,), (w,))[1])
        return lambda: cf(x, v)

    def bound(g, *args):
        cg = C(g)
        return lambda: cg(*args)

    strategies = {
        "energy": [("compile(E)", lambda: bound(f, x))],
        "gradient": [("compile(autograd.grad)", lambda: bound(grad_fn, x)), ("compiled backward", compiled_backward)],
        "hvp": [("compile(double autograd.grad)", lambda: bound(hvp_fn, x, v)), ("compile(jvp(grad))", jvp_grad)],
    }
    out = {}
    for op, tries in strategies.items():
        errors = []
        for name, build in tries:
            try:
                fn = build()
                fn()
                out[op] = (name, fn)
                break
            except Exception as e:  # noqa: BLE001  (a strategy that does not compile is reported, not raised)
                errors.append(f"{name}: {type(e).__name__}")
        else:
            out[op] = ("; ".join(errors), None)
    return out


def operator_rows(mem: MembraneEnergy, x: torch.Tensor, v: torch.Tensor, repeat: int,
                  with_compile: bool = False) -> None:
    """The energy, gradient and HVP rows of one membrane."""
    f = lambda y, mem=mem: plain_energy(mem, y)  # noqa: E731

    def ag_grad(x=x, f=f):
        xg = x.clone().requires_grad_()
        return torch.autograd.grad(f(xg), xg)[0]

    def ag_hvp(x=x, v=v, f=f):
        xg = x.clone().requires_grad_()
        (g,) = torch.autograd.grad(f(xg), xg, create_graph=True)
        return torch.autograd.grad((g * v).sum(), xg)[0]

    gfun = torch.func.grad(f)
    rows = {
        "energy": (lambda mem=mem, x=x: mem(x), lambda f=f, x=x: f(x), lambda f=f, x=x: f(x)),
        "gradient": (lambda mem=mem, x=x: mem.gradient(x), ag_grad, lambda g=gfun, x=x: g(x)),
        "hvp": (lambda mem=mem, x=x, v=v: mem.hvp(x, v), ag_hvp,
                lambda g=gfun, x=x, v=v: torch.func.jvp(g, (x,), (v,))[1]),
    }
    compiled = compiled_plain(f, x, v) if with_compile else {}
    for op, (ours, ag, fu) in rows.items():
        t0, t1, t2 = timeit(ours, repeat), timeit(ag, repeat), timeit(fu, repeat)
        ref = ag()
        err = float((ours() - ref).abs().max() / ref.abs().max())
        extra = ""
        if with_compile:
            name, cfn = compiled[op]
            tc = timeit(cfn, repeat) if cfn is not None else None
            extra = f" {tc * 1e3:8.3f}ms {tc / t0:8.1f}x" if tc is not None else f" {'failed':>10s} {'':>9s}"
            extra += f"  [{name}]"
        print(f"{mem.face_count:>10d} {mem.model.value:>20s} {op:>9s} {t0 * 1e3:9.3f}ms {t1 * 1e3:8.3f}ms "
              f"{t2 * 1e3:9.3f}ms {t1 / t0:9.1f}x {t2 / t0:7.1f}x{extra}  max rel. diff {err:.1e}", flush=True)


def compiled_cloth(sizes: list[int], repeat: int, models: list[str]) -> None:
    """A cloth energy of bending (tan) and membrane: its value, and a training step (value, backward), eagerly and
    under ``torch.compile(fullgraph=True)``, one mesh, float64."""
    print(f"{'triangles':>10s} {'model':>20s} {'op':>6s} {'eager':>10s} {'compiled':>10s} {'speedup':>8s}  check")
    for T in sizes:
        n = max(3, round((T / 2) ** 0.5) + 1)
        rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=torch.float64)
        gen = torch.Generator().manual_seed(0)
        x = rest * 1.05 + (0.3 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64)
        bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-4)
        for model in models:
            mem = MembraneEnergy(faces, rest, model=model, young=1e5, poisson=0.3, thickness=1e-3)

            def energy(y, bend=bend, mem=mem):
                return bend(y) + mem(y)

            def step(y, energy=energy):
                value = energy(y)
                value.backward()
                return value.detach()

            torch._dynamo.reset()
            c_energy = torch.compile(energy, fullgraph=True)
            with torch._dynamo.config.patch(trace_autograd_ops=True):
                c_step = torch.compile(step, fullgraph=True)
                y = x.clone().requires_grad_()
                c_step(y)
                for op, eager, comp, arg in (("energy", energy, c_energy, lambda x=x: x),
                                             ("step", step, c_step, lambda x=x: x.clone().requires_grad_())):
                    te = timeit(lambda f=eager, a=arg: f(a()), repeat)
                    tc = timeit(lambda f=comp, a=arg: f(a()), repeat)
                    ulp = float((c_energy(x) - energy(x)).abs() / (torch.finfo(x.dtype).eps * energy(x).abs()))
                    print(f"{mem.face_count:>10d} {model:>20s} {op:>6s} {te * 1e3:8.3f}ms {tc * 1e3:8.3f}ms "
                          f"{te / tc:7.2f}x  energy {ulp:.1f} ulp from eager", flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--model-hessian", type=int, nargs="*", default=None, metavar="N",
                   help="the solver's Newton matrix of the N x N drape instead (default N: 41 81 161)")
    p.add_argument("--operators", action="store_true",
                   help="energy, gradient and HVP against eager autograd and torch.func instead")
    p.add_argument("--with-compile", action="store_true",
                   help="with --operators: also torch.compile of the plain energy (minutes of compiling)")
    p.add_argument("--compile", action="store_true",
                   help="bending + membrane under torch.compile(fullgraph=True) against eager instead")
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    p.add_argument("--models", nargs="+", default=["stvk", "arap", "symmetric_dirichlet", "neohookean"])
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--repeat", type=int, default=3)
    a = p.parse_args(argv)
    dtype = getattr(torch, a.dtype)
    print("machine:", machine())
    if a.operators:
        operators(a.sizes + ([1000000] if a.sizes == [1000, 10000, 100000] else []), dtype, a.repeat, a.models,
                  a.with_compile)
        return
    if a.compile:
        compiled_cloth(a.sizes, a.repeat, a.models)
        return
    if a.model_hessian is not None:
        model_hessians(a.model_hessian or [41, 81, 161], a.repeat)
        return
    print(f"{'triangles':>10s} {'model':>20s} {'torchbend':>12s} {'eager':>10s} {'func+eigh':>11s} "
          f"{'x eager':>9s} {'x func':>9s}  check")
    for T in a.sizes:
        n = max(3, round((T / 2) ** 0.5) + 1)
        rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
        gen = torch.Generator().manual_seed(0)
        x = rest * 1.05 + (0.3 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
        for model in a.models:
            mem = MembraneEnergy(faces, rest, model=model, young=1e5, poisson=0.3, thickness=1e-3)
            print(measure(mem, x, a.repeat))


if __name__ == "__main__":
    main()
