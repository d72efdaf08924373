"""Machine floors of the benchmarked operations: measured memory bandwidth, flop rate and costs of the costly
operations, bytes and operations per hinge, so that every timing can be compared with what this machine's units
allow for the counted formulas.

* **Bandwidth**: a STREAM-like copy (``b <- a``) and triad (``a <- b + s c``) in torch on the device,
  all threads (``torch.get_num_threads()`` on the CPU), arrays of 2^25 float64 (256 MiB each, far
  above any cache), best of several runs.  Bytes counted as STREAM does: 2 arrays per element for the
  copy, 3 for the triad (no write-allocate traffic).  The floors use the larger of the two.
* **Flop rate**: a square ``torch.mm`` (n = 2048 on the CPU, 8192 on a GPU) in the dtype, ``2 n^3`` flops:
  the fused multiply-add peak of the vector units, which no elementwise kernel reaches (divisions,
  square roots and atan2 are several instructions each: see the op costs below).
* **Bytes per hinge** (:func:`bytes_per_hinge`): the compulsory traffic of one call, every array
  read or written once, from the actual sizes of the mesh: the hinge index array ``(H, 4)`` int64,
  the positions ``(V, 3)`` (a sheet has V ~ H/3, so about one coordinate per hinge: the 12 coordinates
  a hinge gathers come from the caches, the hinges being ordered along the mesh), the per-hinge
  parameters (weight ``a`` and rest angle; the stiffness is one scalar), and the op's own traffic:
  nothing more for the energy (a scalar), the gradient ``(V, 3)`` written, the HVP's direction
  ``(V, 3)`` read and product ``(V, 3)`` written, the blocks ``(H, 12, 12)`` written, the CSR values
  (``nnz``) written for the assembly (its index arrays are built once and reused).
* **Flops per hinge** (:func:`flops_per_hinge`): an operation count of torchbend's closed forms,
  counted by running the eager path (``backend="eager"``: the same formulas the C++ kernels compile)
  under a dispatch mode that adds up the output elements of every pointwise aten op (each
  ``+ - * /``, sqrt, atan2, comparison or select counts one, a fused ``a + b c`` two), the input
  elements of every reduction and scatter-add, and ``2 m n k`` per matrix product; gathers, copies
  and views count nothing.

* **Throughput of the costly operations** (:func:`op_costs`, CPU): divisions, square roots and the
  transcendental functions (sin, cos, tan, atan2, ...) are not one flop each.  Each is timed on this machine as
  PyTorch's own vectorized kernel (MKL's vector math or SLEEF, as the build has them) over arrays of 32768
  elements in the L2 cache, on one thread, best of many calls, minus the time of a multiplication over the same
  arrays (the loads, stores and call that a kernel keeping its values in registers does not pay; this errs low):
  ns per element, divided by the run's thread count (perfect scaling: errs low again).  The counter keeps every
  aten op's count by name (:func:`ops_per_hinge`).
* **Compute floor** (:func:`compute_floor_ns`): the two kinds of unit overlap, so the floor is the larger of
  the FMA units' work (the plain arithmetic at the matmul flop rate, as if every multiply paired with an add,
  plus each transcendental's cost: they are polynomials on the same units) and the divider's (each division,
  reciprocal and square root at its cost).  A sine and a cosine are priced as one sincos (the dearer of the two)
  as far as their counts pair up, whether or not they share an argument (errs low).  Without measured costs (the
  GPU section) every counted op is one flop at the matmul rate.  It is the eager formula's operation count at
  this machine's library throughputs, not a bound on every implementation: a kernel that needs fewer divisions
  or transcendentals than the eager formula (a rest angle's sine precomputed, say) can run below it.

``floor = max(bytes / bandwidth, compute floor)`` per hinge; the tables give ``measured / floor``.
"""
from __future__ import annotations

import time

import torch
from torch.utils._python_dispatch import TorchDispatchMode

OPS = ["energy", "gradient", "hvp", "hinge_hessians", "assembly"]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _best(fn, device: torch.device, repeat: int) -> float:
    fn()
    _sync(device)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        best = min(best, time.perf_counter() - t0)
    return best


def _release(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.empty_cache()  # the measurement processes that follow need the memory


def _stream_times(device: torch.device, n: int, repeat: int) -> tuple[float, float]:
    a = torch.ones(n, dtype=torch.float64, device=device)
    b = torch.full_like(a, 2.0)
    c = torch.full_like(a, 0.5)
    return (_best(lambda: b.copy_(a), device, repeat),
            _best(lambda: torch.add(b, c, alpha=3.0, out=a), device, repeat))


def stream_bandwidth(device="cpu", n: int = 2**25, repeat: int = 10) -> dict:
    """``{"copy": B/s, "triad": B/s, "bandwidth": max of both, "array_mib": ..., "threads": ...}``."""
    device = torch.device(device)
    if device.type == "cuda":
        n = max(n, 2**28)  # 2 GiB per array: far above the L2 cache
    t_copy, t_triad = _stream_times(device, n, repeat)
    _release(device)
    s = 8
    copy, triad = 2 * n * s / t_copy, 3 * n * s / t_triad
    return {"copy": copy, "triad": triad, "bandwidth": max(copy, triad), "array_mib": n * s / 2**20,
            "threads": torch.get_num_threads() if device.type == "cpu" else None}


def _mm_time(dtype: torch.dtype, device: torch.device, n: int, repeat: int) -> float:
    gen = torch.Generator(device=device).manual_seed(0)
    a = torch.rand(n, n, dtype=dtype, device=device, generator=gen)
    b = torch.rand(n, n, dtype=dtype, device=device, generator=gen)
    out = torch.empty_like(a)
    return _best(lambda: torch.mm(a, b, out=out), device, repeat)


def matmul_flops(dtype: torch.dtype, device="cpu", n: int | None = None, repeat: int = 5) -> float:
    """Flop rate [flop/s] of a square matrix product in ``dtype``: the FMA peak proxy."""
    device = torch.device(device)
    n = n or (8192 if device.type == "cuda" else 2048)
    t = _mm_time(dtype, device, n, repeat)
    _release(device)
    return 2.0 * n**3 / t


DIVIDER = ("div", "reciprocal", "sqrt", "rsqrt")
TRANSCENDENTAL = ("sin", "cos", "tan", "atan2", "atan", "asin", "acos", "exp", "expm1", "log", "log1p", "tanh")


def op_costs(dtype: torch.dtype, device="cpu", n: int = 32768, repeat: int = 300) -> dict[str, float]:
    """``{aten op name: ns per element}`` of the divider's and the transcendental ops in ``dtype`` on the CPU
    (see the module docstring): PyTorch's kernel over L2-resident arrays minus a multiplication's time, at least 0.
    Empty for other devices (their compute floor counts every op as one flop)."""
    if torch.device(device).type != "cpu":
        return {}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # PyTorch splits the transcendentals over threads from 2048 elements on
    try:
        return _op_costs_one_thread(dtype, n, repeat)
    finally:
        torch.set_num_threads(threads)


def _op_costs_one_thread(dtype: torch.dtype, n: int, repeat: int) -> dict[str, float]:
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(n, dtype=dtype, generator=gen) + 0.5  # (0.5, 1.5): no special cases
    b = torch.rand(n, dtype=dtype, generator=gen) + 0.5
    out = torch.empty_like(a)
    unary = {"reciprocal": torch.reciprocal, "sqrt": torch.sqrt, "rsqrt": torch.rsqrt, "sin": torch.sin,
             "cos": torch.cos, "tan": torch.tan, "atan": torch.atan, "asin": lambda t, out: torch.asin(t - 0.5, out=out),
             "acos": lambda t, out: torch.acos(t - 0.5, out=out), "exp": torch.exp, "expm1": torch.expm1,
             "log": torch.log, "log1p": torch.log1p, "tanh": torch.tanh}
    calls = {"mul": lambda: torch.mul(a, b, out=out), "div": lambda: torch.div(a, b, out=out),
             "atan2": lambda: torch.atan2(a, b, out=out)}
    calls.update({k: (lambda f=f: f(a, out=out)) for k, f in unary.items()})
    per = {k: _best(f, torch.device("cpu"), repeat) / n * 1e9 for k, f in calls.items()}
    base = per.pop("mul")
    shift = _best(lambda: torch.sub(a, 0.5), torch.device("cpu"), repeat) / n * 1e9  # asin's and acos's own pass
    per["asin"], per["acos"] = per["asin"] - shift, per["acos"] - shift
    return {k: max(0.0, t - base) for k, t in per.items()}


def compute_floor_ns(counts: dict[str, float], flop_rate: float, costs: dict[str, float] | None,
                     threads: int = 1) -> float:
    """Compute floor [ns per hinge] of an op whose aten ops ran ``counts`` (per hinge, by name; see
    :class:`FlopCounter`) on a machine of ``flop_rate`` [flop/s] (at ``threads`` threads) and one-thread op costs
    ``costs`` (:func:`op_costs`)."""
    total = sum(counts.values())
    if not costs:
        return total / flop_rate * 1e9
    costly = {k: v for k, v in counts.items() if k in costs}
    arithmetic = total - sum(costly.values())
    fma = sum(v * costs[k] for k, v in costly.items() if k not in DIVIDER)
    if "sin" in costly and "cos" in costly:  # a paired sine and cosine: one sincos, the dearer of the two
        fma -= min(costly["sin"], costly["cos"]) * min(costs["sin"], costs["cos"])
    divider = sum(v * costs[k] for k, v in costly.items() if k in DIVIDER)
    return max(arithmetic / flop_rate * 1e9 + fma / threads, divider / threads)


def bytes_per_hinge(op: str, itemsize: int, hinges: int, vertices: int, nnz: int, param_elems: int) -> float:
    """Compulsory bytes of one call of ``op`` per hinge (see the module docstring).

    ``param_elems``: elements of the per-hinge parameter arrays the kernel reads (weights, rest angles,
    stiffness), ``nnz``: values of the assembled CSR matrix."""
    H, s = hinges, itemsize
    inputs = 4 * 8 * H + 3 * vertices * s + param_elems * s
    own = {
        "energy": 0,
        "gradient": 3 * vertices * s,
        "hvp": 2 * 3 * vertices * s,
        "hinge_hessians": 144 * H * s,
        "assembly": nnz * s,
    }[op]
    return (inputs + own) / H


class FlopCounter(TorchDispatchMode):
    """Counts arithmetic of the aten ops run inside it (see the module docstring); per op name in ``by_op``."""

    MATMUL = {"mm", "bmm", "addmm", "baddbmm"}
    FREE = {"copy_", "_to_copy", "clone", "index", "index_select", "gather", "cat", "stack", "expand", "view",
            "reshape", "permute", "transpose", "select", "slice", "unsqueeze", "squeeze", "t", "contiguous",
            "empty", "empty_like", "zeros", "zeros_like", "new_zeros", "new_empty", "full", "fill_", "zero_",
            "_unsafe_view", "as_strided", "detach", "lift_fresh", "alias", "unbind", "split", "split_with_sizes",
            "resize_", "_reshape_alias", "arange", "lift_fresh_copy", "set_", "scalar_tensor", "ones_like"}

    def __init__(self):
        super().__init__()
        self.total = 0
        self.by_op: dict[str, int] = {}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = func.overloadpacket.__name__
        n = 0
        if name in self.FREE:
            pass
        elif name in self.MATMUL:
            a, b = [t for t in args if isinstance(t, torch.Tensor)][-2:]
            n = 2 * a.numel() * b.shape[-1]
        elif name in ("index_add", "index_add_", "scatter_add", "scatter_add_", "index_put", "index_put_"):
            src = [t for t in args if isinstance(t, torch.Tensor)][-1]
            n = src.numel()
        elif torch.Tag.pointwise in func.tags:
            outs = out if isinstance(out, (tuple, list)) else (out,)
            n = sum(t.numel() for t in outs if isinstance(t, torch.Tensor))
            n *= 2 if name in ("addcmul", "addcmul_", "addcdiv", "addcdiv_", "lerp", "lerp_") else 1
        elif torch.Tag.reduction in func.tags or name in ("sum", "mean", "linalg_vector_norm", "norm", "amax", "amin"):
            n = sum(t.numel() for t in args if isinstance(t, torch.Tensor))
        if n:
            self.total += n
            self.by_op[name] = self.by_op.get(name, 0) + n
        return out


def flops_per_hinge(bend, x: torch.Tensor, v: torch.Tensor) -> dict:
    """``{op: flops per hinge}`` of torchbend's closed forms (eager path) at ``x``, direction ``v``."""
    return {op: sum(counts.values()) for op, counts in ops_per_hinge(bend, x, v).items()}


def ops_per_hinge(bend, x: torch.Tensor, v: torch.Tensor) -> dict:
    """``{op: {aten op name: count per hinge}}`` of torchbend's closed forms (eager path), as :func:`flops_per_hinge`
    counts them."""
    calls = {
        "energy": lambda: bend(x, backend="eager"),
        "gradient": lambda: bend.gradient(x, backend="eager"),
        "hvp": lambda: bend.hvp(x, v, backend="eager"),
        "hinge_hessians": lambda: bend.hinge_hessians(x, backend="eager"),
        "assembly": lambda: bend.hessian(x, backend="eager"),
    }
    out = {}
    H = bend.hinge_count
    bend.hessian(x, backend="eager")  # builds the CSR pattern outside the count
    with torch.no_grad():
        for op, fn in calls.items():
            counter = FlopCounter()
            with counter:
                fn()
            out[op] = {name: n / H for name, n in counter.by_op.items()}
    return out
