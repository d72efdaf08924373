"""Physics losses as modules (beside ``sim``; imports ``mesh``, ``ops`` and ``energies``): gravity, inertia,
pinning, body contact, stretch and bending terms with batched per-sample materials, and
:class:`ClothLoss`, their weighted sum by name with per-term values for logging.

Each term maps positions ``x (B, V, 3)`` [m] (or ``(V, 3)``) to per-sample energies ``(B,)`` [J]; see
:mod:`torchbend.losses.cloth_loss` for loss scaling and :mod:`torchbend.energies.materials` for the
conversions from a material and from HOOD's/SNUG's coefficients; :mod:`torchbend.losses.hood` holds HOOD's
criteria formula by formula.
"""
from ..energies.materials import bending_stiffness_from_hood, hood_bending_coeff, material_from_lame
from . import hood
from ._base import LossTerm
from .cloth_loss import ClothLoss, energy_scale
from .contact import BodyContact, vertex_normals
from .elastic import Bending, Stretch
from .inertial import Gravity, Inertia, Pinning
from .self_contact import SelfRepulsion

__all__ = ["Bending", "BodyContact", "ClothLoss", "Gravity", "Inertia", "LossTerm", "Pinning", "SelfRepulsion", "hood", "Stretch",
           "bending_stiffness_from_hood", "energy_scale", "hood_bending_coeff", "material_from_lame",
           "vertex_normals"]
