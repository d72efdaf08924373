"""The membrane energy as a twice analytically differentiable ``torch.autograd.Function`` (private).

``_Energy``'s backward applies ``_Gradient`` (the closed-form gradient ``P = U diag(psi_i) V^T``
pulled back to positions); ``_Gradient``'s backward is the Hessian-vector product through the
closed-form eigensystem (:func:`torchbend.ops.membrane.eigensystem`).  Every forward checks its
elements first (:func:`~torchbend.ops.membrane.check_collapsed`) and its values after
(:func:`~torchbend.ops.membrane.check_finite_values`), outside ``torch.func`` transforms.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .._checks import check_direction, check_positions, is_traced
from ..backends import native
from ..backends.compile_guard import compiled_backward_guard
from ..ops.membrane import (
    MembraneModel,
    check_collapsed,
    check_finite_values,
    deformation,
    deformation_gradient,
    eigensystem,
    energy_density,
    stress,
)
from ..ops.projection import project_eigenvalues
from ..ops.stencil import scatter
from ..options import Projection

__all__ = ["energy_function", "gradient_function", "hvp_faces", "to_vertices", "check_values", "compiled_hvp", "compiled_module",
           "kernel_energy_gradient", "kernel_hvp", "kernels"]


def hvp_faces(l: Tensor, Q: Tensor, dF: Tensor) -> Tensor:
    """``Q diag(l) Q^T dF`` per element: ``l (..., T, 6)``, ``Q (..., T, 6, 6)``, ``dF (..., T, 6)`` ->
    ``(..., T, 3, 2)``."""
    c = (Q * dF[..., :, None]).sum(-2)  # coordinates in the eigenbasis
    return (Q * (l * c)[..., None, :]).sum(-1).unflatten(-1, (3, 2))


def to_vertices(G: Tensor, D: Tensor, faces: Tensor, vertex_count: int) -> Tensor:
    """Pull a per-element ``dE/dF``-like ``G (..., T, 3, 2)`` back to vertices: ``(..., V, 3)``."""
    if G.numel() == 0:  # an empty batch or no faces: nothing to sum
        return G.new_zeros(G.shape[:-3] + (vertex_count, 3))
    return scatter((G @ D.transpose(-1, -2)).transpose(-1, -2), faces, vertex_count)


def check_values(model: MembraneModel, what: str, values: Tensor, F: Tensor, N: Tensor | None = None) -> None:
    """:func:`~torchbend.ops.membrane.check_finite_values` where there are values (none in an empty batch)."""
    if values.numel():
        check_finite_values(model, what, values, F, N)


def _eager_energy(model: MembraneModel, x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor,
                  lam: Tensor) -> Tensor:
    """``E (...,)`` by the eager formulas, checked (collapse, non-finite values: the errors name the faces)."""
    F, N = deformation(x, faces, D)
    check_collapsed(model, F, N)
    psi = energy_density(model, F, mu, lam, N)
    check_values(model, "energy", psi, F, N)
    return (coef * psi).sum(-1)


def _eager_stress(model: MembraneModel, x: Tensor, faces: Tensor, D: Tensor, mu: Tensor,
                  lam: Tensor) -> tuple[Tensor, Tensor]:
    """``(psi (..., T), P (..., T, 3, 2))`` by the eager formulas, checked as :func:`_eager_energy`."""
    F, N = deformation(x, faces, D)
    check_collapsed(model, F, N)
    psi, P = stress(model, F, mu, lam, N)
    check_values(model, "gradient", P, F, N)
    return psi, P


def _pulled_back(gE: Tensor, coef: Tensor, P: Tensor, D: Tensor, faces: Tensor, vertex_count: int) -> Tensor:
    """``gE dE/dx (..., V, 3)`` from the stress ``P`` and the per-sample weight ``gE (...,)``."""
    return to_vertices((gE[..., None] * coef)[..., None, None] * P, D, faces, vertex_count)


def kernels(x: Tensor):
    """The module of the compiled membrane kernels for ``x``'s device (:mod:`torchbend.backends.native` on the CPU,
    :mod:`torchbend.backends.cuda` on CUDA), or ``None`` where they are not built (or the device has none)."""
    if x.device.type == "cpu":
        return native if native.load() is not None else None
    if x.device.type == "cuda":
        from ..backends import cuda

        return cuda if cuda.load() is not None else None
    return None


def compiled_module(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor,
                    weight: Tensor | None = None):
    """The module of the compiled membrane kernels (:func:`kernels`) where they take these arguments: CPU or CUDA,
    float32/64, one material, per-face ``coef``, not traced by a ``torch.func`` transform nor compiled; else
    ``None``."""
    if (x.device.type not in ("cpu", "cuda") or x.dtype not in (torch.float32, torch.float64) or mu.ndim
            or lam.ndim or coef.shape != faces.shape[:1] or torch.compiler.is_compiling()
            or any(is_traced(t) for t in (x, D, coef, mu, lam) + (() if weight is None else (weight,)))):
        return None
    return kernels(x)


def _compiled(model: MembraneModel, x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor,
              weight: Tensor | None) -> tuple[Tensor, Tensor | None] | None:
    """``(E (...,), weight dE/dx (..., V, 3) or None)`` by the compiled kernel
    (:func:`torchbend.backends.native.membrane_energy_gradient`) where it applies (:func:`compiled_module`) and its
    results are finite, else ``None``: the eager formulas then (also for the error that names the faces of a
    collapsed triangle or a non-finite result)."""
    module = compiled_module(x, faces, D, coef, mu, lam, weight)
    if module is None:
        return None
    if weight is not None:
        weight = weight.to(x.dtype).expand(x.shape[:-2]).reshape(-1)
    E, g = module.membrane_energy_gradient(x.detach(), faces, D, coef, mu, lam, weight, model.value)
    if not bool(torch.isfinite(E).all()) or (g is not None and not bool(torch.isfinite(g.sum()))):
        return None
    return E, g


def compiled_hvp(model: MembraneModel, projection: str, x: Tensor, v: Tensor, faces: Tensor, D: Tensor, coef: Tensor,
                 mu: Tensor, lam: Tensor, weight: Tensor | None = None) -> tuple[Tensor, Tensor] | None:
    """``(weight (d^2E/dx^2) v (..., V, 3), dE/dx . v (...,))`` by the compiled kernel
    (:func:`torchbend.backends.native.membrane_hvp`; eigenvalues projected by ``projection``) where it applies
    (:func:`compiled_module`) and its result is finite, else ``None`` (the eager formulas then)."""
    if v.shape != x.shape or v.dtype != x.dtype or v.device != x.device or is_traced(v):
        return None
    module = compiled_module(x, faces, D, coef, mu, lam, weight)
    if module is None:
        return None
    w = x.new_ones(()) if weight is None else weight.to(x.dtype)
    hv, dot = module.membrane_hvp(x.detach(), v.detach(), faces, D, coef, mu, lam, w.expand(x.shape[:-2]).reshape(-1),
                                  model.value, projection)
    if not bool(torch.isfinite(hv.sum())):
        return None
    return hv, dot


def _compiled_backward(model: MembraneModel, saved: tuple, ggx: Tensor | None) -> tuple[Tensor, Tensor] | None:
    """The gradient Function's backward by the compiled HVP (:func:`compiled_hvp`) where no graph of it is asked for
    (``create_graph=False``: grad mode is off in the backward), else ``None``."""
    if ggx is None or torch.is_grad_enabled():
        return None
    gE, x, faces, D, coef, mu, lam = saved
    return compiled_hvp(model, "none", x, ggx, faces, D, coef, mu, lam, gE)


def _gradient_tangent(model: MembraneModel, saved, t_gE: Tensor | None, t_x: Tensor | None):
    """The eager second order of the gradient Function ``gE * dE/dx`` (``saved``: its inputs): ``(dx, dg)``, its
    derivative along ``(t_gE, t_x)`` ``(..., V, 3)`` and the per-triangle ``P : dF`` ``(..., T)`` (the weight's
    cotangent, before the sum), each ``None`` where it has no input."""
    gE, x, faces, D, coef, mu, lam = saved
    F, N = deformation(x, faces, D)
    l, Q, _, P = eigensystem(model, F, mu, lam, N)
    G = dg = None
    if t_x is not None:
        check_values(model, "Hessian", l, F, N)
        dF = deformation_gradient(t_x, faces, D).flatten(-2)  # (..., T, 6)
        G = (gE[..., None] * coef)[..., None, None] * hvp_faces(l, Q, dF)
        dg = (coef[..., None, None] * P * dF.unflatten(-1, (3, 2))).sum((-1, -2))  # (..., T)
    if t_gE is not None:
        term = (t_gE[..., None] * coef)[..., None, None] * P
        G = term if G is None else G + term
    dx = None if G is None else to_vertices(G, D, faces, x.shape[-2])
    return dx, dg


def _make(model: MembraneModel, compiled: bool = False):

    class _GradientImpl(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(gE, x, faces, D, coef, mu, lam):
            out = _compiled(model, x, faces, D, coef, mu, lam, gE) if compiled else None
            if out is not None:
                return out[1]
            _, P = _eager_stress(model, x, faces, D, mu, lam)
            return _pulled_back(gE, coef, P, D, faces, x.shape[-2])

        @staticmethod
        def setup_context(ctx, inputs, output):
            gE, x, faces, D, coef, mu, lam = inputs
            ctx.save_for_backward(gE, x, faces, D, coef, mu, lam)
            ctx.save_for_forward(gE, x, faces, D, coef, mu, lam)

        @staticmethod
        def backward(ctx, ggx):
            # the compiled HVP where no graph of it is asked for (create_graph=False: grad mode is off here)
            out = _compiled_backward(model, ctx.saved_tensors, ggx) if compiled else None
            if out is not None:
                return (out[1] if ctx.needs_input_grad[0] else None), out[0], None, None, None, None, None
            dx, dg = _gradient_tangent(model, ctx.saved_tensors, None, ggx)
            dgE = None if dg is None or not ctx.needs_input_grad[0] else dg.sum(-1)
            return dgE, dx, None, None, None, None, None

        @staticmethod
        def jvp(ctx, t_gE, t_x, t_faces, t_D, t_coef, t_mu, t_lam):
            dx, _ = _gradient_tangent(model, ctx.saved_tensors, t_gE, t_x)
            return torch.zeros_like(ctx.saved_tensors[1]) if dx is None else dx

    class _EnergyImpl(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(x, faces, D, coef, mu, lam):
            out = _compiled(model, x, faces, D, coef, mu, lam, None) if compiled else None
            if out is not None:
                return out[0]
            return _eager_energy(model, x, faces, D, coef, mu, lam)

        @staticmethod
        def setup_context(ctx, inputs, output):
            x, faces, D, coef, mu, lam = inputs
            ctx.save_for_backward(x, faces, D, coef, mu, lam)
            ctx.save_for_forward(x, faces, D, coef, mu, lam)

        @staticmethod
        def backward(ctx, gE):
            gE = compiled_backward_guard(gE)
            x, faces, D, coef, mu, lam = ctx.saved_tensors
            return _Gradient.apply(gE, x, faces, D, coef, mu, lam), None, None, None, None, None

        @staticmethod
        def jvp(ctx, t_x, t_faces, t_D, t_coef, t_mu, t_lam):
            x, faces, D, coef, mu, lam = ctx.saved_tensors
            F, N = deformation(x, faces, D)
            _, P = stress(model, F, mu, lam, N)
            dF = deformation_gradient(t_x, faces, D)
            return (coef[..., None, None] * P * dF).sum((-1, -2, -3))

    name = "".join(w.capitalize() for w in model.value.split("_")) + ("Compiled" if compiled else "")
    _Gradient = type(f"{name}MembraneGradient", (_GradientImpl,), {"__module__": __name__})
    _Energy = type(f"{name}MembraneEnergy", (_EnergyImpl,), {"__module__": __name__})
    return _Energy, _Gradient


_FUNCTIONS = {(m, c): _make(m, c) for m in MembraneModel for c in (False, True)}


# ------------------------------------------------------------------------------ the operators torch.compile traces
def kernel_energy_gradient(x: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor, weight: Tensor,
                           gradient: bool, model: str) -> tuple[Tensor, Tensor]:
    """The kernel of ``torch.ops.torchbend.membrane_energy_gradient``: ``(E (...,), weight dE/dx (..., V, 3) or
    empty)`` by the compiled kernel where it applies, else (other devices, a collapsed or overflowing triangle) by
    the eager formulas, whose checks raise the ValueError that names the faces."""
    m = MembraneModel.parse(model)
    out = _compiled(m, x, faces, D, coef, mu, lam, weight if gradient else None)
    if out is not None:
        E, g = out
        return E, (g if g is not None else x.new_empty(0))
    check_positions(x, x.shape[-2], check_finite=True)  # a non-finite input is named as such
    if not gradient:
        return _eager_energy(m, x, faces, D, coef, mu, lam), x.new_empty(0)
    psi, P = _eager_stress(m, x, faces, D, mu, lam)
    return (coef * psi).sum(-1), _pulled_back(weight.to(x.dtype).expand(x.shape[:-2]), coef, P, D, faces, x.shape[-2])


def kernel_hvp(x: Tensor, v: Tensor, faces: Tensor, D: Tensor, coef: Tensor, mu: Tensor, lam: Tensor, weight: Tensor,
               model: str, projection: str) -> tuple[Tensor, Tensor]:
    """The kernel of ``torch.ops.torchbend.membrane_hvp``: ``(weight H v (..., V, 3), dE/dx . v (...,))`` with the
    eigenvalues projected by ``projection``, compiled where it applies, else by the eigensystem's eager formulas."""
    m = MembraneModel.parse(model)
    out = compiled_hvp(m, projection, x, v, faces, D, coef, mu, lam, weight)
    if out is not None:
        return out
    check_positions(x, x.shape[-2], check_finite=True)
    check_direction(v, x, True)
    F, N = deformation(x, faces, D)
    check_collapsed(m, F, N)
    l, Q, _, P = eigensystem(m, F, mu, lam, N)
    check_values(m, "Hessian", l, F, N)
    dF = deformation_gradient(v, faces, D).flatten(-2)
    w = weight.to(x.dtype).expand(x.shape[:-2])[..., None] * coef
    hv = to_vertices(w[..., None, None] * hvp_faces(project_eigenvalues(l, Projection(projection)), Q, dF), D, faces,
                     x.shape[-2])
    return hv, (coef[..., None, None] * P * dF.unflatten(-1, (3, 2))).sum((-1, -2, -3))


def _make_kernel(model: MembraneModel):
    """The pair of Functions that ``torch.compile`` traces (the operators above): no ``jvp`` and no vmap rule
    (Dynamo does not trace Functions that define a custom ``jvp``), ``ctx`` in ``forward``.  The energy's forward
    computes the gradient in the same pass when it will be differentiated; a double backward that records a graph
    goes to the eager pair (and, through a compiled region, to the guard's error)."""
    code = model.value

    class _GradientImpl(torch.autograd.Function):
        @staticmethod
        def forward(ctx, gE, x, faces, D, coef, mu, lam):
            ctx.save_for_backward(gE, x, faces, D, coef, mu, lam)
            return _ops().run("membrane_energy_gradient", x, faces, D, coef, mu, lam, gE, True, code)[1]

        @staticmethod
        def backward(ctx, ggx):
            gE, x, faces, D, coef, mu, lam = ctx.saved_tensors
            hv, dot = _ops().run("membrane_hvp", x, ggx, faces, D, coef, mu, lam, gE, code, "none")
            return (dot if ctx.needs_input_grad[0] else None), hv, None, None, None, None, None

    class _EnergyImpl(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x, faces, D, coef, mu, lam):
            need = ctx.needs_input_grad[0]
            E, g = _ops().run("membrane_energy_gradient", x, faces, D, coef, mu, lam, x.new_ones(x.shape[:-2]), need,
                              code)
            ctx.save_for_backward(x, faces, D, coef, mu, lam, g if need else None)
            return E

        @staticmethod
        def backward(ctx, gE):
            gE = compiled_backward_guard(gE)  # a compiled backward cannot be differentiated: a clear error
            x, faces, D, coef, mu, lam, g = ctx.saved_tensors
            if torch.is_grad_enabled():  # create_graph=True (eagerly): the differentiable gradient
                gx = _FUNCTIONS[model, True][1].apply(gE, x, faces, D, coef, mu, lam)
            else:
                gx = gE[..., None, None] * g
            return gx, None, None, None, None, None

    name = "".join(w.capitalize() for w in model.value.split("_"))
    _Gradient = type(f"{name}MembraneGradientKernel", (_GradientImpl,), {"__module__": __name__})
    _Energy = type(f"{name}MembraneEnergyKernel", (_EnergyImpl,), {"__module__": __name__})
    return _Energy, _Gradient


def _ops():
    from ..backends import ops  # imported on first use: ops registers its kernels, which import this module

    return ops


_KERNEL_FUNCTIONS = {m: _make_kernel(m) for m in MembraneModel}


def energy_function(model: MembraneModel | str, compiled: bool = False) -> type[torch.autograd.Function]:
    """The private energy Function of ``model`` (a :class:`MembraneModel` or its name); ``compiled``: its forward
    (and the gradient's, and the gradient's backward) take the compiled kernels where they apply (:func:`_compiled`);
    while ``torch.compile`` traces, the Functions of the operators ``torch.ops.torchbend.membrane_*``."""
    if compiled and torch.compiler.is_compiling():  # the operators torch.compile traces
        return _KERNEL_FUNCTIONS[MembraneModel.parse(model)][0]
    return _FUNCTIONS[MembraneModel.parse(model), bool(compiled)][0]


def gradient_function(model: MembraneModel | str, compiled: bool = False) -> type[torch.autograd.Function]:
    """The private gradient Function of ``model`` (its backward is the analytic HVP); ``compiled`` as in
    :func:`energy_function`."""
    if compiled and torch.compiler.is_compiling():
        return _KERNEL_FUNCTIONS[MembraneModel.parse(model)][1]
    return _FUNCTIONS[MembraneModel.parse(model), bool(compiled)][1]
