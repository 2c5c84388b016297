"""Collision checking (python-fcl) against known geometry, brute force and pybullet."""

from __future__ import annotations

import math
import os

import fcl
import numpy as np
import pybullet as p
import pybullet_data
import pytest

from planners.config import GridConfig
from planners.grid import OccupancyGrid
from planners.motion.collision import (
    CollisionChecker,
    CollisionConfig,
    RobotCollisionModel,
    TorchShape,
    _octree_data,
    densify_joint_path,
    grid_scene_voxels,
)
from planners.motion.limits import PANDA_JOINT_NAMES, PANDA_Q_MAX, PANDA_Q_MIN, PANDA_Q_READY
from planners.motion.trajectory import plan_joint_motion

URDF = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
FLANGE = "panda_hand"
HOME = np.array([0.0, -0.7, 0.0, -2.4, 0.0, 2.2, 0.785])  # a low "ready" pose, hand near z = 0.5
HAND_GROUP = {"panda_hand", "panda_leftfinger", "panda_rightfinger", "camera"}
VOXEL = 0.01
ONE_DEG = math.radians(1.0)


def hand_eye() -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.07, 0.0, 0.05]  # the twin's default mount
    return T


@pytest.fixture(scope="module")
def robot() -> RobotCollisionModel:
    return RobotCollisionModel(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye())


@pytest.fixture()
def checker(robot) -> CollisionChecker:
    return CollisionChecker(robot)


def world_points(robot: RobotCollisionModel, q: np.ndarray, names=None) -> np.ndarray:
    """Hull vertices of the moving parts in the base frame."""
    P = robot.part_poses(q)
    pts = [part.vertices @ T[:3, :3].T + T[:3, 3] for part, T, fixed in zip(robot.parts, P, robot.fixed)
           if not fixed and (names is None or part.name in names)]
    return np.concatenate(pts)


def block(lo: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Centres of a box of voxels whose min corner is ``lo``."""
    g = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    return np.asarray(lo, dtype=np.float64) + (g + 0.5) * VOXEL


def slab_below(robot, q, gap: float) -> np.ndarray:
    """A 10 x 10 x 3 cm slab whose top face is ``gap`` below the hand's lowest point, right under
    it: the robot-slab distance is exactly ``gap`` (every part above the slab is higher)."""
    pts = world_points(robot, q, HAND_GROUP)
    low = pts[np.argmin(pts[:, 2])]
    return block([low[0] - 0.05, low[1] - 0.05, low[2] - gap - 0.03], (10, 10, 3))


# ---------------------------------------------------------------------------- model


def test_parts_and_self_pairs(robot):
    assert robot.part_names[:1] == ("panda_link0",) and "camera" in robot.part_names
    assert robot.fixed.tolist() == [n == "panda_link0" for n in robot.part_names]
    pairs = {frozenset((robot.part_names[i], robot.part_names[j])) for i, j in robot.self_pairs}
    # rigid (link7 / hand / fingers / camera) and adjacent pairs are off, the rest is checked
    for off in [("panda_link7", "panda_hand"), ("panda_hand", "camera"), ("panda_leftfinger", "panda_rightfinger"),
                ("panda_link0", "panda_link1"), ("panda_link5", "panda_link6")]:
        assert frozenset(off) not in pairs
    for on in [("panda_link0", "panda_hand"), ("panda_link1", "camera"), ("panda_link6", "camera"),
               ("panda_link2", "panda_link4"), ("panda_link5", "panda_link7")]:
        assert frozenset(on) in pairs
    assert robot.always_touching == ()


def test_home_is_free_against_an_empty_scene(checker):
    for q in (HOME, PANDA_Q_READY):
        assert checker.check(q) is None
        assert not checker.in_collision(q)
    checker.set_scene(np.empty((0, 3)), VOXEL)
    assert checker.scene_voxels == 0 and checker.check(HOME) is None


def test_hand_into_the_floor_is_reported_with_the_link(checker, robot):
    q = np.array([0.0, 1.5, 0.0, -0.8, 0.0, 2.0, 0.785])
    assert world_points(robot, q, HAND_GROUP)[:, 2].min() < -0.03  # the hand is well below z = 0
    hit = checker.check(q)
    assert hit is not None and hit.kind == "floor" and hit.other == "floor"
    assert hit.part in HAND_GROUP
    assert hit.part in str(hit) and "floor" in str(hit)
    # the floor margin: lowest point 1.5 cm above the floor
    q = np.array([0.0, 1.2, 0.0, -0.8, 0.0, 2.0, 0.785])
    zmin = world_points(robot, q)[:, 2].min()
    assert checker.check(q) is None and zmin > 0.02
    high = CollisionChecker(robot, CollisionConfig(floor_margin_m=zmin + 0.005))
    assert high.check(q).kind == "floor"


def test_voxels_at_the_hand_and_the_margin(checker, robot):
    T = robot.kin.fk(HOME, "flange")
    checker.set_scene(block(np.floor(T[:3, 3] / VOXEL) * VOXEL - 0.03, (6, 6, 6)), VOXEL)
    hit = checker.check(HOME)
    assert hit is not None and hit.kind == "scene" and hit.other == "scene"
    assert hit.part in HAND_GROUP | {"panda_link6", "panda_link7"}  # parts are tried from the base out
    assert checker.scene_voxels == 216

    for gap, expect in [(0.0, True), (0.015, True), (0.025, False), (0.10, False)]:
        checker.set_scene(slab_below(robot, HOME, gap), VOXEL)
        hit = checker.check(HOME)
        assert (hit is not None) == expect, (gap, hit)
        if expect:
            assert hit.kind == "scene" and hit.part in ("panda_leftfinger", "panda_rightfinger")
    # without the margin, 1.5 cm is free
    bare = CollisionChecker(robot, CollisionConfig(margin_m=0.0))
    bare.set_scene(slab_below(robot, HOME, 0.015), VOXEL)
    assert bare.check(HOME) is None
    bare.set_scene(slab_below(robot, HOME, -0.005), VOXEL)
    assert bare.check(HOME) is not None


def test_solid_voxels_deep_inside_a_link_collide(robot):
    # one voxel inside the hand, touching none of its faces: a solid-vs-solid test sees it
    bare = CollisionChecker(robot, CollisionConfig(margin_m=0.0, self_collision=False))
    c = robot.kin.fk(HOME, "flange")[:3, :3] @ np.array([0.0, 0.0, 0.03]) + robot.kin.fk(HOME, "flange")[:3, 3]
    bare.set_scene(np.floor(c / VOXEL)[None] * VOXEL + VOXEL / 2, VOXEL)
    assert bare.check(HOME).part == "panda_hand"


def test_unknown_cells_count_only_when_configured(robot):
    slab = slab_below(robot, HOME, 0.015)
    occ, unk = slab[: len(slab) // 2] - [0.0, 0.0, 0.2], slab
    on = CollisionChecker(robot)
    off = CollisionChecker(robot, CollisionConfig(unknown_as_occupied=False))
    for ch in (on, off):
        ch.set_scene(occ, VOXEL, unk)
    assert on.check(HOME).kind == "scene" and on.scene_voxels == len(occ) + len(unk)
    assert off.check(HOME) is None and off.scene_voxels == len(occ)


def test_torch_on_the_flange(robot):
    torch = TorchShape(radius_m=0.015, length_m=0.25, T_flange_torch=np.eye(4))
    with_torch = CollisionChecker(RobotCollisionModel(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye(), torch=torch))
    assert with_torch.check(HOME) is None
    T = robot.kin.fk(HOME, "flange")
    tip = T[:3, 3] + 0.25 * T[:3, 2]
    assert world_points(robot, HOME, HAND_GROUP)[:, 2].min() > tip[2] + 0.05  # the torch reaches 5 cm past the fingers
    slab = block(np.floor(tip / VOXEL) * VOXEL - [0.02, 0.02, 0.04], (4, 4, 3))  # just under the tip
    with_torch.set_scene(slab, VOXEL)
    plain = CollisionChecker(robot)
    plain.set_scene(slab, VOXEL)
    assert plain.check(HOME) is None
    assert with_torch.check(HOME).part == "torch"


def test_known_self_collisions_agree_with_pybullet(checker, bullet):
    cid, body, joints, links = bullet
    cases = [np.array([0.0, -1.7, 0.0, -3.0, 0.0, 1.0, 0.785]),  # hand folded back onto link1
             np.array([-0.92, 1.28, 0.6, -3.05, -1.36, 2.28, -1.07])]  # hand down onto the base
    for q in cases:
        assert np.all(q >= PANDA_Q_MIN) and np.all(q <= PANDA_Q_MAX)
        hit = checker.check(q)
        assert hit is not None and hit.kind == "self", hit
        assert {hit.part, hit.other} & HAND_GROUP and {hit.part, hit.other} & {"panda_link0", "panda_link1"}
        set_q(cid, body, joints, q)
        a, b = links[hit.part], links[hit.other]
        d = min(c[8] for c in p.getClosestPoints(body, body, 0.05, linkIndexA=a, linkIndexB=b, physicsClientId=cid))
        assert d < 0, (hit, d)
    off = CollisionChecker(checker.robot, CollisionConfig(self_collision=False))
    assert off.check(cases[0]) is None


# ---------------------------------------------------------------------------- paths


def wall_y(y0: float) -> np.ndarray:
    """A 2 cm thick wall y in [y0, y0 + 0.02], x in [0.1, 0.9], z in [0.1, 1.0]."""
    return block([0.1, y0, 0.1], (80, 2, 90))


def test_path_through_a_wall_reports_the_first_colliding_sample(checker):
    checker.set_scene(wall_y(0.25), VOXEL)
    q1 = HOME.copy()
    q1[0] = 1.2  # swing joint 1: the hand sweeps towards +y through the wall
    assert checker.check(HOME) is None and checker.check(q1) is not None
    hit = checker.check_path(np.stack([HOME, q1]))
    assert hit is not None and hit.kind == "scene" and hit.segment == 0 and hit.part in HAND_GROUP
    S, seg = checker.path_samples(np.stack([HOME, q1]))
    assert np.abs(np.diff(S, axis=0)).max() <= ONE_DEG + 1e-9
    free = [checker.check(s) is None for s in S]
    assert free.index(False) == hit.index
    np.testing.assert_array_equal(hit.q, S[hit.index])
    # brute force on a 10x finer sweep: the first collision is less than 1 degree before the report
    fine = np.linspace(0, 1.2, 1200 * 2 + 1)
    Qf = np.repeat(HOME[None], len(fine), axis=0)
    Qf[:, 0] = fine
    first = checker.first_collision(Qf)
    assert first is not None and checker.check_all(Qf).index == first
    assert fine[first] <= hit.q[0] <= fine[first] + ONE_DEG + 1e-9
    # the same motion as a 100 Hz jerk-limited trajectory: thinned, same verdict
    traj = plan_joint_motion(HOME, q1, [2.175] * 4 + [2.61] * 3, [15, 7.5, 10, 12.5, 15, 20, 20],
                             [7500, 3750, 5000, 6250, 7500, 10000, 10000], speed_factor=0.5, dt=0.01)
    hit2 = checker.check_path(traj.positions)
    assert hit2 is not None and hit2.part in HAND_GROUP
    assert fine[first] - 1e-9 <= hit2.q[0] <= fine[first] + ONE_DEG + 1e-9
    assert np.all(traj.positions[hit2.segment, 0] <= hit2.q[0] + 1e-12)
    assert checker.first_collision(np.stack([HOME, HOME])) is None


def test_path_samples_respect_the_bounds(checker):
    rng = np.random.default_rng(5)
    Q = rng.uniform(PANDA_Q_MIN, PANDA_Q_MAX, (5, 7))
    kin = checker.robot.kin
    for step, tcp in [(ONE_DEG, 0.01), (ONE_DEG, None), (math.radians(3), 0.02)]:
        S, seg = checker.path_samples(Q, step, tcp)
        np.testing.assert_array_equal(S[0], Q[0])
        np.testing.assert_array_equal(S[-1], Q[-1])
        assert np.abs(np.diff(S, axis=0)).max() <= step + 1e-9
        if tcp is not None:
            assert np.linalg.norm(np.diff(kin.fk_positions(S), axis=0), axis=1).max() <= tcp + 1e-9
        # every sample lies on its segment of the polyline
        assert np.all(np.diff(seg) >= 0) and seg.min() == 0 and seg.max() == len(Q) - 2
        a, b = Q[seg], Q[seg + 1]
        alpha = np.einsum("ij,ij->i", S - a, b - a) / np.einsum("ij,ij->i", b - a, b - a)
        np.testing.assert_allclose(a + alpha[:, None] * (b - a), S, atol=1e-9)
        assert np.all((alpha >= -1e-12) & (alpha <= 1 + 1e-12))
    # a dense trajectory is thinned, yet every one of its rows is within the bound of a sample
    traj = plan_joint_motion(HOME, Q[0], [2.175] * 4 + [2.61] * 3, [15, 7.5, 10, 12.5, 15, 20, 20],
                             [7500, 3750, 5000, 6250, 7500, 10000, 10000], speed_factor=0.5, dt=0.002)
    S, _ = checker.path_samples(traj.positions)
    assert len(S) < len(traj.positions) / 3
    assert np.abs(np.diff(S, axis=0)).max() <= ONE_DEG + 1e-9
    gap = np.abs(traj.positions[:, None, :] - S[None]).max(axis=2).min(axis=1)
    assert gap.max() <= ONE_DEG
    # plain densification keeps every row
    D, dseg = densify_joint_path(Q, ONE_DEG)
    assert np.abs(np.diff(D, axis=0)).max() <= ONE_DEG + 1e-9
    assert all(any(np.array_equal(q, d) for d in D) for q in Q) and dseg[-1] == len(Q) - 2


# ---------------------------------------------------------------------------- scene


def test_octree_encoding_matches_point_in_voxel():
    rng = np.random.default_rng(2)
    for _ in range(3):
        base = rng.integers(-40, 40, 3)
        cells = rng.integers(0, 12, (300, 3)) + base
        solid = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3) + (base // 8) * 8 + 16
        cells = np.unique(np.concatenate([cells, solid]), axis=0)  # an aligned 8^3 block merges into one leaf
        data, n = _octree_data(cells + 32768)
        assert n == len(cells)
        tree = fcl.CollisionObject(fcl.OcTree(VOXEL, data), fcl.Transform())
        occupied = {tuple(c) for c in cells}
        pts = (base + rng.uniform(-2, 30, (1500, 3))) * VOXEL
        f = pts / VOXEL
        away = np.all(np.abs(f - np.rint(f)) > 0.01, axis=1)  # not on a cell face
        for x in pts[away]:
            truth = tuple(np.floor(x / VOXEL).astype(int)) in occupied
            probe = fcl.CollisionObject(fcl.Sphere(1e-5), fcl.Transform(x))
            assert (fcl.collide(tree, probe) > 0) == truth


def test_unknown_near_occupied_from_a_grid(robot):
    g = OccupancyGrid(GridConfig(lo_m=(0, 0, 0), hi_m=(0.4, 0.4, 0.4), voxel_m=VOXEL))
    g.logodds[20, 20, 20] = 2.0  # one occupied cell
    g.logodds[23:, :, :] = -1.0  # seen free beyond x index 22
    g.logodds[0, 0, 0] = 2.0  # a corner cell: the search box is clipped at the grid edge
    occ, unk = grid_scene_voxels(g, 0.05)
    ijk = np.argwhere(np.ones(g.shape, dtype=bool))
    occ_ijk = np.argwhere(g.occupied)
    d = np.linalg.norm(ijk[:, None, :] - occ_ijk[None], axis=2).min(axis=1)
    want = ijk[(d <= 5 + 1e-9) & g.unknown.reshape(-1)]
    np.testing.assert_allclose(np.sort(occ, axis=0), np.sort(g.centers(occ_ijk), axis=0))
    assert len(unk) == len(want) and len(unk) > 300
    got = {tuple(c) for c in np.rint(unk / VOXEL - 0.5).astype(int)}
    assert got == {tuple(c) for c in want}
    assert len(grid_scene_voxels(g, 0.0)[1]) == 0
    ch = CollisionChecker(robot)
    ch.set_scene_from_grid(g)
    assert ch.scene_voxels == len(occ) + len(unk)
    ch_off = CollisionChecker(robot, CollisionConfig(unknown_as_occupied=False))
    ch_off.set_scene_from_grid(g)
    assert ch_off.scene_voxels == len(occ)


def test_unknown_in_the_object_box_counts_when_asked():
    """object_box_m: a part nobody has seen yet, 10 cm from any seen surface, is inside the box around
    the seen object, so it is solid; with the option off only the 5 cm shell is."""
    g = OccupancyGrid(GridConfig(lo_m=(0, 0, 0), hi_m=(0.4, 0.4, 0.4), voxel_m=VOXEL))
    g.logodds[:] = -1.0  # all seen free ...
    g.logodds[10:30, 10:12, 5:20] = 2.0  # ... but a seen plate
    g.logodds[10:30, 20:30, 5:25] = 0.0  # and an unseen block 8 cm behind it
    far = g.centers(np.array([[20, 25, 22]]))[0]
    _, shell = grid_scene_voxels(g, 0.05)
    assert len(shell) == 0  # the unseen block is 8 cm behind the plate: out of the 5 cm shell
    _, boxed = grid_scene_voxels(g, 0.05, object_box_m=0.15)
    assert np.min(np.linalg.norm(boxed - far, axis=1)) < 1e-9
    assert np.all(boxed[:, 1] <= g.centers(np.array([[0, 11 + 15, 0]]))[0, 1] + 1e-9)  # the box, not the grid


# ---------------------------------------------------------------------------- pybullet


@pytest.fixture(scope="module")
def bullet():
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(URDF, useFixedBase=True, physicsClientId=cid)
        joints, links = {}, {"panda_link0": -1}
        for j in range(p.getNumJoints(body, physicsClientId=cid)):
            info = p.getJointInfo(body, j, physicsClientId=cid)
            joints[info[1].decode()] = j
            links[info[12].decode()] = j
        yield cid, body, joints, links
    finally:
        p.disconnect(cid)


def set_q(cid, body, joints, q):
    for name, v in zip(PANDA_JOINT_NAMES, q):
        p.resetJointState(body, joints[name], float(v), physicsClientId=cid)
    for name in ("panda_finger_joint1", "panda_finger_joint2"):  # locked at neutral, like the model
        p.resetJointState(body, joints[name], 0.0, physicsClientId=cid)


def test_scene_verdicts_agree_with_pybullet_distances(bullet):
    """A 4 cm voxel cube near a random part: collision iff pybullet's distance < margin."""
    cid, body, joints, links = bullet
    robot = RobotCollisionModel(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye(), camera_box_m=None, sweep_gripper=False)
    ch = CollisionChecker(robot, CollisionConfig(margin_m=0.02, floor_margin_m=0.0, self_collision=False))
    half = 0.02
    cube = p.createMultiBody(0, p.createCollisionShape(p.GEOM_BOX, halfExtents=[half] * 3, physicsClientId=cid),
                             physicsClientId=cid)
    rng = np.random.default_rng(0)
    hits = misses = 0
    try:
        for _ in range(200):
            q = rng.uniform(PANDA_Q_MIN, PANDA_Q_MAX)
            ch.clear_scene()
            if ch.check(q) is not None:  # under the floor: not this test's business
                continue
            set_q(cid, body, joints, q)
            i = int(rng.integers(1, len(robot.parts)))
            T = robot.part_poses(q)[i]
            v = robot.parts[i].vertices[rng.integers(len(robot.parts[i].vertices))]
            c = np.round((T[:3, :3] @ v + T[:3, 3] + rng.normal(size=3) * 0.05) / VOXEL) * VOXEL
            p.resetBasePositionAndOrientation(cube, c.tolist(), [0, 0, 0, 1], physicsClientId=cid)
            pts = [cp for cp in p.getClosestPoints(body, cube, 0.2, physicsClientId=cid) if cp[3] != -1]
            d = min((cp[8] for cp in pts), default=1.0)
            if abs(d - 0.02) < 0.002:  # the inflated hulls overshoot the margin by <= 7 %
                continue
            ch.set_scene(block(c - half, (4, 4, 4)), VOXEL)
            hit = ch.check(q)
            assert (hit is not None) == (d < 0.02), (q, d, hit)
            hits += hit is not None
            misses += hit is None
    finally:
        p.removeBody(cube, physicsClientId=cid)
    assert hits > 30 and misses > 30


# ---------------------------------------------------------------------------- validation


def test_invalid_inputs_are_rejected(checker, robot):
    with pytest.raises(ValueError, match="q"):
        checker.check(np.zeros(6))
    with pytest.raises(ValueError, match="NaN"):
        checker.check(np.full(7, np.nan))
    with pytest.raises(ValueError, match="Q"):
        checker.first_collision(np.zeros((3, 6)))
    with pytest.raises(ValueError, match="occupied_xyz"):
        checker.set_scene(np.zeros((4, 2)), VOXEL)
    with pytest.raises(ValueError, match="unknown_xyz"):
        checker.set_scene(np.zeros((1, 3)), VOXEL, np.full((1, 3), np.inf))
    with pytest.raises(ValueError, match="voxel_m"):
        checker.set_scene(np.zeros((1, 3)), 0.0)
    with pytest.raises(ValueError, match="lattice"):
        checker.set_scene(np.array([[0.0, 0, 0], [0.0153, 0, 0]]), VOXEL)
    with pytest.raises(ValueError, match="max_joint_step_rad"):
        checker.check_path(np.zeros((2, 7)), max_joint_step_rad=0.0)
    with pytest.raises(ValueError, match="max_tcp_step_m"):
        checker.check_path(np.zeros((2, 7)), max_tcp_step_m=-1.0)
    with pytest.raises(ValueError, match="too small"):
        checker.check_path(np.stack([HOME, PANDA_Q_READY]), max_joint_step_rad=1e-9)
    with pytest.raises(ValueError, match="margin_m"):
        CollisionConfig(margin_m=-0.01)
    with pytest.raises(ValueError, match="camera_box_m"):
        CollisionConfig(camera_box_m=(0.09, 0.0, 0.025))
    with pytest.raises(ValueError, match="unknown_near_m"):
        CollisionConfig(unknown_near_m=float("nan"))
    with pytest.raises(ValueError, match="radius_m"):
        TorchShape(radius_m=0.0, length_m=0.2, T_flange_torch=np.eye(4))
    with pytest.raises(ValueError, match="T_flange_torch"):
        TorchShape(radius_m=0.01, length_m=0.2, T_flange_torch=np.eye(3))
    with pytest.raises(ValueError, match="unknown_near_m"):
        grid_scene_voxels(OccupancyGrid(GridConfig()), -1.0)
    with pytest.raises(ValueError, match="robot"):
        CollisionChecker("panda")
    with pytest.raises(ValueError, match="urdf_path"):
        RobotCollisionModel(URDF + ".missing", PANDA_JOINT_NAMES, FLANGE, hand_eye())


def test_finger_hulls_cover_the_open_gripper(robot, bullet):
    """The kinematic model holds the fingers closed; the swept hulls still contain the fingers of a
    gripper opened to 4 cm each (placed by pybullet), which the closed hulls do not."""
    cid, body, joints, links = bullet
    q = PANDA_Q_READY
    set_q(cid, body, joints, q)
    closed = RobotCollisionModel(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye(), sweep_gripper=False)
    try:
        for name in ("panda_finger_joint1", "panda_finger_joint2"):
            p.resetJointState(body, joints[name], 0.04, physicsClientId=cid)
        for finger in ("panda_leftfinger", "panda_rightfinger"):
            st = p.getLinkState(body, links[finger], computeForwardKinematics=True, physicsClientId=cid)
            R = np.array(p.getMatrixFromQuaternion(st[5])).reshape(3, 3)
            V = closed.parts[closed.part_names.index(finger)].vertices @ R.T + np.array(st[4])  # the open finger
            assert robot.on_robot(V, q, 1e-6).all(), finger
            assert not closed.on_robot(V, q, 1e-6).all(), finger
    finally:
        for name in ("panda_finger_joint1", "panda_finger_joint2"):
            p.resetJointState(body, joints[name], 0.0, physicsClientId=cid)


def test_static_boxes_of_the_cell_are_obstacles(robot):
    from planners.motion.collision import StaticBox

    hand = robot.part_poses(PANDA_Q_READY)[robot.part_names.index("panda_hand")][:3, 3]
    stand = StaticBox(name="stand", center_m=tuple(hand + [0, 0, -0.05]), size_m=(0.1, 0.1, 0.04))
    hit = CollisionChecker(robot, CollisionConfig(static_boxes=[stand])).check(PANDA_Q_READY)
    assert hit is not None and hit.kind == "static" and hit.other == "stand"
    far = stand.model_copy(update={"center_m": (hand[0], hand[1] + 0.6, 0.05)})
    assert CollisionChecker(robot, CollisionConfig(static_boxes=[far])).check(PANDA_Q_READY) is None
    with pytest.raises(ValueError):
        CollisionConfig(static_boxes=[{"name": "x", "center_m": [0, 0, 0], "size_m": [0, 1, 1]}])


def test_the_batched_check_gives_every_row_the_single_verdict(robot):
    """free(Q) is the cut planner's check of thousands of configurations at once; it must say for
    every row what check(q) says (floor, static box, scene with its distance-map shortcut, self)."""
    from planners.motion.collision import StaticBox

    hand = robot.part_poses(HOME)[robot.part_names.index("panda_hand")][:3, 3]
    stand = StaticBox(name="stand", center_m=(0.5, -0.4, 0.1), size_m=(0.2, 0.2, 0.2))
    torch = TorchShape(radius_m=0.015, length_m=0.2, T_flange_torch=np.eye(4))
    ch = CollisionChecker(RobotCollisionModel(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye(), torch=torch),
                          CollisionConfig(static_boxes=[stand]))
    ch.set_scene(block(np.floor(hand / VOXEL) * VOXEL - [0.1, 0.1, 0.25], (20, 20, 6)), VOXEL)  # a slab under the hand
    rng = np.random.default_rng(3)
    Q = np.clip(np.vstack([HOME + rng.normal(0.0, 0.5, (400, 7)), rng.uniform(PANDA_Q_MIN, PANDA_Q_MAX, (400, 7))]),
                PANDA_Q_MIN, PANDA_Q_MAX)
    single = [ch.check(q) for q in Q]
    kinds = {None if h is None else h.kind for h in single}
    assert kinds == {None, "floor", "static", "scene", "self"}, kinds  # every branch of the check is met
    np.testing.assert_array_equal(ch.free(Q), [h is None for h in single])
    ch.clear_scene()
    np.testing.assert_array_equal(ch.free(Q[:50]), [ch.check(q) is None for q in Q[:50]])
    with pytest.raises(ValueError):
        ch.free(np.full((2, 7), np.nan))


def test_the_balls_of_a_part_contain_it(robot):
    """The distance-map shortcut of free() is only as safe as its balls: every point of every
    inflated part lies in one of its balls."""
    from planners.motion.collision import _ball_cover, _inflate

    rng = np.random.default_rng(7)
    for part in robot.parts:
        v, f = _inflate(part.vertices, 0.02)
        c, r = _ball_cover(v, f)
        w = rng.dirichlet(np.full(len(v), 0.3), size=3000)  # points inside the hull, many near its faces
        pts = np.vstack([w @ v, v])
        d = np.linalg.norm(pts[:, None, :] - c[None], axis=2)
        assert (d <= r[None] + 1e-9).any(axis=1).all(), part.name
        assert len(c) >= 1 and r.max() <= np.linalg.norm(np.ptp(v, axis=0)) / 2 + 1e-9


def test_hulls_are_computed_once_per_geometry_and_shared_read_only():
    """Each cut plan builds its own checker for the same arm: the hulls (and their inflations and
    ball covers) come from a memo keyed by the points' contents, read-only since every checker
    shares them; different points get their own hull."""
    from planners.motion.collision import _hull, _inflate

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    v, f = _hull(pts)
    assert _hull(pts.copy())[0] is v, "same contents: the same hull"
    assert not v.flags.writeable and not f.flags.writeable
    with pytest.raises(ValueError):
        v[0, 0] = 1.0
    other = _hull(pts * 2.0)[0]
    np.testing.assert_allclose(np.sort(other, axis=0), np.sort(v * 2.0, axis=0))
    assert _inflate(v, 0.01)[0] is _inflate(v.copy(), 0.01)[0] and _inflate(v, 0.02)[0] is not _inflate(v, 0.01)[0]
