"""A body mesh moved between time steps (``MeshCollider.vertices`` assigned): the next step carries out the move in
stages where the body would otherwise come into contact with the cloth, so the body pushes the cloth ahead of it
(checked by the exact segment-triangle test of tests/test_self_contact.py); the friction's slip is relative to the
body's move, so a body moving under a cloth drags it along as far as Coulomb's law allows; a move the cloth cannot
make way for stops, says so and leaves no intersection."""
import pytest
import torch

import torchbend as tb
from tests.test_self_contact import box, intersects

F64 = torch.float64


def sheet_on_box(*, friction: float = 0.0, pinned=None, n: int = 5, size: float = 0.1, gap: float = 1e-3):
    """A ``n x n`` sheet lying ``gap`` above the top (z = 0) of a 0.2 m box with a 2 mm barrier; returns
    ``(model, rest, body, box vertices, box faces)``."""
    rest, faces = tb.scenes.grid(n, n, (size, size), dtype=F64)
    rest = rest + torch.tensor([0.1 - size / 2 + 1e-3, 0.1 - size / 2 + 2e-3, gap], dtype=F64)
    bv, bf = box((0.0, 0.0, -0.1), (0.2, 0.2, 0.0))
    body = tb.MeshCollider(bv, bf, dhat=2e-3, friction=friction)
    model = tb.ClothModel(faces, rest, membrane=tb.MembraneEnergy(faces, rest, young=1e5, poisson=0.3, thickness=5e-4),
                          bending=tb.BendingEnergy(faces, rest, stiffness=1e-5), colliders=[body], density=0.2,
                          pinned=pinned)
    return model, rest, body, bv, bf


def crossing_free(model, x, body, bf) -> bool:
    V = x.shape[0]
    allf = torch.cat([model.topology.faces, bf + V])
    alle = torch.cat([allf[:, [0, 1]], allf[:, [1, 2]], allf[:, [2, 0]]]).sort(1).values.unique(dim=0)
    return not intersects(torch.cat([x, body.vertices.detach()]), allf, alle, cloth=V)


@pytest.mark.parametrize("lift", [5e-3, 0.015])
def test_a_body_moved_up_into_a_cloth_pushes_it_up_in_one_step(lift):
    """The box is lifted by 5 mm (the cloth would cross its top) or 15 mm (the whole cloth would end inside the
    box, where no edge crosses a face): the step lifts the cloth with it, apart and without a crossing."""
    model, rest, body, bv, bf = sheet_on_box()
    body.vertices = bv + torch.tensor([0.0, 0.0, lift], dtype=F64)
    assert body.pending_move()
    state, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
    assert info.converged, info.message
    assert "stages" in info.message and not body.pending_move()
    assert torch.equal(body.vertices, bv + torch.tensor([0.0, 0.0, lift], dtype=F64))  # the move is complete
    assert float(state.x[:, 2].min()) > lift  # every cloth vertex above the box's new top
    assert 0 < info.min_distance < body.dhat and crossing_free(model, state.x, body, bf)


def test_a_move_clear_of_the_cloth_takes_one_solve():
    model, rest, body, bv, bf = sheet_on_box(gap=0.05)
    body.vertices = bv + torch.tensor([0.0, 0.0, 0.01], dtype=F64)  # still 40 mm below the cloth
    _, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
    assert info.converged and info.solves == 1 and "stages" not in info.message
    assert not body.pending_move()


def test_a_body_sliding_far_under_a_resting_cloth_in_one_step_takes_no_stage():
    """The box slides 5 cm (fifty gaps) along x in one step under a cloth resting on it, frictionless: the move
    advances by step bounds without solving between them (the gap does not close), the step ends with the body at
    its new pose and the cloth where it was, apart and without a crossing."""
    model, rest, body, bv, bf = sheet_on_box()
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    for _ in range(3):
        state, info = tb.implicit_euler_step(model, state, 0.01)
    x0 = state.x.clone()
    body.vertices = bv + torch.tensor([0.05, 0.0, 0.0], dtype=F64)
    state, info = tb.implicit_euler_step(model, state, 0.01, max_substep_depth=0)
    assert info.converged and info.solves == 1, info.message
    assert torch.equal(body.vertices, bv + torch.tensor([0.05, 0.0, 0.0], dtype=F64))
    assert float((state.x[:, :2] - x0[:, :2]).abs().max()) < 1e-3  # the cloth stays (no friction)
    assert info.min_distance > 0 and crossing_free(model, state.x, body, bf)


@pytest.mark.parametrize("mu", [0.0, 0.5])
def test_a_body_sliding_under_a_cloth_drags_it_by_friction(mu):
    """The box slides along x at 5 cm/s under a cloth resting on it: with friction 0.5 the cloth sticks and moves
    with it (the acceleration needed, 5 m/s^2 over one step, is below mu g); without friction it stays put.  (Before the
    friction's slip was taken relative to the body's move, a moving body's friction held the cloth still.)"""
    model, rest, body, bv, bf = sheet_on_box(friction=mu)
    state = tb.ClothState(rest.clone(), torch.zeros_like(rest))
    for _ in range(3):  # settle onto the box
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, info.message
    x0 = state.x.clone()
    shift = 0.0
    for _ in range(10):
        shift += 5e-4
        body.vertices = bv + torch.tensor([shift, 0.0, 0.0], dtype=F64)
        state, info = tb.implicit_euler_step(model, state, 0.01)
        assert info.converged, info.message
        assert info.min_distance > 0 and crossing_free(model, state.x, body, bf)
    moved = float((state.x[:, 0] - x0[:, 0]).mean())
    if mu > 0:
        assert moved == pytest.approx(shift, rel=0.05)
    else:
        assert abs(moved) < 0.05 * shift  # (the barrier of the top face's diagonal edge nudges it a little)


def test_a_move_too_long_for_one_step_stops_and_says_so():
    """A cloth pinned all round over a post that rises 5 cm in one step: the cloth makes way by stretching, one
    stage per fraction of a gap, until the stages run out; the step says so, the body stays at the pose reached,
    and neither the state nor the body's pose has a crossing."""
    rest, _ = tb.scenes.grid(7, 7, (0.1, 0.1), dtype=F64)
    local = rest[:, :2] - rest[:, :2].amin(0)
    rim = (local < 1e-9).any(1) | (local > 0.1 - 1e-9).any(1)
    model, rest, body, bv, bf = sheet_on_box(n=7, pinned=rim, gap=5e-3)
    small = box((0.08, 0.08, -0.1), (0.12, 0.12, 0.0))[0]  # a post under the middle of the cloth
    body.vertices = small
    tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)  # (the post placed)
    body.vertices = small + torch.tensor([0.0, 0.0, 0.05], dtype=F64)
    state, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
    assert not info.converged and info.stop_reason == "body_move" and info.substeps == 1
    assert "stopped at" in info.message and "move the body less per step" in info.message
    assert not body.pending_move()
    top = float(body.vertices[:, 2].max())
    assert 5e-3 < top < 0.05  # it moved, and stopped short
    assert info.min_distance > 0 and crossing_free(model, state.x, body, bf)


def test_a_cloth_caught_between_two_bodies_stops_the_move():
    """A block pressed down onto a cloth lying on a floor (two body meshes): the cloth cannot make way; the step
    stops the block short of the floor, says so, and leaves the cloth between the two, apart from both."""
    model, rest, floor, fv, ff = sheet_on_box()
    bv, bf = box((0.08, 0.08, 5e-3), (0.12, 0.12, 0.045))
    block = tb.MeshCollider(bv, bf, dhat=2e-3, name="block")
    model = tb.ClothModel(model.topology.faces, rest, membrane=model.membrane, bending=model.bending,
                          colliders=[floor, block], density=0.2)
    block.vertices = bv - torch.tensor([0.0, 0.0, 0.01], dtype=F64)  # its bottom 5 mm into the floor
    state, info = tb.implicit_euler_step(model, tb.ClothState(rest.clone(), torch.zeros_like(rest)), 0.01)
    assert not info.converged and info.stop_reason == "body_move" and "stopped at" in info.message
    bottom = float(block.vertices[:, 2].min())
    assert 0 < bottom < 5e-3  # it moved down, and stopped above the floor
    assert info.min_distance > 0
    assert crossing_free(model, state.x, floor, ff) and crossing_free(model, state.x, block, bf)
