r"""Body contact as a loss: a one-sided penalty against a body mesh, the project's colliders and
per-sample spheres, in torchbend's convention (SNUG's nearest-vertex variant for a body mesh).

For cloth positions ``x (B, V, 3)`` [m] and every contact source::

    E = sum_i phi(eps - s_i),    phi(d) = k max(0, d)^p   [J],   k = stiffness [J/m^p], p = power (default 3)

the power barrier of :mod:`torchbend.energies.contact` (``law="barrier"``; ``law="penalty"`` is
``k/2 max(0, d)^2``, a solver collider's ``law="penalty"``: the same module serves both)

with ``s_i`` the signed distance of cloth vertex ``i`` from the body (positive outside):

* body mesh ``(body (B, Vb, 3), body_faces (Fb, 3))``: ``s_i = (x_i - b_j) . n_j`` with ``b_j`` the body
  vertex nearest to ``x_i`` and ``n_j`` its unit normal (the normalised sum of the area-weighted normals
  of its faces; the faces must be oriented outwards, counter-clockwise seen from outside).  This is
  HOOD's and SNUG's collision criterion, ``k max(0, eps - (x - b) . n)^3`` with ``eps`` a few
  millimetres.  The nearest vertex is chosen without gradient (a piecewise-constant index); the
  penalty is differentiable in ``x`` and in the body positions.
* the project's colliders (:class:`~torchbend.Sphere`, :class:`~torchbend.Plane`,
  :class:`~torchbend.Capsule`): their exact signed distance and their own ``margin`` (their ``stiffness``
  and ``law`` are not used: this term's law is);
* per-sample spheres ``sphere_center (B, 3)``, ``sphere_radius (B,)``: ``s_i = |x_i - c| - r``.

``law="penalty", eps=0`` and ``stiffness = k_c`` give the quadratic penalty ``k_c/2 max(0, -s)^2`` of a
solver collider with ``law="penalty"`` (as ``power=2`` with ``stiffness = k_c / 2`` does).
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from .._checks import nonnegative, positive
from ..energies.colliders import Collider
from ..energies.contact import ContactLaw, contact_law
from ._base import LossTerm, check_points

__all__ = ["BodyContact", "vertex_normals"]

_CDIST_BLOCK = 1 << 22  # entries of one block of the cloth-body distance matrix


def vertex_normals(positions: Tensor, faces: Tensor) -> Tensor:
    """Unit vertex normals ``(..., V, 3)`` of a triangle mesh ``positions (..., V, 3)``, ``faces (F, 3)``:
    the normalised sums of the area-weighted face normals (zero at a vertex in no face or whose
    normals cancel)."""
    p0, p1, p2 = (positions[..., faces[:, k], :] for k in range(3))
    fn = torch.linalg.cross(p1 - p0, p2 - p0, dim=-1)  # (..., F, 3), |.| = 2 area
    n = positions.new_zeros(positions.shape).index_add(-2, faces.reshape(-1), fn.repeat_interleave(3, dim=-2))
    length = n.norm(dim=-1, keepdim=True)
    ok = length > 0
    return torch.where(ok, n / torch.where(ok, length, torch.ones_like(length)), torch.zeros_like(n))


def _nearest(x: Tensor, body: Tensor) -> Tensor:
    """Index ``(B, V)`` of the body vertex nearest to each cloth vertex (no gradient); ``x (B, V, 3)``,
    ``body (B, Vb, 3)``; the distance matrix is formed in blocks of rows."""
    with torch.no_grad():
        x, body = x.detach(), body.detach()
        rows = max(1, _CDIST_BLOCK // max(1, body.shape[0] * body.shape[1]))
        parts = [torch.cdist(x[:, i:i + rows], body, compute_mode="donot_use_mm_for_euclid_dist").argmin(-1)
                 for i in range(0, x.shape[1], rows)]
        return torch.cat(parts, 1)


def _as_tensor(value, what: str, term: str, x: Tensor) -> Tensor:
    """``value`` as a tensor; Python numbers straight in the dtype of ``x`` (a float64 run never sees them
    rounded to float32)."""
    if isinstance(value, Tensor):
        return value
    try:
        return torch.as_tensor(value, dtype=x.dtype)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{term}: {what} must be a tensor or numbers, got {value!r}") from None


class BodyContact(LossTerm):
    """One-sided contact penalty ``E = k sum_i max(0, eps - s_i)^p`` [J] (module docstring).

    Args:
        stiffness: ``k`` [J/m^p] (> 0).
        eps: ``eps`` [m] (>= 0): the penalty acts below this distance from the body (default 4 mm).
        power: ``p`` (finite, > 1; default 3, as HOOD and SNUG) of the barrier.
        law: ``"barrier"`` (default), ``"penalty"`` (``k/2 max(0, d)^2``) or a
            :class:`~torchbend.energies.contact.ContactLaw`.
        body_faces: ``(Fb, 3)`` int faces of a body mesh whose positions every call passes as ``body``.
        colliders: static :class:`~torchbend.Sphere`/``Plane``/``Capsule`` colliders.

    ``forward(x, *, body=None, sphere_center=None, sphere_radius=None)``: ``x (B, V, 3)`` or ``(V, 3)``
    [m]; ``body`` ``(Vb, 3)`` or ``(B, Vb, 3)`` [m] (needed with ``body_faces``); ``sphere_center`` ``(3,)``
    or ``(B, 3)`` and ``sphere_radius`` ``()`` or ``(B,)`` [m] add per-sample spheres.  ``(B,)`` or ``()``
    [J], summed over the sources; a call with no source is a ``ValueError``.
    """

    inputs = ("body", "sphere_center", "sphere_radius")
    body_faces: Tensor | None

    def __init__(self, *, stiffness: float, eps: float = 4e-3, power: float | None = None, body_faces=None,
                 colliders: Sequence[Collider] = (), law: str | ContactLaw = "barrier"):
        super().__init__()
        self.stiffness = positive(stiffness, "BodyContact: stiffness")
        self.eps = nonnegative(eps, "BodyContact: eps")
        if law == "ipc" or getattr(law, "bounded", False):
            raise ValueError("BodyContact: the ipc law is infinite inside the body, which a prediction may be: a "
                             "training loss takes law='barrier' or 'penalty'")
        try:
            self.law = contact_law(law, self.stiffness, power)
        except ValueError as e:
            raise ValueError(f"BodyContact: {e}") from None
        self.power = self.law.power
        if body_faces is not None:
            f = torch.as_tensor(body_faces)
            if f.ndim != 2 or f.shape[1] != 3 or f.is_floating_point() or f.numel() == 0 or bool((f < 0).any()):
                raise ValueError(f"BodyContact: body_faces must be a non-empty (Fb, 3) tensor of non-negative ints, "
                                 f"got shape {tuple(f.shape)} dtype {f.dtype}")
            body_faces = f.long()
        self.register_buffer("body_faces", body_faces)
        colliders = tuple(colliders)
        for c in colliders:
            if not isinstance(c, Collider):
                raise ValueError(f"BodyContact: colliders must be torchbend colliders (Sphere, Plane, Capsule), "
                                 f"got {type(c).__name__}")
        self.colliders = colliders

    def _penalty(self, s: Tensor) -> Tensor:
        """``sum_i phi(eps - s_i)`` over the last axis."""
        return self.law.value(self.eps - s).sum(-1)

    def body_distance(self, x: Tensor, body: Tensor) -> Tensor:
        """Signed distances ``(B, V)`` or ``(V,)`` [m] of the cloth vertices from the body mesh (nearest body
        vertex, its normal)."""
        faces = self.body_faces
        if faces is None:
            raise ValueError("BodyContact: a body was given but the term has no body_faces")
        body = check_points(body, "body", self.term_name, count=None, batch=tuple(x.shape[:-2]), device=x.device,
                            dtype=x.dtype)
        if int(faces.max()) >= body.shape[-2]:
            raise ValueError(f"BodyContact: body_faces index {int(faces.max())} out of range for body of shape "
                             f"{tuple(body.shape)}")
        n = vertex_normals(body, faces.to(x.device))
        xb = x if x.ndim == 3 else x[None]
        bb = body if body.ndim == 3 else body[None]
        nb = n if n.ndim == 3 else n[None]
        bb, nb = bb.expand(xb.shape[0], -1, -1), nb.expand(xb.shape[0], -1, -1)
        idx = _nearest(xb, bb)[..., None].expand(-1, -1, 3)
        s = ((xb - bb.gather(1, idx)) * nb.gather(1, idx)).sum(-1)
        return s if x.ndim == 3 else s[0]

    def forward(self, x: Tensor, *, body=None, sphere_center=None, sphere_radius=None) -> Tensor:
        name = self.term_name
        x = self._positions(x, None, None)
        out = x.new_zeros(x.shape[:-2])
        sources = 0
        if self.body_faces is not None:
            if body is None:
                raise ValueError(f"{name}: has body_faces: pass the body positions as body (Vb, 3) or (B, Vb, 3)")
            out = out + self._penalty(self.body_distance(x, body))
            sources += 1
        elif body is not None:
            raise ValueError(f"{name}: a body was given but the term has no body_faces")
        for c in self.colliders:
            s = c.signed_distance(x)
            out = out + self._penalty(s)
            sources += 1
        if (sphere_center is None) != (sphere_radius is None):
            raise ValueError(f"{name}: per-sample spheres need both sphere_center and sphere_radius")
        if sphere_center is not None:
            out = out + self._penalty(self._sphere_distance(x, sphere_center, sphere_radius))
            sources += 1
        if not sources:
            raise ValueError(f"{name}: nothing to collide with (no body_faces, colliders or sphere_center/sphere_radius)")
        return out

    def _sphere_distance(self, x: Tensor, center, radius) -> Tensor:
        name, batch = self.term_name, tuple(x.shape[:-2])
        c = _as_tensor(center, "sphere_center", name, x)
        if c.shape not in ((3,), batch + (3,)):
            raise ValueError(f"{name}: sphere_center must have shape (3,) or {batch + (3,)}, got {tuple(c.shape)}")
        r = _as_tensor(radius, "sphere_radius", name, x)
        if r.shape not in ((), batch):
            raise ValueError(f"{name}: sphere_radius must be a scalar or have shape {batch}, got {tuple(r.shape)}")
        c, r = c.to(device=x.device, dtype=x.dtype), r.to(device=x.device, dtype=x.dtype)
        if not bool(torch.isfinite(c.detach()).all() & torch.isfinite(r.detach()).all()) or bool((r.detach() <= 0).any()):
            raise ValueError(f"{name}: sphere_center must be finite and sphere_radius positive and finite")
        d = x - (c[..., None, :] if c.ndim == 2 else c)
        r2 = (d * d).sum(-1)
        apart = r2 > 0  # (a vertex exactly at the centre gets distance 0 and a zero gradient, not NaN)
        dist = torch.where(apart, torch.where(apart, r2, torch.ones_like(r2)).sqrt(), torch.zeros_like(r2))
        return dist - (r[..., None] if r.ndim else r)

    def extra_repr(self) -> str:
        body = "none" if self.body_faces is None else f"{self.body_faces.shape[0]} faces"
        return (f"law={type(self.law).__name__}, stiffness={self.stiffness:g}, eps={self.eps:g}, power={self.power:g}, body={body}, "
                f"colliders={len(self.colliders)}")
