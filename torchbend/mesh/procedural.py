"""Procedural triangle meshes for tests, examples and benchmarks.

Every function returns ``(vertices, faces)``: ``vertices`` is a ``(V, 3)`` floating tensor of
positions in metres [m], ``faces`` a ``(F, 3)`` int64 tensor of vertex indices.  Faces are
counter-clockwise about their normal and consistently oriented: the two faces of every interior
edge traverse it in opposite directions.  ``dtype``/``device`` default to torch's defaults.
Pure torch; random scenes draw from a CPU ``torch.Generator`` so they do not depend on the device.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .._checks import integer, positive

__all__ = ["grid", "icosphere", "cylinder", "mannequin", "random_curved_sheet", "single_hinge"]


def _quad_faces(nu: int, nv: int, wrap: bool, device) -> Tensor:
    """Two CCW triangles per cell of a lattice with vertex index ``u + nu * v``.

    The diagonal alternates between neighbouring cells (criss-cross), so the mesh has no preferred
    direction.  With ``wrap`` the ``u`` direction is periodic (a tube).  Returns ``(F, 3)`` int64.
    """
    v, u = torch.meshgrid(
        torch.arange(nv - 1, device=device),
        torch.arange(nu if wrap else nu - 1, device=device),
        indexing="ij",
    )
    a = u + nu * v
    b = (u + 1) % nu + nu * v
    c, d = b + nu, a + nu
    flip = ((u + v) % 2 == 1).unsqueeze(-1)
    first = torch.where(flip, torch.stack((a, b, d), -1), torch.stack((a, b, c), -1))
    second = torch.where(flip, torch.stack((b, c, d), -1), torch.stack((a, c, d), -1))
    return torch.stack((first, second), -2).reshape(-1, 3)


def grid(
    nx: int, ny: int, size: tuple[float, float] = (1.0, 1.0), *, dtype=None, device=None
) -> tuple[Tensor, Tensor]:
    """Flat rectangular cloth ``[0, size[0]] x [0, size[1]]`` [m] in the ``z = 0`` plane.

    ``nx * ny`` vertices, vertex ``(i, j)`` (``i`` along x, ``j`` along y) at index ``i + nx * j``;
    ``2 (nx - 1)(ny - 1)`` faces with alternating diagonals, normals ``+z``.
    Returns ``vertices (nx*ny, 3)`` [m] and ``faces (2(nx-1)(ny-1), 3)`` int64.
    """
    nx, ny = integer(nx, "nx", 2), integer(ny, "ny", 2)
    sx, sy = positive(size[0], "size[0]"), positive(size[1], "size[1]")
    y, x = torch.meshgrid(
        torch.linspace(0, sy, ny, dtype=dtype, device=device),
        torch.linspace(0, sx, nx, dtype=dtype, device=device),
        indexing="ij",
    )
    vertices = torch.stack((x, y, torch.zeros_like(x)), -1).reshape(-1, 3)
    return vertices, _quad_faces(nx, ny, False, vertices.device)


_ICO_FACES = [
    [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
    [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
    [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
    [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
]


def icosphere(
    subdivisions: int, radius: float = 1.0, center=(0.0, 0.0, 0.0), *, dtype=None, device=None
) -> tuple[Tensor, Tensor]:
    """Sphere of ``radius`` [m] about ``center`` [m]: an icosahedron subdivided ``subdivisions`` times.

    Each step splits every triangle into four through its edge midpoints (one shared vertex per
    edge) and projects the new vertices onto the sphere.  Closed manifold with outward normals:
    ``F = 20 * 4**s`` faces, ``E = 3F/2`` edges, ``V = F/2 + 2`` vertices.
    Returns ``vertices (V, 3)`` [m] and ``faces (F, 3)`` int64.
    """
    subdivisions = integer(subdivisions, "subdivisions", 0)
    radius = positive(radius, "radius")
    t = (1 + math.sqrt(5)) / 2
    vertices = torch.tensor(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
         [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        dtype=dtype, device=device,
    )
    vertices = vertices / vertices.norm(dim=-1, keepdim=True)
    faces = torch.tensor(_ICO_FACES, dtype=torch.int64, device=vertices.device)
    for _ in range(subdivisions):
        edges = faces[:, [[0, 1], [1, 2], [2, 0]]].sort(-1).values  # (F, 3, 2) undirected
        # midpoint cache: one new vertex per unique undirected edge
        unique, inverse = torch.unique(edges.reshape(-1, 2), dim=0, return_inverse=True)
        mid = vertices[unique].mean(1)
        mid = mid / mid.norm(dim=-1, keepdim=True)
        m01, m12, m20 = (len(vertices) + inverse.reshape(-1, 3)).unbind(-1)
        a, b, c = faces.unbind(-1)
        faces = torch.stack(
            [torch.stack(f, -1) for f in ((a, m01, m20), (b, m12, m01), (c, m20, m12), (m01, m12, m20))],
            1,
        ).reshape(-1, 3)
        vertices = torch.cat((vertices, mid))
    center = torch.as_tensor(center, dtype=vertices.dtype, device=vertices.device)
    return radius * vertices + center, faces


def cylinder(
    n_around: int, n_along: int, radius: float = 1.0, length: float = 1.0, *, dtype=None, device=None
) -> tuple[Tensor, Tensor]:
    """Open tube of ``radius`` [m] along the z-axis from ``z = 0`` to ``z = length`` [m].

    ``n_around`` vertices per ring, ``n_along`` rings; vertex ``(k, j)`` (``k`` around, ``j`` along)
    at index ``k + n_around * j``; alternating diagonals, outward normals.
    Returns ``vertices (n_around*n_along, 3)`` [m] and ``faces (2 n_around (n_along-1), 3)`` int64.
    """
    n_around, n_along = integer(n_around, "n_around", 3), integer(n_along, "n_along", 2)
    radius, length = positive(radius, "radius"), positive(length, "length")
    dtype = dtype or torch.get_default_dtype()
    z, k = torch.meshgrid(
        torch.linspace(0, length, n_along, dtype=dtype, device=device),
        torch.arange(n_around, dtype=dtype, device=device),
        indexing="ij",
    )
    phi = k * (2 * math.pi / n_around)
    vertices = torch.stack((radius * phi.cos(), radius * phi.sin(), z), -1).reshape(-1, 3)
    return vertices, _quad_faces(n_around, n_along, True, vertices.device)


def mannequin(subdivisions: int = 3, n_around: int = 16, n_along: int = 12, *, hip_center=(0.0, 0.0, -0.12),
              hip_radius: float = 0.175, leg_radius: float = 0.07, legs=(((0.08, 0.0, -0.2), (0.1, 0.0, -0.9)),
                                                                     ((-0.08, 0.0, -0.2), (-0.1, 0.0, -0.9))),
              dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """A simple body of triangles for a skirt to drape on (a :class:`~torchbend.MeshCollider`): the hips, an
    icosphere of ``hip_radius`` [m] at ``hip_center`` [m] (``subdivisions``), and the legs, open tubes of
    ``leg_radius`` [m] (``n_around`` x ``n_along``) along the segments ``legs`` [m], the defaults those of
    ``configs/skirt_drape.yaml``'s sphere and capsules (the waist ring of the shipped skirt at ``z = 0``).  The
    pieces overlap; each is inscribed in its primitive.  Returns ``vertices (Vb, 3)`` [m] and ``faces (Fb, 3)``."""
    dtype = dtype or torch.get_default_dtype()
    parts = [icosphere(subdivisions, hip_radius, hip_center, dtype=dtype, device=device)]
    for a, b in legs:
        a = torch.as_tensor(a, dtype=dtype, device=device)
        b = torch.as_tensor(b, dtype=dtype, device=device)
        axis = b - a
        length = float(axis.norm())
        tube, faces = cylinder(n_around, n_along, leg_radius, length, dtype=dtype, device=device)
        w = axis / length  # the tube's z axis onto the leg, by the rotation taking e_z to w
        ez = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
        v = torch.linalg.cross(ez, w)
        c = float(w @ ez)
        K = torch.tensor([[0.0, -float(v[2]), float(v[1])], [float(v[2]), 0.0, -float(v[0])],
                          [-float(v[1]), float(v[0]), 0.0]], dtype=dtype, device=device)
        R = torch.eye(3, dtype=dtype, device=device) + K + K @ K / (1 + c)  # (w != -e_z for these legs)
        parts.append((tube @ R.T + a, faces))
    vertices, faces, offset = [], [], 0
    for v_, f_ in parts:
        vertices.append(v_)
        faces.append(f_ + offset)
        offset += v_.shape[0]
    return torch.cat(vertices), torch.cat(faces)


def random_curved_sheet(
    nx: int, ny: int, *, amplitude: float = 0.3, seed: int = 0, dtype=None, device=None
) -> tuple[Tensor, Tensor]:
    """Unit-square :func:`grid` with irregular triangles lifted to a smooth random height field.

    Each vertex is moved in-plane by an independent uniform jitter of at most 15% of the grid
    spacing per axis (this keeps every triangle's projected area at least 40% of its unjittered
    value, so none is degenerate or flipped), then lifted to ``z = amplitude * h(x, y)`` [m], where
    ``h`` is a random mix of four plane sinusoids of wavelength 0.5..2 [m] with ``|h| <= 1``.
    Deterministic for a given ``seed`` (independent of ``device``).
    Returns ``vertices (nx*ny, 3)`` [m] and ``faces (2(nx-1)(ny-1), 3)`` int64.
    """
    amplitude = float(amplitude)
    if not math.isfinite(amplitude):
        raise ValueError(f"amplitude must be finite, got {amplitude}")
    vertices, faces = grid(nx, ny, dtype=dtype, device=device)
    gen = torch.Generator().manual_seed(seed)

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=gen, dtype=torch.float64).to(vertices)

    spacing = vertices.new_tensor([1 / (nx - 1), 1 / (ny - 1)])
    xy = vertices[:, :2] + 0.15 * spacing * (2 * rand(len(vertices), 2) - 1)
    n_waves = 4
    frequency = 2 * math.pi * (0.5 + 1.5 * rand(n_waves, 2))  # wave vectors [rad/m]
    phase = 2 * math.pi * rand(n_waves)
    weight = 2 * rand(n_waves) - 1
    weight = weight / weight.abs().sum()
    z = amplitude * (torch.sin(xy @ frequency.T + phase) @ weight)
    return torch.cat((xy, z.unsqueeze(-1)), -1), faces


def single_hinge(theta: float, *, dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """One hinge (two triangles sharing an edge) bent by ``theta`` [rad].

    Vertices: hinge edge ``x0 = (0, 0, 0) -> x1 = (1, 0, 0)``, wing ``x2 = (0.5, 1, 0)`` of
    triangle A ``(0, 1, 2)``, wing ``x3 = (0.5, -cos theta, -sin theta)`` of triangle B ``(1, 0, 3)``
    (``x2`` mirrored across the edge, then rotated about the x-axis).  With
    ``nA = e0 x (x2 - x0)`` and ``nB = (x3 - x1) x e0``, ``atan2(e0_hat . (nA x nB), nA . nB) = theta``:
    zero when flat, positive when B bends away from the normals (``+z`` when flat).
    ``theta`` must lie in ``[-pi, pi]``.  Returns ``vertices (4, 3)`` [m] and ``faces (2, 3)`` int64.
    """
    theta = float(theta)
    if not abs(theta) <= math.pi:
        raise ValueError(f"theta must lie in [-pi, pi], got {theta}")
    vertices = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -math.cos(theta), -math.sin(theta)]],
        dtype=dtype, device=device,
    )
    faces = torch.tensor([[0, 1, 2], [1, 0, 3]], dtype=torch.int64, device=vertices.device)
    return vertices, faces
