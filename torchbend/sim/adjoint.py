r"""Differentiating through a static equilibrium with the implicit-function adjoint.

At an equilibrium ``x*(p)`` of a :class:`~torchbend.sim.ClothModel` whose energy terms depend
on parameters ``p`` (for example a learnable bending stiffness, or the end points of a collider
attached to a robot link), the free coordinates satisfy ``g_f(x*, p) = 0`` with ``g`` the gradient
of the potential.  Differentiating, ``H_ff dx_f/dp = -dg_f/dp``, so for a loss ``L(x*)``

    dL/dp = -lambda^T dg/dp,       H_ff lambda = dL/dx_f       (H: the exact Hessian at x*)

one linear solve with the same Hessian as Newton's last step, and a vector-Jacobian product of the
gradient (through torchbend's analytic double backward).  Pinned positions ``x_p`` are inputs too
(vertices held by a robot gripper): ``x_f`` depends on them through ``H_ff dx_f/dx_p = -H_fp``, so

    dL/dx_p = dL/dx_p|_direct - H_pf lambda.

No Newton iteration is unrolled.

The adjoint is the derivative of an equilibrium only where one was found: the backward pass of a
solve that did not converge (``info.converged`` False, e.g. ``max_iters`` reached) raises a
``RuntimeError`` quoting ``info.message``, unless ``allow_unconverged=True`` was passed (then the
formula above is applied at the returned, best, iterate).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from ..options import Projection
from .model import ClothModel
from .newton import SolveInfo, solve_static

__all__ = ["solve_static_adjoint"]


class _Equilibrium(torch.autograd.Function):
    @staticmethod
    def forward(ctx, model, x0, solve_kw, info_out, pin_positions, allow_unconverged, *params):
        x0 = x0.detach().clone()
        if pin_positions is not None:
            x0[model.pinned] = pin_positions.detach().to(x0.dtype)
        with torch.no_grad():
            x, info = solve_static(model, x0, **solve_kw)
        info_out.append(info)
        ctx.info, ctx.allow_unconverged = info, allow_unconverged
        ctx.model = model
        ctx.has_pins = pin_positions is not None
        ctx.save_for_backward(x.detach(), *params)
        return x.detach().clone()

    @staticmethod
    def backward(ctx, gx):
        info: SolveInfo = ctx.info
        if not info.converged and not ctx.allow_unconverged:
            raise RuntimeError("solve_static_adjoint: backward through a static solve that did not converge "
                               f"({info.message}); the implicit adjoint is the derivative of an equilibrium only. "
                               "Converge the solve (max_iters, continuation=True) or pass allow_unconverged=True")
        x, *params = ctx.saved_tensors
        model: ClothModel = ctx.model
        pinned = model.pinned.repeat_interleave(3).cpu().numpy()
        free = ~pinned
        H = model.hessian(x, Projection.NONE).tocsr()
        rhs = gx.reshape(-1).detach().cpu().double().numpy()
        lam = spla.splu(H[free][:, free].tocsc()).solve(rhs[free])
        lam_full = np.zeros(free.shape[0])
        lam_full[free] = lam
        lam_t = torch.from_numpy(lam_full).to(dtype=x.dtype, device=x.device).reshape(-1, 3)
        g_pins = None
        if ctx.has_pins:
            g_pins = rhs[pinned] - H[pinned][:, free] @ lam
            g_pins = torch.from_numpy(g_pins).to(dtype=gx.dtype, device=gx.device).reshape(-1, 3)
        grads = ()
        if params:
            with torch.enable_grad():
                g = model.gradient(x)
                grads = torch.autograd.grad(g, params, grad_outputs=-lam_t, allow_unused=True)
            grads = tuple(torch.zeros_like(p) if gp is None else gp for p, gp in zip(params, grads))
        return (None, None, None, None, g_pins, None, *grads)


def solve_static_adjoint(model: ClothModel, x0: Tensor, params=(), *, pin_positions: Tensor | None = None,
                         allow_unconverged: bool = False, **solve_kw) -> tuple[Tensor, SolveInfo]:
    """Static equilibrium ``x*: (V, 3)`` differentiable by the implicit-function adjoint with respect to
    ``params`` (tensors the model's energy terms use, e.g. ``[bend.stiffness]`` or the tensor end
    points of a :meth:`Capsule.transformed` collider) and to ``pin_positions``.

    ``pin_positions``: ``(P, 3)`` [m] positions of the pinned vertices (``model.pinned``, in
    increasing vertex order) replacing those of ``x0``; ``None`` keeps ``x0``'s.
    ``solve_kw`` go to :func:`~torchbend.sim.solve_static`.  The backward pass solves one sparse
    linear system with the exact Hessian at ``x*`` (pinned DOFs eliminated).  The adjoint is the
    derivative of an equilibrium only if one was found: the backward pass of a solve that did not
    converge raises a ``RuntimeError`` with ``info.message``, unless ``allow_unconverged=True`` (then it
    differentiates at the returned best iterate as if it were one).  The forward pass never raises
    for a failed solve: check ``info.converged``."""
    params = list(params)
    n_pinned = int(model.pinned.sum())
    if pin_positions is not None:
        if not isinstance(pin_positions, Tensor) or pin_positions.shape != (n_pinned, 3):
            shape = tuple(pin_positions.shape) if isinstance(pin_positions, Tensor) else type(pin_positions).__name__
            raise ValueError(f"pin_positions must be a ({n_pinned}, 3) tensor (one row per pinned vertex), got {shape}")
        if not bool(torch.isfinite(pin_positions).all()):
            raise ValueError("pin_positions holds non-finite values")
    elif not params:
        raise ValueError("nothing to differentiate: give params (tensors the energies use) and/or pin_positions")
    info: list = []
    x = _Equilibrium.apply(model, torch.as_tensor(x0), solve_kw, info, pin_positions, bool(allow_unconverged), *params)
    return x, info[0]
