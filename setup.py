r"""Builds torchbend's compiled kernels at install time (the metadata is in ``pyproject.toml``).

    pip install torch==2.13.0 && pip install --no-build-isolation -e .        # or without -e

``--no-build-isolation``: the extensions are compiled against the torch already installed (torch is not a
build requirement: pip's isolated build environment would download a multi-GB CUDA build of it).

- ``torchbend._native``: the CPU kernels (``csrc/bending_cpu.cpp`` and the ``csrc/cpu_*.cpp`` it binds, the list
  ``NATIVE_SOURCES`` of ``torchbend/backends/_build_config.py``; OpenMP, ``-O3 -fno-math-errno``).
  ``-march=native`` by default: the documented install builds from source on the machine that runs it.
  For a wheel that other machines run, set ``TORCHBEND_CPU_ARCH=portable`` (no ``-march``) or e.g.
  ``=x86-64-v3``.
- ``torchbend._cuda``: ``csrc/bending_cuda.cu`` compiled by ``nvcc`` (SASS for sm_80 and sm_90 and PTX of
  sm_90, or ``TORCHBEND_CUDA_ARCH="80;90"``), linked with the torch binding ``csrc/cuda_binding.cpp`` and
  cudart.  Built by default where the installed torch is a CUDA build and nvcc is found (``TORCHBEND_NVCC``,
  ``CUDA_HOME``, the ``PATH``); ``TORCHBEND_BUILD_CUDA=1`` builds it with any torch (it needs no GPU and no CUDA
  build of torch: CI compiles and links it that way), so a CPU-only install does not pay its compile.

``TORCHBEND_BUILD_NATIVE`` / ``TORCHBEND_BUILD_CUDA``: ``0`` skips the extension, ``1`` makes its failure
fail the install (CI); unset, a failure prints a warning and the install goes on without it: the package
then compiles the kernels on first use (JIT, cached) or, without a compiler, runs its eager PyTorch path.
Each module carries a hash of the sources it was built from; the loaders ignore a module whose hash no
longer matches the installed sources (see ``torchbend/backends/_build_config.py``).
"""
from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import threading
import time
import warnings
from typing import Any

from setuptools import setup

# pyproject's `license = { text = ... }` keeps setuptools 64-76 working (the SPDX string form needs >= 77)
warnings.filterwarnings("ignore", message=r".*project\.license.* as a TOML table is deprecated")
# torch imported before pip installed numpy (the build runs before the dependencies are installed)
warnings.filterwarnings("ignore", message=r"Failed to initialize NumPy")

ROOT = os.path.dirname(os.path.abspath(__file__))


def _load_config() -> Any:
    path = os.path.join(ROOT, "torchbend", "backends", "_build_config.py")
    spec = importlib.util.spec_from_file_location("_torchbend_build_config", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


cfg = _load_config()
CSRC_REL = os.path.join("torchbend", "csrc")
COMMON_CFLAGS = ["-g0", "-fno-wrapv"]
"""Undo two of Python's own compile flags that the JIT build (torch.utils.cpp_extension.load) does not use:
debug info (a 12 MB module instead of 0.4 MB) and -fwrapv, so that both builds compile the same code."""


def _mode(var: str) -> str:
    """``"off"``, ``"required"`` or ``"auto"`` from an environment variable."""
    value = os.environ.get(var, "").strip().lower()
    if value in ("0", "no", "false", "off"):
        return "off"
    if value in ("1", "yes", "true", "on", "required"):
        return "required"
    return "auto"


def _say(msg: str) -> None:
    print(f"torchbend setup: {msg}", file=sys.stderr, flush=True)


def _package_data() -> list[str]:
    """Every non-Python file under torchbend/ (the C++ sources for the JIT fallback, robot assets, ...), as
    the previous hatchling build shipped them, less build products."""
    out = []
    pkg = os.path.join(ROOT, "torchbend")
    for dirpath, dirnames, filenames in os.walk(pkg):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for f in filenames:
            if not f.endswith((".py", ".pyc", ".so", ".pyd", ".o")):
                out.append(os.path.relpath(os.path.join(dirpath, f), pkg))
    return sorted(out)


_local = threading.local()


class _BuildMixin:
    """Mixed into torch's BuildExtension (ninja, torch's flags) by :func:`_extensions_and_cmdclass`: nvcc for
    the CUDA driver (started first, so that it runs while the CPU extension compiles), both extensions
    compiled in parallel (each in its own build folder: torch writes one build.ninja per folder), the build
    info compiled into each module, and optional extensions whose failure is a warning."""

    nvcc: str | None = None
    csrc: str = ""
    torch_version: str = ""

    @property
    def build_temp(self) -> str:  # per extension while the parallel builds run
        return getattr(_local, "build_temp", None) or self._build_temp

    @build_temp.setter
    def build_temp(self, value: str) -> None:
        self._build_temp = value

    def build_extensions(self) -> None:
        self._nvcc: tuple[list[tuple[subprocess.Popen, str]], float] | None = None
        self._nvcc_error: str | None = None
        try:  # torch's own first step (runs the C++ compiler): without a working compiler nothing builds
            self._check_abi()
        except Exception as e:
            if any(not ext.optional for ext in self.extensions):
                raise
            _say(f"WARNING: no working C++ compiler ({type(e).__name__}: {str(e)[-500:]}): the package installs "
                 "without its compiled kernels and runs its eager PyTorch path (or compiles them on first use "
                 "where a compiler appears)")
            self.extensions = []
            return
        self._reuse = {ext.name: path for ext in self.extensions if (path := self._reusable(ext))}
        if any(e.name == "torchbend._cuda" and e.name not in self._reuse for e in self.extensions):
            try:
                self._start_nvcc()
            except Exception as e:
                self._nvcc_error = f"{type(e).__name__}: {e}"
        if self.use_ninja and len(self.extensions) > 1:  # the non-ninja compile patches shared compiler state
            self.parallel = len(self.extensions)
        t0 = time.perf_counter()
        todo = [e.name for e in self.extensions if e.name not in self._reuse]
        if todo:  # (pip shows these lines with -v)
            _say(f"compiling {', '.join(todo)}: a few minutes on 2 cores (the C++ kernels; the CUDA ones take about "
                 "1.5 min more); a later install of the same sources reuses them")
        super().build_extensions()
        _say(f"extensions built in {time.perf_counter() - t0:.1f} s")

    def _start_nvcc(self) -> None:
        """One nvcc process per CUDA source, in the background."""
        nvcc = self.nvcc
        assert nvcc is not None
        os.makedirs(self.build_temp, exist_ok=True)
        jobs = []
        for src in cfg.CUDA_SOURCES:
            obj = os.path.abspath(os.path.join(self.build_temp, os.path.splitext(src)[0] + ".o"))
            cmd = [nvcc, "-c", *cfg.NVCC_FLAGS, *cfg.gencode_flags(cfg.cuda_archs(), ptx=True), "-I", self.csrc,
                   os.path.join(self.csrc, src), "-o", obj]
            _say(" ".join(cmd))
            jobs.append((subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True), obj))
        self._nvcc = (jobs, time.perf_counter())

    def _finish_nvcc(self, ext) -> None:
        if self._nvcc is None:
            raise RuntimeError(self._nvcc_error or "nvcc did not start")
        jobs, t0 = self._nvcc
        for proc, _ in jobs:
            out, _ = proc.communicate()
            if proc.returncode != 0:
                raise RuntimeError(f"nvcc failed ({proc.returncode}):\n{out[-3000:]}")
        _say(f"nvcc: {time.perf_counter() - t0:.1f} s")
        nvcc = self.nvcc
        assert nvcc is not None
        lib = cfg.cudart_dir(nvcc)
        ext.extra_objects = [*ext.extra_objects, *(obj for _, obj in jobs)]
        ext.library_dirs = [*ext.library_dirs, lib]
        ext.libraries = [*ext.libraries, "cudart"]
        ext.extra_link_args = [*ext.extra_link_args, f"-Wl,-rpath,{lib}"]

    def _info(self, ext) -> dict:
        """What goes into the module: everything that decides its code."""
        info = {"module": ext.name, "torch": self.torch_version, "cflags": list(ext.torchbend_cflags),
                "cpu": cfg.cpu_id()}
        if ext.name == "torchbend._cuda":
            return {**info, "source_hash": cfg.cuda_source_hash(self.csrc), "archs": cfg.cuda_archs(), "ptx": True,
                    "nvcc_flags": list(cfg.NVCC_FLAGS), "nvcc": self.nvcc}
        return {**info, "source_hash": cfg.native_source_hash(self.csrc)}

    def _reusable(self, ext) -> str | None:
        """The module already in the source tree (an earlier editable install) if it was built from the same
        sources with the same flags, torch and CPU: a reinstall copies it instead of compiling again."""
        if os.environ.get("TORCHBEND_FORCE_BUILD", "") == "1":
            return None
        path = os.path.join(ROOT, *ext.name.split(".")[:-1], os.path.basename(self.get_ext_filename(ext.name)))
        return path if os.path.exists(path) and cfg.read_build_info(path) == self._info(ext) else None

    def _add_info(self, ext, info: dict) -> None:
        short = ext.name.rsplit(".", 1)[-1].lstrip("_")
        os.makedirs(self.build_temp, exist_ok=True)
        path = os.path.join(self.build_temp, f"torchbend_{short}_build_info.cpp")
        with open(path, "w") as fh:
            fh.write(cfg.info_source(f"torchbend_{short}_build_info", info))
        if path not in ext.sources:
            ext.sources = [*ext.sources, path]

    def build_extension(self, ext) -> None:
        required = not ext.optional
        t0 = time.perf_counter()
        _local.build_temp = os.path.join(self._build_temp, ext.name.rsplit(".", 1)[-1])
        try:
            if ext.name in self._reuse:
                target = self.get_ext_fullpath(ext.name)
                os.makedirs(os.path.dirname(target), exist_ok=True)
                shutil.copyfile(self._reuse[ext.name], target)
                _say(f"{ext.name}: reusing {self._reuse[ext.name]} (same sources, flags, torch and CPU; "
                     "TORCHBEND_FORCE_BUILD=1 compiles anyway)")
                return
            if ext.name == "torchbend._cuda":
                self._finish_nvcc(ext)
            self._add_info(ext, self._info(ext))
            super().build_extension(ext)
        except Exception as e:
            if required:
                raise
            _say(f"WARNING: could not build {ext.name} ({type(e).__name__}: {str(e)[-2000:]}); the package "
                 "installs without it and compiles the kernels on first use, or runs its eager path")
            return
        finally:
            _local.build_temp = None
        _say(f"built {ext.name} in {time.perf_counter() - t0:.1f} s")


def _extensions_and_cmdclass() -> tuple[list, dict]:
    native_mode, cuda_mode = _mode("TORCHBEND_BUILD_NATIVE"), _mode("TORCHBEND_BUILD_CUDA")
    if native_mode == "off" and cuda_mode == "off":
        return [], {}
    try:
        import torch
        from torch.utils.cpp_extension import BuildExtension, CppExtension
    except ImportError as e:
        if "required" in (native_mode, cuda_mode):
            raise RuntimeError("torchbend: torch must be installed before building the extensions "
                               "(pip install torch, then pip install --no-build-isolation ...)") from e
        _say("torch is not importable in the build environment (install torch first and use "
             "--no-build-isolation): no extension is built now; the kernels are compiled on first use instead")
        return [], {}

    csrc = os.path.join(ROOT, CSRC_REL)
    exts = []
    if native_mode != "off":
        exts.append(CppExtension(
            "torchbend._native", [os.path.join(CSRC_REL, f) for f in cfg.NATIVE_SOURCES], include_dirs=[csrc],
            extra_compile_args=[*COMMON_CFLAGS, *(f for f in cfg.NATIVE_CFLAGS if not f.startswith("-march=")),
                                *cfg.cpu_arch_flags()],
            extra_link_args=list(cfg.NATIVE_LDFLAGS), optional=native_mode != "required"))
    if cuda_mode == "auto" and torch.version.cuda is None:
        cuda_mode = "off"
        _say("the installed torch is a CPU build: the CUDA kernels are not built (TORCHBEND_BUILD_CUDA=1 builds "
             "them anyway, about 1-3 minutes more)")
    if native_mode != "off":
        _say("compiling the C++ CPU kernels (torchbend._native): about 1-4 minutes on 2 cores, once; a later install "
             "of the same sources reuses them")
    nvcc = cfg.find_nvcc() if cuda_mode != "off" else None
    if cuda_mode != "off":
        if nvcc is None and cuda_mode == "required":
            raise RuntimeError("torchbend: TORCHBEND_BUILD_CUDA=1 but nvcc was not found "
                               "(set TORCHBEND_NVCC or CUDA_HOME)")
        if nvcc is None:
            _say("nvcc not found: the CUDA kernels are not built (TORCHBEND_BUILD_CUDA=1 to require them)")
        else:
            exts.append(CppExtension(
                "torchbend._cuda", [os.path.join(CSRC_REL, cfg.CUDA_BINDING)], include_dirs=[csrc],
                extra_compile_args=[*COMMON_CFLAGS, "-O2"], optional=cuda_mode != "required"))

    for ext in exts:  # our flags, before torch's BuildExtension adds its own (recorded in the build info)
        ext.torchbend_cflags = list(ext.extra_compile_args)
    cmd = type("BuildTorchbend", (_BuildMixin, BuildExtension),
               {"nvcc": nvcc, "csrc": csrc, "torch_version": torch.__version__})
    return exts, {"build_ext": cmd}


ext_modules, cmdclass = _extensions_and_cmdclass()
setup(ext_modules=ext_modules, cmdclass=cmdclass, package_data={"torchbend": _package_data()})
