"""torchbend: discrete hinge bending energies with exact closed-form derivatives for PyTorch.

The public API (SPEC sec. 2); everything else is private.
"""
from . import scenes
from .bending import BendingEnergy, PackedMeshes, hinge_angles, pack_meshes, rest_hinge_weights
from .hessian import HessianProjection, to_scipy
from .membrane import MembraneEnergy, MembraneModel, lame_parameters
from .models import BendingModel, stiffness_from_material
from .topology import HingeTopology

__version__ = "0.1.0"

__all__ = [
    "BendingEnergy",
    "BendingModel",
    "HessianProjection",
    "HingeTopology",
    "MembraneEnergy",
    "MembraneModel",
    "PackedMeshes",
    "hinge_angles",
    "lame_parameters",
    "pack_meshes",
    "rest_hinge_weights",
    "scenes",
    "stiffness_from_material",
    "to_scipy",
]
