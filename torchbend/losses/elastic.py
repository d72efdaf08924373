r"""Elastic loss terms with per-sample materials: stretch (membrane) and bending.

Both keep torchbend's conventions (Young's modulus and a Poisson ratio; Discrete Shells bending with rest
lengths and rest angles); HOOD's formulas themselves are :mod:`torchbend.losses.hood`.  Both wrap the
package's energies (closed-form gradients, analytic double backward) and are linear in
their material parameters, which makes per-sample materials exact and cheap:

* :class:`Stretch`: ``E = sum_T A_T t Psi(F_T; mu, lam)`` (:class:`~torchbend.MembraneEnergy`) with
  ``(mu, lam)`` the plane-stress Lame parameters of ``(young, poisson)``.  Every model's density is
  linear in ``(mu, lam)`` (``stvk``: ``mu |G|^2 + lam/2 tr(G)^2``), so for per-sample materials
  ``E_b = t_b (mu_b E_mu(x_b) + lam_b E_lam(x_b))`` with ``E_mu``, ``E_lam`` the energies of unit
  ``mu`` and unit ``lam`` (two evaluations; one when the material is the same for the whole batch);
* :class:`Bending`: ``E = k sum_h 3 |e|^2 / (A_A + A_B) (phi(theta) - phi(theta_rest))^2``
  (:class:`~torchbend.BendingEnergy`), ``E_b = k_b E_1(x_b)`` with ``E_1`` the energy of unit stiffness.

Why :class:`Bending` defaults to ``model="quadratic"``: the ``tan`` model (``phi = 2 tan(theta/2)``,
the default of :class:`~torchbend.BendingEnergy`) puts a barrier at ``theta = pi`` that keeps a
simulated hinge from folding through, the right choice for a solver that starts from a valid state.
A loss sees the outputs of an untrained network, where hinges near ``pi`` are common; there the
barrier's gradient (``~ 1/cos^3(theta/2)``) is enormous and wrecks the first optimiser steps: on a
grid plus noise of one edge length, ``|dE/dx| |x - rest| / E`` (2 for a quadratic form with an isotropic
Hessian) stays below 20 with ``quadratic`` and exceeds ``1e4`` with ``tan``, whose largest gradient
entries are a million times larger (``tests/test_losses.py``).
"""
from __future__ import annotations

from typing import cast

import torch
from torch import Tensor

from .._checks import is_traced
from ..energies import _membrane_fn
from ..energies.bending import BendingEnergy
from ..energies.membrane import MembraneEnergy
from ..ops.membrane import MembraneModel
from ..options import Backend
from ._base import LossTerm, per_sample

__all__ = ["Stretch", "Bending"]

_USES_LAMBDA = frozenset({MembraneModel.STVK, MembraneModel.NEOHOOKEAN})


class Stretch(LossTerm):
    """Membrane (stretch) energy ``sum_T A_T t Psi(F_T)`` [J] with per-sample materials.

    Args:
        faces: ``(F, 3)`` int triangles (or a :class:`~torchbend.HingeTopology`).
        rest: ``(V, 3)`` rest positions [m].
        young: Young's modulus ``Y`` [Pa] (> 0); poisson: ``nu`` in (-1, 0.5); thickness: ``t`` [m] (> 0).
            Each a float or a tensor ``()``/``(B,)`` (per sample; an ``nn.Parameter`` is learnable).
        model: ``"stvk" | "arap" | "symmetric_dirichlet" | "neohookean"`` (:class:`~torchbend.MembraneModel`).

    ``forward(x, *, young=None, poisson=None, thickness=None)``: ``x (B, V, 3)`` or ``(V, 3)`` [m] ->
    ``(B,)`` or ``()`` [J]; the keywords override the stored material for this call.  HOOD/SNUG
    coefficients: :func:`torchbend.energies.materials.material_from_lame`.  ``.membrane`` is the wrapped
    :class:`~torchbend.MembraneEnergy`: of the stored material when it is given as floats (e.g. for a
    solver's :class:`~torchbend.ClothModel`), else of a unit one.
    """

    inputs = ("young", "poisson", "thickness")

    def __init__(self, faces, rest: Tensor, *, young, poisson, thickness, model="stvk"):
        super().__init__()
        self._set_material("young", young)
        self._set_material("poisson", poisson, positive=None)
        self._set_material("thickness", thickness)
        self._check_poisson(torch.as_tensor(self.poisson))
        material = (self.young, self.poisson, self.thickness)
        if not all(isinstance(v, float) for v in material):
            material = (2.0, 0.0, 1.0)  # (mu, lam) = (1, 0); only its rest-state buffers are used then
        young_f, poisson_f, thickness_f = cast("tuple[float, float, float]", material)
        self.membrane = MembraneEnergy(faces, rest, model=model, young=young_f, poisson=poisson_f,
                                       thickness=thickness_f)

    @property
    def vertex_count(self) -> int:
        return self.membrane.vertex_count

    def _check_poisson(self, nu: Tensor) -> None:
        d = nu.detach()
        if not is_traced(d) and bool(((d <= -1) | (d >= 0.5)).any()):  # (checked eagerly, not compiled)
            raise ValueError(f"{self.term_name}: poisson must lie in the open interval (-1, 0.5), got "
                             f"[{float(d.min()):g}, {float(d.max()):g}]")

    def _material(self, x: Tensor, young, poisson, thickness) -> tuple[Tensor, Tensor, Tensor]:
        """``(mu, lam, t)`` of this call, each ``()`` or ``(B,)`` in the dtype of ``x``."""
        name = self.term_name
        Y = per_sample(self.young if young is None else young, "young", x, name, positive=True)
        nu = per_sample(self.poisson if poisson is None else poisson, "poisson", x, name, positive=None)
        t = per_sample(self.thickness if thickness is None else thickness, "thickness", x, name, positive=True)
        self._check_poisson(nu)
        return Y / (2 * (1 + nu)), Y * nu / (1 - nu * nu), t

    def _parts(self, x: Tensor, mu: Tensor, lam: Tensor, t: Tensor, gradient: bool) -> Tensor:
        """The energy (or its gradient): one call when the material is one scalar set that needs no
        gradient, else the exact split into the parts of unit ``mu`` and unit ``lam``."""
        mem = self.membrane
        D, area = mem.shape_matrices.to(x.dtype), mem.rest_areas.to(x.dtype)
        ones = x.new_ones(x.shape[:-2])

        compiled = mem._selected("gradient" if gradient else "energy", None, x) is Backend.NATIVE

        def call(m, l, coef):
            if gradient:
                return _membrane_fn.gradient_function(mem.model, compiled).apply(ones, x, mem.faces, D, coef, m, l)
            return _membrane_fn.energy_function(mem.model, compiled).apply(x, mem.faces, D, coef, m, l)

        uses_lam = mem.model in _USES_LAMBDA
        if mu.ndim == 0 and lam.ndim == 0 and t.ndim == 0 and not any(p.requires_grad for p in (mu, lam, t)):
            return call(mu, lam if uses_lam else torch.zeros_like(lam), area * t)
        zero, one = x.new_zeros(()), x.new_ones(())

        def scale(c: Tensor) -> Tensor:
            return c[..., None, None] if gradient and c.ndim else c

        out = scale(t * mu) * call(one, zero, area)
        if uses_lam:
            out = out + scale(t * lam) * call(zero, one, area)
        return out

    def forward(self, x: Tensor, *, young=None, poisson=None, thickness=None) -> Tensor:
        x = self._positions(x, self.vertex_count, self.membrane.faces.device)
        return self._parts(x, *self._material(x, young, poisson, thickness), gradient=False)

    def gradient(self, x: Tensor, *, young=None, poisson=None, thickness=None) -> Tensor:
        """``dE/dx (B, V, 3)`` or ``(V, 3)`` [N], closed form and differentiable (analytic HVP)."""
        x = self._positions(x, self.vertex_count, self.membrane.faces.device)
        return self._parts(x, *self._material(x, young, poisson, thickness), gradient=True)

    def extra_repr(self) -> str:
        return f"model={self.membrane.model.value}, faces={self.membrane.face_count}"


class Bending(LossTerm):
    """Hinge bending energy ``k sum_h 3 |e|^2/(A_A + A_B) (phi(theta) - phi(theta_rest))^2`` [J] with a
    per-sample stiffness.

    Args:
        faces: ``(F, 3)`` int triangles, consistently oriented (or a :class:`~torchbend.HingeTopology`).
        rest: ``(V, 3)`` rest positions [m] (weights and default rest angles).
        stiffness: ``k`` [N m] (>= 0), a float or a tensor ``()``/``(B,)`` (per sample; an
            ``nn.Parameter`` is learnable).  For a per-hinge stiffness put a
            :class:`~torchbend.BendingEnergy` in the :class:`ClothLoss` directly.
            :func:`~torchbend.stiffness_from_material`, :func:`~torchbend.energies.materials.bending_stiffness_from_hood`.
        model: ``"quadratic"`` (default, see the module docstring) ``| "tan" | "sin"``.
        rest_angles: ``(H,)`` [rad], default those of ``rest``.

    ``forward(x, *, bending_stiffness=None)``: ``x (B, V, 3)`` or ``(V, 3)`` [m] -> ``(B,)`` or ``()``
    [J]; ``bending_stiffness`` overrides the stored stiffness for this call.  ``.bending`` is the
    wrapped :class:`~torchbend.BendingEnergy` of unit stiffness.
    """

    inputs = ("bending_stiffness",)

    def __init__(self, faces, rest: Tensor, stiffness, *, model="quadratic", rest_angles=None):
        super().__init__()
        self.bending = BendingEnergy(faces, rest, model=model, stiffness=1.0, rest_angles=rest_angles)
        self._set_material("stiffness", stiffness, positive=False)

    @property
    def vertex_count(self) -> int:
        return self.bending.vertex_count

    def _k(self, x: Tensor, bending_stiffness) -> Tensor:
        x = self._positions(x, self.vertex_count, self.bending.hinges.device)
        return per_sample(self.stiffness if bending_stiffness is None else bending_stiffness, "bending_stiffness",
                          x, self.term_name)

    def forward(self, x: Tensor, *, bending_stiffness=None) -> Tensor:
        return self._k(x, bending_stiffness) * self.bending(x)

    def gradient(self, x: Tensor, *, bending_stiffness=None) -> Tensor:
        """``dE/dx (B, V, 3)`` or ``(V, 3)`` [N], closed form and differentiable (analytic HVP)."""
        k = self._k(x, bending_stiffness)
        return (k[..., None, None] if k.ndim else k) * self.bending.gradient(x)

    def extra_repr(self) -> str:
        return f"model={self.bending.model.value}, hinges={self.bending.hinge_count}"
