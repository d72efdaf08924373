"""Garment-like meshes made by the project, with sewing seams as exported garments have them.

:func:`skirt` builds a flared skirt from two panels whose vertices are duplicated along the side seams (each
panel is one UV island, its UVs the flat sewing pattern in metres), as a garment exported from a pattern
tool arrives; :func:`torchbend.mesh.load` / :func:`torchbend.mesh.clean` weld the seams.  The shipped
``assets/skirt.obj`` is ``skirt()`` with its defaults; regenerate it with ``python -m torchbend.mesh.make_assets``.
"""
from __future__ import annotations

import math
import os

import torch
from torch import Tensor

from .._checks import integer, positive
from .io import ASSETS, save_obj
from .procedural import _quad_faces

__all__ = ["skirt", "write_skirt_asset"]


def skirt(
    n_around: int = 32,
    n_along: int = 12,
    *,
    waist_radius: float = 0.15,
    hem_radius: float = 0.3,
    length: float = 0.4,
    dtype=None,
    device=None,
) -> tuple[Tensor, Tensor, Tensor]:
    """A flared skirt (truncated cone about the z-axis) sewn from a back and a front panel.

    The waist ring (radius ``waist_radius`` [m]) lies at ``z = 0`` (the vertices to pin), the hem ring
    (``hem_radius`` [m]) at ``z = -length`` [m].  Panel 0 (back) spans the angles ``[0, pi]`` (``y >= 0``),
    panel 1 (front) ``[pi, 2 pi]``; the side seams lie at ``x = +-r``, ``y = 0``.  Each panel is a lattice of
    ``n_around / 2 + 1`` columns by ``n_along`` rings with alternating diagonals, so the seam vertices exist
    twice (at identical positions).  Welded, the skirt is a tube with ``n_around * n_along`` vertices, outward
    normals and two boundary loops (waist and hem).

    Returns:
        positions: ``(2 (n_around/2 + 1) n_along, 3)`` [m]; panel ``p``'s vertex (column ``i``, ring ``j``,
            ``j = 0`` at the waist) at index ``p (n_around/2 + 1) n_along + i + (n_around/2 + 1) j``.
        faces: ``(2 n_around (n_along - 1), 3)`` int64, counter-clockwise seen from outside.
        uvs: ``(V, 2)`` [m] the flat sewing pattern: each panel unrolled (an annulus sector, lengths along the
            rulings and the rings preserved), the two islands side by side.
    """
    n_around, n_along = integer(n_around, "n_around", 4), integer(n_along, "n_along", 2)
    if n_around % 2:
        raise ValueError(f"n_around must be even (two equal panels), got {n_around}")
    rw, rh, L = positive(waist_radius, "waist_radius"), positive(hem_radius, "hem_radius"), positive(length, "length")
    if rh < rw:
        raise ValueError(f"hem_radius must be >= waist_radius (a skirt flares), got {rh} < {rw}")
    dtype = dtype or torch.get_default_dtype()
    half = n_around // 2
    cols = half + 1
    t = torch.linspace(0, 1, n_along, dtype=torch.float64)  # 0 at the waist, 1 at the hem
    radius = rw + (rh - rw) * t  # (n_along,)
    z = 0.0 - L * t  # + 0.0: the waist at z = 0, not -0
    # one angle per ring vertex, so the two copies of a seam vertex are bit-identical
    ring = torch.arange(n_around + 1, dtype=torch.float64) % n_around * (2 * math.pi / n_around)
    slant = math.hypot(L, rh - rw)
    positions, uvs, faces = [], [], []
    for p in range(2):
        phi = ring[p * half: p * half + cols]  # (cols,)
        xyz = torch.stack(
            (radius[:, None] * phi.cos(), radius[:, None] * phi.sin(), z[:, None].expand(-1, cols)), -1
        )  # (n_along, cols, 3)
        local = torch.arange(cols, dtype=torch.float64) * (2 * math.pi / n_around) - math.pi / 2  # [-pi/2, pi/2] per panel
        if rh > rw:  # the cone unrolled about its apex: ruling distance s, sector angle local * r / s
            s = rw * slant / (rh - rw) + slant * t  # (n_along,) distance to the apex
            alpha = local[None, :] * (rw / s[0])
            uv = torch.stack((s[:, None] * alpha.sin(), -s[:, None] * alpha.cos()), -1)
            uv[..., 1] += s[0]
        else:  # a cylinder unrolls to a rectangle
            uv = torch.stack((rw * local[None, :].expand(n_along, -1), -slant * t[:, None].expand(-1, cols)), -1)
        uv[..., 0] += p * (2.2 * rh * math.pi / 2 + 0.05)  # the second island beside the first
        positions.append(xyz.reshape(-1, 3))
        uvs.append(uv.reshape(-1, 2))
        faces.append(_quad_faces(cols, n_along, False, None)[:, [0, 2, 1]] + p * cols * n_along)
    return (torch.cat(positions).to(dtype=dtype, device=device), torch.cat(faces).to(device),
            torch.cat(uvs).to(dtype=dtype, device=device))


def write_skirt_asset(path: str | None = None) -> str:
    """Write :func:`skirt` with its defaults as an OBJ (``v``, ``vt``, ``f v/vt``, seams unwelded) to ``path``
    (default: the shipped ``torchbend/mesh/assets/skirt.obj``); returns the path."""
    path = path or os.path.join(ASSETS, "skirt.obj")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    positions, faces, uvs = skirt(dtype=torch.float64)
    save_obj(path, positions, faces, uvs, header=(
        "torchbend skirt: torchbend.mesh.garments.skirt() with its defaults (python -m torchbend.mesh.make_assets)\n"
        "two panels (back, front), vertices duplicated along the two side seams, vt = sewing pattern [m]\n"
        "units: m; waist ring at z = 0 (radius 0.15), hem at z = -0.4 (radius 0.3); weld with torchbend.mesh.load"))
    return path

