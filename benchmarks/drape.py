"""A draped cloth: a square sheet resting on a sphere under gravity (static equilibrium).

Used by the Hessian benchmark to count the hinges whose exact Hessian block is indefinite in a
realistic configuration.  The membrane is a simple edge-spring model (a stand-in until a membrane
energy is used) and the contact a smooth quadratic penalty; the equilibrium is found by L-BFGS with
torchbend's analytic bending gradient (the residual is reported: this is a realistic drape, not a
tightly converged one).
"""
from __future__ import annotations

import numpy as np
import scipy.optimize
import torch

import torchbend as tb


def drape(n: int = 21, *, size: float = 1.0, radius: float = 0.3, bend_k: float = 2e-3, iters: int = 3000):
    """Returns ``(x, faces, bend, info)``: equilibrium positions ``(n*n, 3)`` [m] of the draped sheet."""
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=torch.float64)
    rest = rest - torch.tensor([size / 2, size / 2, 0.0], dtype=torch.float64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=bend_k)
    topo = bend.topology
    E = topo.edges
    L0 = (rest[E[:, 1]] - rest[E[:, 0]]).norm(dim=-1)
    spring_k = 50.0
    mass = 0.2 * size * size / (n * n)  # 0.2 kg/m^2
    g = 9.81
    center = torch.tensor([0.0, 0.0, -radius], dtype=torch.float64)
    contact_k = 2e3
    x0 = rest + torch.tensor([0.0, 0.0, 0.01], dtype=torch.float64)

    def energy_grad(flat):
        x = torch.from_numpy(flat).reshape(-1, 3).requires_grad_()
        d = x[E[:, 1]] - x[E[:, 0]]
        stretch = 0.5 * spring_k * ((d.norm(dim=-1) - L0) ** 2 / L0).sum()
        grav = mass * g * x[:, 2].sum()
        pen = (radius + 0.005 - (x - center).norm(dim=-1)).clamp_min(0)
        contact = 0.5 * contact_k * (pen**2).sum()
        total = stretch + grav + contact + bend(x)
        (gx,) = torch.autograd.grad(total, x)
        return total.item(), gx.reshape(-1).numpy()

    res = scipy.optimize.minimize(energy_grad, x0.reshape(-1).numpy(), jac=True, method="L-BFGS-B",
                                  options={"maxiter": iters, "gtol": 1e-10})
    x = torch.from_numpy(np.asarray(res.x)).reshape(-1, 3)
    gnorm = float(np.linalg.norm(energy_grad(res.x)[1]))
    info = f"{n}x{n} sheet on a sphere, L-BFGS {res.nit} iterations, |grad| {gnorm:.1e} vs gravity {mass * g * n * n:.1e} N"
    return x, faces, bend, info
