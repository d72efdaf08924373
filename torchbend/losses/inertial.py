r"""Loss terms of the cloth's mass: gravity, inertia (the incremental potential) and pinning.

For positions ``x (B, V, 3)`` [m] with lumped masses ``m_i = rho a_i`` (``rho`` the areal density
[kg/m^2], ``a_i`` a third of the rest area of each triangle at vertex ``i`` [m^2], as in
:class:`~torchbend.ClothModel`)::

    Gravity   E = - sum_i m_i g . x_i                                      [J]
    Inertia   E = sum_i m_i / (2 dt^2) |x_i - x_hat_i|^2,   x_hat = x_prev + dt v_prev
    Pinning   E = sum_{p in pins} k_p / 2 |x_p - target_p|^2

Minimising ``Inertia + Gravity + elastic + contact`` over ``x`` is one backward-Euler step (the
incremental potential, the dynamic loss of HOOD and SNUG); without ``Inertia`` it is the static
equilibrium.  ``rho``, ``dt`` and the pin targets may differ per sample (``(B,)``, ``(B,)``,
``(B, P, 3)``), given at construction or per call.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .._checks import vec3
from ..mesh.topology import lumped_areas, mesh_and_rest
from ._base import LossTerm, check_points, lumped_masses, per_sample

__all__ = ["Gravity", "Inertia", "Pinning"]


class _Lumped(LossTerm):
    """A term with lumped rest areas ``a_i`` [m^2] and an areal density [kg/m^2]."""

    areas: Tensor  # (V,) [m^2]

    def __init__(self, faces, rest: Tensor, density):
        super().__init__()
        topo, rest = mesh_and_rest(faces, rest)
        self.register_buffer("areas", lumped_areas(topo.faces.to(rest.device), rest))
        self._set_material("density", density)

    @property
    def vertex_count(self) -> int:
        return int(self.areas.shape[0])

    def _masses(self, x: Tensor, density) -> Tensor:
        """Lumped masses ``(V,)`` or ``(B, V)`` [kg] in the dtype of ``x``."""
        return lumped_masses(self.density if density is None else density, self.areas, x, self.term_name)


class Gravity(_Lumped):
    """Gravitational potential ``E = - sum_i m_i g . x_i`` [J] (module docstring).

    Args:
        faces: ``(F, 3)`` int triangles (or a :class:`~torchbend.HingeTopology`).
        rest: ``(V, 3)`` rest positions [m] (the lumped areas).
        density: areal density ``rho`` [kg/m^2] (> 0): a float or a tensor ``()``/``(B,)`` (per sample).
        gravity: acceleration ``g`` [m/s^2], default ``(0, 0, -9.81)``.

    ``forward(x, *, density=None)``: ``x (B, V, 3)`` or ``(V, 3)`` [m] -> ``(B,)`` or ``()`` [J];
    ``density`` overrides the stored one for this call (``(B,)`` per sample).
    """

    inputs = ("density",)

    def __init__(self, faces, rest: Tensor, density, *, gravity=(0.0, 0.0, -9.81)):
        super().__init__(faces, rest, density)
        self.gravity = vec3(gravity, "Gravity: gravity")

    def forward(self, x: Tensor, *, density=None) -> Tensor:
        x = self._positions(x, self.vertex_count, self.areas.device)
        m = self._masses(x, density)
        return -(m * (x @ x.new_tensor(self.gravity))).sum(-1)

    def extra_repr(self) -> str:
        return f"vertices={self.vertex_count}, gravity={self.gravity}"


class Inertia(_Lumped):
    """Inertia of the incremental potential ``E = sum_i m_i / (2 dt^2) |x_i - x_hat_i|^2`` [J] with
    ``x_hat = x_prev + dt v_prev`` (module docstring).

    Args:
        faces, rest, density: as :class:`Gravity`.
        dt: time step [s] (> 0): a float or a tensor ``()``/``(B,)`` (per sample).

    ``forward(x, *, x_prev=None, v_prev=None, x_hat=None, dt=None, density=None)``: either ``x_prev``
    [m] and ``v_prev`` [m/s] or ``x_hat`` [m], each ``(V, 3)`` (shared) or ``(B, V, 3)``; ``dt`` and
    ``density`` override the stored ones.  ``(B,)`` or ``()`` [J].
    """

    inputs = ("x_prev", "v_prev", "x_hat", "dt", "density")

    def __init__(self, faces, rest: Tensor, density, dt):
        super().__init__(faces, rest, density)
        self._set_material("dt", dt)

    def forward(self, x: Tensor, *, x_prev=None, v_prev=None, x_hat=None, dt=None, density=None) -> Tensor:
        V, name = self.vertex_count, self.term_name
        x = self._positions(x, V, self.areas.device)
        step = per_sample(self.dt if dt is None else dt, "dt", x, name, positive=True)
        step_v = step[..., None, None] if step.ndim else step
        kw = {"count": V, "batch": tuple(x.shape[:-2]), "device": x.device, "dtype": x.dtype}
        if x_hat is not None:
            if x_prev is not None or v_prev is not None:
                raise ValueError(f"{name}: give either x_hat or (x_prev, v_prev), not both")
            target = check_points(x_hat, "x_hat", name, **kw)
        elif x_prev is not None and v_prev is not None:
            target = check_points(x_prev, "x_prev", name, **kw) + step_v * check_points(v_prev, "v_prev", name, **kw)
        else:
            raise ValueError(f"{name}: needs x_hat or both x_prev and v_prev")
        m = self._masses(x, density)
        d = x - target
        w = m / (2 * step[..., None] ** 2) if step.ndim else m / (2 * step * step)
        return (w * (d * d).sum(-1)).sum(-1)

    def extra_repr(self) -> str:
        return f"vertices={self.vertex_count}"


class Pinning(LossTerm):
    """Quadratic penalty ``E = sum_p k_p / 2 |x_p - target_p|^2`` [J] holding vertices at targets.

    Args:
        indices: ``(P,)`` int vertex indices (distinct) or a ``(V,)`` bool mask.
        stiffness: ``k`` [N/m] (> 0), a float or ``(P,)`` per pin.
        targets: default targets ``(P, 3)`` or ``(B, P, 3)`` [m] (e.g. the rest positions of the pins);
            ``None``: every call passes ``pin_targets``.

    ``forward(x, *, pin_targets=None)``: ``x (B, V, 3)`` or ``(V, 3)`` [m]; ``pin_targets`` ``(P, 3)`` or
    ``(B, P, 3)`` (per sample) replaces the default.  ``(B,)`` or ``()`` [J].
    """

    inputs = ("pin_targets",)
    indices: Tensor  # (P,) int64
    stiffness: Tensor  # () or (P,) [N/m]
    targets: Tensor | None

    def __init__(self, indices, stiffness, targets: Tensor | None = None):
        super().__init__()
        idx = torch.as_tensor(indices)
        if idx.dtype == torch.bool:
            if idx.ndim != 1:
                raise ValueError(f"Pinning: a mask must have shape (V,), got {tuple(idx.shape)}")
            idx = torch.nonzero(idx).reshape(-1)
        if idx.ndim != 1 or idx.is_floating_point() or idx.is_complex() or idx.numel() == 0:
            raise ValueError(f"Pinning: indices must be a non-empty (P,) int tensor or a (V,) bool mask, got "
                             f"shape {tuple(idx.shape)} dtype {idx.dtype}")
        idx = idx.long()
        if bool((idx < 0).any()) or torch.unique(idx).numel() != idx.numel():
            raise ValueError(f"Pinning: indices must be distinct and non-negative, got {idx.tolist()[:16]}")
        self.register_buffer("indices", idx)
        # Python numbers are kept in float64 (cast to the positions' dtype per call: no float32 rounding)
        try:
            k = stiffness if isinstance(stiffness, Tensor) else torch.as_tensor(stiffness, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(f"Pinning: stiffness must be a number or a tensor, got {stiffness!r}") from None
        if k.ndim > 1 or (k.ndim == 1 and k.shape[0] != idx.numel()):
            raise ValueError(f"Pinning: stiffness must be a scalar or have shape ({idx.numel()},) (one per pin), "
                             f"got {tuple(k.shape)}")
        if not bool(torch.isfinite(k).all()) or bool((k <= 0).any()):
            raise ValueError(f"Pinning: stiffness must be positive and finite, got {stiffness!r}")
        self.register_buffer("stiffness", k)
        if targets is not None:
            targets = check_points(targets, "targets", "Pinning", count=idx.numel())
        self.register_buffer("targets", targets)

    @property
    def pin_count(self) -> int:
        return int(self.indices.shape[0])

    def forward(self, x: Tensor, *, pin_targets=None) -> Tensor:
        name = self.term_name
        x = self._positions(x, None, self.indices.device)
        top = int(self.indices.max())
        if top >= x.shape[-2]:
            raise ValueError(f"{name}: pin index {top} out of range for x of shape {tuple(x.shape)}")
        target = self.targets if pin_targets is None else pin_targets
        if target is None:
            raise ValueError(f"{name}: no targets: pass pin_targets (P, 3) or (B, P, 3), or targets at construction")
        target = check_points(target, "pin_targets", name, count=self.pin_count, batch=tuple(x.shape[:-2]),
                              device=x.device, dtype=x.dtype)
        d = x[..., self.indices, :] - target
        return 0.5 * (self.stiffness.to(x.dtype) * (d * d).sum(-1)).sum(-1)

    def extra_repr(self) -> str:
        return f"pins={self.pin_count}"
