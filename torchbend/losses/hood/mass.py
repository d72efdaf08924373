r"""HOOD's inertia and gravity criteria, with lumped masses ``m_i`` (a third of each rest triangle's mass)::

    Inertia   E = sum_i m_i |x_i - (2 x_curr_i - x_prev_i)|^2 / (2 dt^2)
    Gravity   E = g sum_i m_i x_i[axis]

``x`` the prediction, ``x_curr`` and ``x_prev`` the cloth at the current and previous steps (HOOD's
``pred_pos``, ``pos``, ``prev_pos``).  HOOD steps at ``dt = 1/30`` s and takes the first step of a sequence
(where ``x_prev = x_curr``) with ``dt = 1/3`` s (``first_step=True``).  Its data is y-up (``axis=1``).
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..._checks import nonnegative
from .._base import per_sample
from ._common import HoodTerm

__all__ = ["Gravity", "Inertia", "REGULAR_DT", "FIRST_STEP_DT"]

REGULAR_DT = 1.0 / 30.0
"""HOOD's time step [s]."""
FIRST_STEP_DT = 1.0 / 3.0
"""HOOD's time step of the first step of a sequence [s]."""


class Inertia(HoodTerm):
    """HOOD's inertia criterion (module docstring) [J].

    Args:
        faces, rest: the cloth's triangles and rest positions (lumped masses).
        density: areal density [kg/m^2] (HOOD's default 0.20022), a float or ``(B,)``.
        dt: the time step [s], a float or ``(B,)`` (default 1/30).

    ``forward(x, *, x_curr, x_prev, dt=None, density=None, first_step=False)``: ``first_step`` (a bool or
    a ``(B,)`` bool tensor) uses ``FIRST_STEP_DT`` for those samples.
    """

    inputs = ("x_curr", "x_prev", "dt", "density", "first_step")

    def __init__(self, faces, rest: Tensor, density: float | Tensor = 0.20022, dt: float | Tensor = REGULAR_DT):
        super().__init__()
        self._set_mesh(faces, rest)
        self._set_material("density", density)
        self._set_material("dt", dt)

    def forward(self, x: Tensor, *, x_curr, x_prev, dt=None, density=None, first_step=False) -> Tensor:
        x = self._positions(x, self.vertex_count, self.faces.device)
        x_curr = self._points(x_curr, "x_curr", x, count=self.vertex_count)
        x_prev = self._points(x_prev, "x_prev", x, count=self.vertex_count)
        step = per_sample(self.dt if dt is None else dt, "dt", x, self.term_name, positive=True)
        first = torch.as_tensor(first_step, device=x.device)
        if first.dtype != torch.bool or (first.ndim and tuple(first.shape) != tuple(x.shape[:-2])):
            raise ValueError(f"{self.term_name}: first_step must be a bool or a ({', '.join(map(str, x.shape[:-2]))},) "
                             f"bool tensor, got {first_step!r}")
        step = torch.where(first, torch.full_like(step, FIRST_STEP_DT), step)
        d = x - (2 * x_curr - x_prev)
        m = self._masses(x, density)
        per = (m * (d * d).sum(-1)).sum(-1)
        return per / (2 * step * step)

    def extra_repr(self) -> str:
        return f"vertices={self.vertex_count}"


class Gravity(HoodTerm):
    """HOOD's gravity criterion ``g sum_i m_i x_i[axis]`` [J] (module docstring).

    Args:
        faces, rest, density: as :class:`Inertia`; g: [m/s^2]; axis: the up axis (HOOD's data: 1, y-up).

    ``forward(x, *, density=None)``.
    """

    inputs = ("density",)

    def __init__(self, faces, rest: Tensor, density: float | Tensor = 0.20022, g: float = 9.81, axis: int = 1):
        super().__init__()
        self._set_mesh(faces, rest)
        self._set_material("density", density)
        self.g = nonnegative(g, f"{self.term_name}: g")
        if axis not in (0, 1, 2):
            raise ValueError(f"{self.term_name}: axis must be 0, 1 or 2, got {axis!r}")
        self.axis = axis

    def forward(self, x: Tensor, *, density=None) -> Tensor:
        x = self._positions(x, self.vertex_count, self.faces.device)
        return self.g * (self._masses(x, density) * x[..., self.axis]).sum(-1)

    def extra_repr(self) -> str:
        return f"vertices={self.vertex_count}, axis={self.axis}"
