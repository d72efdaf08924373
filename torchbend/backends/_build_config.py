r"""What the compiled extensions are built from, shared by ``setup.py`` (the build at install time) and the
loaders in :mod:`torchbend.backends.native` / :mod:`torchbend.backends.cuda` (the JIT build on first use,
and the check that an installed module still matches the shipped sources).

Standard library only: ``setup.py`` loads this file by its path, before torch or torchbend can be imported.

Both builds put a *source hash* into their module: a SHA-256 over the C++/CUDA sources, every header in
``csrc`` and the flags that change the generated code, but not the instruction-set flag (``-march``, the
CUDA architectures), which only decides where the code runs.  An installed module whose hash differs from
the hash of the sources next to it (an editable install after an edit of a header, say) is not used: the
loader builds the current sources on first use instead (cached).  The install-time build writes its hash,
flags and torch version into the binary as a marker string (:data:`INFO_MARKER`), which
:func:`read_build_info` finds without loading the library.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import shutil
import subprocess

CSRC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "csrc")

# ---- CPU extension (torchbend._native; JIT name torchbend_native_<hash>) ----
NATIVE_SOURCES = ("bending_cpu.cpp", "cpu_tiles.cpp", "cpu_first_order.cpp", "cpu_second_order.cpp", "cpu_blocks.cpp",
                  "cpu_assembly.cpp", "cpu_projection.cpp", "cpu_membrane.cpp", "cpu_contact.cpp", "cpu_contact_sum.cpp",
                  "cpu_broad_phase.cpp",
                  "cpu_registration.cpp")
"""The translation units of the CPU extension (add a new ``.cpp`` here; headers are found by themselves)."""
NATIVE_CFLAGS = ("-O3", "-march=native", "-fopenmp", "-fno-math-errno", "-fno-trapping-math")
"""-fno-math-errno: sqrt without its errno branch, so that the half-hinge lane loops vectorize (about 8%
faster; the results stay correctly rounded).  -fno-trapping-math: the compiler may evaluate both sides of a
select (no floating-point trap handler is assumed to be installed), which AVX2 needs to if-convert the lane
loops (AVX-512 does it with masked instructions): without it GCC vectorizes about half of the lane loops of
an ``x86-64-v3`` build (the vectorization check, ``python tools/check_vectorization.py``, run by CI).
Neither flag changes a result: the same operations in the same order, no reassociation, no flush to zero
(``-ffast-math`` would change results, and must not be used).  ``-march=native`` is the default; both the install build and
the JIT build replace it with :func:`cpu_arch_flags` (``TORCHBEND_CPU_ARCH``), see :func:`native_cflags`."""
NATIVE_LDFLAGS = ("-fopenmp",)

# ---- CUDA extension (torchbend._cuda; JIT name torchbend_cuda_<hash>) ----
CUDA_SOURCES = ("bending_cuda.cu",)
CUDA_BINDING = "cuda_binding.cpp"
NVCC_FLAGS = ("-O3", "-std=c++17", "-Xcompiler", "-fPIC")
CUDA_INSTALL_ARCHS = ("80", "90")
"""Architectures of the install-time build when ``TORCHBEND_CUDA_ARCH`` is unset: SASS for each, and PTX of
the newest, which the driver compiles for newer GPUs."""

INFO_MARKER = b"TORCHBEND_BUILD_INFO:"


def headers(csrc: str = CSRC) -> tuple[str, ...]:
    """Every header in ``csrc`` (a new header is hashed without being listed anywhere)."""
    return tuple(sorted(os.path.basename(p) for p in glob.glob(os.path.join(csrc, "*.h"))))


def _is_arch_flag(flag: str) -> bool:
    return flag.startswith(("-march=", "-mtune=", "-mcpu="))


def _hash(files: tuple[str, ...], flags: tuple[str, ...], csrc: str) -> str:
    digest = hashlib.sha256(" ".join(f for f in flags if not _is_arch_flag(f)).encode())
    for f in sorted(set(files)):
        with open(os.path.join(csrc, f), "rb") as fh:
            digest.update(b"\0" + f.encode() + b"\0" + fh.read())
    return digest.hexdigest()


def native_source_hash(csrc: str = CSRC) -> str:
    """Hash of the CPU extension's sources, headers and (non-arch) flags."""
    return _hash(NATIVE_SOURCES + headers(csrc), NATIVE_CFLAGS, csrc)


def cuda_source_hash(csrc: str = CSRC) -> str:
    """Hash of the CUDA driver, its binding, the headers and the nvcc flags (not the architectures)."""
    return _hash(CUDA_SOURCES + (CUDA_BINDING,) + headers(csrc), NVCC_FLAGS, csrc)


def cpu_arch_flags() -> list[str]:
    """The instruction-set flag of the CPU build (install time and JIT) from ``TORCHBEND_CPU_ARCH``: unset or
    ``native`` -> ``-march=native`` (this machine's CPU: right for a build from source, as the documented
    install is; not for a wheel copied to other machines), ``none``/``portable``/empty -> no flag (the
    compiler's baseline, e.g. x86-64), anything else ``X`` -> ``-march=X`` (e.g. ``x86-64-v3``).

    The flag decides more than where the code runs: the vector width and whether ``a*b + c`` is contracted
    into one fused multiply-add change the last bits of the results (x86-64: SSE2 without FMA; x86-64-v3:
    AVX2 with FMA; native on an AVX-512 machine: 512-bit vectors with FMA).  The tests take tolerances
    that hold for every one of them; ``tests/test_portable_builds.py`` runs them against such builds."""
    value = os.environ.get("TORCHBEND_CPU_ARCH", "native").strip()
    if value.lower() in ("", "none", "portable"):
        return []
    return [f"-march={value}"]


def cpu_arch_tag(flags: list[str] | tuple[str, ...] | None = None) -> str:
    """A short identifier of the instruction-set flags ``flags`` (default :func:`cpu_arch_flags`): ``"native"``,
    ``"portable"`` (no ``-march``) or the ``-march`` value with every character outside ``[A-Za-z0-9]`` as ``_``
    (``"x86_64_v3"``); part of the JIT module's name, so that builds for different architectures do not
    overwrite one another in ``TORCH_EXTENSIONS_DIR``."""
    arch = [f.split("=", 1)[1] for f in (cpu_arch_flags() if flags is None else flags) if f.startswith("-march=")]
    if not arch:
        return "portable"
    return "".join(c if c.isalnum() else "_" for c in arch[-1])


def native_cflags() -> list[str]:
    """The CPU extension's compile flags: :data:`NATIVE_CFLAGS` with the instruction-set flag of
    :func:`cpu_arch_flags` (``TORCHBEND_CPU_ARCH``) in place of ``-march=native``."""
    return [*(f for f in NATIVE_CFLAGS if not _is_arch_flag(f)), *cpu_arch_flags()]


def cuda_archs(default: tuple[str, ...] = CUDA_INSTALL_ARCHS) -> list[str]:
    """``TORCHBEND_CUDA_ARCH`` (``"90"``, ``"80;90"``, ``"8.0,9.0"``) as ``["80", "90"]``, else ``default``."""
    env = os.environ.get("TORCHBEND_CUDA_ARCH")
    if env:
        return [a.strip().replace(".", "") for a in env.replace(",", ";").split(";") if a.strip()]
    return list(default)


def gencode_flags(archs: list[str], ptx: bool) -> list[str]:
    """SASS for every architecture, plus PTX of the newest if ``ptx`` (runs on later GPUs through the driver's JIT)."""
    flags = [f"-gencode=arch=compute_{a},code=sm_{a}" for a in archs]
    if ptx and archs:
        top = max(archs, key=int)
        flags.append(f"-gencode=arch=compute_{top},code=compute_{top}")
    return flags


def arch_compatible(archs: list[str], ptx: bool, capability: tuple[int, int]) -> bool:
    """Whether code built for ``archs`` (SASS, plus PTX of the newest if ``ptx``) runs on a GPU of compute
    ``capability``: SASS runs on the same major version with an equal or higher minor, PTX on anything newer."""
    major, minor = capability
    cap = 10 * major + minor
    for a in archs:
        v = int(a)
        if v // 10 == major and v % 10 <= minor:
            return True
    return bool(ptx and archs and max(int(a) for a in archs) <= cap)


def find_nvcc() -> str | None:
    """``TORCHBEND_NVCC``, else ``nvcc`` in ``CUDA_HOME``/``CUDA_PATH``, on the ``PATH``, or in ``/usr/local/cuda``."""
    explicit = os.environ.get("TORCHBEND_NVCC")
    if explicit:
        return explicit
    for var in ("CUDA_HOME", "CUDA_PATH"):
        home = os.environ.get(var)
        if home and os.path.exists(os.path.join(home, "bin", "nvcc")):
            return os.path.join(home, "bin", "nvcc")
    found = shutil.which("nvcc")
    if found:
        return found
    default = "/usr/local/cuda/bin/nvcc"
    return default if os.path.exists(default) else None


def cudart_dir(nvcc: str, extra: tuple[str | None, ...] = ()) -> str:
    """The folder with ``libcudart.so``: next to nvcc's toolkit (nvcc may be a wrapper script: it is asked
    where it lives), ``CUDA_HOME``'s, or ``/usr/local/cuda``'s."""
    candidates = [os.path.dirname(os.path.dirname(os.path.realpath(nvcc))), *extra,
                  os.environ.get("CUDA_HOME"), "/usr/local/cuda"]
    try:
        out = subprocess.run([nvcc, "--dryrun", "--version"], capture_output=True, text=True, timeout=60).stderr
        candidates += [line.split("=", 1)[1].strip() for line in out.splitlines() if "TOP=" in line]
    except Exception:  # pragma: no cover
        pass
    for home in candidates:
        for sub in ("lib64", "lib", os.path.join("targets", "x86_64-linux", "lib")):
            d = os.path.join(home, sub) if home else ""
            if d and os.path.exists(os.path.join(d, "libcudart.so")):
                return d
    raise RuntimeError(f"libcudart.so not found near {nvcc} (tried {[c for c in candidates if c]})")


def cpu_id() -> str:
    """The machine and CPU model (``-march=native`` code runs on the CPU it was built on)."""
    import platform

    model = ""
    try:
        with open("/proc/cpuinfo") as fh:
            model = next((line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")), "")
    except OSError:  # pragma: no cover - not Linux
        model = platform.processor()
    return f"{platform.machine()} {model}".strip()


def info_source(symbol: str, info: dict) -> str:
    """A C++ translation unit that puts ``info`` (JSON) into the binary after :data:`INFO_MARKER`."""
    text = (INFO_MARKER.decode() + json.dumps(info, sort_keys=True)).replace("\\", "\\\\").replace('"', '\\"')
    return (f'// generated by setup.py: how this module was built (read by torchbend.backends._build_config)\n'
            f'extern "C" __attribute__((visibility("default"), used)) const char {symbol}[] = "{text}";\n')


def read_build_info(path: str) -> dict | None:
    """The build info that ``setup.py`` embedded in the library at ``path`` (``None`` if there is none)."""
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError:
        return None
    i = data.find(INFO_MARKER)
    if i < 0:
        return None
    end = data.find(b"\0", i)
    try:
        return json.loads(data[i + len(INFO_MARKER):end if end >= 0 else None].decode())
    except (ValueError, UnicodeDecodeError):
        return None


def find_prebuilt(module: str, expected_hash: str, torch_version: str,
                  cpu_arch: bool = False) -> tuple[str | None, dict | None, str]:
    """``(path, info, "")`` of the installed extension ``module`` (e.g. ``"torchbend._native"``) if it was built
    from the current sources (``expected_hash``) against this torch, else ``(path or None, info, why not)``.
    ``cpu_arch`` (the CPU extension): where ``TORCHBEND_CPU_ARCH`` is set, the installed module must also have
    been built with its instruction-set flag (:func:`cpu_arch_flags`).  The library is only read, not loaded."""
    import importlib.util

    if os.environ.get("TORCHBEND_PREBUILT", "1").strip().lower() in ("0", "no", "false", "off"):
        return None, None, "TORCHBEND_PREBUILT=0"
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError) as e:  # pragma: no cover
        return None, None, f"{type(e).__name__}: {e}"
    if spec is None or not spec.origin or not os.path.exists(spec.origin):
        return None, None, "not installed (built at install time only with --no-build-isolation and a compiler)"
    info = read_build_info(spec.origin)
    if info is None:
        return spec.origin, None, f"{spec.origin} carries no build info"
    if info.get("source_hash") != expected_hash:
        return spec.origin, info, "stale: built from other sources than the ones installed next to it"
    if info.get("torch") != torch_version:
        return spec.origin, info, f"built against torch {info.get('torch')}, running torch {torch_version}"
    if "-march=native" in info.get("cflags", []) and info.get("cpu") != cpu_id():
        return spec.origin, info, f"built with -march=native for another CPU ({info.get('cpu')})"
    if cpu_arch and os.environ.get("TORCHBEND_CPU_ARCH") is not None:
        built = [f for f in info.get("cflags", []) if _is_arch_flag(f)]
        if built != cpu_arch_flags():
            return spec.origin, info, (f"built with {built or 'no -march'}, TORCHBEND_CPU_ARCH asks for "
                                       f"{cpu_arch_flags() or 'no -march'}")
    return spec.origin, info, ""
