r"""HOOD's training criteria, formula by formula (Grigorev et al. 2023, its public code ``criterions/postcvpr``).

Each term is an ``nn.Module`` whose ``forward(x, **inputs)`` takes the cloth prediction ``x (B, V, 3)`` or
``(V, 3)`` [m] and returns per-sample values ``(B,)`` or ``()`` [J] (HOOD averages them over the batch);
per-sample materials are floats or ``(B,)`` tensors.  They compose with :class:`~torchbend.ClothLoss`
(inputs routed by name: ``x_curr``, ``x_prev``, ``body_prev``, ``body_curr``, ``body_next``, ``iteration``,
``density``, ``lame_mu``, ``lame_lambda``, ``bending_coeff``, ``dt``, ``first_step``).

* :class:`Stretching`, :class:`Bending` (:mod:`.elastic`): StVK with Lame parameters given directly;
  HOOD's bending with the current edge length, rest areas and angles from flat, on torchbend's compiled
  hinge operators.
* :class:`Collision`, :class:`Friction` (:mod:`.body`): against a moving body mesh, nearest face centroids,
  HOOD's weight ramp and its squared-distance friction radius.
* :class:`Inertia`, :class:`Gravity` (:mod:`.mass`): HOOD's first-step ``dt`` and its y-up gravity axis.
* :mod:`.material`: the factor 50 between ``bending_coeff`` and ``D``, the conversions, HOOD's sampler.

Where torchbend's own terms (:mod:`torchbend.losses`) differ: their bending uses the rest edge length and
rest angles (Discrete Shells), their stretch takes Young's modulus and a Poisson ratio below 1/2, their
body contact is SNUG's nearest-vertex variant.  ``torchbend.testing.hood_reference_loss`` is a plain
PyTorch transcription of these formulas (the tests' reference and the benchmark's baseline).
"""
from torch import Tensor

from ..cloth_loss import ClothLoss
from .body import Collision, Friction
from .elastic import DEFAULT_MATERIAL, Bending, Stretching
from .mass import FIRST_STEP_DT, REGULAR_DT, Gravity, Inertia
from .material import (
    BENDING_MULTIPLIER,
    HOOD_RANGES,
    bending_coeff_from_material,
    flexural_rigidity,
    lame_from_material,
    sample_materials,
    stiffness_from_bending_coeff,
)

__all__ = ["criteria", "BENDING_MULTIPLIER", "Bending", "Collision", "DEFAULT_MATERIAL", "FIRST_STEP_DT", "Friction", "Gravity",
           "HOOD_RANGES", "Inertia", "REGULAR_DT", "Stretching", "bending_coeff_from_material", "flexural_rigidity",
           "lame_from_material", "sample_materials", "stiffness_from_bending_coeff"]


def criteria(faces, rest: Tensor, body_faces, *, density: float | Tensor = DEFAULT_MATERIAL["density"],
             lame_mu: float | Tensor = DEFAULT_MATERIAL["lame_mu"],
             lame_lambda: float | Tensor = DEFAULT_MATERIAL["lame_lambda"],
             bending_coeff: float | Tensor = DEFAULT_MATERIAL["bending_coeff"],
             thickness: float = DEFAULT_MATERIAL["thickness"], dt: float | Tensor = REGULAR_DT, eps: float = 2e-3,
             collision_weight: tuple[float, float] = (5e3, 5e5), friction: float = 0.5, radius: float = 3e-3,
             gravity_axis: int = 1) -> ClothLoss:
    """HOOD's six criteria as one :class:`~torchbend.ClothLoss` over positions ``x (B, V, 3)`` [m] (``faces
    (F, 3)``, ``rest (V, 3)`` [m], ``body_faces (Fb, 3)``; materials in HOOD's units, floats or ``(B,)``),
    returning the batch mean [J] (``reduction="mean"``: HOOD's batch average),
    terms named ``stretching``, ``bending``, ``inertia``, ``gravity``, ``collision``, ``friction``, with HOOD's
    defaults.  Call it as ``loss(x, x_curr=..., x_prev=..., body_prev=..., body_curr=..., body_next=...,
    iteration=...)`` (per-sample materials as keywords too); it returns ``(total, {name: value})``."""
    terms = {"stretching": Stretching(faces, rest, lame_mu=lame_mu, lame_lambda=lame_lambda, thickness=thickness),
             "bending": Bending(faces, rest, bending_coeff=bending_coeff),
             "inertia": Inertia(faces, rest, density=density, dt=dt),
             "gravity": Gravity(faces, rest, density=density, axis=gravity_axis),
             "collision": Collision(body_faces, eps=eps, weight_start=collision_weight[0],
                                    weight_max=collision_weight[1]),
             "friction": Friction(faces, rest, body_faces, density=density, mu=friction, radius=radius)}
    return ClothLoss(terms)
