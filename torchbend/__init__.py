"""torchbend: discrete hinge bending energies with exact closed-form derivatives for PyTorch.

The public API (SPEC sec. 2); everything else is private.
"""
from . import scenes
from .bending import BendingEnergy, PackedMeshes, hinge_angles, pack_meshes, rest_hinge_weights
from .hessian import HessianProjection, to_scipy
from .colliders import Capsule, Plane, Sphere
from .membrane import MembraneEnergy, MembraneModel, lame_parameters
from .solver import ClothModel, ClothState, SolveInfo, implicit_euler_step, solve_static
from .models import BendingModel, stiffness_from_material
from .topology import HingeTopology

__version__ = "0.1.0"

__all__ = [
    "BendingEnergy",
    "BendingModel",
    "Capsule",
    "ClothModel",
    "ClothState",
    "HessianProjection",
    "HingeTopology",
    "MembraneEnergy",
    "MembraneModel",
    "PackedMeshes",
    "Plane",
    "SolveInfo",
    "Sphere",
    "hinge_angles",
    "implicit_euler_step",
    "lame_parameters",
    "pack_meshes",
    "rest_hinge_weights",
    "scenes",
    "solve_static",
    "stiffness_from_material",
    "to_scipy",
]
