"""torchbend: discrete hinge bending energies with exact closed-form derivatives for PyTorch.

The one public import path (SPEC sec. 2).  The package is layered, each layer importing only the
ones before it: ``mesh`` (topology, packing, procedural meshes, mesh files: ``tb.mesh.load``) ->
``ops`` (pure per-element kernels) -> ``backends`` (eager or compiled, decided in one function) ->
``energies`` (bending, membrane, colliders) -> ``sim`` (cloth model, Newton solvers, adjoint) -> ``robot`` -> ``scenes``
(YAML configs and their runner).  ``options`` (the option enums) and ``testing`` (plain autograd
references) stand beside the chain.
"""
from importlib.metadata import PackageNotFoundError, version

from . import mesh, scenes
from .backends import select_backend, use_backend
from .energies import (
    BendingEnergy,
    Capsule,
    MembraneEnergy,
    Plane,
    Sphere,
    hinge_angles,
    lame_parameters,
    rest_hinge_weights,
    stiffness_from_material,
    to_scipy,
)
from .mesh import HingeTopology, PackedMeshes, pack_meshes
from .ops.membrane import MembraneModel
from .ops.psi import BendingModel
from .options import Assembly, Backend, Projection
from .sim import ClothModel, ClothState, SolveInfo, implicit_euler_step, solve_static, solve_static_adjoint

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
    "ClothModel",
    "ClothState",
    "HingeTopology",
    "MembraneEnergy",
    "MembraneModel",
    "PackedMeshes",
    "Plane",
    "Projection",
    "SolveInfo",
    "Sphere",
    "__version__",
    "hinge_angles",
    "implicit_euler_step",
    "lame_parameters",
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
