"""Input validation shared by the energy modules and the solver (ValueErrors that name the input)."""
from __future__ import annotations

import torch
from torch import Tensor

from .topology import HingeTopology


def _is_traced(t: Tensor) -> bool:
    return torch._C._functorch.is_functorch_wrapped_tensor(t)


def _check_positions(x, vertex_count: int, name: str = "x", check_finite: bool = True) -> Tensor:
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape (..., {vertex_count}, 3), got {type(x).__name__}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating point tensor, got dtype {x.dtype}")
    if x.ndim < 2 or x.shape[-1] != 3 or x.shape[-2] != vertex_count:
        raise ValueError(f"{name} must have shape (..., {vertex_count}, 3) (V = {vertex_count}), got {tuple(x.shape)}")
    if check_finite and not _is_traced(x):
        bad = ~torch.isfinite(x.detach())
        if bool(bad.any()):
            verts = torch.nonzero(bad.reshape(-1, vertex_count, 3).any(-1).any(0)).reshape(-1)[:8].tolist()
            raise ValueError(f"{name} holds non-finite (NaN or Inf) coordinates at vertices {verts}")
    return x


def mesh_and_rest(faces, rest_positions) -> tuple[HingeTopology, Tensor]:
    """Validated ``(topology, rest positions (V, 3) float)`` from faces (or a topology) and positions."""
    topo = faces if isinstance(faces, HingeTopology) else HingeTopology.from_faces(faces)
    rest = torch.as_tensor(rest_positions)
    if not rest.is_floating_point():
        rest = rest.to(torch.get_default_dtype())
    _check_positions(rest, topo.vertex_count, "rest_positions")
    if rest.ndim != 2:
        raise ValueError(f"rest_positions must have shape (V, 3), got {tuple(rest.shape)}")
    return topo, rest
