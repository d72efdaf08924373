"""Exact bending Hessians: per-hinge blocks, per-hinge vs per-triangle assembly, projections."""
import pytest
import torch

from torchbend import to_scipy
from torchbend.energies.sparse import HessianPattern
from torchbend.ops import hinge as geometry
from torchbend.ops.projection import project_blocks
from torchbend.options import Projection as HessianProjection

from .helpers import MESHES, MODELS, mesh_cases, per_hinge_reference, random_bending, reference_hessian, rel

F64 = torch.float64
PROJECTIONS = ["clamp", "abs", "gauss_newton", "reduced"]


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("model", MODELS)
def test_hinge_hessians_match_torch_func(sheet, model, damped):
    rest, faces, x = sheet
    bend = random_bending(rest, faces, model, damped)
    kw = {}
    if damped:
        kw = {"theta_prev": bend.angles(x) + 0.03 * torch.randn(bend.hinge_count, dtype=F64), "dt": 0.05}
    Hb = bend.hinge_hessians(x, **kw)
    assert Hb.shape == (bend.hinge_count, 12, 12)
    Hr = per_hinge_reference(bend, x, kw)
    assert rel(Hb, Hr) <= 1e-12
    per_block = (Hb - Hr).flatten(1).norm(dim=1) / Hr.flatten(1).norm(dim=1)
    assert per_block.max() <= 1e-12
    assert (Hb - Hb.transpose(-1, -2)).abs().max() <= 1e-14 * Hb.abs().max()
    for j in range(3):  # translations are in the null space of every block
        t = torch.zeros(12, dtype=F64)
        t[j::3] = 1
        assert (Hb @ t).norm() <= 1e-13 * Hb.norm()


def test_hinge_hessians_batched(sheet):
    rest, faces, x = sheet
    bend = random_bending(rest, faces, "tan")
    xb = torch.stack([x, rest + 0.01])
    Hb = bend.hinge_hessians(xb)
    assert Hb.shape == (2, bend.hinge_count, 12, 12)
    assert rel(Hb[1], bend.hinge_hessians(rest + 0.01)) < 1e-15


@pytest.mark.parametrize("mesh", MESHES)
@pytest.mark.parametrize("model", MODELS)
def test_assembly_paths_agree_and_match_dense_reference(mesh, model):
    rest, faces = mesh_cases()[mesh]
    gen = torch.Generator().manual_seed(2)
    x = rest + 0.05 * torch.randn(rest.shape, generator=gen, dtype=F64)
    bend = random_bending(rest, faces, model)
    signs = bend.topology.face_edge_signs[bend.topology.face_edge_hinges >= 0]
    assert (signs > 0).any() and (signs < 0).any()  # both orientations occur
    Ht = bend.hessian(x, assembly="triangle")
    Hh = bend.hessian(x, assembly="hinge")
    assert Ht.layout == torch.sparse_csr and Ht.shape == (3 * len(x), 3 * len(x))
    Dt, Dh = Ht.to_dense(), Hh.to_dense()
    assert rel(Dt, Dh) <= 1e-13
    n = 3 * len(x)
    ref = reference_hessian(bend, x)
    assert rel(Dt, ref) <= 1e-13
    v = torch.randn_like(x)
    assert rel(Dt @ v.reshape(-1), bend.hvp(x, v).reshape(-1)) <= 1e-13
    S = to_scipy(Ht)
    assert S.shape == (n, n) and abs(S - S.T).max() <= 1e-14 * abs(S).max()
    assert rel(torch.as_tensor(S @ v.reshape(-1).numpy()), bend.hvp(x, v).reshape(-1)) <= 1e-13


def test_pattern_is_cached_per_module(sheet):
    rest, faces, x = sheet
    bend = random_bending(rest, faces, "tan")
    bend.hessian(x)
    p1 = bend._pattern
    bend.hessian(x)
    assert bend._pattern is p1 and isinstance(p1, HessianPattern)
    assert p1.nnz == bend.hessian(x).values().numel()
    assert p1.nnz == HessianPattern(bend.topology).nnz
    # index arrays go to another device once and stay there ("meta" stands in for a GPU); the CPU ones are the
    # pattern's own
    meta = p1.on("meta")
    assert p1.on("meta") is meta and meta["element_blocks"].is_meta
    assert {"crow_indices", "col_indices", "row_len", "face_blocks", "hinged_faces"} <= set(meta)
    assert p1.on("cpu")["crow_indices"] is p1.crow_indices
    # off the CPU the full maps are expanded per call from the block bases there, on the CPU built once and kept
    assert p1.element_positions(torch.device("meta")).is_meta
    assert p1.hinged_face_positions(torch.device("meta")).shape == p1.face_pos[p1.face_has_hinge].shape
    assert p1.element_positions(torch.device("cpu")).data_ptr() == p1.element_pos.data_ptr()
    # the full position maps (the block bases spread over the rows): every entry of every vertex block of a hinge
    # or a hinged face, no two entries of one block at one position, all inside the values
    for pos, m in ((p1.hinge_pos, 4), (p1.face_pos[p1.face_has_hinge], 3)):
        assert pos.shape[1] == 9 * m * m and int(pos.min()) >= 0 and int(pos.max()) < p1.nnz
        assert all(len(set(row.tolist())) == 9 * m * m for row in pos)
    cols = p1.col_indices[p1.hinge_pos].reshape(-1, 4, 3, 4, 3)  # column of entry (a, p; b, q): 3 v_b + q
    want = 3 * bend.hinges[:, None, None, :, None] + torch.arange(3)[None, None, None, None, :]
    assert torch.equal(cols, want.expand_as(cols))
    rows = (torch.searchsorted(p1.crow_indices, p1.hinge_pos, right=True) - 1).reshape(-1, 4, 3, 4, 3)  # 3 v_a + p
    want = 3 * bend.hinges[:, :, None, None, None] + torch.arange(3)[None, None, :, None, None]
    assert torch.equal(rows, want.expand_as(rows))


@pytest.mark.parametrize("project", PROJECTIONS)
@pytest.mark.parametrize("model", MODELS)
def test_projections_are_psd_and_consistent(sheet, model, project):
    rest, faces, x = sheet
    x = x + 0.2 * torch.randn_like(x)  # strongly bent: indefinite blocks
    bend = random_bending(rest, faces, model)
    P = bend.hinge_hessians(x, projection=project)
    L = torch.linalg.eigvalsh(P)
    norms = P.flatten(-2).norm(dim=-1)
    assert (L.min(-1).values >= -1e-12 * norms).all()
    assert (P - P.transpose(-1, -2)).abs().max() <= 1e-13 * P.abs().max()
    # the assembled projected Hessian and the matrix-free projected HVP agree
    v = torch.randn_like(x)
    Hp = bend.hessian(x, projection=project)
    assert rel(Hp.to_dense() @ v.reshape(-1), bend.hvp(x, v, projection=project).reshape(-1)) <= 1e-13
    for j in range(3):  # every projection keeps translations in the null space
        t = torch.zeros(12, dtype=F64)
        t[j::3] = 1
        assert (P @ t).norm() <= 1e-12 * P.norm()


def test_exact_blocks_are_indefinite_and_projections_leave_psd_blocks_unchanged(sheet):
    rest, faces, x = sheet
    x = x + 0.2 * torch.randn_like(x)
    bend = random_bending(rest, faces, "tan")
    Hb = bend.hinge_hessians(x)
    assert (torch.linalg.eigvalsh(Hb).min(-1).values < -1e-10).any()  # something to project
    psd = project_blocks(Hb, HessianProjection.CLAMP)
    for p in (HessianProjection.CLAMP, HessianProjection.ABS, HessianProjection.REDUCED):
        assert rel(project_blocks(psd, p), psd) <= 1e-12
    # abs flips negative eigenvalues, clamp zeroes them: abs - clamp = 2 * (negative part)
    neg = project_blocks(Hb, HessianProjection.CLAMP) - Hb
    assert rel(project_blocks(Hb, HessianProjection.ABS) - Hb, 2 * neg) <= 1e-11


def test_gauss_newton_is_the_clamped_rank_one_term(sheet):
    rest, faces, x = sheet
    bend = random_bending(rest, faces, "sin")
    P = bend.hinge_hessians(x, projection="gauss_newton")
    x4 = x[bend.hinges]
    _, g4 = geometry.hinge_angle_and_gradient(x4)
    g = g4.flatten(-2)
    from torchbend.ops.psi import psi_theta_derivatives

    _, d2 = psi_theta_derivatives(bend.model, geometry.hinge_angle(x4), bend.weights, bend.stiffness, bend.rest_angles)
    ref = d2.clamp_min(0)[:, None, None] * g[:, :, None] * g[:, None, :]
    assert rel(P, ref) <= 1e-14


def test_bad_hessian_arguments(sheet):
    rest, faces, x = sheet
    bend = random_bending(rest, faces, "tan")
    with pytest.raises(ValueError, match="unknown Hessian projection 'eig'"):
        bend.hessian(x, projection="eig")
    with pytest.raises(ValueError, match="unknown assembly 'edge'"):
        bend.hessian(x, assembly="edge")
    with pytest.raises(ValueError, match="one mesh"):
        bend.hessian(torch.stack([x, x]))
    with pytest.raises(ValueError, match="unknown Hessian projection"):
        bend.hvp(x, x, projection="nearest")
