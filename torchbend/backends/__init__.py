"""Layer 3, backends: the single place that decides whether eager PyTorch or compiled code runs.

Every entry point of the energies calls :func:`select_backend` with the name of its operation, the
requested backend (``"auto" | "eager" | "native"``: the module's ``backend=`` or a call's) and its
inputs; the answer depends only on those (device, dtype, whether an autograd graph is recorded or
a ``torch.func`` transform traces them) and on whether the compiled extension could be built.
There is no global switch; :func:`use_backend` changes what ``"auto"`` means inside a ``with``
block (a context variable, so threads and tasks do not see each other's choice).

Compiled operations (:mod:`torchbend.backends.native`, C++ sources in ``torchbend/csrc``):
:data:`NATIVE_OPS`.  Every other operation runs eagerly whatever is asked.
"""
from __future__ import annotations

import contextlib
import contextvars
import warnings
from collections.abc import Iterator

import torch
from torch import Tensor

from .._torch_compat import assume_constant_result, forward_ad_level, is_functorch_wrapped
from ..options import Backend
from . import native
from ._table import DIFFERENTIABLE, ENTRY_POINTS, ONE_MESH
from .compile_guard import CompiledDoubleBackwardError

__all__ = ["Backend", "CompiledDoubleBackwardError", "NATIVE_OPS", "select_backend", "native_unavailable_reason", "use_backend"]

NATIVE_OPS = frozenset(ENTRY_POINTS)
"""Operations with a compiled kernel (:data:`torchbend.backends._table.ENTRY_POINTS`, which says on which devices)."""

CUDA_OPS = frozenset(op for op, devices in ENTRY_POINTS.items() if "cuda" in devices)
"""Operations whose compiled kernel also runs on CUDA devices."""

_AUTO, _EAGER, _NATIVE = Backend.AUTO, Backend.EAGER, Backend.NATIVE  # (plain names: no enum lookups per call)
_auto: contextvars.ContextVar[Backend] = contextvars.ContextVar("torchbend_auto_backend", default=Backend.AUTO)


@contextlib.contextmanager
def use_backend(backend) -> Iterator[None]:
    """Inside the block, ``backend="auto"`` (the default of every module) means ``backend``."""
    token = _auto.set(Backend.parse(backend))
    try:
        yield
    finally:
        _auto.reset(token)


@assume_constant_result
def _auto_value() -> str:
    """What ``"auto"`` means here (:func:`use_backend`); a constant for ``torch.compile`` (a compiled
    function keeps the choice it was traced with)."""
    return _auto.get().value


def native_unavailable_reason(op: str, x: Tensor, *params: Tensor) -> str | None:
    """Why the compiled kernel cannot run ``op`` on these inputs (``None`` if it can)."""
    if op not in NATIVE_OPS:
        return f"there is no compiled kernel for {op!r}"
    device = x.device.type
    if device != "cpu" and (device != "cuda" or op not in CUDA_OPS):
        return f"there is no compiled {op!r} kernel for {device} tensors"
    if x.dtype is not torch.float32 and x.dtype is not torch.float64:
        return f"the compiled kernels take float32 or float64, x is {x.dtype}"
    compiling = torch.compiler.is_compiling()
    wrapped, grad, batched = not compiling and _wrapped(x), x.requires_grad, x.ndim > 2
    for t in params:  # one pass (this runs on every call of the hot paths)
        wrapped = wrapped or (not compiling and _wrapped(t))
        grad = grad or t.requires_grad
        batched = batched or t.ndim > 1
    if wrapped:
        return "the inputs are traced by a torch.func transform"
    if not compiling and forward_ad_level() >= 0:
        return "forward-mode AD is active (the eager Functions define jvp)"
    if grad and op not in DIFFERENTIABLE and torch.is_grad_enabled():
        return "an autograd graph is being recorded (the compiled kernels are not differentiable)"
    if batched:
        batch = tuple(x.shape[:-2])
        if op in ONE_MESH:
            return "the compiled assembly takes one mesh"
        if any(t.ndim > 1 and tuple(t.shape[:-1]) != batch for t in params):
            return "per-sample parameters whose batch shape differs from x's"
    return _unavailable(device)


_wrapped = is_functorch_wrapped
"""Whether a tensor is wrapped by a ``torch.func`` transform (:func:`torchbend._checks.is_traced` outside
compilation)."""


@assume_constant_result
def _unavailable(device_type: str) -> str | None:
    """Why the compiled kernels of ``device_type`` cannot be loaded (builds them on first use; a constant
    for ``torch.compile``, which does not trace the build)."""
    if device_type == "cuda":
        from . import cuda

        return None if cuda.load() is not None else f"the CUDA kernels are not available ({cuda.build_error()})"
    return None if native.load() is not None else f"the C++ extension is not available ({native.build_error()})"


def select_backend(op: str, backend, x: Tensor, *params: Tensor) -> Backend:
    """The backend that runs operation ``op`` on positions ``x`` with per-hinge ``params``: ``EAGER`` or
    ``NATIVE``.

    ``backend="auto"`` gives ``NATIVE`` wherever the compiled kernel applies (see
    :func:`native_unavailable_reason`) and ``EAGER`` elsewhere; ``"eager"`` always ``EAGER``;
    ``"native"`` gives ``NATIVE`` where a kernel exists for ``op`` and raises a ``ValueError`` saying
    why when it cannot run on these inputs (operations without a kernel run eagerly)."""
    requested = backend if type(backend) is Backend else Backend.parse(backend)
    if requested is _AUTO:  # eagerly the context variable itself; a constant for torch.compile
        requested = Backend(_auto_value()) if torch.compiler.is_compiling() else _auto.get()
    if requested is _EAGER:
        return _EAGER
    reason = native_unavailable_reason(op, x, *params)
    if reason is None:
        return _NATIVE
    if requested is Backend.NATIVE and op in NATIVE_OPS:
        raise ValueError(f"backend='native' cannot run {op}: {reason}")
    if op in NATIVE_OPS and reason.startswith(_WARN_REASONS) and not torch.compiler.is_compiling():
        _warn_once(op, reason)
    return Backend.EAGER


_WARN_REASONS = ("the compiled kernels take", "there is no compiled")
"""Fallbacks that cost speed without the caller having asked for them (an unsupported dtype or device):
they warn once per operation and reason.  A missing compiler warns once where the build fails; torch.func
transforms, forward-mode AD and recorded graphs of non-differentiable kernels are by design."""
_warned: set[tuple[str, str]] = set()


def _warn_once(op: str, reason: str) -> None:
    if (op, reason) not in _warned:
        _warned.add((op, reason))
        warnings.warn(f"torchbend: {op} runs on the eager path: {reason}", RuntimeWarning, stacklevel=4)
