"""Bending Hessian benchmark: per-hinge blocks, sparse assembly paths, PSD projections.

    python benchmarks/bm_hessian.py                 # 1e3, 1e4, 1e5 hinges, float64
    python benchmarks/bm_hessian.py --sizes 1000 10000 --dtype float32
    python benchmarks/bm_hessian.py --native        # also the fused C++ kernel (torchbend.native)

Prints, per size: torchbend ``hinge_hessians`` vs ``torch.func.vmap(torch.func.hessian)`` of the
plain per-hinge energy; sparse CSR assembly per hinge vs per triangle vs autodiff blocks + the same
scatter; the cost of each projection; and, on a cloth draped over a sphere, the share of hinges
whose exact block is indefinite (needs projecting).  No assertions on time.
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(__file__))
from common import machine, sheet_for_hinges, timeit  # noqa: E402

import torchbend as tb  # noqa: E402
from torchbend.energies.sparse import HessianPattern  # noqa: E402
from torchbend.testing import plain_bending_energy  # noqa: E402


def autodiff_blocks(bend, x):
    idx = torch.arange(4)[None]

    def e(y4, a, k, r):
        return plain_bending_energy(y4, idx, a[None], k[None], r[None], bend.model)

    k = bend.stiffness.to(x.dtype).expand(bend.hinge_count)
    H = torch.func.vmap(torch.func.hessian(e))(x[bend.hinges], bend.weights.to(x.dtype), k, bend.rest_angles.to(x.dtype))
    return H.reshape(-1, 12, 12)


def run_size(hinges: int, dtype, repeat: int, native: bool = False) -> None:
    n = sheet_for_hinges(hinges)
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3)
    gen = torch.Generator().manual_seed(0)
    x = rest + (0.2 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    H = bend.hinge_count
    pat = HessianPattern(bend.topology)  # built once per topology (not timed below)

    def autodiff_sparse():
        Hb = autodiff_blocks(bend, x)
        vals = x.new_zeros(pat.nnz).index_add_(0, pat.hinge_pos.reshape(-1), Hb.reshape(-1))
        return pat.csr(vals)

    t_tb = timeit(lambda: bend.hinge_hessians(x), repeat)
    t_func = timeit(lambda: autodiff_blocks(bend, x), repeat)
    if native:
        import torchbend.native as nat

        nat.enable()
        t_nat = timeit(lambda: bend.hinge_hessians(x), max(repeat, 7))

        def cold():  # fresh output memory every call (page faults included)
            nat.empty_cache()
            return bend.hinge_hessians(x)

        t_cold = timeit(cold, repeat)
        err_nat = float((bend.hinge_hessians(x) - autodiff_blocks(bend, x)).norm() / autodiff_blocks(bend, x).norm())
        t_nat_hinge = timeit(lambda: bend.hessian(x, assembly="hinge"), max(repeat, 5))
        t_nat_tri = timeit(lambda: bend.hessian(x, assembly="triangle"), max(repeat, 5))
        nat.disable()
    t_hinge = timeit(lambda: bend.hessian(x, assembly="hinge"), repeat)
    t_tri = timeit(lambda: bend.hessian(x, assembly="triangle"), repeat)
    t_ad = timeit(lambda: autodiff_sparse(), repeat)
    err = float((bend.hinge_hessians(x) - autodiff_blocks(bend, x)).norm() / autodiff_blocks(bend, x).norm())
    print(f"\n{H} hinges ({n}x{n} sheet), {pat.nnz} nonzeros, {str(dtype).split('.')[-1]}")
    print(f"  per-hinge blocks   torchbend {t_tb * 1e3:9.2f} ms   torch.func {t_func * 1e3:9.2f} ms   "
          f"ratio {t_func / t_tb:6.1f}x   ({t_tb / H * 1e9:7.0f} ns/hinge, rel. diff {err:.1e})")
    if native:
        print(f"  per-hinge blocks   native    {t_nat * 1e3:9.2f} ms   torch.func {t_func * 1e3:9.2f} ms   "
              f"ratio {t_func / t_nat:6.1f}x   ({t_nat / H * 1e9:7.0f} ns/hinge, rel. diff {err_nat:.1e}; "
              f"{t_tb / t_nat:4.1f}x over eager)")
        print(f"  per-hinge blocks   native, fresh output memory {t_cold * 1e3:9.2f} ms   ratio {t_func / t_cold:6.1f}x   "
              f"({t_cold / H * 1e9:7.0f} ns/hinge; the default reuses the buffer of a dropped result)")
    print(f"  sparse assembly    per hinge {t_hinge * 1e3:9.2f} ms   per triangle {t_tri * 1e3:9.2f} ms   "
          f"autodiff+scatter {t_ad * 1e3:9.2f} ms   (hinge/triangle {t_hinge / t_tri:4.2f}x, "
          f"autodiff/triangle {t_ad / t_tri:5.1f}x)")
    if native:
        print(f"  sparse assembly    native: per hinge {t_nat_hinge * 1e3:9.2f} ms   per triangle {t_nat_tri * 1e3:9.2f} ms   "
              f"(hinge/triangle {t_nat_hinge / t_nat_tri:4.2f}x; native triangle {t_tri / t_nat_tri:4.1f}x faster than eager triangle)")
    line = "  projections (blocks, incl. evaluation)"
    for p in ("clamp", "abs", "gauss_newton", "reduced"):
        t = timeit(lambda: bend.hinge_hessians(x, project=p), max(1, repeat // 2))
        line += f"  {p} {t * 1e3:8.1f} ms"
    print(line)


def drape_report() -> None:
    from drape import drape

    x, faces, bend, info = drape()
    Hb = bend.hinge_hessians(x)
    L = torch.linalg.eigvalsh(Hb)
    lmin, lmax = L[:, 0], L.abs().amax(-1)
    need = lmin < -1e-12 * lmax
    ratio = (-lmin).clamp_min(0) / lmax
    theta = bend.angles(x)
    print(f"\ndraped cloth ({info}), tan model, {bend.hinge_count} hinges, max |theta| {theta.abs().max():.3f} rad, "
          f"median |theta - rest| {(theta - bend.rest_angles).abs().median():.4f} rad")
    print(f"  indefinite exact blocks (lambda_min < -1e-12 |lambda|_max): {int(need.sum())} "
          f"({100 * need.float().mean():.1f}%)")
    for thr in (1e-6, 1e-3, 1e-2, 1e-1):
        share = (ratio > thr).float().mean()
        print(f"  share with |lambda_min| > {thr:g} |lambda|_max: {100 * share:.1f}%")
    gn = bend.hinge_hessians(x, project="gauss_newton")
    lost = (Hb - gn).flatten(1).norm(dim=1) / Hb.flatten(1).norm(dim=1)
    print(f"  gauss_newton drops a median {100 * lost.median():.1f}% (max {100 * lost.max():.1f}%) of each block (Frobenius)")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-drape", action="store_true")
    p.add_argument("--native", action="store_true", help="also time the fused C++ kernel (built on first use)")
    a = p.parse_args(argv)
    print("machine:", machine())
    for h in a.sizes:
        run_size(h, getattr(torch, a.dtype), a.repeat, a.native)
    if not a.no_drape:
        drape_report()


if __name__ == "__main__":
    main()
