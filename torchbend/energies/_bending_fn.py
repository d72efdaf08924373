"""The bending energy as a twice analytically differentiable ``torch.autograd.Function``.

Two private Functions per bending model (the public entry point is :class:`torchbend.BendingEnergy`;
the unvalidated functional entries ``bending_*_raw`` below serve tests and benchmarks):

* ``_Energy``: ``(x, hinges, a, k, rest[, c, prev]) -> E``, the energy per mesh ``(...,)`` (or per
  segment ``(..., S)`` for packed meshes).  Its ``backward`` applies ``_Gradient``.
* ``_Gradient``: ``(gE, x, hinges, a, k, rest[, c, prev]) -> (gE dE/dx, gE dE/dk, gE dE/drest[, ...])``,
  the closed-form gradient (tech report eqs. 18-21).  Its ``backward`` is the closed-form
  Hessian-vector product (paper eqs. 5-6 applied to a vector, :func:`torchbend.ops.hinge.hinge_angle_gradient_hvp`),
  so ``torch.autograd.grad(E, x, create_graph=True)`` followed by a second ``grad`` runs the analytic
  HVP and never records an autograd graph of the gradient computation.

Both define ``jvp`` (forward mode) and use ``generate_vmap_rule``, so ``torch.func.vmap``,
``jacrev``, ``jacfwd`` and ``hessian`` compose with them.  Every argument is a tensor except the
segment count of packed meshes.

Notation (per hinge): ``psi(p)`` with ``p = (theta, k, rest, c, prev)`` (:mod:`torchbend.ops.psi`);
``g = d theta/d x4`` and ``H_theta`` its Hessian.  For a cotangent ``gE`` and an input direction
``(v, t_k, t_rest, ...)``::

    d/dx   <grad, (v, t)> = gE (z_theta g + psi_theta H_theta v),     z = Hess_p(psi) (g.v, t_k, t_rest, ...)
    d/dp_j <grad, (v, t)> = gE z_j,                                    d/dgE = sum_h grad_p(psi) . (g.v, t_k, ...)

The rest weights ``a`` are constants (buffers computed from the rest shape); no gradient flows to them.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..backends import kernels
from ..backends import ops as _ops  # registers torch.ops.torchbend
from ..backends.compile_guard import compiled_backward_guard
from ..ops import hinge as geometry
from ..ops.psi import THETA, BendingModel, contract_hessian, psi_derivatives, psi_theta_derivatives
from ..ops.stencil import cat_or_none, chunks, gather_soa, scatter_soa, sliced
from .params import HingeParams

__all__ = ["energy_function", "gradient_function", "bending_energy_raw", "bending_gradient_raw", "bending_hvp_raw"]

_PARAM_SLOTS = (1, 2, 3, 4)  # K, REST, C, PREV in models' slot numbering


def _scatter_soa(vs, hinges: Tensor, vertex_count: int) -> Tensor:
    """:func:`~torchbend.ops.stencil.scatter_soa`, or the zeros ``(..., V, 3)`` when there is nothing to sum
    (an empty batch or no hinges)."""
    c = vs[0][0]
    if c.numel() == 0:
        return c.new_zeros(c.shape[:-1] + (vertex_count, 3))
    return scatter_soa(vs, hinges, vertex_count)


def _chunk_weight(gE: Tensor, seg: Tensor | None, sl) -> Tensor:
    """Per-hinge cotangent of one chunk (``(..., 1)`` broadcasts when there are no segments)."""
    return gE[..., None] if seg is None else gE[..., seg[sl]]


def _scale4(vs, s: Tensor):
    return tuple(tuple(c * s for c in v) for v in vs)


def _axpy4(s: Tensor, a, b):
    """``s a + b`` over SoA stencils."""
    return tuple(tuple(torch.addcmul(cb, ca, s) for ca, cb in zip(va, vb)) for va, vb in zip(a, b))


def _dot4(a, b) -> Tensor:
    out = a[0][0] * b[0][0]
    for i, (va, vb) in enumerate(zip(a, b)):
        for j, (ca, cb) in enumerate(zip(va, vb)):
            if i or j:
                out = torch.addcmul(out, ca, cb)
    return out


def _reduce(psi: Tensor, seg: Tensor | None, seg_count: int) -> Tensor:
    if seg is None:  # compiled code: ATen's sum behind an operator, in eager's order (ops.sum_last)
        return _ops.run("sum_last", psi) if torch.compiler.is_compiling() else psi.sum(-1)
    out = psi.new_zeros(psi.shape[:-1] + (seg_count,))
    return out.index_add(-1, seg, psi)


def _params(params) -> tuple:
    """``(k, rest)`` or ``(k, rest, c, prev)`` -> the 4 psi slots (``None`` where absent)."""
    return tuple(params) + (None,) * (4 - len(params))


def _pvec(first: Tensor | None, tangents: tuple) -> list:
    vec = [first]
    vec += [t for t in tangents] + [None] * (4 - len(tangents))
    return vec


def _dot_p(grad: list, vec: list) -> Tensor | None:
    out = None
    for gi, vi in zip(grad, vec):
        if gi is None or vi is None:
            continue
        out = gi * vi if out is None else out + gi * vi
    return out


def _psi(model: BendingModel, theta: Tensor, a: Tensor, p: list, *, hessian: bool) -> tuple[Tensor, list, dict]:
    """``psi_derivatives`` with the parameter slots ``p = [k, rest, c, prev]`` of one chunk (``hess``
    is empty without ``hessian``)."""
    psi, grad, hess = psi_derivatives(model, theta, p[0], p[1], a, p[2], p[3], hessian=hessian)
    return psi, grad, {} if hess is None else hess


def _hinge_weight(gE: Tensor, seg: Tensor | None, H: int) -> Tensor:
    """The cotangent of each hinge's energy for the kernels: one value, or ``(..., H)``."""
    if seg is not None:
        return gE[..., seg]
    return gE.reshape(1) if gE.numel() == 1 else gE[..., None].expand(*gE.shape, H)


def _gradient_forward(model: BendingModel, gE, x, hinges, seg, a, params) -> tuple:
    """``(gE dE/dx, gE dE/dk, gE dE/drest[, ...])`` chunk by chunk (closed form)."""
    V = x.shape[-2]
    gx, gps = None, [[] for _ in params]
    for sl in chunks(hinges.shape[0]):
        h = hinges[sl]
        theta, g4, _ = geometry.hinge_angle_gradient_hvp_soa(gather_soa(x, h))
        _, pg, _ = _psi(model, theta, a[sl], [sliced(t, sl) for t in _params(params)], hessian=False)
        w = _chunk_weight(gE, seg, sl)  # (..., h) or (..., 1)
        part = _scatter_soa(_scale4(g4, w * pg[THETA]), h, V)
        gx = part if gx is None else gx + part
        for i, slot in enumerate(_PARAM_SLOTS[: len(params)]):
            gps[i].append(w * pg[slot])
    return (gx,) + tuple(cat_or_none(g) for g in gps)


def _add(a: Tensor | None, b: Tensor | None) -> Tensor | None:
    if a is None:
        return b
    return a if b is None else a + b


def _position_part(hv4, g4, psi1: Tensor, coef: Tensor | None):
    """``psi' H_theta v + coef g`` over SoA stencils (``hv4`` may be ``None``: no direction in x)."""
    if hv4 is not None:
        dx4 = _scale4(hv4, psi1)
        return dx4 if coef is None else _axpy4(coef, g4, dx4)
    return None if coef is None else _scale4(g4, coef)


def _second_chunk(model: BendingModel, saved: tuple, sl: slice, t_gE, t_x, t_params):
    """One chunk of :func:`_second_order`: ``(dx4 or None, [d params], d gE per hinge, theta)``."""
    gE, x, hinges, seg, a, *params = saved
    h = hinges[sl]
    v4 = None if t_x is None else gather_soa(t_x, h)
    theta, g4, hv4 = geometry.hinge_angle_gradient_hvp_soa(gather_soa(x, h), v4)
    _, pg, ph = _psi(model, theta, a[sl], [sliced(t, sl) for t in _params(params)], hessian=True)
    w = _chunk_weight(gE, seg, sl)
    u = None if v4 is None else _dot4(g4, v4)  # g . v  (..., h)
    vec = _pvec(u, tuple(sliced(t, sl) for t in t_params))
    z = contract_hessian(ph, vec)  # Hess_p(psi) vec
    tw = None if t_gE is None else _chunk_weight(t_gE, seg, sl)
    coef = _add(None if z[THETA] is None else w * z[THETA], None if tw is None else tw * pg[THETA])
    dx4 = _position_part(hv4, g4, w * pg[THETA], coef)
    dps = []
    for slot in _PARAM_SLOTS[: len(params)]:
        d = _add(None if z[slot] is None else w * z[slot], None if tw is None else tw * pg[slot])
        if d is not None and d.shape[-1] != theta.shape[-1]:
            d = d.expand_as(theta)
        dps.append(d)
    return dx4, dps, _dot_p(pg, vec), h


def _second_order(model: BendingModel, saved: tuple, t_gE, t_x, t_params):
    """The Hessian of ``<gE, E>`` in ``(gE, x, params)`` applied to one direction.

    Shared by the gradient Function's ``backward`` (cotangents of the outputs: ``t_gE`` is ``None``)
    and ``jvp`` (tangents of the inputs).  Returns ``(dx, [d params], d gE per hinge)``."""
    x, hinges, params = saved[1], saved[2], saved[5:]
    dx, dps, dgs = None, [[] for _ in params], []
    for sl in chunks(hinges.shape[0]):
        dx4, dp, dg, h = _second_chunk(model, saved, sl, t_gE, t_x, t_params)
        if dx4 is not None:
            dx = _add(dx, _scatter_soa(dx4, h, x.shape[-2]))
        for i, d in enumerate(dp):
            dps[i].append(d)
        dgs.append(dg)
    return dx, [cat_or_none(d) for d in dps], cat_or_none(dgs)


def _energy_forward(model: BendingModel, x, hinges, seg, seg_count, a, params) -> Tensor:
    psis = []
    for sl in chunks(hinges.shape[0]):
        theta = geometry.hinge_angle_soa(gather_soa(x, hinges[sl]))  # (..., h)
        psis.append(_psi(model, theta, a[sl], [sliced(t, sl) for t in _params(params)], hessian=False)[0])
    return _reduce(psis[0] if len(psis) == 1 else torch.cat(psis, -1), seg, seg_count)


def _energy_jvp(model: BendingModel, saved: tuple, seg_count: int, t_x, t_params) -> Tensor:
    x, hinges, seg, a, *params = saved
    xs = gather_soa(x, hinges)
    u = None
    if t_x is not None:
        theta, g4, _ = geometry.hinge_angle_gradient_hvp_soa(xs)
        u = _dot4(g4, gather_soa(t_x, hinges))
    else:
        theta = geometry.hinge_angle_soa(xs)
    _, pg, _ = _psi(model, theta, a, list(_params(params)), hessian=False)
    d = _dot_p(pg, _pvec(u, tuple(t_params)))
    return _reduce(torch.zeros_like(theta) if d is None else d, seg, seg_count)


def _save_energy_inputs(ctx, inputs, output) -> None:
    """The energy Function's ``setup_context``: the inputs but ``seg_count`` saved for backward and forward mode
    (``seg_count``, an int, kept on ``ctx``)."""
    x, hinges, seg, seg_count, a, *params = inputs
    ctx.save_for_backward(x, hinges, seg, a, *params)
    ctx.save_for_forward(x, hinges, seg, a, *params)
    ctx.seg_count = seg_count


def _make(model: BendingModel):
    """The pair of Functions for one bending model (bodies in the module-level functions above)."""

    class _GradientImpl(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(gE, x, hinges, seg, a, *params):
            return _gradient_forward(model, gE, x, hinges, seg, a, params)

        @staticmethod
        def setup_context(ctx, inputs, output):
            ctx.save_for_backward(*inputs)
            ctx.save_for_forward(*inputs)

        @staticmethod
        def backward(ctx, ggx, *ggp):
            gE, seg = ctx.saved_tensors[0], ctx.saved_tensors[3]
            dx, dps, dg = _second_order(model, ctx.saved_tensors, None, ggx, tuple(ggp))
            dgE = None
            if ctx.needs_input_grad[0] and dg is not None:
                dgE = _reduce(dg, seg, gE.shape[-1] if seg is not None else 0)
            dps = [d if ctx.needs_input_grad[5 + i] else None for i, d in enumerate(dps)]
            return (dgE, dx, None, None, None, *dps)

        @staticmethod
        def jvp(ctx, t_gE, t_x, t_hinges, t_seg, t_a, *t_params):
            x, params = ctx.saved_tensors[1], ctx.saved_tensors[5:]
            dx, dps, _ = _second_order(model, ctx.saved_tensors, t_gE, t_x, tuple(t_params))
            # tangents must match the (possibly expanded) output shapes exactly
            dx = torch.zeros_like(x) if dx is None else dx
            dps = [torch.zeros_like(params[i]) if d is None else d for i, d in enumerate(dps)]
            return (dx, *dps)

    class _EnergyImpl(torch.autograd.Function):
        generate_vmap_rule = True

        @staticmethod
        def forward(x, hinges, seg, seg_count, a, *params):
            return _energy_forward(model, x, hinges, seg, seg_count, a, params)

        setup_context = staticmethod(_save_energy_inputs)

        @staticmethod
        def backward(ctx, gE):
            gE = compiled_backward_guard(gE)
            x, hinges, seg, a, *params = ctx.saved_tensors
            out = _Gradient.apply(gE, x, hinges, seg, a, *params)
            gx, gps = out[0], out[1:]
            gx = gx if ctx.needs_input_grad[0] else None
            gps = [g if ctx.needs_input_grad[5 + i] else None for i, g in enumerate(gps)]
            return (gx, None, None, None, None, *gps)

        @staticmethod
        def jvp(ctx, t_x, t_hinges, t_seg, t_seg_count, t_a, *t_params):
            return _energy_jvp(model, ctx.saved_tensors, ctx.seg_count, t_x, t_params)

    # named subclasses so that autograd nodes read e.g. "TanBendingGradientBackward"
    name = model.value.capitalize()
    _Gradient = type(f"{name}BendingGradient", (_GradientImpl,), {"__module__": __name__})
    _Energy = type(f"{name}BendingEnergy", (_EnergyImpl,), {"__module__": __name__})
    return _Energy, _Gradient


_FUNCTIONS = {m: _make(m) for m in BendingModel}


def _kernel_second_order(model: BendingModel, saved: tuple, ggx, ggp):
    """The general double backward of the kernel path (cotangents of ``gx`` and of the parameter gradients
    ``gp``) in one compiled pass: ``(dx, [d k, d rest(, d c, d prev)] per hinge, d gE per hinge)``."""
    gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx = saved
    dx, dp, dg = _ops.run("bending_second_order", x, ggx, ggp, hinges, a, k, rest, c, prev, model.value,
                                                          _hinge_weight(gE, seg, hinges.shape[0]), ptr, idx)
    n = 4 if c is not None and prev is not None else 2
    return dx, [dp[..., j] for j in range(n)], dg


def _sum_to(g: Tensor, p: Tensor) -> Tensor:
    """A per-hinge parameter gradient reduced to the parameter's shape (one value or ``(H,)``)."""
    return g.sum_to_size(p.shape) if g.shape != p.shape else g


def _kernel_double_backward(model: BendingModel, saved: tuple, needs, ggx, ggp) -> tuple:
    """The backward of the kernel path's gradient Function: cotangents ``ggx`` of ``gx`` and ``ggp`` of the
    per-hinge parameter gradients ``(..., H, 4)`` (``None`` or empty when unused)."""
    gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx = saved
    if ggp is not None and ggp.numel() == 0:
        ggp = None
    out: list = [None] * 13
    if ggx is None and ggp is None:
        return tuple(out)
    if ggp is None and not needs[0] and not any(needs[5:9]):
        # the double backward of a Newton step or of hvp(): the compiled Hessian-vector product
        w = _hinge_weight(gE, seg, hinges.shape[0])
        out[1] = _ops.run("bending_hvp", x, ggx, hinges, a, k, rest, c, prev, model.value, w, ptr, idx)
        return tuple(out)
    dx, dps, dg = _kernel_second_order(model, saved, ggx, ggp)
    out[1] = dx if needs[1] else None
    if needs[0] and dg is not None:
        out[0] = _reduce(dg, seg, gE.shape[-1] if seg is not None else 0)
    for j, p in enumerate((k, rest, c, prev)):
        d = dps[j] if j < len(dps) else None  # c, prev: only with damping
        if needs[5 + j] and p is not None and d is not None:
            out[5 + j] = _sum_to(d, p)
    return tuple(out)


def _scaled(gE: Tensor, g1: Tensor, gp1: Tensor | None) -> tuple[Tensor, Tensor]:
    """The gradients of a mesh's energy ``(dE/dx (..., V, 3), dpsi/dp (..., H, 4) or None)`` times its cotangent
    ``gE (...,)``: ``(gx, gp)`` as the gradient operator returns them (``gp`` empty without parameters)."""
    s = gE[..., None, None]
    return s * g1, (s * gp1 if gp1 is not None else g1.new_empty(0))


def _kernel_energy(code: str, x, hinges, seg, seg_count, a, k, rest, c, prev, check) -> Tensor:
    """The energy of the kernel path: the operator's per-hinge energies, summed per mesh (or segment)."""
    psi = _ops.run("bending_energy", x, hinges, a, k, rest, c, prev, code, check)
    return _reduce(psi, seg, seg_count)


def _kernel_gradient(code: str, gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx, params, check) -> tuple:
    """``(gE dE/dx, gE dpsi/d(k, rest, c, prev) per hinge (empty without params))`` by the gradient operator."""
    w = _hinge_weight(gE, seg, hinges.shape[0])
    return _ops.run("bending_gradient", x, hinges, a, k, rest, c, prev, code, w, ptr, idx, params, check)


def _make_kernel(model: BendingModel):
    """The pair of Functions of the compiled path (``torch.ops.torchbend``): no ``jvp`` and no vmap rule, so
    that ``torch.compile(fullgraph=True)`` traces them (the backends choose the eager Functions above under
    ``torch.func`` transforms and forward-mode AD).  Parameters are passed as they are stored (one value,
    ``(H,)`` or ``(..., H)``), not expanded; the parameter gradients are reduced to their shapes.

    They take ``ctx`` in ``forward`` (no ``setup_context``): ``Function.apply`` binds the arguments of a
    ``setup_context`` Function through ``inspect.signature`` on every call, which on a thousand hinges costs
    more than the kernels (``setup_context`` is what ``torch.func`` needs, and these never run under it)."""
    code = model.value

    class _GradientImpl(torch.autograd.Function):
        @staticmethod
        def forward(ctx, gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx, params, check, g1=None, gp1=None):
            ctx.save_for_backward(gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx)
            ctx.set_materialize_grads(False)
            if g1 is not None:  # the unweighted gradients of the energy's forward pass, scaled by the cotangent
                return _scaled(gE, g1, gp1)
            return _kernel_gradient(code, gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx, params, check)

        @staticmethod
        def backward(ctx, ggx, ggp):
            return _kernel_double_backward(model, ctx.saved_tensors, ctx.needs_input_grad, ggx, ggp) + (None, None)

    class _EnergyImpl(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x, hinges, seg, seg_count, a, k, rest, c, prev, ptr, idx, check):
            needs = ctx.needs_input_grad
            params = any(needs[5:9])
            if seg is None and (needs[0] or params):
                # a recorded energy is differentiated next: one pass computes the energies and the gradients
                # (with the weight 1), which the backward scales by the cotangent
                psi, g1, gp1 = _ops.run("bending_energy_gradient", x, hinges, a, k, rest, c, prev, code, ptr, idx,
                                        params, check)
                ctx.save_for_backward(x, hinges, seg, a, k, rest, c, prev, ptr, idx, g1, gp1 if params else None)
                return _reduce(psi, seg, seg_count)
            ctx.save_for_backward(x, hinges, seg, a, k, rest, c, prev, ptr, idx, None, None)
            return _kernel_energy(code, x, hinges, seg, seg_count, a, k, rest, c, prev, check)

        @staticmethod
        def backward(ctx, gE):
            gE = compiled_backward_guard(gE)  # a compiled backward cannot be differentiated: a clear error
            x, hinges, seg, a, k, rest, c, prev, ptr, idx, g1, gp1 = ctx.saved_tensors
            needs = ctx.needs_input_grad
            params = any(needs[5:9])
            # the positions were checked by the forward
            if torch.is_grad_enabled():  # create_graph=True: the gradient is differentiable (analytic HVP)
                gx, gp = _Gradient.apply(gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx, params, False, g1, gp1)
            elif g1 is not None:  # a plain backward (and torch.compile's trace of it): scale the forward's gradients
                gx, gp = _scaled(gE, g1, gp1)
            else:  # the operator alone
                gx, gp = _kernel_gradient(code, gE, x, hinges, seg, a, k, rest, c, prev, ptr, idx, params, False)
            out: list = [None] * 12
            out[0] = gx if needs[0] else None
            for j, p in enumerate((k, rest, c, prev)):
                if needs[5 + j] and p is not None:
                    out[5 + j] = _sum_to(gp[..., j], p)
            return tuple(out)

    name = model.value.capitalize()
    _Gradient = type(f"{name}BendingGradientKernel", (_GradientImpl,), {"__module__": __name__})
    _Energy = type(f"{name}BendingEnergyKernel", (_EnergyImpl,), {"__module__": __name__})
    return _Energy, _Gradient


_KERNEL_FUNCTIONS = {m: _make_kernel(m) for m in BendingModel}


def _incidence(hinges: Tensor, V: int, inc) -> tuple[Tensor, Tensor]:
    return kernels.incidence(hinges, V) if inc is None else inc


def _records(*tensors: Tensor | None) -> bool:
    """Whether autograd records a graph of a call on ``tensors``: otherwise the kernel path runs its Functions'
    ``forward`` directly (``Function.apply`` costs about as much as the kernels on a thousand hinges)."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def energy_function(model: BendingModel | str) -> type[torch.autograd.Function]:
    """The private energy Function of ``model`` (for tests and advanced use)."""
    return _FUNCTIONS[BendingModel.parse(model)][0]


def gradient_function(model: BendingModel | str) -> type[torch.autograd.Function]:
    """The private gradient Function of ``model`` (its backward is the analytic HVP)."""
    return _FUNCTIONS[BendingModel.parse(model)][1]


def _expand_params(x: Tensor, a: Tensor, k: Tensor, rest: Tensor, c, prev) -> list:
    """Per-hinge scalars as ``(..., H)`` views (the Functions return gradients of that shape)."""
    return HingeParams(a, k, rest, c, prev).expanded(x.shape[:-2])


def bending_energy_raw(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Tensor | None = None,
                       prev: Tensor | None = None, *, model: BendingModel | str = BendingModel.TAN,
                       seg: Tensor | None = None, seg_count: int = 0, impl: str | None = None, inc: tuple[Tensor, Tensor] | None = None,
                       check: bool = False) -> Tensor:
    """Unvalidated functional entry: energy ``(...,)`` (or ``(..., seg_count)`` with ``seg``).

    ``x: (..., V, 3)``; ``hinges: (H, 4)`` int64; ``a: (H,)``; ``k``, ``rest``, ``c``, ``prev``
    broadcastable to ``(..., H)`` (``c``/``prev`` both given or both ``None``).  Differentiable
    twice (analytic backward and double backward) in ``x``, ``k``, ``rest``, ``c``, ``prev``.
    ``impl="native"``: the compiled operators (``torch.ops.torchbend``; ``inc`` the vertex incidence lists,
    computed when not given; ``check``: the operator checks that x is finite).
    """
    if type(model) is not BendingModel:  # a name ("tan"): parsed, an unknown one a ValueError listing the models
        model = BendingModel.parse(model)
    if impl is not None:
        ptr, idx = _incidence(hinges, x.shape[-2], inc)
        if _records(x, k, rest, c, prev):
            return _KERNEL_FUNCTIONS[model][0].apply(x, hinges, seg, seg_count, a, k, rest, c, prev, ptr, idx, check)
        return _kernel_energy(model.value, x, hinges, seg, seg_count, a, k, rest, c, prev, check)
    params = _expand_params(x, a, k, rest, c, prev)
    return _FUNCTIONS[model][0].apply(x, hinges, seg, seg_count, a, *params)


def bending_gradient_raw(x: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Tensor | None = None,
                         prev: Tensor | None = None, *, model: BendingModel | str = BendingModel.TAN,
                         impl: str | None = None, inc: tuple[Tensor, Tensor] | None = None,
                         check: bool = False) -> Tensor:
    """Unvalidated ``dE/dx: (..., V, 3)`` through the gradient Function (differentiable: analytic HVP);
    ``check``: the compiled operator checks that x is finite."""
    if type(model) is not BendingModel:  # a name ("tan"): parsed, an unknown one a ValueError listing the models
        model = BendingModel.parse(model)
    ones = x.new_ones(x.shape[:-2])
    if impl is not None:
        ptr, idx = _incidence(hinges, x.shape[-2], inc)
        if _records(x, k, rest, c, prev):
            params = any(t is not None and t.requires_grad for t in (k, rest, c, prev))
            return _KERNEL_FUNCTIONS[model][1].apply(ones, x, hinges, None, a, k, rest, c, prev, ptr, idx, params,
                                                     check)[0]
        return _kernel_gradient(model.value, ones, x, hinges, None, a, k, rest, c, prev, ptr, idx, False, check)[0]
    params = _expand_params(x, a, k, rest, c, prev)
    return _FUNCTIONS[model][1].apply(ones, x, hinges, None, a, *params)[0]


def bending_hvp_raw(x: Tensor, v: Tensor, hinges: Tensor, a: Tensor, k: Tensor, rest: Tensor, c: Tensor | None = None,
                    prev: Tensor | None = None, *, model: BendingModel | str = BendingModel.TAN,
                    impl: str | None = None, inc: tuple[Tensor, Tensor] | None = None, check: bool = False) -> Tensor:
    """Unvalidated ``Hess_x(E) v: (..., V, 3)`` straight from the closed form (no autograd involved).

    Per hinge ``H v = psi'' (g . v) g + psi' (H_theta v)`` with ``psi' = d psi/d theta``; ``impl="native"``:
    the compiled kernel (CPU or CUDA, by x's device; ``check``: it checks that x and v are finite)."""
    if type(model) is not BendingModel:  # a name ("tan"): parsed, an unknown one a ValueError listing the models
        model = BendingModel.parse(model)
    if impl is not None:
        ptr, idx = _incidence(hinges, x.shape[-2], inc)
        return _ops.run("bending_hvp", x, v, hinges, a, k, rest, c, prev, model.value, x.new_ones(1), ptr, idx,
                                               check)
    out = None
    for sl in chunks(hinges.shape[0]):
        h = hinges[sl]
        v4 = gather_soa(v, h)
        theta, g4, hv4 = geometry.hinge_angle_gradient_hvp_soa(gather_soa(x, h), v4)
        f1, f2 = psi_theta_derivatives(model, theta, a[sl], sliced(k, sl), sliced(rest, sl), sliced(c, sl),
                                       sliced(prev, sl))
        part = _scatter_soa(_axpy4(f2 * _dot4(g4, v4), g4, _scale4(hv4, f1)), h, x.shape[-2])
        out = part if out is None else out + part
    assert out is not None  # chunks() yields at least one slice
    return out
