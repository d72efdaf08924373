"""A clear error for a double backward through a ``torch.compile``'d energy.

PyTorch compiles the backward of a compiled region together with its forward (AOTAutograd) and cannot
differentiate that compiled backward: ``torch.autograd.grad(E, x, create_graph=True)`` of a compiled energy
returns a gradient whose graph does not lead back to ``x``, and the next ``torch.autograd.grad`` fails with
"The differentiated Tensor ... appears to not have been used in the graph" (or, with ``allow_unused=True``,
silently returns ``None``: a Hessian term lost).  The energies' backward therefore passes its cotangent
through :func:`compiled_backward_guard` while it is traced; at run time the guard raises
:class:`CompiledDoubleBackwardError`, which names the limitation and the eager alternatives, when that
backward runs with ``create_graph=True``.  A plain ``backward()`` pays one check of the autograd engine's
state (and a copy of the per-mesh cotangent).
"""
from __future__ import annotations

import sys

import torch
from torch import Tensor

from .._torch_compat import current_graph_task_id, graph_task_keeps_graph

__all__ = ["CompiledDoubleBackwardError", "compiled_backward_guard"]

MESSAGE = (
    "a torch.compile'd torchbend energy was differentiated with create_graph=True: PyTorch cannot differentiate "
    "the backward it compiled (AOTAutograd; the gradient would have no graph back to the positions, and the "
    "second derivative would fail or silently miss this energy). Take second derivatives eagerly: call the "
    "energy module without torch.compile (its double backward is the analytic Hessian-vector product, compiled "
    "C++ on the CPU and CUDA on the GPU), or use its hvp(x, v) / hessian(x) methods; torch.compile stays "
    "supported for the energy and its first derivatives (a forward with backward())."
)


class CompiledDoubleBackwardError(RuntimeError):
    """A double backward through a ``torch.compile``'d energy (see :mod:`torchbend.backends.compile_guard`)."""


def _inside_compiled_double_backward() -> bool:
    """Whether the compiled backward runs as the forward of AOTAutograd's ``CompiledFunctionBackward``: the
    Function it uses for ``create_graph=True`` (its own backward only raises) -- the one case of a create_graph
    backward in which grad mode reads off.  Only consulted when the engine keeps the graph."""
    frame = sys._getframe(2)
    for _ in range(32):
        if frame is None:
            return False
        if "CompiledFunctionBackward." in getattr(frame.f_code, "co_qualname", ""):
            return True
        frame = frame.f_back
    return False


@torch.library.custom_op("torchbend::compiled_backward_guard", mutates_args=())
def _guard(g: Tensor) -> Tensor:
    if current_graph_task_id() != -1 and graph_task_keeps_graph() and (
            torch.is_grad_enabled() or _inside_compiled_double_backward()):
        raise CompiledDoubleBackwardError(MESSAGE)
    return g.clone()


@_guard.register_fake
def _(g: Tensor) -> Tensor:
    return torch.empty_like(g)


def compiled_backward_guard(g: Tensor) -> Tensor:
    """``g`` itself, or, while ``torch.compile`` traces, ``g`` through the run-time guard (see the module)."""
    return _guard(g) if torch.compiler.is_compiling() else g
