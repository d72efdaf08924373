"""Shared pieces of the loss terms: the base class, input checks that name the term, lumped areas."""
from __future__ import annotations

import torch
from torch import Tensor, nn

from .._checks import check_finite_tensor, is_traced

__all__ = ["LossTerm", "check_points", "lumped_masses", "per_sample"]


class LossTerm(nn.Module):
    """Base of the loss terms: ``forward(x, **inputs)`` returns per-sample values ``(B,)`` [J] for
    positions ``x (B, V, 3)`` [m] (a 0-dim tensor for ``x (V, 3)``).

    ``inputs`` names the keyword inputs a term accepts; :class:`~torchbend.losses.ClothLoss` routes
    its keyword arguments to the terms by these names (one namespace for all terms: ``density`` is
    shared by :class:`Gravity` and :class:`Inertia`; two terms of one class share all their names, and
    take term-specific inputs as ``loss(x, name={...})``)."""

    inputs: tuple[str, ...] = ()

    @property
    def term_name(self) -> str:
        return type(self).__name__

    def _set_material(self, name: str, value, *, positive: bool | None = True) -> None:
        """Store a material value under ``name``: a float, or a tensor of shape ``()`` or ``(B,)`` (one per
        sample; a buffer, or a parameter if it is an ``nn.Parameter``: then learnable).  Checked to be
        finite and positive (``positive=False``: non-negative; ``None``: any sign)."""
        if isinstance(value, Tensor):
            if value.ndim > 1:
                raise ValueError(f"{self.term_name}: {name} must be a scalar or have shape (B,) (one per sample), "
                                 f"got shape {tuple(value.shape)}")
            check = value.detach()
            if not check.is_floating_point():
                raise ValueError(f"{self.term_name}: {name} must be a floating point tensor, got dtype {value.dtype}")
        else:
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{self.term_name}: {name} must be a number or a tensor, got {value!r}") from None
            check = torch.tensor(value, dtype=torch.float64)
        check_finite_tensor(check, f"{self.term_name}: {name}")
        if positive is not None and bool((check <= 0).any() if positive else (check < 0).any()):
            raise ValueError(f"{self.term_name}: {name} must be {'positive' if positive else 'non-negative'}, "
                             f"got {value!r}")
        if isinstance(value, nn.Parameter):
            self.register_parameter(name, value)
        elif isinstance(value, Tensor):
            self.register_buffer(name, value)
        else:
            setattr(self, name, value)

    def _positions(self, x, count: int | None, device: torch.device | None) -> Tensor:
        """The positions ``x``: a finite floating ``(V, 3)`` or ``(B, V, 3)`` tensor on ``device``."""
        return check_points(x, "x", self.term_name, count=count, device=device)


def check_points(t, name: str, term: str, *, count: int | None, batch: tuple | None = None,
                 device: torch.device | None = None, dtype: torch.dtype | None = None) -> Tensor:
    """``t`` as a finite floating ``(N, 3)`` or ``(B, N, 3)`` tensor (``N = count`` when given), on
    ``device`` in ``dtype`` when given.  ``batch``: the batch shape of the positions ``x`` (``()`` or
    ``(B,)``) that ``t`` must broadcast to (a batched ``t`` needs ``t.shape[0] = B``).  ``ValueError``
    naming ``term`` and ``name`` otherwise."""
    n = "N" if count is None else str(count)
    want = f"({n}, 3) or (B, {n}, 3)"
    if not isinstance(t, Tensor):
        raise ValueError(f"{term}: {name} must be a tensor of shape {want}, got {type(t).__name__}")
    if not t.is_floating_point():
        raise ValueError(f"{term}: {name} must be a floating point tensor, got dtype {t.dtype}")
    if t.ndim not in (2, 3) or t.shape[-1] != 3 or (count is not None and t.shape[-2] != count):
        raise ValueError(f"{term}: {name} must have shape {want}, got {tuple(t.shape)}")
    if batch is not None and t.ndim == 3 and tuple(t.shape[:1]) != tuple(batch):
        raise ValueError(f"{term}: {name} has batch size {t.shape[0]} but the positions x have batch shape "
                         f"{tuple(batch)}, got {name} of shape {tuple(t.shape)}")
    if device is not None and t.device != device:
        raise ValueError(f"{term}: {name} is on {t.device} but the term is on {device}; move one with .to()")
    if not is_traced(t) and t.device.type != "meta" and not bool(torch.isfinite(t.detach()).all()):
        raise ValueError(f"{term}: {name} holds non-finite (NaN or Inf) values")
    return t if dtype is None else t.to(dtype)


def per_sample(value, name: str, x: Tensor, term: str, *, positive: bool | None = False) -> Tensor:
    """A material value as a tensor of shape ``()`` or ``x.shape[:-2]`` (one per sample) in the dtype
    and on the device of ``x``; finite and non-negative (``positive=True``: positive; ``None``: any
    sign), else ``ValueError`` naming ``term`` and ``name``.  Gradients flow through it (e.g. an
    ``nn.Parameter``)."""
    if isinstance(value, Tensor):
        t = value
    else:
        try:
            t = torch.tensor(value, dtype=x.dtype)  # python numbers straight into x's dtype (no float32 detour)
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(f"{term}: {name} must be a number or a tensor, got {value!r}") from None
    batch = tuple(x.shape[:-2])
    if t.shape != () and tuple(t.shape) != batch:
        want = "a scalar" if not batch else f"a scalar or have shape {batch} (one per sample)"
        raise ValueError(f"{term}: {name} must be {want}, got shape {tuple(t.shape)}")
    t = t.to(device=x.device, dtype=x.dtype)
    if not is_traced(t):
        d = t.detach()
        check_finite_tensor(d, f"{term}: {name}")
        if positive is not None and bool((d <= 0).any() if positive else (d < 0).any()):
            raise ValueError(f"{term}: {name} must be {'positive' if positive else 'non-negative'}, "
                             f"got min {float(d.min())}")
    return t


def lumped_masses(density, areas: Tensor, x: Tensor, term: str) -> Tensor:
    """Lumped masses ``(V,)`` or ``(B, V)`` [kg] in the dtype of ``x``: a density per sample (:func:`per_sample`,
    positive) times the lumped vertex areas ``(V,)`` [m^2] (a third of each rest triangle's area)."""
    rho = per_sample(density, "density", x, term, positive=True)
    a = areas.to(x.dtype)
    return rho[..., None] * a if rho.ndim else rho * a
