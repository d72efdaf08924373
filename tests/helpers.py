"""What several test files share: meshes, references, devices, tolerances, and the loader of the ``train/`` scripts.

A plain module (not collected): tests import it (``from .helpers import ...``); no test file imports another.
The fixtures (``sheet``, ``device``, ``dtype``) live in ``conftest.py``."""
from __future__ import annotations

import importlib.util
import os
import sys
from types import ModuleType
from typing import Any

import pytest
import torch
from torch.overrides import TorchFunctionMode

import torchbend as tb
from torchbend.sim import pardiso
from torchbend.testing import plain_bending_energy

DIRECT_METHOD = "ldlt" if pardiso.available() else "lu"
"""The factorisation the default direct solver uses here (``linear_method`` of a Newton direction):
MKL PARDISO's ``L D L^T`` where ``mkl`` is installed, SciPy's SuperLU elsewhere."""

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIGS = os.path.join(ROOT, "configs")

F64, F32 = torch.float64, torch.float32
MODELS = ["quadratic", "tan", "sin"]
"""The bending models."""
MEMBRANE_MODELS = ["stvk", "arap", "symmetric_dirichlet", "neohookean"]
DTYPES = [F64, F32]

# ------------------------------------------------------------------------------------------------ devices

HAS_CUDA = torch.cuda.is_available()
requires_gpu = pytest.mark.skipif(not HAS_CUDA, reason="no CUDA device")
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, requires_gpu])]
"""``cpu`` always, ``cuda`` marked ``gpu`` and skipped without a CUDA device (the ``device`` fixture's params)."""

# ------------------------------------------------------------------------------------------------ tolerances

ROUND_OFF = {F64: 1e-12, F32: 1e-5}
"""Relative error of a closed-form result against its reference, computed once each (a few hundred ulps)."""


SAME_FORMULA = 32 * torch.finfo(F64).eps
"""Relative (Frobenius) difference allowed between two float64 evaluations of the same closed form in different
operation orders: the compiled kernels against the eager PyTorch path (FMA contraction, vector-width-dependent
reductions, vectorized atan2/sincos within 2 ulp of the library's).  Measured 1.3-6 ulps of the norm on Intel
AVX-512 and AMD Zen builds (the tan model's half-angle terms amplify them the most); 32 ulps leaves room
without hiding a wrong term, which shows at 1e-8 and above."""


def assert_collider_derivatives_match_autograd(collider, x: torch.Tensor, rtol: float, hessian_rtol: float,
                                               hessian_atol: float) -> None:
    """A collider's gradient and exact per-vertex Hessian blocks against autograd of its energy (row by row: the
    energy is a sum over vertices), and its clamped blocks PSD; ``x (V, 3)``, some vertices in contact; the
    absolute tolerances are relative to the largest entry."""
    x = x.detach().requires_grad_()
    active = collider.depth(x.detach()) > 0
    assert 5 < int(active.sum()) < x.shape[0]  # some points in contact, some free
    (g,) = torch.autograd.grad(collider.energy(x), x, create_graph=True)
    gd = g.detach()
    torch.testing.assert_close(collider.gradient(x.detach()), gd, rtol=rtol, atol=rtol * float(gd.abs().max()))
    H = torch.stack([torch.autograd.grad(g[:, j].sum(), x, retain_graph=True)[0] for j in range(3)], -1)
    blocks = collider.hessian_blocks(x.detach(), projection="none")
    torch.testing.assert_close(blocks, H.transpose(-1, -2), rtol=hessian_rtol,
                               atol=hessian_atol * float(H.abs().max()))
    projected = collider.hessian_blocks(x.detach(), projection="clamp")
    assert float(torch.linalg.eigvalsh(projected).min()) >= -1e-12 * float(projected.abs().max())


def round_off(dtype: torch.dtype) -> float:
    """:data:`ROUND_OFF` of ``dtype``."""
    return ROUND_OFF[dtype]


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """``|a - b| / |b|`` (Frobenius norms, detached)."""
    a, b = a.detach(), b.detach()
    return float((a - b).norm() / b.norm())


# ------------------------------------------------------------------------------------------------ meshes


def curved_sheet(dtype: torch.dtype = F64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(rest, faces, x)``: a small random curved sheet (irregular triangles, boundary) and a perturbed state."""
    rest, faces = tb.scenes.random_curved_sheet(5, 4, amplitude=0.3, seed=3, dtype=F64)
    gen = torch.Generator().manual_seed(7)
    x = rest + 0.05 * torch.randn(rest.shape, generator=gen, dtype=F64)
    return rest.to(dtype), faces, x.to(dtype)


def mesh_cases() -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """``{name: (rest, faces)}`` (float64): a curved sheet, an icosphere, a cylinder, and the sheet with its
    vertices permuted (which mixes the global edge orientations relative to the faces)."""
    sheet, fs = tb.scenes.random_curved_sheet(5, 4, amplitude=0.3, seed=3, dtype=F64)
    ico, fi = tb.scenes.icosphere(1, dtype=F64)
    cyl, fc = tb.scenes.cylinder(7, 4, dtype=F64)
    gen = torch.Generator().manual_seed(1)
    perm = torch.randperm(sheet.shape[0], generator=gen)
    inv = torch.argsort(perm)
    return {"sheet": (sheet, fs), "icosphere": (ico, fi), "cylinder": (cyl, fc), "permuted": (sheet[perm], inv[fs])}


MESHES = ["sheet", "icosphere", "cylinder", "permuted"]
"""The names of :func:`mesh_cases`."""


def random_bending(rest: torch.Tensor, faces: torch.Tensor, model: str, damped: bool = False) -> tb.BendingEnergy:
    """A :class:`~torchbend.BendingEnergy` with random per-hinge stiffness in [0.5, 1.5) (and damping 0.2)."""
    H = tb.HingeTopology.from_faces(faces).hinge_count
    gen = torch.Generator().manual_seed(3)
    k = 0.5 + torch.rand(H, generator=gen, dtype=F64)
    return tb.BendingEnergy(faces, rest, model=model, stiffness=k, damping=0.2 if damped else None)


def strip_mesh(nx: int, ny: int, pattern: str = "criss", L: float = 0.2, W: float = 0.05):
    """``(rest, faces)`` of a flat ``L x W`` [m] grid of ``nx x ny`` vertices; ``pattern``: ``"criss"``
    (alternating diagonals, :func:`torchbend.scenes.grid`) or ``"one_way"`` (every quad split along the same
    diagonal)."""
    rest, faces = tb.scenes.grid(nx, ny, (L, W), dtype=F64)
    if pattern == "one_way":
        i, j = torch.meshgrid(torch.arange(nx - 1), torch.arange(ny - 1), indexing="ij")
        a = (i + nx * j).reshape(-1)
        b, c, d = a + 1, a + nx + 1, a + nx
        faces = torch.cat((torch.stack((a, b, c), -1), torch.stack((a, c, d), -1)))
    return rest, faces


def cantilever(nx, ny, *, L=0.2, W=0.05, young=5e7, nu=0.3, t=1e-2, rho=1000.0, pattern="criss"):
    """``(model, rest, kirchhoff)``: a :func:`strip_mesh` (StVK membrane, quadratic bending) clamped along its
    first two columns, under gravity, and the Kirchhoff plate theory's tip deflection [m]."""
    rest, faces = strip_mesh(nx, ny, pattern, L, W)
    bend = tb.BendingEnergy(faces, rest, model="quadratic", stiffness=tb.stiffness_from_material(young, t, nu))
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=young, poisson=nu, thickness=t)
    columns = rest[:, 0].unique()
    pinned = rest[:, 0] <= columns[1] + 1e-12
    model = tb.ClothModel(faces, rest, bending=bend, membrane=mem, density=rho * t, gravity=(0, 0, -9.81), pinned=pinned)
    kirchhoff = rho * t * 9.81 * (L - columns[1].item()) ** 4 / (8 * young * t**3 / (12 * (1 - nu**2)))
    return model, rest, kirchhoff


def tip(x: torch.Tensor, rest: torch.Tensor) -> float:
    """The mean downward deflection [m] of the free end of a :func:`cantilever`."""
    return float(-(x[:, 2] - rest[:, 2])[rest[:, 0] >= rest[:, 0].max() - 1e-12].mean())


# ------------------------------------------------------------------------------------------------ references


def reference_hessian(bend: tb.BendingEnergy, x: torch.Tensor) -> torch.Tensor:
    """``(3V, 3V)`` torch.func Hessian of the plain autograd energy with ``bend``'s parameters."""
    n = x.numel()

    def energy(y):
        return plain_bending_energy(y, bend.hinges, bend.weights, bend.stiffness, bend.rest_angles, bend.model)

    return torch.func.hessian(energy)(x).reshape(n, n)


def per_hinge_reference(bend: tb.BendingEnergy, x: torch.Tensor, kw: dict) -> torch.Tensor:
    """``(H, 12, 12)``: torch.func.hessian of the plain per-hinge energy, vmapped over hinges (``kw``: the
    viscous term's ``theta_prev`` and ``dt``, or empty)."""
    idx = torch.arange(4)[None]
    c = None if not kw else (bend.damping / kw["dt"]).expand(bend.hinge_count)
    prev = kw.get("theta_prev")

    def e(y4, a, k, r, cc, pp):
        return plain_bending_energy(y4, idx, a[None], k[None], r[None], bend.model,
                                    None if cc is None else cc[None], None if pp is None else pp[None])

    k = bend.stiffness.expand(bend.hinge_count)
    dims = (0, 0, 0, 0, None if c is None else 0, None if prev is None else 0)
    Hr = torch.func.vmap(torch.func.hessian(e), in_dims=dims)(x[bend.hinges], bend.weights, k, bend.rest_angles, c, prev)
    return Hr.reshape(-1, 12, 12)


def second_order_case(model: str, damped: bool, dtype, per_hinge: bool, batch: tuple = (2,),
                      seed: int = 0) -> dict[str, Any]:
    """The arguments of the second-order bending kernels: a random curved sheet, positions ``(*batch, V, 3)``
    and parameters: scalars or per hinge (``k``), per-hinge rest angles, per-sample ``prev``; directions ``v``
    and ``t (*batch, H, 4)``; weights ``w (*batch, H)``."""
    rest_x, faces = tb.scenes.random_curved_sheet(6, 5, amplitude=0.3, seed=seed + 1, dtype=F64)
    topo = tb.HingeTopology.from_faces(faces)
    hinges = topo.hinges
    H = hinges.shape[0]
    gen = torch.Generator().manual_seed(seed)
    x = rest_x + 0.05 * torch.randn(batch + rest_x.shape, generator=gen, dtype=F64)
    a = 0.5 + torch.rand(H, generator=gen, dtype=F64)
    k = (0.5 + torch.rand(H, generator=gen, dtype=F64)) if per_hinge else torch.tensor([0.7], dtype=F64)
    rest = tb.hinge_angles(rest_x, topo) + 0.1 * torch.randn(H, generator=gen, dtype=F64)
    c = prev = None
    if damped:
        c = (0.2 + torch.rand(H, generator=gen, dtype=F64)) if per_hinge else torch.tensor([0.3], dtype=F64)
        prev = tb.hinge_angles(x, topo) + 0.05 * torch.randn(batch + (H,), generator=gen, dtype=F64)
    v = torch.randn(x.shape, generator=gen, dtype=F64)
    t = torch.randn(batch + (H, 4), generator=gen, dtype=F64)
    w = 0.5 + torch.rand(batch + (H,), generator=gen, dtype=F64)
    cast = (lambda z: None if z is None else z.to(dtype))  # noqa: E731
    return dict(x=cast(x), hinges=hinges, a=cast(a), k=cast(k), rest=cast(rest), c=cast(c), prev=cast(prev),
                v=cast(v), t=cast(t), w=cast(w), model=model, V=x.shape[-2])


# ------------------------------------------------------------------------------------------------ recorders

SIM_DIR = os.path.dirname(os.path.abspath(str(tb.sim.__file__)))
TORCH_DIR = os.path.dirname(os.path.abspath(str(torch.__file__)))
FACTORIES = {torch.zeros, torch.ones, torch.empty, torch.full, torch.eye, torch.arange, torch.linspace, torch.tensor,
             torch.as_tensor, torch.scalar_tensor, torch.rand, torch.randn}


class DevicelessFactories(TorchFunctionMode):
    """Records the tensor factory calls made from ``torchbend/sim`` without an explicit ``device=``
    (such a tensor lands on the CPU whatever the device of the positions)."""

    def __init__(self):
        super().__init__()
        self.calls: list = []
        self.seen = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES:
            frame = sys._getframe(1)
            while frame is not None and frame.f_code.co_filename.startswith(TORCH_DIR):
                frame = frame.f_back
            if frame is not None and frame.f_code.co_filename.startswith(SIM_DIR):
                self.seen += 1
                keeps_device = func is torch.as_tensor and bool(args) and isinstance(args[0], torch.Tensor)
                if kwargs.get("device") is None and not keeps_device:
                    self.calls.append(f"torch.{func.__name__} at {os.path.basename(frame.f_code.co_filename)}:{frame.f_lineno}")
        return func(*args, **kwargs)


# ------------------------------------------------------------------------------------------------ scripts

TRAIN_SIBLINGS = {"drape_net": ("common",), "material_id": ("common",), "hood_style": ("common",),
                  "robot_drape": ("common", "drape_net")}
"""The sibling scripts each ``train/`` script imports by plain name (``import common``)."""


def load_script(folder: str, name: str) -> ModuleType:
    """``<folder>/<name>.py`` (``folder`` relative to the repository root) imported from its path, without
    touching ``sys.path``, registered in ``sys.modules`` as ``name`` (the plain name its siblings import it by);
    loaded once per process."""
    path = os.path.join(ROOT, folder, f"{name}.py")
    loaded = sys.modules.get(name)
    if loaded is not None and getattr(loaded, "__file__", None) == path:
        return loaded
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def train_script(name: str) -> ModuleType:
    """``train/<name>.py`` (:func:`load_script`), its siblings (:data:`TRAIN_SIBLINGS`) loaded first: the scripts
    import them by plain name (``import common``, as ``python train/X.py`` allows)."""
    for sibling in TRAIN_SIBLINGS.get(name, ("common",) if name != "common" else ()):
        load_script("train", sibling)
    return load_script("train", name)


def benchmark_script(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` (:func:`load_script`; for the scripts that import no sibling)."""
    return load_script("benchmarks", name)
