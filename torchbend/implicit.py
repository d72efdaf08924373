r"""Differentiating through a static equilibrium with the implicit-function adjoint.

At an equilibrium ``x*(p)`` of a :class:`~torchbend.solver.ClothModel` whose energy terms depend
on parameters ``p`` (for example a learnable bending stiffness), the free coordinates satisfy
``g(x*, p) = 0`` with ``g`` the gradient of the potential.  Differentiating,
``H dx*/dp = -dg/dp``, so for a loss ``L(x*)``

    dL/dp = -lambda^T dg/dp,       H lambda = dL/dx*       (H: the exact Hessian on the free DOFs)

one linear solve with the same Hessian as Newton's last step, and a vector-Jacobian product of the
gradient (through torchbend's analytic double backward).  No Newton iteration is unrolled.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from .solver import ClothModel, HessianOption, SolveInfo, solve_static

__all__ = ["solve_static_adjoint"]


class _Equilibrium(torch.autograd.Function):
    @staticmethod
    def forward(ctx, model, x0, solve_kw, info_out, *params):
        with torch.no_grad():
            x, info = solve_static(model, x0, **solve_kw)
        info_out.append(info)
        ctx.model = model
        ctx.save_for_backward(x.detach(), *params)
        return x.detach().clone()

    @staticmethod
    def backward(ctx, gx):
        x, *params = ctx.saved_tensors
        model: ClothModel = ctx.model
        free = (~model.pinned).repeat_interleave(3).cpu().numpy()
        H = model.hessian(x, HessianOption.EXACT)[free][:, free].tocsc()
        rhs = gx.reshape(-1).detach().cpu().double().numpy()[free]
        lam = spla.splu(H).solve(rhs)
        lam_full = np.zeros(free.shape[0])
        lam_full[free] = lam
        lam_t = torch.from_numpy(lam_full).to(x.dtype).reshape(-1, 3)
        with torch.enable_grad():
            g = model.gradient(x)
            grads = torch.autograd.grad(g, params, grad_outputs=-lam_t, allow_unused=True)
        grads = tuple(torch.zeros_like(p) if gp is None else gp for p, gp in zip(params, grads))
        return (None, None, None, None, *grads)


def solve_static_adjoint(model: ClothModel, x0: Tensor, params, **solve_kw) -> tuple[Tensor, SolveInfo]:
    """Static equilibrium ``x*: (V, 3)`` differentiable with respect to ``params`` (tensors the
    model's energy terms use, e.g. ``[bend.stiffness]``) by the implicit-function adjoint.

    ``solve_kw`` go to :func:`~torchbend.solver.solve_static`.  The backward pass solves one sparse
    linear system with the exact Hessian at ``x*`` (pinned DOFs eliminated)."""
    params = list(params)
    if not params:
        raise ValueError("params must list at least one tensor to differentiate with respect to")
    info: list = []
    x = _Equilibrium.apply(model, x0, solve_kw, info, *params)
    return x, info[0]
