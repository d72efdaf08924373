"""One loader for the compiled extensions (:mod:`torchbend.backends.native`, :mod:`torchbend.backends.cuda`).

Once per process, :meth:`Extension.load` takes the module ``setup.py`` built at install time if it was built from
the sources installed next to it (:func:`torchbend.backends._build_config.find_prebuilt`, and the extension's own
``compatible`` test, e.g. the GPU's architecture), and otherwise the extension's JIT build (compiled on first use,
cached by torch); without a compiler it records why, and the eager path runs.  :meth:`Extension.build_info` says
which happened.
"""
from __future__ import annotations

import importlib
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any

from . import _build_config as cfg


class Extension:
    """A compiled extension: ``prebuilt`` (the install-time module, e.g. ``"torchbend._native"``) if current, else
    ``jit_build()`` (returns the module and what :meth:`build_info` adds about it).

    ``source_hash``: the hash the installed module must carry (called at load time); ``cpu_arch``: the installed
    module must also match ``TORCHBEND_CPU_ARCH`` (the CPU extension); ``compatible(info)``: ``""`` if an installed
    module with build info ``info`` runs here, else why not; ``install_info(info)``: what :meth:`build_info` adds
    about the installed module; ``warn``: a failed build warns (once) that the eager path runs; ``on_load(module)``:
    called once with the loaded module (e.g. to register the status helper its operators call back)."""

    def __init__(self, label: str, prebuilt: str, source_hash: Callable[[], str],
                 jit_build: Callable[[], tuple[Any, dict[str, Any]]], *, cpu_arch: bool = False,
                 compatible: Callable[[dict], str] | None = None,
                 install_info: Callable[[dict], dict[str, Any]] | None = None, warn: bool = False,
                 info_keys: tuple[str, ...] = (), on_load: Callable[[Any], None] | None = None):
        self.label, self.prebuilt, self.source_hash, self.jit_build = label, prebuilt, source_hash, jit_build
        self.cpu_arch, self.compatible, self.install_info, self.warn = cpu_arch, compatible, install_info, warn
        self.on_load = on_load
        self.info: dict[str, Any] = dict.fromkeys(("source", "seconds", "path", "prebuilt", "build", *info_keys))
        self._result: tuple[Any, str | None] | None = None
        self._lock = threading.Lock()

    def load_prebuilt(self) -> tuple[Any, str, dict[str, Any]]:
        """``(module, "", found)`` if the installed module is current and runs here, else ``(None, why not, found)``;
        ``found``: the installed module's path and build info, if any."""
        import torch

        path, info, why = cfg.find_prebuilt(self.prebuilt, self.source_hash(), torch.__version__,
                                            cpu_arch=self.cpu_arch)
        found = {"path": path, "build": info}
        if not why and self.compatible is not None:
            why = self.compatible(info or {})
        if why:
            return None, why, found
        try:
            return importlib.import_module(self.prebuilt), "", found
        except Exception as e:  # an ABI mismatch, a missing library, ...
            return None, f"import failed: {type(e).__name__}: {e}", found

    def _build(self) -> tuple[Any, str | None]:
        t0 = time.perf_counter()
        module, why, found = self.load_prebuilt()
        self.info.update(found, prebuilt=why or "used")
        if module is not None:
            extra = self.install_info(found["build"] or {}) if self.install_info else {}
            self.info.update(extra, source="install", seconds=time.perf_counter() - t0, path=module.__file__)
            return module, None
        try:
            module, extra = self.jit_build()
        except Exception as e:  # no compiler, no nvcc, no ninja, a failed compile, ...
            reason = f"{type(e).__name__}: {str(e)[-800:]}"
            self.info.update(source=None, seconds=time.perf_counter() - t0, path=None)
            if self.warn:
                warnings.warn(f"torchbend: could not build the {self.label} ({reason[:300]}); using the eager path",
                              RuntimeWarning, stacklevel=5)
            return None, reason
        self.info.update(extra, source="jit", seconds=time.perf_counter() - t0, path=getattr(module, "__file__", None))
        return module, None

    def result(self) -> tuple[Any, str | None]:
        """``(module, None)`` or ``(None, why not)``, built once per process."""
        result = self._result
        if result is None:
            with self._lock:
                if self._result is None:
                    built = self._build()
                    if built[0] is not None and self.on_load is not None:
                        self.on_load(built[0])
                    self._result = built
                result = self._result
        return result

    def load(self) -> Any:
        """The compiled module, or ``None`` if it cannot be built here (see :meth:`build_error`)."""
        return self.result()[0]

    def build_error(self) -> str | None:
        """Why the module could not be built (``None`` if it was)."""
        return self.result()[1]

    def build_info(self) -> dict[str, Any]:
        """How :meth:`load` got the module: ``source`` (``"install"``: the module built by ``pip install``;
        ``"jit"``: compiled or taken from torch's extension cache on first use; ``None``: not available),
        ``seconds`` (the time :meth:`load` took in this process), ``path`` (the library), ``prebuilt`` (``"used"``
        or why the installed module was not used), ``build`` (what the installed module says of its build), and
        the extension's own keys.  Loads the module if that has not happened yet."""
        self.result()
        return dict(self.info)

    def module(self) -> Any:
        """The compiled module; a ``RuntimeError`` saying why if it is not available."""
        module, why = self.result()
        if module is None:
            raise RuntimeError(f"torchbend: the {self.label} is not available ({why})")
        return module
