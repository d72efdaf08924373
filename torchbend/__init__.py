"""torchbend: discrete hinge bending energies with exact closed-form derivatives for PyTorch.

The one public import path.  The package is layered, each layer importing only the
ones before it: ``mesh`` (topology, packing, procedural meshes, mesh files: ``tb.mesh.load``) ->
``ops`` (pure per-element kernels) -> ``backends`` (eager or compiled, decided in one function) ->
``energies`` (bending, membrane, colliders) -> ``sim`` (cloth model, Newton solvers, adjoint) -> ``robot`` -> ``scenes``
(YAML configs and their runner); ``losses`` (physics losses as modules for training: gravity,
inertia, pinning, contact, stretch, bending, ``ClothLoss``; HOOD's criteria in ``losses.hood``) stands beside ``sim`` and imports only
``mesh``, ``ops``, ``backends`` and ``energies``.  ``options`` (the option enums) and ``testing`` (plain autograd
references) stand beside the chain.
"""
from importlib.metadata import PackageNotFoundError, version

from . import losses, mesh, scenes
from .backends import select_backend, use_backend
from .energies import (
    BendingEnergy,
    Capsule,
    MembraneEnergy,
    Plane,
    Sphere,
    bending_stiffness_from_hood,
    hinge_angles,
    hood_bending_coeff,
    lame_parameters,
    material_from_lame,
    rest_hinge_weights,
    stiffness_from_material,
    to_scipy,
)
from .losses import ClothLoss
from .mesh import HingeTopology, PackedMeshes, pack_meshes
from .ops.membrane import MembraneModel
from .ops.psi import BendingModel
from .options import Assembly, Backend, Projection
from .sim import (
    ClothModel,
    ClothState,
    EnergyTerm,
    LinearSolver,
    MeshCollider,
    NewtonOptions,
    SelfContact,
    SolveInfo,
    StepContext,
    implicit_euler_step,
    solve_static,
    solve_static_adjoint,
)

try:
    __version__ = version("torchbend")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"

__all__ = [
    "Assembly",
    "Backend",
    "BendingEnergy",
    "BendingModel",
    "Capsule",
    "ClothLoss",
    "ClothModel",
    "ClothState",
    "EnergyTerm",
    "HingeTopology",
    "LinearSolver",
    "MembraneEnergy",
    "MembraneModel",
    "MeshCollider",
    "NewtonOptions",
    "PackedMeshes",
    "Plane",
    "Projection",
    "SelfContact",
    "SolveInfo",
    "Sphere",
    "StepContext",
    "__version__",
    "bending_stiffness_from_hood",
    "hinge_angles",
    "hood_bending_coeff",
    "implicit_euler_step",
    "lame_parameters",
    "losses",
    "material_from_lame",
    "mesh",
    "pack_meshes",
    "rest_hinge_weights",
    "scenes",
    "select_backend",
    "solve_static",
    "solve_static_adjoint",
    "stiffness_from_material",
    "to_scipy",
    "use_backend",
]
