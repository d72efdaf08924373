r"""Static and implicit-Euler cloth solvers: Newton on the (incremental) potential with exact or
projected second-order terms.

Static equilibrium minimises ``Phi(x) = E_membrane + E_bending + E_colliders - sum_i m_i g . x_i``;
one backward-Euler step of size ``dt`` minimises the incremental potential

    Phi(x) = 1/(2 dt^2) (x - x_hat)^T M (x - x_hat) + E(x),      x_hat = x_n + dt v_n,

then sets ``v = (x - x_n)/dt``.  The viscous bending term of the paper (``k_d/dt``,
``theta_prev`` = the angles of ``x_n``) is included when the bending module has ``damping``.

Newton iteration: pinned degrees of freedom are eliminated; the direction solves ``H p = -g`` on
the free ones with the Hessian option (``"exact" | "clamp" | "abs" | "gauss_newton"``, mapped to
the bending and membrane projections; colliders drop their concave curvature term whenever a
projection is asked for), by a sparse direct solve (scipy) or matrix-free CG on Hessian-vector
products with a block-Jacobi preconditioner (truncated at negative curvature).  A direction that
is not a descent direction (possible with the indefinite exact Hessian) is replaced by a
Levenberg-regularised one.  Armijo backtracking guarantees that the potential never increases.
The iteration stops when ``|g_free| <= tol * scale`` with ``scale`` the magnitude of the resultant
gravity force ``|sum_i m_i g|`` plus, for a time step, the norm of the inertial force
``M (x_n - x_hat)/dt^2`` (a scale-aware, unit-consistent rule; without gravity, the initial
residual).  In float64 the attainable residual is limited by coordinate round-off: the bend angles
carry an absolute error of about ``eps |x| / h``, so very stiff shells on fine meshes far from the
origin have a floor; ``info.residual_history`` shows it.  Failures are reported in :class:`SolveInfo`; the input is never modified
and NaN positions are never returned.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from ..energies.bending import BendingEnergy
from ..energies.colliders import Capsule, Plane, Sphere
from ..energies.membrane import MEMBRANE_PROJECTIONS, MembraneEnergy
from ..energies.sparse import to_scipy
from ..mesh.topology import mesh_and_rest
from ..options import Option, Projection

__all__ = ["ClothModel", "ClothState", "SolveInfo", "LinearSolver", "solve_static", "implicit_euler_step"]


class LinearSolver(Option):
    """How Newton directions are solved: sparse direct factorisation or matrix-free CG."""

    __label__ = "linear_solver"

    DIRECT = "direct"
    CG = "cg"


SOLVER_PROJECTIONS = frozenset({Projection.NONE, Projection.CLAMP, Projection.ABS, Projection.GAUSS_NEWTON,
                                Projection.REDUCED})
"""``hessian=`` options of the solvers (``"exact"`` is ``none``): the bending projection; membranes get
the nearest one they support (:meth:`Projection.restricted`), colliders drop their curvature term."""


@dataclass
class ClothState:
    """Dynamic state: positions ``x (V, 3)`` [m] and velocities ``v (V, 3)`` [m/s]."""

    x: Tensor
    v: Tensor


@dataclass
class SolveInfo:
    """Outcome of a solve (never raised; inspect ``converged`` and ``message``)."""

    converged: bool = False
    iterations: int = 0
    residual: float = math.nan
    energy: float = math.nan
    line_search_failures: int = 0
    seconds: float = 0.0
    message: str = ""
    tolerance: float = math.nan
    energies: dict = field(default_factory=dict)
    energy_history: list = field(default_factory=list)
    residual_history: list = field(default_factory=list)
    regularized_steps: int = 0
    cg_iterations: int = 0
    substeps: int = 1


class ClothModel:
    """Static data of a cloth scene: only the terms it declares are built and evaluated.

    Args:
        faces: ``(F, 3)`` int triangles (or a :class:`HingeTopology`).
        rest_positions: ``(V, 3)`` [m].
        bending: a :class:`BendingEnergy` over the same mesh, or ``None``.
        membrane: a :class:`MembraneEnergy` over the same mesh, or ``None``.
        density: areal density [kg/m^2] (> 0): lumped masses, 1/3 of each triangle's rest-area mass per vertex.
        gravity: ``(3,)`` [m/s^2].
        pinned: ``(V,)`` bool mask of vertices held at their given positions (or ``None``).
        colliders: :class:`Sphere`, :class:`Plane`, :class:`Capsule` instances.
    """

    def __init__(self, faces, rest_positions, *, bending: BendingEnergy | None = None,
                 membrane: MembraneEnergy | None = None, density: float = 0.1,
                 gravity=(0.0, 0.0, -9.81), pinned=None, colliders=()):
        topo, rest = mesh_and_rest(faces, rest_positions)
        V = topo.vertex_count
        density = float(density)
        if not (density > 0 and math.isfinite(density)):
            raise ValueError(f"density must be positive and finite [kg/m^2], got {density}")
        try:
            g = torch.as_tensor(gravity, dtype=rest.dtype).reshape(3)
        except (RuntimeError, ValueError, TypeError):
            raise ValueError(f"gravity must be a 3-vector [m/s^2], got {gravity!r}") from None
        if not bool(torch.isfinite(g).all()):
            raise ValueError("gravity must be finite")
        for name, term in (("bending", bending), ("membrane", membrane)):
            if term is not None and term.vertex_count != V:
                raise ValueError(f"{name} has {term.vertex_count} vertices but the mesh has {V}")
        if bending is not None and not isinstance(bending, BendingEnergy):
            raise ValueError(f"bending must be a BendingEnergy or None, got {type(bending).__name__}")
        if membrane is not None and not isinstance(membrane, MembraneEnergy):
            raise ValueError(f"membrane must be a MembraneEnergy or None, got {type(membrane).__name__}")
        if pinned is None:
            pinned = torch.zeros(V, dtype=torch.bool)
        pinned = torch.as_tensor(pinned)
        if pinned.dtype != torch.bool:
            if pinned.ndim == 1 and not pinned.is_floating_point() and pinned.numel() != V:
                # a list of vertex indices
                if pinned.numel() and (int(pinned.min()) < 0 or int(pinned.max()) >= V):
                    raise ValueError(f"pinned indices must lie in [0, {V}), got range "
                                     f"[{int(pinned.min())}, {int(pinned.max())}]")
                mask = torch.zeros(V, dtype=torch.bool)
                mask[pinned.long()] = True
                pinned = mask
            else:
                raise ValueError(f"pinned must be a (V,) = ({V},) bool mask or a list of vertex indices")
        if pinned.shape != (V,):
            raise ValueError(f"pinned must have shape ({V},), got {tuple(pinned.shape)}")
        colliders = tuple(colliders)
        for i, c in enumerate(colliders):
            if not isinstance(c, (Sphere, Plane, Capsule)):
                raise ValueError(f"colliders[{i}] must be a Sphere, Plane or Capsule, got {type(c).__name__}")
        self.topology = topo
        self.rest_positions = rest
        self.bending, self.membrane = bending, membrane
        self.density = density
        self.gravity = g
        self.pinned = pinned.to(rest.device)
        self.colliders = colliders
        F = topo.faces
        p = rest[F]
        area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)
        self.mass = torch.zeros(V, dtype=rest.dtype).index_add_(0, F.reshape(-1), (density * area / 3).repeat_interleave(3))

    @property
    def vertex_count(self) -> int:
        return self.topology.vertex_count

    def external_force(self, dtype=None) -> Tensor:
        """Gravity force ``m_i g`` ``(V, 3)`` [N]."""
        return (self.mass[:, None] * self.gravity[None, :]).to(dtype or self.mass.dtype)

    # ---------------------------------------------------------------- potential and derivatives
    def energies(self, x: Tensor, bend_kw: dict | None = None) -> dict:
        """Per-term energies [J] (only the declared terms)."""
        bend_kw = bend_kw or {}
        out = {}
        if self.membrane is not None:
            out["membrane"] = float(self.membrane(x))
        if self.bending is not None:
            out["bending"] = float(self.bending(x, **bend_kw))
        out["gravity"] = float(-(self.external_force(x.dtype) * x).sum())
        for i, c in enumerate(self.colliders):
            out[f"collider{i}"] = float(c.energy(x))
        return out

    def potential(self, x: Tensor, bend_kw: dict | None = None) -> float:
        return sum(self.energies(x, bend_kw).values())

    def gradient(self, x: Tensor, bend_kw: dict | None = None) -> Tensor:
        g = -self.external_force(x.dtype).clone()
        if self.membrane is not None:
            g = g + self.membrane.gradient(x)
        if self.bending is not None:
            g = g + self.bending.gradient(x, **(bend_kw or {}))
        for c in self.colliders:
            g = g + c.gradient(x)
        return g

    def hessian(self, x: Tensor, option: Projection, bend_kw: dict | None = None):
        """``scipy.sparse`` Hessian ``(3V, 3V)`` of the potential (without inertia)."""
        n = 3 * self.vertex_count
        H = sp.csr_matrix((n, n))
        if self.membrane is not None:
            H = H + to_scipy(self.membrane.hessian(x, project=option.restricted(MEMBRANE_PROJECTIONS)))
        if self.bending is not None:
            H = H + to_scipy(self.bending.hessian(x, project=option, **(bend_kw or {})))
        if self.colliders:
            blocks = sum(c.hessian_blocks(x, project=option) for c in self.colliders)
            H = H + sp.block_diag(list(blocks.detach().cpu().numpy()), format="csr")
        return H.tocsr()

    def hvp(self, x: Tensor, v: Tensor, option: Projection, bend_kw: dict | None = None) -> Tensor:
        out = torch.zeros_like(x)
        if self.membrane is not None:
            out = out + self.membrane.hvp(x, v, project=option.restricted(MEMBRANE_PROJECTIONS))
        if self.bending is not None:
            out = out + self.bending.hvp(x, v, project=option, **(bend_kw or {}))
        for c in self.colliders:
            out = out + (c.hessian_blocks(x, project=option) @ v[..., None])[..., 0]
        return out

    def block_diagonal(self, x: Tensor, option: Projection, bend_kw: dict | None = None) -> Tensor:
        """Per-vertex 3x3 diagonal blocks of the Hessian ``(V, 3, 3)`` (block-Jacobi preconditioner)."""
        V = self.vertex_count
        out = x.new_zeros(V, 3, 3)
        if self.membrane is not None:
            He = self.membrane.element_hessians(x, project=option.restricted(MEMBRANE_PROJECTIONS)).unflatten(-1, (3, 3)).unflatten(-3, (3, 3))
            diag = torch.stack([He[:, k, :, k, :] for k in range(3)], 1)  # (T, 3, 3, 3)
            out = out.index_add(0, self.membrane.faces.reshape(-1), diag.reshape(-1, 3, 3))
        if self.bending is not None:
            Hb = self.bending.hinge_hessians(x, project=option, **(bend_kw or {}))
            Hb = Hb.unflatten(-1, (4, 3)).unflatten(-3, (4, 3))
            diag = torch.stack([Hb[:, k, :, k, :] for k in range(4)], 1)
            out = out.index_add(0, self.bending.hinges.reshape(-1), diag.reshape(-1, 3, 3))
        for c in self.colliders:
            out = out + c.hessian_blocks(x, project=option)
        return out


# -------------------------------------------------------------------- Newton
def _pcg(apply, b: np.ndarray, precond, tol: float, maxiter: int):
    """Preconditioned CG, truncated at negative curvature (Steihaug); returns ``(p, iterations)``."""
    x = np.zeros_like(b)
    r = b.copy()
    z = precond(r)
    d = z.copy()
    rz = r @ z
    bnorm = np.linalg.norm(b)
    for it in range(1, maxiter + 1):
        Ad = apply(d)
        curv = d @ Ad
        if curv <= 0:
            return (x if it > 1 else b.copy()), it
        alpha = rz / curv
        x += alpha * d
        r -= alpha * Ad
        if np.linalg.norm(r) <= tol * bnorm:
            return x, it
        z = precond(r)
        rz_new = r @ z
        d = z + (rz_new / rz) * d
        rz = rz_new
    return x, maxiter


def _newton(model: ClothModel, x0: Tensor, *, option: Projection, linear: LinearSolver, tol: float,
            max_iters: int, inertia: tuple | None, bend_kw: dict, max_line_search: int = 30):
    """Minimise the (incremental) potential from ``x0`` (not modified).  Returns ``(x, info)``."""
    t0 = time.perf_counter()
    info = SolveInfo()
    x = x0.detach().clone()
    free = (~model.pinned).repeat_interleave(3).cpu().numpy()
    dtype = x.dtype

    if inertia is not None:
        x_hat, dt = inertia
        m3 = model.mass.to(dtype).repeat_interleave(3)
        w = m3 / (dt * dt)  # mass / dt^2 per DOF

    def phi(y):
        e = model.energies(y, bend_kw)
        if inertia is not None:
            e["inertia"] = float(0.5 * (w * ((y - x_hat).reshape(-1)) ** 2).sum())
        return sum(e.values()), e

    def grad(y):
        g = model.gradient(y, bend_kw).reshape(-1)
        if inertia is not None:
            g = g + w * (y - x_hat).reshape(-1)
        return g

    # scale of the forces: the resultant weight (plus the inertial force of a time step); without
    # gravity, the initial residual
    scale = float(model.external_force(dtype).sum(0).norm())
    if inertia is not None:
        scale += float((w * (x0 - x_hat).reshape(-1)).norm())
    if scale == 0:
        scale = float(grad(x).norm())
    scale = max(scale, torch.finfo(dtype).tiny)
    info.tolerance = tol * scale
    energy, terms = phi(x)
    info.energy_history.append(energy)
    if not math.isfinite(energy):
        info.message = "non-finite potential at the initial state"
        info.seconds = time.perf_counter() - t0
        return x0, info
    for it in range(max_iters + 1):
        g = grad(x)
        gf = g.cpu().numpy()[free]
        res = float(np.linalg.norm(gf))
        info.residual, info.energy, info.energies, info.iterations = res, energy, terms, it
        info.residual_history.append(res)
        if not math.isfinite(res):
            info.message = "non-finite gradient"
            info.seconds = time.perf_counter() - t0
            return x0, info
        if res <= info.tolerance:
            info.converged = True
            info.message = "converged"
            break
        if it == max_iters:
            info.message = f"no convergence in {max_iters} Newton iterations"
            break
        # --- direction
        if linear is LinearSolver.DIRECT:
            H = model.hessian(x, option, bend_kw)
            if inertia is not None:
                H = H + sp.diags(w.cpu().numpy())
            Hf = H[free][:, free].tocsc()
            p = _direct_solve(Hf, -gf, info)
        else:
            blocks = model.block_diagonal(x, option, bend_kw)
            if inertia is not None:
                blocks = blocks + torch.diag_embed(w.reshape(-1, 3))
            blocks = blocks + 1e-12 * blocks.diagonal(dim1=-2, dim2=-1).abs().amax() * torch.eye(3, dtype=dtype)
            inv = torch.linalg.pinv(blocks.cpu().double()).numpy()
            mask3 = free.reshape(-1, 3)

            def precond(r):
                full = np.zeros(free.shape[0])
                full[free] = r
                out = np.einsum("vij,vj->vi", inv, full.reshape(-1, 3)) * mask3
                return out.reshape(-1)[free]

            def apply(d):
                full = np.zeros(free.shape[0])
                full[free] = d
                v = torch.from_numpy(full).to(dtype).reshape(-1, 3)
                out = model.hvp(x, v, option, bend_kw).reshape(-1)
                if inertia is not None:
                    out = out + w * v.reshape(-1)
                return out.cpu().double().numpy()[free]

            forcing = min(0.1, math.sqrt(res / max(scale, 1e-300))) * 1e-2
            p, cg_it = _pcg(apply, -gf, precond, tol=max(forcing, 1e-14), maxiter=10 * len(gf))
            info.cg_iterations += cg_it
        slope = float(gf @ p)
        if not slope < 0 or not np.all(np.isfinite(p)):
            info.regularized_steps += 1
            p = -gf / max(np.linalg.norm(gf), 1e-300) * min(1.0, np.linalg.norm(gf))
            slope = float(gf @ p)
        # --- Armijo backtracking
        step = torch.zeros(free.shape[0], dtype=dtype)
        step[torch.from_numpy(free)] = torch.from_numpy(p).to(dtype)
        step = step.reshape(-1, 3)
        alpha, accepted = 1.0, False
        # below this the potential's round-off hides the decrease: fall back to the residual
        noise = 64 * torch.finfo(dtype).eps * max(abs(energy), sum(abs(v) for v in terms.values()))
        for _ in range(max_line_search):
            y = x + alpha * step
            try:
                e_new, terms_new = phi(y)
            except ValueError:  # e.g. a hinge folded through (tan model): treat as infinite energy
                e_new = math.inf
            if math.isfinite(e_new) and e_new <= energy + 1e-4 * alpha * slope:
                accepted = True
                break
            if math.isfinite(e_new) and e_new - energy <= noise and -alpha * slope <= noise:
                r_new = float(np.linalg.norm(grad(y).cpu().numpy()[free]))
                if r_new < res:
                    accepted = True
                    break
            alpha *= 0.5
        if not accepted:
            info.line_search_failures += 1
            info.message = "line search exhausted (no decrease along the Newton direction)"
            break
        x, energy, terms = y, e_new, terms_new
        info.energy_history.append(energy)
    info.seconds = time.perf_counter() - t0
    if not bool(torch.isfinite(x).all()):
        info.converged = False
        info.message = "non-finite positions"
        return x0, info
    return x, info


def _direct_solve(Hf, rhs: np.ndarray, info: SolveInfo) -> np.ndarray:
    """Sparse direct solve; a failure or non-descent direction gets Levenberg regularisation."""
    n = Hf.shape[0]
    diag_scale = float(abs(Hf.diagonal()).max()) if n else 1.0
    shift = 0.0
    for _ in range(12):
        try:
            A = Hf if shift == 0 else Hf + sp.identity(n, format="csc") * shift
            p = spla.splu(A).solve(rhs)
        except RuntimeError:  # singular
            p = None
        if p is not None and np.all(np.isfinite(p)) and float(rhs @ p) > 0:
            return p
        info.regularized_steps += 1
        shift = max(shift * 10, 1e-8 * diag_scale)
    return rhs.copy()


def _prepare_x(model: ClothModel, x, name: str = "x0") -> Tensor:
    x = torch.as_tensor(x)
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating point tensor, got dtype {x.dtype}")
    if x.shape != (model.vertex_count, 3):
        raise ValueError(f"{name} must have shape ({model.vertex_count}, 3), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} holds non-finite values")
    return x


def solve_static(model: ClothModel, x0, *, hessian: str = "exact", linear_solver: str = "direct",
                 tol: float = 1e-9, max_iters: int = 50, continuation: bool = False,
                 max_relax_steps: int = 200) -> tuple[Tensor, SolveInfo]:
    """Static equilibrium from ``x0 (V, 3)`` [m]; pinned vertices keep their ``x0`` positions.

    ``tol`` is relative to the resultant gravity force (stop when ``|g_free| <= tol |sum_i m_i g|``).
    With ``continuation=True``, a Newton solve that fails from ``x0`` (large rotations of soft
    shells) is globalised by pseudo-transient continuation: implicit-Euler steps from rest (the
    velocity is reset every step, so each step is a proximal step on the potential) with a growing
    step size, retrying Newton every few steps.  ``info.iterations`` counts all Newton iterations.
    Returns ``(x, info)``; on failure ``x`` is ``x0`` unchanged and ``info.converged`` is False."""
    x0 = _prepare_x(model, x0)
    option, linear = Projection.parse(hessian, what="hessian", supported=SOLVER_PROJECTIONS), LinearSolver.parse(linear_solver)
    if not (tol > 0):
        raise ValueError(f"tol must be positive, got {tol}")
    x, info = _newton(model, x0, option=option, linear=linear, tol=tol, max_iters=int(max_iters),
                      inertia=None, bend_kw={})
    if info.converged or not continuation:
        return (x, info) if info.converged else (x0, info)
    t0 = time.perf_counter()
    total = info.iterations
    xk, dt = x0, 1e-2
    for k in range(max_relax_steps):
        state, step_info = implicit_euler_step(model, ClothState(xk, torch.zeros_like(xk)), dt,
                                               hessian=hessian, linear_solver=linear, tol=1e-6, max_iters=30)
        total += step_info.iterations
        if not step_info.converged:
            dt *= 0.25
            continue
        xk, dt = state.x, dt * 1.5
        if k % 5 == 4:
            x, info = _newton(model, xk, option=option, linear=linear, tol=tol, max_iters=int(max_iters),
                              inertia=None, bend_kw={})
            total += info.iterations
            if info.converged:
                break
    info.iterations = total
    info.seconds = time.perf_counter() - t0
    if info.converged:
        info.message = "converged (after pseudo-transient continuation)"
        return x, info
    return x0, info


def implicit_euler_step(model: ClothModel, state: ClothState, dt: float, *, hessian: str = "exact",
                        linear_solver: str = "direct", tol: float = 1e-6, max_iters: int = 30,
                        max_substep_depth: int = 3) -> tuple[ClothState, SolveInfo]:
    """One backward-Euler step of size ``dt`` [s]: Newton on the incremental potential.

    Pinned vertices keep their positions (zero velocity).  With bending damping, the viscous term
    uses the angles of ``state.x`` as ``theta_prev``.  A step whose Newton solve fails is retried as
    two half steps (recursively, at most ``max_substep_depth`` halvings; ``info.substeps`` counts the
    solves).  If that fails too, the input state is returned unchanged with ``info.converged = False``."""
    dt = float(dt)
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError(f"dt must be positive and finite [s], got {dt}")
    if not isinstance(state, ClothState):
        raise ValueError(f"state must be a ClothState, got {type(state).__name__}")
    _prepare_x(model, state.x, "state.x")
    _prepare_x(model, state.v, "state.v")
    option, linear = Projection.parse(hessian, what="hessian", supported=SOLVER_PROJECTIONS), LinearSolver.parse(linear_solver)
    new, info = _euler_solve(model, state, dt, option, linear, tol, int(max_iters))
    if info.converged or max_substep_depth <= 0:
        info.substeps = 1
        return new, info
    t0 = time.perf_counter()
    mid, info1 = implicit_euler_step(model, state, dt / 2, hessian=hessian, linear_solver=linear_solver, tol=tol,
                                     max_iters=max_iters, max_substep_depth=max_substep_depth - 1)
    if not info1.converged:
        info1.seconds += info.seconds
        return state, info1
    end, info2 = implicit_euler_step(model, mid, dt / 2, hessian=hessian, linear_solver=linear_solver, tol=tol,
                                     max_iters=max_iters, max_substep_depth=max_substep_depth - 1)
    info2.iterations += info1.iterations + info.iterations
    info2.substeps = info1.substeps + info2.substeps
    info2.seconds = info.seconds + (time.perf_counter() - t0)
    info2.energy_history = info1.energy_history + info2.energy_history
    if not info2.converged:
        return state, info2
    info2.message = f"converged in {info2.substeps} substeps"
    return end, info2


def _euler_solve(model, state, dt, option, linear, tol, max_iters):
    x_n, v_n = state.x, state.v
    pinned = model.pinned[:, None]
    v_n = torch.where(pinned, torch.zeros_like(v_n), v_n)
    x_hat = x_n + dt * v_n
    bend_kw = {}
    if model.bending is not None and model.bending.damping is not None:
        bend_kw = {"theta_prev": model.bending.angles(x_n).detach(), "dt": dt}
    x, info = _newton(model, x_hat.clone(), option=option, linear=linear, tol=tol, max_iters=max_iters,
                      inertia=(x_hat, dt), bend_kw=bend_kw)
    if not info.converged:
        return state, info
    v = torch.where(pinned, torch.zeros_like(v_n), (x - x_n) / dt)
    return ClothState(x=x, v=v), info
