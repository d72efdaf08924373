"""Membrane projection benchmark: closed-form eigensystem vs numerical eigendecomposition.

    python benchmarks/bm_membrane.py                # 1e3, 1e4, 1e5 triangles, float64

Per size and model, the time to produce PSD-projected element Hessians (T, 9, 9):
  closed form  : MembraneEnergy.element_hessians(x, projection="clamp") (eigenvalues clamped in F-space);
  eigh (F)     : the same F-space Hessian rebuilt densely, torch.linalg.eigh (6x6), clamp, map with dF/dx;
  eigh (x)     : the unprojected 9x9 position-space blocks, torch.linalg.eigh (9x9), clamp (a different,
                 generic projection that many codes use).
No assertions on time.
"""
from __future__ import annotations

import argparse

import torch
from common import machine, timeit

import torchbend as tb
from torchbend import MembraneEnergy
from torchbend.ops.membrane import deformation_gradient, eigensystem


def numerical_f_projection(mem: MembraneEnergy, x: torch.Tensor) -> torch.Tensor:
    D = mem.shape_matrices.to(x.dtype)
    F = deformation_gradient(x, mem.faces, D)
    l, Q, _, _ = eigensystem(mem.model, F, mem.mu.to(x.dtype), mem.lam.to(x.dtype))
    M = (Q * l[..., None, :]) @ Q.transpose(-1, -2)  # dense F-space Hessian (T, 6, 6)
    L, R = torch.linalg.eigh(M)
    M = (R * L.clamp_min(0)[..., None, :]) @ R.transpose(-1, -2)
    # B = df/dx: (T, 6, 9) with df[a,b]/dx_k[a'] = delta_aa' D[k, b]
    eye = torch.eye(3, dtype=x.dtype)
    B = torch.einsum("ac,tkb->tabkc", eye, D).reshape(-1, 6, 9)
    coef = (mem.rest_areas * mem.thickness).to(x.dtype)
    return coef[:, None, None] * (B.transpose(-1, -2) @ M @ B)


def numerical_x_projection(mem: MembraneEnergy, x: torch.Tensor) -> torch.Tensor:
    He = mem.element_hessians(x)
    L, R = torch.linalg.eigh(He)
    return (R * L.clamp_min(0)[..., None, :]) @ R.transpose(-1, -2)


def measure(mem: MembraneEnergy, x: torch.Tensor, repeat: int) -> str:
    """One row: the three projections timed on ``x``, and the closed form against eigh (F)."""
    t_c = timeit(lambda: mem.element_hessians(x, projection="clamp"), repeat)
    t_f = timeit(lambda: numerical_f_projection(mem, x), repeat)
    t_x = timeit(lambda: numerical_x_projection(mem, x), repeat)
    ref = numerical_f_projection(mem, x)
    err = float((mem.element_hessians(x, projection="clamp") - ref).norm() / ref.norm())
    return (f"{mem.face_count:>10d} {mem.model.value:>20s} {t_c * 1e3:10.2f}ms {t_f * 1e3:8.2f}ms {t_x * 1e3:8.2f}ms "
            f"{t_f / t_c:8.2f}x {t_x / t_c:8.2f}x  closed vs eigh(F) rel. diff {err:.1e}")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    p.add_argument("--models", nargs="+", default=["stvk", "arap", "symmetric_dirichlet", "neohookean"])
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--repeat", type=int, default=3)
    a = p.parse_args(argv)
    dtype = getattr(torch, a.dtype)
    print("machine:", machine())
    print(f"{'triangles':>10s} {'model':>20s} {'closed form':>12s} {'eigh (F)':>10s} {'eigh (x)':>10s} "
          f"{'F/closed':>9s} {'x/closed':>9s}  check")
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
