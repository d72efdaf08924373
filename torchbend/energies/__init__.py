"""Layer 4, energies: ``nn.Module`` facades over the operations, with their parameters, Hessians and
sparse assembly (bending, membrane, colliders)."""
from .bending import BendingEnergy, hinge_angles
from .colliders import Capsule, Collider, Plane, Sphere
from .contact import ContactLaw, Penalty, PowerBarrier, contact_law
from .materials import (
    bending_stiffness_from_hood,
    hood_bending_coeff,
    lame_parameters,
    material_from_lame,
    stiffness_from_material,
)
from .membrane import MembraneEnergy
from .params import HingeParams, rest_hinge_weights
from .sparse import to_scipy

__all__ = ["BendingEnergy", "Capsule", "Collider", "ContactLaw", "Penalty", "PowerBarrier", "contact_law", "HingeParams", "MembraneEnergy", "Plane", "Sphere",
           "bending_stiffness_from_hood", "hinge_angles", "hood_bending_coeff", "lame_parameters", "material_from_lame",
           "rest_hinge_weights", "stiffness_from_material", "to_scipy"]
