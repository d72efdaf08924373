r"""The CUDA driver of the compiled bending operations: build, load and call.

``csrc/bending_cuda.cu`` (one thread per hinge over the per-hinge mathematics of ``hinge_math.h`` and
``hinge_ops.h``, the same functions the CPU driver runs) has a plain C interface (``bending_cuda.h``) and
no torch headers, so it is compiled by ``nvcc`` alone into an object file; ``csrc/cuda_binding.cpp`` binds
it to torch and is compiled by ``torch.utils.cpp_extension.load`` against the installed torch, CPU-only
builds included, and linked with the object and ``cudart``.  So the CUDA part builds, links and imports on
any machine with ``nvcc`` (CI checks exactly that), and runs where torch sees a GPU.

``pip install --no-build-isolation .`` (or ``-e .``) builds it as ``torchbend._cuda`` where ``nvcc`` is
found (``setup.py``: SASS for sm_80 and sm_90 and PTX of sm_90 unless ``TORCHBEND_CUDA_ARCH`` says
otherwise; ``TORCHBEND_BUILD_CUDA=0`` skips it, ``=1`` makes a failure fail the install).  :func:`load` uses
that module if it was built from the sources installed next to it and, where a GPU is visible, for an
architecture that runs on it; otherwise it builds on first use, as follows.

Build options of the JIT build (environment): ``TORCHBEND_CUDA_ARCH`` (e.g. ``"90"`` or ``"80;90"``; default: the
visible GPU's compute capability, else ``90``), ``TORCHBEND_NVCC`` (the compiler; default ``nvcc`` from
``CUDA_HOME`` or the ``PATH``).  Everything is cached under torch's extension directory, keyed by a hash
of the sources, the flags and the architectures.  ``TORCHBEND_PREBUILT=0`` ignores the installed module.
"""
from __future__ import annotations

import hashlib
import os
import subprocess
from typing import Any

import torch
from torch import Tensor

from . import _build_config as cfg
from ._loader import Extension
from ._status import fold_status, input_status, raise_for_status
from ._table import CUDA_KERNELS, MEMBRANE_MODEL_CODE, MEMBRANE_PROJECTION_CODE, model_code

__all__ = ["load", "build_error", "build_info", "available", "kernels", "bending_energy", "bending_gradient",
           "bending_energy_gradient", "bending_hvp", "bending_hessians", "membrane_energy_gradient", "membrane_hvp",
           "membrane_blocks", "contact_barrier"]

KERNELS = CUDA_KERNELS
"""The operations the CUDA driver implements, each for float32 and float64 (:data:`torchbend.backends._table.OPERATORS`
and the membrane's, :data:`torchbend.backends._table.MEMBRANE_CUDA_KERNELS`)."""
PREBUILT = "torchbend._cuda"
"""The module ``setup.py`` builds at install time."""


def _archs() -> list[str]:
    if not os.environ.get("TORCHBEND_CUDA_ARCH") and torch.cuda.is_available():
        major, minor = torch.cuda.get_device_capability()
        return [f"{major}{minor}"]
    return cfg.cuda_archs(default=("90",))


def extension_name(archs: list[str]) -> str:
    """``torchbend_cuda_<hash>`` of the sources, headers, flags and ``archs`` (the JIT build's name)."""
    digest = hashlib.sha256((cfg.cuda_source_hash() + "|" + ";".join(archs)).encode())
    return f"torchbend_cuda_{digest.hexdigest()[:12]}"


def _compatible(info: dict) -> str:
    """``""`` if the installed module runs on the visible GPU (or no GPU is visible), else why not."""
    if not torch.cuda.is_available():
        return ""
    cap = torch.cuda.get_device_capability()
    if cfg.arch_compatible(list(info.get("archs", [])), bool(info.get("ptx")), cap):
        return ""
    return f"built for sm_{info.get('archs')} (ptx: {info.get('ptx')}), the GPU is sm_{cap[0]}{cap[1]}"


def _jit_build() -> tuple[Any, dict[str, Any]]:
    """nvcc compiles the driver into object files, ``torch.utils.cpp_extension.load`` the binding, linked with
    them and cudart."""
    nvcc = cfg.find_nvcc()
    if nvcc is None:
        raise FileNotFoundError("nvcc not found (set TORCHBEND_NVCC or CUDA_HOME)")
    from torch.utils.cpp_extension import CUDA_HOME, _get_build_directory, load

    archs = _archs()
    name = extension_name(archs)
    build_dir = _get_build_directory(name, verbose=False)
    objs = []
    for src in cfg.CUDA_SOURCES:
        obj = os.path.join(build_dir, os.path.splitext(src)[0] + ".o")
        if not os.path.exists(obj):
            cmd = [nvcc, "-c", *cfg.NVCC_FLAGS, *cfg.gencode_flags(archs, ptx=False), "-I", cfg.CSRC,
                   os.path.join(cfg.CSRC, src), "-o", obj + ".tmp"]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                raise RuntimeError(f"nvcc failed: {(done.stderr or done.stdout or '')[-800:]}")
            os.replace(obj + ".tmp", obj)
        objs.append(obj)
    lib = cfg.cudart_dir(nvcc, (CUDA_HOME,))
    module = load(name=name, sources=[os.path.join(cfg.CSRC, cfg.CUDA_BINDING)], extra_include_paths=[cfg.CSRC],
                  extra_cflags=["-O2"], extra_ldflags=[*objs, f"-L{lib}", f"-Wl,-rpath,{lib}", "-lcudart"],
                  build_directory=build_dir, verbose=False)
    return module, {}


def _on_load(module) -> None:
    """The CUDA kernels of the operators (``torch.ops.torchbend.*``, registered by the module) raise the ValueError of
    a status word through :func:`torchbend.backends._status.raise_for_status`."""
    module.set_status_handler(raise_for_status)


_EXT = Extension("CUDA kernels", PREBUILT, lambda: cfg.cuda_source_hash(), _jit_build, compatible=_compatible,
                 on_load=_on_load)


_load_prebuilt = _EXT.load_prebuilt  # (torchbend._cuda, "", found) if installed, current and runnable here
load = _EXT.load  # the compiled CUDA binding module, or None if it cannot be built here (see build_error)
build_error = _EXT.build_error
build_info = _EXT.build_info  # as torchbend.backends.native.build_info (build: also the installed module's archs)
_module = _EXT.module


def available() -> bool:
    """Whether the CUDA kernels can run here: built, and torch sees a GPU."""
    return torch.cuda.is_available() and load() is not None


def kernels() -> list[str]:
    """The kernel names in the built CUDA driver (``[]`` if it is not built)."""
    module = load()
    return [] if module is None else list(module.kernels())


def _stream(x: Tensor) -> int:
    return int(torch.cuda.current_stream(x.device).cuda_stream)


def _opt(t: Tensor | None) -> Tensor | None:
    return None if t is None else t.detach()


def _check(check: bool, x: Tensor, v: Tensor | None = None) -> None:
    """With ``check``: the ``ValueError`` of non-finite positions (and directions ``v``), before any work."""
    if check:
        status = input_status(x, v)
        if status:
            raise_for_status(status, None, x, None, v)


def _folded(model, x: Tensor, theta: Tensor) -> None:
    """The ``ValueError`` of a folded ``tan`` hinge (after the kernel, from its angles)."""
    status = fold_status(model, theta)
    if status:
        raise_for_status(status, model, x, theta)


def bending_energy(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, check: bool = False) -> Tensor:
    """Per-hinge energies ``psi (..., H)`` (folded ``tan`` hinges: ``ValueError``; with ``check`` also non-finite
    positions)."""
    _check(check, x)
    psi, theta = _module().bending_energy(x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                          _opt(prev), model_code(model), _stream(x))
    _folded(model, x, theta)
    return psi


def bending_gradient(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, weight: Tensor, inc, params: bool,
                     check: bool = False):
    """``(w dE/dx (..., V, 3), w dpsi/d(k, rest, c, prev) (..., H, 4) or None)`` (``inc`` unused: atomic scatter)."""
    _check(check, x)
    gx, gp, _, theta = _module().bending_gradient(x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                                  _opt(prev), model_code(model), weight.detach(), params, False, _stream(x))
    _folded(model, x, theta)
    return gx, (gp if params else None)


def bending_energy_gradient(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, inc, params: bool,
                            check: bool = False):
    """``(psi (..., H), dE/dx (..., V, 3), dpsi/d(k, rest, c, prev) (..., H, 4) or None)`` from one kernel (the
    gradient kernel also storing the energies it computes)."""
    _check(check, x)
    gx, gp, psi, theta = _module().bending_gradient(x.detach(), hinges, a.detach(), k.detach(), rest.detach(),
                                                    _opt(c), _opt(prev), model_code(model), x.new_ones(1), params, True,
                                                    _stream(x))
    _folded(model, x, theta)
    return psi, gx, (gp if params else None)


def bending_hvp(x: Tensor, v: Tensor, hinges: Tensor, a, k, rest, c, prev, model, weight: Tensor, inc=None,
                check: bool = False) -> Tensor:
    """``w H v (..., V, 3)`` (with ``check``: non-finite ``x`` or ``v`` are a ``ValueError``)."""
    _check(check, x, v)
    hv, theta = _module().bending_hvp(x.detach(), v.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                      _opt(prev), model_code(model), weight.detach(), _stream(x))
    _folded(model, x, theta)
    return hv


def bending_second_order(x: Tensor, v: Tensor | None, t: Tensor | None, hinges: Tensor, a, k, rest, c, prev, model,
                         weight: Tensor, inc=None) -> tuple[Tensor, Tensor, Tensor]:
    """``(dx (..., V, 3), dp (..., H, 4), dg (..., H))``: the general double backward, as
    :func:`torchbend.backends.native.bending_second_order` (``inc`` unused: atomic scatter)."""
    dx, dp, dg, theta = _module().bending_second_order(x.detach(), _opt(v), _opt(t), hinges, a.detach(), k.detach(),
                                                       rest.detach(), _opt(c), _opt(prev), model_code(model),
                                                       weight.detach(), _stream(x))
    _folded(model, x, theta)
    return dx, dp, dg


def bending_hessians(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, check: bool = False
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """``(Hb (..., H, 12, 12), g (..., H, 12), psi'' (..., H))`` as :func:`torchbend.backends.native.bending_hessians`."""
    _check(check, x)
    Hb, g, d2, theta = _module().bending_hessians(x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                                  _opt(prev), model_code(model), _stream(x))
    _folded(model, x, theta)
    return Hb, g, d2


def hinge_angles(x: Tensor, hinges: Tensor) -> Tensor:
    """Bend angles ``(..., H)`` as the compiled energy computes them (the same instructions)."""
    zero = x.new_zeros(1)
    return _module().bending_energy(x.detach(), hinges, zero, zero, zero, None, None, 0, _stream(x))[1]


def membrane_energy_gradient(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor,
                             weight: Tensor | None, model: str = "stvk") -> tuple[Tensor, Tensor | None]:
    """As :func:`torchbend.backends.native.membrane_energy_gradient`, on CUDA tensors: ``(E (...,), weight dE/dx or
    None)``; one thread per (sample, triangle), the energies summed by torch, the gradient scattered atomically."""
    w = x.new_zeros(0) if weight is None else weight.detach()
    psi, g = _module().membrane_energy_gradient(x.detach(), faces, D, coef, float(mu), float(lam), w, weight is not None,
                                                MEMBRANE_MODEL_CODE[model], _stream(x))
    return psi.sum(-1), (None if weight is None else g)


def membrane_hvp(x: Tensor, v: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor,
                 weight: Tensor, model: str = "stvk", projection: str = "none") -> tuple[Tensor, Tensor]:
    """As :func:`torchbend.backends.native.membrane_hvp`, on CUDA tensors."""
    hv, dots = _module().membrane_hvp(x.detach(), v.detach(), faces, D, coef, float(mu), float(lam), weight.detach(),
                                      MEMBRANE_MODEL_CODE[model], MEMBRANE_PROJECTION_CODE[projection], _stream(x))
    return hv, dots.sum(-1)


def contact_barrier(x: Tensor, stencils: Tensor, types: Tensor, eps: Tensor | None, dhat_sq: float, kappa: float,
                    want: int = 2) -> tuple[Tensor, Tensor, Tensor]:
    """As :func:`torchbend.backends.native.contact_barrier` without projection, on CUDA tensors (one thread per
    stencil over ``contact_math.h``): ``(E (N,), g (N, 12), H (N, 12, 12))``; project with
    :func:`torchbend.ops.projection.project_blocks` (``eigh``)."""
    e = torch.zeros(0, dtype=x.dtype, device=x.device) if eps is None else eps
    return _module().contact_barrier(x.detach(), stencils, types, e, float(dhat_sq), float(kappa), int(want),
                                     _stream(x))


def membrane_blocks(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor, model: str,
                    projection: str = "none") -> tuple[Tensor, bool]:
    """As :func:`torchbend.backends.native.membrane_blocks`, on CUDA tensors: ``(H (..., T, 9, 9), finite)``."""
    H = _module().membrane_blocks(x.detach(), faces, D, coef, float(mu), float(lam), MEMBRANE_MODEL_CODE[model],
                                  MEMBRANE_PROJECTION_CODE[projection], _stream(x))
    return H, bool(torch.isfinite(H.sum()))
