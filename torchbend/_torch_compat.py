"""Where torchbend leans on PyTorch internals, gathered in one place (each with the public API it stands for).

``assume_constant_result``: :func:`torch.compiler.assume_constant_result` imports ``torch._dynamo`` (about 2 s)
when it decorates; torchbend decorates at import time, so it sets the marker that function sets
(``tests/test_import.py`` checks that both mark a function alike on the installed torch)."""
from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

_F = TypeVar("_F", bound=Callable)


def assume_constant_result(fn: _F) -> _F:
    """``fn`` marked as :func:`torch.compiler.assume_constant_result` marks it, without importing ``torch._dynamo``."""
    fn._dynamo_marked_constant = True  # pyright: ignore[reportFunctionMemberAccess]
    return fn
