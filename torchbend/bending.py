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

* ``phi`` is the bending model (:class:`~torchbend.models.BendingModel`): ``quadratic`` (``theta``),
  ``tan`` (``2 tan(theta/2)``, paper sec. 5) or ``sin`` (``2 sin(theta/2)``);
* ``k_h`` [N m] the bending stiffness (scalar or per hinge; ``stiffness_from_material`` gives
  ``Y t^3 / (24 (1 - nu^2))``), ``rest_h`` the rest angle (by default that of the rest shape);
* the second term is the optional viscous (Rayleigh) damping of the paper's sec. 5: present only
  when the module has ``damping = k_d`` [N m s] and a call passes ``theta_prev`` and ``dt``.

Derivatives are closed form (:mod:`torchbend.geometry`): the backward of ``forward`` is the
analytic gradient and its backward the analytic Hessian-vector product (:mod:`torchbend.autograd`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from . import autograd as _ag
from . import hessian as _hs
from . import native as _native
from ._assemble import gather, scatter
from .geometry import hinge_angle
from .geometry import hinge_angle_and_gradient as geometry_angle_and_gradient
from .models import BendingModel
from ._validate import _check_positions, _is_traced, mesh_and_rest
from .topology import HingeTopology

__all__ = ["BendingEnergy", "hinge_angles", "rest_hinge_weights", "PackedMeshes", "pack_meshes"]


def hinge_angles(x: Tensor, topo: HingeTopology) -> Tensor:
    """Signed bend angles ``theta: (..., H)`` [rad] in (-pi, pi] of positions ``x: (..., V, 3)``.

    ``theta = atan2(e0_hat . (nA x nB), nA . nB)`` (SPEC sec. 1): exactly 0 for a flat hinge,
    positive where the surface bends away from its normals.  ``x`` must be finite.
    """
    if not isinstance(topo, HingeTopology):
        raise ValueError(f"topo must be a HingeTopology, got {type(topo).__name__}")
    _check_positions(x, topo.vertex_count)
    return hinge_angle(gather(x, topo.hinges.to(x.device)))


def rest_hinge_weights(rest_positions: Tensor, topo: HingeTopology) -> Tensor:
    """``a_h = 3 |e0|^2 / (A_A + A_B)`` [dimensionless]: ``(H,)`` from rest positions ``(V, 3)`` [m].

    Raises ``ValueError`` naming the zero-length edges (with their hinge index) and the faces with
    (numerically) zero area: the weight is undefined there.
    """
    X = rest_positions.detach().to(torch.float64)
    tol = torch.finfo(rest_positions.dtype).eps
    scale = X.abs().amax().clamp_min(1.0) if X.numel() else X.new_tensor(1.0)
    E = topo.edges.to(X.device)
    elen = (X[E[:, 1]] - X[E[:, 0]]).norm(dim=-1)
    bad = torch.nonzero(~(elen > tol * scale)).reshape(-1)
    if bad.numel():
        pairs = [tuple(p) for p in E[bad[:8]].tolist()]
        hinge_ids = topo.edge_hinges.to(X.device)[bad[:8]].tolist()
        raise ValueError(
            f"rest shape has zero-length edges {pairs} (hinge index or -1 for boundary: {hinge_ids})"
            + (f" ... ({bad.numel()} in all)" if bad.numel() > 8 else "")
        )
    F = topo.faces.to(X.device)
    p0, p1, p2 = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    longest = torch.stack(((p1 - p0).norm(dim=-1), (p2 - p1).norm(dim=-1), (p0 - p2).norm(dim=-1)), 1).amax(-1)
    area2 = torch.linalg.cross(p1 - p0, p2 - p0).norm(dim=-1)  # 2 * area
    bad = torch.nonzero(~(area2 > tol * longest * longest)).reshape(-1)
    if bad.numel():
        raise ValueError(
            f"rest shape has zero-area (degenerate) triangles: faces {bad[:8].tolist()}"
            + (f" ... ({bad.numel()} in all)" if bad.numel() > 8 else "")
            + "; the bending weights 3|e|^2/(A_A+A_B) are undefined there"
        )
    H = topo.hinges.to(X.device)
    elen2 = ((X[H[:, 1]] - X[H[:, 0]]) ** 2).sum(-1)
    hf = topo.hinge_faces.to(X.device)
    area = 0.5 * area2
    a = 3.0 * elen2 / (area[hf[:, 0]] + area[hf[:, 1]])
    return a.to(rest_positions.dtype)


def _as_param(value, name: str, H: int, dtype, device, nonneg: bool = True):
    """A scalar or ``(H,)`` tensor (kept as is when it is an ``nn.Parameter``)."""
    if isinstance(value, nn.Parameter):
        t = value
    else:
        t = torch.as_tensor(value, dtype=dtype, device=device)
        if not t.is_floating_point():
            t = t.to(dtype)
    if t.ndim > 1 or (t.ndim == 1 and t.shape[0] != H):
        raise ValueError(f"{name} must be a scalar or have shape ({H},) (one per hinge), got {tuple(t.shape)}")
    d = t.detach()
    if not bool(torch.isfinite(d).all()):
        raise ValueError(f"{name} must be finite")
    if nonneg and bool((d < 0).any()):
        raise ValueError(f"{name} must be non-negative, got min {float(d.min())}")
    return t


class BendingEnergy(nn.Module):
    """Discrete hinge bending energy with exact closed-form first and second derivatives.

    Args:
        faces: ``(F, 3)`` int triangle vertex indices, consistently oriented (or a :class:`HingeTopology`).
        rest_positions: ``(V, 3)`` float rest positions [m]; defines ``a_h`` and the default rest angles.
        model: ``"quadratic" | "tan" | "sin"`` (:class:`BendingModel`), keyword.
        stiffness: ``k`` [N m], scalar or ``(H,)``; may be an ``nn.Parameter`` (then learnable).
        rest_angles: ``(H,)`` [rad]; defaults to the angles of ``rest_positions``.  Pass an
            ``nn.Parameter`` to learn them.
        damping: viscous coefficient ``k_d`` [N m s] (scalar or ``(H,)``) or ``None`` (no term).
        check_finite: check every input for NaN/Inf (``ValueError``); switch off for speed.

    Shapes: ``x: (..., V, 3)``; leading dimensions are meshes sharing this topology.  The energy
    is ``(...,)`` [J] (``(..., M)`` for a module built by :meth:`packed` over ``M`` meshes).
    dtype and device follow ``x``; module buffers are cast to ``x.dtype`` per call.
    """

    def __init__(
        self,
        faces,
        rest_positions: Tensor,
        *,
        model: str | BendingModel = "tan",
        stiffness=1.0,
        rest_angles=None,
        damping=None,
        check_finite: bool = True,
    ):
        super().__init__()
        topo, rest_positions = mesh_and_rest(faces, rest_positions)
        self.model = BendingModel.parse(model)
        self.topology = topo
        self.check_finite = bool(check_finite)
        H = topo.hinge_count
        dtype, device = rest_positions.dtype, rest_positions.device
        self.register_buffer("hinges", topo.hinges.to(device))
        self.register_buffer("weights", rest_hinge_weights(rest_positions, topo))
        if rest_angles is None:
            rest_angles = hinge_angle(gather(rest_positions.detach(), self.hinges))
        rest_angles = _as_param(rest_angles, "rest_angles", H, dtype, device, nonneg=False)
        if rest_angles.ndim == 0 and not isinstance(rest_angles, nn.Parameter):
            rest_angles = rest_angles.expand(H).clone()
        if self.model is BendingModel.TAN and bool((rest_angles.detach().abs() >= math.pi).any()):
            raise ValueError("rest_angles must satisfy |theta| < pi for the 'tan' model (phi is unbounded at pi)")
        self._set("rest_angles", rest_angles)
        self._set("stiffness", _as_param(stiffness, "stiffness", H, dtype, device))
        if damping is None:
            self.damping = None
        else:
            self._set("damping", _as_param(damping, "damping", H, dtype, device))
        self.register_buffer("segments", None)
        self.segment_count = 0

    def _set(self, name: str, t: Tensor) -> None:
        if isinstance(t, nn.Parameter):
            self.register_parameter(name, t)
        else:
            self.register_buffer(name, t)

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def packed(cls, meshes: "PackedMeshes", rest_positions: Tensor | None = None, **kwargs) -> "BendingEnergy":
        """A module over meshes of different topologies packed into one (see :func:`pack_meshes`).

        Its ``forward`` returns per-mesh energies ``(..., M)``.  ``rest_positions`` defaults to
        ``meshes.verts``."""
        rest = meshes.verts if rest_positions is None else rest_positions
        mod = cls(meshes.faces, rest, **kwargs)
        mesh_of_hinge = meshes.face_mesh.to(mod.hinges.device)[mod.topology.hinge_faces[:, 0].to(mod.hinges.device)]
        mod.segments = mesh_of_hinge
        mod.segment_count = meshes.mesh_count
        return mod

    @property
    def hinge_count(self) -> int:
        return int(self.hinges.shape[0])

    @property
    def vertex_count(self) -> int:
        return self.topology.vertex_count

    # ------------------------------------------------------------------ evaluation
    def _args(self, x: Tensor, theta_prev, dt, check_finite: bool = True):
        _check_positions(x, self.vertex_count, check_finite=self.check_finite and check_finite)
        if x.device != self.hinges.device:
            raise ValueError(f"x is on {x.device} but the module is on {self.hinges.device}; move one with .to()")
        dt_ = x.dtype
        a = self.weights.to(dt_)
        k = self.stiffness.to(dt_)
        rest = self.rest_angles.to(dt_)
        c = prev = None
        if theta_prev is not None or dt is not None:
            if self.damping is None:
                raise ValueError("theta_prev/dt given but the module has no damping (pass damping=k_d)")
            if theta_prev is None or dt is None:
                raise ValueError("viscous damping needs both theta_prev and dt")
            dt = float(dt)
            if not (dt > 0 and math.isfinite(dt)):
                raise ValueError(f"dt must be positive and finite, got {dt}")
            prev = torch.as_tensor(theta_prev, device=x.device)
            if prev.shape[-1:] != (self.hinge_count,):
                raise ValueError(
                    f"theta_prev must have shape (..., {self.hinge_count}) (one angle per hinge), got {tuple(prev.shape)}"
                )
            if self.check_finite and not _is_traced(prev) and not bool(torch.isfinite(prev.detach()).all()):
                raise ValueError("theta_prev holds non-finite values")
            prev = prev.to(dt_)
            c = self.damping.to(dt_) / dt
        return a, k, rest, c, prev

    def _native_blocks(self, x: Tensor, args: tuple, x_checked: bool):
        """``(Hb, g, psi'')`` from the fused kernel of :mod:`torchbend.native` for ``args = _args(...)``,
        or ``None`` when it is off or does not apply.  With ``x_checked=False`` the NaN/Inf check of
        ``x`` is left to the kernel's flag (or done here before a fallback); it raises as usual."""
        out = _native.bending_hessians(x, self.hinges, *args, self.model)
        if out is None or not out[3]:
            if self.check_finite and not x_checked:
                _check_positions(x, self.vertex_count)  # raises, naming the vertices, if x is not finite
            if out is None:
                return None
        return out[:3]

    def forward(self, x: Tensor, *, theta_prev: Tensor | None = None, dt: float | None = None) -> Tensor:
        """Energy [J] of ``x: (..., V, 3)`` [m]: ``(...,)`` (or ``(..., M)`` when packed).

        ``theta_prev: (..., H)`` and ``dt`` [s] switch on the viscous term (module ``damping``).
        Differentiable twice in ``x``, stiffness, rest angles and ``theta_prev`` with analytic
        backward and double backward.
        """
        a, k, rest, c, prev = self._args(x, theta_prev, dt)
        return _ag.bending_energy_raw(
            x, self.hinges, a, k, rest, c, prev, model=self.model, seg=self.segments, seg_count=self.segment_count
        )

    def gradient(self, x: Tensor, *, theta_prev: Tensor | None = None, dt: float | None = None) -> Tensor:
        """``dE/dx: (..., V, 3)`` [N] (summed over meshes when packed), closed form.

        Differentiable: its backward is the analytic HVP."""
        a, k, rest, c, prev = self._args(x, theta_prev, dt)
        return _ag.bending_gradient_raw(x, self.hinges, a, k, rest, c, prev, model=self.model)

    def hvp(
        self, x: Tensor, v: Tensor, *, project=None, theta_prev: Tensor | None = None, dt: float | None = None
    ) -> Tensor:
        """Hessian-vector product ``(d^2E/dx^2) v: (..., V, 3)`` [N/m * v], closed form.

        ``v`` has the shape of ``x`` (or broadcasts to it).  With ``project=None`` this is, per hinge,
        ``psi'' (grad theta . v) grad theta + psi' (Hess theta) v`` with no 12x12 matrix formed.
        ``project`` (see :class:`~torchbend.hessian.HessianProjection`) applies the same PSD
        projection as :meth:`hessian`, matrix-free for ``"gauss_newton"`` (``max(psi'',0)(g.v) g``)
        and through the projected 12x12 hinge blocks otherwise (for CG-type solvers)."""
        projection = _hs.HessianProjection.parse(project)
        a, k, rest, c, prev = self._args(x, theta_prev, dt)
        v = torch.as_tensor(v, device=x.device)
        if v.shape[-2:] != x.shape[-2:]:
            raise ValueError(f"v must have shape (..., {self.vertex_count}, 3) like x, got {tuple(v.shape)}")
        if self.check_finite and not _is_traced(v) and not bool(torch.isfinite(v.detach()).all()):
            raise ValueError("v holds non-finite values")
        v = v.to(x.dtype)
        if projection is None:
            return _ag.bending_hvp_raw(x, v, self.hinges, a, k, rest, c, prev, model=self.model)
        v4 = gather(v, self.hinges).flatten(-2)  # (..., H, 12)
        gn = projection is _hs.HessianProjection.GAUSS_NEWTON
        fused = None if gn else self._native_blocks(x, (a, k, rest, c, prev), x_checked=True)
        if fused is not None:  # torchbend.native: blocks in one C++ pass
            Hb, g, d2 = fused
            out = (_hs.project_blocks(Hb, projection, g, d2) @ v4[..., None])[..., 0]
            return scatter(out.unflatten(-1, (4, 3)), self.hinges, self.vertex_count)
        x4 = gather(x, self.hinges)
        theta = hinge_angle(x4)
        d1, d2 = _hs.psi_theta_derivatives(self.model, theta, a, k, rest, c, prev)
        if projection is _hs.HessianProjection.GAUSS_NEWTON:
            _, g4 = geometry_angle_and_gradient(x4)
            g = g4.flatten(-2)
            out = (d2.clamp_min(0) * (g * v4).sum(-1))[..., None] * g
        else:
            Hb, g = _hs.hinge_hessian_blocks(x4, d1, d2)
            out = (_hs.project_blocks(Hb, projection, g, d2) @ v4[..., None])[..., 0]
        return scatter(out.unflatten(-1, (4, 3)), self.hinges, self.vertex_count)

    def hinge_hessians(
        self, x: Tensor, *, project=None, theta_prev: Tensor | None = None, dt: float | None = None
    ) -> Tensor:
        """Per-hinge energy Hessians ``(..., H, 12, 12)`` [J/m^2] in stencil order (flat ``3*k + j``).

        Closed form (paper eqs. 3, 5, 6): ``psi'' g g^T + psi' Hess(theta)``; optionally projected
        to PSD per block (``project``: ``"clamp" | "abs" | "gauss_newton" | "reduced"``)."""
        projection = _hs.HessianProjection.parse(project)
        native = _native.enabled()  # the kernel checks x for NaN/Inf in its pass
        args = self._args(x, theta_prev, dt, check_finite=not native)
        fused = self._native_blocks(x, args, x_checked=False) if native else None
        if fused is not None:  # one C++ pass (same formulas)
            Hb, g, d2 = fused
        else:
            a, k, rest, c, prev = args
            x4 = gather(x, self.hinges)
            d1, d2 = _hs.psi_theta_derivatives(self.model, hinge_angle(x4), a, k, rest, c, prev)
            Hb, g = _hs.hinge_hessian_blocks(x4, d1, d2)
        return Hb if projection is None else _hs.project_blocks(Hb, projection, g, d2)

    def hessian(
        self,
        x: Tensor,
        *,
        project=None,
        assembly: str = "triangle",
        theta_prev: Tensor | None = None,
        dt: float | None = None,
    ) -> Tensor:
        """Assembled Hessian as a torch sparse CSR tensor ``(3V, 3V)`` for one mesh ``x: (V, 3)``.

        ``assembly="triangle"`` is the paper's per-triangle refactoring (eq. 7, conditional
        transpose; ``psi'' g g^T`` added per hinge); ``"hinge"`` scatters the 12x12 hinge blocks.
        Both give the same matrix.  The sparsity pattern is built once per topology and cached on
        it.  ``project``: ``None`` or a :class:`~torchbend.hessian.HessianProjection`; the
        eigenvalue projections (``clamp``, ``abs``, ``reduced``) act on whole hinge blocks, so they
        are assembled per hinge whatever ``assembly`` says; ``gauss_newton`` has no ``Hess(theta)``
        part.  Use :func:`torchbend.hessian.to_scipy` for a ``scipy.sparse.csr_matrix``.
        """
        projection = _hs.HessianProjection.parse(project)
        how = _hs.Assembly.parse(assembly)
        a, k, rest, c, prev = self._args(x, theta_prev, dt)
        if x.ndim != 2:
            raise ValueError(f"hessian() assembles one mesh: x must have shape ({self.vertex_count}, 3), got {tuple(x.shape)}")
        pat = _hs.pattern_of(self.topology)
        if projection is None and _native.enabled():  # torchbend.native: either assembly in C++
            values = _native.assemble(x, self.hinges, a, k, rest, c, prev, self.model, pat, self.topology,
                                      how is _hs.Assembly.TRIANGLE)
            if values is not None:
                return pat.csr(values)
        values = x.new_zeros(pat.nnz)
        hinge_pos = pat.hinge_pos.to(x.device)
        per_triangle = how is _hs.Assembly.TRIANGLE and projection in (None, _hs.HessianProjection.GAUSS_NEWTON)
        fused = None if per_triangle else self._native_blocks(x, (a, k, rest, c, prev), x_checked=True)
        if fused is not None:  # torchbend.native: all blocks in one C++ pass
            Hb, g, d2 = fused
            if projection is not None:
                Hb = _hs.project_blocks(Hb, projection, g, d2)
            values.index_add_(0, hinge_pos.reshape(-1), Hb.reshape(-1))
            return pat.csr(values)
        x4 = gather(x, self.hinges)
        d1, d2 = _hs.psi_theta_derivatives(self.model, hinge_angle(x4), a, k, rest, c, prev)
        if per_triangle:
            _, g4 = geometry_angle_and_gradient(x4)
            g = g4.flatten(-2)
            w = d2 if projection is None else d2.clamp_min(0)
            gg = (w[:, None] * g)[:, :, None] * g[:, None, :]
            values.index_add_(0, hinge_pos.reshape(-1), gg.reshape(-1))
            if projection is None:
                Hf = _hs.triangle_hessian_blocks(x, self.topology, d1)
                keep = pat.face_has_hinge.to(x.device)
                values.index_add_(0, pat.face_pos.to(x.device)[keep].reshape(-1), Hf[keep].reshape(-1))
        else:
            for sl in _ag._chunks(self.hinge_count):  # chunks: the blocks of one chunk stay in cache
                Hb, g = _hs.hinge_hessian_blocks(x4[sl], d1[sl], d2[sl])
                if projection is not None:
                    Hb = _hs.project_blocks(Hb, projection, g, d2[sl])
                values.index_add_(0, hinge_pos[sl].reshape(-1), Hb.reshape(-1))
        return pat.csr(values)

    def angles(self, x: Tensor) -> Tensor:
        """Bend angles ``(..., H)`` [rad] of ``x`` (e.g. to pass as the next step's ``theta_prev``)."""
        _check_positions(x, self.vertex_count, check_finite=self.check_finite)
        return hinge_angle(gather(x, self.hinges))

    def extra_repr(self) -> str:
        return (
            f"model={self.model.value}, vertices={self.vertex_count}, hinges={self.hinge_count}, "
            f"damping={'yes' if self.damping is not None else 'no'}"
        )


@dataclass(frozen=True)
class PackedMeshes:
    """Meshes of different topologies packed into one (PyTorch3D-style "packed" representation).

    Attributes:
        verts: ``(sum V_m, 3)`` concatenated vertex positions [m].
        faces: ``(sum F_m, 3)`` int64 faces with vertex indices offset into ``verts``.
        vert_offsets: ``(M + 1,)`` int64; mesh ``m`` owns vertices ``vert_offsets[m]:vert_offsets[m+1]``.
        face_mesh: ``(sum F_m,)`` int64 mesh index of each face.
    """

    verts: Tensor
    faces: Tensor
    vert_offsets: Tensor
    face_mesh: Tensor

    @property
    def mesh_count(self) -> int:
        return int(self.vert_offsets.shape[0] - 1)

    def pack(self, verts_list) -> Tensor:
        """Concatenate per-mesh positions ``[(V_m, 3)]`` (e.g. deformed states) into ``(sum V_m, 3)``."""
        sizes = (self.vert_offsets[1:] - self.vert_offsets[:-1]).tolist()
        if len(verts_list) != len(sizes):
            raise ValueError(f"expected {len(sizes)} meshes, got {len(verts_list)}")
        for m, (v, n) in enumerate(zip(verts_list, sizes)):
            if tuple(v.shape) != (n, 3):
                raise ValueError(f"mesh {m}: positions must have shape ({n}, 3), got {tuple(v.shape)}")
        return torch.cat(list(verts_list), 0)

    def unpack(self, x: Tensor) -> list[Tensor]:
        """Split packed ``(..., sum V_m, 3)`` back into per-mesh ``(..., V_m, 3)`` views."""
        sizes = (self.vert_offsets[1:] - self.vert_offsets[:-1]).tolist()
        return list(torch.split(x, sizes, dim=-2))


def pack_meshes(meshes) -> PackedMeshes:
    """Pack ``[(verts (V_m, 3), faces (F_m, 3)), ...]`` into one :class:`PackedMeshes`."""
    meshes = list(meshes)
    if not meshes:
        raise ValueError("pack_meshes needs at least one (verts, faces) pair")
    verts, faces, face_mesh, offsets = [], [], [], [0]
    for m, (v, f) in enumerate(meshes):
        v = torch.as_tensor(v)
        f = torch.as_tensor(f)
        if v.ndim != 2 or v.shape[-1] != 3:
            raise ValueError(f"mesh {m}: verts must have shape (V, 3), got {tuple(v.shape)}")
        if f.ndim != 2 or f.shape[-1] != 3:
            raise ValueError(f"mesh {m}: faces must have shape (F, 3), got {tuple(f.shape)}")
        if f.numel() and (int(f.min()) < 0 or int(f.max()) >= v.shape[0]):
            raise ValueError(f"mesh {m}: face indices must lie in [0, {v.shape[0]})")
        verts.append(v)
        faces.append(f.to(torch.int64) + offsets[-1])
        face_mesh.append(torch.full((f.shape[0],), m, dtype=torch.int64))
        offsets.append(offsets[-1] + v.shape[0])
    return PackedMeshes(
        verts=torch.cat(verts, 0),
        faces=torch.cat(faces, 0),
        vert_offsets=torch.tensor(offsets, dtype=torch.int64),
        face_mesh=torch.cat(face_mesh, 0),
    )

