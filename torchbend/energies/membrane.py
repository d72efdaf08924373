"""Triangle membrane (stretch) energies as an ``nn.Module`` (Smith, De Goes & Kim 2019).

Energy [J]: ``sum_T A_T t Psi(F_T)`` with the deformation gradient ``F`` of each triangle and the
isotropic densities of :mod:`torchbend.ops.membrane` (``stvk``, ``arap``, ``symmetric_dirichlet``,
``neohookean``; formulas and the closed-form eigensystem there).  The backward of ``forward`` is the
closed-form gradient and its backward the Hessian-vector product through the eigensystem
(:mod:`torchbend.energies._membrane_fn`); projecting the six closed-form eigenvalues (``clamp``,
``abs``) gives PSD element Hessians without a numerical eigendecomposition.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from .. import backends
from .._checks import check_direction, check_positions, positive
from ..backends import native
from ..mesh.topology import mesh_and_rest
from ..ops.membrane import (
    MembraneModel,
    check_collapsed,
    deformation,
    deformation_gradient,
    eigensystem,
    rest_shape_matrices,
    stvk_blocks,
    stvk_hvp_stress,
)
from ..ops.projection import project_eigenvalues
from ..options import Projection, projection_argument
from . import _membrane_fn as fn
from .materials import lame_parameters
from .sparse import StencilPattern

__all__ = ["MembraneEnergy", "MEMBRANE_PROJECTIONS"]

MEMBRANE_PROJECTIONS = frozenset({Projection.NONE, Projection.CLAMP, Projection.ABS})
"""The projections a membrane supports (of its closed-form eigenvalues)."""


class _MembraneData(nn.Module):
    """The mesh, rest shapes and material of a :class:`MembraneEnergy` (its constructor) and the checks of its
    inputs."""

    faces: Tensor  # (F, 3) int64
    shape_matrices: Tensor  # (F, 3, 2): F = X D; rows 1-2 are W = Dm^-1 (F = Ds W is what is computed)
    rest_areas: Tensor  # (F,) [m^2]
    mu: Tensor  # () [Pa]
    lam: Tensor  # () [Pa]

    def __init__(self, faces, rest_positions: Tensor, *, model="stvk", young: float, poisson: float,
                 thickness: float, check_finite: bool = True, backend="auto"):
        super().__init__()
        topo, rest_positions = mesh_and_rest(faces, rest_positions)
        self.thickness = positive(thickness, "thickness")
        mu, lam = lame_parameters(young, poisson)
        self.model = MembraneModel.parse(model)
        self.backend = backends.Backend.parse(backend)
        self.topology = topo
        self.check_finite = bool(check_finite)
        self.young, self.poisson = float(young), float(poisson)
        dev, dtype = rest_positions.device, rest_positions.dtype
        faces_t = topo.faces.to(dev)
        D, area = rest_shape_matrices(rest_positions, faces_t)
        self.register_buffer("faces", faces_t)
        self.register_buffer("shape_matrices", D)
        self.register_buffer("rest_areas", area)
        self.register_buffer("mu", rest_positions.new_tensor(mu, dtype=dtype))
        self.register_buffer("lam", rest_positions.new_tensor(lam, dtype=dtype))
        self._pattern: StencilPattern | None = None  # CSR pattern, built by the first hessian()

    @property
    def vertex_count(self) -> int:
        return self.topology.vertex_count

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])

    def _args(self, x: Tensor, op: str, backend=None):
        # compiled code checks inside the operators (torch.ops.torchbend.membrane_*): no data-dependent branch here
        check_positions(x, self.vertex_count, check_finite=self.check_finite and not torch.compiler.is_compiling())
        if x.device != self.faces.device:
            raise ValueError(f"x is on {x.device} but the module is on {self.faces.device}; move one with .to()")
        dt = x.dtype
        return self.shape_matrices.to(dt), (self.rest_areas * self.thickness).to(dt), self.mu.to(dt), self.lam.to(dt)

    def _selected(self, op: str, backend, x: Tensor, *params: Tensor) -> backends.Backend:
        """The backend of ``membrane_<op>`` (:func:`torchbend.backends.select_backend`; the operations with compiled
        kernels are the entry points ``membrane_*`` of :data:`torchbend.backends._table.ENTRY_POINTS`)."""
        return backends.select_backend(f"membrane_{op}", self.backend if backend is None else backend, x, *params)

    def extra_repr(self) -> str:
        return (f"model={self.model.value}, faces={self.face_count}, young={self.young:g}, "
                f"poisson={self.poisson:g}, thickness={self.thickness:g}")


class _MembraneHessians(_MembraneData):
    """The second order of a :class:`MembraneEnergy`: the closed-form eigensystem, the element Hessians (projected
    or not), the Hessian-vector product and the assembled Hessian."""

    def _eigen(self, x: Tensor, op: str, projection, backend, v=None):
        """``(l (..., T, 6) projected and weighted by A t, Q (..., T, 6, 6), D, v)``; ``v`` (an HVP's
        direction) is checked with the inputs, before any work."""
        projection = Projection.parse(projection, what="membrane projection", supported=MEMBRANE_PROJECTIONS)
        D, coef, mu, lam = self._args(x, op, backend)
        self._selected(op, backend, x)
        if v is not None:
            v = check_direction(v, x, self.check_finite)
        F, N = deformation(x, self.faces, D)
        check_collapsed(self.model, F, N)
        l, Q, _, _ = eigensystem(self.model, F, mu, lam, N)
        fn.check_values(self.model, "Hessian", l, F, N)
        return project_eigenvalues(l, projection) * coef[..., None], Q, D, v

    def _blocks_module(self, x: Tensor, backend, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor):
        """The module of the compiled element Hessians for ``x`` (``native`` or ``cuda``), where the backend selects
        them and they take these arguments (:func:`~torchbend.energies._membrane_fn.compiled_module`), else ``None``."""
        if self._selected("element_hessians", backend, x, mu, lam) is not backends.Backend.NATIVE:
            return None
        return fn.compiled_module(x, self.faces, D, coef, mu, lam)

    def element_eigensystems(self, x: Tensor, *, backend=None) -> tuple[Tensor, Tensor]:
        """Closed-form eigensystem of each element's energy Hessian in ``f = vec(F)``: eigenvalues
        ``(..., T, 6)`` and orthonormal eigenvectors ``(..., T, 6, 6)`` (columns) with ``Q diag(l) Q^T =
        A t d^2Psi/df^2`` (row-major ``f``, index ``2a + b``).  Order: scaling 1, scaling 2, twist, flip,
        normal 1, normal 2."""
        l, Q, _, _ = self._eigen(x, "eigensystems", None, backend)
        return l, Q

    def element_hessians(self, x: Tensor, *, projection=None, backend=None, project=None) -> Tensor:
        """Position-space element Hessians ``(..., T, 9, 9)`` [N/m] (flat index ``3*k + j``, face order):
        ``B^T (Q diag(l) Q^T) B`` from the closed-form eigensystem, eigenvalues projected first
        (``projection``; ``project=``: its deprecated alias); unprojected StVK in closed form."""
        projection = projection_argument(projection, project, "MembraneEnergy.element_hessians")
        proj = Projection.parse(projection, what="membrane projection", supported=MEMBRANE_PROJECTIONS)
        D, coef, mu, lam = self._args(x, "element_hessians", backend)
        module = self._blocks_module(x, backend, D, coef, mu, lam)
        if module is not None:
            H, finite = module.membrane_blocks(x.detach(), self.faces, D, coef, mu, lam, self.model.value, proj.value)
            if finite:
                return H  # else the eager path names the faces
        if self.model is MembraneModel.STVK and proj is Projection.NONE:  # the closed form, no eigensystem
            F = deformation_gradient(x, self.faces, D)
            H = stvk_blocks(F, D, mu, lam) * coef[..., None, None]
            fn.check_values(self.model, "Hessian", H, F)
            return H
        l, Q, D, _ = self._eigen(x, "element_hessians", proj, backend)
        # z_k = B^T q_k: (Q_k D^T)^T as a 9-vector over (vertex, axis)
        Qm = Q.transpose(-1, -2).unflatten(-1, (3, 2))  # (..., T, 6 modes, 3, 2)
        Z = (Qm @ D.transpose(-1, -2)[..., None, :, :]).transpose(-1, -2).flatten(-2)  # (..., T, 6, 9)
        return (Z.transpose(-1, -2) * l[..., None, :]) @ Z

    def hvp(self, x: Tensor, v: Tensor, *, projection=None, backend=None, project=None) -> Tensor:
        """``(d^2E/dx^2) v: (..., V, 3)``, matrix-free through the eigensystem (optionally projected:
        ``projection``; ``project=``: its deprecated alias); unprojected StVK in closed form."""
        projection = projection_argument(projection, project, "MembraneEnergy.hvp")
        proj = Projection.parse(projection, what="membrane projection", supported=MEMBRANE_PROJECTIONS)
        D, coef, mu, lam = self._args(x, "hvp", backend)
        selected = self._selected("hvp", backend, x, mu, lam)
        v = check_direction(v, x, self.check_finite)
        if selected is backends.Backend.NATIVE:
            out = fn.compiled_hvp(self.model, proj.value, x, v.expand_as(x), self.faces, D, coef, mu, lam)
            if out is not None:
                return out[0]
        if self.model is MembraneModel.STVK and proj is Projection.NONE:
            F = deformation_gradient(x, self.faces, D)
            dP = stvk_hvp_stress(F, deformation_gradient(v, self.faces, D), mu, lam) * coef[..., None, None]
            fn.check_values(self.model, "Hessian-vector product", dP, F)
            return fn.to_vertices(dP, D, self.faces, x.shape[-2])
        l, Q, D, vc = self._eigen(x, "hvp", proj, backend, v)
        assert vc is not None  # _eigen returns the checked direction when given one
        dF = deformation_gradient(vc, self.faces, D).flatten(-2)
        return fn.to_vertices(fn.hvp_faces(l, Q, dF), D, self.faces, x.shape[-2])

    def hessian(self, x: Tensor, *, projection=None, backend=None, project=None) -> Tensor:
        """Assembled Hessian, torch sparse CSR ``(3V, 3V)``, for one mesh ``x: (V, 3)`` (``projection``;
        ``project=``: its deprecated alias)."""
        projection = projection_argument(projection, project, "MembraneEnergy.hessian")
        if x.ndim != 2:
            raise ValueError(f"hessian() assembles one mesh: x must have shape ({self.vertex_count}, 3), got {tuple(x.shape)}")
        if self._pattern is None:
            self._pattern = StencilPattern(self.topology.faces.numpy(), self.vertex_count)
        pat = self._pattern
        proj = Projection.parse(projection, what="membrane projection", supported=MEMBRANE_PROJECTIONS)
        D, coef, mu, lam = self._args(x, "element_hessians", backend)
        if self._blocks_module(x, backend, D, coef, mu, lam) is native:  # blocks added as computed (no (T, 9, 9))
            values = native.membrane_assemble(x.detach(), self.faces, D, coef, mu, lam, self.model.value, proj.value,
                                              pat.element_blocks, pat.row_len, pat.nnz)
            if values is not None:
                return pat.csr(values)
        He = self.element_hessians(x, projection=proj, backend=backend)
        pos = pat.element_positions(x.device)
        return pat.csr(x.new_zeros(pat.nnz).index_add_(0, pos.reshape(-1), He.reshape(-1)))


class MembraneEnergy(_MembraneHessians):
    """Triangle membrane energy with closed-form gradient, Hessian eigensystem and projections.

    Args:
        faces: ``(F, 3)`` int triangles (validated like :class:`HingeTopology`), or a topology.
        rest_positions: ``(V, 3)`` float rest positions [m]; each triangle's rest frame.
        model: ``"stvk" | "arap" | "symmetric_dirichlet" | "neohookean"`` (keyword).
        young: Young's modulus ``Y`` [Pa] (> 0); poisson: ``nu`` in (-1, 0.5);
        thickness: ``t`` [m] (> 0).
        check_finite: check inputs for NaN/Inf.
        backend: ``"auto" | "eager" | "native"``: every model has compiled CPU and CUDA kernels, taken by
            ``"auto"``: the energy and gradient (also under a recorded graph: they sit inside the analytic autograd
            Functions), the ``hvp`` (projected or not) and the double backward, and the element Hessians (projected
            or not; ``element_hessians``, ``hessian``) without a recorded graph; other devices run eagerly.

    Energy ``(...,)`` [J] for ``x: (..., V, 3)``; ``forward`` is differentiable twice with analytic
    backward and double backward.  ``project`` arguments take ``None | "clamp" | "abs"``.

    Numerical policy (details in :mod:`torchbend.ops.membrane`): ``F`` is built from edge vectors,
    so results do not depend on where the mesh is (float32 included).  A 3x2 ``F`` cannot invert (a
    flipped triangle is a rotated one): ``J >= 0`` always.  At collapsed triangles (``J = 0``:
    collinear vertices, a collapsed edge, all at one point) ``stvk`` is exact and ``arap`` finite (the
    cone of its Hessian is evaluated with the stretches floored at ``sqrt(eps)``); ``neohookean`` and
    ``symmetric_dirichlet`` are undefined there, and every entry point raises a ``ValueError`` naming
    the faces.  A needed value that overflows the dtype (``symmetric_dirichlet`` or ``neohookean``
    very near collapse in float32) raises a ``ValueError`` too: never NaN or Inf.  These checks are
    skipped under ``torch.func`` transforms.
    """

    def forward(self, x: Tensor, *, backend=None) -> Tensor:
        """Membrane energy ``(...,)`` [J] of ``x: (..., V, 3)`` [m]."""
        D, coef, mu, lam = self._args(x, "energy", backend)
        compiled = self._selected("energy", backend, x) is backends.Backend.NATIVE
        return fn.energy_function(self.model, compiled).apply(x, self.faces, D, coef, mu, lam)

    def gradient(self, x: Tensor, *, backend=None) -> Tensor:
        """``dE/dx: (..., V, 3)`` [N], closed form (``P = U diag(psi_i) V^T``); differentiable."""
        D, coef, mu, lam = self._args(x, "gradient", backend)
        compiled = self._selected("gradient", backend, x) is backends.Backend.NATIVE
        return fn.gradient_function(self.model, compiled).apply(x.new_ones(x.shape[:-2]), x, self.faces, D, coef, mu,
                                                                lam)

    def deformation_gradients(self, x: Tensor) -> Tensor:
        """``F: (..., T, 3, 2)``."""
        return deformation_gradient(x, self.faces, self._args(x, "deformation_gradients")[0])
