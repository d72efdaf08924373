r"""HOOD's materials: its coefficients from a physical material, torchbend's stiffness from them, and its sampler.

Bending coefficients (the factor 50)
------------------------------------
With the plate's flexural rigidity ``D = Y t^3 / (12 (1 - nu^2))`` (Young's modulus ``Y`` [Pa], thickness
``t`` [m], Poisson ratio ``nu``), the materials HOOD and SNUG use have ``bending_coeff = 50 D``: HOOD's
default 3.9626e-5 N m is exactly ``50 D`` of its default material (``lame_mu = 23600``,
``lame_lambda = 44400`` Pa, ``t = 4.7e-4`` m), and SNUG multiplies ``D`` by its ``bending_multiplier = 50``.
HOOD's hinge energy ``bending_coeff l^2 theta^2 / (8 (A_0 + A_1))`` equals torchbend's
``3 k l^2 theta^2 / (A_0 + A_1)`` for ``k = bending_coeff / 24``; torchbend's stiffness of the same
material is ``k = D / 2`` (:func:`~torchbend.stiffness_from_material`), so HOOD's cloth is
``50 / 12 = 4.17`` times stiffer in bending than the same material in torchbend.

Sampling
--------
:func:`sample_materials` draws as HOOD's ``RandomMaterial``: density and ``lame_lambda`` uniform,
``lame_mu`` and ``bending_coeff`` log-uniform, independently (so about a third of the draws have
``lame_lambda >= 2 lame_mu``: stable 2-D materials that no Poisson ratio below 1/2 describes), over the
ranges of HOOD's training configuration (:data:`HOOD_RANGES`), with the normalised values HOOD feeds its
network.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ..._checks import positive

__all__ = ["HOOD_RANGES", "BENDING_MULTIPLIER", "flexural_rigidity", "bending_coeff_from_material",
           "stiffness_from_bending_coeff", "lame_from_material", "sample_materials"]

BENDING_MULTIPLIER = 50.0
"""``bending_coeff / D`` of HOOD's and SNUG's materials (module docstring)."""

HOOD_RANGES = {"density": (4.34e-2, 0.7), "lame_mu": (15909.0, 63636.0),
               "lame_lambda": (3535.414406069427, 93333.73508005822),
               "bending_coeff": (6.370782056371576e-08, 0.0013139737991266374)}
"""HOOD's training ranges: density [kg/m^2], Lame parameters [Pa], bending coefficient [N m]."""

_LOG = {"density": False, "lame_mu": True, "lame_lambda": False, "bending_coeff": True}


def flexural_rigidity(young: float, thickness: float, poisson: float) -> float:
    """``D = Y t^3 / (12 (1 - nu^2))`` [N m]; ``Y``, ``t`` > 0, ``nu`` in (-1, 1)."""
    young, thickness = positive(young, "young"), positive(thickness, "thickness")
    if not -1.0 < poisson < 1.0:
        raise ValueError(f"poisson must lie in (-1, 1), got {poisson}")
    return young * thickness**3 / (12.0 * (1.0 - poisson**2))


def bending_coeff_from_material(young: float, thickness: float, poisson: float,
                                multiplier: float = BENDING_MULTIPLIER) -> float:
    """HOOD's/SNUG's ``bending_coeff = multiplier D`` [N m] of a material (``multiplier`` 50 as theirs)."""
    return positive(multiplier, "multiplier") * flexural_rigidity(young, thickness, poisson)


def stiffness_from_bending_coeff(bending_coeff):
    """torchbend's bending stiffness ``k`` [N m] whose hinge energy (rest lengths) equals HOOD's with
    ``bending_coeff``: ``bending_coeff / 24``.  Float or tensor."""
    return bending_coeff / 24.0


def lame_from_material(young: float, poisson: float) -> tuple[float, float]:
    """Plane-stress ``(lame_mu, lame_lambda) = (Y / (2 (1 + nu)), Y nu / (1 - nu^2))`` [Pa], ``nu`` in (-1, 1)."""
    young = positive(young, "young")
    if not -1.0 < poisson < 1.0:
        raise ValueError(f"poisson must lie in (-1, 1), got {poisson}")
    return young / (2.0 * (1.0 + poisson)), young * poisson / (1.0 - poisson**2)


def sample_materials(batch: int, *, generator: torch.Generator | None = None, ranges: dict | None = None,
                     dtype: torch.dtype = torch.float64, device=None) -> dict[str, Tensor]:
    """``batch`` materials drawn as HOOD draws them (module docstring): a dict of ``(batch,)`` tensors
    ``density`` [kg/m^2], ``lame_mu``, ``lame_lambda`` [Pa], ``bending_coeff`` [N m] and their normalised values in [0, 1]
    (``<name>_input``: relative position in the range, in log space for the log-uniform ones)."""
    if int(batch) <= 0:
        raise ValueError(f"batch must be positive, got {batch!r}")
    ranges = {**HOOD_RANGES, **(ranges or {})}
    unknown = set(ranges) - set(HOOD_RANGES)
    if unknown:
        raise ValueError(f"unknown material range(s) {sorted(unknown)}; known: {sorted(HOOD_RANGES)}")
    out: dict[str, Tensor] = {}
    for name, (lo, hi) in ranges.items():
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ValueError(f"range of {name} must satisfy 0 < min <= max < inf, got ({lo}, {hi})")
        u = torch.rand(int(batch), generator=generator, dtype=torch.float64)
        if _LOG[name]:
            value = torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
        else:
            value = lo + u * (hi - lo)
        out[name] = value.to(dtype=dtype, device=device)
        out[f"{name}_input"] = u.to(dtype=dtype, device=device)
    return out
