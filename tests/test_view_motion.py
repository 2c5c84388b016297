"""Camera moves planned with IK + FCL + Ruckig: straight when clear, via waypoints around an obstacle,
refused with a reason when nothing is clear; and the arm's own returns are recognised."""

from __future__ import annotations

import math
import os

import numpy as np
import pybullet_data
import pytest

from planners.motion.collision import CollisionChecker, RobotCollisionModel
from planners.motion.ik import Unreachable
from planners.motion.kinematics import Kinematics
from planners.motion.limits import (PANDA_JOINT_NAMES, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK, PANDA_MAX_VELOCITY,
                                    PANDA_Q_MAX, PANDA_Q_MIN)
from planners.motion.view_motion import ViewMotionPlanner
from planners.views import look_at_rotations, poses_from

URDF = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
HOME = np.array([0.0, -0.7, 0.0, -1.7, 0.0, 1.5, 0.785])  # the twin's home


def hand_eye() -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.07, 0.0, 0.05]
    return T


@pytest.fixture(scope="module")
def robot():
    return RobotCollisionModel(URDF, PANDA_JOINT_NAMES, "panda_hand", hand_eye())


@pytest.fixture()
def planner(robot):
    kin = Kinematics(URDF, PANDA_JOINT_NAMES, "panda_hand", hand_eye(), lower=PANDA_Q_MIN, upper=PANDA_Q_MAX)
    checker = CollisionChecker(robot)
    return ViewMotionPlanner(kin, PANDA_MAX_VELOCITY, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK, checker,
                             park_q=HOME), checker


def view(eye, target) -> np.ndarray:
    eye = np.asarray(eye, float)[None]
    return poses_from(eye, look_at_rotations(eye, np.asarray(target, float)))


def slab(lo, hi, voxel=0.01) -> np.ndarray:
    axes = [np.arange(a + voxel / 2, b, voxel) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_clear_move_goes_straight_and_reaches_the_pose(planner):
    mp, checker = planner
    T = view([0.45, 0.25, 0.45], [0.55, 0.0, 0.1])
    mv = mp.plan(HOME, T)
    assert mv.via == "direct" and mv.index == 0 and mv.tried == 1
    T_end = mp.kin.fk(mv.path.positions[-1])
    assert np.linalg.norm(T_end[:3, 3] - T[0][:3, 3]) < 1e-3
    assert math.degrees(math.acos(np.clip(T_end[:3, 2] @ T[0][:3, 2], -1, 1))) < 0.5
    assert checker.check_path(mv.path.positions) is None


def test_a_wall_in_the_way_is_gone_around_and_the_path_is_clear(planner):
    mp, checker = planner
    start = mp.plan(HOME, view([0.45, 0.30, 0.45], [0.5, 0.3, 0.0])).q_goal
    goal = view([0.45, -0.30, 0.45], [0.5, -0.3, 0.0])
    wall = slab([0.25, -0.05, 0.0], [0.75, 0.05, 0.42])  # a wall between the views, just below the camera
    checker.set_scene(wall, 0.01)
    straight = mp._path([start, mp._ik(goal[0], start)])
    assert checker.check_path(straight.positions) is not None  # the straight joint motion would hit it
    mv = mp.plan(start, goal)
    assert mv.via != "direct"
    assert checker.check_path(mv.path.positions) is None
    assert np.linalg.norm(mp.kin.fk(mv.path.positions[-1])[:3, 3] - goal[0][:3, 3]) < 1e-3


def test_no_clear_candidate_is_refused_with_the_reasons(planner):
    mp, checker = planner
    inside = view([0.5, 0.0, 0.3], [0.5, 0.0, 0.0])  # the camera would sit inside the block
    far = view([2.5, 0.0, 0.3], [3.0, 0.0, 0.0])
    checker.set_scene(slab([0.4, -0.1, 0.2], [0.6, 0.1, 0.4]), 0.01)
    with pytest.raises(Unreachable, match=r"none of 2 candidate views .*1 beyond reach, 1 no collision-free IK"):
        mp.plan(HOME, np.concatenate([inside, far]))
    with pytest.raises(ValueError, match="poses must have shape"):
        mp.plan(HOME, np.zeros((0, 4, 4)))


def test_a_start_inside_a_new_obstacle_may_back_out(planner):
    mp, checker = planner
    T_home = mp.kin.fk(HOME)
    # a small plate of voxels just in front of the camera at home: the arm may back out, not go through
    c = T_home[:3, 3] + 0.03 * T_home[:3, 2]
    checker.set_scene(slab(c - 0.015, c + 0.015), 0.01)
    assert checker.in_collision(HOME)
    back = T_home.copy()
    back[:3, 3] -= 0.15 * T_home[:3, 2]
    mv = mp.plan(HOME, back[None])
    assert not checker.in_collision(mv.path.positions[-1])
    through = T_home.copy()
    through[:3, 3] += 0.12 * T_home[:3, 2]
    with pytest.raises(Unreachable):
        mp.plan(HOME, through[None])


def test_returns_on_the_arm_are_recognised(robot):
    P = robot.part_poses(HOME)
    names = robot.part_names
    T = P[names.index("panda_link4")]
    on_link = T[:3, 3] + T[:3, :3] @ robot.parts[names.index("panda_link4")].vertices.mean(axis=0)
    away = on_link + [0.0, 0.0, 0.3]
    mask = robot.on_robot(np.array([on_link, away, [0.6, 0.0, 0.05]]), HOME, 0.02)
    assert mask.tolist() == [True, False, False]
    with pytest.raises(ValueError):
        robot.on_robot(np.zeros((3, 2)), HOME)


def _rolled(T: np.ndarray, deg: float) -> np.ndarray:
    """The camera pose T turned by ``deg`` about its optical axis."""
    a = math.radians(deg)
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                                        [0.0, 0.0, 1.0]])
    return out


def _tight_wrist() -> Kinematics:
    """The Panda with its last joint held within 0.3 rad of home: most rolls are out of reach."""
    lo, hi = PANDA_Q_MIN.copy(), PANDA_Q_MAX.copy()
    lo[6], hi[6] = HOME[6] - 0.3, HOME[6] + 0.3
    return Kinematics(URDF, PANDA_JOINT_NAMES, "panda_hand", hand_eye(), lower=lo, upper=hi)


def _roll_deg(R_got: np.ndarray, R_want: np.ndarray) -> float:
    """Angle between the image x axes, modulo the half turn (the image frames the same rectangle)."""
    c = abs(float(R_got[:, 0] @ R_want[:, 0]))
    return math.degrees(math.acos(min(c, 1.0)))


def test_a_framed_scan_view_keeps_the_planned_roll_and_a_free_one_need_not(robot):
    """The D435's image is 87 x 58 deg: the roll the planner scored is the one the arm must take."""
    kin = Kinematics(URDF, PANDA_JOINT_NAMES, "panda_hand", hand_eye(), lower=PANDA_Q_MIN, upper=PANDA_Q_MAX)
    T = view([0.45, 0.25, 0.45], [0.55, 0.0, 0.1])[0]
    rolled = _rolled(T, 90.0)
    got = {}
    for framed in (False, True):
        mp = ViewMotionPlanner(kin, PANDA_MAX_VELOCITY, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK, CollisionChecker(robot),
                               park_q=HOME, framed=framed)
        for name, want in (("planned", T), ("rolled", rolled)):
            T_end = kin.fk(mp.plan(HOME, want[None]).path.positions[-1])
            assert np.linalg.norm(T_end[:3, 3] - want[:3, 3]) < 1e-3
            got[framed, name] = _roll_deg(T_end[:3, :3], want[:3, :3])
    assert got[True, "planned"] < 0.5 and got[True, "rolled"] < 0.5
    # free roll: IK stays near the start's roll, so at most one of two rolls 90 deg apart comes out as asked
    assert max(got[False, "planned"], got[False, "rolled"]) > 30.0


def test_a_framed_view_the_arm_cannot_roll_to_falls_back_to_any_roll(robot):
    tight = _tight_wrist()
    mp = ViewMotionPlanner(tight, PANDA_MAX_VELOCITY, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK, CollisionChecker(robot),
                           park_q=HOME, framed=True)
    T = view([0.45, 0.25, 0.45], [0.55, 0.0, 0.1])[0]
    rolls = []
    for deg in range(0, 180, 30):
        want = _rolled(T, deg)
        R = want[:3, :3]
        T_end = tight.fk(mp.plan(HOME, want[None]).path.positions[-1])  # always reached...
        assert np.linalg.norm(T_end[:3, 3] - want[:3, 3]) < 1e-3 and T_end[:3, 2] @ want[:3, 2] > 0.9999
        rolls.append(_roll_deg(T_end[:3, :3], R))
    assert min(rolls) < 0.5 and max(rolls) > 20.0  # ...as asked where the wrist allows, else at another roll


def test_a_framed_plan_prefers_a_lower_ranked_view_at_its_scored_roll(robot):
    """The ranking holds for the image each pose was scored with: a better-ranked pose the wrist can
    reach only at another roll is a different, unscored view."""
    tight = _tight_wrist()
    args = (tight, PANDA_MAX_VELOCITY, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK, CollisionChecker(robot))
    exact = ViewMotionPlanner(*args, park_q=HOME, free_roll=False)
    T = view([0.45, 0.25, 0.45], [0.55, 0.0, 0.1])[0]
    rolled, at_roll = [], []
    for deg in range(0, 180, 15):
        want = _rolled(T, deg)
        rolled.append(want)
        half = _rolled(want, 180.0)
        at_roll.append(any(exact._ik(P, HOME) is not None for P in (want, half)))
    at_roll = np.array(at_roll)
    assert at_roll.any() and not at_roll.all()  # the limited wrist reaches some rolls, not all
    order = np.concatenate([np.flatnonzero(~at_roll), np.flatnonzero(at_roll)])  # the unreachable ones ranked first
    poses = np.array(rolled)[order]
    free = ViewMotionPlanner(*args, park_q=HOME).plan(HOME, poses)
    framed = ViewMotionPlanner(*args, park_q=HOME, framed=True).plan(HOME, poses)
    assert free.index == 0  # any roll: the best-ranked pose, at a roll it was not scored at
    assert framed.index == int((~at_roll).sum())  # the first pose reachable at its own roll (or half turn)
    assert _roll_deg(tight.fk(framed.path.positions[-1])[:3, :3], poses[framed.index][:3, :3]) < 0.5
