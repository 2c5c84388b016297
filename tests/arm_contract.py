"""The ``drivers.interfaces.Arm`` contract, as plain functions taking an ``ArmUnderTest``: every arm
implementation (the pybullet twin, the franky adapter on franky-sim, later the real robot) must pass
the same cases. Also the harnesses that build each arm (tests/test_arm_contract.py parametrizes over
them) and the embedded franky-sim server.

Not collected by pytest itself (no ``test_`` prefix); imported by the test modules.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
import pinocchio as pin
import trimesh

from drivers.interfaces import Arm, JointTrajectory, TrajectoryError
from planners.motion.trajectory import plan_through

HOME_Q = np.array([0.0, -0.7, 0.0, -1.7, 0.0, 1.5, 0.785])  # the twin's home, inside Panda and FR3 limits
HAND_EYE = {"xyz": [0.07, 0.0, 0.05], "rpy_deg": [0.0, 0.0, 0.0]}  # the twin's default


@dataclass
class ArmUnderTest:
    """An arm plus what the contract needs to judge it from outside the adapter."""

    name: str
    arm: Arm
    truth: Callable[[], np.ndarray]  # joints read from the simulator itself, not through the adapter
    go_to: Callable[[np.ndarray], None]  # bring the arm to q (between cases)
    # make a running execute() fail the way this arm can fail; the fault lasts until ``failed()`` (the
    # test saw execute() end), so how long it must last does not depend on how loaded the machine is
    fault: Callable[[Callable[[], bool]], None]
    tracking_tolerance: float  # execute()'s return on the smooth 2 s test motion
    reach_tolerance: float  # joints vs the last sample once execute() returned
    still_tolerance: float  # how still "did not move" is (a simulator holding position jitters)
    path_tolerance: float  # distance of the measured joints from the planned path
    commands_seen: Callable[[], int] | None = None  # motion commands the simulated robot received
    settle: Callable[[], None] = lambda: None  # until the arm is at rest (a simulated controller's lag)


# ----------------------------------------------------------------------------- helpers
def smooth_trajectory(q0, q1, duration: float, rate: float = 100.0) -> JointTrajectory:
    """Straight line in joint space with a quintic (minimum-jerk) time law."""
    t = np.linspace(0.0, duration, int(round(duration * rate)) + 1)
    s = t / duration
    s = 10 * s**3 - 15 * s**4 + 6 * s**5
    return JointTrajectory(times=t, positions=np.asarray(q0) + s[:, None] * (np.asarray(q1) - np.asarray(q0)))


def planned(arm: Arm, waypoints, speed: float = 0.3) -> JointTrajectory:
    """What the scan runner sends: Ruckig rest-to-rest segments within the arm model's limits."""
    m = arm.model
    p = plan_through(np.asarray(waypoints), m.max_velocity, m.max_acceleration, m.max_jerk, speed_factor=speed,
                     lower=m.lower, upper=m.upper)
    return JointTrajectory(p.times, p.positions, p.velocities)


def run_in_thread(fn, *args) -> tuple[threading.Thread, list]:
    out: list = []

    def target():
        try:
            out.append(fn(*args))
        except BaseException as e:  # noqa: BLE001 - handed to the test thread
            out.append(e)

    th = threading.Thread(target=target, daemon=True)
    th.start()
    return th, out


def wait_until_moving(arm: Arm, q_start: np.ndarray, timeout: float = 60.0) -> None:
    """Until the joints left q_start by 5 mrad: more than a simulated controller settling on it.
    ``timeout`` is a liveness bound (a hang), not a speed requirement."""
    deadline = time.monotonic() + timeout
    while np.max(np.abs(arm.joint_positions() - q_start)) < 5e-3:
        assert time.monotonic() < deadline, "the arm never started moving"
        time.sleep(0.002)


def wait_until_still(joints: Callable[[], np.ndarray], sim_time: Callable[[], float], window_s: float = 0.1,
                     tol: float = 1e-4, timeout: float = 60.0) -> None:
    """Until the joints moved less than ``tol`` over ``window_s`` of the simulator's own time. A
    simulated controller closes its lag exponentially (franky-sim: ~0.2 s, then ~4e-5 rad of jitter);
    a wall-clock sleep would cover less simulated time the more loaded the machine is. ``timeout`` is
    a liveness bound only."""
    deadline = time.monotonic() + timeout
    t_a, q_a = sim_time(), np.array(joints())
    while True:
        assert time.monotonic() < deadline, "the arm never came to rest"
        time.sleep(0.01)
        t_b = sim_time()
        if t_b - t_a < window_s:
            continue
        q_b = np.array(joints())
        if np.max(np.abs(q_b - q_a)) < tol:
            return
        t_a, q_a = t_b, q_b


def franky_sim_still(robot, **kw) -> None:
    """wait_until_still on franky-sim's own joints and MuJoCo clock."""
    wait_until_still(lambda: np.array(robot.inner_state.q), lambda: float(robot.data.time), **kw)


def path_distance(actual: np.ndarray, path: np.ndarray) -> float:
    """Largest distance (max-norm over joints) of measured joints from the piecewise-linear path."""
    a, b = path[:-1], path[1:]
    d = b - a
    L = np.maximum(np.einsum("ij,ij->i", d, d), 1e-18)
    # (N, S) projection of every actual sample on every segment, vectorized
    t = np.clip(np.einsum("nj,sj->ns", actual, d) - np.einsum("sj,sj->s", a, d), 0.0, None) / L
    t = np.minimum(t, 1.0)
    closest = a[None] + t[..., None] * d[None]
    return float(np.min(np.max(np.abs(closest - actual[:, None]), axis=2), axis=1).max())


# ----------------------------------------------------------------------------- the contract
def check_model_and_camera_pose(h: ArmUnderTest) -> None:
    arm = h.arm
    assert isinstance(arm, Arm)
    m = arm.model
    assert len(m.joint_names) == 7 and m.lower.shape == m.upper.shape == (7,)
    assert np.all(m.lower < m.upper)
    for lim in (m.max_velocity, m.max_acceleration, m.max_jerk):
        assert lim.shape == (7,) and np.all(lim > 0)
    assert m.T_flange_cam.shape == (4, 4) and np.allclose(m.T_flange_cam[3], [0, 0, 0, 1])
    # camera_pose() is the URDF's flange composed with the hand-eye, by an independent FK
    model = pin.buildModelFromUrdf(m.urdf_path)
    data = model.createData()
    fid = model.getFrameId(m.flange_link)
    q = arm.joint_positions()
    T = arm.camera_pose()
    pin.framesForwardKinematics(model, data, np.concatenate([q, np.zeros(model.nq - 7)]))
    assert np.allclose(T, data.oMf[fid].homogeneous @ m.T_flange_cam, atol=1e-4)
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)


def check_reach_joint_targets(h: ArmUnderTest) -> None:
    arm = h.arm
    h.go_to(HOME_Q)
    q1 = HOME_Q + np.array([0.4, 0.3, -0.3, 0.4, 0.5, -0.3, 0.6])
    err = arm.execute(smooth_trajectory(HOME_Q, q1, 2.0))
    assert 0.0 <= err < h.tracking_tolerance, f"{h.name}: tracking error {err}"
    assert np.max(np.abs(arm.joint_positions() - q1)) < h.reach_tolerance
    assert np.max(np.abs(h.truth() - q1)) < h.reach_tolerance
    # back, with explicit velocities
    tr = smooth_trajectory(q1, HOME_Q, 1.5)
    tr.velocities = np.gradient(tr.positions, tr.times, axis=0)
    assert 0.0 <= arm.execute(tr) < h.tracking_tolerance
    assert np.max(np.abs(arm.joint_positions() - HOME_Q)) < h.reach_tolerance


def check_execute_trajectory(h: ArmUnderTest) -> None:
    """A planned multi-segment motion: the arm ends on it, and went along it."""
    arm = h.arm
    h.go_to(HOME_Q)
    via = [HOME_Q, HOME_Q + [0.3, 0.2, 0.0, 0.3, 0.0, -0.2, 0.0], HOME_Q + [-0.2, 0.1, 0.2, 0.2, 0.3, 0.0, -0.3]]
    tr = planned(arm, via, speed=0.3)
    err = arm.execute(tr)
    assert 0.0 <= err < h.tracking_tolerance
    assert np.max(np.abs(arm.joint_positions() - via[-1])) < h.reach_tolerance
    actual = getattr(arm, "last_motion_actual", None)
    if actual is not None and len(actual):
        assert path_distance(np.asarray(actual), tr.positions) < h.path_tolerance
    h.go_to(HOME_Q)


def check_stop_mid_motion(h: ArmUnderTest) -> None:
    arm = h.arm
    h.go_to(HOME_Q)
    q1 = HOME_Q + np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    th, out = run_in_thread(arm.execute, smooth_trajectory(HOME_Q, q1, 20.0, rate=20.0))
    wait_until_moving(arm, HOME_Q)
    arm.stop()
    th.join(60.0)  # a liveness bound: the motion itself has 20 s to go
    assert not th.is_alive(), f"{h.name}: stop() did not end execute()"
    assert isinstance(out[0], TrajectoryError), out
    h.settle()
    assert np.max(np.abs(h.truth() - q1)) > 0.1  # stopped well before the end
    q = arm.joint_positions()  # the arm still works afterwards
    assert arm.execute(smooth_trajectory(q, HOME_Q, 1.0)) < h.tracking_tolerance
    assert np.max(np.abs(arm.joint_positions() - HOME_Q)) < h.reach_tolerance


def bad_trajectories(good: JointTrajectory) -> dict[str, JointTrajectory]:
    def variant(**kw) -> JointTrajectory:
        d = dict(times=good.times.copy(), positions=good.positions.copy(), velocities=None)
        d.update(kw)
        return JointTrajectory(**d)

    nan = good.positions.copy()
    nan[50, 2] = np.nan
    beyond = good.positions.copy()
    beyond[-10:, 3] = 0.05  # joint 4 must stay below 0 (Panda) / -0.15 (FR3)
    times_back = good.times.copy()
    times_back[10] = times_back[9]
    return {
        "nan": variant(positions=nan),
        "beyond joint limit": variant(positions=beyond),
        "time goes back": variant(times=times_back),
        "time not from 0": variant(times=good.times + 0.1),
        "6 joints": variant(positions=good.positions[:, :6]),
        "starts away": variant(positions=good.positions + 0.3),
        "far too fast": variant(times=good.times * 0.05),
        "infinite velocities": variant(velocities=np.full_like(good.positions, np.inf)),
    }


def check_refuse_bad_trajectories(h: ArmUnderTest) -> None:
    arm = h.arm
    h.go_to(HOME_Q)
    h.settle()  # a simulated controller at rest before "did not move" is judged
    q_before, truth_before, pose_before = arm.joint_positions(), h.truth(), arm.camera_pose()
    seen_before = h.commands_seen() if h.commands_seen else None
    for name, tr in bad_trajectories(smooth_trajectory(HOME_Q, HOME_Q + 0.2, 1.0)).items():
        try:
            arm.execute(tr)
        except TrajectoryError:
            pass
        else:
            raise AssertionError(f"{h.name}: {name} was executed")
        assert np.max(np.abs(arm.joint_positions() - q_before)) <= h.still_tolerance, name
        assert np.max(np.abs(h.truth() - truth_before)) <= h.still_tolerance, name
    assert np.allclose(arm.camera_pose(), pose_before, atol=10 * h.still_tolerance)
    if seen_before is not None:
        h.settle()  # the simulated controller ran on (and read its commands) before this is judged
        assert h.commands_seen() == seen_before, "a motion command reached the robot"


def check_recover_after_error(h: ArmUnderTest) -> None:
    """A running motion fails (the arm's own failure mode); after recover() (if the arm has one)
    the arm executes again and reaches its target."""
    arm = h.arm
    h.go_to(HOME_Q)
    q1 = HOME_Q + np.array([0.4, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    th, out = run_in_thread(arm.execute, smooth_trajectory(HOME_Q, q1, 4.0))
    wait_until_moving(arm, HOME_Q)
    h.fault(lambda: not th.is_alive())
    th.join(60.0)  # a liveness bound
    assert not th.is_alive() and isinstance(out[0], TrajectoryError), out
    recover = getattr(arm, "recover", None)
    if recover is not None:
        recover()
    h.settle()
    q = arm.joint_positions()
    assert arm.execute(smooth_trajectory(q, HOME_Q, 1.5)) < h.tracking_tolerance
    assert np.max(np.abs(arm.joint_positions() - HOME_Q)) < h.reach_tolerance


CASES: dict[str, Callable[[ArmUnderTest], None]] = {
    "model_and_camera_pose": check_model_and_camera_pose,
    "reach_joint_targets": check_reach_joint_targets,
    "execute_trajectory": check_execute_trajectory,
    "stop_mid_motion": check_stop_mid_motion,
    "refuse_bad_trajectories": check_refuse_bad_trajectories,
    "recover_after_error": check_recover_after_error,
}


# ----------------------------------------------------------------------------- harnesses
def _far_box_scene():
    from sim.scenes.model import Scene

    box = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    box.apply_translation([-0.6, 0.6, 0.05])
    return Scene(name="contract", category=None, object_mesh=box, paint_mesh=trimesh.Trimesh(),
                 drawing_polylines=[], drawing_width=0.02, gt_points=np.zeros((0, 3), np.float32),
                 extremities=np.zeros((0, 3)))


@contextmanager
def twin_under_test() -> Iterator[ArmUnderTest]:
    from sim.config import TwinConfig
    from sim.twin import Twin

    with Twin(_far_box_scene(), TwinConfig(execution="step", hand_eye=HAND_EYE, home_q=HOME_Q.tolist())) as twin:
        arm = twin.arm
        yield ArmUnderTest(name="twin", arm=arm, truth=arm.joint_positions, go_to=arm.reset,
                           fault=lambda _failed: arm.stop(),  # the twin's only failure: an aborted execution
                           tracking_tolerance=0.02, reach_tolerance=2e-3, still_tolerance=0.0,
                           path_tolerance=0.02)


class _MoveCounter(logging.Handler):
    """Counts the Move commands franky-sim's server parsed off the wire (it logs each one)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage().startswith("Received Move command"):
            self.count += 1


@contextmanager
def franky_sim_server(initial_q=HOME_Q):
    """franky-sim embedded: MuJoCo FR3 behind a libfranka server on the first free 127.x.y.z:1337
    (libfranka's port is fixed, so a free loopback address stands in for a free port), stepping in
    a background thread at up to 1 kHz. Yields (server, simulated robot, Move counter)."""
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MujocoSimulator

    counter = _MoveCounter()
    proto = logging.getLogger("franky_sim.franka_robot_protocol")
    old_level = proto.level
    proto.setLevel(logging.INFO)
    proto.addHandler(counter)
    sim = MujocoSimulator(enable_visualization=False)
    sim.init()
    robot = sim.add_robot(initial_q=tuple(float(v) for v in initial_q))
    server = SimulationServer(sim)
    try:
        server.init()
        server.run_async()
        yield server, robot, counter
    finally:
        server.cleanup()
        sim.cleanup()
        proto.removeHandler(counter)
        proto.setLevel(old_level)


def stall(server, until: Callable[[], bool], max_s: float = 60.0) -> None:
    """Freeze the simulated controller (no state, no commands: a pulled cable) until ``until()`` (the
    adapter has given up: libfranka's 1 s UDP timeout fired), then let it run again. A fixed freeze
    just over 1 s would race libfranka's timeout on a loaded machine. ``max_s``: a liveness bound."""
    server.running = False
    server.async_thread.join()
    deadline = time.monotonic() + max_s
    try:
        while not until() and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        server.run_async()


def franky_config(host: str, **kw):
    from drivers.panda.config import FrankaConfig

    # settle_timeout_s: execute() settles until close or at rest, this is only its wall-clock cap, and the
    # in-process simulator runs slower than the wall clock on a loaded machine
    base = dict(host=host, model="fr3", realtime=False, relative_dynamics_factor=1.0, connect_timeout_s=3.0,
                settle_timeout_s=10.0, hand_eye=HAND_EYE)
    base.update(kw)
    return FrankaConfig(**base)


@contextmanager
def franky_under_test() -> Iterator[ArmUnderTest]:
    from drivers.panda.arm import FrankaArm

    with franky_sim_server() as (server, robot, counter):
        arm = FrankaArm(franky_config(robot.hostname))

        def go_to(q):
            if arm.needs_recovery:
                arm.recover()
            q0 = arm.joint_positions()
            if np.max(np.abs(q0 - q)) > 1e-3:
                arm.execute(planned(arm, [q0, q], speed=0.6))

        try:
            yield ArmUnderTest(name="franky", arm=arm, truth=lambda: np.array(robot.inner_state.q),
                               go_to=go_to, fault=lambda failed: stall(server, failed),
                               # franky-sim's joint PD (kv/kp = 0.1 s) lags 0.1 rad per rad/s (0.06 on
                               # the smooth test motion, 0.11 on a plan at 30 % speed) and holds a few
                               # mrad off the target, jittering ~1e-4 rad
                               tracking_tolerance=0.15, reach_tolerance=5e-3, still_tolerance=5e-4,
                               path_tolerance=0.03, commands_seen=lambda: counter.count,
                               settle=lambda: franky_sim_still(robot))
        finally:
            arm.close()


def free_loopback_address() -> str:
    """A 127.x.y.z where nothing listens on libfranka's port: connecting there is refused."""
    for last in range(1, 250):
        host = f"127.77.13.{last}"
        with socket.socket() as s:
            try:
                s.bind((host, 1337))
            except OSError:
                continue
            return host
    raise RuntimeError("no free loopback address")
