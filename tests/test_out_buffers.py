"""Caller-owned output buffers (``out=``): ``BendingEnergy.hessian`` (its CSR values),
``BendingEnergy.hinge_hessians`` and ``torchbend.backends.native.assemble_arrays`` write into the buffer, return
it (the matrix's ``values()`` are the buffer itself), give the same bits as a new output on every path (compiled
and eager, per hinge and per triangle, projected), and refuse a buffer of the wrong shape, dtype, device or
layout with a ``ValueError`` naming ``out``."""
import pytest
import torch

import torchbend as tb
from torchbend.backends import native

F64 = torch.float64


def _sheet(dtype=F64, model="tan"):
    rest, faces = tb.scenes.random_curved_sheet(9, 7, amplitude=0.3, seed=4, dtype=F64)
    bend = tb.BendingEnergy(faces, rest, model=model, stiffness=1e-2).to(dtype)
    x = (rest + 0.01 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(4), dtype=F64)).to(dtype)
    return bend, x


def _backends():
    return ["eager"] + (["native"] if native.load() is not None else [])


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize("projection", [None, "clamp", "gauss_newton"])
@pytest.mark.parametrize("assembly", ["triangle", "hinge"])
def test_hessian_out_same_bits_and_the_buffer_itself(backend, projection, assembly):
    bend, x = _sheet()
    kw = dict(projection=projection, assembly=assembly, backend=backend)
    fresh = bend.hessian(x, **kw)
    buf = torch.full((bend.hessian_nnz(),), float("nan"), dtype=F64)  # every entry is written
    for _ in range(2):  # reused
        H = bend.hessian(x, out=buf, **kw)
        assert H.values().data_ptr() == buf.data_ptr()
        assert torch.equal(H.values(), fresh.values())
        assert torch.equal(H.crow_indices(), fresh.crow_indices()) and torch.equal(H.col_indices(), fresh.col_indices())


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("projection", [None, "clamp"])
def test_hinge_hessians_out_same_bits_and_the_buffer_itself(backend, dtype, projection):
    bend, x = _sheet(dtype, model="sin")
    for y in (x, torch.stack((x, 1.01 * x))):  # one mesh and a batch
        fresh = bend.hinge_hessians(y, projection=projection, backend=backend)
        buf = torch.full(fresh.shape, float("nan"), dtype=dtype)
        out = bend.hinge_hessians(y, projection=projection, backend=backend, out=buf)
        assert out is buf
        assert torch.equal(out, fresh)


def test_out_is_validated_with_a_value_error_naming_it():
    bend, x = _sheet()
    n, H = bend.hessian_nnz(), bend.hinge_count
    cases = [
        (torch.empty(n + 1, dtype=F64), f"out must have shape \\({n},\\), got \\({n + 1},\\)"),
        (torch.empty(n, dtype=torch.float32), "out must have x's dtype \\(torch.float64\\), got torch.float32"),
        (torch.empty(2 * n, dtype=F64)[::2], "out must be contiguous"),
        (torch.empty(n, dtype=F64, device="meta"), "out must be on x's device \\(cpu\\), got meta"),
        (torch.empty(n, dtype=F64, requires_grad=True), "out must not require grad"),
        ([0.0] * n, "out must be a tensor, got list"),
    ]
    for backend in _backends():
        for out, match in cases:
            with pytest.raises(ValueError, match="BendingEnergy.hessian: " + match):
                bend.hessian(x, out=out, backend=backend)
        with pytest.raises(ValueError, match=rf"BendingEnergy.hinge_hessians: out must have shape \({H}, 12, 12\)"):
            bend.hinge_hessians(x, out=torch.empty(H, 12, 13, dtype=F64), backend=backend)
    big = torch.empty(n + x.numel(), dtype=F64)
    y = big[:x.numel()].view(x.shape)
    y.copy_(x)
    with pytest.raises(ValueError, match="BendingEnergy.hessian: out overlaps x"):
        bend.hessian(y, out=big[x.numel() - 3:x.numel() - 3 + n])


@pytest.mark.skipif(native.load() is None, reason="C++ extension unavailable")
@pytest.mark.parametrize("per_triangle", [False, True])
def test_native_assemble_arrays_out(per_triangle):
    """The compiled assembly's own out=: the buffer comes back, the same bits as a new output; a wrong buffer is
    the ValueError of the operator naming ``out``."""
    from torchbend.energies.sparse import HessianPattern

    bend, x = _sheet()
    topo, pat = bend.topology, HessianPattern(bend.topology)
    args = (x, bend.hinges, bend.weights, bend.stiffness.reshape(1), bend.rest_angles, None, None, "tan",
            pat.hinge_blocks, topo.faces, topo.face_edge_hinges, topo.face_edge_signs, pat.face_blocks, pat.row_len,
            pat.nnz, per_triangle)
    fresh = native.assemble_arrays(*args)
    assert torch.equal(fresh, torch.ops.torchbend.assemble(*args))
    buf = torch.full((pat.nnz,), float("nan"), dtype=F64)
    out = native.assemble_arrays(*args, out=buf)
    assert out.data_ptr() == buf.data_ptr() and torch.equal(out, fresh)
    bad = [
        (torch.empty(pat.nnz + 1, dtype=F64), rf"torchbend.assemble: out must have shape \(nnz,\) = \({pat.nnz},\)"),
        (torch.empty(pat.nnz, dtype=torch.float32), "torchbend.assemble: out must have x's dtype"),
        (torch.empty(2 * pat.nnz, dtype=F64)[::2], "torchbend.assemble: out must be contiguous"),
    ]
    for out, match in bad:
        with pytest.raises(ValueError, match=match):
            native.assemble_arrays(*args, out=out)
    xr = torch.empty(pat.nnz + x.numel(), dtype=F64)
    xr[:x.numel()] = x.reshape(-1)
    with pytest.raises(ValueError, match="torchbend.assemble: out overlaps x"):
        native.assemble_arrays(xr[:x.numel()].view(x.shape), *args[1:], out=xr[:pat.nnz])
