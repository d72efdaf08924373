"""Material constants: bending stiffness and plane-stress Lame parameters from Young's modulus,
thickness and Poisson ratio."""
from __future__ import annotations

from .._checks import positive

__all__ = ["stiffness_from_material", "lame_parameters"]


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
