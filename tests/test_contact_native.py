"""The compiled contact operators (torchbend/csrc/contact_math.h, cpu_contact.cpp) against the eager reference
(torchbend.ops.distance, SelfContact's per-type formulas under autograd, eigh's projection), central differences
and brute force: distance types, squared distances, barrier energies, gradients and (projected) Hessians of every
type (mollified edge pairs included), the broad phase, the stencil sum, bad input and SelfContact's two paths."""
import pytest
import torch

import torchbend as tb
from torchbend.backends import native
from torchbend.ops import distance as dist
from torchbend.sim import self_contact as scm

pytestmark = pytest.mark.skipif(native.load() is None, reason="the CPU extension is not built")
F64 = torch.float64


def stencils(n: int, seed: int, dtype=F64, parallel: bool = False):
    """Random stencils ``(n, 4, 3)`` whose second primitive lies near the first (every distance type occurs);
    ``parallel``: the second edge nearly parallel to the first."""
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(n, 4, 3, generator=g, dtype=F64)
    X[:, 1:] = X[:, :1] + 0.5 * (X[:, 1:] - X[:, :1])
    if parallel:
        X[:, 3] = X[:, 2] + (X[:, 1] - X[:, 0]) * (1 + 0.1 * torch.rand(n, 1, generator=g, dtype=F64)) \
            + 1e-4 * torch.randn(n, 3, generator=g, dtype=F64)
    return X.to(dtype)


def flat(X):
    return X.reshape(-1, 3).contiguous(), torch.arange(X.shape[0] * 4).reshape(-1, 4)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("edge_edge", [False, True])
def test_types_and_squared_distances_are_the_eager_ones(edge_edge, dtype):
    X = torch.cat([stencils(3000, 1, dtype), stencils(500, 2, dtype, parallel=True)]) if edge_edge \
        else stencils(3000, 1, dtype)
    xa, st = flat(X)
    types, D = native.contact_distances(xa, st, edge_edge)
    ref = dist.edge_edge_type(X) if edge_edge else dist.point_triangle_type(X)
    assert torch.equal(types, ref)  # the same rounding: a stencil on a boundary gets the eager type
    assert len(torch.unique(types)) == (9 if edge_edge else 7)
    Dref = dist._by_type(X, ref)
    tol = 1e-12 if dtype == F64 else 1e-4
    torch.testing.assert_close(D, Dref, rtol=tol, atol=tol * float(Dref.abs().max()))


def eager_pair(X, kind, eps, dhat, kappa):
    """(energy, gradient (N, 12), Hessian (N, 12, 12)) of SelfContact's per-type formulas under autograd."""
    sc = tb.SelfContact(dhat=dhat, stiffness=kappa)
    Z = X.clone().requires_grad_(True)
    E = sc._pair_energy(Z, kind, eps)
    g = torch.autograd.grad(E.sum(), Z)[0].reshape(-1, 12)
    H = sc._pair_hessians(X.reshape(-1, 12), kind, eps)
    return E.detach(), g, H


def psd(H, mode):
    w, Q = torch.linalg.eigh(H)
    w = w.abs() if mode == "abs" else w.clamp_min(0)
    return (Q * w[:, None, :]) @ Q.transpose(1, 2)


@pytest.mark.parametrize("mollified", [False, True])
@pytest.mark.parametrize("edge_edge", [False, True])
def test_barrier_energy_gradient_and_hessians_match_autograd_of_the_eager_formulas(edge_edge, mollified):
    if mollified and not edge_edge:
        pytest.skip("point-triangle pairs have no mollifier")
    X = torch.cat([stencils(1500, 3), stencils(300, 4, parallel=True)]) if edge_edge else stencils(1500, 3)
    xa, st = flat(X)
    types, D = native.contact_distances(xa, st, edge_edge)
    dhat, kappa = float(D.median().sqrt()) * 1.5, 3.0
    eps = None
    if edge_edge:
        a, b = X[:, 1] - X[:, 0], X[:, 3] - X[:, 2]
        # |a x b|^2 <= |a|^2 |b|^2: every pair mollified with the second, none but the near-parallel with the first
        eps = (a * a).sum(-1) * (b * b).sum(-1) * (1.0 if mollified else 1e-3)
    E, G, H = native.contact_barrier(xa, st, types, eps, dhat ** 2, kappa, 2, "none")
    _, _, Hc = native.contact_barrier(xa, st, types, eps, dhat ** 2, kappa, 2, "clamp")
    _, _, Ha = native.contact_barrier(xa, st, types, eps, dhat ** 2, kappa, 2, "abs")
    E0, G0, _ = native.contact_barrier(xa, st, types, eps, dhat ** 2, kappa, 0, "none")
    assert torch.equal(E0, E) and G0.numel() == 0
    active = 0
    for kind in torch.unique(types).tolist():
        sel = types == kind
        Er, gr, Hr = eager_pair(X[sel], kind, None if eps is None else eps[sel], dhat, kappa)
        scale = Hr.abs().amax((1, 2), keepdim=True).clamp_min(1e-300)
        torch.testing.assert_close(E[sel], Er, rtol=1e-10, atol=1e-10 * float(Er.abs().max()))
        torch.testing.assert_close(G[sel] / scale[:, 0], gr / scale[:, 0], rtol=0, atol=1e-10)
        torch.testing.assert_close(H[sel] / scale, Hr / scale, rtol=0, atol=1e-10)
        torch.testing.assert_close(Hc[sel] / scale, psd(Hr, "clamp") / scale, rtol=0, atol=1e-10)
        torch.testing.assert_close(Ha[sel] / scale, psd(Hr, "abs") / scale, rtol=0, atol=1e-10)
        active += int((Er > 0).sum())
    assert active > 500
    # invariants: no net force; translations in the Hessians' null space
    assert float(G.reshape(-1, 4, 3).sum(1).abs().max()) <= 1e-10 * float(G.abs().max())
    t = torch.eye(3, dtype=F64).repeat(1, 4)  # (3, 12): the three translations
    for M in (H, Hc, Ha):
        assert float((M @ t.T).abs().max()) <= 1e-10 * float(M.abs().max())


def test_barrier_gradient_and_hessian_are_central_differences_of_the_energy():
    X = stencils(200, 5)
    xa, st = flat(X)
    for edge_edge in (False, True):
        types, D = native.contact_distances(xa, st, edge_edge)
        dh2 = float(D.max()) * 2
        a, b = X[:, 1] - X[:, 0], X[:, 3] - X[:, 2]
        eps = (a * a).sum(-1) * (b * b).sum(-1) * 0.5 if edge_edge else None
        E, G, H = native.contact_barrier(xa, st, types, eps, dh2, 1.0, 2, "none")
        best_g, best_h = float("inf"), float("inf")
        for h in (1e-4, 1e-5, 1e-6):
            d = torch.randn(X.shape, generator=torch.Generator().manual_seed(9), dtype=F64) * h
            # the same types along the small step (the difference of each type's smooth formula)
            Ep, Gp, _ = native.contact_barrier(xa + d.reshape(-1, 3), st, types, eps, dh2, 1.0, 1, "none")
            Em, Gm, _ = native.contact_barrier(xa - d.reshape(-1, 3), st, types, eps, dh2, 1.0, 1, "none")
            dv = d.reshape(-1, 12)
            fd_g, an_g = (Ep - Em) / 2, (G * dv).sum(1)
            fd_h, an_h = (Gp - Gm) / 2, (H @ dv[:, :, None])[:, :, 0]
            best_g = min(best_g, float(((fd_g - an_g).abs() / an_g.abs().clamp_min(1e-300)).median()))
            best_h = min(best_h, float(((fd_h - an_h).norm(dim=1) / an_h.norm(dim=1).clamp_min(1e-300)).median()))
        assert best_g < 1e-7 and best_h < 1e-7


def test_touching_pairs_have_infinite_energy_and_no_nan():
    X = stencils(4, 6)
    X[:, 0] = X[:, 1]  # the point on a corner of the triangle
    xa, st = flat(X)
    types, D = native.contact_distances(xa, st, False)
    E, G, H = native.contact_barrier(xa, st, types, None, 1.0, 1.0, 2, "clamp")
    assert bool((D == 0).all()) and bool(torch.isinf(E).all())
    assert bool((G == 0).all()) and bool((H == 0).all())


def brute_box_pairs(lo_a, hi_a, lo_b, hi_b, pad):
    ok = ((lo_a[:, None] <= hi_b[None] + 2 * pad) & (hi_a[:, None] + 2 * pad >= lo_b[None])).all(-1)
    return ok.nonzero()


def test_box_pairs_are_those_of_brute_force_without_shared_ids():
    g = torch.Generator().manual_seed(7)
    x = torch.rand(400, 3, generator=g, dtype=F64)
    faces = torch.randint(0, 400, (300, 3), generator=g)
    tri = x[faces]
    lo, hi = tri.amin(1), tri.amax(1)
    got = native.contact_box_pairs(x, x, lo, hi, 0.01, ids_a=torch.arange(400)[:, None], ids_b=faces)
    ref = brute_box_pairs(x, x, lo, hi, 0.01)
    ref = ref[(faces[ref[:, 1]] != ref[:, :1]).all(-1)]
    assert torch.equal(got, ref)  # row-major: each box's partners in order
    up = native.contact_box_pairs(lo, hi, lo, hi, 0.02, upper=True)
    ref = brute_box_pairs(lo, hi, lo, hi, 0.02)
    assert torch.equal(up, ref[ref[:, 0] < ref[:, 1]])
    far = native.contact_box_pairs(x, x, x + 1e6, x + 1e6, 0.01)  # huge offsets: nothing, and no overflow
    assert far.shape == (0, 2)


@pytest.mark.parametrize("spread", [1.0, 1e4])
def test_box_pairs_of_mixed_sizes_are_those_of_brute_force(spread):
    """Long boxes (a step's swept boxes) among small ones, on a dense grid of cells (one cluster) and on hashed
    cells (two clusters ``spread`` apart: most of the grid empty): every overlapping pair once, in order."""
    g = torch.Generator().manual_seed(11)
    n = 500
    far = (torch.arange(n) % 2 == 1)[:, None] * spread if spread > 1 else torch.zeros(n, 1)
    lo = torch.rand(n, 3, generator=g, dtype=F64) + far
    ext = 0.1 * torch.rand(n, 3, generator=g, dtype=F64)
    long = torch.rand(n, generator=g) < 0.2  # a fifth swept along one axis, up to half the cluster
    axis = torch.randint(0, 3, (n,), generator=g)
    ext[long, axis[long]] = 0.5 * torch.rand(int(long.sum()), generator=g, dtype=F64)
    hi = lo + ext
    pts = torch.rand(n, 3, generator=g, dtype=F64) + far
    for pad in (0.0, 0.01):
        got = native.contact_box_pairs(pts, pts, lo, hi, pad)
        assert torch.equal(got, brute_box_pairs(pts, pts, lo, hi, pad)) and got.shape[0] > 20
        up = native.contact_box_pairs(lo, hi, lo, hi, pad, upper=True)
        ref = brute_box_pairs(lo, hi, lo, hi, pad)
        assert torch.equal(up, ref[ref[:, 0] < ref[:, 1]]) and up.shape[0] > 50


@pytest.mark.parametrize("swept", [False, True])
def test_mesh_candidates_are_those_of_the_box_pairs(swept):
    """contact_candidates (one call) against its definition by two box-pair searches over the primitives' boxes:
    a crumpled grid, its vertices' boxes around the points or swept along a random step."""
    rest, faces = tb.scenes.grid(12, 12, (0.2, 0.2), dtype=F64)
    g = torch.Generator().manual_seed(3)
    x = rest + 0.02 * torch.randn(rest.shape, generator=g, dtype=F64)
    edges = tb.ClothModel(faces, x).topology.edges
    dx = 0.05 * torch.randn(x.shape, generator=g, dtype=F64) if swept else None
    lo, hi = scm.vertex_boxes(x, dx, 1e-4)
    pt, ee, pairs = native.contact_candidates(lo, hi, faces, edges, 0.01)
    idx = torch.arange(x.shape[0])
    ref_pt = native.contact_box_pairs(lo, hi, lo[faces].amin(1), hi[faces].amax(1), 0.005, ids_a=idx[:, None],
                                      ids_b=faces)
    assert torch.equal(pt, torch.cat([ref_pt[:, :1], faces[ref_pt[:, 1]]], 1))
    elo, ehi = lo[edges].amin(1), hi[edges].amax(1)
    ref_ee = native.contact_box_pairs(elo, ehi, elo, ehi, 0.005, upper=True, ids_a=edges, ids_b=edges)
    assert torch.equal(pairs, ref_ee) and torch.equal(ee, torch.cat([edges[ref_ee[:, 0]], edges[ref_ee[:, 1]]], 1))
    assert pt.shape[0] > 100 and ee.shape[0] > 100
    with pytest.raises(ValueError, match="faces"):
        native.contact_candidates(lo, hi, faces + x.shape[0], edges, 0.01)


def test_box_pairs_in_float32_far_from_the_origin_are_those_of_brute_force():
    """float32 boxes about 1e3 m from the origin whose gaps are 2 pad rounded in float32 (the test's sum rounds up to
    an overlap): each such pair is found whatever cell boundary falls in the gap (the grid's margin covers the final
    test's rounding)."""
    g = torch.Generator().manual_seed(12)
    n, pad, w = 3000, 1e-3, 1e-3  # boxes a millimetre wide: cells of a few millimetres, float32's ulp 3e-5-1e-4 m
    hb = (500 + 1000 * torch.rand(n, generator=g, dtype=F64)).float()
    lo_b = torch.stack([hb - w, torch.zeros(n), torch.zeros(n)], 1)
    hi_b = torch.stack([hb, torch.full((n,), w), torch.full((n,), w)], 1)
    la = hb + torch.tensor(2 * pad, dtype=torch.float32)  # rounded in float32, as the kernel's test is
    lo_a = torch.stack([la, torch.zeros(n), torch.zeros(n)], 1)
    hi_a = torch.stack([la + w, torch.full((n,), w), torch.full((n,), w)], 1)
    got = native.contact_box_pairs(lo_a, hi_a, lo_b, hi_b, pad)
    ref = brute_box_pairs(lo_a, hi_a, lo_b, hi_b, torch.tensor(pad, dtype=torch.float32))
    assert torch.equal(got, ref) and (got[:, 0] == got[:, 1]).sum() == n


def test_stencil_sum_is_the_eager_one():
    g = torch.Generator().manual_seed(8)
    V = 30
    st = torch.randint(0, V + 5, (200, 4), generator=g)  # some body vertices (>= V)
    H = torch.randn(200, 12, 12, generator=g, dtype=F64)
    got = native.contact_stencil_sum(st, H, V)
    ref = scm.stencil_sum(st, H, V)
    assert got.is_coalesced()
    torch.testing.assert_close(got.to_dense(), ref.to_dense(), rtol=1e-14, atol=1e-13)
    assert torch.equal(got.indices(), ref.indices())



def same_sum(got, ref, atol: float) -> int:
    """Assert that contact_hessian_sum's ``got`` is the stencil sum ``ref`` (both coalesced COO) within ``atol``,
    its entries among ref's and the ones it leaves out (blocks of corners a pair's energy does not depend on)
    zeros; returns how many it leaves out."""
    torch.testing.assert_close(got.to_dense(), ref.to_dense(), rtol=0, atol=atol)
    n = ref.shape[1]
    key_ref, key_got = ref.indices()[0] * n + ref.indices()[1], got.indices()[0] * n + got.indices()[1]
    kept = torch.isin(key_ref, key_got)
    assert bool(torch.isin(key_got, key_ref).all()) and bool((ref.values()[~kept] == 0).all())
    return int((~kept).sum())


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_hessian_sum_with_friction_pairs_is_the_stencil_sum_of_their_blocks(dtype):
    """contact_hessian_sum's friction pairs (stencils, weights w, point blocks H): the sum of the barrier's blocks
    and the friction's w w^T (x) H, as contact_stencil_sum of the two sets concatenated (body vertices >= V left
    out); none given: the barrier's alone."""
    xa, st = flat(stencils(60, 5, dtype))
    V = xa.shape[0] - 6  # the last two stencils' vertices partly a body's
    types, _ = native.contact_distances(xa, st, False)
    g = torch.Generator().manual_seed(4)
    M = 25
    sf = torch.randint(0, xa.shape[0], (M, 4), generator=g)
    w = torch.randn(M, 4, generator=g, dtype=F64).to(dtype)
    A = torch.randn(M, 3, 3, generator=g, dtype=F64)
    H3 = (A @ A.transpose(1, 2)).to(dtype)
    dh2 = 0.3
    _, _, H = native.contact_barrier(xa, st, types, None, dh2, 2.0, 2, "clamp")
    Hf = (w[:, :, None, None, None] * w[:, None, None, :, None] * H3[:, None, :, None, :]).reshape(-1, 12, 12)
    ref = native.contact_stencil_sum(torch.cat([st, sf]), torch.cat([H, Hf]), V)
    got = native.contact_hessian_sum(xa, st, types, None, dh2, 2.0, "clamp", V, (sf, w, H3))
    assert got.is_coalesced() and got.dtype == dtype
    eps = torch.finfo(dtype).eps
    same_sum(got, ref, 64 * eps * float(ref.values().abs().max()))
    alone = native.contact_hessian_sum(xa, st, types, None, dh2, 2.0, "clamp", V)
    torch.testing.assert_close(alone.to_dense(), native.contact_stencil_sum(st, H, V).to_dense(), rtol=0,
                               atol=64 * eps * float(H.abs().max()))
    with pytest.raises(ValueError, match="f_w"):
        native.contact_hessian_sum(xa, st, types, None, dh2, 2.0, "clamp", V, (sf, w[:, :3], H3))
    with pytest.raises(ValueError, match="f_stencils"):
        native.contact_hessian_sum(xa, st, types, None, dh2, 2.0, "clamp", V, (sf + xa.shape[0], w, H3))

def test_bad_arguments_are_value_errors_naming_them():
    xa, st = flat(stencils(3, 1))
    with pytest.raises(ValueError, match=r"stencils\[2, 1\] = 99 is out of range"):
        bad = st.clone()
        bad[2, 1] = 99
        native.contact_distances(xa, bad, False)
    types, _ = native.contact_distances(xa, st, False)
    with pytest.raises(ValueError, match="types"):
        native.contact_barrier(xa, st, types + 40, None, 1.0, 1.0, 2, "clamp")
    with pytest.raises(ValueError, match="dhat_sq"):
        native.contact_barrier(xa, st, types, None, -1.0, 1.0, 2, "clamp")
    with pytest.raises(ValueError, match="contact_gradient_sum.*types"):
        native.contact_gradient_sum(xa, st, types + 40, None, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"contact_gradient_sum.*stencils\[2, 1\] = 99"):
        bad = st.clone()
        bad[2, 1] = 99
        native.contact_gradient_sum(xa, bad, types, None, 1.0, 1.0)
    with pytest.raises(ValueError, match="finite"):
        lo = torch.zeros(2, 3, dtype=F64)
        lo[1, 0] = float("nan")
        native.contact_box_pairs(lo, lo, lo, lo, 0.1)


def folded(n=12):
    rest, faces = tb.scenes.grid(n, n, (0.1, 0.1), dtype=F64)
    h = 0.1 / (n - 1)
    x = torch.cat([rest, rest + torch.tensor([h / 3, h / 5, 1e-3], dtype=F64)])
    return x, torch.cat([faces, faces + rest.shape[0]])


def test_self_contact_compiled_and_eager_paths_agree(monkeypatch):
    x, f = folded()
    sc = tb.SelfContact(dhat=2e-3, stiffness=1e3)
    tb.ClothModel(f, x, terms=[sc])
    ctx = tb.StepContext()
    fast = [sc.energy(x, ctx), sc.gradient(x, ctx), sc.hessian(x, ctx, tb.Projection.CLAMP).to_dense(),
            sc.hessian(x, ctx, tb.Projection.NONE).to_dense(), sc.min_distance(x)]
    dx = torch.zeros_like(x)
    dx[x.shape[0] // 2:, 2] = -1e-3
    step = sc.max_step(x, dx, ctx)
    monkeypatch.setattr(scm, "_native_ok", lambda t: False)
    sc._cache = sc._close_cache = None
    slow = [sc.energy(x, ctx), sc.gradient(x, ctx), sc.hessian(x, ctx, tb.Projection.CLAMP).to_dense(),
            sc.hessian(x, ctx, tb.Projection.NONE).to_dense(), sc.min_distance(x)]
    assert fast[4] == slow[4] and fast[4][1] > 300
    for a, b in zip(fast[:4], slow[:4]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10 * float(b.abs().max()))
    assert sc.max_step(x, dx, ctx) == pytest.approx(step, rel=1e-12)



@pytest.mark.parametrize("dtype", [F64, torch.float32])
@pytest.mark.parametrize("shift", [1 / 3, 0.0], ids=["point_edge", "point_point"])
def test_hessian_sum_counts_a_contact_found_by_several_stencils_once_per_stencil(shift, dtype):
    """A vertex near an edge (or a vertex) of the other layer is found by several stencils (the triangles at the edge,
    the edges at the vertex); contact_hessian_sum (and contact_gradient_sum) computes one of them and counts it as
    many times: the sum is the stencil sum of every pair's own block (gradient), with the projection and without,
    mollified edge pairs (the layers' edges are parallel) left alone.  Its pattern leaves out the blocks of a corner
    the pair's energy does not depend on (a point-edge pair's fourth, a point-point pair's third and fourth): the
    stencil sum's entries it lacks are zeros."""
    rest, faces = tb.scenes.grid(9, 9, (0.1, 0.1), dtype=F64)
    h = 0.1 / 8
    x = torch.cat([rest, rest + torch.tensor([shift * h, shift * 0.6 * h, 1e-3], dtype=F64)]).to(dtype)
    f = torch.cat([faces, faces + rest.shape[0]])
    sc = tb.SelfContact(dhat=2e-3, stiffness=1e3)
    tb.ClothModel(f, x, terms=[sc])
    st, types, eps = sc._close(x)
    # the scene has what it tests: point-edge (or point-point) contacts found several times, mollified edge pairs
    corner = {3: (0, 1, 2), 4: (0, 2, 3), 5: (0, 3, 1), 11: (2, 0, 1), 12: (3, 0, 1), 13: (0, 2, 3), 14: (1, 2, 3),
              0: (0, 1), 1: (0, 2), 2: (0, 3), 7: (0, 2), 8: (0, 3), 9: (1, 2), 10: (1, 3)}
    X = x[st].double()
    mollified = (types >= 7) & (eps > 0) & (torch.linalg.cross(X[:, 1] - X[:, 0], X[:, 3] - X[:, 2]).square().sum(1) < eps)
    keys = [(s[c[0]], *sorted(s[j] for j in c[1:])) if len(c) == 3 else tuple(sorted(s[j] for j in c))
            for s, t, m in zip(st.tolist(), types.tolist(), mollified.tolist()) if t in corner and not m
            for c in [corner[t]]]
    assert len(keys) - len(set(keys)) > 100 and int(mollified.sum()) > 20
    V = x.shape[0]
    eps_ = torch.finfo(dtype).eps
    # the gradient's sum counts them the same way
    _, G, _ = native.contact_barrier(x, st, types, eps, 4e-6, 1e3, 1)
    ref_g = torch.zeros(V, 3, dtype=dtype).index_add_(0, st.reshape(-1), G.reshape(-1, 3))
    got_g = native.contact_gradient_sum(x, st, types, eps, 4e-6, 1e3)
    assert got_g.dtype == dtype and got_g.shape == (V, 3)
    # (added in another order: within 64 epsilons of each entry's sum of magnitudes)
    scale = torch.zeros(V, 3, dtype=dtype).index_add_(0, st.reshape(-1), G.abs().reshape(-1, 3))
    assert bool(((got_g - ref_g).abs() <= 64 * eps_ * scale).all())
    for mode in ("clamp", "none"):
        _, _, H = native.contact_barrier(x, st, types, eps, 4e-6, 1e3, 2, mode)
        ref = native.contact_stencil_sum(st, H, V)
        got = native.contact_hessian_sum(x, st, types, eps, 4e-6, 1e3, mode, V)
        assert same_sum(got, ref, 64 * eps_ * float(ref.values().abs().max())) > 100


@pytest.mark.parametrize("body", [False, True], ids=["self", "mesh_collider"])
def test_compiled_and_eager_hessians_agree_with_friction(monkeypatch, body):
    """In a time step with lagged friction the compiled Hessian (the barrier's from the pairs' reduced coordinates,
    the friction pairs' added in the same sum) is the eager one (12x12 blocks of both, summed), for self-contact and
    for a body (its vertices are not unknowns)."""
    x, f = folded()
    n = x.shape[0] // 2
    if body:
        term = tb.MeshCollider(x[:n], f[:f.shape[0] // 2], dhat=2e-3, stiffness=1e3, friction=0.4, eps_v=1e-3)
        x, f = x[n:], f[f.shape[0] // 2:] - n
    else:
        term = tb.SelfContact(dhat=2e-3, stiffness=1e3, friction=0.4, eps_v=1e-3)
    tb.ClothModel(f, x, terms=[term])
    v = torch.zeros_like(x)
    v[:, 0] = 0.02
    ctx = tb.StepContext.for_step([term], x, v, 0.01)
    assert term.name in ctx.lagged and ctx.lagged[term.name]["stencils"].shape[0] > 50
    y = x + 0.01 * v + 1e-6 * torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    fast = [term.hessian(y, ctx, p).to_dense() for p in (tb.Projection.CLAMP, tb.Projection.NONE)]
    monkeypatch.setattr(scm, "_native_ok", lambda t: False)
    term._cache = term._close_cache = None
    slow = [term.hessian(y, ctx, p).to_dense() for p in (tb.Projection.CLAMP, tb.Projection.NONE)]
    without = tb.StepContext()
    plain = term.hessian(y, without, tb.Projection.NONE).to_dense()
    assert float((slow[1] - plain).abs().max()) > 1e-3 * float(plain.abs().max())  # the friction counts
    for a, b in zip(fast, slow):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10 * float(b.abs().max()))

def test_close_pairs_are_the_eager_ones_every_pair_counted():
    """contact_close: the stencils closer than dhat (a box test first) and their types, as the eager distances
    give them, every one of them: a vertex above the shared edge of two triangles is a pair of each (the IPC
    toolkit's collision sets weigh such a contact by the number of pairs that find it)."""
    x, f = folded(10)
    x = x + 2e-4 * torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(1).values.unique(dim=0)
    pt, ee, _ = scm.candidate_pairs(x, f, edges, 4e-3)
    dh2 = (2.5e-3) ** 2
    for st, edge_edge in ((pt, False), (ee, True)):
        idx, types = native.contact_close(x, st, edge_edge, dh2)
        t_ref = dist.edge_edge_type(x[st]) if edge_edge else dist.point_triangle_type(x[st])
        D = dist._by_type(x[st], t_ref)
        close = (D < dh2).nonzero()[:, 0]
        assert close.numel() > 10 and torch.equal(idx, close) and torch.equal(types, t_ref[close])
    # one vertex above the shared edge of two triangles, the edge the second of one and the third of the other
    X = torch.tensor([[0.5, 0.0, 0.3], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -1.0, 0.0]],
                     dtype=F64)
    st = torch.tensor([[0, 1, 2, 3], [0, 4, 1, 2]])  # edge (1, 2): E01 in the first, E12 in the second
    idx, types = native.contact_close(X, st, False, 1.0)
    assert set(types.tolist()) == {dist.PT_E01, dist.PT_E12} and idx.tolist() == [0, 1]


def hard_stencils(dtype, edge_edge):
    """Random stencils of every type with the hard ones among them: nearly and exactly parallel edges, edges and
    triangles on a grid's lattice (a point exactly above an edge or a corner: stencils on the boundary between two
    types), collapsed edges and triangles, and a far offset."""
    parts = [stencils(2000, 11, dtype), stencils(400, 12, dtype, parallel=edge_edge)]
    g = torch.Generator().manual_seed(13)
    L = torch.randint(-2, 3, (600, 4, 3), generator=g).to(F64) * 0.25  # lattice points: exact ties
    L[:300, :, 2] = 0.0  # flat: coplanar, parallel and collinear stencils
    parts.append(L.to(dtype))
    C = stencils(200, 14, dtype)
    C[:100, 1] = C[:100, 0]  # a collapsed edge (a triangle with two equal corners)
    C[100:, 3] = C[100:, 2]
    parts.append(C)
    parts.append(stencils(200, 15, dtype) + 100.0)  # far from the origin
    return torch.cat(parts)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("edge_edge", [False, True])
def test_close_pairs_type_their_stencils_as_the_scalar_classifier(edge_edge, dtype):
    """contact_close classifies lanes of stencils branch-free; the types must be the scalar classifier's (the eager
    reference's, contact_distances) bit for bit, ties and degenerate stencils included, and a stencil is kept
    exactly when its distance is below dhat (up to rounding for one within 1e-6 of dhat)."""
    X = hard_stencils(dtype, edge_edge)
    xa, st = flat(X)
    ref_types, D = native.contact_distances(xa, st, edge_edge)
    assert torch.equal(ref_types, dist.edge_edge_type(X) if edge_edge else dist.point_triangle_type(X))
    idx, types = native.contact_close(xa, st, edge_edge, 1e30)  # everything finite is kept
    finite = torch.isfinite(D).nonzero()[:, 0]
    assert idx.shape[0] >= finite.shape[0] > 0.95 * st.shape[0]
    keep = torch.zeros(st.shape[0], dtype=torch.bool)
    keep[idx] = True
    assert keep[finite].all()
    assert torch.equal(types, ref_types[idx])
    for dh2 in (float(D[finite].median()), float(D[finite].quantile(0.1))):
        idx, types = native.contact_close(xa, st, edge_edge, dh2)
        kept = torch.zeros(st.shape[0], dtype=torch.bool)
        kept[idx] = True
        clear = ((D - dh2).abs() > 1e-6 * dh2) & torch.isfinite(D)
        assert torch.equal(kept[clear], (D < dh2)[clear]) and 0 < int(kept.sum()) < st.shape[0]
        assert torch.equal(types, ref_types[idx])


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("n", [3, 6, 9])
def test_the_contact_eigensolver_projects_as_eigh_on_hard_matrices(n, dtype):
    """The tridiagonal QL projection of the contact kernels (cpu_symeig.h) against eigh: random matrices, repeated
    and zero eigenvalues, rank one, zero and diagonal blocks, tiny and huge scales (clamp and abs)."""
    g = torch.Generator().manual_seed(n)
    A = torch.randn(300, n, n, generator=g, dtype=F64)
    A = A + A.transpose(1, 2)
    Q = torch.linalg.qr(torch.randn(300, n, n, generator=g, dtype=F64))[0]
    w = torch.randn(300, n, generator=g, dtype=F64).round()  # repeated integers, zeros among them
    B = (Q * w[:, None]) @ Q.transpose(1, 2)
    u = torch.randn(20, n, 1, generator=g, dtype=F64)
    M = torch.cat([A, B, u @ u.transpose(1, 2), -u @ u.transpose(1, 2), torch.zeros(3, n, n, dtype=F64),
                   torch.diag_embed(torch.randn(5, n, generator=g, dtype=F64)), 1e-30 * A[:9], 1e30 * A[:9]])
    M = M.to(dtype)
    w, V = torch.linalg.eigh(M.double())
    for mode, f in ((0, w.clamp_min(0)), (1, w.abs())):
        P = native._module().contact_project_blocks(M, mode)
        ref = (V * f[:, None, :]) @ V.transpose(1, 2)
        scale = M.double().abs().amax((1, 2)).clamp_min(1e-300)
        err = float(((P.double() - ref).abs().amax((1, 2)) / scale).max())
        assert err <= (50 if dtype == F64 else 20) * torch.finfo(dtype).eps * n, err


def test_step_bound_is_the_eager_one():
    """contact_step_bound (the box gap skips stencils that cannot set the bound) against 0.9 d / (m_A + m_B) over
    every stencil, eager, for random moves of every size."""
    x, f = folded(10)
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(1).values.unique(dim=0)
    pt, ee, _ = scm.candidate_pairs(x, f, edges, 0.05)
    g = torch.Generator().manual_seed(4)
    for scale in (1e-5, 1e-3, 1e-1):
        move = scale * torch.rand(x.shape[0], generator=g, dtype=F64)
        move[::7] = 0.0
        for st, edge_edge in ((pt, False), (ee, True)):
            got = native.contact_step_bound(x, st, edge_edge, move)
            d = dist._by_type(x[st], dist.edge_edge_type(x[st]) if edge_edge else dist.point_triangle_type(x[st]))
            split = 2 if edge_edge else 1
            rate = move[st][:, :split].amax(1) + move[st][:, split:].amax(1)
            ok = rate > 0
            ref = min(1.0, float((0.9 * d[ok].clamp_min(0).sqrt() / rate[ok]).min()))
            assert got == pytest.approx(ref, rel=1e-12)


def test_step_bound_of_displacements_ignores_the_move_a_pair_shares():
    """contact_step_bound with displacements (n, 3): each side's largest displacement less the pair's mean (or the
    displacements' own lengths where theirs is the smaller sum), against the eager formula over every stencil; a
    translation of everything leaves every pair unbounded (1), and no bound is below the one of the moves'
    lengths."""
    x, f = folded(10)
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(1).values.unique(dim=0)
    pt, ee, _ = scm.candidate_pairs(x, f, edges, 0.05)
    g = torch.Generator().manual_seed(5)
    for scale in (1e-5, 1e-3, 1e-1):
        dx = scale * torch.randn(x.shape, generator=g, dtype=F64)
        dx[::7] = 0.0
        shift = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
        for st, edge_edge in ((pt, False), (ee, True)):
            got = native.contact_step_bound(x, st, edge_edge, dx)
            d = dist._by_type(x[st], dist.edge_edge_type(x[st]) if edge_edge else dist.point_triangle_type(x[st]))
            split = 2 if edge_edge else 1
            mv = (dx[st] - dx[st].mean(1, keepdim=True)).norm(dim=-1)
            ln = dx[st].norm(dim=-1)
            rate = torch.minimum(mv[:, :split].amax(1) + mv[:, split:].amax(1),
                                 ln[:, :split].amax(1) + ln[:, split:].amax(1))
            ok = rate > 0
            ref = min(1.0, float((0.9 * d[ok].clamp_min(0).sqrt() / rate[ok]).min()))
            assert got == pytest.approx(ref, rel=1e-12)
            assert native.contact_step_bound(x, st, edge_edge, (scale * shift).expand_as(x).contiguous()) == 1.0
            lengths = native.contact_step_bound(x, st, edge_edge, dx.norm(dim=1))
            assert got >= lengths * (1 - 1e-12)
    with pytest.raises(ValueError, match="move must hold"):
        native.contact_step_bound(x, pt, False, torch.zeros(x.shape[0], 2, dtype=F64))


def test_a_folded_cloth_falling_as_a_whole_is_not_held_back_by_its_step_bound():
    """Two layers 1 mm apart moved down 5 cm together: no pair's distance changes, so the self-contact's step bound
    lets the whole step through (with the moves' lengths it was 0.9 mm / 10 cm, about 0.01)."""
    x, f = folded(10)
    sc = tb.SelfContact(dhat=2e-3, stiffness=1.0)
    tb.ClothModel(f, x, terms=[sc])
    dx = torch.zeros_like(x)
    dx[:, 2] = -0.05
    assert sc.max_step(x, dx, tb.StepContext()) == 1.0
    dx[x.shape[0] // 2:, 2] = -0.05 - 2e-3  # the upper layer 2 mm further: it may close 0.9 of the 1 mm gap
    assert sc.max_step(x, dx, tb.StepContext()) == pytest.approx(0.9 * 1e-3 / 2e-3, rel=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("case", ["tiny_gap", "tiny_scale", "huge_scale", "offset"])
def test_projection_in_the_normal_frame_holds_at_the_extremes(case, dtype):
    """The clamp and abs projections in the pairs' normal frame (contact_frame.h: a 4x4 or 5x5 eigenproblem) against
    eigh of the same unprojected Hessians (in float64): gaps a millionth of the edges, coordinates at 1e-3 and 1e3 m,
    and stencils 1e3 m from the origin; the error relative to the block's largest entry, as eigh's."""
    X = stencils(600, 7)
    scale, offset = {"tiny_scale": (1e-3, 0.0), "huge_scale": (1e3, 0.0), "offset": (1.0, 1e3)}.get(case, (1.0, 0.0))
    if case == "tiny_gap":  # the point a millionth of the triangle's size above its centroid
        X = X.clone()
        n = torch.linalg.cross(X[:, 2] - X[:, 1], X[:, 3] - X[:, 1])
        X[:, 0] = X[:, 1:].mean(1) + 1e-6 * n / n.norm(dim=-1, keepdim=True)
    xa, st = flat(X * scale + offset)
    xa = xa.to(dtype)
    for edge_edge in (False, True):
        types, D = native.contact_distances(xa, st, edge_edge)
        dhat = float(D.double().median().sqrt()) * 1.5
        _, _, H = native.contact_barrier(xa, st, types, None, dhat ** 2, 1.0, 2, "none")
        H = H.double()
        active = H.abs().amax((1, 2)) > 0
        assert int(active.sum()) > 100
        for mode in ("clamp", "abs"):
            P = native.contact_barrier(xa, st, types, None, dhat ** 2, 1.0, 2, mode)[2].double()
            err = ((P - psd(H, mode)).abs() / H.abs().amax((1, 2), keepdim=True).clamp_min(1e-300)).amax((1, 2))
            assert float(err[active].max()) <= 200 * torch.finfo(dtype).eps, (edge_edge, mode, float(err.max()))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_projection_in_the_normal_frame_of_pairs_just_inside_dhat(dtype):
    """A point-plane and a point-line pair a ten-millionth to a ten-thousandth inside dhat = 1 mm: the barrier's
    gradient is so small that its square underflows in float32 (the frame is built from the gradient scaled by its
    largest entry); the clamp projection against eigh of the same unprojected Hessian."""
    dhat = 1e-3
    rows = []
    for frac in (1 - 1e-7, 1 - 1e-6, 1 - 1e-4, 0.5):
        d = dhat * frac
        rows.append([[0.2, 0.2, d], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # above the face
        rows.append([[0.5, -d, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # beside the edge t0 t1
    X = torch.tensor(rows, dtype=dtype)
    xa, st = flat(X)
    types = torch.tensor([dist.PT_FACE, dist.PT_E01] * 4)
    assert torch.equal(native.contact_distances(xa, st, False)[0], types)
    for kappa in (1.0, 1e-6):
        H = native.contact_barrier(xa, st, types, None, dhat ** 2, kappa, 2, "none")[2].double()
        P = native.contact_barrier(xa, st, types, None, dhat ** 2, kappa, 2, "clamp")[2].double()
        scale = H.abs().amax((1, 2), keepdim=True)
        assert bool((scale > 0).all())
        err = ((P - psd(H, "clamp")).abs() / scale).amax((1, 2))
        assert float(err.max()) <= 200 * torch.finfo(dtype).eps, (kappa, err.tolist())

