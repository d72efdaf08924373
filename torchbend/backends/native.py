r"""Compiled CPU kernels for the per-hinge 12x12 bending Hessians and their sparse assembly.

The eager-PyTorch path (:func:`torchbend.geometry.hinge_energy_hessian_soa`) is a chain of some
hundred elementwise passes over per-hinge arrays; it is memory bound.  This module compiles the whole
computation into one pass over hinges: gather the stencil from the positions, the bend angle (the
SPEC's ``atan2`` formula), ``psi'`` and ``psi''`` of the three models with the optional viscous term
(:func:`torchbend.models.psi_theta_derivatives`), and the closed-form block (the half-hinge factors of
the tech report, sec. 6, and ``H = Y + Y^T`` with the B terms, see :mod:`torchbend.geometry`).
Hinges are processed in tiles of 8 with every quantity stored per lane, so the compiler vectorizes
the formulas across hinges; tiles run in parallel (``at::parallel_for``), blocks are written with
streaming stores.

The C++ sources are ``torchbend/csrc/*.cpp``; they are compiled on first use with
``torch.utils.cpp_extension.load`` (about half a minute, then cached in ``TORCH_EXTENSIONS_DIR``).
Without a working compiler a warning says why, once, and the eager path runs.  Which code runs is
decided by :func:`torchbend.backends.select_backend`, never here; the functions below assume it
said ``native``.
"""
from __future__ import annotations

import functools
import os
import warnings

from torch import Tensor

__all__ = ["load", "build_error", "bending_hessians", "assemble", "MODEL_CODE"]

CSRC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "csrc")
SOURCES = ("bending_cpu.cpp",)
MODEL_CODE = {"quadratic": 0, "tan": 1, "sin": 2}


@functools.lru_cache(maxsize=1)
def _build():
    """``(module, None)`` or ``(None, reason)``; built once per process (cached on disk by torch)."""
    try:
        from torch.utils.cpp_extension import load as load_extension

        module = load_extension(
            name="torchbend_native_v10", sources=[os.path.join(CSRC, f) for f in SOURCES],
            extra_cflags=["-O3", "-march=native", "-fopenmp"], extra_ldflags=["-fopenmp"], verbose=False)
        return module, None
    except Exception as e:  # no compiler, no ninja, ...
        reason = f"{type(e).__name__}: {e}"
        warnings.warn(f"torchbend: could not build the C++ kernels ({reason[:300]}); using the eager path",
                      RuntimeWarning, stacklevel=4)
        return None, reason


def load():
    """The compiled extension module, or ``None`` if it cannot be built here."""
    return _build()[0]


def build_error() -> str | None:
    """Why the extension could not be built (``None`` if it was)."""
    return _build()[1]


def _model_code(model) -> int:
    return MODEL_CODE[getattr(model, "value", model)]


def _opt(t: Tensor | None) -> Tensor | None:
    return None if t is None else t.detach()


def bending_hessians(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c, prev, model):
    """Fused gather + angle + ``psi'``/``psi''`` + blocks for positions ``x: (..., V, 3)``:
    ``(Hb (..., H, 12, 12), g (..., H, 12), psi'' (..., H), x_is_finite)``.  Parameters: scalars or
    ``(H,)`` (``prev`` also ``(..., H)`` with x's batch shape); ``c``, ``prev`` ``None`` without damping."""
    return load().bending_hessians(x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c), _opt(prev),
                                   _model_code(model))


def assemble(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, pattern, topo, per_triangle: bool) -> Tensor:
    """CSR values ``(nnz,)`` of the (unprojected) Hessian of one mesh ``x: (V, 3)``, assembled per
    hinge or per triangle in C++ (serial: the scatter targets overlap)."""
    return load().assemble(
        x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c), _opt(prev), _model_code(model),
        pattern.hinge_pos, topo.faces, topo.face_edge_hinges, topo.face_edge_signs, pattern.face_pos, pattern.nnz,
        per_triangle)
