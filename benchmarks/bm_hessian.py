"""Bending Hessian benchmark: per-hinge blocks, sparse assembly paths, PSD projections.

    python benchmarks/bm_hessian.py                 # 1e3, 1e4, 1e5 hinges, float64
    python benchmarks/bm_hessian.py --sizes 1000 10000 --dtype float32
    python benchmarks/bm_hessian.py --native        # also the compiled C++ kernels (backend="native")

Prints, per size: torchbend ``hinge_hessians`` in eager PyTorch (``backend="eager"``) vs
``torch.func.vmap(torch.func.hessian)`` of the plain per-hinge energy; sparse CSR assembly per hinge vs
per triangle vs autodiff blocks + the same scatter; the cost of each projection (eager); with
``--native`` the same blocks, projections and assemblies by the compiled kernels, and first the cost of fresh
output memory vs ``out=`` buffers; and, on a cloth draped over a sphere, the share of hinges whose
exact block is indefinite (needs projecting).  No assertions on time.
"""
from __future__ import annotations

import argparse

import torch
from common import machine, sheet_for_hinges, timeit

import torchbend as tb
from torchbend.energies.sparse import HessianPattern
from torchbend.testing import plain_bending_energy


def autodiff_blocks(bend, x):
    idx = torch.arange(4)[None]

    def e(y4, a, k, r):
        return plain_bending_energy(y4, idx, a[None], k[None], r[None], bend.model)

    k = bend.stiffness.to(x.dtype).expand(bend.hinge_count)
    H = torch.func.vmap(torch.func.hessian(e))(x[bend.hinges], bend.weights.to(x.dtype), k, bend.rest_angles.to(x.dtype))
    return H.reshape(-1, 12, 12)


def scene(hinges: int, dtype):
    """``(bend, x, n)``: a curved ``n x n`` sheet with about ``hinges`` hinges, tan model, perturbed positions."""
    n = sheet_for_hinges(hinges)
    rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.2, seed=0, dtype=dtype)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3)
    gen = torch.Generator().manual_seed(0)
    x = rest + (0.2 / n) * torch.randn(rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    return bend, x, n


def native_blocks(bend, x, out=None):
    """The compiled blocks kernel called directly (no input checks), into ``out=(Hb, g)`` if given."""
    from torchbend.backends import native

    return native.bending_hessians(x, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, None, None,
                                   bend.model, out=out)


def out_buffers(bend, x):
    H = bend.hinge_count
    return x.new_empty(H, 12, 12), x.new_empty(H, 12)


def output_memory_probe(sizes, dtype, repeat: int) -> None:
    """Fresh outputs vs caller-provided ``out=`` buffers, measured first, on a heap that no eager run has
    grown yet: outputs above glibc's largest mmap threshold (32 MiB: the blocks of about 29k hinges in
    float64) are then mapped and page-faulted on every call.  Later in the process, freed eager
    temporaries usually leave a heap large enough to serve them (the 'native' rows below)."""
    print("native blocks, output memory (clean heap: before any eager run)")
    for h in sizes:
        bend, x, _ = scene(h, dtype)
        H = bend.hinge_count
        t_fresh, t_out = time_fresh_and_out(bend, x, max(repeat, 7))
        mib = H * (144 + 12 + 1) * x.element_size() / 2**20
        print(f"  {H:7d} hinges ({mib:6.1f} MiB of outputs)   fresh outputs {t_fresh / H * 1e9:6.0f} ns/hinge   "
              f"out= buffers {t_out / H * 1e9:6.0f} ns/hinge   ({t_fresh / t_out:4.1f}x)")


def time_fresh_and_out(bend, x, repeat: int) -> tuple[float, float]:
    """Seconds of the compiled blocks kernel with fresh outputs and into reused ``out=`` buffers."""
    out = out_buffers(bend, x)
    return timeit(lambda: native_blocks(bend, x), repeat), timeit(lambda: native_blocks(bend, x, out), repeat)


def run_size(hinges: int, dtype, repeat: int, native: bool = False) -> None:
    bend, x, n = scene(hinges, dtype)
    H = bend.hinge_count
    pat = HessianPattern(bend.topology)  # built once per topology (not timed below)

    def autodiff_sparse():
        Hb = autodiff_blocks(bend, x)
        vals = x.new_zeros(pat.nnz).index_add_(0, pat.hinge_pos.reshape(-1), Hb.reshape(-1))
        return pat.csr(vals)

    t_tb = timeit(lambda: bend.hinge_hessians(x, backend="eager"), repeat)
    t_func = timeit(lambda: autodiff_blocks(bend, x), repeat)
    ref = autodiff_blocks(bend, x)
    nat: dict[str, float] = {}  # the compiled kernels (backend="native")
    if native:
        nat["blocks"] = timeit(lambda: bend.hinge_hessians(x, backend="native"), max(repeat, 7))
        _, nat["out"] = time_fresh_and_out(bend, x, max(repeat, 7))
        nat["err"] = float((bend.hinge_hessians(x, backend="native") - ref).norm() / ref.norm())
        nat["hinge"] = timeit(lambda: bend.hessian(x, assembly="hinge", backend="native"), max(repeat, 5))
        nat["triangle"] = timeit(lambda: bend.hessian(x, assembly="triangle", backend="native"), max(repeat, 5))
    with tb.use_backend("eager"):  # the eager rows below
        t_hinge = timeit(lambda: bend.hessian(x, assembly="hinge"), repeat)
        t_tri = timeit(lambda: bend.hessian(x, assembly="triangle"), repeat)
        t_ad = timeit(lambda: autodiff_sparse(), repeat)
        err = float((bend.hinge_hessians(x) - ref).norm() / ref.norm())
    print(f"\n{H} hinges ({n}x{n} sheet), {pat.nnz} nonzeros, {str(dtype).split('.')[-1]}")
    print(f"  per-hinge blocks   eager     {t_tb * 1e3:9.2f} ms   torch.func {t_func * 1e3:9.2f} ms   "
          f"ratio {t_func / t_tb:6.1f}x   ({t_tb / H * 1e9:7.0f} ns/hinge, rel. diff {err:.1e})")
    if nat:
        t = nat["blocks"]
        print(f"  per-hinge blocks   native    {t * 1e3:9.2f} ms   torch.func {t_func * 1e3:9.2f} ms   "
              f"ratio {t_func / t:6.1f}x   ({t / H * 1e9:7.0f} ns/hinge, rel. diff {nat['err']:.1e}; "
              f"{t_tb / t:4.1f}x over eager)")
        t = nat["out"]
        print(f"  per-hinge blocks   native kernel into out= buffers {t * 1e3:9.2f} ms   ratio {t_func / t:6.1f}x   "
              f"({t / H * 1e9:7.0f} ns/hinge; no input checks)")
    print(f"  sparse assembly    per hinge {t_hinge * 1e3:9.2f} ms   per triangle {t_tri * 1e3:9.2f} ms   "
          f"autodiff+scatter {t_ad * 1e3:9.2f} ms   (hinge/triangle {t_hinge / t_tri:4.2f}x, "
          f"autodiff/triangle {t_ad / t_tri:5.1f}x)")
    if nat:
        th, tt = nat["hinge"], nat["triangle"]
        print(f"  sparse assembly    native: per hinge {th * 1e3:9.2f} ms   per triangle {tt * 1e3:9.2f} ms   "
              f"(hinge/triangle {th / tt:4.2f}x; native triangle {t_tri / tt:4.1f}x faster than eager triangle)")
    line = "  projections (eager blocks, incl. evaluation)"
    eager_proj = {}
    for p in ("clamp", "abs", "gauss_newton", "reduced"):
        eager_proj[p] = timeit(lambda p=p: bend.hinge_hessians(x, projection=p, backend="eager"), max(1, repeat // 2))
        line += f"  {p} {eager_proj[p] * 1e3:8.1f} ms"
    print(line)
    if nat:
        line = "  projections (native blocks + Jacobi, incl. evaluation)"
        for p in ("clamp", "abs", "reduced"):
            t = timeit(lambda p=p: bend.hinge_hessians(x, projection=p, backend="native"), max(repeat, 5))
            want = bend.hinge_hessians(x, projection=p, backend="eager")
            err = float((bend.hinge_hessians(x, projection=p, backend="native") - want).norm() / want.norm())
            line += f"  {p} {t * 1e3:8.1f} ms ({eager_proj[p] / t:4.1f}x eager, rel. diff {err:.0e})"
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
    gn = bend.hinge_hessians(x, projection="gauss_newton")
    lost = (Hb - gn).flatten(1).norm(dim=1) / Hb.flatten(1).norm(dim=1)
    print(f"  gauss_newton drops a median {100 * lost.median():.1f}% (max {100 * lost.max():.1f}%) of each block (Frobenius)")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-drape", action="store_true")
    p.add_argument("--native", action="store_true", help="also time the compiled C++ kernels (built on first use)")
    a = p.parse_args(argv)
    print("machine:", machine())
    dtype = getattr(torch, a.dtype)
    if a.native:
        output_memory_probe(a.sizes, dtype, a.repeat)
    for h in a.sizes:
        run_size(h, dtype, a.repeat, a.native)
    if not a.no_drape:
        drape_report()


if __name__ == "__main__":
    main()
