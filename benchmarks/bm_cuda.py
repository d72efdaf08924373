"""GPU benchmark of the compiled bending operations (CUDA driver) against the autodiff a user would write.

``python benchmarks/bm_cuda.py [--sizes 1e5 1e6] [--out FILE]`` on a machine with a CUDA device: ns per
hinge of energy, gradient, HVP and per-hinge 12x12 blocks through the CUDA kernels, eager autograd of the
plain energy (double backward for the HVP, ``torch.func.hessian`` per hinge for the blocks), on the same GPU,
float32 and float64; and each kernel's bandwidth floor (the bytes it must move per hinge divided by the
measured device-to-device copy bandwidth).
"""
from __future__ import annotations

import argparse
import math

import torch

import torchbend as tb
from torchbend.backends import cuda
from torchbend.testing import plain_bending_energy


def timed(fn, repeat: int = 10) -> float:
    """Median seconds of ``fn()`` on the GPU (CUDA events), after two warm-up calls."""
    for _ in range(2):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeat):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        torch.cuda.synchronize()
        times.append(a.elapsed_time(b) / 1e3)
    return sorted(times)[len(times) // 2]


def copy_bandwidth() -> float:
    """Device-to-device copy bandwidth [bytes/s] (bytes read + written)."""
    src = torch.empty(2**28, dtype=torch.uint8, device="cuda")
    dst = torch.empty_like(src)
    t = timed(lambda: dst.copy_(src))
    return 2 * src.numel() / t


def bytes_per_hinge(op: str, s: int) -> int:
    """Bytes an operation must move per hinge (dtype size ``s``): 4 indices, 12 coordinates gathered, the
    weight a, and its outputs (theta for the fold check; the scatter of 12 values as read + write)."""
    base = 4 * 8 + 12 * s + s + s
    return base + {"energy": s, "gradient": 24 * s, "hvp": 12 * s + 24 * s, "blocks": (144 + 12 + 1) * s}[op]


def case(verts, faces, dtype, bw: float) -> list[str]:
    """The table rows of one mesh and dtype."""
    dev = torch.device("cuda")
    rest = verts.to(dtype)
    gen = torch.Generator().manual_seed(0)
    x = (rest + 0.01 * torch.randn(rest.shape, dtype=dtype, generator=gen)).to(dev)
    v = torch.randn(rest.shape, dtype=dtype, generator=gen).to(dev)
    bend = tb.BendingEnergy(faces, rest, model="tan").to(dev)
    H, hinges = bend.hinge_count, bend.hinges
    p, _ = bend._bind(x, "", "eager")
    w = torch.ones(1, dtype=dtype, device=dev)

    def plain(y):
        return plain_bending_energy(y, hinges, bend.weights, bend.stiffness, bend.rest_angles, "tan")

    def ag_energy():
        with torch.no_grad():
            return plain(x)

    def ag_gradient():
        y = x.detach().requires_grad_()
        return torch.autograd.grad(plain(y), y)[0]

    def ag_hvp():
        y = x.detach().requires_grad_()
        (g,) = torch.autograd.grad(plain(y), y, create_graph=True)
        return torch.autograd.grad(g, y, v)[0]

    def one(x4, a, k, r):
        return plain_bending_energy(x4, torch.arange(4, device=x4.device)[None], a[None], k, r[None], "tan")

    def ag_blocks():
        hess = torch.vmap(torch.func.hessian(one), in_dims=(0, 0, None, 0))
        return hess(x[hinges], bend.weights, bend.stiffness, bend.rest_angles)

    ops = {
        "energy": (lambda: cuda.bending_energy(x, hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model).sum(), ag_energy),
        "gradient": (lambda: cuda.bending_gradient(x, hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model, w, None, False), ag_gradient),
        "hvp": (lambda: cuda.bending_hvp(x, v, hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model, w), ag_hvp),
        "blocks": (lambda: cuda.bending_hessians(x, hinges, p.a, p.k, p.rest, p.c, p.prev, bend.model), ag_blocks),
    }
    s = torch.finfo(dtype).bits // 8
    rows = []
    for name, (fast, ref) in ops.items():
        t_fast = timed(fast)
        try:
            t_ref = timed(ref, repeat=3)
        except torch.OutOfMemoryError:
            t_ref = float("nan")
            torch.cuda.empty_cache()
        floor = bytes_per_hinge(name, s) / bw
        rows.append(f"{H:9d} {str(dtype).split('.')[-1]:>7s} {name:>9s} {t_fast / H * 1e9:10.3f} "
                    f"{t_ref / H * 1e9:14.3f} {t_ref / t_fast:7.1f} {floor * 1e9:10.3f} {t_fast / H / floor:8.2f}")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=float, nargs="+", default=[1e5, 1e6])
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    lines = [f"device: {torch.cuda.get_device_name()}; torch {torch.__version__}"]
    bw = copy_bandwidth()
    lines.append(f"device-to-device copy bandwidth: {bw / 1e12:.2f} TB/s (read + write)")
    lines.append(f"{'hinges':>9s} {'dtype':>7s} {'op':>9s} {'cuda ns/h':>10s} {'autograd ns/h':>14s} {'ratio':>7s} "
                 f"{'floor ns/h':>10s} {'x floor':>8s}")
    for size in args.sizes:
        n = int(math.sqrt(size / 3.0)) + 1
        verts, faces = tb.scenes.grid(n, n)
        for dtype in (torch.float32, torch.float64):
            lines += case(verts, faces, dtype, bw)
            torch.cuda.empty_cache()
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
