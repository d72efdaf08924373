"""Layer 5, simulation: the cloth model (static data) and state, Newton solvers for static equilibria
and implicit-Euler steps, and the implicit adjoint of a static solve."""
from .adjoint import solve_static_adjoint
from .newton import ClothModel, ClothState, LinearSolver, SolveInfo, implicit_euler_step, solve_static

__all__ = ["ClothModel", "ClothState", "LinearSolver", "SolveInfo", "implicit_euler_step", "solve_static",
           "solve_static_adjoint"]
