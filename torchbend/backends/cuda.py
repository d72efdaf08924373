r"""The CUDA driver of the compiled bending operations: build, load and call.

``csrc/bending_cuda.cu`` (one thread per hinge over the per-hinge mathematics of ``hinge_math.h`` and
``hinge_ops.h``, the same functions the CPU driver runs) has a plain C interface (``bending_cuda.h``) and
no torch headers, so it is compiled by ``nvcc`` alone into an object file; ``csrc/cuda_binding.cpp`` binds
it to torch and is compiled by ``torch.utils.cpp_extension.load`` against the installed torch, CPU-only
builds included, and linked with the object and ``cudart``.  So the CUDA part builds, links and imports on
any machine with ``nvcc`` (CI checks exactly that), and runs where torch sees a GPU.

Build options (environment): ``TORCHBEND_CUDA_ARCH`` (e.g. ``"90"`` or ``"80;90"``; default: the
visible GPU's compute capability, else ``90``), ``TORCHBEND_NVCC`` (the compiler; default ``nvcc`` from
``CUDA_HOME`` or the ``PATH``).  Everything is cached under torch's extension directory, keyed by a hash
of the sources, the flags and the architectures.
"""
from __future__ import annotations

import functools
import hashlib
import os
import shutil
import subprocess
import warnings
from typing import Any

import torch
from torch import Tensor

from ..ops.psi import BendingModel, check_fold

__all__ = ["load", "build_error", "available", "kernels", "bending_energy", "bending_gradient", "bending_hvp",
           "bending_hessians"]

CSRC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "csrc")
CU_SOURCES = ("bending_cuda.cu",)
HEADERS = ("bending_cuda.h", "hinge_math.h", "hinge_ops.h")
BINDING = "cuda_binding.cpp"
NVCC_FLAGS = ("-O3", "-std=c++17", "-Xcompiler", "-fPIC")
MODEL_CODE = {"quadratic": 0, "tan": 1, "sin": 2}
KERNELS = ("energy", "gradient", "hvp", "hinge_hessians", "second_order")
"""The operations the CUDA driver implements, each for float32 and float64."""


def _nvcc() -> str | None:
    explicit = os.environ.get("TORCHBEND_NVCC")
    if explicit:
        return explicit
    from torch.utils.cpp_extension import CUDA_HOME

    if CUDA_HOME and os.path.exists(os.path.join(CUDA_HOME, "bin", "nvcc")):
        return os.path.join(CUDA_HOME, "bin", "nvcc")
    return shutil.which("nvcc")


def _archs() -> list[str]:
    env = os.environ.get("TORCHBEND_CUDA_ARCH")
    if env:
        return [a.strip().replace(".", "") for a in env.replace(",", ";").split(";") if a.strip()]
    if torch.cuda.is_available():
        major, minor = torch.cuda.get_device_capability()
        return [f"{major}{minor}"]
    return ["90"]


def _cudart_dir(nvcc: str) -> str:
    """The folder with ``libcudart.so``: next to nvcc's toolkit, ``CUDA_HOME``'s, or ``/usr/local/cuda``'s."""
    from torch.utils.cpp_extension import CUDA_HOME

    candidates = [os.path.dirname(os.path.dirname(os.path.realpath(nvcc))), CUDA_HOME, "/usr/local/cuda"]
    try:  # nvcc may be a wrapper script: ask it where it lives
        out = subprocess.run([nvcc, "--dryrun", "--version"], capture_output=True, text=True, timeout=60).stderr
        candidates += [line.split("=", 1)[1].strip() for line in out.splitlines() if "TOP=" in line]
    except Exception:  # pragma: no cover
        pass
    for home in candidates:
        for sub in ("lib64", "lib", os.path.join("targets", "x86_64-linux", "lib")):
            d = os.path.join(home, sub) if home else ""
            if d and os.path.exists(os.path.join(d, "libcudart.so")):
                return d
    raise RuntimeError(f"libcudart.so not found near {nvcc} (tried {candidates})")


def extension_name(archs: list[str]) -> str:
    digest = hashlib.sha256((" ".join(NVCC_FLAGS) + "|" + ";".join(archs)).encode())
    for f in sorted(CU_SOURCES + HEADERS + (BINDING,)):
        with open(os.path.join(CSRC, f), "rb") as fh:
            digest.update(b"\0" + f.encode() + b"\0" + fh.read())
    return f"torchbend_cuda_{digest.hexdigest()[:12]}"


@functools.lru_cache(maxsize=1)
def _build() -> tuple[Any, str | None]:
    """``(module, None)`` or ``(None, reason)``, once per process."""
    nvcc = _nvcc()
    if nvcc is None:
        return None, "nvcc not found (set TORCHBEND_NVCC or CUDA_HOME)"
    try:
        from torch.utils.cpp_extension import _get_build_directory, load

        archs = _archs()
        name = extension_name(archs)
        build_dir = _get_build_directory(name, verbose=False)
        obj = os.path.join(build_dir, "bending_cuda.o")
        if not os.path.exists(obj):
            gencode = [f"-gencode=arch=compute_{a},code=sm_{a}" for a in archs]
            cmd = [nvcc, "-c", *NVCC_FLAGS, *gencode, "-I", CSRC, os.path.join(CSRC, CU_SOURCES[0]), "-o", obj + ".tmp"]
            subprocess.run(cmd, check=True, capture_output=True, text=True)
            os.replace(obj + ".tmp", obj)
        lib = _cudart_dir(nvcc)
        module = load(name=name, sources=[os.path.join(CSRC, BINDING)], extra_include_paths=[CSRC],
                      extra_cflags=["-O2"], extra_ldflags=[obj, f"-L{lib}", f"-Wl,-rpath,{lib}", "-lcudart"],
                      build_directory=build_dir, verbose=False)
        return module, None
    except subprocess.CalledProcessError as e:
        return None, f"nvcc failed: {(e.stderr or '')[-800:]}"
    except Exception as e:  # no compiler, no cudart, ...
        return None, f"{type(e).__name__}: {str(e)[-800:]}"


def load() -> Any:
    """The compiled CUDA binding module, or ``None`` if it cannot be built here (see :func:`build_error`)."""
    return _build()[0]


def build_error() -> str | None:
    return _build()[1]


def available() -> bool:
    """Whether the CUDA kernels can run here: built, and torch sees a GPU."""
    return torch.cuda.is_available() and load() is not None


def kernels() -> list[str]:
    """The kernel names in the built CUDA driver (``[]`` if it is not built)."""
    module = load()
    return [] if module is None else list(module.kernels())


def _module() -> Any:
    module = load()
    if module is None:
        raise RuntimeError(f"torchbend: the CUDA kernels are not available ({build_error()})")
    return module


def _stream(x: Tensor) -> int:
    return int(torch.cuda.current_stream(x.device).cuda_stream)


def _code(model) -> int:
    return MODEL_CODE[getattr(model, "value", model)]


def _opt(t: Tensor | None) -> Tensor | None:
    return None if t is None else t.detach()


def _warn_once(msg: str) -> None:  # pragma: no cover - used by the dispatcher
    warnings.warn(msg, RuntimeWarning, stacklevel=3)


def bending_energy(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model) -> Tensor:
    """Per-hinge energies ``psi (..., H)`` (folded ``tan`` hinges: ``ValueError``)."""
    psi, theta = _module().bending_energy(x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                          _opt(prev), _code(model), _stream(x))
    check_fold(BendingModel.parse(model), theta)
    return psi


def bending_gradient(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, weight: Tensor, inc, params: bool):
    """``(w dE/dx (..., V, 3), w dpsi/d(k, rest, c, prev) (..., H, 4) or None)`` (``inc`` unused: atomic scatter)."""
    gx, gp, theta = _module().bending_gradient(x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                               _opt(prev), _code(model), weight.detach(), params, _stream(x))
    check_fold(BendingModel.parse(model), theta)
    return gx, (gp if params else None)


def bending_hvp(x: Tensor, v: Tensor, hinges: Tensor, a, k, rest, c, prev, model, weight: Tensor, inc=None) -> Tensor:
    """``w H v (..., V, 3)``."""
    hv, theta = _module().bending_hvp(x.detach(), v.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                      _opt(prev), _code(model), weight.detach(), _stream(x))
    check_fold(BendingModel.parse(model), theta)
    return hv


def bending_second_order(x: Tensor, v: Tensor | None, t: Tensor | None, hinges: Tensor, a, k, rest, c, prev, model,
                         weight: Tensor, inc=None) -> tuple[Tensor, Tensor, Tensor]:
    """``(dx (..., V, 3), dp (..., H, 4), dg (..., H))``: the general double backward, as
    :func:`torchbend.backends.native.bending_second_order` (``inc`` unused: atomic scatter)."""
    dx, dp, dg, theta = _module().bending_second_order(x.detach(), _opt(v), _opt(t), hinges, a.detach(), k.detach(),
                                                       rest.detach(), _opt(c), _opt(prev), _code(model),
                                                       weight.detach(), _stream(x))
    check_fold(BendingModel.parse(model), theta)
    return dx, dp, dg


def bending_hessians(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model) -> tuple[Tensor, Tensor, Tensor]:
    """``(Hb (..., H, 12, 12), g (..., H, 12), psi'' (..., H))`` as :func:`torchbend.backends.native.bending_hessians`."""
    Hb, g, d2, theta = _module().bending_hessians(x.detach(), hinges, a.detach(), k.detach(), rest.detach(), _opt(c),
                                                  _opt(prev), _code(model), _stream(x))
    check_fold(BendingModel.parse(model), theta)
    return Hb, g, d2


def hinge_angles(x: Tensor, hinges: Tensor) -> Tensor:
    """Bend angles ``(..., H)`` as the compiled energy computes them (the same instructions)."""
    zero = x.new_zeros(1)
    return _module().bending_energy(x.detach(), hinges, zero, zero, zero, None, None, 0, _stream(x))[1]
