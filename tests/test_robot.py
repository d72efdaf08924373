"""Robot-driven cloth: URDF loading, pins bound to link frames, link capsules, differentiable statics."""
import math
import os

import pytest
import torch

import torchbend as tb
from torchbend.robot import LinkCapsule, LinkPins, Robot, RobotScene, asset_path, trajectory
from torchbend.scenes.config import build_robot_scene, load_config
from torchbend.scenes.config import parse_robot as parse_config
from torchbend.scenes.run import run_config

ROOT = os.path.dirname(os.path.dirname(__file__))
F64 = torch.float64


@pytest.fixture(scope="module")
def robot():
    return Robot("folding_arm.urdf")


def planar_finger_tips(q):
    """Independent forward kinematics of the shipped arm (URDF numbers written out by hand)."""
    yaw, s, e, w, fl, fr = [float(v) for v in q]
    L = 0.45
    # in the arm's vertical plane: x forward, z up; rotation about y by a turns x towards -z
    a1, a2, a3 = s, s + e, s + e + w
    wx = L * math.cos(a1) + L * math.cos(a2)
    wz = 0.3 - L * math.sin(a1) - L * math.sin(a2)
    # finger tip: 0.05 below the wrist in the gripper frame, and +-(0.25 + opening) along y
    tx = wx + (-0.05) * math.sin(a3)
    tz = wz + (-0.05) * math.cos(a3)
    out = []
    for side, d in ((1, fl), (-1, fr)):
        p = (tx, side * (0.25 + d), tz)
        c, sn = math.cos(yaw), math.sin(yaw)
        out.append((-0.3 + c * p[0] - sn * p[1], sn * p[0] + c * p[1], p[2]))
    return torch.tensor(out, dtype=F64)


def test_shipped_urdf_forward_kinematics_matches_hand_derivation(robot):
    assert os.path.isfile(asset_path("folding_arm.urdf"))
    assert robot.joint_names == ["yaw", "shoulder", "elbow", "wrist", "finger_left", "finger_right"]
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        q = (torch.rand(6, generator=gen, dtype=F64) - 0.5) * torch.tensor([2, 2, 2, 2, 0.2, 0.2], dtype=F64)
        T = robot.link_transforms(q, ["finger_left", "finger_right"])
        assert float((T[:, :3, 3] - planar_finger_tips(q)).abs().max()) < 1e-14
        R = T[:, :3, :3]
        assert float((R.transpose(-1, -2) @ R - torch.eye(3, dtype=F64)).abs().max()) < 1e-14


def test_batched_forward_kinematics_and_pins(robot):
    gen = torch.Generator().manual_seed(1)
    q = 0.3 * torch.randn(4, 3, 6, generator=gen, dtype=F64)
    T = robot.link_transforms(q, ["gripper", "forearm"])
    assert T.shape == (4, 3, 2, 4, 4)
    for i in range(4):
        for j in range(3):
            assert torch.allclose(T[i, j], robot.link_transforms(q[i, j], ["gripper", "forearm"]), atol=0, rtol=0)
    q0 = torch.zeros(6, dtype=F64)
    pos = torch.tensor([[0.6, 0.3, 0.2], [0.5, -0.2, 0.25], [0.0, 0.0, 0.0]], dtype=F64)
    pins = LinkPins(robot, [5, 2, 9], ["finger_left", "gripper", "world"], pos, q0)
    assert torch.equal(pins.vertices, torch.tensor([2, 5, 9]))
    assert float((pins.positions(q0) - pos[[1, 0, 2]]).abs().max()) < 1e-15
    # rigid attachment: distances to the link origin are preserved; the world pin never moves
    p = pins.positions(q)
    assert p.shape == (4, 3, 3, 3)
    origin = robot.link_transforms(q, ["finger_left"])[..., 0, :3, 3]
    d0 = (pos[0] - robot.link_transforms(q0, ["finger_left"])[0, :3, 3]).norm()
    assert float(((p[..., 1, :] - origin).norm(dim=-1) - d0).abs().max()) < 1e-14
    assert float((p[..., 2, :] - pos[2]).abs().max()) == 0.0


def _hanging_towel(robot, q0, n=6):
    tips = robot.link_transforms(q0, ["finger_left", "finger_right"])[:, :3, 3]
    flat, faces = tb.scenes.grid(n, n, (0.3, 0.3), dtype=F64)
    down = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    rest = tips[1] + flat[:, :1] * (tips[0] - tips[1]) / 0.3 - flat[:, 1:2] * down
    bend = tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-3)
    mem = tb.MembraneEnergy(faces, rest, model="stvk", young=1e5, poisson=0.3, thickness=1e-3)
    pinned = torch.zeros(n * n, dtype=torch.bool)
    pinned[[0, n - 1]] = True
    model = tb.ClothModel(faces, rest, bending=bend, membrane=mem, density=0.2, pinned=pinned)
    pins = LinkPins(robot, [n - 1, 0], ["finger_left", "finger_right"], rest[[n - 1, 0]], q0)
    return RobotScene(model, robot, pins), rest


def _fd_check(scene, q0, x0, weights, h=1e-6):
    q = q0.clone().requires_grad_()
    x, info = scene.solve_static(q, x0, tol=1e-12, continuation=True)
    assert info.converged
    (g,) = torch.autograd.grad((weights * x).sum(), q)
    fd = []
    for j in range(len(q0)):
        vals = []
        for s in (1, -1):
            qq = q0.clone()
            qq[j] += s * h
            xj, ij = scene.solve_static(qq, x.detach(), tol=1e-12)
            assert ij.converged
            vals.append(float((weights * xj).sum()))
        fd.append((vals[0] - vals[1]) / (2 * h))
    return g, torch.tensor(fd, dtype=F64), x.detach()


def test_joint_gradient_through_static_solve_matches_finite_differences(robot):
    """d(loss)/d(q) of a towel hanging from both finger tips (the pins carry the dependence)."""
    q0 = torch.tensor([0.1, -0.8, 1.2, -0.4, 0.02, -0.01], dtype=F64)
    scene, rest = _hanging_towel(robot, q0)
    w = torch.randn(rest.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    g, fd, x = _fd_check(scene, q0, rest, w)
    assert float((x[scene.pins.vertices] - scene.pins.positions(q0)).abs().max()) < 1e-12
    assert float(g.abs().min()) > 1e-3  # every joint moves the towel
    assert float((g - fd).abs().max()) <= 1e-6 * float(fd.abs().max())


def test_joint_gradient_through_link_capsule_contact_matches_finite_differences(robot):
    """A membrane clamped to the table frame ('world' link) pressed down by a capsule on the
    forearm: the equilibrium depends on q only through the capsule's end points."""
    q0 = torch.tensor([0.05, 0.02, -0.03, 0.0, 0.0, 0.0], dtype=F64)
    rest, faces = tb.scenes.grid(9, 9, (0.4, 0.4), dtype=F64)
    rest = rest + torch.tensor([0.25, -0.2, 0.0], dtype=F64)
    edge = (rest[:, 0] < 0.251) | (rest[:, 0] > 0.649) | (rest[:, 1].abs() > 0.199)
    model = tb.ClothModel(faces, rest, density=0.2, pinned=edge,
                          membrane=tb.MembraneEnergy(faces, rest, model="stvk", young=1e4, poisson=0.3, thickness=1e-3),
                          bending=tb.BendingEnergy(faces, rest, model="tan", stiffness=1e-4))
    idx = edge.nonzero()[:, 0]
    T = robot.link_transforms(q0, ["forearm"])[0]
    R, t = T[:3, :3], T[:3, 3]
    a = R.T @ (torch.tensor([0.38, -0.08, -0.03], dtype=F64) - t)
    b = R.T @ (torch.tensor([0.52, 0.06, -0.03], dtype=F64) - t)
    cap = LinkCapsule("forearm", a=a.tolist(), b=b.tolist(), radius=0.025, stiffness=2e3)
    scene = RobotScene(model, robot, LinkPins(robot, idx, "world", rest[idx], q0), [cap])
    w = torch.randn(rest.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
    g, fd, x = _fd_check(scene, q0, rest, w)
    assert int((scene.colliders(q0)[0].depth(x) > 0).sum()) >= 2  # in contact
    assert float(g[:3].abs().min()) > 1e-3 and float(g[3:].abs().max()) == 0.0  # wrist/fingers do not move it
    assert float((g - fd).abs().max()) <= 1e-6 * float(fd.abs().max())


def test_robot_scene_pins_follow_forward_kinematics_every_step(tmp_path):
    cfg = load_config(os.path.join(ROOT, "configs", "robot_fold.yaml"))
    stats = run_config(cfg, str(tmp_path), steps=60, resolution=(7, 7), progress=False)
    assert all(s["converged"] for s in stats["steps"])
    assert max(stats["pin_error"]) <= 1e-6
    assert os.path.isfile(tmp_path / "snapshot.png")
    frames = sorted(os.listdir(tmp_path / "frames"))
    assert frames[0] == "frame_0000.obj" and "frame_0050.obj" in frames and "frame_0060.obj" in frames
    # independent check on the written frames: held vertices at the forward kinematics of q(t)
    import meshio

    scene, x0, faces, keyframes = build_robot_scene(cfg, resolution=(7, 7))
    for name in frames:
        step = int(name[6:10])
        p = torch.from_numpy(meshio.read(tmp_path / "frames" / name).points).to(F64)
        q = trajectory(keyframes, step * cfg["solver"]["dt"])
        assert float((p[scene.pins.vertices] - scene.pins.positions(q)).norm(dim=-1).max()) <= 1e-6
    z_tips = scene.pins.positions(trajectory(keyframes, 60 * cfg["solver"]["dt"]))[:, 2]
    assert float(z_tips.max()) > 0.1  # the towel has been lifted


def test_robot_scene_step_moves_pins_and_keeps_cloth_finite(robot):
    q0 = torch.tensor([0.1, -0.8, 1.2, -0.4, 0.0, 0.0], dtype=F64)
    scene, rest = _hanging_towel(robot, q0)
    state = tb.ClothState(rest, torch.zeros_like(rest))
    for k in range(1, 6):
        q = q0 + 0.02 * k * torch.tensor([1, 1, -1, 0, 0.5, 0.5], dtype=F64)
        state, info = scene.step(state, q, 0.01)
        assert info.converged and bool(torch.isfinite(state.x).all())
        assert float((state.x[scene.pins.vertices] - scene.pins.positions(q)).abs().max()) == 0.0


@pytest.mark.parametrize("urdf, match", [
    ("<robot name='r'><link name='a'/>", "XML syntax"),
    ("<robo name='r'/>", "root element must be <robot>"),
    ("<robot name='r'><link name='a'/></robot>", "no <joint>"),
    ("<robot name='r'><link name='a'/><joint name='j' type='revolute'><parent link='a'/><child link='b'/></joint></robot>",
     "joint 'j' names child link 'b'"),
    ("<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='ball'><parent link='a'/><child link='b'/></joint></robot>",
     "joint 'j' has type 'ball'"),
    ("<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='fixed'><parent link='a'/></joint></robot>",
     "joint 'j' has no <child"),
    ("<robot name='r'><link name='a'/><link name='b'/><joint name='j' type='fixed'><parent link='a'/><child link='b'/>"
     "<origin xyz='0 1'/></joint></robot>", "three numbers"),
    ("<robot name='r'><link name='a'/><link name='b'/><link name='c'/><link name='d'/>"
     "<joint name='j' type='fixed'><parent link='a'/><child link='b'/></joint>"
     "<joint name='k' type='fixed'><parent link='c'/><child link='d'/></joint></robot>", "one root link"),
    ("no_such_robot.urdf", "URDF file not found"),
])
def test_malformed_urdf_is_a_value_error_naming_it(urdf, match):
    with pytest.raises(ValueError, match=match):
        Robot(urdf)


def test_wrong_link_names_and_joint_vector_lengths_are_value_errors(robot):
    q0 = torch.zeros(6, dtype=F64)
    with pytest.raises(ValueError, match="no link 'hand'"):
        LinkPins(robot, [0], ["hand"], torch.zeros(1, 3, dtype=F64), q0)
    with pytest.raises(ValueError, match="no link 'hand'"):
        robot.link_transforms(q0, ["hand"])
    with pytest.raises(ValueError, match="no link 'elbow_link'"):
        LinkCapsule("elbow_link").endpoints(robot, q0)
    for q in (torch.zeros(5, dtype=F64), torch.zeros(2, 7, dtype=F64), torch.tensor(0.0)):
        with pytest.raises(ValueError, match="6 movable joints"):
            robot.link_transforms(q, ["gripper"])
    with pytest.raises(ValueError, match="non-finite"):
        robot.link_transforms(torch.full((6,), float("nan")), ["gripper"])
    scene, rest = _hanging_towel(robot, q0)
    with pytest.raises(ValueError, match="q_next has length 4"):
        scene.step(tb.ClothState(rest, torch.zeros_like(rest)), torch.zeros(4, dtype=F64), 0.01)
    with pytest.raises(ValueError, match="length 3"):
        scene.solve_static(torch.zeros(3, dtype=F64), rest)
    with pytest.raises(ValueError, match="capsules\\[0\\]: robot .* has no link 'claw'"):
        RobotScene(scene.model, robot, scene.pins, [LinkCapsule("claw")])
    with pytest.raises(ValueError, match="not pinned in the model"):
        model = tb.ClothModel(scene.model.topology, rest, density=0.2)
        RobotScene(model, robot, scene.pins)


@pytest.mark.parametrize("patch, match", [
    ({"pins": [{"link": "hand", "vertices": [0]}]}, "robot.pins\\[0\\].link.*no link 'hand'"),
    ({"trajectory": [{"t": 0.0, "q": [0, 0, 0]}]}, "robot.trajectory\\[0\\].q has length 3"),
    ({"trajectory": [{"t": 0.0, "q": [0] * 6}, {"t": 0.0, "q": [0] * 6}]}, "trajectory\\[1\\].t must be"),
    ({"capsules": [{"link": "forearm", "radius": -1}]}, "robot.capsules\\[0\\].*radius"),
    ({"urdf": "missing.urdf"}, "URDF file not found"),
    ({"gripper": 1}, "unknown config key 'robot.gripper'"),
])
def test_bad_robot_config_names_the_key(patch, match):
    cfg = load_config(os.path.join(ROOT, "configs", "robot_fold.yaml"))
    section = {**cfg["robot"], **patch}
    rest, _ = tb.scenes.grid(5, 5, dtype=F64)
    with pytest.raises(ValueError, match=match):
        parse_config(section, rest)


def test_a_static_collider_moved_in_a_robot_scene_moves_once(robot):
    """A static collider of the scene's model replaced by a moved one (the ipc law: a move in stages) is moved by
    the next robot step, and that step ends the move on the scene's model too: the step after does not move it
    again from its old pose."""
    q0 = torch.tensor([0.1, -0.8, 1.2, -0.4, 0.0, 0.0], dtype=F64)
    scene, rest = _hanging_towel(robot, q0)
    low = float(rest[:, 2].min())
    scene.model.colliders = [tb.Sphere(center=(0.0, 0.0, low - 0.3), radius=0.1)]
    scene.model.colliders = [tb.Sphere(center=(0.0, 0.0, low - 0.2), radius=0.1)]
    assert scene.model._collider_move(0)[0] is not None
    state = tb.ClothState(rest, torch.zeros_like(rest))
    state, info = scene.step(state, q0, 0.01)
    assert info.converged and scene.model._collider_move(0)[0] is None
    assert scene.model.colliders[0].center == pytest.approx((0.0, 0.0, low - 0.2))
