"""Demo: bending energy, gradient and Hessian-vector product on a curved sheet, against autograd.

    python examples/demo.py                 # small embedded default (about 30k hinges, float64)
    python examples/demo.py --n 185 --dtype float32 --model quadratic
    python examples/demo.py --device cuda   # on a GPU (an unavailable device exits with one line)

Builds a random curved sheet (its own rest shape), deforms it (a smooth wave plus noise), and evaluates the energy, the
gradient and the HVP three ways: torchbend's closed forms (``bend.gradient``/``bend.hvp`` and the
double backward through the custom Function) and plain autograd of the SPEC's atan2 energy
(:mod:`torchbend.testing`).  Prints relative errors and median wall-clock times side by side.
"""
from __future__ import annotations

import argparse
import functools
import platform

import torch

import torchbend as tb
from torchbend.scenes import cli
from torchbend.testing import autograd_gradient, autograd_hvp, median_time, plain_bending_energy


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(torch.finfo(b.dtype).tiny))


def run(n: int = 100, model: str = "tan", dtype: str = "float64", repeat: int = 5, seed: int = 0,
        device: str = "cpu") -> dict:
    """Run the comparison on an ``n x n`` sheet on ``device``; returns the measured numbers."""
    dt, dev = getattr(torch, dtype), torch.device(device)
    gen = torch.Generator().manual_seed(seed)
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=seed, dtype=dt, device=dev)
    bend = tb.BendingEnergy(faces, rest, model=model, stiffness=1e-3)
    # a smooth bending wave plus a little noise (a fraction of the grid spacing)
    wave = 0.05 * torch.sin(2 * torch.pi * rest[:, 0]) * torch.cos(3 * torch.pi * rest[:, 1])
    noise = (0.05 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype=dt, device=dev)
    x = rest + noise + torch.stack((torch.zeros_like(wave), torch.zeros_like(wave), wave), -1)
    v = torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype=dt, device=dev)
    H = bend.hinge_count
    plain = lambda y: plain_bending_energy(y, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, model)  # noqa: E731

    tb_double_backward = functools.partial(autograd_hvp, bend, x, v)  # torchbend's analytic double backward
    tb_grad_backward = functools.partial(autograd_gradient, bend, x)
    ag_grad = functools.partial(autograd_gradient, plain, x)  # autograd of the plain energy
    ag_hvp = functools.partial(autograd_hvp, plain, x, v)

    # accuracy: against autograd in float64 (independent of the working dtype)
    x64, v64 = x.double(), v.double()
    bend64 = tb.BendingEnergy(faces, rest.double(), model=model, stiffness=1e-3)
    y = x64.clone().requires_grad_()
    E_ref = plain_bending_energy(y, bend64.hinges, bend64.weights, bend64.stiffness, bend64.rest_angles, model)
    (g_ref,) = torch.autograd.grad(E_ref, y, create_graph=True)
    (h_ref,) = torch.autograd.grad(g_ref, y, v64)
    errors = {
        "energy": abs(float(bend(x)) - float(E_ref.detach())) / abs(float(E_ref.detach())),
        "gradient": _rel(bend.gradient(x).double(), g_ref.detach()),
        "hvp": _rel(bend.hvp(x, v).double(), h_ref),
        "double_backward": _rel(tb_double_backward().double(), h_ref),
    }
    def timed(fn):  # the wall time of fn including the device's queued work
        if dev.type != "cuda":
            return median_time(fn, repeat)
        return median_time(lambda: (fn(), torch.cuda.synchronize(dev)), repeat)

    with torch.no_grad():
        t_energy = timed(lambda: bend(x))
        t_energy_ag = timed(lambda: plain(x))
    timings = {
        "energy": (t_energy, t_energy_ag),
        "gradient": (timed(lambda: bend.gradient(x)), timed(ag_grad)),
        "energy+backward": (timed(tb_grad_backward), timed(ag_grad)),
        "hvp": (timed(lambda: bend.hvp(x, v)), timed(ag_hvp)),
        "double backward": (timed(tb_double_backward), timed(ag_hvp)),
    }
    print(
        f"torchbend demo: {n}x{n} sheet, {bend.vertex_count} vertices, {H} hinges, model={model}, {dtype}, {dev}\n"
        f"machine: {platform.machine()} {platform.processor() or ''} | torch {torch.__version__} | "
        f"threads {torch.get_num_threads()}"
    )
    print(f"energy = {float(bend(x)):.6e} J")
    print("relative error against float64 autograd of the plain atan2 energy:")
    for k, e in errors.items():
        print(f"  {k:<16s} {e:.2e}")
    print(f"median time over {repeat} runs (torchbend vs autograd of the plain energy):")
    print(f"  {'operation':<16s} {'torchbend':>11s} {'autograd':>11s} {'speed-up':>9s}")
    for k, (a, b) in timings.items():
        print(f"  {k:<16s} {a * 1e3:9.2f}ms {b * 1e3:9.2f}ms {b / a:8.1f}x")
    return {"hinges": H, "errors": errors, "timings": timings}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--n", type=int, default=100, help="vertices per side of the sheet (default 100)")
    p.add_argument("--model", default="tan", choices=["quadratic", "tan", "sin"])
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:1, ... (default cpu)")
    a = p.parse_args(argv)
    device = cli.resolve_device(a.device, prog=p.prog)
    if a.n < 2:
        p.error("--n must be >= 2")
    if a.repeat < 1:
        p.error("--repeat must be >= 1")
    run(a.n, a.model, a.dtype, a.repeat, a.seed, str(device))


if __name__ == "__main__":
    main()
