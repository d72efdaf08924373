"""HOOD's whole loss, forward + backward: torchbend.losses.hood against the same six criteria written in plain
PyTorch (torchbend.testing.HoodReference: autograd through atan2, 2x2 matrix products, brute-force
nearest centroids as a plain-PyTorch user or HOOD's knn_points computes them), side by side in one run, on
a flared skirt over a moving mannequin at HOOD's garment sizes (5k-20k vertices, batch 1-16).

    python benchmarks/bm_hood.py                          # 5k, 10k, 20k vertices; batch 1, 4, 16 (to 1e5 x)
    python benchmarks/bm_hood.py --vertices 10000 --batch 4

Per term and in total: milliseconds per forward + backward (median), and the ratio plain / torchbend.
No assertions (tests/test_hood.py checks that both compute the same values and gradients)."""
from __future__ import annotations

import argparse
import math
from typing import cast

import torch
from common import bench, cpu_vector_extensions, machine

import torchbend as tb
from torchbend.losses import LossTerm, hood
from torchbend.mesh.garments import skirt
from torchbend.mesh.procedural import mannequin
from torchbend.testing import HoodReference

TERMS = ("stretching", "bending", "inertia", "gravity", "collision", "friction")


def scene(vertices: int, batch: int, seed: int = 0):
    n_along = max(4, round(math.sqrt(vertices / 2.5)))
    n_around = 2 * max(4, round(vertices / n_along / 2))
    pos, faces, _ = skirt(n_around, n_along, dtype=torch.float64)
    rest, faces = tb.mesh.clean(pos, faces)
    body, body_faces = mannequin(4, 48, 40, dtype=torch.float64)  # 12,800 faces (SMPL: 13,776)
    g = torch.Generator().manual_seed(seed)

    def cloth(scale):
        return rest * torch.tensor([scale, scale, 1.05]) + 2e-3 * torch.randn((batch, *rest.shape), generator=g,
                                                                             dtype=torch.float64)

    shift = torch.tensor([0.0, 0.003, -0.002], dtype=torch.float64)
    bodies = [(body + k * shift).expand(batch, *body.shape).contiguous() for k in range(3)]
    mats = hood.sample_materials(batch, generator=g)
    mats = {k: mats[k] for k in ("density", "lame_mu", "lame_lambda", "bending_coeff")}
    return dict(rest=rest, faces=faces, body_faces=body_faces, x_prev=cloth(0.89), x_curr=cloth(0.9), x=cloth(0.91),
                body_prev=bodies[0], body_curr=bodies[1], body_next=bodies[2]), mats


def run(vertices: int, batch: int, budget: float) -> None:
    s, mats = scene(vertices, batch)
    loss = hood.criteria(s["faces"], s["rest"], s["body_faces"], density=mats["density"], lame_mu=mats["lame_mu"],
                         lame_lambda=mats["lame_lambda"], bending_coeff=mats["bending_coeff"])
    kw = {k: s[k] for k in ("x_curr", "x_prev", "body_prev", "body_curr", "body_next")}

    def ours(name=None):
        x = s["x"].clone().requires_grad_()
        if name is None:
            value = loss(x, **kw)[0]
        else:
            term = loss.terms[name]
            value = term(x, **{k: kw[k] for k in cast("LossTerm", term).inputs if k in kw}).mean()
        value.backward()

    reference = HoodReference(s["faces"], s["rest"], s["body_faces"])

    def plain(name=None):
        x = s["x"].clone().requires_grad_()
        ref = reference(x, x_curr=s["x_curr"], x_prev=s["x_prev"], body_prev=s["body_prev"], body_curr=s["body_curr"],
                        body_next=s["body_next"], density=mats["density"], lame_mu=mats["lame_mu"],
                        lame_lambda=mats["lame_lambda"], bending_coeff=mats["bending_coeff"],
                        terms=None if name is None else (name,))
        torch.stack(list(ref.values())).sum(0).mean().backward()

    print(f"\n{s['rest'].shape[0]} vertices, {s['faces'].shape[0]} faces, batch {batch}, body "
          f"{s['body_faces'].shape[0]} faces, float64")
    print(f"{'term':>11} {'torchbend ms':>13} {'plain ms':>10} {'plain/torchbend':>16}")
    for name in (*TERMS, None):
        a = bench(lambda n=name: ours(n), budget=budget)["median"]
        b = bench(lambda n=name: plain(n), budget=budget)["median"]
        print(f"{name or 'total':>11} {1e3 * a:13.2f} {1e3 * b:10.2f} {b / a:16.2f}")


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--vertices", type=int, nargs="+", default=[5000, 10000, 20000])
    p.add_argument("--batch", type=int, nargs="+", default=[1, 4, 16])
    p.add_argument("--max-work", type=float, default=1e5,
                   help="skip sizes with vertices x batch above this (the transcription's brute-force search "
                        "takes minutes there)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--budget", type=float, default=1.0, help="seconds of timed calls per measurement")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    print(machine(), "|", " ".join(cpu_vector_extensions()))
    for v in a.vertices:
        for b in a.batch:
            if v * b <= a.max_work:
                run(v, b, a.budget)


if __name__ == "__main__":
    main()
