"""One function decides the backend: every entry point goes through torchbend.backends.select_backend,
and its answer alone decides whether compiled code runs."""
from unittest import mock

import pytest
import torch

import torchbend as tb
from torchbend import backends
from torchbend.backends import native
from torchbend.options import Backend

from .conftest import rel

F64 = torch.float64


def _modules(sheet):
    rest, faces, x = sheet
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=0.1, damping=1e-3)
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=1e3, poisson=0.3, thickness=1e-3)
    return bend, mem, x


def _entry_points(bend, mem, x):
    """Every public evaluation of the energies, as (name, thunk)."""
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=x.dtype)
    kw = {"theta_prev": bend.angles(x), "dt": 0.01}
    calls = {
        "bend.forward": lambda: bend(x),
        "bend.forward damped": lambda: bend(x, **kw),
        "bend.gradient": lambda: bend.gradient(x),
        "bend.hvp": lambda: bend.hvp(x, v),
        "bend.hinge_hessians": lambda: bend.hinge_hessians(x),
        "bend.hessian triangle": lambda: bend.hessian(x),
        "bend.hessian hinge": lambda: bend.hessian(x, assembly="hinge"),
        "mem.forward": lambda: mem(x),
        "mem.gradient": lambda: mem.gradient(x),
        "mem.hvp": lambda: mem.hvp(x, v),
        "mem.element_hessians": lambda: mem.element_hessians(x),
        "mem.element_eigensystems": lambda: mem.element_eigensystems(x),
        "mem.hessian": lambda: mem.hessian(x),
    }
    for p in ("clamp", "abs", "gauss_newton", "reduced"):
        calls[f"bend.hvp {p}"] = lambda p=p: bend.hvp(x, v, projection=p)
        calls[f"bend.hinge_hessians {p}"] = lambda p=p: bend.hinge_hessians(x, projection=p)
        calls[f"bend.hessian {p}"] = lambda p=p: bend.hessian(x, projection=p)
    return calls


def test_every_entry_point_asks_select_backend(sheet):
    bend, mem, x = _modules(sheet)
    seen = []
    original = backends.select_backend

    def recording(op, backend, x, *params):
        seen.append((op, Backend.parse(backend)))
        return original(op, backend, x, *params)

    for name, call in _entry_points(bend, mem, x).items():
        seen.clear()
        with mock.patch.object(backends, "select_backend", side_effect=recording):
            call()
        assert seen, f"{name} did not go through select_backend"
        assert all(b is Backend.AUTO for _, b in seen), (name, seen)
    # the per-call option reaches the dispatcher unchanged
    seen.clear()
    with mock.patch.object(backends, "select_backend", side_effect=recording):
        bend.hinge_hessians(x, backend="eager")
    assert seen == [("hinge_hessians", Backend.EAGER)]


def test_the_dispatchers_answer_alone_decides(sheet):
    """Told EAGER, no compiled code runs anywhere; told NATIVE, the kernels run and agree with eager."""
    bend, mem, x = _modules(sheet)
    boom = mock.Mock(side_effect=AssertionError("compiled code ran"))
    with mock.patch.object(backends, "select_backend", return_value=Backend.EAGER), \
            mock.patch.object(native, "bending_hessians", boom), mock.patch.object(native, "assemble_arrays", boom):
        eager = {name: call() for name, call in _entry_points(bend, mem, x).items()}
    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")
    ran = []
    real_blocks, real_assemble = native.bending_hessians, native.assemble_arrays

    def blocks(*a):
        ran.append("blocks")
        return real_blocks(*a)

    def assemble(*a):
        ran.append("assemble")
        return real_assemble(*a)

    def decide(op, backend, x, *params):
        return Backend.NATIVE if op in backends.NATIVE_OPS else Backend.EAGER

    with mock.patch.object(backends, "select_backend", side_effect=decide), \
            mock.patch.object(native, "bending_hessians", side_effect=blocks), \
            mock.patch.object(native, "assemble_arrays", side_effect=assemble):
        fused = {name: call() for name, call in _entry_points(bend, mem, x).items() if name.startswith("bend.h")}
    assert "blocks" in ran and "assemble" in ran
    for name, out in fused.items():
        a, b = (t.to_dense() if t.layout == torch.sparse_csr else t for t in (out, eager[name]))
        assert rel(a, b) <= 1e-13, name


def test_select_backend_rules(sheet):
    _, _, x = sheet
    p = torch.ones(3, dtype=F64)
    assert backends.select_backend("solve", "auto", x, p) is Backend.EAGER  # no kernel for that
    # the energy's kernels run inside the analytic autograd Functions: a recorded graph does not matter
    assert backends.native_unavailable_reason("energy", x.clone().requires_grad_(), p) in (
        None, f"the C++ extension is not available ({native.build_error()})")
    assert "for cuda tensors" not in str(backends.native_unavailable_reason("gradient", x, p))
    assert backends.select_backend("hinge_hessians", "eager", x, p) is Backend.EAGER
    reason = backends.native_unavailable_reason("hinge_hessians", x.clone().requires_grad_(), p)
    assert reason is not None and "autograd graph" in reason
    assert "float32 or float64" in str(backends.native_unavailable_reason("hinge_hessians", x.half(), p))
    assert "one mesh" in str(backends.native_unavailable_reason("hessian_hinge", x.expand(2, -1, -1), p))
    with torch.no_grad():
        assert backends.native_unavailable_reason("hinge_hessians", x.clone().requires_grad_(), p) in (
            None, f"the C++ extension is not available ({native.build_error()})")
    with pytest.raises(ValueError, match="unknown backend"):
        backends.select_backend("energy", "gpu", x)
    with tb.use_backend("eager"):
        assert backends.select_backend("hinge_hessians", "auto", x, p) is Backend.EAGER
    if native.load() is not None:
        assert backends.select_backend("hinge_hessians", "auto", x, p) is Backend.NATIVE
        with pytest.raises(ValueError, match="backend='native' cannot run hinge_hessians: .*autograd graph"):
            backends.select_backend("hinge_hessians", "native", x.clone().requires_grad_(), p)
