"""Where torchbend leans on PyTorch internals, gathered in one place (each with what it stands for).

``assume_constant_result``: :func:`torch.compiler.assume_constant_result` imports ``torch._dynamo`` (about 2 s)
when it decorates; torchbend decorates at import time, so it sets the marker that function sets
(``tests/test_import.py`` checks that both mark a function alike on the installed torch)."""
from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch
from torch.autograd import forward_ad as _forward_ad

_F = TypeVar("_F", bound=Callable)


def assume_constant_result(fn: _F) -> _F:
    """``fn`` marked as :func:`torch.compiler.assume_constant_result` marks it, without importing ``torch._dynamo``."""
    fn._dynamo_marked_constant = True  # pyright: ignore[reportFunctionMemberAccess]
    return fn


# The private entry points below have no public equivalent; each is read once here (an AttributeError at import
# names the one a new torch removed).  Checked on torch 2.13 (the tested version; pyproject's minimum).

is_functorch_wrapped = torch._C._functorch.is_functorch_wrapped_tensor  # pyright: ignore[reportAttributeAccessIssue]
"""Whether a tensor is wrapped by a ``torch.func`` transform (``vmap``, ``grad``, ``jacrev``...)."""
dispatch_stack_len = torch._C._len_torch_dispatch_stack  # pyright: ignore[reportAttributeAccessIssue]
"""The number of active ``TorchDispatchMode``\\ s (0: no mode would intercept an operator call)."""
torch_function_mode_enabled = torch._C._is_torch_function_mode_enabled  # pyright: ignore[reportAttributeAccessIssue]
"""Whether a ``TorchFunctionMode`` is active."""
parse_to = torch._C._nn._parse_to  # pyright: ignore[reportAttributeAccessIssue]
"""``Tensor.to``'s argument parser: ``(device, dtype, non_blocking, memory_format)``."""
current_graph_task_id = torch._C._current_graph_task_id  # pyright: ignore[reportAttributeAccessIssue]
"""The id of the running autograd backward (-1 outside a backward)."""
graph_task_keeps_graph = torch._C._autograd._get_current_graph_task_keep_graph  # pyright: ignore[reportAttributeAccessIssue]
"""Whether the running backward keeps its graph (``create_graph``/``retain_graph``)."""


def forward_ad_level() -> int:
    """The innermost active forward-mode AD level (-1: none)."""
    return _forward_ad._current_level
