"""The CPU kernels built for other instruction sets than this machine's (``TORCHBEND_CPU_ARCH``).

The instruction-set flag changes the last bits of the results (vector width, fused multiply-adds or not), and
CI may run on any x86-64 CPU: the kernel and solver tests must pass against every such build.  The fast tests
check that the JIT build honours ``TORCHBEND_CPU_ARCH`` (flags, a module name per architecture, no installed
module built for another one); the slow ones build the kernels for ``x86-64-v3`` (AVX2 + FMA) and ``x86-64``
(SSE2, no FMA) in a subprocess and run the kernel tests against them::

    python -m pytest -q -m slow tests/test_portable_builds.py

or by hand, any test file against any build (the first run compiles, a few minutes; cached per architecture)::

    TORCHBEND_PREBUILT=0 TORCHBEND_CPU_ARCH=x86-64-v3 python -m pytest -q tests/test_ops.py tests/test_native.py
    TORCHBEND_PREBUILT=0 TORCHBEND_CPU_ARCH=x86-64 python -m pytest -q tests/test_ops.py tests/test_native.py
"""
import os
import subprocess
import sys

import pytest
import torch

from torchbend.backends import _build_config as cfg
from torchbend.backends import native

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
KERNEL_TESTS = ("tests/test_ops.py", "tests/test_native.py", "tests/test_native_second_order.py", "tests/test_membrane.py")


@pytest.mark.parametrize("value,flags,tag", [
    ("native", ["-march=native"], "native"),
    ("x86-64-v3", ["-march=x86-64-v3"], "x86_64_v3"),
    ("x86-64", ["-march=x86-64"], "x86_64"),
    ("portable", [], "portable"),
])
def test_jit_flags_and_name_follow_the_requested_arch(monkeypatch, value, flags, tag):
    monkeypatch.setenv("TORCHBEND_CPU_ARCH", value)
    assert cfg.cpu_arch_flags() == flags
    assert cfg.cpu_arch_tag() == tag
    cflags = native.jit_cflags()
    assert [f for f in cflags if f.startswith("-march=")] == flags
    assert [f for f in cflags if not f.startswith("-march=")] == [f for f in cfg.NATIVE_CFLAGS if not f.startswith("-march=")]
    name = native.extension_name()
    assert name.startswith(f"torchbend_native_{cfg.native_source_hash()[:12]}") and name.isidentifier()
    assert name.endswith("" if tag == "native" else f"_{tag}")


def test_jit_names_differ_per_arch(monkeypatch):
    names = set()
    for value in ("native", "x86-64-v3", "x86-64", "portable"):
        monkeypatch.setenv("TORCHBEND_CPU_ARCH", value)
        names.add(native.extension_name())
    assert len(names) == 4
    monkeypatch.delenv("TORCHBEND_CPU_ARCH")
    assert cfg.cpu_arch_flags() == ["-march=native"]


def test_installed_module_for_another_arch_is_not_used(monkeypatch):
    """With ``TORCHBEND_CPU_ARCH`` set, an installed module built for another instruction set is passed over
    (the JIT build for the requested one is used instead); unset, any current one is used."""
    info = {"source_hash": "h", "torch": torch.__version__, "cflags": ["-O3", "-march=x86-64-v3"], "cpu": cfg.cpu_id()}
    monkeypatch.setattr(cfg, "read_build_info", lambda path: dict(info))
    monkeypatch.delenv("TORCHBEND_PREBUILT", raising=False)
    module = "torchbend.options"  # any installed module file: its build info is the fake above
    monkeypatch.delenv("TORCHBEND_CPU_ARCH", raising=False)
    assert cfg.find_prebuilt(module, "h", torch.__version__, cpu_arch=True)[2] == ""
    monkeypatch.setenv("TORCHBEND_CPU_ARCH", "x86-64-v3")
    assert cfg.find_prebuilt(module, "h", torch.__version__, cpu_arch=True)[2] == ""
    monkeypatch.setenv("TORCHBEND_CPU_ARCH", "x86-64")
    why = cfg.find_prebuilt(module, "h", torch.__version__, cpu_arch=True)[2]
    assert "TORCHBEND_CPU_ARCH" in why, why
    assert cfg.find_prebuilt(module, "h", torch.__version__)[2] == ""  # the CUDA module: no CPU arch check


def test_loaded_module_has_the_requested_arch():
    """Whichever build runs the tests, ``build_info`` says its flags; with ``TORCHBEND_CPU_ARCH`` set, they are
    the requested ones (the suite then really tests that build)."""
    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")
    info = native.build_info()
    assert info["cflags"] is not None and info["arch"] is not None, info
    if "TORCHBEND_CPU_ARCH" in os.environ:
        assert [f for f in info["cflags"] if f.startswith("-march=")] == cfg.cpu_arch_flags(), info
        assert info["arch"] == cfg.cpu_arch_tag(), info


@pytest.mark.slow
@pytest.mark.parametrize("arch", ["x86-64-v3", "x86-64"])
def test_kernel_tests_pass_against_other_arch_builds(arch):
    """The kernel tests against the kernels built for ``arch`` (compiled in the subprocess on first use)."""
    env = dict(os.environ, TORCHBEND_CPU_ARCH=arch, TORCHBEND_PREBUILT="0")
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *KERNEL_TESTS, "tests/test_portable_builds.py"]
    run = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=3600)
    assert run.returncode == 0, f"{arch}:\n{run.stdout[-4000:]}\n{run.stderr[-2000:]}"
