"""Snapshots (matplotlib, headless): cloth meshes with every collider drawn.

Spheres and capsules (static ones and robot link capsules, in world space) as wireframes, planes (a
table, the ground) as a translucent square around the cloth; axes with equal scale on x, y and z, so
spheres look round and gaps read true.  Needs matplotlib (the ``scenes``/``train`` extras).
"""
from __future__ import annotations

import numpy as np
import torch

from .._extras import require
from ..energies import Capsule, Plane, Sphere

__all__ = ["snapshot", "draw_mesh", "draw_colliders"]


def _np(v) -> np.ndarray:
    return torch.as_tensor(v).detach().cpu().double().numpy() if not isinstance(v, np.ndarray) else v


def draw_mesh(ax, x, faces, color: str = "tab:blue", alpha: float = 0.9) -> np.ndarray:
    """Draw one triangle mesh ``x (V, 3)``, ``faces (F, 3)`` (opacity ``alpha``); returns its points ``(V, 3)``."""
    p = _np(x)
    ax.plot_trisurf(p[:, 0], p[:, 1], p[:, 2], triangles=_np(faces).astype(np.int64), color=color,
                    edgecolor="k", linewidth=0.1, alpha=alpha)
    return p


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to ``n`` and to each other."""
    n = n / np.linalg.norm(n)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _sphere_points(center, radius: float, n: int = 24) -> np.ndarray:
    u, v = np.mgrid[0 : 2 * np.pi : complex(0, n + 1), 0 : np.pi : complex(0, n // 2 + 1)]
    d = np.stack((np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)), -1)
    return np.asarray(center) + radius * d


def _capsule_points(a, b, radius: float, n: int = 24) -> np.ndarray:
    """A capsule's surface as a ``(n + 1, m, 3)`` grid: hemisphere at ``a``, cylinder, hemisphere at ``b``."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    axis = b - a
    length = float(np.linalg.norm(axis))
    d = axis / length if length > 0 else np.array([0.0, 0.0, 1.0])
    e1, e2 = _basis(d)
    lat = np.concatenate((np.linspace(-np.pi / 2, 0, n // 4 + 1), np.linspace(0, np.pi / 2, n // 4 + 1)))
    ends = np.concatenate((np.zeros(n // 4 + 1), np.ones(n // 4 + 1)))
    u = np.linspace(0, 2 * np.pi, n + 1)
    ring = np.cos(u)[:, None, None] * e1 + np.sin(u)[:, None, None] * e2  # (n+1, 1, 3)
    centers = a + ends[None, :, None] * axis  # (1, m, 3)
    return centers + radius * (np.cos(lat)[None, :, None] * ring + np.sin(lat)[None, :, None] * d)


def draw_colliders(ax, colliders, bounds: np.ndarray) -> list[np.ndarray]:
    """Draw spheres, capsules and planes; ``bounds (2, 3)`` (min, max corner of the cloth) sizes the
    plane patches.  Returns the drawn points (for the axis limits)."""
    center = bounds.mean(0)
    half = 0.6 * max(float((bounds[1] - bounds[0]).max()), 1e-3)
    drawn = []
    for c in colliders:
        if isinstance(c, Sphere):
            p = _sphere_points(c.center, c.radius)
            ax.plot_wireframe(p[..., 0], p[..., 1], p[..., 2], color="tab:red", linewidth=0.4)
        elif isinstance(c, Capsule):
            p = _capsule_points(c.a, c.b, c.radius)
            ax.plot_wireframe(p[..., 0], p[..., 1], p[..., 2], color="tab:gray", linewidth=0.4)
        elif isinstance(c, Plane):
            n = np.asarray(c.normal, dtype=float)
            n /= np.linalg.norm(n)
            o = center - np.dot(center - np.asarray(c.point), n) * n  # the cloth's centre projected
            u, w = _basis(n)
            s = np.array([-half, half])
            p = o + s[:, None, None] * u + s[None, :, None] * w
            ax.plot_surface(p[..., 0], p[..., 1], p[..., 2], color="tab:brown", alpha=0.25, linewidth=0)
            loop = p[[0, 0, 1, 1, 0], [0, 1, 1, 0, 0]]
            ax.plot(loop[:, 0], loop[:, 1], loop[:, 2], color="tab:brown", linewidth=0.8)
        else:
            continue
        drawn.append(p.reshape(-1, 3))
    return drawn


def _equal_limits(ax, points: list[np.ndarray]) -> None:
    p = np.concatenate(points)
    lo, hi = p.min(0), p.max(0)
    mid, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6)
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))


def snapshot(path: str, panels, *, titles=None, size: float = 5.0, dpi: int = 100, views=(None,),
             alpha: float = 0.9) -> None:
    """Write a PNG of ``panels``: a list of ``(meshes, colliders)``, one 3D view each, with
    ``meshes`` a list of ``(x (V, 3), faces (F, 3))`` and ``colliders`` torchbend colliders.
    ``views``: one row of panels per entry, ``(elevation, azimuth)`` [degrees] or ``None``
    (matplotlib's default view); ``alpha``: the meshes' opacity (below 1 shows colliders behind them)."""
    matplotlib = require("matplotlib", "plotting")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    views = list(views)
    fig = plt.figure(figsize=(size * len(panels), size * len(views)))
    for row, view in enumerate(views):
        for i, (meshes, colliders) in enumerate(panels):
            ax = fig.add_subplot(len(views), len(panels), row * len(panels) + i + 1, projection="3d")
            points = [draw_mesh(ax, x, f, alpha=alpha) for x, f in meshes]
            cloth = np.concatenate(points) if points else np.zeros((1, 3))
            points += draw_colliders(ax, colliders, np.stack((cloth.min(0), cloth.max(0))))
            _equal_limits(ax, points)
            if view is not None:
                ax.view_init(elev=view[0], azim=view[1])
            if titles and row == 0:
                ax.set_title(titles[i], fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
