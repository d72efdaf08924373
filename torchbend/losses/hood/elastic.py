r"""HOOD's stretching and bending criteria, with torchbend's closed-form derivatives.

Stretching (HOOD's and SNUG's, Saint Venant-Kirchhoff): per triangle with rest area ``A`` [m^2]::

    E_T = A t (lame_mu |G|_F^2 + lame_lambda / 2 tr(G)^2),   G = (F^T F - I) / 2,   F = D_s D_m^-1

``D_m`` the rest triangle's edges in a frame of its plane (HOOD's material-space coordinates; the energy
does not depend on the choice of that frame).  Computed per component with the analytic gradient
``dE/dF = A t F S``, ``S = 2 lame_mu G + lame_lambda tr(G) I`` (a backward that is itself differentiable).

Bending (HOOD's): per interior edge (hinge) with the two adjacent triangles' *rest* areas ``A_0, A_1``::

    E_h = bending_coeff * l^2 / (4 (A_0 + A_1)) * theta^2 / 2

``l`` the edge's *current* length (on the prediction) and ``theta`` the dihedral angle measured from flat
(HOOD has no rest angles).  Evaluated by the compiled hinge operators with a per-hinge stiffness
``bending_coeff l^2 / (8 (A_0 + A_1))`` that depends on ``x``: the gradient (and its derivative) is
torchbend's closed form of ``theta`` plus the chain rule through ``l^2``, no atan2 through autograd.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ... import backends
from ..._checks import is_traced, positive
from ...energies._bending_fn import bending_energy_raw
from ...energies.bending import BendingEnergy
from ...ops.psi import BendingModel
from .._base import per_sample
from ._common import HoodTerm

__all__ = ["Bending", "Stretching", "DEFAULT_MATERIAL"]

DEFAULT_MATERIAL = {"density": 0.20022, "lame_mu": 23600.0, "lame_lambda": 44400.0, "bending_coeff": 3.9625778333333325e-05,
                    "thickness": 4.7e-4}
"""HOOD's default material (its validation material): areal density [kg/m^2], Lame parameters [Pa],
bending coefficient [N m] (``= 50 D``, :func:`~torchbend.losses.hood.bending_coeff_from_material`) and
the thickness of its stretching criterion [m]."""


def _rest_frames(rest: Tensor, faces: Tensor) -> Tensor:
    """``D_m^-1`` ``(F, 2, 2)`` of the rest triangles in an orthonormal frame of their planes (float64)."""
    X = rest.detach().to(torch.float64)
    p0, p1, p2 = X[faces[:, 0]], X[faces[:, 1]], X[faces[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    l1 = e1.norm(dim=-1)
    u = e1 / l1[:, None]
    n = torch.linalg.cross(e1, e2, dim=-1)
    w = torch.linalg.cross(n, u, dim=-1)
    w = w / w.norm(dim=-1, keepdim=True)
    a, b, d = l1, (e2 * u).sum(-1), (e2 * w).sum(-1)  # D_m = [[a, b], [0, d]]
    inv = torch.zeros(faces.shape[0], 2, 2, dtype=torch.float64, device=X.device)
    inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1] = 1 / a, -b / (a * d), 1 / d
    return inv


def _strain(x: Tensor, faces: Tensor, Dinv: Tensor):
    """Columns ``f0, f1`` ``(N, 3, F)`` of ``F`` and the Green strain ``(g00, g01, g11)`` ``(N, F)`` per triangle
    of ``x (..., V, 3)``, in components-first layout (contiguous rows: vectorised sums over the 3 components)."""
    xs = x.reshape(-1, *x.shape[-2:]).transpose(1, 2)  # (N, 3, V)
    x0 = xs.index_select(2, faces[:, 0])
    e1, e2 = xs.index_select(2, faces[:, 1]) - x0, xs.index_select(2, faces[:, 2]) - x0
    f0 = torch.addcmul(e1 * Dinv[:, 0, 0], e2, Dinv[:, 1, 0])
    f1 = torch.addcmul(e1 * Dinv[:, 0, 1], e2, Dinv[:, 1, 1])
    g00 = 0.5 * ((f0 * f0).sum(1) - 1)
    g01 = 0.5 * (f0 * f1).sum(1)
    g11 = 0.5 * ((f1 * f1).sum(1) - 1)
    return f0, f1, g00, g01, g11


def _parts_gradient(x: Tensor, strain, faces: Tensor, corners: Tensor, Dinv: Tensor, area: Tensor, gmu: Tensor,
                    glam: Tensor) -> Tensor:
    """``gmu dE_mu/dx + glam dE_lam/dx`` (``E_mu = sum A |G|^2``, ``E_lam = sum A tr(G)^2 / 2``), ``x``'s shape;
    ``corners``: ``faces[:, (1, 2, 0)]`` flattened column by column (the scatter's indices)."""
    f0, f1, g00, g01, g11 = strain
    gm = (2 * gmu).reshape(-1, 1) * area  # (N, F)
    gl = glam.reshape(-1, 1) * area
    tr = gl * (g00 + g11)
    s00, s01, s11 = (gm * g00 + tr)[:, None], (gm * g01)[:, None], (gm * g11 + tr)[:, None]
    p0, p1 = f0 * s00 + f1 * s01, f0 * s01 + f1 * s11  # P = F S
    d1 = torch.addcmul(p0 * Dinv[:, 0, 0], p1, Dinv[:, 0, 1])  # dE/dDs = P D_m^-T
    d2 = torch.addcmul(p0 * Dinv[:, 1, 0], p1, Dinv[:, 1, 1])
    g = f0.new_zeros(f0.shape[0], 3, x.shape[-2]).index_add(2, corners, torch.cat([d1, d2, -(d1 + d2)], dim=2))
    return g.transpose(1, 2).reshape(x.shape)


class _StVKParts(torch.autograd.Function):
    """``(E_mu, E_lam)`` per sample; the backward is the closed form (recomputed from ``x`` where a graph of it
    is recorded, so that it is differentiable again)."""

    @staticmethod
    def forward(x, faces, corners, Dinv, area):
        strain = _strain(x, faces, Dinv)
        _, _, g00, g01, g11 = strain
        e_mu = (area * (g00 * g00 + 2 * g01 * g01 + g11 * g11)).sum(-1)
        tr = g00 + g11
        e_lam = (0.5 * area * tr * tr).sum(-1)
        return e_mu.reshape(x.shape[:-2]), e_lam.reshape(x.shape[:-2]), strain

    @staticmethod
    def setup_context(ctx, inputs, output):
        x, faces, corners, Dinv, area = inputs
        ctx.save_for_backward(x, faces, corners, Dinv, area, *output[2])
        ctx.mark_non_differentiable(*output[2])

    @staticmethod
    def backward(ctx, gmu, glam, *_):
        x, faces, corners, Dinv, area, *strain = ctx.saved_tensors
        if torch.is_grad_enabled():  # a double backward: the gradient as a function of x
            strain = _strain(x, faces, Dinv)
        return _parts_gradient(x, strain, faces, corners, Dinv, area, gmu, glam), None, None, None, None


def _alias(term: str, name: str, value, hood_name: str, hood_value):
    """One of two names of a parameter (``mu`` or HOOD's ``lame_mu``); both given is a ``ValueError``."""
    if value is not None and hood_value is not None:
        raise ValueError(f"{term}: give {name} or {hood_name}, not both")
    return hood_value if value is None else value


class Stretching(HoodTerm):
    """HOOD's stretching criterion (module docstring) [J], Lame parameters given directly.

    Args:
        faces: ``(F, 3)`` int triangles; rest: ``(V, 3)`` rest positions [m] (HOOD's rest garment).
        mu: HOOD's ``lame_mu`` [Pa] (> 0); lam: ``lame_lambda`` [Pa] (> -mu: the 2-D stability condition; no
            upper bound, unlike a Poisson ratio below 1/2): floats or ``(B,)`` tensors (per sample); HOOD's
            names ``lame_mu=``, ``lame_lambda=`` are accepted too.  Defaults: HOOD's material.
        thickness: ``t`` [m], HOOD's 4.7e-4.

    ``forward(x, *, mu=None, lam=None)`` (or ``lame_mu=``, ``lame_lambda=``): ``x (B, V, 3)`` or ``(V, 3)`` [m] ->
    ``(B,)`` or ``()`` [J].
    """

    inputs = ("mu", "lam", "lame_mu", "lame_lambda")
    Dinv: Tensor  # (F, 2, 2) D_m^-1
    corners: Tensor  # (3F,) faces[:, (1, 2, 0)] column by column

    def __init__(self, faces, rest: Tensor, mu: float | Tensor | None = None, lam: float | Tensor | None = None,
                 thickness: float = DEFAULT_MATERIAL["thickness"], *, lame_mu: float | Tensor | None = None,
                 lame_lambda: float | Tensor | None = None):
        super().__init__()
        mu, lam = _alias(self.term_name, "mu", mu, "lame_mu", lame_mu), _alias(self.term_name, "lam", lam, "lame_lambda",
                                                                              lame_lambda)
        lame_mu = DEFAULT_MATERIAL["lame_mu"] if mu is None else mu
        lame_lambda = DEFAULT_MATERIAL["lame_lambda"] if lam is None else lam
        rest = self._set_mesh(faces, rest)
        self.register_buffer("Dinv", _rest_frames(rest, self.faces).to(rest.dtype))
        self.register_buffer("corners", self.faces[:, [1, 2, 0]].T.reshape(-1).contiguous())
        self._set_material("lame_mu", lame_mu)
        self._set_material("lame_lambda", lame_lambda, positive=None)
        self.thickness = positive(thickness, f"{self.term_name}: thickness")

    def forward(self, x: Tensor, *, mu=None, lam=None, lame_mu=None, lame_lambda=None) -> Tensor:
        x = self._positions(x, self.vertex_count, self.faces.device)
        name = self.term_name
        lame_mu, lame_lambda = _alias(name, "mu", mu, "lame_mu", lame_mu), _alias(name, "lam", lam, "lame_lambda",
                                                                                  lame_lambda)
        mu = per_sample(self.lame_mu if lame_mu is None else lame_mu, "lame_mu", x, name, positive=True)
        lam = per_sample(self.lame_lambda if lame_lambda is None else lame_lambda, "lame_lambda", x, name,
                         positive=None)
        if not is_traced(lam) and bool((lam.detach() <= -mu.detach()).any()):  # (checked eagerly, not compiled)
            raise ValueError(f"{name}: lame_lambda must exceed -lame_mu (2-D stability), got lame_mu "
                             f"{mu.detach().tolist()} and lame_lambda {lam.detach().tolist()}")
        e_mu, e_lam, _ = _StVKParts.apply(x, self.faces, self.corners, self.Dinv.to(x.dtype),
                                          self.face_areas.to(x.dtype))
        return self.thickness * (mu * e_mu + lam * e_lam)

    def extra_repr(self) -> str:
        return f"faces={self.faces.shape[0]}, thickness={self.thickness}"


class Bending(HoodTerm):
    """HOOD's bending criterion (module docstring) [J]: current edge lengths, rest areas, angles from flat.

    Args:
        faces: ``(F, 3)`` int triangles; rest: ``(V, 3)`` rest positions [m] (for the rest areas only).
        bending_coeff: HOOD's ``bending_coeff`` [N m] (>= 0), a float or ``(B,)`` (per sample); HOOD's
            default 3.9626e-5 (``50 D`` of its default material).

    ``forward(x, *, bending_coeff=None)``: ``x (B, V, 3)`` or ``(V, 3)`` -> ``(B,)`` or ``()``.
    """

    inputs = ("bending_coeff",)
    scale: Tensor  # (H,) 1 / (8 (A0 + A1))

    def __init__(self, faces, rest: Tensor, bending_coeff: float | Tensor = DEFAULT_MATERIAL["bending_coeff"]):
        super().__init__()
        rest = self._set_mesh(faces, rest)
        self._set_material("bending_coeff", bending_coeff, positive=False)
        self.hinge = BendingEnergy(self._topology, rest, model="quadratic", stiffness=1.0)
        pair = self._topology.hinge_faces.to(rest.device)
        self.register_buffer("scale", (1 / (8 * self.face_areas[pair].sum(-1).to(torch.float64))).to(rest.dtype))

    def forward(self, x: Tensor, *, bending_coeff=None) -> Tensor:
        x = self._positions(x, self.vertex_count, self.faces.device)
        coeff = per_sample(self.bending_coeff if bending_coeff is None else bending_coeff, "bending_coeff", x,
                           self.term_name)
        hinges = self.hinge.hinges
        e = x[..., hinges[:, 1], :] - x[..., hinges[:, 0], :]
        k = (e * e).sum(-1) * self.scale.to(x.dtype)
        k = k * (coeff[..., None] if coeff.ndim else coeff)
        ones, zeros = x.new_ones(hinges.shape[0]), x.new_zeros(hinges.shape[0])
        native = backends.select_backend("energy", self.hinge.backend, x, k) is backends.Backend.NATIVE
        return bending_energy_raw(x, hinges, ones, k, zeros, model=BendingModel.QUADRATIC,
                                  impl="native" if native else None, inc=self.hinge._incidence() if native else None)

    def extra_repr(self) -> str:
        return f"hinges={self.hinge.hinges.shape[0]}"
