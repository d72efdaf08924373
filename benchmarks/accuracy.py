"""High-precision reference for the hinge energy, its gradient and its Hessian (mpmath, 40 digits).

Independent of torchbend's kernels: the energy is the SPEC formula evaluated with second-order
Taylor arithmetic ("Hessian numbers": value, 12-gradient, 12x12 Hessian, all mpmath ``mpf``), so
the derivatives are exact up to 40-digit round-off, with no finite differences and no shared code.

``python benchmarks/accuracy.py`` prints normwise relative errors in ulps (``|a - r| / (|r| eps)``)
of torchbend (analytic) and of autograd of the plain energy, in float64 and float32, on random
and adversarial hinges (flat, near pi, slivers, curved rest).
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch

try:
    import mpmath as mp
except ImportError as e:  # pragma: no cover
    raise SystemExit("benchmarks/accuracy.py needs mpmath: pip install mpmath (or the 'bench' extra)") from e

import torchbend as tb
from torchbend.testing import plain_bending_energy

N = 12


class Jet:
    """Second-order Taylor number in 12 variables over mpmath."""

    __slots__ = ("v", "g", "h")

    def __init__(self, v, g=None, h=None):
        self.v = v
        self.g = g if g is not None else np.full(N, mp.mpf(0), dtype=object)
        self.h = h if h is not None else np.full((N, N), mp.mpf(0), dtype=object)

    @staticmethod
    def var(value, i):
        g = np.full(N, mp.mpf(0), dtype=object)
        g[i] = mp.mpf(1)
        return Jet(mp.mpf(value), g)

    def _lift(self, o):
        return o if isinstance(o, Jet) else Jet(mp.mpf(o))

    def __add__(self, o):
        o = self._lift(o)
        return Jet(self.v + o.v, self.g + o.g, self.h + o.h)

    __radd__ = __add__

    def __neg__(self):
        return Jet(-self.v, -self.g, -self.h)

    def __sub__(self, o):
        return self + (-self._lift(o))

    def __rsub__(self, o):
        return self._lift(o) - self

    def __mul__(self, o):
        o = self._lift(o)
        return Jet(self.v * o.v, self.g * o.v + o.g * self.v,
                   self.h * o.v + o.h * self.v + np.outer(self.g, o.g) + np.outer(o.g, self.g))

    __rmul__ = __mul__

    def unary(self, f, f1, f2):
        return Jet(f, self.g * f1, self.h * f1 + np.outer(self.g, self.g) * f2)

    def sqrt(self):
        s = mp.sqrt(self.v)
        return self.unary(s, 1 / (2 * s), -1 / (4 * s * self.v))

    def recip(self):
        return self.unary(1 / self.v, -1 / self.v**2, 2 / self.v**3)

    def __truediv__(self, o):
        return self * self._lift(o).recip()


def atan2(y: Jet, x: Jet) -> Jet:
    r2 = x.v * x.v + y.v * y.v
    fy, fx = x.v / r2, -y.v / r2
    fyy, fxx, fxy = -2 * x.v * y.v / r2**2, 2 * x.v * y.v / r2**2, (y.v * y.v - x.v * x.v) / r2**2
    g = fy * y.g + fx * x.g
    h = (fy * y.h + fx * x.h + fyy * np.outer(y.g, y.g) + fxx * np.outer(x.g, x.g)
         + fxy * (np.outer(y.g, x.g) + np.outer(x.g, y.g)))
    return Jet(mp.atan2(y.v, x.v), g, h)


def _phi(model: str, t: Jet) -> Jet:
    if model == "quadratic":
        return t
    half = t.v / 2
    if model == "tan":
        tn = mp.tan(half)
        s2 = 1 + tn * tn
        return t.unary(2 * tn, s2, s2 * tn)
    s, c = mp.sin(half), mp.cos(half)
    return t.unary(2 * s, c, -s / 2)


def _phi_scalar(model: str, t):
    return {"quadratic": t, "tan": 2 * mp.tan(t / 2), "sin": 2 * mp.sin(t / 2)}[model]


def reference(x4: np.ndarray, a: float, k: float, rest: float, model: str):
    """``(E, grad (12,), Hess (12, 12))`` of one hinge at 40 digits (as float64 arrays)."""
    with mp.workdps(40):
        X = [Jet.var(mp.mpf(float(x4.reshape(-1)[i])), i) for i in range(N)]
        p = [X[3 * j : 3 * j + 3] for j in range(4)]

        def sub(u, v):
            return [ui - vi for ui, vi in zip(u, v, strict=True)]

        def cross(u, v):
            return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

        def dot(u, v):
            return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]

        e = sub(p[1], p[0])
        nA = cross(e, sub(p[2], p[0]))
        nB = cross(sub(p[3], p[1]), e)
        elen = dot(e, e).sqrt()
        theta = atan2(dot(e, cross(nA, nB)) / elen, dot(nA, nB))
        d = _phi(model, theta) - _phi_scalar(model, mp.mpf(rest))
        E = d * d * (mp.mpf(a) * mp.mpf(k))
        return (float(E.v), np.array([float(v) for v in E.g]), np.array([[float(v) for v in r] for r in E.h]))


def hinge_cases(n_random: int = 40, seed: int = 0):
    """Random and adversarial hinges: ``[(name, x4 (4, 3) float64, rest angle)]``."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(n_random):
        x4 = rng.normal(size=(4, 3))
        cases.append(("random", x4, float(rng.uniform(-1, 1))))
    base = np.array([[0.0, 0, 0], [1, 0, 0], [0.4, 0.9, 0], [0.6, -0.8, 0]])
    for _ in range(10):
        x4 = base + 1e-3 * rng.normal(size=(4, 3)) * np.array([1, 1, 0])  # exactly flat
        cases.append(("flat", x4, 0.3))
    for _ in range(10):
        th = math.pi - 10.0 ** -rng.uniform(2, 5)
        x3 = np.array([0.6, -0.8 * math.cos(th), -0.8 * math.sin(th)])
        cases.append(("near_pi", np.array([base[0], base[1], base[2], x3]), 0.5))
    for _ in range(10):
        x4 = base.copy()
        x4[2, 1] = 10.0 ** -rng.uniform(3, 6)  # sliver triangle A
        x4[3, 2] = 0.3 * rng.normal()
        cases.append(("sliver", x4, 0.0))
    for _ in range(10):
        x4 = rng.normal(size=(4, 3))
        cases.append(("curved_rest", x4, float(rng.uniform(-2.5, 2.5))))
    return cases


def errors(model: str = "tan", n_random: int = 40):
    """Per-case normwise relative errors in ulps: ``{(method, dtype, quantity): [..]}`` and case names."""
    out: dict = {}
    names = []
    a, k = 1.7, 0.9
    hinges = torch.tensor([[0, 1, 2, 3]])
    for name, x4, rest in hinge_cases(n_random):
        names.append(name)
        for dtype in (torch.float64, torch.float32):
            eps = torch.finfo(dtype).eps
            # the reference is evaluated at the inputs as rounded to this dtype: the errors measure
            # the evaluation, not the rounding of the data
            x = torch.tensor(x4, dtype=dtype)
            a_d, k_d, rest_d = (float(torch.tensor(v, dtype=dtype)) for v in (a, k, rest))
            E_r, g_r, H_r = reference(x.double().numpy(), a_d, k_d, rest_d, model)
            faces = torch.tensor([[0, 1, 2], [1, 0, 3]])
            aw = torch.tensor([a_d], dtype=dtype)
            rr = torch.tensor([rest_d], dtype=dtype)
            # the eager closed forms (the compiled kernels are checked against them in tests/test_native.py)
            bend = tb.BendingEnergy(faces, x.detach().clone(), model=model, stiffness=k_d, rest_angles=rr,
                                    check_finite=False, backend="eager")
            bend.weights = aw
            E = float(bend(x))
            g = bend.gradient(x).reshape(-1).double().numpy()
            Hb = bend.hinge_hessians(x)[0].double().numpy()

            plain = functools.partial(plain_bending_energy, hinges=hinges, a=aw, k=k_d, rest=rr, model=model)

            y = x.clone().requires_grad_()
            Ep = plain(y)
            (gp,) = torch.autograd.grad(Ep, y)
            Hp = torch.func.hessian(plain)(x).reshape(12, 12).double().numpy()
            for method, (Ev, gv, Hv) in {"torchbend": (E, g, Hb),
                                        "autograd": (float(Ep.detach()), gp.reshape(-1).double().numpy(), Hp)}.items():
                for q, (val, ref) in {"energy": (np.array([Ev]), np.array([E_r])), "gradient": (gv, g_r),
                                      "hessian": (Hv, H_r)}.items():
                    denom = max(np.linalg.norm(ref), 1e-300)
                    out.setdefault((method, str(dtype).split(".")[-1], q), []).append(
                        float(np.linalg.norm(val - ref) / denom / eps))
    return out, names


def main() -> None:
    for model in ("tan", "quadratic"):
        errs, names = errors(model)
        print(f"\nmodel {model}: normwise relative error in ulps over {len(names)} hinges (median / 90% / max)")
        for key, v in sorted(errs.items()):
            v = np.array(v)
            print(f"  {key[0]:>9s} {key[1]:>7s} {key[2]:>8s}  {np.median(v):8.2f} {np.quantile(v, 0.9):9.2f} {v.max():10.2f}")


if __name__ == "__main__":
    main()
