"""Input checks shared by every layer: each raises a ``ValueError`` that names the input and what it got."""
from __future__ import annotations

import math
import operator

import torch
from torch import Tensor

from ._torch_compat import is_functorch_wrapped

__all__ = [
    "is_traced",
    "check_positions",
    "check_direction",
    "check_finite_tensor",
    "positive",
    "nonnegative",
    "vec3",
    "integer",
]


def is_traced(t: Tensor) -> bool:
    """True under ``torch.func`` transforms and while ``torch.compile``/``torch.export`` trace (checks that need
    data-dependent control flow are skipped there; the compiled operators check inside)."""
    if torch.compiler.is_compiling():
        return True
    return bool(is_functorch_wrapped(t))


def _finite_sum(t: Tensor) -> bool:
    """A finite sum proves every entry finite (a NaN or an infinity makes it NaN or infinite) at the cost of one
    reduction, without the boolean tensor of ``isfinite``; an overflowing sum of finite entries says nothing (the
    callers then check entry by entry)."""
    return t.numel() == 0 or bool(torch.isfinite(t.detach().sum()))


def check_positions(x, vertex_count: int, name: str = "x", check_finite: bool = True) -> Tensor:
    """``x`` must be a floating ``(..., V, 3)`` tensor; with ``check_finite`` also finite (the error
    names the first offending vertices).  ``meta`` tensors have no values: only their shape is checked."""
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape (..., {vertex_count}, 3), got {type(x).__name__}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating point tensor, got dtype {x.dtype}")
    if x.ndim < 2 or x.shape[-1] != 3 or x.shape[-2] != vertex_count:
        raise ValueError(f"{name} must have shape (..., {vertex_count}, 3) (V = {vertex_count}), got {tuple(x.shape)}")
    if check_finite and not is_traced(x) and x.device.type != "meta" and not _finite_sum(x):
        bad = ~torch.isfinite(x.detach())
        if bool(bad.any()):
            verts = torch.nonzero(bad.reshape(-1, vertex_count, 3).any(-1).any(0)).reshape(-1)[:8].tolist()
            raise ValueError(f"{name} holds non-finite (NaN or Inf) coordinates at vertices {verts}")
    return x


def check_finite_tensor(t: Tensor, name: str, check: bool = True) -> Tensor:
    """``t`` must hold finite values (skipped under ``torch.func`` transforms or with ``check=False``)."""
    if check and not is_traced(t) and not _finite_sum(t) and not bool(torch.isfinite(t.detach()).all()):
        raise ValueError(f"{name} holds non-finite values")
    return t


def check_direction(v, x: Tensor, check_finite: bool = True) -> Tensor:
    """A Hessian-vector product's direction: ``v`` shaped like ``x`` (or broadcasting to it), finite,
    returned on ``x``'s device in ``x``'s dtype."""
    v = torch.as_tensor(v, device=x.device)
    if v.shape[-2:] != x.shape[-2:]:
        raise ValueError(f"v must have shape (..., {x.shape[-2]}, 3) like x, got {tuple(v.shape)}")
    check_finite_tensor(v, "v", check_finite)
    return v.to(x.dtype)


def positive(value, name: str) -> float:
    """``value`` as a positive, finite float."""
    v = float(value)
    if not (v > 0 and math.isfinite(v)):
        raise ValueError(f"{name} must be positive and finite, got {value!r}")
    return v


def nonnegative(value, name: str) -> float:
    """``value`` as a non-negative, finite float."""
    v = float(value)
    if not (v >= 0 and math.isfinite(v)):
        raise ValueError(f"{name} must be >= 0 and finite, got {value!r}")
    return v


def vec3(value, name: str) -> tuple[float, float, float]:
    """``value`` as a finite 3-tuple of floats."""
    try:
        t = tuple(float(v) for v in value)
    except TypeError:
        raise ValueError(f"{name} must be a 3-vector, got {value!r}") from None
    if len(t) != 3 or not all(math.isfinite(v) for v in t):
        raise ValueError(f"{name} must be a finite 3-vector, got {value!r}")
    return t  # type: ignore[return-value]


def integer(value, name: str, minimum: int) -> int:
    """``value`` as an ``int >= minimum``."""
    value = operator.index(value)
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value
