"""The compiled kernels of the current device: :mod:`torchbend.backends.native` on the CPU,
:mod:`torchbend.backends.cuda` on a GPU, with one calling convention (the CUDA driver scatters with
atomics and ignores the incidence lists the CPU driver sums through)."""
from __future__ import annotations

from typing import Any

from torch import Tensor

from . import native

__all__ = ["module", "incidence"]


def module(x: Tensor) -> Any:
    """The kernel module for ``x``'s device."""
    if x.is_cuda:
        from . import cuda

        return cuda
    return native


def incidence(hinges: Tensor, vertex_count: int) -> tuple[Tensor, Tensor]:
    """Vertex incidence lists of ``hinges`` (:func:`torchbend.backends.native.incidence`), cached per
    hinges tensor (a module's buffer) and rebuilt if it changes."""
    key = (vertex_count, hinges._version)
    hit = getattr(hinges, "_torchbend_incidence", None)
    if hit is not None and hit[0] == key:
        return hit[1]
    inc = native.incidence(hinges, vertex_count)
    hinges._torchbend_incidence = (key, inc)  # pyright: ignore[reportAttributeAccessIssue]
    return inc

