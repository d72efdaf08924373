"""The compiled extensions: where they come from (built by ``pip install`` or JIT on first use), that an
installed module built from other sources is not used, and that every function and CUDA kernel is in them.

CI (``.ci/run``) installs with ``TORCHBEND_BUILD_CUDA=1`` (an nvcc failure fails the install) and runs the
tests with ``TORCHBEND_EXPECT_PREBUILT=1``, so there the modules must be the ones the install built; then
``test_cuda_module_builds_imports_and_registers_every_kernel`` fails for a kernel that did not compile,
link or register.  The CUDA part is built and checked on any machine with nvcc; no GPU is needed."""
import json
import os
import re
import shutil
import subprocess
import sys

import pytest
import torch

from torchbend.backends import _build_config as cfg
from torchbend.backends import cuda, native

NATIVE_FUNCTIONS = ("bending_hessians", "assemble", "bending_energy", "bending_gradient", "bending_hvp",
                    "project_blocks")
"""The least set of functions of the CPU module (``PYBIND11_MODULE`` in ``csrc/bending_cpu.cpp``); a new
binding is checked without being listed (every ``m.def`` of the source must be there), list it here too
if the Python side relies on it."""
CUDA_FUNCTIONS = ("bending_energy", "bending_gradient", "bending_hvp", "bending_hessians", "kernels")
"""The same for the CUDA binding (``csrc/cuda_binding.cpp``)."""

EXPECT_PREBUILT = os.environ.get("TORCHBEND_EXPECT_PREBUILT", "") == "1"
has_nvcc = cfg.find_nvcc() is not None
needs_nvcc = pytest.mark.skipif(not has_nvcc, reason="nvcc not found (TORCHBEND_NVCC, CUDA_HOME, PATH): the CUDA "
                                "part is built and checked only where nvcc is installed, as on CI")


def _bound_names(source: str) -> list[str]:
    """The names a ``PYBIND11_MODULE`` block of ``csrc/<source>`` defines."""
    with open(os.path.join(cfg.CSRC, source)) as fh:
        text = fh.read()
    block = text[text.index("PYBIND11_MODULE"):]
    return re.findall(r'm\.def\(\s*"(\w+)"', block)


def _global_kernels() -> list[tuple[str, bool]]:
    """``(name, templated)`` of every ``__global__`` function of the CUDA driver (templates: float and double)."""
    text = ""
    for src in cfg.CUDA_SOURCES:
        with open(os.path.join(cfg.CSRC, src)) as fh:
            text += fh.read()
    pattern = r"(template\s*<[^>]*>\s*)?__global__\s+void\s+(\w+)\s*\("
    return [(m.group(2), m.group(1) is not None) for m in re.finditer(pattern, text)]


def test_csrc_is_shipped_for_the_jit_fallback():
    for f in (*cfg.NATIVE_SOURCES, *cfg.CUDA_SOURCES, cfg.CUDA_BINDING, "hinge_math.h", "vector_math.h", "hinge_ops.h"):
        assert os.path.exists(os.path.join(cfg.CSRC, f)), f


def test_every_cpu_source_is_built_and_small():
    """Every translation unit of the CPU driver in ``csrc`` is in ``NATIVE_SOURCES`` (what ``setup.py`` and the JIT
    build compile), and none of them, nor a header, grows past about 500 lines."""
    on_disk = {f for f in os.listdir(cfg.CSRC) if f.endswith(".cpp") and f != cfg.CUDA_BINDING}
    assert on_disk == set(cfg.NATIVE_SOURCES)
    for f in (*cfg.NATIVE_SOURCES, *cfg.headers()):
        with open(os.path.join(cfg.CSRC, f)) as fh:
            assert sum(1 for _ in fh) <= 600, f


def test_native_module_is_loaded_once_and_has_every_function():
    module = native.load()
    if module is None:
        assert not EXPECT_PREBUILT, native.build_info()
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")
    assert native.load() is module and native._module() is module
    names = _bound_names("bending_cpu.cpp")
    assert set(NATIVE_FUNCTIONS) <= set(names), "a function of NATIVE_FUNCTIONS lost its binding"
    for fn in names:
        assert callable(getattr(module, fn, None)), f"torchbend native module lacks {fn} ({native.build_info()})"
    info = native.build_info()
    assert info["source"] in ("install", "jit") and info["path"] and os.path.exists(info["path"])
    assert info["seconds"] is not None and info["seconds"] >= 0


def _check_source(info: dict, module_name: str, expected_hash: str) -> None:
    """The installed module is used exactly when it is current."""
    _, _, why = cfg.find_prebuilt(module_name, expected_hash, torch.__version__)
    if not why:
        assert info["source"] == "install", info
    if EXPECT_PREBUILT:
        assert info["source"] == "install" and info["prebuilt"] == "used", info
        assert info["build"]["source_hash"] == expected_hash


def test_native_installed_module_is_used_when_current():
    _check_source(native.build_info(), native.PREBUILT, cfg.native_source_hash())


def test_stale_installed_module_is_not_used(monkeypatch):
    """After an edit of the sources (an editable install, say) the hash differs: the loader must not take the
    installed module (it JIT-builds the current sources instead)."""
    monkeypatch.setattr(cfg, "native_source_hash", lambda csrc=cfg.CSRC: "0" * 64)
    module, why, _ = native._load_prebuilt()
    assert module is None
    assert why.startswith(("stale", "not installed", "TORCHBEND_PREBUILT")), why
    monkeypatch.setenv("TORCHBEND_PREBUILT", "0")
    assert cfg.find_prebuilt(native.PREBUILT, cfg.native_source_hash(), torch.__version__)[2] == "TORCHBEND_PREBUILT=0"


def test_cpu_operators_are_registered_when_asked_not_at_import():
    """The CPU extension registers torch.ops.torchbend.* in ``register_operators`` (the loader calls it on the module
    it chose), not in static initializers: a stale in-place build imported directly (``import torchbend._native``
    by a documentation tool after an edit of ``csrc/``) and the JIT build of the current sources then share one
    process, where two ``TORCH_LIBRARY(torchbend)`` blocks abort it."""
    for src in cfg.NATIVE_SOURCES:
        with open(os.path.join(cfg.CSRC, src)) as fh:
            text = fh.read()
        assert not re.search(r"^\s*TORCH_LIBRARY(_IMPL|_FRAGMENT)?\s*\(", text, re.M), src
    module = native.load()
    if module is None:
        pytest.skip(f"the CPU extension is not available: {native.build_error()}")
    assert hasattr(module, "register_operators")
    module.register_operators()  # once per process: a second call changes nothing
    assert hasattr(torch.ops.torchbend, "bending_energy")


def _fake_extension(tmp_path, monkeypatch, info: dict | None) -> str:
    pkg = tmp_path / "tb_fake_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    payload = b"\x7fELF junk" + (cfg.INFO_MARKER + json.dumps(info).encode() if info else b"") + b"\0 more junk"
    (pkg / f"_ext{_ext_suffix()}").write_bytes(payload)
    monkeypatch.syspath_prepend(str(tmp_path))
    return "tb_fake_pkg._ext"


def _ext_suffix() -> str:
    import importlib.machinery

    return importlib.machinery.EXTENSION_SUFFIXES[0]


def test_find_prebuilt_reads_the_embedded_hash(tmp_path, monkeypatch):
    monkeypatch.delenv("TORCHBEND_PREBUILT", raising=False)
    name = _fake_extension(tmp_path, monkeypatch, {"source_hash": "abc", "torch": torch.__version__, "archs": ["90"]})
    path, info, why = cfg.find_prebuilt(name, "abc", torch.__version__)
    assert why == "" and path is not None and info is not None and info["archs"] == ["90"]
    assert cfg.find_prebuilt(name, "abd", torch.__version__)[2].startswith("stale")
    assert "built against torch" in cfg.find_prebuilt(name, "abc", "0.0")[2]
    assert cfg.find_prebuilt("tb_fake_pkg._missing", "abc", torch.__version__)[2].startswith("not installed")
    sys.modules.pop("tb_fake_pkg", None)


def test_info_source_round_trips_through_a_compiler(tmp_path):
    """The generated translation unit compiles and its marker string is found in the object file."""
    cxx = shutil.which(os.environ.get("CXX", "c++")) or shutil.which("g++")
    if cxx is None:
        pytest.skip("no C++ compiler")
    info = {"source_hash": "0123", "cflags": ['-DX="a b"', "-O3"], "torch": torch.__version__}
    src = tmp_path / "info.cpp"
    src.write_text(cfg.info_source("tb_test_build_info", info))
    obj = tmp_path / "info.o"
    subprocess.run([cxx, "-c", str(src), "-o", str(obj)], check=True)
    assert cfg.read_build_info(str(obj)) == info


def test_hash_covers_every_header_and_source(tmp_path):
    csrc = tmp_path / "csrc"
    shutil.copytree(cfg.CSRC, csrc)
    h0, c0 = cfg.native_source_hash(str(csrc)), cfg.cuda_source_hash(str(csrc))
    (csrc / "new_header.h").write_text("// new\n")
    h1, c1 = cfg.native_source_hash(str(csrc)), cfg.cuda_source_hash(str(csrc))
    assert h1 != h0 and c1 != c0
    with open(csrc / cfg.CUDA_SOURCES[0], "a") as fh:
        fh.write("// edit\n")
    assert cfg.native_source_hash(str(csrc)) == h1 and cfg.cuda_source_hash(str(csrc)) != c1


def test_arch_compatibility():
    assert cfg.arch_compatible(["80", "90"], True, (8, 6))  # sm_80 SASS runs on 8.6
    assert cfg.arch_compatible(["80", "90"], True, (12, 0))  # PTX of sm_90
    assert not cfg.arch_compatible(["80", "90"], False, (12, 0))
    assert not cfg.arch_compatible(["80", "90"], True, (7, 5))
    assert cfg.gencode_flags(["80", "90"], ptx=True)[-1] == "-gencode=arch=compute_90,code=compute_90"


@needs_nvcc
def test_cuda_module_builds_imports_and_registers_every_kernel():
    """Built (at install, or here on first use), linked with cudart and imported (unresolved symbols fail the
    import); its kernel registry lists every operation in both dtypes; every ``__global__`` kernel of the
    driver is compiled into the module (host stub and the name under which the runtime registers it)."""
    assert cuda.build_error() is None, cuda.build_error()
    module = cuda.load()
    names = _bound_names(cfg.CUDA_BINDING)
    assert set(CUDA_FUNCTIONS) <= set(names)
    for fn in names:
        assert callable(getattr(module, fn, None)), f"torchbend CUDA module lacks {fn}"
    assert set(cuda.kernels()) == {f"{op}_{d}" for op in cuda.KERNELS for d in ("f32", "f64")}
    _check_source(cuda.build_info(), cuda.PREBUILT, cfg.cuda_source_hash())

    kernels = _global_kernels()
    assert len(kernels) >= len(cuda.KERNELS)
    path = module.__file__
    with open(path, "rb") as fh:
        binary = fh.read()
    nm = shutil.which("nm")
    symbols = subprocess.run([nm, "-C", path], capture_output=True, text=True, check=True).stdout if nm else None
    missing = []
    for name, templated in kernels:
        for ctype, code in ((("float", "f"), ("double", "d")) if templated else ((None, None),)):
            mangled = f"{len(name)}{name}" + (f"I{code}E" if code else "")
            if mangled.encode() not in binary:
                missing.append(f"{name}<{ctype}> (registration)")
            if symbols is not None and not re.search(rf"\b{name}{f'<{ctype}>' if ctype else ''}\(", symbols):
                missing.append(f"{name}<{ctype}> (host stub)")
    assert not missing, f"kernels missing from {path}: {missing}"


@needs_nvcc
def test_cuda_build_info():
    info = cuda.build_info()
    assert info["source"] in ("install", "jit") and os.path.exists(info["path"])
    if info["source"] == "install":
        assert info["build"]["archs"] and info["build"]["ptx"] is True
