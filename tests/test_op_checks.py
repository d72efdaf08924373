"""The argument checks of the compiled operators ``torch.ops.torchbend.*`` (torchbend/csrc/checks.h): every
argument a caller can get wrong is a ``ValueError`` naming the operator, the argument and the first offending
entry, before any memory is read through it; each check has a case here that fails without it.  Zero-size
inputs (no samples, no hinges) are valid.  A fuzz test calls every operator with corrupted arguments in a
subprocess and asserts a clean exception, never a signal."""
import functools
import os
import re
import subprocess
import sys

import pytest
import torch

import torchbend as tb
from torchbend.backends import native
from torchbend.energies.sparse import HessianPattern

F64 = torch.float64
OPS = torch.ops.torchbend


@pytest.fixture(scope="module", autouse=True)
def kernel():
    if native.load() is None:
        pytest.skip(f"C++ kernel could not be built here: {native.build_error()}")


class Case:
    """A small mesh and valid arguments of every operator; ``shuffled``: hinges in random order, so that the
    gradient operators sum through the incidence lists (their unblocked path) instead of blocks of hinges."""

    def __init__(self, n=6, shuffled=False, batch=()):
        rest, faces = tb.scenes.random_curved_sheet(n, n, amplitude=0.3, seed=3, dtype=F64)
        bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1.0)
        self.topo = bend.topology
        h = bend.hinges
        if shuffled:
            h = h[torch.randperm(h.shape[0], generator=torch.Generator().manual_seed(0))]
        self.h = h.contiguous()
        self.H, self.V = self.h.shape[0], rest.shape[0]
        gen = torch.Generator().manual_seed(1)
        self.x = rest + 0.02 * torch.randn((*batch, *rest.shape), generator=gen, dtype=F64)
        self.v = torch.randn(self.x.shape, generator=gen, dtype=F64)
        self.a = bend.weights.to(F64)
        self.k = torch.ones(1, dtype=F64)
        self.r = bend.rest_angles.to(F64) if not shuffled else torch.zeros(self.H, dtype=F64)
        self.ptr, self.idx = native.incidence(self.h, self.V)
        self.w = torch.ones(1, dtype=F64)
        self.t = torch.randn(self.H, 4, generator=gen, dtype=F64)
        self.pat = HessianPattern(self.topo)
        self.shuffled = shuffled

    def call(self, op, **kw):
        """``torch.ops.torchbend.<op>`` with the valid arguments, some replaced by ``kw``."""
        g = {"x": self.x, "v": self.v, "hinges": self.h, "a": self.a, "k": self.k, "rest": self.r, "c": None,
             "prev": None, "model": "tan", "weight": self.w, "ptr": self.ptr, "idx": self.idx, "t": self.t,
             "params": False, "check": False, "M": None, "mode": "clamp", "hinge_blocks": self.pat.hinge_blocks,
             "faces": self.topo.faces, "face_edge_hinges": self.topo.face_edge_hinges,
             "face_edge_signs": self.topo.face_edge_signs, "face_blocks": self.pat.face_blocks,
             "row_len": self.pat.row_len, "nnz": self.pat.nnz, "per_triangle": True}
        g.update(kw)
        base = (g["x"], g["hinges"], g["a"], g["k"], g["rest"], g["c"], g["prev"], g["model"])
        if op == "bending_energy":
            return OPS.bending_energy(*base, g["check"])
        if op == "bending_gradient":
            return OPS.bending_gradient(*base, g["weight"], g["ptr"], g["idx"], g["params"], g["check"])
        if op == "bending_energy_gradient":
            return OPS.bending_energy_gradient(*base, g["ptr"], g["idx"], g["params"], g["check"])
        if op == "bending_hvp":
            return OPS.bending_hvp(g["x"], g["v"], *base[1:], g["weight"], g["ptr"], g["idx"], g["check"])
        if op == "bending_second_order":
            return OPS.bending_second_order(g["x"], g["v"], g["t"], *base[1:], g["weight"], g["ptr"], g["idx"])
        if op == "hinge_hessians":
            return OPS.hinge_hessians(*base, g["check"])
        if op == "assemble":
            return OPS.assemble(g["x"], *base[1:], g["hinge_blocks"], g["faces"], g["face_edge_hinges"],
                                g["face_edge_signs"], g["face_blocks"], g["row_len"], g["nnz"], g["per_triangle"])
        raise KeyError(op)


@functools.cache
def case(n=6, shuffled=False, batch=()) -> Case:
    """A shared :class:`Case` (tests replace its arguments through ``call``'s keywords, never in place)."""
    return Case(n, shuffled, batch)


BENDING = ["bending_energy", "bending_gradient", "bending_energy_gradient", "bending_hvp", "bending_second_order",
           "hinge_hessians", "assemble"]
GRADIENT = ["bending_gradient", "bending_energy_gradient", "bending_hvp", "bending_second_order"]


def raises(op: str, pattern: str, fn, *args, **kw):
    with pytest.raises(ValueError, match=rf"torchbend\.{op}: .*{pattern}") as e:
        fn(*args, **kw)
    return str(e.value)


def corrupted(t: torch.Tensor, pos: "int | tuple[int, ...]", value: float) -> torch.Tensor:
    t = t.clone()
    t[pos] = value
    return t


@pytest.mark.parametrize("shuffled", [False, True], ids=["blocked", "incidence"])
@pytest.mark.parametrize("op", BENDING)
@pytest.mark.parametrize("value", ["V", -1, 2**62, -2**63], ids=["one_past_end", "negative", "huge", "min"])
def test_hinge_index_out_of_range(op, value, shuffled):
    c = case(n=40 if shuffled else 6, shuffled=shuffled)
    if op == "assemble" and shuffled:
        pytest.skip("the assembly's pattern follows the topology's hinge order")
    val = c.V if value == "V" else value
    h = corrupted(c.h, (c.H - 2, 3), val)
    msg = raises(op, re.escape(f"hinges[{c.H - 2}, 3] = {val} is out of range [0, {c.V})"), c.call, op, hinges=h)
    assert f"V = {c.V}" in msg


@pytest.mark.parametrize("op", BENDING)
def test_first_offending_entry_named(op):
    c = case()
    h = corrupted(corrupted(c.h, (5, 1), c.V + 7), (9, 0), -3)
    raises(op, re.escape(f"hinges[5, 1] = {c.V + 7}"), c.call, op, hinges=h)


@pytest.mark.parametrize("op", BENDING)
@pytest.mark.parametrize("half", ["c", "prev"])
def test_half_viscous_pair(op, half):
    c = case()
    one = torch.full((1,), 0.3, dtype=F64)
    raises(op, "viscous term needs both c and prev", c.call, op, **{half: one})


@pytest.mark.parametrize("op", BENDING)
def test_viscous_pair_both_given_works(op):
    c = case()
    out = c.call(op, c=torch.full((1,), 0.3, dtype=F64), prev=torch.zeros(c.H, dtype=F64))
    for t in (out if isinstance(out, (tuple, list)) else (out,)):
        assert torch.isfinite(t).all()


@pytest.mark.parametrize("op", BENDING)
@pytest.mark.parametrize("bad", ["int32", "shape", "float"])
def test_hinges_tensor_kind(op, bad):
    c = case()
    h = {"int32": c.h.int(), "shape": c.h[:, :3].contiguous(), "float": c.h.double()}[bad]
    raises(op, "hinges must", c.call, op, hinges=h)


@pytest.mark.parametrize("op", BENDING)
@pytest.mark.parametrize("name", ["a", "k", "rest"])
def test_parameter_size(op, name):
    c = case()
    raises(op, f"{name} has 3 values", c.call, op, **{name: torch.ones(3, dtype=F64)})


@pytest.mark.parametrize("op", BENDING)
def test_parameter_device(op):
    c = case()
    raises(op, "(k must be on the CPU|every tensor argument must be on)", c.call, op, k=torch.ones(1, dtype=F64, device="meta"))


@pytest.mark.parametrize("op", BENDING)
@pytest.mark.parametrize("dtype", [torch.float16, torch.int64])
def test_position_dtype(op, dtype):
    c = case()
    raises(op, "x must be float32 or float64", c.call, op, x=c.x.to(dtype))


@pytest.mark.parametrize("op", BENDING)
def test_unknown_model(op):
    c = case()
    raises(op, "model must be one of 'quadratic', 'tan', 'sin', got 'cubic'", c.call, op, model="cubic")


@pytest.mark.parametrize("op", ["bending_gradient", "bending_hvp", "bending_second_order"])
def test_weight_size(op):
    c = case()
    raises(op, "weight has 2 values", c.call, op, weight=torch.ones(2, dtype=F64))


@pytest.mark.parametrize("op", ["bending_hvp", "bending_second_order"])
def test_direction_shape(op):
    c = case()
    raises(op, "v must be a CPU tensor of x's shape", c.call, op, v=c.v[:-1])


def test_second_order_tangent_shape():
    c = case()
    raises("bending_second_order", "t must be", c.call, "bending_second_order", t=c.t[:-1])


# ---- incidence lists ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("shuffled", [False, True], ids=["blocked", "incidence"])
@pytest.mark.parametrize("op", GRADIENT)
@pytest.mark.parametrize("bad", ["ptr_size", "idx_size", "ptr_start", "ptr_end", "ptr_decreasing", "idx_range",
                                 "idx_negative", "int32"])
def test_incidence_lists(op, bad, shuffled):
    c = case(n=40 if shuffled else 6, shuffled=shuffled)
    ptr, idx = c.ptr, c.idx
    kw, pattern = {
        "ptr_size": ({"ptr": ptr[:-1]}, r"ptr \(incidence lists\) must have V \+ 1"),
        "idx_size": ({"idx": idx[:-1]}, r"idx \(incidence lists\) must have 4 H"),
        "ptr_start": ({"ptr": corrupted(ptr, 0, 1)}, "must run from 0 to 4 H"),
        "ptr_end": ({"ptr": corrupted(ptr, -1, 4 * c.H + 9)}, "must run from 0 to 4 H"),
        "ptr_decreasing": ({"ptr": corrupted(ptr, 3, 10**9)}, r"nondecreasing: ptr\[4\] < ptr\[3\]"),
        "idx_range": ({"idx": corrupted(idx, 11, 4 * c.H)}, re.escape(f"idx[11] = {4 * c.H} is out of range")),
        "idx_negative": ({"idx": corrupted(idx, 2, -5)}, re.escape("idx[2] = -5 is out of range")),
        "int32": ({"idx": idx.int()}, "must be int64"),
    }[bad]
    if not shuffled and bad in ("ptr_decreasing", "idx_range", "idx_negative"):
        # hinges in a compact order are summed in blocks: the lists' content is not read (and not checked, a pass
        # over them would cost more than the checks' budget), so the result is the one of the true lists
        out, ref = c.call(op, **kw), c.call(op)
        for t, u in zip(out if isinstance(out, (tuple, list)) else (out,), ref if isinstance(ref, (tuple, list))
                        else (ref,)):
            assert torch.equal(t, u)
        return
    raises(op, pattern, c.call, op, **kw)


@pytest.mark.parametrize("op", GRADIENT)
@pytest.mark.parametrize("bad", ["swapped", "duplicate"])
def test_incidence_content_where_read(op, bad):
    """Lists in range but not those of the hinges: wrong sums without the check (the unblocked path reads them)."""
    c = case(n=40, shuffled=True)
    idx = c.idx.clone()
    p0, p1 = int(c.ptr[0]), int(c.ptr[c.V - 1])  # an entry of vertex 0 and one of vertex V - 1
    if bad == "swapped":
        idx[p0], idx[p1] = c.idx[p1].item(), c.idx[p0].item()
    else:
        idx[p0 + 1] = idx[p0]
    raises(op, "not the incidence lists of these hinges", c.call, op, idx=idx)


@pytest.mark.parametrize("op", GRADIENT)
def test_incidence_path_matches_blocked_path(op):
    """The same hinges summed through the incidence lists and in blocks: one result (the checks change nothing)."""
    c = case(n=40, shuffled=True)
    out = c.call(op)
    perm = torch.argsort(c.h[:, 0] * c.V + c.h[:, 1])  # a compact order: blocked
    h2 = c.h[perm].contiguous()
    ptr2, idx2 = native.incidence(h2, c.V)
    kw = dict(hinges=h2, ptr=ptr2, idx=idx2, rest=c.r[perm], a=c.a if c.a.numel() == 1 else c.a[perm], t=c.t[perm])
    out2 = c.call(op, **kw)
    first, second = (out[0], out2[0]) if isinstance(out, (tuple, list)) else (out, out2)
    if op == "bending_energy_gradient":
        first, second = out[1], out2[1]
    torch.testing.assert_close(first, second, rtol=1e-12, atol=1e-12 * float(second.abs().max()))


# ---- assembly pattern --------------------------------------------------------------------------------------

@pytest.mark.parametrize("per_triangle", [False, True], ids=["per_hinge", "per_triangle"])
@pytest.mark.parametrize("bad", ["hinge_block_next_row", "hinge_block_negative", "hinge_block_huge",
                                 "hinge_block_row_end", "row_len_short", "row_len_not_3", "row_len_negative",
                                 "nnz_small", "nnz_large", "hinge_blocks_rows"])
def test_assemble_pattern(bad, per_triangle):
    c = case()
    p = c.pat
    hb, rl = p.hinge_blocks, p.row_len
    v0 = int(c.h[4, 0])
    row_end = 3 * int(rl[:v0].sum()) + int(rl[v0])  # one past the first scalar row of block row v0
    kw, pattern = {
        "hinge_block_next_row": ({"hinge_blocks": corrupted(hb, (4, 1), row_end)}, r"hinge_blocks\[4, 1\]"),
        "hinge_block_negative": ({"hinge_blocks": corrupted(hb, (4, 0), -1)}, r"hinge_blocks\[4, 0\] = -1"),
        "hinge_block_huge": ({"hinge_blocks": corrupted(hb, (4, 2), 2**60)}, r"hinge_blocks\[4, 2\]"),
        "hinge_block_row_end": ({"hinge_blocks": corrupted(hb, (4, 3), row_end - 2)}, r"hinge_blocks\[4, 3\]"),
        "row_len_short": ({"row_len": rl[:-1]}, r"row_len must have shape \(V,\)"),
        "row_len_not_3": ({"row_len": corrupted(rl, 2, int(rl[2]) + 1), "nnz": p.nnz + 3}, "multiple of 3"),
        "row_len_negative": ({"row_len": corrupted(rl, 2, -3)}, r"row_len\[2\] = -3 is out of range"),
        "nnz_small": ({"nnz": p.nnz - 1}, "does not match the pattern"),
        "nnz_large": ({"nnz": p.nnz + 9}, "does not match the pattern"),
        "hinge_blocks_rows": ({"hinge_blocks": hb[:-1]}, "hinge_blocks must have H"),
    }[bad]
    raises("assemble", pattern, c.call, "assemble", per_triangle=per_triangle, **kw)


@pytest.mark.parametrize("bad", ["face_block", "face_vertex", "face_edge_hinge", "face_edge_hinge_low",
                                 "face_edge_sign", "faces_shape", "face_blocks_rows"])
def test_assemble_faces(bad):
    c = case()
    p, topo = c.pat, c.topo
    f = int(p.hinged_faces[3])
    kw, pattern = {
        "face_block": ({"face_blocks": corrupted(p.face_blocks, (f, 4), -7)}, rf"face_blocks\[{f}, 4\] = -7"),
        "face_vertex": ({"faces": corrupted(topo.faces, (f, 2), c.V)}, rf"faces\[{f}, 2\] = {c.V} is out of range"),
        "face_edge_hinge": ({"face_edge_hinges": corrupted(topo.face_edge_hinges, (f, 0), c.H)},
                            rf"face_edge_hinges\[{f}, 0\] = {c.H}"),
        "face_edge_hinge_low": ({"face_edge_hinges": corrupted(topo.face_edge_hinges, (f, 1), -2)},
                                rf"face_edge_hinges\[{f}, 1\] = -2"),
        "face_edge_sign": ({"face_edge_signs": corrupted(topo.face_edge_signs, (f, 1), 0)}, "must be \\+1 or -1"),
        "faces_shape": ({"faces": topo.faces[:, :2].contiguous()}, r"faces must have shape \(n, 3\)"),
        "face_blocks_rows": ({"face_blocks": p.face_blocks[:-1]}, "face_blocks must have F"),
    }[bad]
    raises("assemble", pattern, c.call, "assemble", **kw)


def test_assemble_batched_positions_rejected():
    c = case(batch=(2,))
    raises("assemble", r"x must be a CPU \(V, 3\) tensor", c.call, "assemble")


# ---- projections -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n", [12, 9, 5])
def test_project_blocks_checks(n):
    M = torch.randn(4, n, n, dtype=F64)
    M = M + M.transpose(-1, -2)
    torch.testing.assert_close(OPS.project_blocks(M, "clamp", False), OPS.project_blocks(M.clone(), "clamp", False))
    raises("project_blocks", "non-finite", OPS.project_blocks, corrupted(M, (2, 1, 1), float("nan")), "clamp", False)
    raises("project_blocks", r"\(\.\.\., n, n\)", OPS.project_blocks, M[..., :-1], "clamp", False)
    raises("project_blocks", "mode must be", OPS.project_blocks, M, "bogus", False)


# ---- zero-size inputs are valid ----------------------------------------------------------------------------

@pytest.mark.parametrize("op", [o for o in BENDING if o != "assemble"])
def test_zero_samples(op):
    c = case(batch=(0,))
    H, V = c.H, c.V
    out = c.call(op, t=torch.zeros(0, H, 4, dtype=F64))
    outs = out if isinstance(out, (tuple, list)) else (out,)
    expected = {"bending_energy": [(0, H)], "bending_gradient": [(0, V, 3), (0,)],
                "bending_energy_gradient": [(0, H), (0, V, 3), (0,)], "bending_hvp": [(0, V, 3)],
                "bending_second_order": [(0, V, 3), (0, H, 4), (0, H)],
                "hinge_hessians": [(0, H, 12, 12), (0, H, 12), (0, H)]}[op]
    assert [tuple(t.shape) for t in outs] == expected
    assert all(t.dtype == F64 for t in outs)


@pytest.mark.parametrize("op", BENDING)
def test_no_hinges(op):
    c = case()
    H0 = c.h[:0]
    ptr, idx = native.incidence(H0, c.V)
    out = c.call(op, hinges=H0, a=c.a[:0] if c.a.numel() > 1 else c.a, rest=c.r[:0], ptr=ptr, idx=idx, t=c.t[:0],
                 hinge_blocks=c.pat.hinge_blocks[:0], face_edge_hinges=torch.full_like(c.topo.face_edge_hinges, -1),
                 row_len=torch.zeros_like(c.pat.row_len), nnz=0)
    outs = out if isinstance(out, (tuple, list)) else (out,)
    for t in outs:
        assert torch.isfinite(t).all()
    if op in GRADIENT:
        assert outs[1 if op == "bending_energy_gradient" else 0].abs().max() == 0


# ---- fuzz: corrupted arguments in a subprocess, a clean exception and never a signal -----------------------

FUZZ = r'''
import random, sys, torch
sys.path.insert(0, sys.argv[1])
from tests.test_op_checks import Case, BENDING, GRADIENT
seed, n = int(sys.argv[2]), int(sys.argv[3])
rng = random.Random(seed)
torch.manual_seed(seed)
cases = [Case(), Case(n=40, shuffled=True), Case(batch=(2,)), Case(batch=(0,))]
PATTERN = ["hinge_blocks", "faces", "face_edge_hinges", "face_edge_signs", "face_blocks", "row_len"]
def used(op, c):  # the index arguments the operator reads (incidence lists: only for hinges in no compact order)
    index = ["hinges"] + (["ptr", "idx"] if op in GRADIENT and c.shuffled else []) + (PATTERN if op == "assemble" else [])
    real = ["x", "a", "k", "rest"] + (["weight"] if op in ("bending_gradient", "bending_hvp", "bending_second_order") else []) \
        + (["v"] if op in ("bending_hvp", "bending_second_order") else []) + (["t"] if op == "bending_second_order" else [])
    return index, real
def array(c, name):
    for owner in (c, c.pat, c.topo):
        t = getattr(owner, {"hinges": "h"}.get(name, name) if owner is c else name, None)
        if isinstance(t, torch.Tensor):
            return t
    raise KeyError(name)
def bad_value(name, c):
    if name == "face_edge_signs":
        return rng.choice([0, 2, -2, 2**40])
    if name == "face_edge_hinges":
        return rng.choice([c.H, c.H + 5, -2, -2**63, 2**62])
    top = {"hinges": c.V, "faces": c.V, "idx": 4 * c.H, "ptr": 4 * c.H + 1, "row_len": 3 * c.V + 1}.get(name)
    if top is None:  # block bases: outside [0, nnz) is always wrong
        top = c.pat.nnz
    return rng.choice([top, top + 1, -1, -rng.randrange(1, 10**6), 2**62, 2**63 - 1, -2**63, rng.randrange(top, 10**12)])
def blocks(bad):
    n = rng.choice([9, 12, 5])
    M = torch.randn(rng.choice([0, 1, 3, 17]), n, n, dtype=rng.choice([torch.float32, torch.float64]))
    M = M + M.transpose(-1, -2)
    mode, hinge = rng.choice(["clamp", "abs"]), rng.random() < 0.5
    if bad == "nan" and M.numel():
        M.view(-1)[rng.randrange(M.numel())] = rng.choice([float("nan"), float("inf"), -float("inf")])
    elif bad == "shape":
        M = M[..., :-1]
    elif bad == "mode":
        mode = rng.choice(["bogus", "reduced" if n != 12 else "gauss_newton", ""])
    elif bad == "dtype":
        M = M.to(torch.int64)
    elif bad == "rank":
        M = M.reshape(-1)
    return M, mode, hinge
valid = caught = 0
for it in range(n):
    if rng.random() < 0.15:
        bad = rng.choice(["nan", "shape", "mode", "dtype", "rank", "valid"])
        M, mode, hinge = blocks(bad)
        print(it, "project_blocks", bad, tuple(M.shape), M.dtype, mode, hinge, flush=True)
        try:
            torch.ops.torchbend.project_blocks(M, mode, hinge)
        except ValueError as e:
            if bad == "valid" or (bad == "nan" and M.numel() == 0):
                print("valid call raised:", e, flush=True)
                sys.exit(2)
            caught += 1
            continue
        if bad != "valid" and not (bad == "nan" and M.numel() == 0):
            print("not caught", flush=True)
            sys.exit(3)
        valid += 1
        continue
    c = rng.choice(cases)
    ops = BENDING if c.x.dim() == 2 and not c.shuffled else [o for o in BENDING if o != "assemble"]
    op = rng.choice(ops)
    index, real = used(op, c)
    kw = {}
    kind = rng.choice(["index"] * 4 + ["viscous", "empty", "size"] + (["nnz"] if op == "assemble" else []) + ["valid"])
    if kind == "index":
        name = rng.choice(index)
        t = array(c, name).clone()
        flat = t.reshape(-1)
        if flat.numel() == 0:
            continue
        if name == "ptr":  # a pointer inside (a value in range may still be valid): its ends or a decrease
            pos = rng.choice([0, flat.numel() - 1, rng.randrange(1, flat.numel() - 1)])
            flat[pos] = bad_value(name, c) if pos else 1
            if 0 < pos < flat.numel() - 1:
                flat[pos] = flat[pos + 1] + 1 + rng.randrange(10**6)
        else:
            for _ in range(rng.choice([1, 1, 2, 5])):
                flat[rng.randrange(flat.numel())] = bad_value(name, c)
        kw[name] = t
    elif kind == "viscous":
        kw[rng.choice(["c", "prev"])] = torch.ones(1, dtype=torch.float64)
    elif kind == "empty":
        name = rng.choice(index + [r for r in real if r != "k"])
        kw[name] = torch.empty(0, dtype=torch.int64 if name in index else torch.float64)
        if name in real and name != "x" and c.x.numel() == 0:
            continue  # no samples: (B * H,) = (0,) values are a valid batched parameter
    elif kind == "size":
        name = rng.choice(real)
        kw[name] = torch.randn(rng.choice([2, 5, 7]), dtype=torch.float64)
    elif kind == "nnz":
        kw["nnz"] = rng.choice([-1, 0, 10**15, c.pat.nnz - 3, c.pat.nnz + 3])
    print(it, op, kind, sorted(kw), "shuffled" if c.shuffled else "", tuple(c.x.shape[:-2]), flush=True)
    try:
        c.call(op, **kw)
    except ValueError as e:
        if kind == "valid":
            print("valid call raised:", e, flush=True)
            sys.exit(2)
        caught += 1
        continue
    if kind != "valid":
        print("not caught", flush=True)
        sys.exit(3)
    valid += 1
print("done", valid, caught, flush=True)
'''


@pytest.mark.parametrize("seed", [0, 1])
def test_fuzz_corrupted_arguments(seed, tmp_path):
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    script = tmp_path / "fuzz.py"
    script.write_text(FUZZ)
    done = subprocess.run([sys.executable, str(script), root, str(seed), "400"], capture_output=True, text=True,
                          timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    last = (done.stdout.strip().splitlines() or [""])[-1]
    assert done.returncode == 0, f"fuzz process ended with {done.returncode} after: {last}\n{done.stderr[-3000:]}"
    assert last.startswith("done"), last
    _, valid, caught = last.split()
    assert int(caught) > 250 and int(valid) > 20, last
