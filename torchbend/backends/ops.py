r"""The compiled bending kernels as PyTorch operators: ``torch.ops.torchbend.*``.

The operators are registered in C++ by the CPU extension (``csrc/cpu_registration.cpp``: the schemas and the CPU
kernels, by ``register_operators``, which the loader calls once it has chosen the module) and the CUDA binding
(``csrc/cuda_binding.cpp``: ``TORCH_LIBRARY_IMPL(torchbend, CUDA)``, registered when the CUDA kernels are first
loaded); this module loads the CPU extension (at import) and registers what stays in Python: the fake
implementations (output shapes and dtypes from the input shapes alone), so that ``torch.compile`` (also
``fullgraph=True``) and ``torch.export`` trace through the operators without a graph break and
``torch.library.opcheck`` can check them, and the kernel of ``project_blocks`` (whose eager fallback, CUDA
tensors and other block sizes, is Python's).  A kernel's status word becomes the ValueError of the eager path in
one place, :func:`torchbend.backends._status.raise_for_status`, which the C++ kernels call back (the loader
registers it).  Where the extension cannot be built (no compiler), the same schemas
(:data:`torchbend.backends._table.SCHEMAS`) are defined here with the Python kernels below, which then say why
the compiled kernels are not available (the eager path runs instead: :func:`torchbend.backends.select_backend`).

In plain eager mode :func:`run` calls the Python kernel below directly instead of going through the dispatcher
(a few microseconds a call less, a tenth of the work on a thousand hinges): the same compiled operator behind
its pybind binding (:mod:`torchbend.backends.native`, or :mod:`torchbend.backends.cuda` by the device of ``x``)
and the same status helper, so both paths give the same results and errors.

The operators are not differentiable themselves: derivatives come from torchbend's autograd Functions
(:mod:`torchbend.energies._bending_fn`), which call ``bending_energy`` in the forward (``bending_energy_gradient``
when autograd records it: the gradient comes in the same pass and the backward scales it),
``bending_gradient`` in the backward otherwise, and ``bending_hvp``/``bending_second_order`` in the double
backward.  The checks stay on in
compiled code because they run inside the operators (on the CPU inside the C++ kernels, which return a status
word): a folded ``tan`` hinge is the ``ValueError`` of :func:`torchbend.ops.psi.check_fold`; with ``check=True``
non-finite positions (and directions ``v`` of ``bending_hvp``) are the ``ValueError`` of
:func:`torchbend._checks.check_positions` (``check_finite_tensor``).  The modules pass ``check=True`` (their
``check_finite``) instead of checking in Python before the call.

Arguments shared by all: ``x (..., V, 3)``; ``hinges (H, 4)`` int64; ``a (H,)``; ``k``, ``rest``, ``c``,
``prev`` one value or ``(H,)`` (``prev`` also ``(..., H)``, x's batch shape); ``c``/``prev`` both given
(viscous term) or both ``None``; ``model`` ``"quadratic" | "tan" | "sin"``; ``weight`` the per-hinge
cotangent of the energy (one value, ``(H,)`` or ``(..., H)``); ``ptr``, ``idx`` the vertex incidence lists
(:func:`torchbend.backends.native.incidence`).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .._torch_compat import dispatch_stack_len, is_functorch_wrapped, torch_function_mode_enabled
from . import kernels, native
from ._table import MODEL_CODE, OPERATORS, SCHEMAS

__all__ = ["bending_energy", "bending_gradient", "bending_energy_gradient", "bending_hvp", "bending_second_order",
           "hinge_hessians", "assemble", "project_blocks", "membrane_energy_gradient", "membrane_hvp", "sum_last", "OPS",
           "run"]

_PYTHON_KERNELS = frozenset({"project_blocks", "membrane_energy_gradient", "membrane_hvp", "sum_last"})
"""Operators whose kernel is registered from Python even where the C++ library defines them."""


def _define() -> tuple[torch.library.Library, bool]:
    """The library the registrations below go to, and whether the operators are defined here: loads the CPU
    extension, whose ``register_operators`` (the loader calls it) defines the schemas and registers the CPU
    kernels; where it cannot be built, the same schemas (:data:`torchbend.backends._table.SCHEMAS`) are defined
    here."""
    if native.load() is not None:
        return torch.library.Library("torchbend", "FRAGMENT"), False
    lib = torch.library.Library("torchbend", "DEF")
    for name, schema in SCHEMAS.items():
        lib.define(name + schema)
    return lib, True


_LIB, PYTHON_DEFINED = _define()
"""``PYTHON_DEFINED``: the operators are defined here with Python kernels (the CPU extension is not available)."""
_KERNELS: dict = {}
"""The Python kernel of every operator by name (what :func:`run` calls in eager mode; what the dispatcher calls
where the operators are defined here, and for ``project_blocks``)."""


_MODELS = tuple(MODEL_CODE)  # the model names the kernels take


def _model(op: str, model: str) -> str:
    """``model`` if it names a bending model, else the ``ValueError`` naming the operator and the choices (the
    other arguments are checked by the kernels, :file:`torchbend/csrc/checks.h`)."""
    if model not in _MODELS:
        raise ValueError(f"torchbend.{op}: model must be one of {', '.join(map(repr, _MODELS))}, got {model!r}")
    return model


def _batch(x: Tensor) -> tuple[int, ...]:
    return tuple(x.shape[:-2])


def _operator(fake):
    """Register ``fake`` for tracing ``torch.ops.torchbend.<fn.__name__>`` (and ``fn`` as its kernel for CPU and
    CUDA tensors where the operator is defined here, or its kernel stays Python) and return the operator; ``fn``'s
    annotations are the operator's schema (:data:`torchbend.backends._table.SCHEMAS`, checked by the tests)."""

    def register(fn):
        name = fn.__name__

        def checked_fake(*args, **kwargs):
            # the dispatcher sends a call whose tensors mix devices to the highest-priority one's kernel (a meta
            # tensor among CPU ones: this fake), so the fake checks what the kernels check: one device
            tensors = [t for t in (*args, *kwargs.values()) if isinstance(t, Tensor)]
            for t in tensors[1:]:
                if t.device != tensors[0].device:
                    raise ValueError(f"torchbend.{name}: every tensor argument must be on the first one's device "
                                     f"({tensors[0].device}), got one on {t.device}")
            return fake(*args, **kwargs)

        if PYTHON_DEFINED or name in _PYTHON_KERNELS:
            _LIB.impl(name, fn, "CPU")
            _LIB.impl(name, fn, "CUDA")
        torch.library.register_fake(f"torchbend::{name}", checked_fake, lib=_LIB)
        _KERNELS[name] = fn
        return getattr(torch.ops.torchbend, name)

    return register


_wrapped = is_functorch_wrapped


def run(name: str, x: Tensor, *args):
    """``torch.ops.torchbend.<name>(x, *args)``.  In plain eager mode (not compiling or exporting, ``x`` a plain
    tensor, no torch function or dispatch mode active, no ``torch.func`` transform) the operator's kernel is
    called directly: the dispatcher round trip into a Python kernel costs a few microseconds a call, a tenth
    of the work on a thousand hinges.  Everything that traces (``torch.compile``, ``torch.export``, ``make_fx``,
    fake tensors) sees the operator."""
    if (not torch.compiler.is_compiling() and type(x) is Tensor and dispatch_stack_len() == 0
            and not torch_function_mode_enabled() and not _wrapped(x)):
        return _KERNELS[name](x, *args)
    return getattr(torch.ops.torchbend, name)(x, *args)


def _energy_fake(x, hinges, a, k, rest, c, prev, model, check):
    return x.new_empty(_batch(x) + (hinges.shape[0],))


@_operator(_energy_fake)
def bending_energy(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                   prev: Optional[Tensor], model: str, check: bool) -> Tensor:
    """Per-hinge energies ``psi (..., H)``."""
    _model("bending_energy", model)
    return kernels.module(x).bending_energy(x, hinges, a, k, rest, c, prev, model, check)


def _gradient_fake(x, hinges, a, k, rest, c, prev, model, weight, ptr, idx, params, check):
    gp = x.new_empty(_batch(x) + (hinges.shape[0], 4)) if params else x.new_empty(0)
    return torch.empty_like(x, memory_format=torch.contiguous_format), gp


@_operator(_gradient_fake)
def bending_gradient(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                     prev: Optional[Tensor], model: str, weight: Tensor, ptr: Tensor, idx: Tensor, params: bool,
                     check: bool) -> tuple[Tensor, Tensor]:
    """``(w dE/dx (..., V, 3), w dpsi/d(k, rest, c, prev) (..., H, 4))``; the second is empty (``(0,)``)
    without ``params``."""
    _model("bending_gradient", model)
    gx, gp = kernels.module(x).bending_gradient(x, hinges, a, k, rest, c, prev, model, weight, (ptr, idx), params,
                                                check)
    return gx, (gp if gp is not None else x.new_empty(0))


def _energy_gradient_fake(x, hinges, a, k, rest, c, prev, model, ptr, idx, params, check):
    return (x.new_empty(_batch(x) + (hinges.shape[0],)),) + _gradient_fake(x, hinges, a, k, rest, c, prev, model, None,
                                                                            ptr, idx, params, check)


@_operator(_energy_gradient_fake)
def bending_energy_gradient(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                            prev: Optional[Tensor], model: str, ptr: Tensor, idx: Tensor, params: bool,
                            check: bool) -> tuple[Tensor, Tensor, Tensor]:
    """``(psi (..., H), dE/dx (..., V, 3), dpsi/d(k, rest, c, prev) (..., H, 4))`` in one pass (the forward of a
    recorded energy, which keeps the gradient for its backward); the third is empty (``(0,)``) without
    ``params``."""
    _model("bending_energy_gradient", model)
    psi, gx, gp = kernels.module(x).bending_energy_gradient(x, hinges, a, k, rest, c, prev, model, (ptr, idx), params,
                                                            check)
    return psi, gx, (gp if gp is not None else x.new_empty(0))


def _hvp_fake(x, v, hinges, a, k, rest, c, prev, model, weight, ptr, idx, check=False):
    return torch.empty_like(x, memory_format=torch.contiguous_format)


@_operator(_hvp_fake)
def bending_hvp(x: Tensor, v: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                prev: Optional[Tensor], model: str, weight: Tensor, ptr: Tensor, idx: Tensor,
                check: bool = False) -> Tensor:
    """``w H v (..., V, 3)``: the Hessian of the energy in the positions applied to ``v`` (x's shape); with
    ``check`` non-finite ``x`` or ``v`` are a ``ValueError``."""
    _model("bending_hvp", model)
    return kernels.module(x).bending_hvp(x, v, hinges, a, k, rest, c, prev, model, weight, (ptr, idx), check)


def _second_order_fake(x, v, t, hinges, a, k, rest, c, prev, model, weight, ptr, idx):
    H = hinges.shape[0]
    return (torch.empty_like(x, memory_format=torch.contiguous_format), x.new_empty(_batch(x) + (H, 4)),
            x.new_empty(_batch(x) + (H,)))


@_operator(_second_order_fake)
def bending_second_order(x: Tensor, v: Optional[Tensor], t: Optional[Tensor], hinges: Tensor, a: Tensor, k: Tensor,
                         rest: Tensor, c: Optional[Tensor], prev: Optional[Tensor], model: str, weight: Tensor,
                         ptr: Tensor, idx: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The general double backward: ``(dx (..., V, 3), dp (..., H, 4), dg (..., H))`` for directions ``v`` in the
    positions and ``t (..., H, 4)`` in the per-hinge ``(k, rest, c, prev)`` (either may be ``None``); see
    :func:`torchbend.backends.native.bending_second_order`."""
    _model("bending_second_order", model)
    return tuple(kernels.module(x).bending_second_order(x, v, t, hinges, a, k, rest, c, prev, model, weight,
                                                        (ptr, idx)))  # type: ignore[return-value]


def _hessians_fake(x, hinges, a, k, rest, c, prev, model, check=False):
    H = hinges.shape[0]
    return x.new_empty(_batch(x) + (H, 12, 12)), x.new_empty(_batch(x) + (H, 12)), x.new_empty(_batch(x) + (H,))


@_operator(_hessians_fake)
def hinge_hessians(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
                   prev: Optional[Tensor], model: str, check: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """``(blocks (..., H, 12, 12), angle gradients g (..., H, 12), psi'' (..., H))`` (unprojected); with ``check``
    non-finite positions are a ``ValueError``."""
    _model("hinge_hessians", model)
    blocks = kernels.module(x).bending_hessians
    out = blocks(x, hinges, a, k, rest, c, prev, model, check=True) if check else blocks(x, hinges, a, k, rest, c,
                                                                                        prev, model)
    return tuple(out[:3])  # type: ignore[return-value]


def _assemble_fake(x, hinges, a, k, rest, c, prev, model, hinge_blocks, faces, face_edge_hinges, face_edge_signs,
                   face_blocks, row_len, nnz, per_triangle):
    return x.new_empty(nnz)


@_operator(_assemble_fake)
def assemble(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Optional[Tensor],
             prev: Optional[Tensor], model: str, hinge_blocks: Tensor, faces: Tensor, face_edge_hinges: Tensor,
             face_edge_signs: Tensor, face_blocks: Tensor, row_len: Tensor, nnz: int, per_triangle: bool) -> Tensor:
    """CSR values ``(nnz,)`` of the unprojected Hessian of one mesh ``x (V, 3)`` (the pattern's block bases
    from :class:`torchbend.energies.sparse.HessianPattern` and the topology)."""
    _model("assemble", model)
    return native.assemble_arrays(x, hinges, a, k, rest, c, prev, model, hinge_blocks, faces, face_edge_hinges,
                                  face_edge_signs, face_blocks, row_len, nnz, per_triangle)


def _project_fake(M, mode, hinge=False):
    return torch.empty_like(M, memory_format=torch.contiguous_format)


@_operator(_project_fake)
def project_blocks(M: Tensor, mode: str, hinge: bool = False) -> Tensor:
    """PSD projection (``mode`` ``"clamp"``, ``"abs"`` or, for hinge blocks, ``"reduced"``) of symmetric blocks
    ``M (..., n, n)``: compiled (cyclic Jacobi; ``hinge``: translation-invariant 12x12 hinge blocks, projected in
    the translations' complement) for CPU float32/float64 blocks of 9x9 or 12x12,
    :func:`torchbend.ops.projection.project_blocks` otherwise (CUDA, other sizes)."""
    from ..ops.projection import project_blocks as eager_project
    from ..options import Projection

    if mode not in ("clamp", "abs", "reduced") or (mode == "reduced" and not (hinge and M.shape[-1] == 12)):
        raise ValueError(f"torchbend.project_blocks: mode must be 'clamp', 'abs' or, for 12x12 hinge blocks, 'reduced'; "
                         f"got {mode!r}")
    if M.dim() < 2 or M.shape[-1] != M.shape[-2] or not M.is_floating_point():
        raise ValueError(f"torchbend.project_blocks: M must be a floating-point (..., n, n) tensor, got "
                         f"{tuple(M.shape)} {M.dtype}")
    if M.is_cuda or M.shape[-1] not in (9, 12) or M.dtype not in (torch.float32, torch.float64):
        if not bool(torch.isfinite(M).all()):
            raise ValueError("torchbend.project_blocks: M holds non-finite values")
        return eager_project(M, Projection(mode)).contiguous()
    return native.project_blocks(M, mode, hinge)


def _membrane_energy_gradient_fake(x, faces, D, coef, mu, lam, weight, gradient, model):
    return x.new_empty(_batch(x)), (x.new_empty(x.shape) if gradient else x.new_empty(0))


@_operator(_membrane_energy_gradient_fake)
def membrane_energy_gradient(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor, weight: Tensor,
                             gradient: bool, model: str) -> tuple[Tensor, Tensor]:
    """``(E (...,), weight dE/dx (..., V, 3) or empty)``: the membrane energy of ``model`` per sample and, with
    ``gradient``, its gradient times ``weight`` (x's batch shape); the compiled kernel on the CPU, the eager formulas
    elsewhere and for the ValueError that names the faces of a collapsed or overflowing triangle
    (:func:`torchbend.energies._membrane_fn.kernel_energy_gradient`)."""
    from ..energies import _membrane_fn

    return _membrane_fn.kernel_energy_gradient(x, faces, D, coef, mu, lam, weight, gradient, model)


def _membrane_hvp_fake(x, v, faces, D, coef, mu, lam, weight, model, projection):
    return x.new_empty(x.shape), x.new_empty(_batch(x))


@_operator(_membrane_hvp_fake)
def membrane_hvp(x: Tensor, v: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor, weight: Tensor,
                 model: str, projection: str) -> tuple[Tensor, Tensor]:
    """``(weight H v (..., V, 3), dE/dx . v (...,))``: the (``projection``) Hessian-vector product of the membrane
    energy of ``model`` (:func:`torchbend.energies._membrane_fn.kernel_hvp`; as :func:`membrane_energy_gradient`)."""
    from ..energies import _membrane_fn

    return _membrane_fn.kernel_hvp(x, v, faces, D, coef, mu, lam, weight, model, projection)


def _sum_last_fake(values):
    return values.new_empty(values.shape[:-1])


@_operator(_sum_last_fake)
def sum_last(values: Tensor) -> Tensor:
    """``values.sum(-1)`` as an operator: the per-hinge energies' sum that compiled code leaves to ATen, so that a
    compiled energy sums in eager's order (bit for bit; the compiled graph's own reduction differs by ~10 ulp on
    1e5 hinges)."""
    return values.sum(-1)


assert set(_KERNELS) == set(OPERATORS) == set(SCHEMAS), "torchbend.backends._table.OPERATORS lists every operator"
OPS = {name: getattr(torch.ops.torchbend, name) for name in OPERATORS}
"""Every registered operator by name (``torch.ops.torchbend.<name>``, :data:`torchbend.backends._table.OPERATORS`)."""
