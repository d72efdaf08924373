r"""HOOD's body criteria: the collision penalty and friction against a body mesh that moves per step.

Both match each cloth vertex to the nearest body *face centroid* (a piecewise-constant choice, without
gradient, as HOOD's ``knn_points``); the penalties are differentiable in the cloth prediction ``x`` and in
the body positions.  Positions of three instants appear: the body at the previous, current and next step
(HOOD's ``obstacle.prev_pos``, ``pos``, ``target_pos``) and the cloth at the current step (``x_curr``, HOOD's
``cloth.pos``) and predicted for the next (``x``, HOOD's ``pred_pos``).

Collision (HOOD's ``collision_penalty``)::

    j_i = nearest centroid of body_curr to x_curr_i
    d_i = (x_i - c_j(body_next)) . n_j(body_next),      E = w(iteration) sum_i max(eps - d_i, 0)^3

with ``w`` ramped linearly from ``weight_start`` to ``weight_max`` over ``n_rampup_iterations`` training
iterations after ``start_rampup_iteration``.

Friction (HOOD's ``friction_energy``), with lumped masses ``m_i``::

    j_i = nearest centroid of body_prev to x_curr_i,    k_i = nearest centroid of body_curr to x_i
    n_i = (n_j(body_prev) + n_k(body_curr)) / 2
    delta_i = x_i - (x_curr_i + c_j(body_curr) - c_j(body_prev)),  t_i = delta_i - (delta_i . n_i) n_i
    E = mu g sum_i m_i s_i |t_i| [r2_prev_i < radius and r2_curr_i < radius]
    s_i = sqrt(1 - cos^2(t_i, floor_normal) + 1e-4)

``r2`` the *squared* distances to the matched centroids: HOOD compares ``knn_points``' squared distance
with ``friction_radius``, so a radius of 3 mm admits vertices within ``sqrt(3e-3) = 5.5 cm``; this term
does the same (pass ``radius=r**2`` for a true distance ``r``).  HOOD evaluates friction with the body
pair ``(prev_pos, pos)`` beside the cloth pair ``(pos, pred_pos)``: pass ``body_prev`` and ``body_curr``
as HOOD does, or the body at the cloth's instants to align them.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ..._checks import nonnegative, positive, vec3
from .._base import check_points
from ._common import HoodTerm, face_centroids, face_normals, nearest, take

__all__ = ["Collision", "Friction"]


def _body_faces(body_faces, term: str) -> Tensor:
    f = torch.as_tensor(body_faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.is_floating_point() or f.shape[0] == 0:
        raise ValueError(f"{term}: body_faces must be a non-empty (Fb, 3) int tensor, got shape "
                         f"{tuple(f.shape)} dtype {f.dtype}")
    if bool((f < 0).any()):
        raise ValueError(f"{term}: body_faces holds negative indices")
    return f.long()


class _BodyTerm(HoodTerm):
    body_faces: Tensor

    def _body(self, t, name: str, x: Tensor) -> Tensor:
        b = check_points(t, name, self.term_name, count=None, batch=tuple(x.shape[:-2]), device=x.device,
                         dtype=x.dtype)
        top = int(self.body_faces.max())
        if top >= b.shape[-2]:
            raise ValueError(f"{self.term_name}: body_faces index {top} out of range for {name} of shape "
                             f"{tuple(b.shape)}")
        return b


class Collision(_BodyTerm):
    """HOOD's collision penalty against a moving body mesh (module docstring) [J], weight schedule included.

    Args:
        body_faces: ``(Fb, 3)`` int triangles of the body, oriented outwards.
        eps: the margin [m] (HOOD's training configuration: 2 mm).
        weight_start, weight_max, start_rampup_iteration, n_rampup_iterations: the weight ramp (HOOD's
            training starts at 5e3; its criterion's default ramp spans a factor 100 from iteration 50,000
            over 100,000 iterations).

    ``forward(x, *, x_curr, body_curr, body_next, iteration=0)``: cloth ``x``, ``x_curr`` ``(V, 3)`` or
    ``(B, V, 3)``; body ``(Vb, 3)`` or ``(B, Vb, 3)`` -> ``(B,)`` or ``()``.
    """

    inputs = ("x_curr", "body_curr", "body_next", "iteration")

    def __init__(self, body_faces, eps: float = 2e-3, weight_start: float = 5e3, weight_max: float = 5e5,
                 start_rampup_iteration: int = 50000, n_rampup_iterations: int = 100000):
        super().__init__()
        self.register_buffer("body_faces", _body_faces(body_faces, self.term_name))
        name = self.term_name
        self.eps = nonnegative(eps, f"{name}: eps")
        self.weight_start = nonnegative(weight_start, f"{name}: weight_start")
        self.weight_max = nonnegative(weight_max, f"{name}: weight_max")
        if int(n_rampup_iterations) <= 0 or int(start_rampup_iteration) < 0:
            raise ValueError(f"{self.term_name}: n_rampup_iterations must be positive and start_rampup_iteration "
                             f"non-negative, got {n_rampup_iterations}, {start_rampup_iteration}")
        self.start_rampup_iteration, self.n_rampup_iterations = int(start_rampup_iteration), int(n_rampup_iterations)

    def weight(self, iteration: int = 0) -> float:
        """HOOD's ramp: ``weight_start`` until ``start_rampup_iteration``, linear to ``weight_max`` after."""
        progress = min(max(int(iteration) - self.start_rampup_iteration, 0) / self.n_rampup_iterations, 1.0)
        return self.weight_start + (self.weight_max - self.weight_start) * progress

    def forward(self, x: Tensor, *, x_curr, body_curr, body_next, iteration: int = 0) -> Tensor:
        x = self._positions(x, None, self.body_faces.device)
        x_curr = self._points(x_curr, "x_curr", x, count=x.shape[-2])
        body_curr, body_next = self._body(body_curr, "body_curr", x), self._body(body_next, "body_next", x)
        f = self.body_faces
        _, j = nearest(x_curr, face_centroids(body_curr.detach(), f))
        c, n = take(face_centroids(body_next, f), j), take(face_normals(body_next, f), j)
        d = ((x - c) * n).sum(-1)
        return self.weight(iteration) * (self.eps - d).clamp_min(0).pow(3).sum(-1)

    def extra_repr(self) -> str:
        return f"body_faces={self.body_faces.shape[0]}, eps={self.eps}"


class Friction(_BodyTerm):
    """HOOD's friction criterion against a moving body mesh (module docstring) [J].

    Args:
        faces, rest: the cloth's triangles and rest positions (lumped masses); density: areal density
            [kg/m^2], a float or ``(B,)``.
        body_faces: ``(Fb, 3)`` int triangles of the body.
        mu: friction coefficient (HOOD's training: 0.5); radius: HOOD's ``friction_radius`` (3e-3),
            compared with *squared* distances [m^2] as HOOD does; g: [m/s^2]; floor_normal: HOOD's (0, 0, 1).

    ``forward(x, *, x_curr, body_prev, body_curr, density=None)`` -> ``(B,)`` or ``()``.
    """

    inputs = ("x_curr", "body_prev", "body_curr", "density")

    def __init__(self, faces, rest: Tensor, body_faces, density: float | Tensor = 0.20022, mu: float = 0.5, radius: float = 3e-3,
                 g: float = 9.81, floor_normal=(0.0, 0.0, 1.0)):
        super().__init__()
        self._set_mesh(faces, rest)
        self.register_buffer("body_faces", _body_faces(body_faces, self.term_name))
        self._set_material("density", density)
        name = self.term_name
        self.mu, self.radius = nonnegative(mu, f"{name}: mu"), positive(radius, f"{name}: radius")
        self.g = nonnegative(g, f"{name}: g")
        self.floor_normal = vec3(floor_normal, f"{self.term_name}: floor_normal")

    def forward(self, x: Tensor, *, x_curr, body_prev, body_curr, density=None) -> Tensor:
        x = self._positions(x, self.vertex_count, self.faces.device)
        x_curr = self._points(x_curr, "x_curr", x, count=self.vertex_count)
        body_prev, body_curr = self._body(body_prev, "body_prev", x), self._body(body_curr, "body_curr", x)
        f = self.body_faces
        c_prev, c_curr = face_centroids(body_prev, f), face_centroids(body_curr, f)
        reach = math.sqrt(self.radius)  # only vertices within it count: a bounded search (the same value)
        r2_prev, j = nearest(x_curr, c_prev.detach(), reach)
        r2_curr, k = nearest(x, c_curr.detach(), reach)
        n = 0.5 * (take(face_normals(body_prev, f), j) + take(face_normals(body_curr, f), k))
        delta = x - (x_curr + take(c_curr, j) - take(c_prev, j))
        t = delta - (delta * n).sum(-1, keepdim=True) * n
        floor = x.new_tensor(self.floor_normal).expand_as(t)
        cos = torch.nn.functional.cosine_similarity(floor, t, dim=-1).abs()
        s = ((1 - cos * cos).abs() + 1e-4).sqrt()
        inside = ((r2_prev < self.radius) & (r2_curr < self.radius)).to(x.dtype)
        m = self._masses(x, density)
        return self.mu * self.g * (m * s * torch.linalg.vector_norm(t, dim=-1) * inside).sum(-1)

    def extra_repr(self) -> str:
        return f"body_faces={self.body_faces.shape[0]}, mu={self.mu}, radius={self.radius}"
