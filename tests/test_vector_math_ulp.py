"""The vectorizable math of ``torchbend/csrc/vector_math.h`` (``tb_atan2v``, ``tb_sincos``, ``tb_half_sincos``,
``tb_half_sincos_tan``, ``tb_logv``)
against a 40-digit reference (mpmath): at most 1 ulp of the exact value over the whole domain, float64 and
float32, IEEE's signed zeros and quadrants exactly.

A torch-free harness (``tests/native_harness/vector_math.cpp``) that includes the header is compiled with g++
and the CPU extension's flags (:data:`torchbend.backends._build_config.NATIVE_CFLAGS`, the ``-march`` replaced),
once for ``-march=native`` and once for ``-march=x86-64-v3`` (AVX2 + FMA: the vector width and the fused
multiply-adds change the last bits), and loaded with ctypes.  Its loops are written as the kernels' lane loops
(the functions inlined into a plain loop), and the test checks from GCC's report that they vectorized; the
scalar (not inlined) evaluation is checked as well.  Skipped without g++."""
from __future__ import annotations

import ctypes
import os
import platform
import re
import shutil
import subprocess
import sys
from collections.abc import Callable, Sequence

import numpy as np
import pytest

from torchbend.backends import _build_config as cfg

mpmath = pytest.importorskip("mpmath")
mp = mpmath.mp

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HARNESS = os.path.join(ROOT, "tests", "native_harness", "vector_math.cpp")
CXX = shutil.which("g++")
IS_X86 = platform.machine().lower() in ("x86_64", "amd64")
ARCHS = ["native", pytest.param("x86-64-v3", marks=pytest.mark.skipif(not IS_X86, reason="not an x86-64 CPU"))]

pytestmark = pytest.mark.skipif(CXX is None or not sys.platform.startswith("linux"), reason="needs g++ (Linux)")

F64, F32 = np.dtype(np.float64), np.dtype(np.float32)
DTYPES = [F64, F32]
SINCOS_LIMIT = 2.0**19  # tb_sincos's documented domain: |x| < 2^19


class Harness:
    """The compiled harness: ``atan2``, ``sincos`` and ``half_sincos`` over numpy arrays."""

    def __init__(self, path: str):
        self.lib = ctypes.CDLL(path)

    def _fn(self, name: str):
        fn = getattr(self.lib, name)
        fn.restype = None
        return fn

    @staticmethod
    def _ptr(a: np.ndarray):
        return a.ctypes.data_as(ctypes.c_void_p)

    def atan2(self, y: np.ndarray, x: np.ndarray, dtype: np.dtype, vec: bool = True) -> np.ndarray:
        y, x = np.ascontiguousarray(y, dtype), np.ascontiguousarray(x, dtype)
        out = np.empty_like(y)
        name = f"tb_atan2_{'vec' if vec else 'scalar'}_{'f64' if dtype == F64 else 'f32'}"
        self._fn(name)(self._ptr(y), self._ptr(x), self._ptr(out), ctypes.c_long(y.size))
        return out

    def _pair(self, kind: str, x: np.ndarray, dtype: np.dtype, vec: bool) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(x, dtype)
        s, c = np.empty_like(x), np.empty_like(x)
        name = f"tb_{kind}_{'vec' if vec else 'scalar'}_{'f64' if dtype == F64 else 'f32'}"
        self._fn(name)(self._ptr(x), self._ptr(s), self._ptr(c), ctypes.c_long(x.size))
        return s, c

    def sincos(self, x: np.ndarray, dtype: np.dtype, vec: bool = True) -> tuple[np.ndarray, np.ndarray]:
        return self._pair("sincos", x, dtype, vec)

    def half_sincos(self, x: np.ndarray, dtype: np.dtype, vec: bool = True) -> tuple[np.ndarray, np.ndarray]:
        return self._pair("half_sincos", x, dtype, vec)

    def _unary(self, kind: str, x: np.ndarray, dtype: np.dtype, vec: bool) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype)
        out = np.empty_like(x)
        name = f"tb_{kind}_{'vec' if vec else 'scalar'}_{'f64' if dtype == F64 else 'f32'}"
        self._fn(name)(self._ptr(x), self._ptr(out), ctypes.c_long(x.size))
        return out

    def half_sincos_tan(self, x: np.ndarray, dtype: np.dtype, vec: bool = True) -> tuple[np.ndarray, ...]:
        x = np.ascontiguousarray(x, dtype)
        s, c, u = np.empty_like(x), np.empty_like(x), np.empty_like(x)
        name = f"tb_half_sct_{'vec' if vec else 'scalar'}_{'f64' if dtype == F64 else 'f32'}"
        self._fn(name)(self._ptr(x), self._ptr(s), self._ptr(c), self._ptr(u), ctypes.c_long(x.size))
        return s, c, u

    def log(self, x: np.ndarray, dtype: np.dtype, vec: bool = True) -> np.ndarray:
        return self._unary("log", x, dtype, vec)


@pytest.fixture(scope="module", params=ARCHS)
def harness(request, tmp_path_factory) -> Harness:
    """The harness built for one -march (once per module and architecture)."""
    arch = request.param
    flags = [f for f in cfg.NATIVE_CFLAGS if not f.startswith(("-march=", "-mtune=", "-mcpu="))]
    out = tmp_path_factory.mktemp(f"vector_math_{arch.replace('-', '_')}")
    lib, report = str(out / "vector_math.so"), str(out / "vector_math.vec")
    cmd = [str(CXX), "-std=c++17", "-fPIC", "-shared", *flags, f"-march={arch}", f"-I{ROOT}",
           f"-fopt-info-vec-optimized={report}", HARNESS, "-o", lib]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, f"{' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}"
    # the twelve *_vec loops (atan2, sincos, sincos_fast, half_sincos, half_sct, log; double and float) must
    # vectorize as the kernels' do
    with open(report) as fh:
        widths = [int(m.group(1)) for m in re.finditer(r"vector_math\.cpp:\d+:\d+: optimized: loop vectorized "
                                                      r"using (\d+) byte vectors", fh.read())]
    wide = [w for w in widths if w >= (32 if arch == "x86-64-v3" else 16)]
    assert len(wide) >= 12, f"-march={arch}: the harness loops did not vectorize (vector widths {widths})"
    return Harness(lib)


# ---- reference and ulps ----------------------------------------------------------------------------
def _rounded(v, dtype: np.dtype) -> float:
    """The exact value v (an mpf) correctly rounded to dtype, as a float."""
    if dtype == F64:
        return float(v)
    with mp.workprec(24):
        r = float(+v)  # unary plus rounds to the context's 24 bits (round to nearest)
    return float(np.float32(r)) if abs(r) <= float(np.finfo(np.float32).max) else float("inf")


def _ulp_errors(computed: np.ndarray, exact: Sequence, dtype: np.dtype) -> np.ndarray:
    """|computed - exact| / ulp(exact), the ulp of the correctly rounded exact value in dtype."""
    err = np.empty(len(exact))
    for i, (c, e) in enumerate(zip(computed.tolist(), exact)):
        ulp = float(np.spacing(dtype.type(abs(_rounded(e, dtype)))))
        err[i] = float(abs(mpmath.mpf(c) - e) / ulp) if np.isfinite(c) else float("inf")
    return err


def _worst(name: str, args: Sequence[np.ndarray], err: np.ndarray) -> str:
    i = int(np.argmax(err))
    at = ", ".join(repr(float(a[i])) for a in args)
    return f"{name}: worst {err[i]:.3f} ulp at ({at}) over {len(err)} arguments"


def _check(name: str, args: Sequence[np.ndarray], err: np.ndarray, bound: float = 1.0) -> str:
    msg = _worst(name, args, err)
    assert float(err.max()) <= bound, msg
    return msg


# ---- arguments ---------------------------------------------------------------------------------------
def _limits(dtype: np.dtype) -> dict[str, float]:
    fi = np.finfo(dtype)
    return {"tiny": float(fi.smallest_subnormal), "min": float(fi.tiny), "huge": 1e300 if dtype == F64 else 1e30,
            "max": float(fi.max), "emin": float(np.log2(fi.smallest_subnormal)), "emax": float(fi.maxexp)}


def _log_uniform(rng: np.random.Generator, n: int, lo: float, hi: float, dtype: np.dtype) -> np.ndarray:
    """n positive values of dtype with exponents uniform in [lo, hi) (base 2) and random mantissas."""
    e = rng.uniform(lo, hi, n)
    with np.errstate(over="ignore", under="ignore"):
        v = np.ldexp(1.0 + rng.random(n), np.floor(e).astype(int) - 1).astype(dtype)
    v = v[np.isfinite(v) & (v > 0)]
    return v


def _signs(rng: np.random.Generator, v: np.ndarray) -> np.ndarray:
    return np.where(rng.random(v.size) < 0.5, -v, v)


def _next(v: float, dtype: np.dtype, k: int) -> float:
    """v moved k representable values of dtype toward +inf (k < 0: toward -inf)."""
    out = dtype.type(v)
    for _ in range(abs(k)):
        if not np.isfinite(out):
            break
        with np.errstate(over="ignore"):
            out = np.nextafter(out, dtype.type(np.inf if k > 0 else -np.inf))
    return float(out)  # inf past the largest finite value (dropped by the callers)


def _atan2_boundaries(dtype: np.dtype, L: dict) -> tuple[list[float], list[float]]:
    """(y, x) at the reduction boundaries |y|/|x| = 7/16, 11/16, 1 (and their reciprocals), a few ulps either
    side, at scales from the subnormals to the largest finite value, in all quadrants."""
    ys: list[float] = []
    xs: list[float] = []
    scales = [L["tiny"] * 64, L["min"], 2.0**-500 if dtype == F64 else 2.0**-60, 1.0, 3.0,
              2.0**500 if dtype == F64 else 2.0**60, L["max"] / 2, L["max"]]
    for ratio in (7 / 16, 11 / 16, 1.0):
        for s in scales:
            for k in range(-3, 4):
                y, x = _next(ratio * s, dtype, k), s
                if not np.isfinite(y):
                    continue
                for sy in (1, -1):
                    for sx in (1, -1):
                        ys += [sy * y, sy * x]
                        xs += [sx * x, sx * y]
    return ys, xs


def _atan2_near_pi(dtype: np.dtype, L: dict) -> tuple[list[float], list[float]]:
    """(y, x) whose atan2 lies next to +-pi (tiny y, x < 0) and +-pi/2 (tiny x), at every scale."""
    ys: list[float] = []
    xs: list[float] = []
    for s in (1.0, L["max"], L["min"], 2.0**-30, 2.0**30):
        for small in (L["tiny"], L["min"], 1e-300 if dtype == F64 else 1e-38, 1e-20, 1e-8, 2.0**-27, 1e-3):
            v = small * s
            if not (0 < v < np.inf) or dtype.type(v) == 0:
                continue
            for sg in (1, -1):
                ys += [sg * v, sg * s, sg * s]
                xs += [-s, v, -v]
    return ys, xs


def _atan2_tiny_over_moderate(dtype: np.dtype, L: dict) -> tuple[list[float], list[float]]:
    """(y, x) with the smaller magnitude tiny (subnormal up to 2^-900) over a moderate larger one (2^-900 to 2^0),
    both orders and all quadrants: the quotient's residual is subnormal unless the arguments are scaled up first."""
    if dtype != F64:
        return [], []
    rng = np.random.default_rng(31)
    n = 400
    small = np.exp2(rng.uniform(-1074.0, -900.0, n))
    large = np.exp2(rng.uniform(-900.0, 0.0, n)) * rng.uniform(1.0, 2.0, n)
    ys: list[float] = []
    xs: list[float] = []
    for a, b in zip(small.tolist(), large.tolist()):
        if a == 0.0:
            continue
        for sy in (1, -1):
            for sx in (1, -1):
                ys += [sy * a, sy * b]
                xs += [sx * b, sx * a]
    return ys, xs


def atan2_cases(dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """(y, x): special values in all combinations, the reduction boundaries (ratios 7/16, 11/16, 1) at every
    scale, results next to +-pi and +-pi/2, tiny over moderate magnitudes (float64), random magnitudes over the
    whole exponent range in all quadrants, and random ratios from 1e-300 to 1e300 (float32: 1e-38 to 1e38)."""
    L = _limits(dtype)
    rng = np.random.default_rng(29)
    special = [0.0, L["tiny"], L["min"], 1.0, L["huge"], L["max"], 3.0 * L["tiny"], 0.75]
    special = special + [-v for v in special]
    ys: list[float] = []
    xs: list[float] = []

    def add(yv: Sequence[float], xv: Sequence[float]) -> None:
        ys.extend(yv)
        xs.extend(xv)

    for a in special:
        add([a] * len(special), special)
    add(*_atan2_boundaries(dtype, L))
    add(*_atan2_near_pi(dtype, L))
    add(*_atan2_tiny_over_moderate(dtype, L))
    # random magnitudes over the whole exponent range, all quadrants
    n = 700
    y = _signs(rng, _log_uniform(rng, n, L["emin"], L["emax"], dtype))
    x = _signs(rng, _log_uniform(rng, y.size, L["emin"], L["emax"], dtype))
    m = min(y.size, x.size)
    add(y[:m].tolist(), x[:m].tolist())
    # random ratios |y/x| log-uniform in [1e-300, 1e300] (float32: [1e-38, 1e38]) and, denser, in [2^-30, 2^30]
    rmax = 996.0 if dtype == F64 else 126.0
    for lo, hi, count in ((-rmax, rmax, 700), (-30.0, 30.0, 900)):
        x = _log_uniform(rng, count, L["emin"], L["emax"], dtype).astype(np.float64)
        r = np.exp2(rng.uniform(lo, hi, x.size))
        with np.errstate(over="ignore", under="ignore"):
            y = (x * r).astype(dtype).astype(np.float64)
        keep = np.isfinite(y) & (y > 0)
        add(_signs(rng, y[keep]).tolist(), _signs(rng, x[keep]).tolist())
    return np.array(ys, dtype), np.array(xs, dtype)


def _pio2_multiples(dtype: np.dtype, count: int) -> np.ndarray:
    """The values of dtype nearest k pi/2 (0 < k pi/2 < 2^19) that lie closest to it (the hardest
    reductions), and a few random k, each with its neighbors."""
    k = np.arange(1, int(SINCOS_LIMIT / (np.pi / 2)), dtype=np.float64)
    p1, p2, p3 = 1.57079632673412561417e+00, 6.07710050630396597660e-11, 2.02226624879595063154e-21
    x = (k * p1 + k * p2).astype(dtype).astype(np.float64)  # k p1, k p2 exact (33-bit constants)
    d = np.abs(((x - k * p1) - k * p2) - k * p3) / np.spacing(x.astype(dtype)).astype(np.float64)
    pick = np.argsort(d)[:count]
    rng = np.random.default_rng(7)
    pick = np.concatenate([pick, rng.integers(0, k.size, count // 2), np.arange(8)])
    out = [_next(float(x[i]), dtype, j) for i in pick for j in (-1, 0, 1)]
    return np.array(out + [-v for v in out], dtype)


def sincos_cases(dtype: np.dtype) -> np.ndarray:
    L = _limits(dtype)
    rng = np.random.default_rng(19)
    vals = [0.0, L["tiny"], 3 * L["tiny"], L["min"], 1e-300 if dtype == F64 else 1e-38, 1e-20, 1e-8, 2.0**-27,
            1e-3, 0.5, 1.0, 2.0, 10.0, 1000.0, _next(SINCOS_LIMIT, dtype, -1)]
    # the reduction's boundaries (x 2/pi = k + 1/2, where the quadrant changes) and their neighbors
    for kk in (0, 1, 2, 3, 10, 1000, 300000):
        b = (kk + 0.5) * np.pi / 2
        vals += [_next(b, dtype, j) for j in range(-2, 3)]
    v = np.array(vals + [-t for t in vals], dtype)
    logu = _signs(rng, _log_uniform(rng, 700, L["emin"], 19.0, dtype))
    unif = rng.uniform(-SINCOS_LIMIT, SINCOS_LIMIT, 400).astype(dtype)
    small = rng.uniform(-8.0, 8.0, 400).astype(dtype)
    return np.concatenate([v, logu, unif, small, _pio2_multiples(dtype, 80)])


# The references, memoized per dtype (the arguments do not depend on the architecture)
_REF: dict[tuple[str, str], tuple] = {}


def _reference(kind: str, dtype: np.dtype, make: Callable[[], tuple]) -> tuple:
    key = (kind, dtype.name)
    if key not in _REF:
        mp.dps = 40
        _REF[key] = make()
    return _REF[key]


def _atan2_ref(dtype: np.dtype):
    y, x = atan2_cases(dtype)
    return y, x, [_atan2_exact(float(a), float(b)) for a, b in zip(y, x)]


def _atan2_exact(y: float, x: float):
    """atan2(y, x) to 40 digits; y = +-0 by IEEE's rules (mpmath has no signed zero): +-0 for x = +0 or x > 0,
    +-pi for x = -0 or x < 0 (the sign of the zero results is checked separately)."""
    if y == 0:
        return mpmath.mpf(0) if np.copysign(1.0, x) > 0 else (mpmath.pi if np.copysign(1.0, y) > 0 else -mpmath.pi)
    return mpmath.atan2(mpmath.mpf(y), mpmath.mpf(x))


def _sincos_ref(dtype: np.dtype):
    x = sincos_cases(dtype)
    mx = [mpmath.mpf(float(a)) for a in x]
    return x, [mpmath.sin(a) for a in mx], [mpmath.cos(a) for a in mx]


def _half_ref(dtype: np.dtype):
    rng = np.random.default_rng(5)
    pi = float(np.pi)
    edge = [pi, pi / 2, 0.0, 1e-300 if dtype == F64 else 1e-38, float(_limits(dtype)["tiny"]), 2.0, 3.0]
    v = [_next(e, dtype, j) for e in edge for j in range(-3, 4)]
    v = [t for t in v if abs(t) <= float(dtype.type(pi))]
    x = np.concatenate([np.array(v + [-t for t in v], dtype), rng.uniform(-pi, pi, 1200).astype(dtype),
                        (pi - _log_uniform(rng, 300, -60, 1, dtype).astype(np.float64)).astype(dtype)])
    x = x[np.abs(x) <= dtype.type(pi)]
    half = [mpmath.mpf(float(a)) / 2 for a in x]
    return x, [mpmath.sin(h) for h in half], [mpmath.cos(h) for h in half], [mpmath.tan(h) for h in half]


def _half_hard_ref(dtype: np.dtype):
    """Bend angles where tan(t/2) is just below 1 (t in [1.53, pi/2]), tb_half_sincos_tan's worst range, and the
    review's worst arguments."""
    rng = np.random.default_rng(17)
    x = np.concatenate([rng.uniform(1.53, np.pi / 2, 3000), [1.5346471800690948, 1.570748169672553]]).astype(dtype)
    half = [mpmath.mpf(float(a)) / 2 for a in x]
    return x, None, None, [mpmath.tan(h) for h in half]


# ---- the tests -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("vec", [True, False], ids=["vector", "scalar"])
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_atan2_ulp(harness, dtype, vec):
    y, x, exact = _reference("atan2", dtype, lambda: _atan2_ref(dtype))
    got = harness.atan2(y, x, dtype, vec)
    _check(f"tb_atan2v {dtype.name}", (y, x), _ulp_errors(got, exact, dtype))
    # the sign of a zero or tiny result is y's (atan2 is odd in y)
    nz = got != 0
    assert np.all(np.signbit(got[nz]) == np.signbit(y[nz]))


@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_atan2_signed_zeros_and_quadrants(harness, dtype):
    t = dtype.type
    pi, pio2 = t(_rounded(mpmath.pi, dtype)), t(_rounded(mpmath.pi / 2, dtype))
    L = _limits(dtype)
    cases = [(0.0, 0.0, t(0.0)), (-0.0, 0.0, t(-0.0)), (0.0, -0.0, pi), (-0.0, -0.0, -pi)]
    for x in (L["tiny"], L["min"], 1.0, L["max"]):
        cases += [(0.0, x, t(0.0)), (-0.0, x, t(-0.0)), (0.0, -x, pi), (-0.0, -x, -pi)]
        cases += [(x, 0.0, pio2), (x, -0.0, pio2), (-x, 0.0, -pio2), (-x, -0.0, -pio2)]
    y = np.array([c[0] for c in cases], dtype)
    x = np.array([c[1] for c in cases], dtype)
    want = np.array([c[2] for c in cases], dtype)
    for vec in (True, False):
        got = harness.atan2(y, x, dtype, vec)
        bad = (got != want) | (np.signbit(got) != np.signbit(want))
        assert not bad.any(), [(float(a), float(b), float(g), float(w))
                               for a, b, g, w in zip(y[bad], x[bad], got[bad], want[bad])]
    ny = np.array([np.nan, 1.0, np.nan, -0.0], dtype)
    nx = np.array([1.0, np.nan, np.nan, np.nan], dtype)
    assert np.isnan(harness.atan2(ny, nx, dtype)).all() and np.isnan(harness.atan2(ny, nx, dtype, False)).all()


@pytest.mark.parametrize("vec", [True, False], ids=["vector", "scalar"])
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_sincos_ulp(harness, dtype, vec):
    x, sin, cos = _reference("sincos", dtype, lambda: _sincos_ref(dtype))
    s, c = harness.sincos(x, dtype, vec)
    es, ec = _ulp_errors(s, sin, dtype), _ulp_errors(c, cos, dtype)
    msg = "; ".join([_worst(f"sin {dtype.name}", (x,), es), _worst(f"cos {dtype.name}", (x,), ec)])
    assert max(float(es.max()), float(ec.max())) <= 1.0, msg
    # sin(+-0) = +-0 and cos(+-0) = 1; sin is odd and cos even, bit for bit
    z = np.array([0.0, -0.0], dtype)
    sz, cz = harness.sincos(z, dtype, vec)
    assert list(np.signbit(sz)) == [False, True] and np.all(sz == 0) and np.all(cz == 1)
    sn, cn = harness.sincos(-x, dtype, vec)
    assert np.array_equal(sn, -s) and np.array_equal(cn, c)


@pytest.mark.parametrize("vec", [True, False], ids=["vector", "scalar"])
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_sincos_fast_ulp_on_the_kernels_domain(harness, dtype, vec):
    """tb_sincos (the kernels' one: the first reduction step only) within 1 ulp on [-pi, pi] but within 1e-9 of
    +-pi/2 and +-pi (where the kernels never use the tiny value, see phi_diff), and bit for bit
    tb_sincos_accurate on [-pi/4, pi/4] (no reduction: the kernels' half angles)."""
    x, sin, cos = _reference("sincos", dtype, lambda: _sincos_ref(dtype))
    keep = (np.abs(x) <= np.pi) & np.all([np.abs(np.abs(x.astype(np.float64)) - k * np.pi / 2) > 1e-9
                                          for k in (1, 2)], axis=0)
    xs = x[keep]
    s, c = harness._pair("sincos_fast", xs, dtype, vec)
    es = _ulp_errors(s, [v for v, k in zip(sin, keep) if k], dtype)
    ec = _ulp_errors(c, [v for v, k in zip(cos, keep) if k], dtype)
    assert xs.size > 500 and max(float(es.max()), float(ec.max())) <= 1.0, _worst("fast sin", (xs,), es)
    small = x[np.abs(x) <= np.pi / 4]
    s1, c1 = harness._pair("sincos_fast", small, dtype, vec)
    s2, c2 = harness.sincos(small, dtype, vec)
    assert np.array_equal(s1, s2) and np.array_equal(c1, c2)


@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_half_sincos_ulp(harness, dtype):
    """tb_half_sincos (sin(t/2), cos(t/2) of the reference angles; here t in [-pi, pi], near +-pi too) to its
    documented accuracy, "a few ulps": 1.5 ulps each (the complement w = ((pi_hi - |t|) + pi_lo) / 2 is rounded once
    before tb_sincos: measured 0.94 / 1.33 ulps in double, 0.67 / 1.12 in float); s / c within 2.5 ulps of tan(t/2)
    (two rounded values and a rounded quotient: measured 2.2 / 1.9), which is why the kernels take a bend angle's
    tan(t/2) from tb_half_sincos_tan (test_half_sincos_tan_ulp)."""
    kind = "half_sincos"
    x, sin, cos, tan = _reference("half", dtype, lambda: _half_ref(dtype))
    for vec in (True, False):
        s, c = harness._pair(kind, x, dtype, vec)
        es, ec = _ulp_errors(s, sin, dtype), _ulp_errors(c, cos, dtype)
        with np.errstate(divide="ignore", invalid="ignore"):
            et = _ulp_errors(s / c, tan, dtype)
        msg = "; ".join(_worst(f"half {n} {dtype.name}", (x,), e) for n, e in (("sin", es), ("cos", ec), ("tan", et)))
        assert es.max() <= 1.5 and ec.max() <= 1.5 and et.max() <= 2.5, msg


@pytest.mark.parametrize("vec", [True, False], ids=["vector", "scalar"])
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_half_sincos_beyond_pi(harness, dtype, vec):
    """tb_half_sincos of the reference angles (rest, theta_prev: any finite value reaches it) past +-pi, up to
    tb_sincos's domain 2^19: within 4 ulps of |t| (absolute; the complement pi_hi - |t| is no longer exact there)
    of sin(t/2) and cos(t/2), so that a reference angle past the fold gives the tan model's periodic value, not
    the polynomials' garbage."""
    rng = np.random.default_rng(11)
    t = np.concatenate([rng.uniform(np.pi, 8.0, 400), _log_uniform(rng, 400, 2, 18, dtype).astype(np.float64),
                        np.array([1.5, 2.0, 3.0, 4.0]) * np.pi]).astype(dtype)
    t = np.concatenate([t, -t])
    s, c = harness.half_sincos(t, dtype, vec)
    mp.dps = 40
    half = [mpmath.mpf(float(a)) / 2 for a in t]
    es = np.array([abs(float(mpmath.sin(h) - float(v))) for h, v in zip(half, s)])
    ec = np.array([abs(float(mpmath.cos(h) - float(v))) for h, v in zip(half, c)])
    bound = 4 * np.spacing(np.abs(t)).astype(np.float64)
    worst = int(np.argmax(np.maximum(es, ec) / bound))
    assert np.all(es <= bound) and np.all(ec <= bound), (
        f"t = {t[worst]!r}: |sin error| {es[worst]:.3g}, |cos error| {ec[worst]:.3g}, bound {bound[worst]:.3g}")


@pytest.mark.parametrize("vec", [True, False], ids=["vector", "scalar"])
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_half_sincos_tan_ulp(harness, dtype, vec):
    """tb_half_sincos_tan, the tan model's sin(t/2), cos(t/2) and tan(t/2) of a bend angle from one kernel evaluation
    and one division: each within 1 ulp for t in [-pi, pi] (float: to the float pi), near 0, +-pi/2 and +-pi (the
    complement's tail carried: the small cosine near +-pi to 1 ulp, where tb_half_sincos's rounded complement gives
    1.3; tan measured 0.77 ulp over 25,000 arguments); odd and even bit for bit, signed zeros."""
    x, sin, cos, tan = _reference("half", dtype, lambda: _half_ref(dtype))
    s, c, u = harness.half_sincos_tan(x, dtype, vec)
    for name, got, exact in (("sin", s, sin), ("cos", c, cos), ("tan", u, tan)):
        _check(f"tb_half_sincos_tan {name} {dtype.name}", (x,), _ulp_errors(got, exact, dtype))
    # where tan(t/2) is just below 1 (t in [1.53, pi/2]) the quotient's errors add up most: 0.92 ulp in a scan of
    # 12 million arguments
    hard, _, _, tan_hard = _reference("half_tan_hard", dtype, lambda: _half_hard_ref(dtype))
    _check(f"tb_half_sincos_tan tan {dtype.name} near pi/2", (hard,),
           _ulp_errors(harness.half_sincos_tan(hard, dtype, vec)[2], tan_hard, dtype))
    s2, c2, u2 = harness.half_sincos_tan(-x, dtype, vec)
    assert np.array_equal(s2, -s) and np.array_equal(c2, c) and np.array_equal(u2, -u)
    zs, zc, zu = harness.half_sincos_tan(np.array([0.0, -0.0], dtype), dtype, vec)
    assert np.all(zc == 1) and list(np.signbit(zs)) == [False, True] and list(np.signbit(zu)) == [False, True]


def _log_ref(dtype: np.dtype):
    """Positive arguments over the whole range (subnormal to the largest, log-uniform), near 1 (where log is
    tiny), and the powers of two and their neighbours."""
    rng = np.random.default_rng(7)
    lim = _limits(dtype)
    near1 = 1.0 + _signs(rng, _log_uniform(rng, 400, -52 if dtype == F64 else -23, -1, dtype).astype(np.float64))
    edges = [_next(2.0**e, dtype, j) for e in (-1, 0, 1, 10, -1022 if dtype == F64 else -126) for j in range(-3, 4)]
    x = np.concatenate([_log_uniform(rng, 1500, lim["emin"], lim["emax"], dtype), near1.astype(dtype),
                        np.array(edges + [lim["tiny"], lim["min"], lim["max"]], dtype)])
    x = x[x > 0]
    return x, [mpmath.log(mpmath.mpf(float(a))) for a in x]


@pytest.mark.parametrize("vec", [True, False], ids=["vector", "scalar"])
@pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: d.name)
def test_log_ulp(harness, dtype, vec):
    """tb_logv (the neo-Hookean's log J in the membrane's lane loops) within 1 ulp over every positive argument,
    subnormals included; log(1) = 0, log(0) = -inf, log(inf) = inf, negative and NaN arguments NaN."""
    x, exact = _reference("log", dtype, lambda: _log_ref(dtype))
    _check(f"tb_logv {dtype.name}", (x,), _ulp_errors(harness.log(x, dtype, vec), exact, dtype))
    special = harness.log(np.array([1.0, 0.0, np.inf, -1.0, np.nan], dtype), dtype, vec)
    assert special[0] == 0 and special[1] == -np.inf and special[2] == np.inf and np.isnan(special[3:]).all()


def test_cuda_device_code_compiles(tmp_path):
    """The same definitions compile as CUDA device code (compile only: nvcc to PTX, no GPU needed), inlined
    into the kernel without a call (no library function on either device)."""
    nvcc = cfg.find_nvcc()
    if nvcc is None or not os.path.exists(nvcc):
        pytest.skip("nvcc not found")
    ptx = str(tmp_path / "vector_math.ptx")
    cmd = [nvcc, "-std=c++17", "-O3", f"-I{ROOT}", "-ptx", os.path.join(ROOT, "tests", "native_harness", "vector_math.cu"),
           "-o", ptx]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}"
    with open(ptx) as fh:
        text = fh.read()
    assert text.count(".entry") == 2 and not re.search(r"^\s*call", text, re.M)
