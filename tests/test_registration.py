"""The operators ``torch.ops.torchbend.*`` registered in C++ (``csrc/cpu_registration.cpp``): the schemas of the one
table (``torchbend.backends._table.SCHEMAS``), the CPU kernels from C++ and the fakes from Python; through the
dispatcher they give the same bits and the same errors (type and message: the one status helper) as the eager
shortcut of ``torchbend.backends.ops.run``; without the extension the same schemas are defined from Python and
the eager path runs."""
import os
import subprocess
import sys

import pytest
import torch

import torchbend as tb
from torchbend.backends import _table, native, ops

F64 = torch.float64
needs_kernel = pytest.mark.skipif(native.load() is None, reason="C++ extension unavailable")


def test_every_schema_is_the_tables():
    for name, schema in _table.SCHEMAS.items():
        assert str(getattr(torch.ops.torchbend, name).default._schema) == f"torchbend::{name}{schema}"
    assert list(_table.SCHEMAS) == list(_table.OPERATORS) == list(ops.OPS)
    for name, fn in ops._KERNELS.items():  # the Python kernels' annotations say the same
        assert torch.library.infer_schema(fn, mutates_args=()) == _table.SCHEMAS[name], name


@needs_kernel
def test_registered_in_cpp_with_python_fakes():
    assert not ops.PYTHON_DEFINED
    for name in _table.OPERATORS:
        dump = torch._C._dispatch_dump(f"torchbend::{name}")
        assert "registered at" in dump and "cpu_registration.cpp" in dump.split("schema:")[1].splitlines()[1], dump
        cpu = next(line for line in dump.splitlines() if line.startswith("CPU:"))
        assert ("ops.py" if name in ops._PYTHON_KERNELS else "cpu_registration.cpp") in cpu, dump
        assert torch._C._dispatch_has_kernel_for_dispatch_key(f"torchbend::{name}", "Meta"), name


def _args():
    rest, faces = tb.scenes.random_curved_sheet(7, 6, amplitude=0.3, seed=2, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2)
    gen = torch.Generator().manual_seed(2)
    x = rest + 0.02 * torch.randn((2, *rest.shape), generator=gen, dtype=F64)
    v = torch.randn(x.shape, generator=gen, dtype=F64)
    t = torch.randn(bend.hinge_count, 4, generator=gen, dtype=F64)
    H = bend.hinge_count
    base = (bend.hinges, bend.weights, bend.stiffness.reshape(1), bend.rest_angles, torch.full((H,), 0.1, dtype=F64),
            bend.angles(x) + 0.01)
    ptr, idx = native.incidence(bend.hinges, x.shape[-2])
    w = torch.rand(H, generator=gen, dtype=F64)
    return bend, x, v, t, base, (w, ptr, idx)


def _calls(x, v, t, base, inc, model="tan", check=True):
    w, ptr, idx = inc
    return {
        "bending_energy": (x, *base, model, check),
        "bending_gradient": (x, *base, model, w, ptr, idx, True, check),
        "bending_energy_gradient": (x, *base, model, ptr, idx, True, check),
        "bending_hvp": (x, v, *base, model, w, ptr, idx, check),
        "bending_second_order": (x, v, t, *base, model, w, ptr, idx),
        "hinge_hessians": (x, *base, model, check),
    }


@needs_kernel
def test_dispatcher_and_shortcut_same_bits():
    bend, x, v, t, base, inc = _args()
    for name, args in _calls(x, v, t, base, inc).items():
        a, b = getattr(torch.ops.torchbend, name)(*args), ops._KERNELS[name](*args)
        for p, q in zip(*((r,) if isinstance(r, torch.Tensor) else r for r in (a, b))):
            assert p.shape == q.shape and p.dtype == q.dtype and torch.equal(p, q), name
    Hb = torch.ops.torchbend.hinge_hessians(x, *base, "tan")[0]
    assert torch.equal(torch.ops.torchbend.project_blocks(Hb, "clamp", True), ops.run("project_blocks", Hb, "clamp", True))


def _error(fn, *args):
    try:
        fn(*args)
    except Exception as e:  # noqa: BLE001 -- the type and message are compared
        return type(e), str(e)
    return None


@needs_kernel
def test_dispatcher_and_shortcut_same_errors():
    """Non-finite positions or directions (check=True), a folded tan hinge, an unknown model, a bad argument: the
    same exception type and message through the C++ kernels as through the Python shortcut."""
    bend, x, v, t, base, inc = _args()
    nan_x = x.clone()
    nan_x[1, 5, 2] = float("nan")
    nan_v = v.clone()
    nan_v[0, 3, 1] = float("inf")
    h0 = bend.hinges[0].tolist()  # fold hinge 0 flat onto itself: x3 onto x2 (|theta| = pi)
    folded = x.clone()
    folded[:, h0[3]] = folded[:, h0[2]]
    bad_hinges = bend.hinges.clone()
    bad_hinges[3, 1] = 10_000
    variants = {
        "nan_x": _calls(nan_x, v, t, base, inc),
        "nan_v": {"bending_hvp": _calls(x, nan_v, t, base, inc)["bending_hvp"]},
        "folded": _calls(folded, v, t, base, inc),
        "model": _calls(x, v, t, base, inc, model="cubic"),
        "hinges": _calls(x, v, t, (bad_hinges, *base[1:]), inc),
    }
    for kind, calls in variants.items():
        for name, args in calls.items():
            a, b = _error(getattr(torch.ops.torchbend, name), *args), _error(ops._KERNELS[name], *args)
            if kind == "nan_x" and name == "bending_second_order":  # no input check (check=False by design)
                assert a is None and b is None
                continue
            assert a is not None and a[0] is ValueError, (kind, name, a)
            assert a == b, (kind, name)
    err = _error(torch.ops.torchbend.bending_energy, *_calls(folded, v, t, base, inc)["bending_energy"])
    assert err is not None and "folded through" in err[1]


_FALLBACK = r"""
import torch, torch.utils.cpp_extension as ce
def no_compiler(*a, **k):
    raise RuntimeError("no compiler here")
ce.load = no_compiler
import warnings
warnings.simplefilter("ignore")
import torchbend as tb
from torchbend.backends import _table, native, ops
assert native.load() is None and "no compiler here" in native.build_error() and ops.PYTHON_DEFINED
for name, schema in _table.SCHEMAS.items():
    assert str(getattr(torch.ops.torchbend, name).default._schema) == f"torchbend::{name}{schema}"
rest, faces = tb.scenes.random_curved_sheet(5, 4, amplitude=0.3, seed=1, dtype=torch.float64)
bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-2)
x = rest + 0.01 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
with tb.use_backend("eager"):
    ref = (bend(x), bend.gradient(x), bend.hessian(x).values())
out = (bend(x), bend.gradient(x), bend.hessian(x).values())
assert all(torch.equal(a, b) for a, b in zip(out, ref))
try:
    torch.ops.torchbend.bending_energy(x, bend.hinges, bend.weights, bend.stiffness.reshape(1), bend.rest_angles,
                                       None, None, "tan", False)
except RuntimeError as e:
    assert "the C++ extension is not available" in str(e), e
else:
    raise AssertionError("no error")
print("fallback ok")
"""


def test_without_the_extension_the_python_schemas_and_the_eager_path():
    env = dict(os.environ, TORCHBEND_PREBUILT="0")
    run = subprocess.run([sys.executable, "-c", _FALLBACK], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and "fallback ok" in run.stdout, run.stdout[-2000:] + run.stderr[-3000:]


@needs_kernel
def test_cuda_kernels_registered_by_the_cuda_binding():
    """Where the CUDA binding builds (nvcc; a CPU-only torch too), loading it registers the CUDA kernels of every
    operator the CUDA driver runs (TORCH_LIBRARY_IMPL(torchbend, CUDA)); project_blocks' stays Python's."""
    from torchbend.backends import _build_config as cfg
    from torchbend.backends import cuda

    if cfg.find_nvcc() is None or cuda.load() is None:
        pytest.skip(f"the CUDA binding is not built here ({cuda.build_error() if cfg.find_nvcc() else 'no nvcc'})")
    for name, kernel in _table.OPERATORS.items():
        line = next((s for s in torch._C._dispatch_dump(f"torchbend::{name}").splitlines() if s.startswith("CUDA:")), "")
        expected = "cuda_binding.cpp" if kernel is not None else ("ops.py" if name in ops._PYTHON_KERNELS else "")
        assert (expected in line) if expected else not line, (name, line)
