"""Kinematics (Pinocchio) against pybullet, and camera IK round trips.

Tests of: planners.motion.kinematics, planners.motion.chain_kernel, planners.motion.ik_batch, configs.chain.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pybullet as p
import pybullet_data
import pytest

from planners.motion.ik import IKResult, Unreachable, solve_camera_ik, solve_camera_ik_many
from planners.motion.kinematics import Kinematics
from planners.motion.limits import (
    PANDA_JOINT_NAMES,
    PANDA_Q_MAX,
    PANDA_Q_MAX_URDF,
    PANDA_Q_MIN,
    PANDA_Q_MIN_URDF,
    PANDA_Q_READY,
)

URDF = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
FLANGE = "panda_hand"
MARGIN = 0.05


def hand_eye() -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.05, 0.0, 0.04]  # camera z along flange z
    return T


def rot_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return math.acos(min(1.0, max(-1.0, c)))


def axis_angle(a: np.ndarray, b: np.ndarray) -> float:
    return math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b))


@pytest.fixture(scope="module")
def kin() -> Kinematics:
    return Kinematics(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye())


@pytest.fixture(scope="module")
def bullet():
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(URDF, useFixedBase=True, physicsClientId=cid)
        joints, links = {}, {}
        for j in range(p.getNumJoints(body, physicsClientId=cid)):
            info = p.getJointInfo(body, j, physicsClientId=cid)
            joints[info[1].decode()] = j
            links[info[12].decode()] = j  # pybullet link index == index of its parent joint
        yield cid, body, joints, links
    finally:
        p.disconnect(cid)


def random_q(kin: Kinematics, n: int, margin: float, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(kin.lower + margin, kin.upper - margin, size=(n, kin.dof))


# ---------------------------------------------------------------------------- model


def test_limits_from_urdf(kin):
    np.testing.assert_allclose(kin.lower, PANDA_Q_MIN_URDF)
    np.testing.assert_allclose(kin.upper, PANDA_Q_MAX_URDF)
    k2 = Kinematics(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye(), lower=PANDA_Q_MIN, upper=PANDA_Q_MAX)
    np.testing.assert_allclose(k2.lower, PANDA_Q_MIN)
    np.testing.assert_allclose(k2.upper, PANDA_Q_MAX)


def test_a_driver_s_arm_model_gives_its_limits_and_hand_eye_to_the_kinematics():
    from drivers.interfaces import ArmModel

    lo, hi = PANDA_Q_MIN + 0.1, PANDA_Q_MAX - 0.1  # a driver's margin inside the published limits
    T = hand_eye()
    T[:3, 3] = [0.07, 0.01, 0.05]
    z = np.zeros(7)
    model = ArmModel(urdf_path=URDF, base_link="panda_link0", flange_link=FLANGE, joint_names=PANDA_JOINT_NAMES,
                     lower=lo, upper=hi, max_velocity=z, max_acceleration=z, max_jerk=z, T_flange_cam=T)
    k = Kinematics.from_arm_model(model)
    np.testing.assert_allclose(k.lower, lo)
    np.testing.assert_allclose(k.upper, hi)
    q = np.asarray(PANDA_Q_READY, dtype=np.float64)
    np.testing.assert_allclose(k.fk(q, "cam"), k.fk(q, "flange") @ T, atol=1e-12)


def test_bad_names_rejected():
    with pytest.raises(ValueError, match="not_a_link"):
        Kinematics(URDF, PANDA_JOINT_NAMES, "not_a_link", hand_eye())
    with pytest.raises(ValueError, match="panda_joint9"):
        Kinematics(URDF, (*PANDA_JOINT_NAMES[:6], "panda_joint9"), FLANGE, hand_eye())
    bad = hand_eye()
    bad[:3, :3] *= 2.0
    with pytest.raises(ValueError, match="T_flange_cam"):
        Kinematics(URDF, PANDA_JOINT_NAMES, FLANGE, bad)


@pytest.mark.parametrize("link", ["panda_link8", "panda_hand"])
def test_fk_matches_pybullet(kin, bullet, link):
    cid, body, joints, links = bullet
    assert link in links
    k = Kinematics(URDF, PANDA_JOINT_NAMES, link, hand_eye())
    for q in random_q(kin, 50, 0.0, seed=1):
        for name, v in zip(PANDA_JOINT_NAMES, q):
            p.resetJointState(body, joints[name], float(v), physicsClientId=cid)
        st = p.getLinkState(body, links[link], computeForwardKinematics=True, physicsClientId=cid)
        pos_pb = np.array(st[4])  # URDF link frame, not the inertial frame ([0], [1])
        R_pb = np.array(p.getMatrixFromQuaternion(st[5])).reshape(3, 3)
        T = k.fk(q, frame="flange")
        assert np.linalg.norm(T[:3, 3] - pos_pb) < 1e-5
        assert rot_angle(T[:3, :3], R_pb) < 1e-5


def test_camera_is_flange_times_hand_eye(kin):
    for q in random_q(kin, 10, 0.0, seed=2):
        np.testing.assert_allclose(kin.fk(q, "cam"), kin.fk(q, "flange") @ hand_eye(), atol=1e-12)


def test_fk_batch_matches_fk(kin):
    Q = random_q(kin, 40, 0.0, seed=3)
    for frame in ("cam", "flange"):
        B = kin.fk_batch(Q, frame)
        ref = np.stack([kin.fk(q, frame) for q in Q])
        np.testing.assert_allclose(B, ref, atol=1e-12)
        np.testing.assert_allclose(kin.fk_positions(Q, frame), ref[:, :3, 3], atol=1e-12)


def test_link_poses_batch_matches_link_poses(kin):
    links = ["panda_link1", "panda_link4", "panda_link7", "panda_hand", "panda_leftfinger"]
    Q = np.random.default_rng(5).uniform(kin.lower, kin.upper, (20, kin.dof))
    P = kin.link_poses_batch(Q, links)
    assert P.shape == (20, len(links), 4, 4)
    for q, got in zip(Q, P):
        np.testing.assert_allclose(got, kin.link_poses(q, links), atol=1e-12)
    assert kin.link_poses_batch(Q[:0], links).shape == (0, len(links), 4, 4)
    with pytest.raises(ValueError):
        kin.link_poses_batch(Q[:, :6], links)


def test_jacobian_cam_finite_differences(kin):
    eps = 1e-6
    for q in random_q(kin, 5, 0.1, seed=4):
        J = kin.jacobian_cam(q)
        assert J.shape == (6, 7)
        T0 = kin.fk(q)
        for i in range(7):
            dq = np.zeros(7)
            dq[i] = eps
            T1 = kin.fk(q + dq)
            v = (T1[:3, 3] - T0[:3, 3]) / eps
            dR = T1[:3, :3] @ T0[:3, :3].T  # world-frame rotation increment
            w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (2 * eps)
            np.testing.assert_allclose(J[:3, i], v, atol=1e-5)
            np.testing.assert_allclose(J[3:, i], w, atol=1e-5)


def test_fk_rejects_bad_input(kin):
    with pytest.raises(ValueError, match="shape"):
        kin.fk(np.zeros(6))
    with pytest.raises(ValueError, match="NaN"):
        kin.fk(np.full(7, np.nan))
    with pytest.raises(ValueError, match="frame"):
        kin.fk(PANDA_Q_READY, frame="tcp")


# ---------------------------------------------------------------------------- IK


def test_ik_round_trip_free_roll(kin):
    Q = random_q(kin, 100, MARGIN + 0.05, seed=10)
    T_targets = kin.fk_batch(Q)
    lo, hi = kin.lower + MARGIN, kin.upper - MARGIN
    times = []
    for T_t in T_targets:
        t0 = time.perf_counter()
        r = solve_camera_ik(kin, T_t, PANDA_Q_READY, free_roll=True, margin=MARGIN)
        times.append(time.perf_counter() - t0)
        assert isinstance(r, IKResult)
        assert np.all(r.q >= lo - 1e-12) and np.all(r.q <= hi + 1e-12)
        T = kin.fk(r.q)
        assert np.linalg.norm(T[:3, 3] - T_t[:3, 3]) < 1e-3
        assert math.degrees(axis_angle(T[:3, 2], T_t[:3, 2])) < 0.5
        assert r.position_error_m < 1e-4 and r.angle_error_rad < 1e-3
    print(f"free-roll IK: median {1e3 * np.median(times):.2f} ms, max {1e3 * max(times):.2f} ms")


def test_ik_round_trip_full_pose(kin):
    Q = random_q(kin, 30, MARGIN + 0.05, seed=11)
    lo, hi = kin.lower + MARGIN, kin.upper - MARGIN
    for T_t in kin.fk_batch(Q):
        r = solve_camera_ik(kin, T_t, PANDA_Q_READY, free_roll=False, margin=MARGIN)
        assert np.all(r.q >= lo - 1e-12) and np.all(r.q <= hi + 1e-12)
        T = kin.fk(r.q)
        assert np.linalg.norm(T[:3, 3] - T_t[:3, 3]) < 1e-3
        assert math.degrees(rot_angle(T[:3, :3], T_t[:3, :3])) < 0.5


def test_ik_near_seed_uses_seed(kin):
    q_true = PANDA_Q_READY + np.array([0.1, -0.05, 0.08, 0.1, -0.1, 0.05, 0.2])
    r = solve_camera_ik(kin, kin.fk(q_true), PANDA_Q_READY, free_roll=False)
    assert r.seed_index == 0
    assert r.iterations < 20
    # 7 joints, 6-D task: the solver may slide along the self-motion, but stays near the seed
    T = kin.fk(r.q)
    assert np.linalg.norm(T[:3, 3] - kin.fk(q_true)[:3, 3]) < 1e-3
    assert np.abs(r.q - PANDA_Q_READY).max() < 0.5


def test_ik_free_roll_ignores_roll(kin):
    T_t = kin.fk(PANDA_Q_READY + 0.1)
    Rz = np.eye(4)
    c, s = math.cos(1.0), math.sin(1.0)
    Rz[:2, :2] = [[c, -s], [s, c]]
    r0 = solve_camera_ik(kin, T_t, PANDA_Q_READY)
    r1 = solve_camera_ik(kin, T_t @ Rz, PANDA_Q_READY)  # same position and axis, other roll
    np.testing.assert_allclose(r0.q, r1.q, atol=1e-9)


def test_ik_solution_respects_margin(kin):
    # target reached by a configuration with joint 4 close to its upper limit (0) and joint 6
    # close to its lower limit; the seed itself is outside the shrunk range.
    q_edge = np.array([0.3, 0.2, -0.2, -0.02, 0.1, -0.07, 0.5])
    T_t = kin.fk(np.clip(q_edge, kin.lower + 0.06, kin.upper - 0.06))
    margin = 0.05
    r = solve_camera_ik(kin, T_t, q_edge, margin=margin)
    assert np.all(r.q >= kin.lower + margin - 1e-12)
    assert np.all(r.q <= kin.upper - margin + 1e-12)
    assert np.linalg.norm(kin.fk(r.q)[:3, 3] - T_t[:3, 3]) < 1e-3


def test_unreachable_far_pose(kin):
    T_t = np.eye(4)
    T_t[:3, 3] = [2.0, 0.0, 0.5]
    with pytest.raises(Unreachable) as ei:
        solve_camera_ik(kin, T_t, PANDA_Q_READY)
    assert "[2.000 0.000 0.500]" in str(ei.value)
    np.testing.assert_allclose(ei.value.position, [2.0, 0.0, 0.5])


def test_unreachable_within_reach_sphere(kin):
    # 1.35 m above the base, looking straight down: within the reach bound, not reachable.
    T_t = np.diag([1.0, -1.0, -1.0, 1.0])
    T_t[:3, 3] = [0.0, 0.0, 1.35]
    t0 = time.perf_counter()
    with pytest.raises(Unreachable) as ei:
        solve_camera_ik(kin, T_t, PANDA_Q_READY, seeds=8)
    elapsed = time.perf_counter() - t0
    msg = str(ei.value)
    assert "[0.000 0.000 1.350]" in msg and "best residual" in msg and "margin" in msg
    assert ei.value.best_position_error_m > 1e-3
    print(f"unreachable pose, 8 seeds: {1e3 * elapsed:.1f} ms")


def test_ik_rejects_bad_input(kin):
    T_bad = np.eye(4)
    T_bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="T_target_cam"):
        solve_camera_ik(kin, T_bad, PANDA_Q_READY)
    with pytest.raises(ValueError, match="q_seed"):
        solve_camera_ik(kin, np.eye(4), np.zeros(6))
    with pytest.raises(ValueError, match="margin"):
        solve_camera_ik(kin, np.eye(4), PANDA_Q_READY, margin=2.0)


def test_solve_many_returns_first_reachable(kin):
    far = np.eye(4)
    far[:3, 3] = [2.0, 0.0, 0.5]
    up = np.diag([1.0, -1.0, -1.0, 1.0])
    up[:3, 3] = [0.0, 0.0, 1.35]
    ok1 = kin.fk(PANDA_Q_READY + 0.2)
    ok2 = kin.fk(PANDA_Q_READY - 0.2)
    idx, r = solve_camera_ik_many(kin, np.stack([far, up, ok1, ok2]), PANDA_Q_READY)
    assert idx == 2
    assert np.linalg.norm(kin.fk(r.q)[:3, 3] - ok1[:3, 3]) < 1e-3
    with pytest.raises(Unreachable, match="none of 2 candidate"):
        solve_camera_ik_many(kin, np.stack([far, up]), PANDA_Q_READY)


_SLIDER_URDF = """<robot name="slider">
  <link name="base"/><link name="carriage"/><link name="arm"/><link name="tool"/>
  <joint name="slide" type="prismatic"><parent link="base"/><child link="carriage"/>
    <origin xyz="0.1 0 0.2" rpy="0 0 0.3"/><axis xyz="0.6 0 0.8"/><limit lower="-0.5" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="turn" type="revolute"><parent link="carriage"/><child link="arm"/>
    <origin xyz="0 0.2 0" rpy="0.4 0 0"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="bend" type="revolute"><parent link="arm"/><child link="tool"/>
    <origin xyz="0.3 0 0" rpy="0 0.2 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>"""


@pytest.mark.parametrize("chain", ["panda", "slider"])
def test_the_compiled_chain_builds_pinocchio_s_jacobian(chain, kin, tmp_path):
    """The batched IK takes its Jacobian from the compiled chain's joint axes and origins
    (``chain_kernel``): for the Panda, and for a chain with an unaligned prismatic joint (no origin:
    its column is the axis), they give Pinocchio's Jacobian and pose."""
    from planners.motion.ik_batch import _chain

    if chain == "slider":
        path = tmp_path / "slider.urdf"
        path.write_text(_SLIDER_URDF)
        kin = Kinematics(str(path), ["slide", "turn", "bend"], "tool", np.eye(4))
    rng = np.random.default_rng(3)
    Q = rng.uniform(kin.lower, kin.upper, size=(20, kin.dof))
    T, ax, org = _chain(kin, Q, "cam")
    lever = T[:, None, :3, 3] - org
    J_lin = np.where(np.isnan(lever), ax, np.cross(ax, np.nan_to_num(lever)))
    J_ang = np.where(np.isnan(org), 0.0, ax)
    for q, Tk, Jl, Ja in zip(Q, T, J_lin, J_ang):
        T_ref, J_ref = kin.pose_and_jacobian(q)
        np.testing.assert_allclose(Tk, T_ref, atol=1e-12)
        np.testing.assert_allclose(Jl.T, J_ref[:3], atol=1e-12)
        np.testing.assert_allclose(Ja.T, J_ref[3:], atol=1e-12)
    assert np.isnan(org[:, 0]).all() == (chain == "slider")


def test_the_compiled_axis_ik_reaches_its_targets_and_agrees_with_the_full_pose_solve(kin):
    """The free-roll batched IK runs row by row in compiled code (``chain_kernel.axis_ik``; on
    15,000 targets it gave the numpy loop it replaced bit for bit, 1e-13 rad). From seeds 0.3 rad
    off, 95 % of reachable targets converge within the tolerances; the full-pose solve (still the
    numpy loop), asked for the roll the free solve found, stays where it is."""
    from planners.motion.ik_batch import solve_axis_ik_batch

    rng = np.random.default_rng(5)
    Qt = rng.uniform(kin.lower + 0.1, kin.upper - 0.1, size=(300, kin.dof))
    T = kin.fk_batch(Qt)
    Q0 = np.clip(Qt + rng.normal(0.0, 0.3, Qt.shape), kin.lower, kin.upper)
    Q, ok = solve_axis_ik_batch(kin, T[:, :3, 3], T[:, :3, 2], Q0, max_iter=60)
    assert ok.mean() > 0.95
    Tq = kin.fk_batch(Q[ok])
    assert np.abs(Tq[:, :3, 3] - T[ok, :3, 3]).max() < 1e-4
    assert np.einsum("ij,ij->i", Tq[:, :3, 2], T[ok, :3, 2]).min() > np.cos(1e-3)
    # the full-pose (numpy) solve from the same seeds, asked for the roll the free solve found
    Qf, okf = solve_axis_ik_batch(kin, T[ok, :3, 3], T[ok, :3, 2], Q[ok], max_iter=5, x_axes=Tq[:, :3, 0])
    assert okf.all() and np.abs(Qf - Q[ok]).max() < 1e-3


def test_reach_map_never_drops_a_pose_ik_reaches():
    """The capability map is a prefilter: over random camera poses in the cell it must keep every
    one IK solves (with the runner's margin), and it must drop a good share of those it cannot."""
    from planners.motion.reach_map import reach_map_for

    kin = Kinematics(URDF, PANDA_JOINT_NAMES, FLANGE, hand_eye(), lower=PANDA_Q_MIN, upper=PANDA_Q_MAX)
    rmap = reach_map_for(kin)
    assert reach_map_for(kin) is rmap  # built once per arm
    rng = np.random.default_rng(7)
    n = 300
    pos = np.column_stack([rng.uniform(0.0, 0.95, n), rng.uniform(-0.6, 0.6, n), rng.uniform(0.1, 0.8, n)])
    axis = rng.normal(size=(n, 3))
    axis[:, 2] = -np.abs(axis[:, 2])  # looking down or level, as scan views do
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    kept = rmap.reachable(pos, axis)
    reached = np.zeros(n, dtype=bool)
    for k in range(n):  # the reference: one IK solve per pose
        x = np.cross(axis[k], [0.0, 0.0, 1.0])
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(axis[k], x), axis[k], pos[k]
        try:
            solve_camera_ik(kin, T, PANDA_Q_READY, free_roll=True, margin=MARGIN, seeds=6)
            reached[k] = True
        except Unreachable:
            pass
    assert 0 < reached.sum() < n
    assert not (reached & ~kept).any(), "the map dropped a pose IK reaches"
    assert (~reached & ~kept).sum() >= 0.3 * (~reached).sum()
    assert rmap.reachable(np.array([[5.0, 0.0, 0.5]]), np.array([[0.0, 0.0, -1.0]])).tolist() == [False]
