r"""Material constants: bending stiffness and plane-stress Lame parameters from Young's modulus,
thickness and Poisson ratio, and the conversions from and to the coefficients of HOOD and SNUG.

From a material (Young's modulus ``Y`` [Pa], thickness ``t`` [m], Poisson ratio ``nu``)
---------------------------------------------------------------------------------------
* bending (:class:`~torchbend.BendingEnergy`): ``k = Y t^3 / (24 (1 - nu^2))`` [N m]
  (:func:`stiffness_from_material`), half the plate's flexural rigidity ``D = Y t^3 / (12 (1 - nu^2))``
  (tech report sec. 2), in the hinge energy ``sum_h 3 |e|^2 / (A_A + A_B) k (theta - theta_rest)^2``;
* stretch (:class:`~torchbend.MembraneEnergy`): pass ``young``, ``poisson`` and ``thickness``
  themselves; the module uses the plane-stress Lame parameters ``mu = Y / (2 (1 + nu))``,
  ``lam = Y nu / (1 - nu^2)`` [Pa] (:func:`lame_parameters`) in ``sum_T A_T t Psi(F_T)``.

HOOD and SNUG (Grigorev et al. 2023; Santesteban et al. 2022)
--------------------------------------------------------------
Compared formula by formula with HOOD's public code (``criterions/postcvpr``); the terms that are HOOD's
formulas exactly are in :mod:`torchbend.losses.hood`:

* bending: HOOD's per-hinge energy is ``bending_coeff * l^2 / (4 (A_A + A_B)) * theta^2 / 2`` with ``l`` the
  *current* edge length and ``theta`` measured from flat; torchbend's is ``3 k |e|^2 (theta - theta_rest)^2 /
  (A_A + A_B)`` with the *rest* length and rest angles.  At rest lengths and zero rest angles the two are
  equal for ``bending_coeff = 24 k`` (:func:`hood_bending_coeff`, :func:`bending_stiffness_from_hood`); on a
  stretched garment they differ by ``(|e| / |e_rest|)^2`` per hinge, on a curved one by the rest angles.
  :class:`torchbend.losses.hood.Bending` is HOOD's formula itself.  The materials HOOD and SNUG use have
  ``bending_coeff = 50 D`` with ``D = Y t^3 / (12 (1 - nu^2))`` (HOOD's default 3.9626e-5 N m is ``50 D`` of its
  default material; SNUG's ``bending_multiplier`` is 50), while :func:`stiffness_from_material` gives
  ``k = D / 2``: for the same ``Y``, ``t``, ``nu`` HOOD's cloth is ``50 / 12 = 4.17`` times stiffer in
  bending (:mod:`torchbend.losses.hood.material`).
* stretch, Saint Venant-Kirchhoff per triangle with Green strain ``G = (F^T F - I) / 2``::

      E_T = A_T t (lame_mu |G|_F^2 + lame_lambda / 2 tr(G)^2)

  with plane-stress ``lame_mu``, ``lame_lambda`` [Pa] (e.g. HOOD's default material ``lame_mu = 23600``,
  ``lame_lambda = 44400``, ``Y = 7e4`` Pa, ``nu = 0.485``, ``t = 4.7e-4`` m): this is our ``stvk``
  membrane with ``(young, poisson) = material_from_lame(lame_mu, lame_lambda)`` and the same thickness
  when ``lame_lambda < 2 lame_mu`` (a Poisson ratio below 1/2); HOOD samples ``lame_mu`` and ``lame_lambda``
  independently, and about a third of its draws lie beyond: :class:`torchbend.losses.hood.Stretching` takes
  the Lame parameters directly (stable for ``lame_lambda > -lame_mu``).
  (A code that stores ``lame_mu t``, ``lame_lambda t`` per unit area takes ``thickness = 1``.)
* mass: their ``density`` is areal [kg/m^2] (HOOD: 0.20022 = 426 kg/m^3 x 4.7e-4 m), as ours.

Every function below takes floats or tensors (per-sample materials ``(B,)``) and returns the same kind.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .._checks import positive

__all__ = ["stiffness_from_material", "lame_parameters", "material_from_lame", "hood_bending_coeff",
           "bending_stiffness_from_hood"]

HOOD_BENDING_FACTOR = 24.0
"""``bending_coeff / k`` for equal hinge energies (module docstring)."""


def stiffness_from_material(young: float, thickness: float, poisson: float = 0.3) -> float:
    """Bending stiffness ``k = Y t^3 / (24 (1 - nu^2))`` [N m] (= D/2, tech report sec. 2).

    Args:
        young: Young's modulus ``Y`` [Pa] (> 0).
        thickness: shell thickness ``t`` [m] (> 0).
        poisson: Poisson ratio ``nu`` in (-1, 0.5].
    """
    young, thickness = positive(young, "young"), positive(thickness, "thickness")
    if not (-1.0 < poisson <= 0.5):
        raise ValueError(f"poisson must lie in (-1, 0.5], got {poisson}")
    return young * thickness**3 / (24.0 * (1.0 - poisson**2))


def lame_parameters(young: float, poisson: float) -> tuple[float, float]:
    """Plane-stress ``(mu, lam) = (Y/(2(1+nu)), Y nu/(1-nu^2))`` [Pa]; ``Y > 0``, ``nu`` in (-1, 0.5)."""
    young, poisson = positive(young, "young"), float(poisson)
    if not (-1.0 < poisson < 0.5):
        raise ValueError(f"poisson must lie in the open interval (-1, 0.5), got {poisson}")
    return young / (2.0 * (1.0 + poisson)), young * poisson / (1.0 - poisson**2)


def _values(t, name: str):
    """``t`` as a float or a floating tensor, and its values as a detached float64 tensor (for checks)."""
    if isinstance(t, Tensor):
        if not t.is_floating_point():
            t = t.to(torch.get_default_dtype())
        return t, t.detach().to(torch.float64)
    try:
        v = float(t)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or a tensor, got {type(t).__name__}") from None
    return v, torch.tensor(v, dtype=torch.float64)


def material_from_lame(mu, lam):
    """``(young, poisson)`` [Pa, -] of the plane-stress Lame parameters ``mu``, ``lam`` [Pa]: the inverse
    of :func:`lame_parameters`, ``nu = lam / (2 mu + lam)``, ``Y = 4 mu (mu + lam) / (2 mu + lam)``.

    Floats or tensors (e.g. per-sample ``(B,)``); ``mu > 0`` and ``-mu < lam < 2 mu`` (``nu`` in (-1, 0.5)),
    else ``ValueError``.  Use it for HOOD's/SNUG's ``lame_mu``, ``lame_lambda`` (module docstring).
    """
    mu, m = _values(mu, "mu")
    lam, lv = _values(lam, "lam")
    if not bool(torch.isfinite(m).all() & torch.isfinite(lv).all()):
        raise ValueError("mu and lam must be finite")
    if not bool((m > 0).all()):
        raise ValueError(f"mu must be positive, got min {float(m.min())}")
    if not bool(((lv > -m) & (lv < 2 * m)).all()):
        raise ValueError("lam must lie in (-mu, 2 mu) (Poisson ratio in (-1, 0.5)), got "
                         f"lam/mu in [{float((lv / m).min()):g}, {float((lv / m).max()):g}]")
    return 4 * mu * (mu + lam) / (2 * mu + lam), lam / (2 * mu + lam)


def _nonneg(value, name: str):
    value, v = _values(value, name)
    if not bool(torch.isfinite(v).all()) or bool((v < 0).any()):
        raise ValueError(f"{name} must be finite and non-negative, got {value!r}")
    return value


def hood_bending_coeff(stiffness):
    """HOOD's/SNUG's ``bending_coeff`` [N m] whose hinge energy equals ours with stiffness ``k`` [N m]:
    ``24 k`` (module docstring).  Float or tensor (e.g. per-sample ``(B,)``), ``>= 0``."""
    return HOOD_BENDING_FACTOR * _nonneg(stiffness, "stiffness")


def bending_stiffness_from_hood(bending_coeff):
    """Our bending stiffness ``k`` [N m] reproducing HOOD's/SNUG's bending loss with ``bending_coeff``
    [N m]: ``bending_coeff / 24`` (module docstring).  Float or tensor, ``>= 0``."""
    return _nonneg(bending_coeff, "bending_coeff") / HOOD_BENDING_FACTOR
