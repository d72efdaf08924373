"""Self-contact (``tb.SelfContact``; :mod:`torchbend.ops.distance`, :mod:`torchbend.sim.self_contact`):
squared distances of every type against the IPC toolkit (``ipctk``, optional) and its derivatives, the
barrier and mollifier against ``ipctk``'s; the term's gradient and Hessian against central differences and
autograd; the step bound that keeps a path free of intersections (an exact segment-triangle test); two
sheets that fall onto each other and rest apart."""
import math

import numpy as np
import pytest
import torch

import torchbend as tb
from torchbend.ops.distance import (
    barrier,
    edge_edge_distance_sq,
    edge_edge_type,
    mollifier,
    point_triangle_distance_sq,
    point_triangle_type,
    typed_distance_sq,
)

F64 = torch.float64


def random_stencils(n: int, seed: int, near_parallel: bool = False) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    X = torch.randn(n, 4, 3, generator=gen, dtype=F64)
    if near_parallel:  # the second edge nearly parallel to the first, offset
        d = X[:, 1] - X[:, 0]
        X[:, 2] = X[:, 0] + 0.3 * torch.randn(n, 3, generator=gen, dtype=F64)
        X[:, 3] = X[:, 2] + d * (0.5 + torch.rand(n, 1, generator=gen, dtype=F64)) + 1e-7 * torch.randn(n, 3, generator=gen, dtype=F64)
    return X


def typed_derivatives(X: torch.Tensor, classify):
    """(squared distances, gradients (N, 12), Hessians (N, 12, 12)) by autograd of each stencil's typed formula."""
    types = classify(X)
    D, G, H = [], [], []
    for i in range(X.shape[0]):
        kind = int(types[i])

        def f(z, kind=kind):
            return typed_distance_sq(z.reshape(1, 4, 3), kind).sum()

        z = X[i].reshape(12)
        D.append(f(z))
        G.append(torch.func.grad(f)(z))
        H.append(torch.func.hessian(f)(z))
    return torch.stack(D), torch.stack(G), torch.stack(H)


def test_point_triangle_distances_and_derivatives_match_ipctk():
    ipctk = pytest.importorskip("ipctk")
    X = random_stencils(300, 1)
    D, G, H = typed_derivatives(X, point_triangle_type)
    torch.testing.assert_close(point_triangle_distance_sq(X), D, rtol=0, atol=0)
    seen = set()
    for i in range(X.shape[0]):
        p, t0, t1, t2 = (X[i, k].numpy() for k in range(4))
        seen.add(int(point_triangle_type(X[i:i + 1])[0]))
        ref = ipctk.point_triangle_distance(p, t0, t1, t2)
        assert math.isclose(float(D[i]), ref, rel_tol=1e-12), i
        np.testing.assert_allclose(G[i].numpy(), ipctk.point_triangle_distance_gradient(p, t0, t1, t2), rtol=1e-10,
                                   atol=1e-12 * float(G[i].abs().max()))
        np.testing.assert_allclose(H[i].numpy(), ipctk.point_triangle_distance_hessian(p, t0, t1, t2), rtol=1e-9,
                                   atol=1e-10 * float(H[i].abs().max()))
    assert len(seen) == 7  # every type met


@pytest.mark.parametrize("near_parallel", [False, True], ids=["random", "near_parallel"])
def test_edge_edge_distances_match_ipctk(near_parallel):
    ipctk = pytest.importorskip("ipctk")
    X = random_stencils(300, 2, near_parallel)
    D = edge_edge_distance_sq(X)
    u, v = X[:, 1] - X[:, 0], X[:, 3] - X[:, 2]
    # the line-line formula's conditioning: |u|^2 |v|^2 / |u x v|^2 (near-parallel edges: ipctk keeps the
    # line-line formula down to sin^2 = 1e-20, this code takes a corner-edge pair below 1e-10)
    cond = (u * u).sum(-1) * (v * v).sum(-1) / (torch.linalg.cross(u, v) ** 2).sum(-1)
    for i in range(X.shape[0]):
        a0, a1, b0, b1 = (X[i, k].numpy() for k in range(4))
        ref = ipctk.edge_edge_distance(a0, a1, b0, b1)
        tol = 1e-10 + 100 * 2.2e-16 * float(cond[i])
        assert math.isclose(float(D[i]), ref, rel_tol=tol, abs_tol=1e-14 * float((X[i] ** 2).sum())), i
    if not near_parallel:
        _, G, H = typed_derivatives(X[:100], edge_edge_type)
        agree = 0
        for i in range(100):
            a0, a1, b0, b1 = (X[i, k].numpy() for k in range(4))
            g = ipctk.edge_edge_distance_gradient(a0, a1, b0, b1)
            np.testing.assert_allclose(G[i].numpy(), g, rtol=1e-9, atol=1e-11 * float(np.abs(g).max()))
            np.testing.assert_allclose(H[i].numpy(), ipctk.edge_edge_distance_hessian(a0, a1, b0, b1), rtol=1e-8,
                                       atol=1e-9 * float(H[i].abs().max()))
            agree += 1
        assert agree == 100


def test_barrier_and_mollifier_match_ipctk():
    ipctk = pytest.importorskip("ipctk")
    dhat = 1e-3
    for D in (1e-12, 1e-9, 2.5e-7, 9.9e-7, 2e-6):  # squared distances around dhat^2 = 1e-6
        ref = ipctk.barrier(D, dhat ** 2) if D < dhat ** 2 else 0.0
        got = float(barrier(torch.tensor([D], dtype=F64), dhat ** 2, 1.0))
        assert math.isclose(got, ref, rel_tol=1e-13, abs_tol=0), D
    X = random_stencils(50, 3, near_parallel=True)
    for i in range(50):
        a0, a1, b0, b1 = (X[i, k].numpy() for k in range(4))
        eps_x = ipctk.edge_edge_mollifier_threshold(a0, a1, b0, b1)
        ref = ipctk.edge_edge_mollifier(a0, a1, b0, b1, eps_x)
        got = float(mollifier(X[i:i + 1], torch.tensor([eps_x], dtype=F64)))
        assert math.isclose(got, ref, rel_tol=1e-10, abs_tol=1e-15), i


def two_sheets(n: int = 4, gap: float = 0.01, dhat: float = 2e-3, size: float = 0.1):
    """A pinned sheet and a free one ``gap`` above it (one mesh of two components)."""
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=F64)
    V = rest.shape[0]
    shift = torch.tensor([0.013, 0.007, gap], dtype=F64)  # not vertex above vertex: every distance type occurs
    x = torch.cat([rest, rest + shift])
    f = torch.cat([faces, faces + V])
    sc = tb.SelfContact(dhat=dhat)
    model = tb.ClothModel(f, x, membrane=tb.MembraneEnergy(f, x, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(f, x, stiffness=1e-5), terms=[sc], density=0.2,
                          pinned=torch.arange(V))
    return model, x, sc, V


def segment_crosses_triangle(p0, p1, t0, t1, t2) -> torch.Tensor:
    """Moller-Trumbore test ``(N,)``: segment p0->p1 crosses triangle (t0, t1, t2) (segments within 1e-10 rad of
    the triangle's plane are not tested: coplanar overlaps do not occur between non-adjacent primitives here)."""
    e1, e2, d = t1 - t0, t2 - t0, p1 - p0
    h = torch.linalg.cross(d, e2)
    a = (e1 * h).sum(-1)
    # a segment (nearly) in the triangle's plane: u, v, t are round-off there; such a pair is not a crossing
    ok = a.abs() > 1e-10 * d.norm(dim=-1) * e1.norm(dim=-1) * e2.norm(dim=-1)
    f = 1 / torch.where(ok, a, torch.ones_like(a))
    s = p0 - t0
    u = f * (s * h).sum(-1)
    q = torch.linalg.cross(s, e1)
    v = f * (d * q).sum(-1)
    t = f * (e2 * q).sum(-1)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def intersects(x: torch.Tensor, faces: torch.Tensor, edges: torch.Tensor, cloth: int | None = None) -> bool:
    """Whether some edge crosses a triangle that does not contain either of its vertices (with ``cloth``: only
    the pairs that involve one of the first ``cloth`` vertices, the cloth's, beside a body's).  Float32 positions are
    tested in float64 (their exact values; float32 products would round gaps of a few float32 ulps away)."""
    x = x.double()
    E, F = edges.shape[0], faces.shape[0]
    ei = edges[:, None, :].expand(E, F, 2).reshape(-1, 2)
    fi = faces[None].expand(E, F, 3).reshape(-1, 3)
    keep = (ei[:, :, None] != fi[:, None, :]).all(-1).all(-1)
    if cloth is not None:
        keep &= (ei[:, 0] < cloth) | (fi[:, 0] < cloth)
    ei, fi = ei[keep], fi[keep]
    return bool(segment_crosses_triangle(x[ei[:, 0]], x[ei[:, 1]], x[fi[:, 0]], x[fi[:, 1]], x[fi[:, 2]]).any())


def test_self_contact_gradient_and_hessian_match_differences_and_autograd():
    model, x, sc, V = two_sheets(gap=1.2e-3)
    ctx = tb.StepContext()
    e0 = float(sc.energy(x, ctx))
    d, count = sc.min_distance(x)
    assert e0 > 0 and count > 20 and 0 < d < 2e-3
    g = sc.gradient(x, ctx)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    best = math.inf
    for h in (1e-6, 1e-7, 1e-8, 1e-9):
        fd = (float(sc.energy(x + h * v, ctx)) - float(sc.energy(x - h * v, ctx))) / (2 * h)
        best = min(best, abs(fd - float((g * v).sum())) / abs(float((g * v).sum())))
    assert best < 1e-7, best
    H = sc.hessian(x, ctx).to_dense()
    Hv = (H @ v.reshape(-1)).reshape(-1, 3)
    best = math.inf
    for h in (1e-6, 1e-7, 1e-8):
        fd = (sc.gradient(x + h * v, ctx) - sc.gradient(x - h * v, ctx)) / (2 * h)
        best = min(best, float((fd - Hv).norm() / Hv.norm()))
    assert best < 1e-6, best
    torch.testing.assert_close(H, H.T, rtol=0, atol=1e-12 * float(H.abs().max()))
    P = sc.hessian(x, ctx, tb.Projection.CLAMP).to_dense()
    assert float(torch.linalg.eigvalsh(P).min()) >= -1e-9 * float(P.abs().max())
    assert float(g.sum(0).norm()) <= 1e-10 * float(g.norm())  # internal forces: no net force


def test_stencil_sum_adds_every_stencil_block_and_leaves_body_vertices_out():
    from torchbend.sim.self_contact import stencil_sum

    gen = torch.Generator().manual_seed(3)
    V, Vb = 30, 5  # 30 cloth vertices, 5 of a body (indices 30..34: not unknowns)
    st = torch.stack([torch.randperm(V + Vb, generator=gen)[:4] for _ in range(60)])
    H = torch.randn(60, 12, 12, generator=gen, dtype=F64)
    ref = torch.zeros(3 * (V + Vb), 3 * (V + Vb), dtype=F64)
    dof = (3 * st[:, :, None] + torch.arange(3)).reshape(-1, 12)
    for m in range(60):
        ref.index_put_((dof[m][:, None].expand(12, 12), dof[m][None, :].expand(12, 12)), H[m], accumulate=True)
    A = stencil_sum(st, H, V)
    assert A.is_coalesced() and A.shape == (3 * V, 3 * V)
    torch.testing.assert_close(A.to_dense(), ref[: 3 * V, : 3 * V], rtol=1e-15, atol=1e-14)
    assert tb.sim.terms.as_csr(A).layout == torch.sparse_csr
    empty = stencil_sum(torch.zeros(0, 4, dtype=torch.int64), torch.zeros(0, 12, 12, dtype=F64), V)
    assert empty.shape == (3 * V, 3 * V) and empty._nnz() == 0


def test_contact_blocks_projected_by_the_compiled_jacobi_match_eigh():
    """The pairs' clamp/abs projections (compiled Jacobi in the translations' complement on the CPU) against eigh of
    the same blocks, within eps of the blocks' largest entry."""
    from torchbend.sim.self_contact import _project

    model, x, sc, V = two_sheets(gap=1.2e-3)
    xa = x.detach()
    blocks = torch.cat([sc._pair_hessians(xa[st].reshape(-1, 12), kind, eps) for st, kind, eps in sc._groups(x)])
    assert blocks.shape[0] > 10
    for proj in (tb.Projection.CLAMP, tb.Projection.ABS):
        w, Q = torch.linalg.eigh(0.5 * (blocks + blocks.transpose(-1, -2)))
        w = w.abs() if proj is tb.Projection.ABS else w.clamp_min(0)
        ref = (Q * w[:, None, :]) @ Q.transpose(-1, -2)
        scale = blocks.abs().amax((-1, -2), keepdim=True)
        assert float(((_project(blocks, proj) - ref).abs() / scale).max()) < 1e-12


def test_self_contact_step_bound_keeps_every_path_free_of_intersections():
    model, x, sc, V = two_sheets(gap=1.5e-3)
    topo = model.topology
    gen = torch.Generator().manual_seed(5)
    for trial in range(5):
        dx = torch.zeros_like(x)
        dx[V:] = 0.01 * torch.randn(V, 3, generator=gen, dtype=F64) - torch.tensor([0, 0, 0.01], dtype=F64)
        alpha = sc.max_step(x, dx, tb.StepContext())
        assert 0 < alpha <= 1
        for t in torch.linspace(0, 1, 41, dtype=F64).tolist():
            y = x + t * alpha * dx
            assert not intersects(y, topo.faces, topo.edges), (trial, t)
            assert sc.min_distance(y, radius=0.05)[0] > 0
        assert alpha < 1  # the whole step would have pushed the sheet through


def test_the_step_bound_lets_pairs_slide_and_part_and_stops_them_short_of_meeting(monkeypatch):
    """Conservative advancement: a sheet 1.5 mm above another (dhat 2 mm) moved 5 cm sideways or 5 cm up keeps
    its distances, so nothing holds the step back (a single bound 0.9 d / rate would stop both at 0.027); moved
    5 cm down, it stops short of the lower sheet (between the first advance and the gap), every point of the path
    free of intersections; a diagonal move (down and sideways) stops short too.  The compiled bound and the eager
    one (torchbend.sim.self_contact._advance) agree."""
    import torchbend.sim.self_contact as sc_module

    model, x, sc, V = two_sheets(n=6, gap=1.5e-3)
    topo = model.topology
    for move, bound in [((0.05, 0.0, 0.0), 1.0), ((0.0, 0.05, 0.0), 1.0), ((0.0, 0.0, 0.05), 1.0),
                        ((0.0, 0.0, -0.05), None), ((0.03, 0.0, -0.05), None)]:
        dx = torch.zeros_like(x)
        dx[V:] = torch.tensor(move, dtype=F64)
        alpha = sc.max_step(x, dx, tb.StepContext())
        with monkeypatch.context() as m:
            m.setattr(sc_module, "_native_ok", lambda t: False)
            sc._cache = None
            eager = sc.max_step(x, dx, tb.StepContext())
            sc._cache = None
        assert math.isclose(alpha, eager, rel_tol=1e-9), (move, alpha, eager)
        if bound is not None:
            assert alpha == bound, (move, alpha)
            continue
        down, length = -move[2], math.hypot(*move)
        assert 0.9 * 1.5e-3 / length * 0.99 < alpha < 1.5e-3 / down, (move, alpha)  # short of the gap
        for t in torch.linspace(0, 1, 41, dtype=F64).tolist():
            y = x + t * alpha * dx
            assert not intersects(y, topo.faces, topo.edges), (move, t)
            assert sc.min_distance(y, radius=0.05)[0] > 0


def test_the_compiled_step_bound_is_the_same_for_any_number_of_threads():
    """The advancement's pruning (a pair past the smallest time found stops) changes no result: the bound of a
    step with thousands of binding pairs, split over threads in chunks, is the one-thread bound bit for bit, and the
    eager bound's to rounding (its own distance formulas); the step so bounded keeps the sheets apart."""
    import torchbend.sim.self_contact as sc_module

    model, x, sc, V = two_sheets(n=40, gap=1e-3, size=0.4)
    dx = torch.zeros_like(x)
    dx[V:] = torch.tensor([0.004, 0.001, -0.002], dtype=F64)
    threads = torch.get_num_threads()
    try:
        got = []
        for n in (1, 2):
            torch.set_num_threads(n)
            sc._cache = None
            got.append(sc.max_step(x, dx, tb.StepContext()))
    finally:
        torch.set_num_threads(threads)
    sc_module_native = sc_module._native_ok
    try:
        sc_module._native_ok = lambda t: False
        sc._cache = None
        eager = sc.max_step(x, dx, tb.StepContext())
    finally:
        sc_module._native_ok = sc_module_native
        sc._cache = None
    assert 0.9 * 1e-3 / float(dx[V].norm()) * 1.5 < got[0] < 1 and got[0] == got[1], got  # advanced past the first
    assert math.isclose(eager, got[0], rel_tol=1e-9), (eager, got)
    for t in torch.linspace(0, 1, 21, dtype=F64).tolist():  # the sheets stay apart along the advanced step
        assert sc.min_distance(x + t * got[0] * dx, radius=0.05)[0] > 0, t


@pytest.mark.parametrize("X, P", [
    # nearly parallel edges 2e-16 m apart at coordinates of 3 cm, the second moved 2e-14 m across the first
    ([[0.02338570666176268, 0.008385059611010019, 0.02120023479170193],
      [0.03048984796209446, 0.012615512913314138, 0.017425447791589478],
      [0.02412068760757331, 0.008822734262721812, 0.020809702508870258],
      [0.03145567738251818, 0.013190389564934919, 0.016911783065171777]],
     [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-1.02636289556308e-15, 1.527106114719012e-14, 1.503239340645579e-14],
      [-1.1051060456157354e-15, 1.4781426330910896e-14, 1.5129365854162607e-14]]),
    # edges 6e-14 m apart at coordinates of 0.6 m
    ([[-0.0, 0.0, 0.0], [0.41878867013338167, -0.4828405262401639, -0.6212719395536138],
      [0.15922388541909968, -0.18357646734166794, -0.23620823382375658],
      [0.4164167260631716, -0.480102516452131, -0.6177749313479634]],
     [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [3.9292859398178834e-14, 4.933934183361044e-14, -1.1858944486493643e-14],
      [3.9292859398178834e-14, 4.933934183361044e-14, -1.1858944486493643e-14]]),
])
def test_pairs_at_round_off_distances_keep_the_single_bound(X, P, monkeypatch):
    """Edge pairs whose distance is at the round-off of their coordinates (found by a review: advancing from the
    distances measured there let the edges pass through each other within the step) take their first advance alone,
    in both paths: the single bound, along which their distance stays positive (dense samples, float64)."""
    import torchbend.sim.self_contact as sc_module
    from torchbend.backends import native

    x, p = torch.tensor(X, dtype=F64), torch.tensor(P, dtype=F64)
    st = torch.arange(4).reshape(1, 4)
    single = native.contact_step_bound(x, st, True, p, 0.0)
    for dhat in (1e-12, 1.0):
        assert native.contact_step_bound(x, st, True, p, dhat) == single
        assert sc_module._advance(x[None], p[None], True, 1.0, dhat) == single
    ts = torch.linspace(0, 1, 4001, dtype=F64) * single
    d = sc_module._stencil_distances(x[None] + ts[:, None, None] * p[None], True)
    assert bool((d > 0).all())


def test_float32_nearly_parallel_edges_are_measured_in_double(monkeypatch):
    """float32 edges nearly parallel and 1.7e-6 m apart (a review's case: float32's distance formulas misjudged their
    distance along the step 10-100x, and the advancement passed through the contact): the bound measures in double,
    the compiled and eager bounds agree, and the distance stays positive along the step (dense samples, double)."""
    import torchbend.sim.self_contact as sc_module
    from torchbend.backends import native

    X = [[0.01834526626865322, 0.224926042185734, -0.11228963835306631],
         [0.07683598197532246, 0.09075805523316596, -0.1750425723711258],
         [0.0145516408782719, 0.2336200269407327, -0.10822406828078449],
         [0.09177691877272913, 0.0564827709287834, -0.19107332372518987]]
    P = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [7.350025682663287e-06, -2.101246479293927e-05, -6.009825022357546e-06],
         [1.4462226095318342e-05, -1.640786760081581e-05, -1.0436970941124403e-05]]
    x, p = torch.tensor(X, dtype=torch.float32), torch.tensor(P, dtype=torch.float32)
    st = torch.arange(4).reshape(1, 4)
    bound = native.contact_step_bound(x, st, True, p, 1e-3)
    monkeypatch.setattr(sc_module, "_native_ok", lambda t: False)
    assert sc_module._advance(x[None], p[None], True, 1.0, 1e-3) == bound
    ts = torch.linspace(0, 1, 20001, dtype=F64) * bound
    d = sc_module._stencil_distances(x.double()[None] + ts[:, None, None] * p.double()[None], True)
    assert bool((d > 0).all())


def test_a_float32_pair_sliding_in_contact_advances_past_its_first_advance(monkeypatch):
    """A float32 point 3e-5 m above a triangle at 0.2 m coordinates slides 1 cm along it (a cloth sliding onto a body
    at speed): the bound advances along the slide (its distances measured in double, the end's rounding to float32 a
    small part of its floor), in both paths, 64 advances at most, where the float32 epsilon's 1024-fold kept it at its
    first advance, 0.9 d / rate = 0.0027 (a float32 cloth sliding onto a sphere mesh at 8 m/s took such steps for 60 iterations);
    the path and the float32 end stay apart from the triangle."""
    import torchbend.sim.self_contact as sc_module
    from torchbend.backends import native

    X = [[0.2, 0.15, 3e-5], [0.15, 0.1, 0.0], [0.26, 0.11, 0.0], [0.2, 0.22, 0.0]]  # the point, then the triangle
    P = [[0.01, 0.002, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    x, p = torch.tensor(X, dtype=torch.float32), torch.tensor(P, dtype=torch.float32)
    st = torch.arange(4).reshape(1, 4)
    first = 0.9 * float(x[0, 2]) / float(p[0].norm())
    bound = native.contact_step_bound(x, st, False, p, 1e-3)
    assert bound > 50 * first  # (64 advances at most)
    monkeypatch.setattr(sc_module, "_native_ok", lambda t: False)
    assert sc_module._advance(x[None], p[None], False, 1.0, 1e-3) == bound
    ts = torch.linspace(0, 1, 4001, dtype=F64) * bound
    d = sc_module._stencil_distances(x.double()[None] + ts[:, None, None] * p.double()[None], False)
    end = (x + bound * p).double()  # rounded to float32
    assert bool((d > 0).all()) and float(sc_module._stencil_distances(end[None], False)[0]) > 0


def test_a_float32_pair_nearer_than_ten_resolvable_floors_advances_down_to_the_floor(monkeypatch):
    """A float32 point 6e-5 m above a triangle at 1.5 m coordinates slides 1 cm along it and closes 2e-5 m: a tenth of
    its distance (6e-6 m) is under the floor float32 resolves there (64 epsilons of the scale, 1.2e-5 m), where the
    pair kept its first advance alone, 0.9 d / rate = 0.0053 (a float32 3 m cloth falling at 8 m/s onto a 1 m sphere
    mesh took such steps for 300 iterations); it now advances while its distance stays above that floor, in both
    paths, and the path and the float32 end stay apart from the triangle."""
    import torchbend.sim.self_contact as sc_module
    from torchbend.backends import native

    X = [[1.5, 1.45, 6e-5], [1.45, 1.4, 0.0], [1.51, 1.41, 0.0], [1.5, 1.52, 0.0]]  # the point, then the triangle
    P = [[0.01, 0.002, -2e-5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    x, p = torch.tensor(X, dtype=torch.float32), torch.tensor(P, dtype=torch.float32)
    st = torch.arange(4).reshape(1, 4)
    first = native.contact_step_bound(x, st, False, p, 0.0)  # dhat 0: the first advance alone
    assert math.isclose(first, 0.9 * float(x[0, 2]) / float(p[0].norm()), rel_tol=1e-5)
    bound = native.contact_step_bound(x, st, False, p, 1e-3)
    assert bound > 30 * first  # (64 advances at most)
    monkeypatch.setattr(sc_module, "_native_ok", lambda t: False)
    assert math.isclose(sc_module._advance(x[None], p[None], False, 1.0, 1e-3), bound, rel_tol=1e-12)
    ts = torch.linspace(0, 1, 4001, dtype=F64) * bound
    d = sc_module._stencil_distances(x.double()[None] + ts[:, None, None] * p.double()[None], False)
    end = (x + bound * p).double()  # rounded to float32
    assert float(d.min()) > 1e-6 and float(sc_module._stencil_distances(end[None], False)[0]) > 1e-6


def tight_fold(nx: int, ny: int, dhat: float, L: float = 0.2, W: float = 0.1):
    """``(flat, folded, faces)``: an L x W strip and the same strip folded in half onto itself, its layers 1.05 dhat
    apart (the fold in one hinge at about 3.1 rad), 1.2 mm above the plane z = 0."""
    gap = 1.05 * dhat
    flat, faces = tb.scenes.grid(nx, ny, (L, W), dtype=F64)
    r = gap / 2
    a = L / 2 - math.pi * r / 2
    s = flat[:, 0]
    x = flat.clone()
    th = ((s - a) / r).clamp(0, math.pi)
    arc = (s >= a) & (s <= a + math.pi * r)
    x[:, 0] = torch.where(s < a, s, torch.where(arc, a + r * torch.sin(th), a - (s - a - math.pi * r)))
    x[:, 2] = torch.where(s < a, torch.zeros_like(s), torch.where(arc, r - r * torch.cos(th), torch.full_like(s, 2 * r)))
    x[:, 2] += 1.2e-3
    return flat, x, faces


@pytest.mark.parametrize("nx, ny, dhat", [(9, 5, 1e-3), (17, 9, 5e-4)])
def test_a_strip_folded_tightly_onto_itself_converges_in_every_step(nx, ny, dhat):
    """A 20 x 10 cm strip folded onto itself with its layers 1.05 dhat apart (the fold in one hinge at 3.1 rad, the
    tan model's forces ~1e3 N push it open) falling onto a plane: every time step converges, with no intersection
    (exact test).  With a single-advance step bound each Newton step was cut to 1e-4..1e-2 of the direction and no
    step of the 9 x 5 strip (dhat 1 mm) converged in 120 iterations; with kappa adapted only at a step's start, no
    step of the 17 x 9 strip with dhat 0.5 mm converged (its layers pressed to 1e-7 m): its kappa now doubles
    within the solve while a contact closes below a tenth of dhat."""
    flat, x, faces = tight_fold(nx, ny, dhat)
    sc = tb.SelfContact(dhat=dhat, friction=0.3)
    model = tb.ClothModel(faces, flat, density=0.2, terms=[sc], colliders=[tb.Plane(friction=0.3)],
                          membrane=tb.MembraneEnergy(faces, flat, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(faces, flat, stiffness=1e-5))
    topo = model.topology
    assert float(tb.hinge_angles(x, topo).abs().max()) > 3.0 and not intersects(x, topo.faces, topo.edges)
    state = tb.ClothState(x, torch.zeros_like(x))
    for i in range(6):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, (i, info.message)
        assert info.min_distance > 0 and not intersects(state.x, topo.faces, topo.edges), i
    assert sc._kappa0 is not None and sc.stiffness is not None and sc.stiffness <= sc.KAPPA_GROWTH * sc._kappa0


def test_a_float32_strip_folded_tightly_at_rest_converges_at_its_round_off_floor():
    """The tight fold in float32 with the fold as its rest shape (the crease's rest angle near pi, where the tan
    model's bending block reaches 2e5 N/m against 1e-2 N of forces): the forces' round-off floor is 2-4% of the
    force scale, and the stop at that floor required at most eps^(1/4) = 1.9% of it: from the third step on every
    step ran to max_iters at the floor (329 iterations in 7 solves, 10 s).  Now each step converges at its floor in a
    few iterations, the state apart (exact test in float64)."""
    _, x, faces = tight_fold(17, 9, 1e-3)
    x = x.float()
    model = tb.ClothModel(faces, x, density=0.2, terms=[tb.SelfContact(dhat=1e-3, friction=0.3)],
                          colliders=[tb.Plane(friction=0.3)],
                          membrane=tb.MembraneEnergy(faces, x, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(faces, x, stiffness=1e-5))
    topo = model.topology
    state = tb.ClothState(x, torch.zeros_like(x))
    for i in range(4):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged and info.iterations <= 60, (i, info.message)
        assert info.min_distance > 0 and not intersects(state.x, topo.faces, topo.edges), i


def test_a_long_step_searches_its_swept_boxes_and_a_short_one_afterwards_searches_afresh():
    """The step bound's pairs come from the boxes swept along the step: a sheet moved 5 cm down onto another 1.5 mm
    below has about its neighbours' candidates (not every pair within 10 cm), the bound stops it short of the lower
    sheet, and a short step afterwards does not keep the long step's candidates."""
    from torchbend.sim.self_contact import candidate_pairs

    model, x, sc, V = two_sheets(n=12, gap=1.5e-3)
    topo = model.topology
    dx = torch.zeros_like(x)
    dx[V:, 2] = -0.05
    alpha = sc.max_step(x, dx, tb.StepContext())
    assert sc._cache is not None
    swept = sum(int(t.shape[0]) for t in sc._cache[4:6])
    everything = sum(int(t.shape[0]) for t in candidate_pairs(x, topo.faces, topo.edges, 0.1 + sc.dhat)[:2])
    assert swept < everything / 10, (swept, everything)
    assert 0 < alpha < 1.5e-3 / 0.05  # 0.9 of the time to cover the gap
    for t in torch.linspace(0, 1, 21, dtype=F64).tolist():
        assert not intersects(x + t * alpha * dx, topo.faces, topo.edges)
    y = x + alpha * dx
    short = 1e-2 * dx
    sc.max_step(y, short, tb.StepContext())
    fresh = sum(int(t.shape[0]) for t in candidate_pairs(y, topo.faces, topo.edges, sc.dhat, short, 0.05 * sc.dhat)[:2])
    assert sc._cache is not None and sum(int(t.shape[0]) for t in sc._cache[4:6]) == fresh


def test_a_sheet_falls_onto_another_and_rests_apart_in_every_step():
    model, x, sc, V = two_sheets(gap=6e-3)
    topo = model.topology
    state = tb.ClothState(x.clone(), torch.zeros_like(x))
    gaps = []
    for _ in range(8):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, info.message
        d, _ = sc.min_distance(state.x, radius=0.05)
        assert d > 0 and not intersects(state.x, topo.faces, topo.edges)
        gaps.append(d)
    assert gaps[-1] < 2e-3  # it came within dhat: the barrier holds it


def test_self_contact_names_what_is_wrong():
    with pytest.raises(ValueError, match="SelfContact: dhat"):
        tb.SelfContact(dhat=0.0)
    with pytest.raises(ValueError, match="SelfContact: friction must be >= 0"):
        tb.SelfContact(friction=-0.3)
    with pytest.raises(ValueError, match="has no mesh"):
        tb.SelfContact().energy(torch.zeros(3, 3, dtype=F64), tb.StepContext())
    model, x, sc, V = two_sheets(gap=0.0)  # the sheets touch
    with pytest.raises(ValueError, match="x0: self_contact: two non-adjacent primitives of the cloth touch"):
        tb.solve_static(model, x)


def test_a_contact_term_belongs_to_one_mesh():
    """A SelfContact (or MeshCollider) given to a model of another mesh is refused (before, the second model took the
    term's mesh over and the first model's solves reported false contacts); a model of the same mesh may share it."""
    model, x, sc, V = two_sheets(gap=5e-4)
    before = sc.min_distance(x)
    small, f = tb.scenes.grid(3, 3, (0.05, 0.05), dtype=F64)
    with pytest.raises(ValueError, match=r"SelfContact 'self_contact' is already part of a model of another mesh "
                                         r"\(\d+ vertices, \d+ faces; this one has 9 and 8\)"):
        tb.ClothModel(f, small, terms=[sc], density=0.2)
    again = tb.ClothModel(model.topology.faces, x, terms=[sc], density=0.2, pinned=torch.arange(V))
    assert sc in again.extra_terms and sc.min_distance(x) == before  # still the two sheets' mesh
    floor = torch.tensor([[-1.0, -1.0, -0.01], [1.0, -1.0, -0.01], [1.0, 1.0, -0.01], [-1.0, 1.0, -0.01]], dtype=F64)
    body = tb.MeshCollider(floor, torch.tensor([[0, 1, 2], [0, 2, 3]]), dhat=1e-3)
    tb.ClothModel(f, small, colliders=[body], density=0.2)
    with pytest.raises(ValueError, match="MeshCollider 'mesh_collider' is already part of a model of another mesh"):
        tb.ClothModel(model.topology.faces, x, colliders=[body], density=0.2)


@pytest.mark.parametrize("kind", range(16))
def test_pair_hessians_of_every_type_are_those_of_torch_func(kind):
    from torchbend.ops.distance import EE_A0B0
    sc = tb.SelfContact(dhat=1.0, stiffness=2.0)
    X = 0.2 * torch.randn(6, 12, generator=torch.Generator().manual_seed(kind), dtype=F64)
    eps = torch.full((6,), 1e-3, dtype=F64) if kind >= EE_A0B0 else None

    def f(z, e):
        return sc._pair_energy(z.reshape(1, 4, 3), kind, e).sum()

    ref = torch.stack([torch.func.hessian(f)(X[i], None if eps is None else eps[i:i + 1]) for i in range(6)])
    torch.testing.assert_close(sc._pair_hessians(X, kind, eps), ref, rtol=1e-12, atol=1e-12 * float(ref.abs().max()))


@pytest.mark.parametrize("n,m,pad", [(1, 1, 0.0), (50, 80, 0.01), (600, 700, 0.002), (300, 200, 0.2)])
def test_broad_phase_finds_exactly_the_overlapping_padded_boxes(n, m, pad):
    from torchbend.sim.self_contact import _box_pairs
    g = torch.Generator().manual_seed(n)
    la = torch.rand(n, 3, generator=g, dtype=F64)
    ha = la + 0.05 * torch.rand(n, 3, generator=g, dtype=F64)
    lb = torch.rand(m, 3, generator=g, dtype=F64) - 0.3
    hb = lb + 0.3 * torch.rand(m, 3, generator=g, dtype=F64) ** 4  # a few long boxes
    got = _box_pairs(la, ha, lb, hb, pad)
    brute = ((la[:, None] <= hb[None] + 2 * pad) & (ha[:, None] + 2 * pad >= lb[None])).all(-1).nonzero()
    assert sorted(map(tuple, got.tolist())) == sorted(map(tuple, brute.tolist()))


def test_config_self_contact_section_builds_the_term():
    from torchbend.scenes.builders import build_model
    model = build_model({"mesh": {"type": "grid", "nx": 4, "ny": 4}, "membrane": {"model": "stvk"},
                         "self_contact": {"dhat": 1.5e-3, "stiffness": 7.0, "friction": 0.3, "eps_v": 2e-3}})
    (sc,) = [t for t in model.terms if isinstance(t, tb.SelfContact)]
    assert sc.dhat == 1.5e-3 and sc.stiffness == 7.0 and sc.faces is not None
    assert sc.friction == 0.3 and sc.eps_v == 2e-3
    auto = build_model({"mesh": {"type": "grid", "nx": 4, "ny": 4}, "self_contact": {}})
    (sc,) = [t for t in auto.terms if isinstance(t, tb.SelfContact)]
    w = 9.81 * float(auto.mass.mean())
    assert sc.stiffness is not None and math.isclose(sc.stiffness, 10 * w / (4.33 * 1e-3 ** 3), rel_tol=1e-12)
    with pytest.raises(ValueError, match="self_contact.dhat"):
        build_model({"self_contact": {"dhat": -1.0}})
    with pytest.raises(ValueError, match="self_contact.friction"):
        build_model({"self_contact": {"friction": -0.5}})


def test_solve_info_reports_the_smallest_distance_and_the_contacts():
    model, x, sc, V = two_sheets(gap=6e-3)
    state = tb.ClothState(x.clone(), torch.zeros_like(x))
    for _ in range(6):
        state, info = tb.implicit_euler_step(model, state, 0.01)
    d, n = sc.min_distance(state.x)
    assert info.contact_count == n > 0 and info.min_distance == d and 0 < d < 2e-3
    rest, faces = tb.scenes.grid(3, 3, (0.1, 0.1), dtype=F64)
    free = tb.ClothModel(faces, rest, membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                         colliders=[tb.Plane(point=(0.0, 0.0, -1.0))], pinned=[0, 2])
    y, info = tb.solve_static(free, rest)
    assert info.contact_count == 0 and math.isclose(info.min_distance, float(y[:, 2].min()) + 1.0, rel_tol=1e-12)


def test_a_strip_folded_onto_itself_never_passes_through_itself():
    """A strip on an ipc table, one short edge held, the other carried over it on an arc and laid above it:
    the upper half settles onto the lower one; every step converges with no intersection (exact test)."""
    rest, faces = tb.scenes.grid(9, 3, (0.2, 0.05), dtype=F64)
    rest = rest + torch.tensor([0.0, 0.0, 1e-3], dtype=F64)
    left = (rest[:, 0] < 1e-9).nonzero()[:, 0]
    right = (rest[:, 0] > 0.2 - 1e-9).nonzero()[:, 0]
    pinned = torch.zeros(rest.shape[0], dtype=torch.bool)
    pinned[left] = pinned[right] = True
    sc = tb.SelfContact(dhat=2e-3)
    table = tb.Plane(point=(0.0, 0.0, 0.0), law="ipc", stiffness=1.0, margin=2e-3)
    model = tb.ClothModel(faces, rest, bending=tb.BendingEnergy(faces, rest, stiffness=1e-6),
                          membrane=tb.MembraneEnergy(faces, rest, young=2e5, poisson=0.3, thickness=5e-4),
                          colliders=[table], terms=[sc], density=0.2, pinned=pinned)
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    touched = 0
    for i in range(44):
        s = min(1.0, (i + 1) / 32)
        ang = math.pi * s
        x = state.x.clone()
        x[right, 0] = 0.11 + 0.09 * math.cos(ang)
        x[right, 2] = 1e-3 + 6e-3 * s + 0.09 * math.sin(ang) * (1 - s)
        state, info = tb.implicit_euler_step(model, tb.ClothState(x, state.v), 0.01)
        assert info.converged, (i, info.message)
        assert not intersects(state.x, model.topology.faces, model.topology.edges), i
        d, n = sc.min_distance(state.x)
        assert d > 0 and info.min_distance > 0
        touched += int(n > 0)
    assert touched >= 5  # the upper half rested on the lower one


def test_self_contact_energy_gradient_and_hessian_match_ipctk_on_a_folded_grid():
    ipctk = pytest.importorskip("ipctk")
    n, size, dhat = 12, 0.2, 2e-3
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=F64)
    h = size / (n - 1)
    x = torch.cat([rest, rest + torch.tensor([h / 3, h / 5, 1e-3], dtype=F64)])
    f = torch.cat([faces, faces + rest.shape[0]])
    sc = tb.SelfContact(dhat=dhat, stiffness=3.0)
    tb.ClothModel(f, x, terms=[sc])
    V, F = x.numpy(), f.numpy().astype(np.int32)
    mesh = ipctk.CollisionMesh(V, ipctk.edges(F), F)
    coll = ipctk.NormalCollisions()
    coll.build(mesh, V, dhat)
    assert len(coll) > 100
    B = ipctk.BarrierPotential(dhat, 3.0)
    ctx = tb.StepContext()
    e = float(sc.energy(x, ctx))
    assert math.isclose(e, B(coll, mesh, V), rel_tol=1e-10)
    g = sc.gradient(x, ctx).reshape(-1).numpy()
    g_ref = B.gradient(coll, mesh, V)
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-10 * np.abs(g_ref).max())
    H = sc.hessian(x, ctx).to_dense().numpy()
    H_ref = B.hessian(coll, mesh, V, ipctk.PSDProjectionMethod.NONE).toarray()
    np.testing.assert_allclose(H, H_ref, rtol=0, atol=1e-9 * np.abs(H_ref).max())


@pytest.mark.parametrize("where", ["vertex", "edge", "diagonal", "inside"])
def test_a_contact_found_by_several_triangles_counts_for_each_as_in_ipctk(where):
    """A sheet above a grid, one of its vertices exactly above a grid vertex, an edge or a diagonal (found there by
    several triangles, as by symmetry in a pile of grids twisted by 45 degrees): the energy, gradient and Hessian are
    ipctk's (whose collision sets weigh such a contact by the number of pairs that find it; counting it once made
    the energy jump by whole barrier values where the point crossed above the edge), and the energy is continuous
    there: moved by 1e-12 m across, it changes by no more than its gradient predicts."""
    ipctk = pytest.importorskip("ipctk")
    rest, faces = tb.scenes.grid(5, 5, (0.04, 0.04), dtype=F64)
    h = 0.01
    offset = {"vertex": (0.0, 0.0), "edge": (0.0, h / 2), "diagonal": (h / 2, h / 2), "inside": (0.31 * h, 0.57 * h)}
    top, top_faces = tb.scenes.grid(3, 3, (0.005, 0.005), dtype=F64)  # its vertex 4 above the grid's vertex 12
    top = top - top[4] + rest[12] + torch.tensor([*offset[where], 4e-4], dtype=F64)
    x = torch.cat([rest, top])
    f = torch.cat([faces, top_faces + rest.shape[0]])
    sc = tb.SelfContact(dhat=1e-3, stiffness=1e6)
    tb.ClothModel(f, x, terms=[sc])
    V, F = x.numpy(), f.numpy().astype(np.int32)
    mesh = ipctk.CollisionMesh(V, ipctk.edges(F), F)
    coll = ipctk.NormalCollisions()
    coll.build(mesh, V, 1e-3)
    B = ipctk.BarrierPotential(1e-3, 1e6)
    ctx = tb.StepContext()
    e = float(sc.energy(x, ctx))
    assert e > 0 and math.isclose(e, B(coll, mesh, V), rel_tol=1e-10)
    g = sc.gradient(x, ctx)
    g_ref = B.gradient(coll, mesh, V)
    np.testing.assert_allclose(g.reshape(-1).numpy(), g_ref, rtol=0, atol=1e-10 * np.abs(g_ref).max())
    if where in ("edge", "inside"):  # above a corner or a diagonal the distance types tie: the energy is C1, not C2,
        H = sc.hessian(x, ctx).to_dense().numpy()  # and each code's Hessian is that of the type its tie-break gives
        H_ref = B.hessian(coll, mesh, V, ipctk.PSDProjectionMethod.NONE).toarray()
        np.testing.assert_allclose(H, H_ref, rtol=0, atol=1e-9 * np.abs(H_ref).max())
    centre = rest.shape[0] + 4
    for direction in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, -1.0, 0.0]):
        d = torch.zeros_like(x)
        d[centre] = torch.tensor(direction, dtype=F64) * 1e-12
        change = float(sc.energy(x + d, ctx)) - e
        assert abs(change) <= 10 * abs(float((g * d).sum())) + 1e-9 * e, (direction, change)


def box(lo, hi):
    """A closed box mesh: 8 corners, 12 triangles."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = torch.tensor([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], dtype=F64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = torch.tensor([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=torch.int64)
    return v, f


def cloth_over_box(gap: float):
    rest, faces = tb.scenes.grid(5, 5, (0.1, 0.1), dtype=F64)
    rest = rest + torch.tensor([0.03, 0.041, gap], dtype=F64)
    bv, bf = box((0.0, 0.0, -0.1), (0.2, 0.2, 0.0))
    body = tb.MeshCollider(bv, bf, dhat=2e-3)
    model = tb.ClothModel(faces, rest, membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(faces, rest, stiffness=1e-5), colliders=[body], density=0.2)
    return model, rest, body, bv, bf


def test_a_free_cloth_solves_statically_on_a_body_mesh_as_on_a_plane():
    """No pinned vertex: a body mesh holds the cloth as a plane collider does (the static solve is not refused as
    unbounded below), and both solves end at the same rest state, within dhat above the body and never on it."""
    rest, faces = tb.scenes.grid(6, 6, (0.1, 0.1), dtype=F64)
    rest = rest + torch.tensor([-0.05, -0.05, 5e-4], dtype=F64)
    floor = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]], dtype=F64)
    out = {}
    for name, collider in (("mesh", tb.MeshCollider(floor, torch.tensor([[0, 1, 2], [0, 2, 3]]), dhat=1e-3)),
                           ("plane", tb.Plane())):
        model = tb.ClothModel(faces, rest, colliders=[collider], density=0.2,
                              membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                              bending=tb.BendingEnergy(faces, rest, stiffness=1e-5))
        x, info = tb.solve_static(model, rest)
        assert info.converged and info.stop_reason != "rigid_body_modes", info.message
        assert 0 < float(x[:, 2].min()) and float(x[:, 2].max()) < 1e-3
        out[name] = (x, info)
    x, info = out["mesh"]
    assert info.contact_count > 0 and 0 < info.min_distance < 1e-3
    # the same flat rest state up to the free slide in the plane (no friction in a static solve): the sheet keeps
    # its shape on both
    for y, _ in out.values():
        torch.testing.assert_close(torch.cdist(y, y), torch.cdist(rest, rest), rtol=0, atol=1e-6)


def test_mesh_collider_matches_ipctk_on_the_cloth_and_body_mesh():
    ipctk = pytest.importorskip("ipctk")
    model, rest, body, bv, bf = cloth_over_box(1e-3)
    x = rest.clone()
    x[:, 2] += 2e-4 * torch.sin(40 * x[:, 0])  # not flat: several distance types
    V = x.shape[0]
    allv = torch.cat([x, bv]).numpy()
    allf = torch.cat([model.topology.faces, bf + V]).numpy().astype(np.int32)
    mesh = ipctk.CollisionMesh(allv, ipctk.edges(allf), allf)
    coll = ipctk.NormalCollisions()
    coll.build(mesh, allv, 2e-3)
    assert len(coll) > 10
    assert body.stiffness is not None
    B = ipctk.BarrierPotential(2e-3, body.stiffness)
    ctx = tb.StepContext()
    assert math.isclose(float(body.energy(x, ctx)), B(coll, mesh, allv), rel_tol=1e-10)
    g_ref = B.gradient(coll, mesh, allv).reshape(-1, 3)[:V]
    np.testing.assert_allclose(body.gradient(x, ctx).numpy(), g_ref, rtol=0, atol=1e-10 * np.abs(g_ref).max())
    H_ref = B.hessian(coll, mesh, allv, ipctk.PSDProjectionMethod.NONE).toarray()[: 3 * V, : 3 * V]
    np.testing.assert_allclose(body.hessian(x, ctx).to_dense().numpy(), H_ref, rtol=0, atol=1e-9 * np.abs(H_ref).max())


@pytest.mark.parametrize("gap", [5e-4, 3e-3, 2e-2])
def test_min_distance_is_the_smallest_distance_also_beyond_dhat(gap):
    """SolveInfo's min_distance of self-contact: ipctk's minimum distance over every pair of non-adjacent
    primitives, whether the closest pair is within dhat (two sheets 0.5 mm apart), a few dhat away (3 mm) or
    only inside a sheet (layers 2 cm apart: the grid's own non-adjacent primitives, 14 mm); inf where nothing is
    within 64 dhat (two triangles 1 m apart); the solver's kept candidates are left as they were."""
    ipctk = pytest.importorskip("ipctk")
    rest, faces = tb.scenes.grid(6, 6, (0.1, 0.1), dtype=F64)
    gen = torch.Generator().manual_seed(0)
    upper = rest + torch.tensor([0.007, 0.003, gap], dtype=F64) + 1e-4 * torch.randn(rest.shape, generator=gen,
                                                                                      dtype=F64)
    x, f = torch.cat([rest, upper]), torch.cat([faces, faces + rest.shape[0]])
    sc = tb.SelfContact(dhat=1e-3, stiffness=1.0)
    tb.ClothModel(f, x, terms=[sc])
    sc.energy(x, tb.StepContext())
    kept = sc._cache
    d, count = sc.contact_stats(x)
    assert sc._cache is kept
    V, F = x.numpy(), f.numpy().astype(np.int32)
    mesh = ipctk.CollisionMesh(V, ipctk.edges(F), F)
    coll = ipctk.NormalCollisions()
    coll.build(mesh, V, 1.0)  # every pair within 1 m: all of them
    assert math.isclose(d, coll.compute_minimum_distance(mesh, V) ** 0.5, rel_tol=1e-12)
    assert (count > 0) == (d < sc.dhat)
    tri = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]], dtype=F64)
    far = tb.SelfContact(dhat=1e-3, stiffness=1.0)
    two = torch.cat([tri, tri + torch.tensor([0.0, 0.0, 1.0], dtype=F64)])
    tb.ClothModel(torch.tensor([[0, 1, 2], [3, 4, 5]]), two, terms=[far])
    assert far.contact_stats(two) == (math.inf, 0)


@pytest.mark.parametrize("offset, dtype, refused", [(1000.0, torch.float32, True), (10.0, torch.float32, False),
                                                     (1000.0, F64, False)])
def test_a_dhat_below_what_the_dtype_resolves_at_the_coordinates_is_refused(offset, dtype, refused):
    """Float32 at 1 km resolves 6e-5 m: a barrier of dhat = 1 mm spans 16 epsilons there, below what the step bound
    and the rounding of a step's end need (RESOLUTION = 64 epsilons), and a float32 pile of three sheets dropped onto
    a mesh floor 1 km from the origin ended its second step intersecting.  Such a start is refused, by the cloth's
    term and by a body's, naming dhat, the dtype and the floor; at 10 m, or in float64 at 1 km, the step runs."""
    rest, faces = tb.scenes.grid(5, 5, (0.1, 0.1), dtype=F64)
    o = torch.tensor([offset, offset, offset], dtype=F64)
    x = torch.cat([rest, rest + torch.tensor([0.0, 0.0, 3e-3], dtype=F64)]) + o
    f = torch.cat([faces, faces + 25])
    fv, ff = tb.scenes.grid(2, 2, (0.3, 0.3), dtype=F64)
    fv = fv + o - torch.tensor([0.1, 0.1, 2e-3], dtype=F64)
    for with_body in (False, True):
        terms = [tb.SelfContact(dhat=1e-3)] + ([tb.MeshCollider(fv.to(dtype), ff, dhat=1e-3)] if with_body else [])
        model = tb.ClothModel(f, x.to(dtype), density=0.2, terms=terms,
                              membrane=tb.MembraneEnergy(f, x.to(dtype), young=1e5, poisson=0.3, thickness=5e-4))
        state = tb.ClothState(x.to(dtype), torch.zeros_like(x.to(dtype)))
        if refused:
            with pytest.raises(ValueError, match=r"dhat = 0\.001 m is below what float32 resolves at these "
                                                 r"coordinates \(64 epsilons of the largest coordinate"):
                tb.implicit_euler_step(model, state, 0.01)
        else:
            state, info = tb.implicit_euler_step(model, state, 0.01)
            assert info.converged and info.min_distance > 0, info.message


def test_a_start_that_passes_through_itself_or_a_body_is_refused():
    """Every distance between primitives is positive where a cloth edge pierces a triangle: the start is refused
    all the same (naming the edge and the triangle), by a step and by a static solve, for two sheets that cross
    and for a cloth cut by a body mesh; the crossing test agrees with the brute-force one, and resting contact
    states are not crossings."""
    a, fa = tb.scenes.grid(4, 4, (0.1, 0.1), dtype=F64)
    b = a.clone()
    b[:, 2] = 0.02 * (b[:, 0] - 0.05)  # tilted through the flat sheet: no vertex of one on the other
    x0, f = torch.cat([a + torch.tensor([0.0131, 0.0071, 0.0], dtype=F64), b]), torch.cat([fa, fa + 16])
    sc = tb.SelfContact(dhat=1e-3)
    model = tb.ClothModel(f, x0, membrane=tb.MembraneEnergy(f, x0, young=1e5, poisson=0.3, thickness=5e-4),
                          terms=[sc], density=0.2, pinned=list(range(16)))
    topo = model.topology
    assert intersects(x0, topo.faces, topo.edges) and sc.min_distance(x0, radius=0.1)[0] > 0
    cross = sc.crossing(x0)
    assert cross is not None
    edge, tri = cross
    assert not set(edge) & set(tri)
    with pytest.raises(ValueError, match=r"self_contact: the cloth passes through itself: edge \(\d+, \d+\) crosses "
                                         r"triangle \(\d+, \d+, \d+\)"):
        tb.implicit_euler_step(model, tb.ClothState(x0.clone(), torch.zeros_like(x0)), 0.01)
    with pytest.raises(ValueError, match="passes through itself"):
        tb.solve_static(model, x0)
    apart = x0.clone()
    apart[16:, 2] += 0.0015  # the tilted sheet lifted clear of the flat one (1 mm at its lowest edge): no crossing
    assert not intersects(apart, topo.faces, topo.edges) and sc.crossing(apart) is None

    rest, faces = tb.scenes.grid(7, 7, (0.3, 0.3), dtype=F64)
    rest = rest + torch.tensor([-0.037, 0.043, 0.0], dtype=F64)  # overhangs the box on both sides
    bv, bf = box((0.0, 0.0, -0.1), (0.2, 0.2, 0.005))  # the box's top 5 mm above the cloth: it cuts the cloth
    body = tb.MeshCollider(bv, bf, dhat=1e-3)
    model = tb.ClothModel(faces, rest, membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                          colliders=[body], density=0.2)
    V = rest.shape[0]
    allf = torch.cat([model.topology.faces, bf + V])
    alle = torch.cat([allf[:, [0, 1]], allf[:, [1, 2]], allf[:, [2, 0]]]).sort(1).values.unique(dim=0)
    assert intersects(torch.cat([rest, bv]), allf, alle, cloth=V) and body.min_distance(rest)[0] > 0
    with pytest.raises(ValueError, match=r"mesh_collider: the cloth and the body mesh intersect: (cloth|body) edge"):
        tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
    body.vertices = bv - torch.tensor([0.0, 0.0, 0.0055], dtype=F64)  # moved below the cloth: a valid start again
    state, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
    assert info.converged and body.crossing(state.x) is None


def test_float32_flat_sheet_is_typed_as_in_float64():
    """Parallel edges of a flat float32 grid: typed in float64 (in float32 the parallel test is round-off and two
    parallel diagonals 17.7 mm apart came out as crossing lines at distance 0, refusing every start); the
    smallest distance is the float64 one to float32's precision, and a step runs."""
    from torchbend.ops.distance import edge_edge_distance_sq, edge_edge_type

    out = {}
    for dt in (torch.float64, torch.float32):
        rest, faces = tb.scenes.grid(9, 3, (0.2, 0.05), dtype=dt)
        rest = rest + torch.tensor([0.0, 0.0, 1e-3], dtype=dt)
        X = rest[torch.tensor([[2, 10, 12, 20]])]  # two parallel diagonals
        assert int(edge_edge_type(X)[0]) == int(edge_edge_type(X.double())[0])
        assert math.isclose(float(edge_edge_distance_sq(X)[0]), 0.025 ** 2 * 2, rel_tol=1e-6)  # 25 mm by 25 mm
        sc = tb.SelfContact(dhat=2e-3)
        model = tb.ClothModel(faces, rest, terms=[sc], density=0.2, pinned=[0, 1, 2],
                              membrane=tb.MembraneEnergy(faces, rest, young=2e5, poisson=0.3, thickness=5e-4))
        out[dt] = sc.contact_stats(rest)
        _, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
        assert info.converged and info.min_distance > 0
    assert math.isclose(out[torch.float32][0], out[torch.float64][0], rel_tol=1e-5)


def test_moving_a_body_mesh_checks_its_vertices():
    bv, bf = box((0.0, 0.0, -0.1), (0.2, 0.2, 0.0))
    body = tb.MeshCollider(bv, bf, dhat=1e-3)
    for bad, what in ((bv[:-1], r"moves the body's 8 vertices .* got \(7, 3\)"), (bv.long(), "float tensor"),
                      (bv * float("nan"), "non-finite"), (bv[:, :2], r"\(Vb, 3\) float tensor")):
        with pytest.raises(ValueError, match="MeshCollider: vertices .*" + what):
            body.vertices = bad
    moved = tb.MeshCollider(bv, bf, dhat=1e-3)
    setattr(moved, "vertices", (bv + 0.01).tolist())  # a nested list of the same shape moves it  # noqa: B010
    assert torch.equal(moved.vertices, bv + 0.01)
    with pytest.raises(ValueError, match="MeshCollider: dhat must be positive"):
        tb.MeshCollider(bv, bf, dhat=-1e-3)


def test_a_cloth_dropped_on_a_body_mesh_rests_on_it_without_passing_through():
    model, rest, body, bv, bf = cloth_over_box(8e-3)
    V = rest.shape[0]
    allf = torch.cat([model.topology.faces, bf + V])
    alle = torch.cat([allf[:, [0, 1]], allf[:, [1, 2]], allf[:, [2, 0]]]).sort(1).values.unique(dim=0)
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    for _ in range(10):
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, info.message
        assert not intersects(torch.cat([state.x, bv]), allf, alle, cloth=V)
        assert info.min_distance > 0
    assert info.contact_count > 0 and float(state.x[:, 2].max()) < 2e-3  # resting within dhat above the top
    with pytest.raises(ValueError, match="mesh_collider: the cloth touches the body mesh"):
        tb.solve_static(model, rest - torch.tensor([0.0, 0.0, 8e-3], dtype=F64))
    with pytest.raises(ValueError, match="MeshCollider: faces index vertices"):
        tb.MeshCollider(bv, bf + 1)


def test_skirt_on_the_mannequin_config_drapes_with_friction_and_never_crosses_the_body(tmp_path):
    """configs/skirt_mannequin.yaml: the shipped skirt on the procedural mannequin (a MeshCollider with friction):
    the steps converge, the skirt comes within dhat of the body and no cloth edge crosses a body triangle, nor a
    body edge a cloth triangle, at any saved state."""
    import os

    from torchbend.scenes.config import build_scene, load_config
    from torchbend.scenes.run import run_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cfg = load_config(os.path.join(root, "configs", "skirt_mannequin.yaml"))
    model, x0, faces = build_scene(cfg)
    (body,) = [t for t in model.terms if isinstance(t, tb.MeshCollider)]
    assert body.friction == 0.3 and body.vertices.shape[0] > 1000
    stats = run_config(cfg, str(tmp_path), steps=8, progress=False)
    assert all(s["converged"] for s in stats["steps"])
    x = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["x"]
    d, count = body.min_distance(x, radius=0.05)
    assert 0 < d < body.dhat and count > 0  # on the hips, never through them
    cloth_edges, body_faces = model.topology.edges, body.body_faces
    bv = body.vertices.to(x.dtype)
    for a, b, tri in ((x[cloth_edges[:, 0]], x[cloth_edges[:, 1]], bv[body_faces]),
                      (bv[body.body_edges[:, 0]], bv[body.body_edges[:, 1]], x[model.topology.faces.to(torch.int64)])):
        for lo in range(0, a.shape[0], 256):  # in chunks of edges against every triangle
            A, B = a[lo:lo + 256, None].expand(-1, tri.shape[0], 3), b[lo:lo + 256, None].expand(-1, tri.shape[0], 3)
            T = tri[None].expand(A.shape[0], -1, 3, 3)
            assert not bool(segment_crosses_triangle(A.reshape(-1, 3), B.reshape(-1, 3), T[..., 0, :].reshape(-1, 3),
                                                     T[..., 1, :].reshape(-1, 3), T[..., 2, :].reshape(-1, 3)).any())


def _pile(tmp_path, steps: int, resolution: int | None):
    """configs/pile.yaml (optionally coarser): every step converges; at every saved frame no cloth edge crosses a
    cloth triangle and the layers are apart; at the end the four layers rest on the floor in their order."""
    import os

    from torchbend.scenes.config import build_scene, load_config
    from torchbend.scenes.run import run_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    overrides = [] if resolution is None else [f"mesh.nx={resolution}", f"mesh.ny={resolution}"]
    cfg = load_config(os.path.join(root, "configs", "pile.yaml"), overrides=overrides)
    cfg["output"]["every"] = 5
    model, x0, faces = build_scene(cfg)
    (sc,) = [t for t in model.terms if isinstance(t, tb.SelfContact)]
    stats = run_config(cfg, str(tmp_path), steps=steps, progress=False)
    assert all(s["converged"] for s in stats["steps"])
    # every step's contact statistics recorded: once the layers land, contacts at a positive distance within dhat
    landed = [s for s in stats["steps"] if s["contact_count"] > 0]
    assert landed and all(0 < s["min_distance"] < sc.dhat for s in landed)
    assert all(s["min_distance"] > 0 for s in stats["steps"])
    topo = model.topology
    frames = sorted((tmp_path / "frames").glob("frame_*.obj"))
    assert len(frames) >= steps // 5
    for path in frames:
        x, _ = tb.mesh.load(str(path), weld_tol=None, dtype=torch.float64)
        assert x.shape == x0.shape
        d, _ = sc.min_distance(x, radius=0.05)
        assert d > 0 and not intersects(x, topo.faces, topo.edges), path.name
    x = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["x"]
    n = x.shape[0] // 4
    heights = [float(x[k * n:(k + 1) * n, 2].mean()) for k in range(4)]
    assert 0 < heights[0] < heights[1] < heights[2] < heights[3] < 5e-3  # piled on the floor, in order


def test_a_pile_of_four_sheets_stays_apart(tmp_path):
    _pile(tmp_path, steps=25, resolution=6)


@pytest.mark.slow
def test_the_pile_config_stays_apart(tmp_path):
    _pile(tmp_path, steps=40, resolution=None)


def test_a_pile_of_sheets_twisted_by_45_degrees_converges_in_every_step():
    """configs/pile.yaml with six sheets, each twisted 45 degrees from the one below (by symmetry vertices lie exactly
    above edges and corners of the sheets below): every step converges without an intersection.  With a contact
    found by several triangles counted once, the energy jumped there and step 10's line search stalled."""
    import os

    from torchbend.scenes.config import SceneConfig, build_scene, load_config, validate

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cfg = validate(load_config(os.path.join(root, "configs", "pile.yaml"),
                               overrides=["mesh.layer_twist=45.0", "mesh.layers=6"]), SceneConfig)
    model, x0, _ = build_scene(cfg)
    topo = model.topology
    state = tb.ClothState(x0, torch.zeros_like(x0))
    for i in range(12):
        state, info = tb.implicit_euler_step(model, state, cfg.solver.dt, cfg.solver.newton_options())
        assert info.converged, (i, info.message)
        assert info.min_distance > 0 and not intersects(state.x, topo.faces, topo.edges), i


def test_the_robot_fold_with_self_contact_folds_the_towel_onto_itself_without_passing_through(tmp_path):
    """configs/robot_fold_self_contact.yaml, whole: every step converges with every contact distance positive (the
    towel's own, the table's and the moving link capsules'); every saved state (every fifth step) has no cloth edge
    through a cloth triangle; at the end the lifted half lies folded on the lower half, apart and in contact."""
    import os

    from torchbend.scenes.config import build_robot_scene, load_config
    from torchbend.scenes.run import run_config

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    cfg = load_config(os.path.join(root, "configs", "robot_fold_self_contact.yaml"))
    cfg["output"]["every"] = 5
    scene, x0, faces, _ = build_robot_scene(cfg)
    (sc,) = [t for t in scene.model.terms if isinstance(t, tb.SelfContact)]
    stats = run_config(cfg, str(tmp_path), progress=False)
    steps = stats["steps"]
    assert len(steps) == 300 and all(s["converged"] for s in steps)
    assert all(s["min_distance"] > 0 for s in steps)
    topo = scene.model.topology
    frames = sorted((tmp_path / "frames").glob("frame_*.obj"))
    assert len(frames) == 61
    for path in frames:
        x, _ = tb.mesh.load(str(path), weld_tol=None, dtype=torch.float64)
        assert not intersects(x, topo.faces, topo.edges), path.name
    x = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["x"]
    d, count = sc.min_distance(x)
    assert 0 < d < sc.dhat and count > 0  # the halves touch through the barrier
    near, far = x0[:, 0] < 0.2, x0[:, 0] > 0.3  # the lifted half lies over the lower one, above it
    assert float(x[near, 0].mean()) > 0.3 and float(x[near, 2].mean()) > float(x[far, 2].mean())


def test_grid_layers_are_a_stack_of_turned_sheets():
    from torchbend.scenes.builders import build_mesh
    from torchbend.scenes.config import SceneConfig, validate
    rest, faces = build_mesh({"type": "grid", "nx": 3, "size": [0.2, 0.2], "layers": 3, "layer_gap": 0.01,
                              "layer_twist": 90.0})
    one, one_faces = build_mesh({"type": "grid", "nx": 3, "size": [0.2, 0.2]})
    assert rest.shape == (27, 3) and torch.equal(faces, torch.cat([one_faces + 9 * k for k in range(3)]))
    torch.testing.assert_close(rest[:9], one)
    c = one.mean(0)
    turned = torch.stack([c[0] - (one[:, 1] - c[1]), c[1] + (one[:, 0] - c[0]), one[:, 2] + 0.01], -1)  # 90 degrees
    torch.testing.assert_close(rest[9:18], turned, rtol=0, atol=1e-15)
    assert torch.allclose(rest[18:, 2], torch.full((9,), 0.02, dtype=rest.dtype))
    with pytest.raises(ValueError, match="pin: corners names vertices of one sheet"):
        validate({"mesh": {"type": "grid", "layers": 2, "pin": "corners"}}, SceneConfig)


def test_an_adaptive_kappa_doubles_while_a_contact_is_pressed_too_close():
    """stiffness=None: a sheet pressed onto a body mesh (gravity x 30) comes within a tenth of dhat in the first
    step's solve; kappa doubles there (``info.adaptations``) and every step ends above a tenth of dhat; the same
    initial kappa given as a stiffness stays as it is and the contact settles below a tenth of dhat."""
    rest, faces = tb.scenes.grid(5, 5, (0.1, 0.1), dtype=F64)
    rest = rest - torch.tensor([0.05, 0.05, -1e-3], dtype=F64)
    floor = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]], dtype=F64)

    def run(stiffness):
        body = tb.MeshCollider(floor, torch.tensor([[0, 1, 2], [0, 2, 3]]), dhat=2e-3, stiffness=stiffness)
        model = tb.ClothModel(faces, rest, colliders=[body], density=0.2, gravity=(0.0, 0.0, -30 * 9.81),
                              membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                              bending=tb.BendingEnergy(faces, rest, stiffness=1e-5))
        state = tb.ClothState(rest, torch.zeros_like(rest))
        kappa, dist, adapted = [], [], []
        for _ in range(8):
            state, info = tb.implicit_euler_step(model, state, 0.01)
            assert info.converged, info.message
            assert body.stiffness is not None
            kappa.append(body.stiffness)
            dist.append(info.min_distance)
            adapted.append(info.adaptations)
        return body, kappa, dist, adapted

    body, kappa, dist, adapted = run(None)
    k0 = body._kappa0
    assert k0 is not None and set(kappa) == {2 * k0} and adapted[0] == 1  # doubled once, within the first solve
    assert min(dist) > 0.1 * body.dhat
    _, kappa_fixed, dist_fixed, adapted_fixed = run(k0)
    assert set(kappa_fixed) == {k0} and set(adapted_fixed) == {0} and max(dist_fixed) < 0.1 * body.dhat


def test_a_stiffness_far_below_the_weight_based_choice_is_warned_about():
    """A given kappa a thousand times below the one stiffness=None chooses (the contacts would be pressed to a tiny
    fraction of dhat, where Newton's intersection-free steps are short) warns, naming both; one near it does not."""
    import warnings
    rest, faces = tb.scenes.grid(5, 5, (0.1, 0.1), dtype=F64)
    auto = tb.SelfContact(dhat=1e-3)
    tb.ClothModel(faces, rest, terms=[auto], density=0.2)
    assert auto.stiffness is not None
    weak = tb.SelfContact(dhat=1e-3, stiffness=1e-4 * auto.stiffness)
    with pytest.warns(UserWarning, match=r"stiffness .* J/m\^4 is 1e\+04 times below the .* stiffness=None"):
        tb.ClothModel(faces, rest, terms=[weak], density=0.2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tb.ClothModel(faces, rest, terms=[tb.SelfContact(dhat=1e-3, stiffness=0.01 * auto.stiffness)], density=0.2)
