"""The input checks of the compiled kernels as one status word, and the one place that turns it into the
``ValueError`` the eager path raises (the wording of :mod:`torchbend._checks` and
:func:`torchbend.ops.psi.check_fold`).

The CPU kernels return the word themselves (``csrc/cpu_tiles.h``: the scans run inside the kernels); the CUDA
driver's words come from :func:`input_status` (before the kernel) and :func:`fold_status` (after it)."""
from __future__ import annotations

import torch
from torch import Tensor

from .._checks import check_finite_tensor, check_positions
from ..ops.psi import _PI, BendingModel, check_fold

BAD_X, BAD_V, FOLDED = 1, 2, 4
"""The bits: ``x`` holds a non-finite value, the direction ``v`` does, a ``tan`` hinge has folded through
(``|theta| >= pi`` in theta's dtype)."""


def raise_for_status(status: int, model, x: Tensor, theta: Tensor | None, v: Tensor | None = None) -> None:
    """The ``ValueError`` of a non-zero ``status`` (the checks of :mod:`torchbend._checks` and
    :func:`torchbend.ops.psi.check_fold` name the offending vertices or hinges)."""
    if status & BAD_X:
        check_positions(x, x.shape[-2])
    if status & BAD_V and v is not None:
        check_finite_tensor(v, "v")
    if status & FOLDED and theta is not None:
        check_fold(BendingModel.parse(model), theta)
    raise ValueError(f"torchbend: the compiled kernel reported invalid input (status {status})")


def input_status(x: Tensor, v: Tensor | None = None) -> int:
    """``BAD_X`` / ``BAD_V`` where ``x`` / ``v`` hold non-finite values (one synchronisation)."""
    bad = ~torch.isfinite(x.detach()).all()
    if v is not None:
        bad = torch.stack((bad, ~torch.isfinite(v.detach()).all()))
        return int(bad[0]) * BAD_X | int(bad[1]) * BAD_V
    return BAD_X if bool(bad) else 0


def fold_status(model, theta: Tensor) -> int:
    """``FOLDED`` where a ``tan`` hinge of the angles ``theta`` has folded through."""
    if getattr(model, "value", model) != "tan" or theta.numel() == 0:
        return 0
    return FOLDED if bool((theta.detach().abs() >= torch.tensor(_PI, dtype=theta.dtype)).any()) else 0
