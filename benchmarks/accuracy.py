"""High-precision reference for the hinge angle and energy, their gradients and Hessians (mpmath, 40 digits),
and the accuracy of torchbend (eager closed forms and compiled kernels) and of plain autograd against it.

Independent of torchbend's kernels: the bend angle is the SPEC formula evaluated with second-order Taylor
arithmetic ("Hessian numbers": value, 12-gradient, 12x12 Hessian, all mpmath ``mpf``), so the derivatives
are exact up to 40-digit round-off, with no finite differences and no shared code.  The energy's jet is
``a k (phi(theta) - phi(rest))^2`` applied to the angle's jet.

``python benchmarks/accuracy.py`` prints normwise relative errors in ulps (``|a - r| / (|r| eps)``, ``eps`` of
the dtype) of

- ``torchbend``: the eager closed forms (``torchbend.ops.hinge``, ``BendingEnergy(backend="eager")``),
- ``native``: the compiled C++ kernels (blocks and per-triangle assembly; skipped if they cannot be built),
- ``autograd``: autograd of the plain energy (``torchbend.testing``; HVP by double backward, Hessian by
  ``torch.func.hessian``),
- ``rounded`` (HVPs only): the exact Hessian rounded to the dtype, times ``v`` in the dtype,

in float64 and float32, for the quantities

- ``theta``, ``theta_grad``, ``theta_hvp``, ``theta_hess``: the bend angle and its derivatives;
- ``energy``, ``gradient``, ``hvp``, ``hessian`` (the 12x12 block), ``assembly`` (the per-triangle sparse
  assembly of the one-hinge mesh, paper eq. 7, as a dense 12x12 matrix): the energy and its derivatives.

HVPs use ``DIRECTIONS`` random directions per hinge, each a sample (:func:`errors`, for
``benchmarks/report.py``, keeps the worst per hinge); the error is relative to
``|H v|``, which for some directions is several times smaller than ``|H| |v|`` (the product cancels), so an
error of a fraction of an ulp of ``|H| |v|`` reads as several ulps.  The reference is
evaluated at the inputs as rounded to each dtype, so the errors measure the evaluation, not the rounding of
the data.

Case families (:func:`hinge_cases`): ``well_shaped`` (the well-conditioned hinges the accuracy target is
about, see :func:`well_shaped_hinge`), ``random`` (Gaussian vertices: some triangles are slivers and some
angles close to the rest angle, i.e. ill-conditioned), ``flat``, ``near_pi``, ``sliver`` (caps: one angle near
180 degrees, axis-aligned), ``curved_rest`` and ``needle`` (one tiny angle, randomly rotated).

``--json PATH`` writes a machine-readable summary (median / 90% / max per model, method, dtype, quantity and
family).
"""
from __future__ import annotations

import argparse
import functools
import json
import math
import platform
import sys

import numpy as np
import torch

try:
    import mpmath as mp
except ImportError as e:  # pragma: no cover
    raise SystemExit("benchmarks/accuracy.py needs mpmath: pip install mpmath (or the 'bench' extra)") from e

import torchbend as tb
from torchbend.ops import hinge as geometry
from torchbend.testing import plain_bending_energy, plain_hinge_angles

N = 12
DIGITS = 40
DIRECTIONS = 3
MODELS = ("tan", "quadratic")
THETA_QUANTITIES = ("theta", "theta_grad", "theta_hvp", "theta_hess")
ENERGY_QUANTITIES = ("energy", "gradient", "hvp", "hessian", "assembly")


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


def theta_jet(x4: np.ndarray) -> Jet:
    """The bend angle of one stencil ``x4 (4, 3)`` (exact binary values) as a 40-digit jet."""
    with mp.workdps(DIGITS):
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
        return atan2(dot(e, cross(nA, nB)) / elen, dot(nA, nB))


def energy_jet(theta: Jet, a: float, k: float, rest: float, model: str) -> Jet:
    """``a k (phi(theta) - phi(rest))^2`` on the angle's jet (parameters as exact binary values)."""
    with mp.workdps(DIGITS):
        d = _phi(model, theta) - _phi_scalar(model, mp.mpf(rest))
        return d * d * (mp.mpf(a) * mp.mpf(k))


def times(h: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``h v`` at 40 digits (``h`` a jet's Hessian, ``v`` exact binary values)."""
    with mp.workdps(DIGITS):
        return np.array([mp.fsum(h[r, c] * mp.mpf(float(v[c])) for c in range(N)) for r in range(N)], dtype=object)


def reference(x4: np.ndarray, a: float, k: float, rest: float, model: str):
    """``(E, grad (12,), Hess (12, 12))`` of one hinge at 40 digits (as float64 arrays)."""
    E = energy_jet(theta_jet(x4), a, k, rest, model)
    return (float(E.v), np.array([float(v) for v in E.g]), np.array([[float(v) for v in r] for r in E.h]))


def ulps(val, ref, eps: float) -> float:
    """Normwise relative error ``|val - ref| / |ref|`` in units of ``eps``; ``ref`` mpf values, the difference
    taken at 40 digits."""
    val = np.asarray(val, dtype=np.float64).reshape(-1)
    ref = np.asarray(ref, dtype=object).reshape(-1)
    with mp.workdps(DIGITS):
        num = math.sqrt(sum(float(mp.mpf(float(v)) - r) ** 2 for v, r in zip(val, ref, strict=True)))
        den = math.sqrt(sum(float(r) ** 2 for r in ref))
    return num / max(den, 1e-300) / eps


# ------------------------------------------------------------------------------------------ cases
def _rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    a, b, c, d = q / np.linalg.norm(q)
    return np.array([[a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
                     [2 * (b * c + a * d), a * a - b * b + c * c - d * d, 2 * (c * d - a * b)],
                     [2 * (b * d - a * c), 2 * (c * d + a * b), a * a - b * b - c * c + d * d]])


WELL_THETA = 2.0
"""``|theta| <= WELL_THETA`` in the well-shaped family (about 115 degrees)."""
WELL_GAP = 0.5
"""``|theta - rest| >= WELL_GAP`` in the well-shaped family."""


def well_shaped_hinge(rng) -> tuple[np.ndarray, float]:
    """A random well-conditioned hinge and rest angle.

    Both triangles have every interior angle between about 34 and 112 degrees (hinge edge of length
    0.7-1.3, each wing's foot at 25-75% of the edge, its height 0.5-1.2 edge lengths), the bend angle is
    uniform in ``[-WELL_THETA, WELL_THETA]``, the stencil randomly rotated and moved by a unit Gaussian.
    The rest angle is at least ``WELL_GAP`` away from the angle: the derivatives of the energy carry a
    factor ``phi(theta) - phi(rest)`` whose relative error any method computing ``theta`` in floating point
    (to ~1 eps absolute) multiplies by ``~|theta| / |theta - rest|``, and near ``|theta| = pi`` the ``tan``
    model multiplies it by ``1 / (pi - |theta|)``: conditioning of the problem, not of a formula, shown by
    the ``random``, ``near_pi`` and ``curved_rest`` families."""
    L = rng.uniform(0.7, 1.3)
    ta, ha, tb_, hb = rng.uniform(0.25, 0.75), rng.uniform(0.5, 1.2), rng.uniform(0.25, 0.75), rng.uniform(0.5, 1.2)
    th = rng.uniform(-WELL_THETA, WELL_THETA)
    x4 = np.array([[0.0, 0.0, 0.0], [L, 0.0, 0.0], [ta * L, ha * L, 0.0],
                   [tb_ * L, -hb * L * math.cos(th), -hb * L * math.sin(th)]])
    x4 = x4 @ _rotation(rng).T + rng.normal(size=3)
    rest = th + rng.choice([-1.0, 1.0]) * rng.uniform(WELL_GAP, 1.0)
    if abs(rest) >= 2.5:
        rest = th - math.copysign(rng.uniform(WELL_GAP, 1.0), rest - th)
    return x4, float(rest)


def hinge_cases(n_random: int = 40, seed: int = 0, n_well: int = 40, n_needle: int = 10):
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
    nrng = np.random.default_rng(seed + 2000)
    for _ in range(n_needle):
        # triangle A a needle: x2 close to x1 (a short edge at a moderate angle, a tiny angle at x0), rotated
        # so that no edge is axis-aligned (the sliver family's caps are)
        phi, d = nrng.uniform(0.25 * math.pi, 0.75 * math.pi), 10.0 ** -nrng.uniform(2, 5)
        x4 = base.copy()
        x4[2] = [1 + d * math.cos(phi), d * math.sin(phi), 0.0]
        x4[3, 2] = 0.3 * nrng.normal()
        cases.append(("needle", x4 @ _rotation(nrng).T + nrng.normal(size=3), 0.0))
    wrng = np.random.default_rng(seed + 1000)  # its own stream: the other families do not change with n_well
    for _ in range(n_well):
        x4, rest = well_shaped_hinge(wrng)
        cases.append(("well_shaped", x4, rest))
    return cases


# ---------------------------------------------------------------------------------- evaluation
def native_available() -> bool:
    from torchbend.backends import native

    return native.load() is not None


HINGES = torch.tensor([[0, 1, 2, 3]])
FACES = torch.tensor([[0, 1, 2], [1, 0, 3]])


def _theta_values(x: torch.Tensor, vs: list, native: bool) -> dict:
    """``{method: {quantity: value or [values per direction]}}`` of the angle quantities."""
    out: dict = {}
    x4 = x[None]
    th, g, _ = geometry.hinge_angle_gradient_hvp(x4, None)
    hvs = [geometry.hinge_angle_gradient_hvp(x4, v.reshape(1, 4, 3))[2] for v in vs]
    out["torchbend"] = {"theta": th, "theta_grad": g, "theta_hvp": hvs, "theta_hess": geometry.hinge_angle_hessian(x4)}

    def angle(y):
        return plain_hinge_angles(y, HINGES)[0]

    y = x.clone().requires_grad_()
    ta = angle(y)
    (ga,) = torch.autograd.grad(ta, y, create_graph=True)
    hva = [torch.autograd.grad(ga, y, v.reshape(4, 3), retain_graph=True)[0] for v in vs]
    out["autograd"] = {"theta": ta, "theta_grad": ga, "theta_hvp": hva, "theta_hess": torch.func.hessian(angle)(x)}
    if native:
        from torchbend.backends import native as nat

        one = torch.ones(1, dtype=x.dtype)
        out["native"] = {"theta_grad": nat.bending_hessians(x, HINGES, one, one, one * 0, None, None, "quadratic")[1]}
    return out


def _energy_values(x: torch.Tensor, vs: list, a: float, k: float, rest: float, model: str, native: bool) -> dict:
    dtype = x.dtype
    aw, rr = torch.tensor([a], dtype=dtype), torch.tensor([rest], dtype=dtype)
    out: dict = {}
    for method, backend in (("torchbend", "eager"), ("native", "native")):
        if method == "native" and not native:
            continue
        bend = tb.BendingEnergy(FACES, x.detach().clone(), model=model, stiffness=k, rest_angles=rr,
                                check_finite=False, backend=backend)
        bend.weights = aw
        d: dict = {"hessian": bend.hinge_hessians(x)[0], "assembly": bend.hessian(x, assembly="triangle").to_dense()}
        if method == "torchbend":  # energy, gradient and hvp have no compiled kernel
            d.update(energy=bend(x), gradient=bend.gradient(x), hvp=[bend.hvp(x, v.reshape(4, 3)) for v in vs])
        out[method] = d
    plain = functools.partial(plain_bending_energy, hinges=HINGES, a=aw, k=k, rest=rr, model=model)
    y = x.clone().requires_grad_()
    Ep = plain(y)
    (gp,) = torch.autograd.grad(Ep, y, create_graph=True)
    hvp = [torch.autograd.grad(gp, y, v.reshape(4, 3), retain_graph=True)[0] for v in vs]
    out["autograd"] = {"energy": Ep, "gradient": gp, "hvp": hvp, "hessian": torch.func.hessian(plain)(x)}
    return out


def _rounded_hvp(h: np.ndarray, vs: list) -> list:
    """The exact Hessian rounded to the dtype of ``vs``, times each ``v`` in that dtype: the HVP of a method
    whose Hessian entries are correctly rounded (a floor that shows how much the product's cancellation
    alone costs)."""
    Hr = torch.tensor([[float(t) for t in r] for r in h], dtype=vs[0].dtype)
    return [Hr @ v for v in vs]


def _record(out: dict, key_prefix: tuple, values: dict, refs: dict, eps: float) -> None:
    for method, qs in values.items():
        for q, val in qs.items():
            ref = refs[q]
            if isinstance(val, list):  # HVP: one error per direction
                err = [ulps(vv.detach().double().numpy(), rr, eps) for vv, rr in zip(val, ref, strict=True)]
            else:
                err = ulps(val.detach().double().numpy(), ref, eps)
            out.setdefault((method,) + key_prefix + (q,), []).append(err)


def errors_all(models=MODELS, n_random: int = 40, n_well: int = 40, seed: int = 0, dtypes=("float64", "float32"),
               native: bool | None = None, families=None):
    """Per-case errors in ulps ``{model: {(method, dtype, quantity): [..]}}`` and the case names, one angle jet
    per case and dtype shared by all models."""
    native = native_available() if native is None else native
    cases = [c for c in hinge_cases(n_random, seed, n_well) if families is None or c[0] in families]
    out: dict = {m: {} for m in models}
    rng = np.random.default_rng(seed + 7)
    a, k = 1.7, 0.9
    for _, x4, rest in cases:
        vdir = [rng.normal(size=N) for _ in range(DIRECTIONS)]
        for dtype_name in dtypes:
            dtype = getattr(torch, dtype_name)
            eps = torch.finfo(dtype).eps
            # the reference is evaluated at the inputs as rounded to this dtype
            x = torch.tensor(x4, dtype=dtype)
            vs = [torch.tensor(v, dtype=dtype) for v in vdir]
            a_d, k_d, rest_d = (float(torch.tensor(v, dtype=dtype)) for v in (a, k, rest))
            th = theta_jet(x.double().numpy())
            vs64 = [v.double().numpy() for v in vs]
            th_refs = {"theta": [th.v], "theta_grad": th.g, "theta_hess": th.h, "theta_hvp": [times(th.h, v) for v in vs64]}
            tv = _theta_values(x, vs, native)
            tv["rounded"] = {"theta_hvp": _rounded_hvp(th.h, vs)}
            for model in models:
                _record(out[model], (dtype_name,), tv, th_refs, eps)
                E = energy_jet(th, a_d, k_d, rest_d, model)
                refs = {"energy": [E.v], "gradient": E.g, "hessian": E.h, "assembly": E.h,
                        "hvp": [times(E.h, v) for v in vs64]}
                ev = _energy_values(x, vs, a_d, k_d, rest_d, model, native)
                ev["rounded"] = {"hvp": _rounded_hvp(E.h, vs)}
                _record(out[model], (dtype_name,), ev, refs, eps)
    return out, [c[0] for c in cases]


def errors(model: str = "tan", n_random: int = 40, n_well: int = 40):
    """Per-case normwise relative errors in ulps: ``{(method, dtype, quantity): [..]}`` and case names (one
    value per case: for HVPs the worst direction)."""
    out, names = errors_all((model,), n_random, n_well)
    return {k: [max(e) if isinstance(e, list) else e for e in v] for k, v in out[model].items()}, names


# --------------------------------------------------------------------------------------- report
QUANTITY_ORDER = THETA_QUANTITIES + ENERGY_QUANTITIES
METHOD_ORDER = ("torchbend", "native", "autograd", "rounded")


def summarize(errs: dict, names: list) -> dict:
    """``{"method/dtype/quantity": {"all": stats, family: stats}}`` with stats median / p90 / max / n (``n``
    samples: cases, or for HVPs cases times directions)."""
    fams = list(dict.fromkeys(names))
    summary: dict = {}
    for key, per_case in errs.items():
        flat = [(n, e) for n, es in zip(names, per_case, strict=True) for e in (es if isinstance(es, list) else [es])]
        names_a, v = np.array([n for n, _ in flat]), np.array([e for _, e in flat])
        entry = {}
        for fam in ["all"] + fams:
            w = v if fam == "all" else v[names_a == fam]
            entry[fam] = {"median": float(np.median(w)), "p90": float(np.quantile(w, 0.9)), "max": float(w.max()),
                          "n": int(w.size)}
        summary["/".join(key)] = entry
    return summary


def _sort_key(key: str):
    m, d, q = key.split("/")
    return (d != "float64", QUANTITY_ORDER.index(q), METHOD_ORDER.index(m))


def format_table(summary: dict, family: str) -> list[str]:
    lines = [f"    {'quantity':>10s} {'method':>9s} {'dtype':>7s}  {'median':>8s} {'90%':>8s} {'max':>10s}"]
    for key in sorted(summary, key=_sort_key):
        s = summary[key].get(family)
        if s is None:
            continue
        m, d, q = key.split("/")
        lines.append(f"    {q:>10s} {m:>9s} {d:>7s}  {s['median']:8.2f} {s['p90']:8.2f} {s['max']:10.2f}")
    return lines


def machine() -> str:
    return (f"{platform.processor() or platform.machine()} | {torch.get_num_threads()} threads | torch {torch.__version__} | "
            f"python {platform.python_version()} | {platform.system()}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=["tan", "quadratic", "sin"])
    ap.add_argument("--n-random", type=int, default=40)
    ap.add_argument("--n-well", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--families", nargs="+", default=None,
                    choices=["random", "flat", "near_pi", "sliver", "curved_rest", "needle", "well_shaped"])
    ap.add_argument("--no-native", action="store_true", help="skip the compiled kernels")
    ap.add_argument("--json", default=None, help="write a machine-readable summary here")
    args = ap.parse_args(argv)
    errs, names = errors_all(tuple(args.models), args.n_random, args.n_well, args.seed,
                             native=False if args.no_native else None, families=args.families)
    fams = list(dict.fromkeys(names))
    print(f"machine: {machine()}")
    print(f"normwise relative error in ulps (median / 90% / max); HVP: {DIRECTIONS} random directions per hinge, each"
          f" a sample; cases: " + ", ".join(f"{f} {names.count(f)}" for f in fams))
    result = {"machine": machine(), "cases": {f: names.count(f) for f in fams}, "models": {}}
    for model in args.models:
        summary = summarize(errs[model], names)
        result["models"][model] = summary
        for fam in ["well_shaped", "all"] + [f for f in fams if f != "well_shaped"]:
            if fam != "all" and fam not in fams:
                continue
            print(f"\nmodel {model}, {fam} ({len(names) if fam == 'all' else names.count(fam)} hinges)")
            print("\n".join(format_table(summary, fam)))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
