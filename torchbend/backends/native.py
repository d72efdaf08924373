r"""Compiled CPU kernels for the per-hinge 12x12 bending Hessians and their sparse assembly.

The eager-PyTorch path (:func:`torchbend.ops.hinge.hinge_energy_hessian_soa`) is a chain of some
hundred elementwise passes over per-hinge arrays; it is memory bound.  This module compiles the whole
computation into one pass over hinges: gather the stencil from the positions, the bend angle (the
``atan2`` formula of :func:`torchbend.hinge_angles`), ``psi'`` and ``psi''`` of the three models with the optional viscous term
(:func:`torchbend.ops.psi.psi_theta_derivatives`), and the closed-form block (the half-hinge factors of
the tech report, sec. 6, and ``H = Y + Y^T`` with the B terms, see :mod:`torchbend.ops.hinge`).
Hinges are processed in tiles of 16 (8 for the blocks) with every quantity stored per lane, so the compiler
vectorizes the formulas across hinges; tiles run in parallel (``at::parallel_for``), blocks are written with
streaming stores.

The C++ sources are in ``torchbend/csrc``: the per-hinge mathematics in ``hinge_math.h`` and ``hinge_ops.h``
(torch-free, compiled for the CUDA driver as well) and the CPU driver, split by role (``cpu_tiles.*``: tiles,
checks, output buffers; ``cpu_first_order.cpp``, ``cpu_second_order.cpp``, ``cpu_blocks.cpp``: the operators;
``cpu_assembly.cpp``; ``cpu_projection.cpp``; ``bending_cpu.cpp``: the Python bindings the functions below call;
``cpu_registration.cpp``: the same operators registered with the dispatcher, ``torch.ops.torchbend.*``; the list is
:data:`torchbend.backends._build_config.NATIVE_SOURCES`).  ``pip install --no-build-isolation .`` (or ``-e .``)
compiles them into ``torchbend._native`` (``setup.py``); :func:`load` (:class:`torchbend.backends._loader.Extension`,
shared with the CUDA driver) uses that module if it was built from the sources installed next to it (their hash
is embedded in it, see :mod:`torchbend.backends._build_config`), and otherwise compiles them on first use with
``torch.utils.cpp_extension.load`` (a few minutes on two cores, then cached in ``TORCH_EXTENSIONS_DIR``; the
name carries the hash of the sources, every header in ``csrc`` and the flags, so an edit of a header rebuilds
too, :func:`extension_name`).  :func:`build_info` says which happened.  ``TORCHBEND_PREBUILT=0`` ignores the
installed module.  Without a working compiler a warning says why, once, and the eager path runs.
Which code runs is decided by :func:`torchbend.backends.select_backend`, never here; the functions below assume
it said ``native``.
"""
from __future__ import annotations

import os
from typing import Any

import torch
from torch import Tensor

from . import _build_config as cfg
from ._loader import Extension
from ._status import raise_for_status
from ._table import MEMBRANE_MODEL_CODE, MEMBRANE_PROJECTION_CODE, PROJECTION_CODE, model_code

__all__ = ["load", "build_error", "build_info", "bending_hessians", "assemble_arrays", "incidence", "bending_energy",
           "bending_gradient", "bending_energy_gradient", "bending_hvp", "bending_second_order", "hinge_angles",
           "project_blocks", "contact_box_pairs", "contact_candidates", "contact_distances", "contact_close",
           "contact_step_bound", "contact_barrier",
           "contact_stencil_sum", "contact_gradient_sum", "contact_hessian_sum", "membrane_blocks", "membrane_assemble", "membrane_energy_gradient", "membrane_hvp",
           "output_cache_info", "empty_output_cache", "set_output_cache_limit"]

PREBUILT = "torchbend._native"
"""The module ``setup.py`` builds at install time."""


def jit_cflags() -> list[str]:
    """The JIT build's compile flags: :data:`torchbend.backends._build_config.NATIVE_CFLAGS` with the
    instruction-set flag of ``TORCHBEND_CPU_ARCH`` (:func:`torchbend.backends._build_config.native_cflags`;
    default ``-march=native``)."""
    return cfg.native_cflags()


def extension_name() -> str:
    """``torchbend_native_<hash>`` (``-march=native``) or ``torchbend_native_<hash>_<arch>`` (``TORCHBEND_CPU_ARCH``,
    e.g. ``_x86_64_v3``, ``_portable``): a short hash of the sources, every header in ``csrc`` and the flags, so
    that any edit rebuilds (``torch.utils.cpp_extension.load`` itself tracks only the ``.cpp`` sources), and the
    instruction set, so that builds for different architectures are cached side by side."""
    tag = cfg.cpu_arch_tag()
    return f"torchbend_native_{cfg.native_source_hash()[:12]}" + ("" if tag == "native" else f"_{tag}")


def _jit_build() -> tuple[Any, dict[str, Any]]:
    from torch.utils.cpp_extension import load as load_extension

    cflags = jit_cflags()
    module = load_extension(
        name=extension_name(), sources=[os.path.join(cfg.CSRC, f) for f in cfg.NATIVE_SOURCES],
        extra_include_paths=[cfg.CSRC], extra_cflags=cflags, extra_ldflags=list(cfg.NATIVE_LDFLAGS), verbose=False)
    return module, {"cflags": cflags, "arch": cfg.cpu_arch_tag(cflags)}


def _install_info(build: dict) -> dict[str, Any]:
    cflags = list(build.get("cflags", []))
    return {"cflags": cflags, "arch": cfg.cpu_arch_tag([f for f in cflags if f.startswith("-march=")])}


def _on_load(module) -> None:
    """Registers the module's operators (``torch.ops.torchbend.*``, ``csrc/cpu_registration.cpp``: explicitly, not at
    import, so that a stale installed module imported directly and the JIT build can share a process), which raise
    the ValueError of a status word through :func:`torchbend.backends._status.raise_for_status`."""
    module.set_status_handler(raise_for_status)
    module.register_operators()


_EXT = Extension("C++ extension", PREBUILT, lambda: cfg.native_source_hash(), _jit_build, cpu_arch=True,
                 install_info=_install_info, warn=True, info_keys=("cflags", "arch"), on_load=_on_load)


_load_prebuilt = _EXT.load_prebuilt  # (torchbend._native, "", found) if installed and current, else (None, why not, found)
load = _EXT.load  # the compiled module, or None if it cannot be built here
build_error = _EXT.build_error  # why it could not be built (None if it was)
build_info = _EXT.build_info
"""How :func:`load` got the module (:meth:`torchbend.backends._loader.Extension.build_info`), with ``cflags`` (the
compile flags of the module in use) and ``arch`` (their instruction set: ``"native"``, ``"portable"`` or e.g.
``"x86_64_v3"``, see ``TORCHBEND_CPU_ARCH``)."""
_module = _EXT.module  # the compiled module, or the RuntimeError saying why not


def bending_hessians(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c, prev, model,
                     out: tuple[Tensor | None, Tensor | None] | None = None, check: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Fused gather + angle + ``psi'``/``psi''`` + blocks for positions ``x: (..., V, 3)``:
    ``(Hb (..., H, 12, 12), g (..., H, 12), psi'' (..., H))``; a folded ``tan`` hinge is the ``ValueError`` of
    :func:`torchbend.ops.psi.check_fold` and, with ``check``, non-finite positions that of
    :func:`torchbend._checks.check_positions` (both detected inside the kernel).  Parameters: scalars or ``(H,)``
    (``prev`` also ``(..., H)`` with x's batch shape); ``c``, ``prev`` ``None`` without damping.

    ``out=(Hb, g)``: buffers to write the blocks and gradients into and return instead of new tensors
    (contiguous, x's dtype, exactly those shapes, not overlapping x; either may be ``None``: a new tensor).  Fresh memory costs the kernel's zeroing of
    every page (a large new output is populated in one pass, ``MADV_POPULATE_WRITE``, instead of a fault a page),
    which for large meshes is about as much as the kernel itself: a caller that asks for the blocks in a loop keeps
    its buffers between the calls (or opts in to the cache of released outputs, :func:`set_output_cache_limit`)."""
    hb, g = (None, None) if out is None else out
    Hb, g, d2, theta, status = _module().bending_hessians(x, hinges, a, k, rest, c, prev, model_code(model), hb, g,
                                                          check)
    if status:
        raise_for_status(status, model, x, theta)
    return Hb, g, d2


def assemble_arrays(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, hinge_blocks: Tensor, faces: Tensor,
                    face_edge_hinges: Tensor, face_edge_signs: Tensor, face_blocks: Tensor, row_len: Tensor, nnz: int,
                    per_triangle: bool, out: Tensor | None = None) -> Tensor:
    """CSR values ``(nnz,)`` of the (unprojected) Hessian of one mesh ``x: (V, 3)``, assembled per hinge or per
    triangle in C++ (serial: the scatter targets overlap) into the pattern of
    :class:`torchbend.energies.sparse.HessianPattern` (its ``hinge_blocks``, ``face_blocks``, ``row_len``, ``nnz``)
    over the topology's ``faces``, ``face_edge_hinges`` and ``face_edge_signs``; a folded ``tan`` hinge is a
    ``ValueError`` as in :func:`bending_hessians`.

    ``out``: a buffer to write the values into and return instead of a new tensor (every entry is written: its
    contents do not matter), a contiguous ``(nnz,)`` tensor of x's dtype and device, not overlapping x (else a
    ``ValueError`` naming ``out``); kept by a caller between calls, it saves the first-touch page faults of fresh
    memory (10 % of the assembly at 1e6 hinges; nothing measurable at 1e5, whose 25 MiB of values malloc reuses:
    benchmarks/results/throughput_outbuffers_2026-12-02.txt)."""
    values, theta, status = _module().assemble(
        x, hinges, a, k, rest, c, prev, model_code(model), hinge_blocks, faces, face_edge_hinges, face_edge_signs,
        face_blocks, row_len, nnz, per_triangle, out)
    if status:
        raise_for_status(status, model, x, theta)
    return values


def project_blocks(M: Tensor, mode: str, hinge: bool = False) -> Tensor:
    """The PSD projection of symmetric blocks ``M (..., n, n)``, ``n`` 9 or 12, float32 or float64:
    ``Q max(L, 0) Q^T`` (``"clamp"``; ``"abs"``: ``Q |L| Q^T``) of ``(M + M^T) / 2``, by cyclic Jacobi vectorized
    across blocks (the C++ counterpart of :func:`torchbend.ops.projection.project_blocks`).  ``hinge``: 12x12
    blocks of four vertices, invariant under translations (hinge blocks), are projected in the 9-dimensional
    complement of the translations (the same matrix, 0.42 of the work); ``"reduced"`` (hinge blocks only) is that
    function's structured projection."""
    return _module().project_blocks(M, PROJECTION_CODE[mode], hinge)


def contact_box_pairs(lo_a: Tensor, hi_a: Tensor, lo_b: Tensor, hi_b: Tensor, pad: float, upper: bool = False,
                      ids_a: Tensor | None = None, ids_b: Tensor | None = None) -> Tensor:
    """Index pairs ``(K, 2)`` of boxes ``(lo, hi)`` of A and B (``(n, 3)`` each) that overlap when each is padded by
    ``pad``: a uniform grid of cells about B's mean box plus ``2 pad`` wide (a dense table, hashed where sparse),
    each box of B filed under every cell it covers and each box of A tested against those of its cells, each pair
    in the first cell the two share (cost: the boxes' cells and the pairs; long boxes do not enlarge the cells).
    ``upper`` (A = B): pairs ``a < b`` only; ``ids_a (Na, ka)``, ``ids_b (Nb, kb)`` (int64): pairs whose rows share
    a value are left out.  Each box's partners in increasing order."""
    none = torch.zeros(0, 0, dtype=torch.int64)
    return _module().contact_box_pairs(lo_a, hi_a, lo_b, hi_b, float(pad), bool(upper),
                                       none if ids_a is None else ids_a, none if ids_b is None else ids_b)


def contact_candidates(lo: Tensor, hi: Tensor, faces: Tensor, edges: Tensor, radius: float
                       ) -> tuple[Tensor, Tensor, Tensor]:
    """``(point-triangle stencils (P, 4), edge-edge stencils (Q, 4), their edges' indices (Q, 2))`` of a mesh over
    its vertices' boxes ``lo``, ``hi`` ``(V, 3)``: each vertex against each face without it and each edge against
    each later edge that shares no vertex with it, whose boxes (a primitive's holds its vertices') come within
    ``radius``; each vertex's and edge's partners in order (:func:`contact_box_pairs` twice, in one call)."""
    return _module().contact_candidates(lo, hi, faces, edges, float(radius))


def contact_distances(x: Tensor, stencils: Tensor, edge_edge: bool) -> tuple[Tensor, Tensor]:
    """``(types (N,) int64, squared distances (N,))`` of point-triangle (``p, t0, t1, t2``) or edge-edge
    (``a0, a1, b0, b1``) stencils ``(N, 4)`` over the points ``x (n, 3)``: the compiled
    :func:`torchbend.ops.distance.point_triangle_type` / ``edge_edge_type`` and ``typed_distance_sq``."""
    return _module().contact_distances(x, stencils, bool(edge_edge))


def contact_close(x: Tensor, stencils: Tensor, edge_edge: bool, dhat_sq: float) -> tuple[Tensor, Tensor]:
    """``(index (K,), types (K,))``: the stencils ``(N, 4)`` (point-triangle or edge-edge) closer than
    ``sqrt(dhat_sq)`` and their distance types, in order (every candidate typed over lanes, the types the scalar
    classifier's bit for bit)."""
    return _module().contact_close(x, stencils, bool(edge_edge), float(dhat_sq))


def contact_step_bound(x: Tensor, stencils: Tensor, edge_edge: bool, move: Tensor, dhat: float = 0.0) -> float:
    """The conservative step bound of point-triangle or edge-edge stencils ``(N, 4)`` over the points ``x (n, 3)``
    that move along a step: ``min(1, 0.9 d / (m_A + m_B))`` over the stencils (``d`` the distance; with ``move (n,)``
    each point's largest move, ``m_A``, ``m_B`` the largest of each side; with ``move (n, 3)`` each point's
    displacement, ``m_A``, ``m_B`` the largest of each side's displacements less the stencil's mean, which no
    distance depends on, or of the displacements themselves where their sum is smaller;
    :meth:`torchbend.SelfContact.max_step`); stencils whose boxes' gap alone bounds them above
    the smallest so far are not measured.  With displacements and ``dhat > 0`` a stencil whose bound binds advances
    on from the distance it reached (conservative advancement, :func:`torchbend.sim.self_contact._advance`)."""
    return float(_module().contact_step_bound(x, stencils, bool(edge_edge), move, float(dhat)))


def contact_barrier(x: Tensor, stencils: Tensor, types: Tensor, eps: Tensor | None, dhat_sq: float, kappa: float,
                    want: int = 2, projection: str = "none") -> tuple[Tensor, Tensor, Tensor]:
    """``(E (N,), g (N, 12), H (N, 12, 12))``: IPC's barrier ``b(D)`` (times the mollifier of an edge-edge pair,
    ``eps (N,)`` its thresholds; None for point-triangle stencils) of stencils ``(N, 4)`` of the given distance
    types, with its gradient (``want >= 1``, else an empty tensor) and Hessian (``want >= 2``) in the stencil's
    12 coordinates, closed form; ``projection`` ``"clamp"`` or ``"abs"``: the Hessians projected to PSD in each
    type's reduced coordinates (a 3x3, 6x6 or 9x9 eigenproblem: Householder tridiagonalization and implicit QL, ``cpu_symeig.h``).  ``D <= 0``: ``E = inf``, zero
    derivatives."""
    mode = {"none": -1, "clamp": 0, "abs": 1}[projection]
    e = torch.zeros(0, dtype=x.dtype) if eps is None else eps
    return _module().contact_barrier(x, stencils, types, e, float(dhat_sq), float(kappa), int(want), mode)


def _coo(indices: Tensor, values: Tensor, V: int) -> Tensor:
    return torch.sparse_coo_tensor(indices, values, (3 * V, 3 * V), is_coalesced=True, check_invariants=False)


def contact_stencil_sum(stencils: Tensor, H: Tensor, V: int) -> Tensor:
    """The ``(3V, 3V)`` torch sparse COO (coalesced, row-major) sum of 12x12 blocks ``H (M, 12, 12)`` of
    four-vertex stencils ``(M, 4)`` (entry ``(3 a + p, 3 b + q)``: vertices ``stencils[a]``, ``stencils[b]``);
    vertices ``>= V`` are left out; the blocks of one vertex pair are added in stencil order
    (:func:`torchbend.sim.self_contact.stencil_sum`, compiled)."""
    indices, values = _module().contact_stencil_sum(stencils, H, int(V))
    return _coo(indices, values, V)


def contact_gradient_sum(x: Tensor, stencils: Tensor, types: Tensor, eps: Tensor | None, dhat_sq: float,
                         kappa: float) -> Tensor:
    """``(n, 3)``: the sum over the points ``x (n, 3)`` of the gradients of :func:`contact_barrier` (``want=1``),
    added in stencil order; a point-point or point-edge contact found by several stencils (a vertex near an edge:
    the triangles at the edge and the edges at the vertex) computed once and counted as many times."""
    e = torch.zeros(0, dtype=x.dtype) if eps is None else eps
    return _module().contact_gradient_sum(x, stencils, types, e, float(dhat_sq), float(kappa))


def contact_hessian_sum(x: Tensor, stencils: Tensor, types: Tensor, eps: Tensor | None, dhat_sq: float,
                        kappa: float, projection: str, V: int,
                        friction: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
    """:func:`contact_stencil_sum` of the Hessians of :func:`contact_barrier` (``want=2``, ``projection``), each
    pair's added from its reduced coordinates without forming its 12x12 block; ``friction = (stencils (M, 4),
    w (M, 4), H (M, 3, 3))``: friction pairs whose 12x12 blocks are ``w w^T (x) H``, added after the barrier's
    (in stencil order, as :func:`contact_stencil_sum` of the barrier's blocks and theirs concatenated).  Its
    pattern leaves out the zero blocks of corners a pair's energy does not depend on (a point-edge pair's fourth
    corner, a point-point pair's other two): the same matrix with fewer stored zeros."""
    mode = {"none": -1, "clamp": 0, "abs": 1}[projection]
    e = torch.zeros(0, dtype=x.dtype) if eps is None else eps
    if friction is None:
        friction = (stencils.new_zeros(0, 4), x.new_zeros(0, 4), x.new_zeros(0, 3, 3))
    indices, values = _module().contact_hessian_sum(x, stencils, types, e, float(dhat_sq), float(kappa), mode, int(V),
                                                    *friction)
    return _coo(indices, values, V)


def membrane_blocks(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor, model: str,
                    projection: str = "none") -> tuple[Tensor, bool]:
    """``(H, finite)``: the Hessian of each triangle of each sample, ``H (..., T, 9, 9)`` [N/m] (flat index ``3 k + i``: vertex ``k``,
    axis ``i``), of positions ``x (..., V, 3)``, its eigenvalues in ``f = vec(F)`` projected (``projection``:
    ``"none"``, ``"clamp"``, ``"abs"``): :meth:`torchbend.MembraneEnergy.element_hessians`, compiled (StVK unprojected
    in closed form, the rest through the closed-form eigensystem).  ``faces (T, 3)``, ``D (T, 3, 2)``, ``coef = A t
    (T,)`` [m^3], one ``mu`` and ``lam`` [Pa]; ``model`` a :class:`torchbend.ops.membrane.MembraneModel` value;
    ``finite``: whether every entry is (checked in the kernel, on each block as it is written)."""
    return _module().membrane_blocks(x, faces, D, coef, mu, lam, MEMBRANE_MODEL_CODE[model],
                                     MEMBRANE_PROJECTION_CODE[projection])


def membrane_assemble(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor, model: str,
                      projection: str, blocks: Tensor, row_len: Tensor, nnz: int) -> Tensor | None:
    """The CSR values ``(nnz,)`` of the (projected) membrane Hessian of one mesh ``x (V, 3)``: the blocks of
    :func:`membrane_blocks` added in face order, in cached chunks instead of a ``(T, 9, 9)`` tensor, entry
    ``(3 k + i, 3 l + j)`` of a triangle at ``blocks[t, 3 k + l] + i row_len[faces[t, k]] + j`` (the layout of
    :class:`torchbend.energies.sparse.StencilPattern`); ``None`` where a value is not finite."""
    values = _module().membrane_assemble(x, faces, D, coef, mu, lam, MEMBRANE_MODEL_CODE[model],
                                         MEMBRANE_PROJECTION_CODE[projection], blocks, row_len, nnz)
    return values if values.numel() == nnz else None


def membrane_energy_gradient(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor,
                             weight: Tensor | None, model: str = "stvk") -> tuple[Tensor, Tensor | None]:
    """The membrane energy ``sum_T coef psi`` [J] of ``x (..., V, 3)`` per sample, ``(...,)``, and with ``weight`` (one
    value per sample, flat ``(B,)``) ``weight dE/dx (..., V, 3)`` [N], else ``None`` (arguments as in
    :func:`membrane_blocks`).  Sums in face order (deterministic)."""
    w = x.new_zeros(0) if weight is None else weight
    E, g = _module().membrane_energy_gradient(x, faces, D, coef, mu, lam, w, weight is not None,
                                              MEMBRANE_MODEL_CODE[model])
    return E, (None if weight is None else g)


def membrane_hvp(x: Tensor, v: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor,
                 weight: Tensor, model: str = "stvk", projection: str = "none") -> tuple[Tensor, Tensor]:
    """``(weight H v (..., V, 3) [N], dE/dx . v (...,) [J])``: the (projected) Hessian-vector product of the membrane
    energy (arguments as in :func:`membrane_blocks`; ``weight`` one value per sample, flat ``(B,)``)."""
    return _module().membrane_hvp(x, v, faces, D, coef, mu, lam, weight, MEMBRANE_MODEL_CODE[model],
                                  MEMBRANE_PROJECTION_CODE[projection])


def output_cache_info() -> dict[str, int]:
    """The opt-in cache of large outputs (4 MiB or more: the per-hinge blocks, projected blocks and assembled values
    of big meshes): memory of released outputs kept, outside PyTorch's allocator, for the next outputs of the same
    size, so that repeated calls write into warm pages instead of fresh memory, which the operating system zeroes
    first (the blocks of 1e5 hinges took 2.5x the time without it, benchmarks/results/backends_registration.txt; 1.5x
    since fresh outputs are populated in one pass).  Off by default (``limit`` 0: every output is a plain tensor of
    PyTorch's allocator, large ones advised to transparent huge pages and populated before the kernel writes them); ``TORCHBEND_OUTPUT_CACHE_MB`` megabytes at start-up or :func:`set_output_cache_limit`
    turn it on.  ``{"blocks", "bytes", "hits", "misses", "limit"}``: at most 4 blocks and ``limit`` bytes are kept
    (the blocks of a million hinges take 1.15 GB in float64); :func:`empty_output_cache` frees them."""
    blocks, nbytes, hits, misses, limit = _module().output_cache_info()
    return {"blocks": blocks, "bytes": nbytes, "hits": hits, "misses": misses, "limit": limit}


def empty_output_cache() -> None:
    """Free the memory held by the cache of large outputs (:func:`output_cache_info`)."""
    module = load()
    if module is not None:
        module.empty_output_cache()


def set_output_cache_limit(megabytes: float) -> None:
    """Turn the cache of large outputs on with at most ``megabytes`` kept (:func:`output_cache_info`), or off with 0
    (the default: outputs take fresh memory of PyTorch's allocator)."""
    _module().set_output_cache_limit(int(megabytes * 2**20))


def incidence(hinges: Tensor, vertex_count: int) -> tuple[Tensor, Tensor]:
    """Vertex -> stencil-slot incidence lists of ``hinges (H, 4)``: ``(ptr (V+1,), idx (4H,))`` with the entries
    ``4 h + slot`` of vertex ``v`` in ``idx[ptr[v]:ptr[v+1]]`` (the compiled gradient and products sum per
    vertex through them when the hinges are in no compact order; hinges in topology order are summed in
    blocks of consecutive hinges instead: deterministic either way, no two threads writing one vertex)."""
    import torch

    flat = hinges.reshape(-1)
    idx = torch.argsort(flat, stable=True)
    ptr = torch.zeros(vertex_count + 1, dtype=torch.int64, device=hinges.device)
    ptr[1:] = torch.cumsum(torch.bincount(flat, minlength=vertex_count), 0)
    return ptr, idx


def bending_energy(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, check: bool = False) -> Tensor:
    """Per-hinge energies ``psi (..., H)`` in one compiled pass (folded ``tan`` hinges: ``ValueError``; with
    ``check`` also non-finite positions, both detected inside the kernel)."""
    psi, theta, status = _module().bending_energy(x, hinges, a, k, rest, c, prev, model_code(model), check)
    if status:
        raise_for_status(status, model, x, theta)
    return psi


def bending_gradient(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, weight: Tensor, inc, params: bool,
                     check: bool = False):
    """``(w dE/dx (..., V, 3), w dpsi/d(k, rest, c, prev) (..., H, 4) or None)`` with the per-hinge weight ``w``
    (checks as :func:`bending_energy`)."""
    gx, gp, theta, status = _module().bending_gradient(x, hinges, a, k, rest, c, prev, model_code(model), weight,
                                                       inc[0], inc[1], params, check)
    if status:
        raise_for_status(status, model, x, theta)
    return gx, (gp if params else None)


def bending_energy_gradient(x: Tensor, hinges: Tensor, a, k, rest, c, prev, model, inc, params: bool,
                            check: bool = False):
    """``(psi (..., H), dE/dx (..., V, 3), dpsi/d(k, rest, c, prev) (..., H, 4) or None)`` in one compiled pass:
    the per-hinge energies and the unweighted gradients (checks as :func:`bending_energy`)."""
    psi, gx, gp, theta, status = _module().bending_energy_gradient(x, hinges, a, k, rest, c, prev, model_code(model),
                                                                   inc[0], inc[1], params, check)
    if status:
        raise_for_status(status, model, x, theta)
    return psi, gx, (gp if params else None)


def bending_hvp(x: Tensor, v: Tensor, hinges: Tensor, a, k, rest, c, prev, model, weight: Tensor, inc,
                check: bool = False) -> Tensor:
    """``w H v (..., V, 3)``: the closed-form Hessian of the energy applied to ``v`` (no matrix stored); with
    ``check``, non-finite ``x`` or ``v`` are the ``ValueError`` of :mod:`torchbend._checks`."""
    hv, theta, status = _module().bending_hvp(x, v, hinges, a, k, rest, c, prev, model_code(model), weight, inc[0],
                                              inc[1], check)
    if status:
        raise_for_status(status, model, x, theta, v)
    return hv


def bending_second_order(x: Tensor, v: Tensor | None, t: Tensor | None, hinges: Tensor, a, k, rest, c, prev, model,
                         weight: Tensor, inc) -> tuple[Tensor, Tensor, Tensor]:
    """The general double backward in one compiled pass: ``(dx (..., V, 3), dp (..., H, 4), dg (..., H))``.

    Per hinge, with ``u = g . v`` (``g = d theta/d x``) and ``z = Hess_p(psi) (u, t_k, t_rest, t_c, t_prev)``
    (``p = (theta, k, rest, c, prev)``): ``dx = sum_h w (z_theta g + psi' H_theta v)``, ``dp = w z_(k, rest, c, prev)``
    and ``dg = grad_p(psi) . (u, t)`` (unweighted): what :func:`torchbend.energies._bending_fn._second_order`
    computes without a tangent of the cotangent.  ``v``: directions in ``x`` or ``None``; ``t``: ``(..., H, 4)`` (or
    ``(H, 4)``) directions in the per-hinge ``(k, rest, c, prev)`` or ``None``; ``weight``: the per-hinge cotangent
    ``w`` (one value, ``(H,)`` or ``(..., H)``).  Without damping the ``c``, ``prev`` columns of ``dp`` are zero (and
    those of ``t`` ignored).  A folded ``tan`` hinge is a ``ValueError``."""
    dx, dp, dg, theta, status = _module().bending_second_order(x, v, t, hinges, a, k, rest, c, prev,
                                                               model_code(model), weight, inc[0], inc[1])
    if status:
        raise_for_status(status, model, x, theta)
    return dx, dp, dg


def hinge_angles(x: Tensor, hinges: Tensor) -> Tensor:
    """Bend angles ``(..., H)`` as the compiled energy computes them (the same instructions)."""
    zero = x.new_zeros(1)
    return _module().bending_energy(x.detach(), hinges, zero, zero, zero, None, None, 0, False)[1]
