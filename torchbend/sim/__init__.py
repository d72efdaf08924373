"""Layer 5, simulation: the cloth model (static data) and state (:mod:`.model`), Newton solvers for
static equilibria and implicit-Euler steps over the energy terms of :mod:`.terms` (:mod:`.newton`, controlled by the options objects of :mod:`.options`, with the linear solves of :mod:`.linear`
and the line search of :mod:`.line_search`), and the implicit adjoint of a static solve (:mod:`.adjoint`)."""
from .adjoint import solve_static_adjoint
from .linearized import LinearizedHessian
from .model import ClothModel, ClothState
from .newton import SolveInfo, implicit_euler_step, solve_static
from .options import LinearSolver, NewtonOptions
from .self_contact import MeshCollider, SelfContact
from .terms import EnergyTerm, StepContext

__all__ = ["ClothModel", "ClothState", "LinearizedHessian", "EnergyTerm", "StepContext", "LinearSolver", "MeshCollider", "NewtonOptions", "SelfContact", "SolveInfo", "implicit_euler_step", "solve_static",
           "solve_static_adjoint"]
