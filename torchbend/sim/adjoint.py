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
formula above is applied at the returned, best, iterate).  Nor is it defined where the equilibrium is not
isolated: where the cloth can move without changing its potential (``H_ff`` singular: a cloth without pinned
vertices on a frictionless body, turning about a single pin), the backward pass raises a ``RuntimeError`` when the
loss changes along that motion, and otherwise takes the ``lambda`` orthogonal to it.
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
        Hff = H[free][:, free].tocsc()
        try:
            lu = spla.splu(Hff)
        except RuntimeError:  # exactly singular
            raise RuntimeError(_NOT_ISOLATED.format(count="a zero pivot")) from None
        lam = lu.solve(rhs[free])
        null = _null_space(lu, Hff)
        if null.shape[1]:
            if np.linalg.norm(null.T @ rhs[free]) > 1e-6 * np.linalg.norm(rhs[free]):
                raise RuntimeError(_NOT_ISOLATED.format(count=f"{null.shape[1]} zero eigenvalues"))
            lam = lam - null @ (null.T @ lam)  # the loss ignores the free motion: its part of lam is round-off
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


_NOT_ISOLATED = (
    "solve_static_adjoint: the equilibrium is not isolated: the exact Hessian on the free coordinates has {count} "
    "(|eigenvalue| <= 1e-10 of its norm): the cloth can move without changing its potential (a cloth without pinned "
    "vertices sliding on a frictionless body or collider, or turning about a single pin), and the loss changes "
    "along that motion, so its derivative is not defined. Pin vertices that fix the motion, or use a loss that "
    "ignores it")


def _null_space(lu, H, size: int = 6, iterations: int = 3) -> np.ndarray:
    """An orthonormal basis ``(n, m)`` of the eigenvectors of the symmetric ``H`` whose eigenvalues are zero to
    working precision (at most ``size``: a body's rigid motions), by block inverse iteration with the factorization
    ``lu`` of ``H`` and a Rayleigh-Ritz step; ``m = 0`` for a nonsingular ``H``.  Each iteration scales the
    eigenvectors by ``1 / |lambda|``, so those of zero eigenvalues (round-off) outgrow the others by orders of
    magnitude per iteration: a few suffice (each costs ``size`` solves, beside the backward pass's one)."""
    n = H.shape[0]
    k = min(size, n)
    if k == 0:
        return np.zeros((n, 0))
    V = np.random.default_rng(0).standard_normal((n, k))
    for _ in range(iterations):
        W = lu.solve(V)
        if not np.isfinite(W).all():
            break
        V, _ = np.linalg.qr(W)
    T = V.T @ (H @ V)
    w, Q = np.linalg.eigh(0.5 * (T + T.T))
    scale = float(abs(H).sum(axis=1).max())  # >= the spectral norm
    return V @ Q[:, np.abs(w) <= 1e-10 * scale]


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
