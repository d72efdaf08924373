r"""Discrete hinge bending energy (Tamstorf & Grinspun 2013) as an ``nn.Module``.

For every interior edge (hinge, stencil and sign convention in :mod:`torchbend.topology`)::

          x2
         /  \
    A   /    \
       x0 ---> x1        e0 = x1 - x0,   theta = atan2(e0_hat . (nA x nB), nA . nB)
        \    /
    B    \  /
          x3

    E = sum_h  a_h [ k_h (phi(theta_h) - phi(rest_h))^2  +  (k_d/dt) (phi(theta_h) - phi(theta_prev_h))^2 ]

    a_h = 3 |e0_rest|^2 / (A_A_rest + A_B_rest)

* ``phi`` is the bending model (:class:`~torchbend.ops.psi.BendingModel`): ``quadratic`` (``theta``),
  ``tan`` (``2 tan(theta/2)``, paper sec. 5) or ``sin`` (``2 sin(theta/2)``);
* ``k_h`` [N m] the bending stiffness (scalar or per hinge; ``stiffness_from_material`` gives
  ``Y t^3 / (24 (1 - nu^2))``), ``rest_h`` the rest angle (by default that of the rest shape);
* the second term is the optional viscous (Rayleigh) damping of the paper's sec. 5: present only
  when the module has ``damping = k_d`` [N m s] and a call passes ``theta_prev`` and ``dt``.

Derivatives are closed form (:mod:`torchbend.ops.hinge`): the backward of ``forward`` is the
analytic gradient and its backward the analytic Hessian-vector product
(:mod:`torchbend.energies._bending_fn`); Hessians in :mod:`torchbend.energies.bending_hessian`.
"""
from __future__ import annotations

import math
from typing import Self

import torch
from torch import Tensor, nn

from .. import backends
from .._checks import check_direction, check_positions
from ..mesh.topology import HingeTopology, mesh_and_rest
from ..ops.hinge import hinge_angle
from ..ops.psi import BendingModel
from ..ops.stencil import gather
from ..options import Assembly, Backend, Projection, projection_argument
from . import _bending_fn as fn
from . import bending_hessian as hs
from .params import HingeParams, hinge_parameter, module_tensor, rest_hinge_weights
from .sparse import HessianPattern

__all__ = ["BendingEnergy", "hinge_angles"]


def hinge_angles(x: Tensor, topo: HingeTopology) -> Tensor:
    """Signed bend angles ``theta: (..., H)`` [rad] in (-pi, pi] of positions ``x: (..., V, 3)``.

    ``theta = atan2(e0_hat . (nA x nB), nA . nB)`` (stencils of :mod:`torchbend.mesh.topology`): exactly 0 for a flat hinge,
    positive where the surface bends away from its normals.  ``x`` must be finite.
    """
    if not isinstance(topo, HingeTopology):
        raise ValueError(f"topo must be a HingeTopology, got {type(topo).__name__}")
    check_positions(x, topo.vertex_count)
    return hinge_angle(gather(x, topo.hinges.to(x.device)))


class HingeModule(nn.Module):
    """The hinges of a mesh and their parameters (stiffness, rest angles, damping), validated, with the
    binding of positions to them and the choice of kernels: the base of :class:`BendingEnergy`, whose
    docstring lists the arguments."""

    hinges: Tensor  # (H, 4) int64 stencils
    weights: Tensor  # (H,) rest weights a_h
    stiffness: Tensor  # () or (H,) [N m]
    rest_angles: Tensor  # (H,) [rad]
    damping: Tensor | None  # () or (H,) [N m s]
    segments: Tensor | None  # (H,) mesh of each hinge when packed
    _inc_ptr: Tensor  # (V+1,) vertex -> stencil-slot incidence lists (native.incidence)
    _inc_idx: Tensor  # (4H,)

    def __init__(self, faces, rest_positions: Tensor, *, model: str | BendingModel = "tan",
                 stiffness: float | Tensor | None = None, rest_angles: float | Tensor | None = None,
                 damping: float | Tensor | None = None, check_finite: bool = True, backend: str | Backend = "auto"):
        super().__init__()
        if stiffness is None:
            raise TypeError(f"{type(self).__name__}: stiffness is required: the bending stiffness k [N m], scalar or (H,), "
                            "e.g. tb.stiffness_from_material(young, thickness, poisson) (cloth: about 1e-6 to 1e-4 N m)")
        topo, rest_positions = mesh_and_rest(faces, rest_positions)
        self.model = BendingModel.parse(model)
        self.backend = Backend.parse(backend)
        self.topology = topo
        self.check_finite = bool(check_finite)
        H, dtype, device = topo.hinge_count, rest_positions.dtype, rest_positions.device
        self.register_buffer("hinges", topo.hinges.to(device))
        self.register_buffer("weights", rest_hinge_weights(rest_positions, topo))
        if rest_angles is None:
            rest_angles = self._theta(rest_positions.detach())
        rest = hinge_parameter(rest_angles, "rest_angles", H, dtype, device, nonneg=False)
        if rest.ndim == 0 and not isinstance(rest, nn.Parameter):
            rest = rest.expand(H).clone()
        if self.model is BendingModel.TAN and bool((rest.detach().abs() >= math.pi).any()):
            raise ValueError("rest_angles must satisfy |theta| < pi for the 'tan' model (phi is unbounded at pi)")
        self._set("rest_angles", rest)
        self._set("stiffness", hinge_parameter(stiffness, "stiffness", H, dtype, device))
        if damping is None:
            self.damping = None
        else:
            self._set("damping", hinge_parameter(damping, "damping", H, dtype, device))
        from ..backends.native import incidence

        ptr, idx = incidence(self.hinges, topo.vertex_count)  # the compiled gradient and HVP sum through them
        self.register_buffer("_inc_ptr", ptr, persistent=False)
        self.register_buffer("_inc_idx", idx, persistent=False)
        self.register_buffer("segments", None)
        self.segment_count = 0
        self._pattern: HessianPattern | None = None  # CSR pattern, built by the first hessian()

    def _set(self, name: str, t: Tensor) -> None:
        if isinstance(t, nn.Parameter):
            self.register_parameter(name, t)
        else:
            self.register_buffer(name, t)

    @classmethod
    def packed(cls, meshes, rest_positions: Tensor | None = None, **kwargs) -> Self:
        """A module over meshes of different topologies packed into one (:func:`torchbend.pack_meshes`);
        its ``forward`` returns per-mesh energies ``(..., M)``.  ``rest_positions`` defaults to ``meshes.verts``."""
        mod = cls(meshes.faces, meshes.verts if rest_positions is None else rest_positions, **kwargs)
        dev = mod.hinges.device
        mod.segments = meshes.face_mesh.to(dev)[mod.topology.hinge_faces[:, 0].to(dev)]
        mod.segment_count = meshes.mesh_count
        return mod

    @property
    def hinge_count(self) -> int:
        return int(self.hinges.shape[0])

    @property
    def vertex_count(self) -> int:
        return self.topology.vertex_count

    def _bind(self, x: Tensor, backend, theta_prev=None, dt=None) -> tuple[HingeParams, Backend | str]:
        """Validated parameters for ``x`` and the backend asked for (``backend`` or the module's)."""
        # under torch.compile/export the finiteness check runs inside the compiled operators (data-dependent
        # Python control flow would break the graph); eagerly it runs here, before any work
        check_positions(x, self.vertex_count, check_finite=self.check_finite and not torch.compiler.is_compiling())
        if x.device != self.hinges.device:
            raise ValueError(f"x is on {x.device} but the module is on {self.hinges.device}; move one with .to()")
        p = HingeParams.bind(self, x, theta_prev, dt)
        return p, self.backend if backend is None else backend

    def _kernel(self, op: str, x: Tensor, theta_prev, dt, backend) -> tuple[HingeParams, str | None]:
        """:meth:`_bind` for the energy, gradient and HVP, then the implementation chosen for ``op``: ``"native"``
        (the compiled operators, which check that x is finite themselves: pass them ``check=self.check_finite``)
        or ``None`` (the eager closed forms, x checked here)."""
        check_positions(x, self.vertex_count, check_finite=False)
        hinges = module_tensor(self, "hinges")
        if not (x.is_cpu and hinges.is_cpu) and x.device != hinges.device:  # (comparing devices costs a microsecond)
            raise ValueError(f"x is on {x.device} but the module is on {self.hinges.device}; move one with .to()")
        p = HingeParams.bind(self, x, theta_prev, dt)
        native = backends.select_backend(op, self.backend if backend is None else backend, x,
                                         *p.tensors()) is Backend.NATIVE
        if not native and self.check_finite:
            check_positions(x, self.vertex_count)
        return p, "native" if native else None

    def _incidence(self) -> tuple[Tensor, Tensor]:
        return module_tensor(self, "_inc_ptr"), module_tensor(self, "_inc_idx")

    def angles(self, x: Tensor) -> Tensor:
        """Bend angles ``(..., H)`` [rad] of ``x`` (e.g. to pass as the next step's ``theta_prev``)."""
        check_positions(x, self.vertex_count, check_finite=self.check_finite)
        return self._theta(x)

    def _theta(self, x: Tensor) -> Tensor:
        """The angles as the energy's default path computes them (the compiled kernel where it runs), so that
        the energy and its gradient vanish bit for bit at the rest shape."""
        if backends.select_backend("energy", self.backend, x.detach()) is Backend.NATIVE:
            from ..backends import kernels

            return kernels.module(x).hinge_angles(x.detach(), self.hinges)
        return hinge_angle(gather(x, self.hinges))

    def extra_repr(self) -> str:
        return (f"model={self.model.value}, vertices={self.vertex_count}, hinges={self.hinge_count}, "
                f"damping={'yes' if self.damping is not None else 'no'}, backend={self.backend.value}")


class BendingEnergy(HingeModule):
    """Discrete hinge bending energy with exact closed-form first and second derivatives.

    Args:
        faces: ``(F, 3)`` int triangle vertex indices, consistently oriented (or a :class:`HingeTopology`).
        rest_positions: ``(V, 3)`` float rest positions [m]; defines ``a_h`` and the default rest angles.
        model: ``"quadratic" | "tan" | "sin"`` (:class:`BendingModel`), keyword.
        stiffness: ``k`` [N m], scalar or ``(H,)``, required (:func:`~torchbend.stiffness_from_material`: a cloth
            is about 1e-6 to 1e-4 N m); may be an ``nn.Parameter`` (then learnable).
        rest_angles: ``(H,)`` [rad]; defaults to the angles of ``rest_positions``.  Pass an
            ``nn.Parameter`` to learn them.
        damping: viscous coefficient ``k_d`` [N m s] (scalar or ``(H,)``) or ``None`` (no term).
        check_finite: check every input for NaN/Inf (``ValueError``); switch off for speed.
        backend: ``"auto" | "eager" | "native"`` (:func:`torchbend.backends.select_backend`); each
            method also takes ``backend=`` for one call.

    Shapes: ``x: (..., V, 3)``; leading dimensions are meshes sharing this topology.  The energy
    is ``(...,)`` [J] (``(..., M)`` for a module built by :meth:`packed` over ``M`` meshes).
    dtype and device follow ``x``; module buffers are cast to ``x.dtype`` per call.
    """

    def forward(self, x: Tensor, *, theta_prev: Tensor | None = None, dt: float | None = None, backend=None) -> Tensor:
        """Energy [J] of ``x: (..., V, 3)`` [m]: ``(...,)`` (or ``(..., M)`` when packed); ``theta_prev: (..., H)``
        and ``dt`` [s] switch on the viscous term.  Differentiable twice (analytic backward and double backward)
        in ``x``, stiffness, rest angles and ``theta_prev``."""
        p, impl = self._kernel("energy", x, theta_prev, dt, backend)
        return fn.bending_energy_raw(x, module_tensor(self, "hinges"), *p.astuple(), model=self.model,
                                     seg=module_tensor(self, "segments"),
                                     seg_count=self.segment_count, impl=impl, inc=self._incidence(),
                                     check=self.check_finite)

    def gradient(self, x: Tensor, *, theta_prev: Tensor | None = None, dt: float | None = None, backend=None) -> Tensor:
        """``dE/dx: (..., V, 3)`` [N] (summed over meshes when packed), closed form; differentiable (analytic HVP)."""
        p, impl = self._kernel("gradient", x, theta_prev, dt, backend)
        return fn.bending_gradient_raw(x, module_tensor(self, "hinges"), *p.astuple(), model=self.model, impl=impl,
                                       inc=self._incidence(), check=self.check_finite)

    def hvp(self, x: Tensor, v: Tensor, *, projection=None, theta_prev: Tensor | None = None, dt: float | None = None,
            backend=None, project=None) -> Tensor:
        """Hessian-vector product ``(d^2E/dx^2) v: (..., V, 3)``, closed form, ``v`` shaped like ``x``.

        Unprojected, per hinge ``psi'' (grad theta . v) grad theta + psi' (Hess theta) v`` with no 12x12 matrix;
        ``projection`` (:class:`~torchbend.options.Projection`) applies the projection of :meth:`hessian`
        (``project=``: its deprecated alias)."""
        projection = projection_argument(projection, project, "BendingEnergy.hvp")
        if projection is Projection.NONE:
            p, impl = self._kernel("hvp", x, theta_prev, dt, backend)
            v = check_direction(v, x, self.check_finite and impl is None)  # the compiled operator checks v itself
            return fn.bending_hvp_raw(x, v, module_tensor(self, "hinges"), *p.astuple(), model=self.model, impl=impl,
                                      inc=self._incidence(), check=self.check_finite)
        p, backend = self._bind(x, backend, theta_prev, dt)
        v = check_direction(v, x, self.check_finite)
        return hs.projected_hvp(x, v, self.hinges, p, self.model, projection, backend)

    def hinge_hessians(self, x: Tensor, *, projection=None, theta_prev: Tensor | None = None, dt: float | None = None,
                       backend=None, project=None, out: Tensor | None = None) -> Tensor:
        """Per-hinge energy Hessians ``(..., H, 12, 12)`` [J/m^2] in stencil order (flat ``3*k + j``):
        ``psi'' g g^T + psi' Hess(theta)`` (paper eqs. 3, 5, 6), optionally projected per block (``projection``;
        ``project=``: its deprecated alias).  ``out``: a buffer of that shape, x's dtype and device (contiguous),
        written and returned instead of a new tensor (the same bits); kept between calls it saves the first-touch
        page faults of fresh memory on large meshes."""
        projection = projection_argument(projection, project, "BendingEnergy.hinge_hessians")
        p, backend = self._bind(x, backend, theta_prev, dt)
        return hs.hinge_hessians(x, self.hinges, p, self.model, projection, backend, out)

    def hessian(self, x: Tensor, *, projection=None, assembly: str | Assembly = "triangle",
                theta_prev: Tensor | None = None, dt: float | None = None, backend=None, project=None,
                out: Tensor | None = None) -> Tensor:
        """Assembled Hessian, a torch sparse CSR tensor ``(3V, 3V)``, of one mesh ``x: (V, 3)``.

        ``assembly="triangle"`` is the paper's per-triangle refactoring (eq. 7), ``"hinge"`` scatters the
        12x12 blocks: the same matrix.  The CSR pattern is built once and kept on the module.  See
        :func:`torchbend.energies.bending_hessian.assemble` for the projections; :func:`torchbend.to_scipy`
        converts.  ``out``: a ``(nnz,)`` buffer of x's dtype and device for the values (``nnz``: the pattern's,
        :meth:`hessian_nnz`), written and used as the matrix's ``values()`` (the same bits as a new one)."""
        projection = projection_argument(projection, project, "BendingEnergy.hessian")
        how = Assembly.parse(assembly)
        p, backend = self._bind(x, backend, theta_prev, dt)
        if x.ndim != 2:
            raise ValueError(f"hessian() assembles one mesh: x must have shape ({self.vertex_count}, 3), got {tuple(x.shape)}")
        if self._pattern is None:
            self._pattern = HessianPattern(self.topology)
        return hs.assemble(x, self.topology, self.hinges, p, self.model, projection, how, self._pattern, backend, out)

    def hessian_nnz(self) -> int:
        """The number of stored values of :meth:`hessian`'s matrix (the size of its ``out=`` buffer)."""
        if self._pattern is None:
            self._pattern = HessianPattern(self.topology)
        return self._pattern.nnz
