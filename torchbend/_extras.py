"""Optional dependencies: the library core needs torch, numpy and scipy only; the rest comes with an extra
(``pyproject.toml``), and a missing one is a one-line ``ImportError`` naming the extra that installs it."""
from __future__ import annotations

import importlib
from types import ModuleType

EXTRAS = {
    "pydantic": "scenes",  # the typed config schema (scenes, training scripts)
    "yaml": "scenes",
    "tqdm": "scenes",
    "matplotlib": "scenes",
    "meshio": "io",
    "pytorch_kinematics": "robot",
    "tensorboard": "train",
}
"""Importable module -> the extra of ``pip install 'torchbend[EXTRA]'`` that provides it."""


def missing_extra(err: ModuleNotFoundError, what: str) -> ImportError | ModuleNotFoundError:
    """The error for a failed import of an optional package: a one-line ``ImportError`` naming the package and
    its extra (``what`` needs it), or ``err`` itself where the missing module is not an optional package."""
    top = (err.name or "").partition(".")[0]
    if top not in EXTRAS:
        return err
    return ImportError(f"{what} needs the '{top}' package: pip install 'torchbend[{EXTRAS[top]}]'")


def require(module: str, what: str) -> ModuleType:
    """``import module``, or the one-line ``ImportError`` of :func:`missing_extra` (``what`` needs it)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        raise missing_extra(err, what) from None
