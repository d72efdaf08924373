"""Check that the CPU kernels' hot lane loops vectorize for a given instruction set (default ``x86-64-v3``:
AVX2 + FMA, the widest vectors of every x86-64 CPU sold since 2015).

The kernels are written as loops over the lanes of a tile of hinges (``TB_LANES`` in ``csrc/vector_math.h``);
their speed depends on GCC vectorizing those loops, which a harmless-looking edit (a branch the compiler
cannot if-convert, a call it cannot inline, a dropped flag) silently undoes.  With AVX-512 the compiler can
if-convert almost anything with masked instructions; with AVX2 it needs ``-fno-trapping-math`` and
branch-free code, so AVX2 is where a loss shows first.

The check compiles the hot translation units with the extension's own flags
(:data:`torchbend.backends._build_config.NATIVE_CFLAGS`, the ``-march`` replaced by ``--arch``), reads GCC's
vectorization report (``-fopt-info-vec-optimized``), maps each vectorized loop to the function of
``csrc`` that contains it, and fails unless every function of :data:`REQUIRED` has a loop vectorized with
vectors of at least ``--min-bytes`` bytes (32 for AVX2: four doubles).  Run by ``.ci/run``; takes about a
minute on two cores.  ``--list`` prints what vectorized (to update :data:`REQUIRED` after a deliberate
change).

    python tools/check_vectorization.py [--arch x86-64-v3] [--list]
"""
from __future__ import annotations

import argparse
import concurrent.futures
import os
import re
import subprocess
import sys
import sysconfig
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from torchbend.backends import _build_config as cfg  # noqa: E402  (standard library only)

# translation unit -> csrc function -> how many of its loops must vectorize: the tile kernels of every
# operator (angle and energy, half-hinges, gradient, HVP, per-hinge blocks, projection, the assembly's angles and
# face blocks; theta_tile's three loops and the full half_tile's two: split for the out-of-order window, see
# csrc/hinge_ops.h), the scatters, and the contact projection (cpu_contact.cpp and cpu_contact_sum.cpp: the tridiagonal
# QL over lanes and the products of the normal frame's projection, cpu_contact_lanes.h; the close-pair search's typing lanes and the pairs' energy lanes, cpu_contact_scan.h).
# x86-64-v3 and x86-64-v4 builds vectorize the same loops (GCC 12.2, 2026-12); ``--list`` prints the counts.
# Loops are counted by source line: half_tile's short form (the angle gradient's) is its full form's first loop, so
# a translation unit with both forms (cpu_assembly.cpp) counts 2; the short form alone is checked in cpu_first_order.cpp.
REQUIRED: dict[str, dict[str, int]] = {
    "cpu_first_order.cpp": {"theta_tile": 3, "halves_tile": 1, "half_tile": 1, "grad_of_halves": 1,
                            "bending_energy": 1, "gradient_pass": 1, "scatter_tiles": 2},
    "cpu_second_order.cpp": {"theta_tile": 3, "halves_tile": 1, "half_tile": 2, "grad_of_halves": 1,
                             "hvp_of_halves": 2, "dot_tile": 1, "bending_hvp": 1, "bending_second_order": 1,
                             "scatter_tiles": 2},
    "cpu_blocks.cpp": {"theta_tile": 3, "halves_tile": 1, "half_tile": 2, "block_lane": 1, "block_tile": 7,
                       "complete_tile": 2, "hessian_tiles": 2},
    "cpu_projection.cpp": {"project_hinge_tile": 6, "jacobi_project": 5, "lanes_scale": 1, "lanes_rebuild": 3},
    "cpu_contact.cpp": {"ql_project": 14, "lanes_scale": 2, "lanes_rebuild": 3, "frame_group": 4,
                        "ee_close_lanes": 1, "pt_close_lanes": 1, "energy_lanes": 1},
    "cpu_contact_sum.cpp": {"ql_project": 14, "lanes_scale": 2, "lanes_rebuild": 3, "frame_group": 4},
    "cpu_assembly.cpp": {"theta_tile": 3, "half_tile": 2, "grad_of_halves": 1, "block_tile": 7, "face_block_tile": 3},
    "cpu_membrane.cpp": {"stress_tile": 2, "hvp_tile": 1, "block_tile": 1},
}
# Template lane loops whose every instantiation must vectorize: translation unit -> function -> how many vectorized
# instances of its loops (one report per instantiation): the membrane's stress tile (energy and forces: 2 loops x
# 3 models x 2 dtypes), HVP and block tiles (4 models x 3 projections x 2 dtypes each); the contact's
# point-triangle typing and energy lanes (2 dtypes each).  A loop that vectorizes for
# one model but not another counts once in REQUIRED; here the lost instance shows.
INSTANCES: dict[str, dict[str, int]] = {
    "cpu_membrane.cpp": {"stress_tile": 12, "hvp_tile": 24, "block_tile": 24},
    "cpu_contact.cpp": {"pt_close_lanes": 2, "energy_lanes": 2},
}

_REPORT = re.compile(r"^(?P<file>[^:\s]+):(?P<line>\d+):\d+: optimized: loop vectorized using (?P<bytes>\d+) byte vectors")
_DEF = re.compile(r"^(?:template\s*<[^>]*>\s*)?(?!namespace|template|struct|class|using|typedef|return|#|//|\}|\{)[A-Za-z_][^;=]*?\b(?P<name>~?[A-Za-z_]\w*)\s*\(")


def enclosing_functions(path: str) -> list[str]:
    """For each line of a C++ source (index = line number - 1), the top-level function it lies in: the
    nearest definition at column 0 above it (the sources do not indent namespaces)."""
    names, current = [], ""
    with open(path) as fh:
        for line in fh:
            m = _DEF.match(line)
            if m and not line.rstrip().endswith(";"):
                current = m.group("name")
            names.append(current)
    return names


def compile_flags(arch: str) -> list[str]:
    import torch.utils.cpp_extension as ext  # the headers of the torch the extension builds against

    flags = [f for f in cfg.NATIVE_CFLAGS if not f.startswith(("-march=", "-mtune="))]
    includes = [f"-I{p}" for p in ext.include_paths()] + [f"-I{sysconfig.get_paths()['include']}"]
    return ["-std=c++17", "-fPIC", "-g0", "-fno-wrapv", f"-march={arch}", *flags, *includes,
            "-DTORCH_EXTENSION_NAME=torchbend_vectorization_check", "-w"]


def vectorized(source: str, arch: str, workdir: str, compiler: str) -> list[tuple[str, int, int]]:
    """(file, line, vector bytes) of every loop GCC vectorized in one translation unit."""
    report = os.path.join(workdir, source + ".vec")
    cmd = [compiler, *compile_flags(arch), f"-fopt-info-vec-optimized={report}", "-c",
           os.path.join(cfg.CSRC, source), "-o", os.path.join(workdir, source + ".o")]
    subprocess.run(cmd, check=True, cwd=cfg.CSRC)
    out = []
    with open(report) as fh:
        for line in fh:
            m = _REPORT.match(line)
            if m:
                out.append((os.path.basename(m.group("file")), int(m.group("line")), int(m.group("bytes"))))
    return out


def functions_vectorized(loops: list[tuple[str, int, int]], min_bytes: int,
                         instances: bool = False) -> dict[str, int]:
    """csrc function -> how many distinct source loops of it vectorized (loops inlined into several callers
    count once; loops narrower than min_bytes are ignored); with ``instances``, how many vectorization reports
    its loops have (one per template instantiation and inlined copy)."""
    cache: dict[str, list[str]] = {}
    seen: dict[str, set[tuple[str, int]]] = {}
    reports: dict[str, int] = {}
    for f, line, nbytes in loops:
        path = os.path.join(cfg.CSRC, f)
        if not os.path.exists(path) or nbytes < min_bytes:
            continue
        if f not in cache:
            cache[f] = enclosing_functions(path)
        name = cache[f][line - 1] if line - 1 < len(cache[f]) else ""
        if name:
            seen.setdefault(name, set()).add((f, line))
            reports[name] = reports.get(name, 0) + 1
    return reports if instances else {name: len(lines) for name, lines in seen.items()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    p.add_argument("--arch", default="x86-64-v3", help="-march value to check (default: x86-64-v3)")
    p.add_argument("--min-bytes", type=int, default=32, help="narrowest vectors that count (default: 32, AVX2)")
    p.add_argument("--list", action="store_true", help="print every function with a vectorized loop")
    p.add_argument("--compiler", default=os.environ.get("CXX", "g++"))
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    args = p.parse_args(argv)
    missing = []
    with tempfile.TemporaryDirectory() as tmp, concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
        jobs = {tu: pool.submit(vectorized, tu, args.arch, tmp, args.compiler) for tu in REQUIRED}
        for tu, job in jobs.items():
            found = functions_vectorized(job.result(), args.min_bytes)
            lost = [f"{name} ({found.get(name, 0)} of {n} loops)" for name, n in sorted(REQUIRED[tu].items())
                    if found.get(name, 0) < n]
            counted = functions_vectorized(job.result(), args.min_bytes, instances=True)
            lost += [f"{name} ({counted.get(name, 0)} of {n} instances)"
                     for name, n in sorted(INSTANCES.get(tu, {}).items()) if counted.get(name, 0) < n]
            missing += [f"{tu}: {name}" for name in lost]
            print(f"{tu} (-march={args.arch}): {len(found)} functions with loops vectorized in "
                  f">= {args.min_bytes}-byte vectors" + (f"; NOT vectorized: {', '.join(lost)}" if lost else ""))
            if args.list:
                for name, count in sorted(found.items()):
                    print(f"    {name}: {count} loop{'s' if count > 1 else ''}")
    if missing:
        print("vectorization check FAILED: these kernel loops no longer vectorize for "
              f"-march={args.arch}:\n  " + "\n  ".join(missing), file=sys.stderr)
        return 1
    print("vectorization check passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
