"""The pybullet twin: a Franka Panda with a simulated D435 on its hand, in front of a `Scene`.

``Twin(scene, config)`` opens its own DIRECT pybullet client (several twins can live in one
process), loads the floor, the Panda (fixed base at the origin, so the pybullet world frame is the
robot base frame) and the scene as two static bodies (object and paint). ``twin.arm`` implements
``drivers.interfaces.Arm`` and ``twin.camera`` implements ``drivers.interfaces.RGBDCamera``; with
``config.faults`` set they are the fault-injecting wrappers of sim/faults.py, and ``twin.scene`` is
the scene as placed (callers take view candidates and ground truth from it).

Never imports planners/ or cellctl/.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import threading
import time
import weakref
from typing import Callable

import numpy as np
import pybullet as p
import pybullet_data
import trimesh
from scipy.spatial.transform import Rotation

from configs.panda import (BASE_LINK, FLANGE_LINK, JOINT_NAMES, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK,
                           PANDA_MAX_TORQUE, PANDA_MAX_VELOCITY, PANDA_URDF)
from drivers.interfaces import (Arm, ArmModel, ContactLog, DeviceError, Intrinsics, JointTrajectory, MotionLog,
                                RGBDCamera, RGBDFrame, TrajectoryError)
from sim.appearance import Painter
from sim.config import TwinConfig
from sim.d435 import apply_depth_noise, grazing_mask, intrinsics_for
from sim.faults import FaultyArm, FaultyCamera, place_out_of_reach
from sim.scenes.model import Scene

PLANE_URDF = os.path.join(pybullet_data.getDataPath(), "plane.urdf")
FINGER_NAMES: tuple[str, ...] = ("panda_finger_joint1", "panda_finger_joint2")
TOOL_LINK = "tool"  # how contacts of TwinConfig.tool are named
TOOL_STEP_M = 0.0005  # the tool's contacts are queried after this much travel of any of its points
# Franka's published limits (configs/panda.py)
MAX_VELOCITY, MAX_ACCELERATION, MAX_JERK, MAX_TORQUE = (PANDA_MAX_VELOCITY, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK,
                                                        PANDA_MAX_TORQUE)
FINGER_OPENING = 0.02  # m per finger, held still

# Trajectory acceptance.
START_TOLERANCE = 0.05  # rad: the first sample must be this close to the current joints
VELOCITY_TOLERANCE = 1.10  # sample-to-sample speed may exceed the published limit by 10 %
LIMIT_TOLERANCE = 1e-9  # rad
# Position-control gains of pybullet's joint motors (tuned for sub-centiradian tracking at 240 Hz).
POSITION_GAIN = 0.3
VELOCITY_GAIN = 1.0
SETTLE_TIME = 0.5  # s of extra stepping after the last sample, until within SETTLE_TOLERANCE
SETTLE_TOLERANCE = 1e-3  # rad

# Rendering.
NEAR_M = 0.02
LIGHT_DIRECTION = (-0.5, 0.2, 1.0)  # towards the light: above and behind the robot, so faces the camera sees are lit
LIGHT = dict(shadow=0, lightAmbientCoeff=0.6, lightDiffuseCoeff=0.4, lightSpecularCoeff=0.02)


def _pose_matrix(position, quaternion_xyzw) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(p.getMatrixFromQuaternion(quaternion_xyzw)).reshape(3, 3)
    T[:3, 3] = position
    return T


def _quaternion(R: np.ndarray) -> list[float]:
    """pybullet's (x, y, z, w) of a rotation matrix."""
    return Rotation.from_matrix(R).as_quat().tolist()


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


def _check_pose(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_base_cam must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError("T_base_cam is not a rigid transform")
    return T


def projection_matrix(K: Intrinsics, near: float, far: float) -> np.ndarray:
    """OpenGL projection (row-major 4x4) that makes pybullet's TinyRenderer sample pixel (u, v) along
    the ray ((u - cx)/fx, (v - cy)/fy, 1) of our optical frame. TinyRenderer samples at pixel corners
    and flips rows, hence the offsets (checked by fitting rendered planes: exact to 1e-3 px)."""
    W, H = K.width, K.height
    return np.array([
        [2.0 * K.fx / W, 0.0, 1.0 - 2.0 * K.cx / W, 0.0],
        [0.0, 2.0 * K.fy / H, (2.0 * K.cy + 2.0) / H - 1.0, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2.0 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])


def view_matrix(T_base_cam: np.ndarray) -> np.ndarray:
    """OpenGL view matrix (row-major) of an optical-frame pose: the GL camera looks along -z with
    y up, our optical frame looks along +z with y down."""
    return np.linalg.inv(T_base_cam @ np.diag([1.0, -1.0, -1.0, 1.0]))


class _Sim:
    """What the arm and camera share: the client id, the body ids and one lock serializing all
    pybullet calls (execute() may run in another thread than joint_positions()/stop())."""

    def __init__(self) -> None:
        self.client = -1
        self.robot = -1
        self.bodies: dict[int, str] = {}  # scene bodies the robot must not touch, by pybullet id
        self.tool = -1  # the tool's body (TwinConfig.tool), -1 without one
        self.T_flange_tool = np.eye(4)  # its tip frame in the flange frame
        self.lock = threading.RLock()
        self.closed = False

    def check(self) -> None:
        if self.closed:
            raise DeviceError("the twin is closed")


class TwinArm(Arm, ContactLog, MotionLog):
    """The simulated Panda (implements ``drivers.interfaces.Arm``), with the twin's own contact check of
    every motion (``ContactLog``) and the joints commanded and reached at every step (``MotionLog``)."""

    def __init__(self, sim: _Sim, config: TwinConfig) -> None:
        self._sim = sim
        self._config = config
        c, robot = sim.client, sim.robot
        by_name = {}
        for j in range(p.getNumJoints(robot, physicsClientId=c)):
            info = p.getJointInfo(robot, j, physicsClientId=c)
            by_name[info[1].decode()] = info
        self._joints = [by_name[n][0] for n in JOINT_NAMES]
        self._fingers = [by_name[n][0] for n in FINGER_NAMES]
        links = {info[12].decode(): info[0] for info in by_name.values()}
        self.flange_index: int = links[FLANGE_LINK]
        self.model = ArmModel(
            urdf_path=PANDA_URDF,
            base_link=BASE_LINK,
            flange_link=FLANGE_LINK,
            joint_names=JOINT_NAMES,
            lower=_readonly([by_name[n][8] for n in JOINT_NAMES]),
            upper=_readonly([by_name[n][9] for n in JOINT_NAMES]),
            max_velocity=_readonly(MAX_VELOCITY),
            max_acceleration=_readonly(MAX_ACCELERATION),
            max_jerk=_readonly(MAX_JERK),
            T_flange_cam=_readonly(config.hand_eye.T_flange_cam()),
        )
        self._dt = 1.0 / config.sim_hz
        self._stop = threading.Event()
        self._link_names = {-1: BASE_LINK, **{info[0]: info[12].decode() for info in by_name.values()}}
        #: contacts (pybullet reports them from a few mm apart; distance < 0 is penetration) of the robot
        #: with the scene during the last execute(): the twin's own check,
        #: independent of the planner's collision model. One entry per (link, body), first sample.
        self.last_motion_contacts: list[dict] = []
        self._tool_checked_at: np.ndarray | None = None  # the tool's pose at its last contact query
        #: joints commanded and reached at every simulation step of the last execute() (T, 7): the
        #: tracking of a path (a cut) can be judged after the fact
        self.last_motion_desired = np.zeros((0, 7))
        self.last_motion_actual = np.zeros((0, 7))
        #: called before each sample (teleport) or simulation step (step) with the trajectory time it
        #: goes to, outside the lock: how sim/faults.py stops a motion part way through the real stop path
        self.on_sample: Callable[[float], None] | None = None

    # ------------------------------------------------------------------ Arm protocol
    def joint_positions(self) -> np.ndarray:
        """Current joint angles (7,), radians. Non-blocking (waits at most one simulation step)."""
        with self._sim.lock:
            self._sim.check()
            states = p.getJointStates(self._sim.robot, self._joints, physicsClientId=self._sim.client)
        return np.array([s[0] for s in states])

    def joint_velocities(self) -> np.ndarray:
        """Current joint speeds (7,), rad/s, as the simulation measures them (twin only: whether a
        stopped arm holds)."""
        with self._sim.lock:
            self._sim.check()
            states = p.getJointStates(self._sim.robot, self._joints, physicsClientId=self._sim.client)
        return np.array([s[1] for s in states])

    def execute(self, trajectory: JointTrajectory) -> float:
        """Follow ``trajectory``; blocks until done and returns the max joint tracking error (rad).

        Refused with TrajectoryError before anything moves when: shapes are not (T,) / (T, 7), a
        value is not finite, times do not start at 0 or do not strictly increase, a sample is outside
        the URDF joint limits, the first sample is more than START_TOLERANCE from the current
        joints, or the speed between samples exceeds the published limit by more than 10 %.
        "step": pybullet position control at sim_hz on the piecewise-linear interpolation of the
        samples (target velocities from ``trajectory.velocities`` when given); "teleport": joint
        states are set sample by sample, error 0. Raises TrajectoryError if stop() aborts it."""
        times, q, qd = self._validate(trajectory)
        self._stop.clear()
        self.last_motion_contacts = []
        if self._config.execution == "teleport":
            self.last_motion_desired = self.last_motion_actual = q.copy()
            return self._teleport(times, q)
        return self._step(times, q, qd)

    def stop(self) -> None:
        """Abort a running execute() at its next simulation step (the arm holds where it is); when
        idle, re-target the motors to the current joints."""
        self._stop.set()
        if self._sim.lock.acquire(blocking=False):
            try:
                if not self._sim.closed:
                    self._hold(self.joint_positions())
            finally:
                self._sim.lock.release()

    def camera_pose(self) -> np.ndarray:
        """T_base_cam: pybullet's own link frame of panda_hand composed with T_flange_cam."""
        with self._sim.lock:
            self._sim.check()
            st = p.getLinkState(self._sim.robot, self.flange_index, computeForwardKinematics=True,
                                physicsClientId=self._sim.client)
        return _pose_matrix(st[4], st[5]) @ self.model.T_flange_cam

    # ------------------------------------------------------------------ twin only
    def reset(self, q) -> None:
        """Teleport to ``q`` (7,) with zero velocity; the motors then hold it. ValueError if not
        finite or outside the joint limits."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (7,) or not np.all(np.isfinite(q)):
            raise ValueError(f"q must be 7 finite joint angles, got {q!r}")
        if np.any(q < self.model.lower - LIMIT_TOLERANCE) or np.any(q > self.model.upper + LIMIT_TOLERANCE):
            raise ValueError(f"q {np.round(q, 4).tolist()} outside the joint limits")
        with self._sim.lock:
            self._sim.check()
            self._set_state(q)
            self._hold(q)

    def mirror(self, samples) -> list[dict]:
        """Twin only: pose the robot at the measured joints of another arm (``(7,)``, or ``(T, 7)``
        visited in order) and return the robot-scene contacts seen on the way (as
        ``last_motion_contacts``). Why: a cell whose arm is real or franky-sim still renders its
        camera and checks contacts here, so the robot in the picture must be where that arm is. No
        limit check (that arm enforces its own, e.g. the FR3's joint 7 range exceeds this URDF's);
        the simulation is not stepped. ValueError for a non-finite or malformed sample."""
        Q = np.atleast_2d(np.asarray(samples, dtype=np.float64))
        if Q.ndim != 2 or Q.shape[1] != 7 or len(Q) == 0 or not np.all(np.isfinite(Q)):
            raise ValueError(f"mirror() needs finite joint samples of shape (7,) or (T, 7), got {Q.shape}")
        self.last_motion_contacts = []
        with self._sim.lock:
            self._sim.check()
            for k, q in enumerate(Q):
                self._set_state(q)
                if len(Q) > 1:
                    p.performCollisionDetection(physicsClientId=self._sim.client)
                    self._note_contacts(k)
            self._hold(Q[-1])
        return self.last_motion_contacts

    # ------------------------------------------------------------------ internals
    def _set_state(self, q: np.ndarray) -> None:
        c, robot = self._sim.client, self._sim.robot
        p.resetJointStatesMultiDof(robot, self._joints, [[float(v)] for v in q], [[0.0]] * 7, physicsClientId=c)
        p.resetJointStatesMultiDof(robot, self._fingers, [[FINGER_OPENING]] * 2, [[0.0]] * 2, physicsClientId=c)

    def _command(self, q: np.ndarray, qd: np.ndarray) -> None:
        c, robot = self._sim.client, self._sim.robot
        p.setJointMotorControlArray(robot, self._joints, p.POSITION_CONTROL, targetPositions=q.tolist(),
                                    targetVelocities=qd.tolist(), forces=MAX_TORQUE.tolist(),
                                    positionGains=[POSITION_GAIN] * 7, velocityGains=[VELOCITY_GAIN] * 7,
                                    physicsClientId=c)
        p.setJointMotorControlArray(robot, self._fingers, p.POSITION_CONTROL, targetPositions=[FINGER_OPENING] * 2,
                                    forces=[20.0, 20.0], physicsClientId=c)

    def _note_contacts(self, sample: int) -> None:
        """Record robot-scene contacts of the current simulation state (caller holds the lock)."""
        c, robot, tool = self._sim.client, self._sim.robot, self._sim.tool
        seen = {(e["link"], e["body"]) for e in self.last_motion_contacts}
        check_tool = False
        if tool >= 0:  # the tool follows the hand; touching (distance <= 0) is a contact
            st = p.getLinkState(robot, self.flange_index, computeForwardKinematics=True, physicsClientId=c)
            T = _pose_matrix(st[4], st[5]) @ self._sim.T_flange_tool
            last = self._tool_checked_at
            # a query per TOOL_STEP_M of tool travel (tip shift plus turn times its length), not per step
            moved = np.inf if last is None or sample == 0 else (
                np.linalg.norm(T[:3, 3] - last[:3, 3])
                + np.linalg.norm(T[:3, :3] - last[:3, :3]) * self._config.tool.length_m)
            if moved >= TOOL_STEP_M:
                check_tool, self._tool_checked_at = True, T
                p.resetBasePositionAndOrientation(tool, T[:3, 3].tolist(), _quaternion(T[:3, :3]), physicsClientId=c)
        for body, name in self._sim.bodies.items():
            points = [(self._link_names.get(cp[3], str(cp[3])), cp)
                      for cp in p.getContactPoints(bodyA=robot, bodyB=body, physicsClientId=c)]
            if check_tool:
                points += [(TOOL_LINK, cp) for cp in p.getClosestPoints(tool, body, 0.0, physicsClientId=c)]
            for link, cp in points:
                if (link, name) not in seen and not (name == "floor" and link == BASE_LINK):
                    seen.add((link, name))
                    self.last_motion_contacts.append({"link": link, "body": name, "sample": sample,
                                                      "distance_m": round(float(cp[8]), 5),
                                                      "position": [round(float(x), 4) for x in cp[6]]})

    def _hold(self, q: np.ndarray) -> None:
        self._command(np.asarray(q, dtype=np.float64), np.zeros(7))

    def _validate(self, tr: JointTrajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        try:
            times = np.asarray(tr.times, dtype=np.float64)
            q = np.asarray(tr.positions, dtype=np.float64)
            qd = None if tr.velocities is None else np.asarray(tr.velocities, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise TrajectoryError(f"trajectory is not numeric: {e}") from e
        if times.ndim != 1 or len(times) < 1 or q.shape != (len(times), 7):
            raise TrajectoryError(f"need times (T,) and positions (T, 7) with T >= 1, got {times.shape} and {q.shape}")
        if qd is not None and qd.shape != q.shape:
            raise TrajectoryError(f"velocities must have shape {q.shape}, got {qd.shape}")
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(q)) and (qd is None or np.all(np.isfinite(qd)))):
            raise TrajectoryError("trajectory contains NaN or inf")
        if abs(times[0]) > 1e-9 or np.any(np.diff(times) <= 0.0):
            raise TrajectoryError("times must start at 0 and strictly increase")
        lo, hi = self.model.lower - LIMIT_TOLERANCE, self.model.upper + LIMIT_TOLERANCE
        bad = (q < lo) | (q > hi)
        if np.any(bad):
            k, j = np.argwhere(bad)[0]
            raise TrajectoryError(f"sample {k}: joint {j + 1} = {q[k, j]:.4f} outside [{lo[j]:.4f}, {hi[j]:.4f}]")
        if qd is not None and np.any(np.abs(qd) > VELOCITY_TOLERANCE * self.model.max_velocity):
            raise TrajectoryError("trajectory velocities exceed the joint velocity limits")
        if len(times) > 1:
            speed = np.abs(np.diff(q, axis=0)) / np.diff(times)[:, None]
            if np.any(speed > VELOCITY_TOLERANCE * self.model.max_velocity):
                k, j = np.argwhere(speed > VELOCITY_TOLERANCE * self.model.max_velocity)[0]
                raise TrajectoryError(f"segment {k}: joint {j + 1} moves at {speed[k, j]:.3f} rad/s, "
                                      f"limit {self.model.max_velocity[j]:.3f}")
        gap = np.max(np.abs(q[0] - self.joint_positions()))
        if gap > START_TOLERANCE:
            raise TrajectoryError(f"trajectory starts {gap:.3f} rad away from the current joints "
                                  f"(tolerance {START_TOLERANCE})")
        return times, q, qd

    def _teleport(self, times: np.ndarray, q: np.ndarray) -> float:
        for k, sample in enumerate(q):
            if self.on_sample is not None:
                self.on_sample(float(times[k]))
            if self._stop.is_set():
                raise TrajectoryError("execution stopped")
            with self._sim.lock:
                self._sim.check()
                self._set_state(sample)
                p.performCollisionDetection(physicsClientId=self._sim.client)
                self._note_contacts(k)
        with self._sim.lock:
            self._hold(q[-1])
        return 0.0

    def _step(self, times: np.ndarray, q: np.ndarray, qd: np.ndarray | None) -> float:
        dt = self._dt
        n = max(1, int(math.ceil(times[-1] / dt - 1e-9)))
        t = np.minimum(np.arange(1, n + 1) * dt, times[-1])
        # piecewise-linear targets at every simulation step (vectorized over steps and joints)
        seg = np.clip(np.searchsorted(times, t, side="right") - 1, 0, max(len(times) - 2, 0))
        if len(times) == 1:
            q_des = np.repeat(q[:1], n, axis=0)
            v_des = np.zeros_like(q_des)
        else:
            h = times[seg + 1] - times[seg]
            a = ((t - times[seg]) / h)[:, None]
            q_des = q[seg] + a * (q[seg + 1] - q[seg])
            v_des = (qd[seg] + a * (qd[seg + 1] - qd[seg])) if qd is not None else (q[seg + 1] - q[seg]) / h[:, None]
        c, robot = self._sim.client, self._sim.robot
        err = 0.0
        self.last_motion_desired = q_des
        self.last_motion_actual = actual = np.full_like(q_des, np.nan)
        for k in range(n):
            if self.on_sample is not None:
                self.on_sample(float(t[k]))
            if self._stop.is_set():
                with self._sim.lock:
                    self._hold(self.joint_positions())
                raise TrajectoryError(f"execution stopped at t={k * dt:.3f} s")
            with self._sim.lock:
                self._sim.check()
                self._command(q_des[k], v_des[k])
                p.stepSimulation(physicsClientId=c)
                self._note_contacts(k)
                now = np.array([s[0] for s in p.getJointStates(robot, self._joints, physicsClientId=c)])
            actual[k] = now
            err = max(err, float(np.max(np.abs(now - q_des[k]))))
        # settle on the last sample
        with self._sim.lock:
            self._hold(q[-1])
            for _ in range(int(SETTLE_TIME / dt)):
                if self._stop.is_set():
                    self._hold(self.joint_positions())
                    raise TrajectoryError("execution stopped while settling")
                p.stepSimulation(physicsClientId=c)
                self._note_contacts(n)
                now = np.array([s[0] for s in p.getJointStates(robot, self._joints, physicsClientId=c)])
                if np.max(np.abs(now - q[-1])) < SETTLE_TOLERANCE:
                    break
        return err


class TwinCamera(RGBDCamera):
    """The simulated D435 on the hand (implements ``drivers.interfaces.RGBDCamera``).

    Each frame: TinyRenderer image at the pose, metric depth along the optical axis, NaN outside
    [min_range_m, max_range_m], NaN at grazing incidence and depth discontinuities, then Gaussian
    noise with the datasheet RMS (rng seeded with ``config.camera.seed``, advancing per frame).
    ``last_truth`` holds the noise-free depth of the last frame (same NaN pattern)."""

    def __init__(self, sim: _Sim, arm: TwinArm, config: TwinConfig) -> None:
        self._sim = sim
        self._arm = arm
        self._cfg = config.camera
        self.intrinsics: Intrinsics = intrinsics_for(self._cfg)
        self.K: np.ndarray = self.intrinsics.matrix()
        self.far_m: float = max(4.0, 2.0 * self._cfg.max_range_m)
        self._proj = projection_matrix(self.intrinsics, NEAR_M, self.far_m).T.ravel().tolist()
        self._rng = np.random.default_rng(self._cfg.seed)
        self._color_rng = np.random.default_rng(self._cfg.seed + 1)  # apart from the depth noise's
        self.last_truth: np.ndarray | None = None
        self.painter: Painter | None = None  # the scene's appearance (sim.appearance), None: flat colours
        self.painter_ids: dict[str, int | None] = {}

    def capture(self) -> RGBDFrame:
        """Render a frame from the arm's current camera_pose(). Blocks for the render (~0.15-0.25 s at 848x480)."""
        return self.capture_at(self._arm.camera_pose())

    def capture_at(self, T_base_cam: np.ndarray) -> RGBDFrame:
        """Twin only: a frame from an explicit T_base_cam (the arm is not moved)."""
        color, raw = self.render(T_base_cam)
        truth = self.sensor_depth(raw)
        self.last_truth = truth
        depth = apply_depth_noise(truth, self._cfg, self._rng)
        return RGBDFrame(color=color, depth=depth, intrinsics=self.intrinsics, timestamp=time.monotonic())

    def render_truth(self, T_base_cam: np.ndarray | None = None) -> np.ndarray:
        """Noise-free sensor depth (range limits and grazing applied) without advancing the noise
        rng; at the arm's current camera pose when ``T_base_cam`` is None."""
        T = self._arm.camera_pose() if T_base_cam is None else T_base_cam
        return self.sensor_depth(self.render(T)[1])

    def render(self, T_base_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw render: (color (H, W, 3) uint8 RGB, depth (H, W) float32 metres along the optical axis,
        NaN where nothing is hit) without any sensor effect."""
        T = _check_pose(T_base_cam)
        K = self.intrinsics
        with self._sim.lock:
            self._sim.check()
            _, _, rgba, zbuf, seg = p.getCameraImage(
                K.width, K.height, viewMatrix=view_matrix(T).T.ravel().tolist(), projectionMatrix=self._proj,
                renderer=p.ER_TINY_RENDERER, flags=0 if self.painter is not None else p.ER_NO_SEGMENTATION_MASK,
                lightDirection=LIGHT_DIRECTION, physicsClientId=self._sim.client, **LIGHT)
        color = np.ascontiguousarray(np.asarray(rgba, dtype=np.uint8).reshape(K.height, K.width, 4)[..., :3])
        zbuf = np.asarray(zbuf, dtype=np.float64).reshape(K.height, K.width)
        n, f = NEAR_M, self.far_m
        z = f * n / (f - (f - n) * zbuf)
        z[z > 0.999 * f] = np.nan  # cleared depth buffer: nothing hit
        if self.painter is not None:
            seg = np.asarray(seg, dtype=np.int64).reshape(K.height, K.width)
            color = self.painter.shade(color, z, seg, self.K, T, self.painter_ids, np.asarray(LIGHT_DIRECTION),
                                       self._color_rng)
        return color, z.astype(np.float32)

    def sensor_depth(self, raw: np.ndarray) -> np.ndarray:
        """What the D435 returns of a raw render's depth: NaN out of range, at grazing incidence and at depth discontinuities."""
        cfg = self._cfg
        invalid = grazing_mask(raw, self.K, cfg.max_incidence_deg)
        with np.errstate(invalid="ignore"):
            invalid |= ~((raw >= cfg.min_range_m) & (raw <= cfg.max_range_m))
        return np.where(invalid, np.float32(np.nan), raw).astype(np.float32)


def _write_mesh(vertices: np.ndarray, faces: np.ndarray, path: str) -> None:
    """Binary STL (vectorized, ~20 ms for 150k faces; trimesh's OBJ writer takes ~0.3 s). pybullet
    loads it for both the visual shape (renders identically to an OBJ without normals: flat
    shading) and the concave collision shape."""
    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)
    with open(path, "wb") as fh:
        fh.write(trimesh.exchange.stl.export_stl(mesh))


def _is_closed(*meshes: trimesh.Trimesh) -> bool:
    """Whether the meshes together form a watertight surface (vertices merged by position)."""
    parts = [m for m in meshes if m is not None and len(m.faces)]
    if not parts:
        return True
    offsets = np.cumsum([0] + [len(m.vertices) for m in parts[:-1]])
    full = trimesh.Trimesh(np.vstack([m.vertices for m in parts]),
                           np.vstack([np.asarray(m.faces) + o for m, o in zip(parts, offsets)]), process=False)
    full.merge_vertices(merge_tex=True, merge_norm=True)
    return bool(full.is_watertight)


def _shutdown(sim: _Sim, tmpdir: str) -> None:
    with sim.lock:
        if not sim.closed:
            sim.closed = True
            try:
                p.disconnect(physicsClientId=sim.client)
            except p.error:
                pass
    shutil.rmtree(tmpdir, ignore_errors=True)


class Twin:
    """pybullet twin of the cell. Use as a context manager or call close()."""

    def __init__(self, scene: Scene, config: TwinConfig | None = None) -> None:
        self.config = config if config is not None else TwinConfig()
        self.scene = place_out_of_reach(scene) if self.config.faults.arm.ik_failure else scene
        self._tmpdir = tempfile.mkdtemp(prefix="scrapcell-twin-")
        self._sim = _Sim()
        self._finalizer = weakref.finalize(self, _shutdown, self._sim, self._tmpdir)
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def _build(self) -> None:
        sim = self._sim
        sim.client = c = p.connect(p.DIRECT)
        if c < 0:
            raise DeviceError("could not open a pybullet DIRECT client")
        p.setGravity(0.0, 0.0, -9.81, physicsClientId=c)
        p.setTimeStep(1.0 / self.config.sim_hz, physicsClientId=c)
        # TinyRenderer culls back faces: an open surface (a sheet modelled by one side) would vanish
        # from behind, so its visual shape gets both windings (about +15 % render time).
        self.double_sided: bool = not _is_closed(self.scene.object_mesh, self.scene.paint_mesh)
        # The scene first: TinyRenderer draws bodies in creation order and skips shading of hidden
        # fragments, so the floor drawn after the object costs less (about 50 ms a frame).
        self.object_id = self._add_static(self.scene.object_mesh, self.scene.object_rgb, "object")
        self.paint_id = self._add_static(self.scene.paint_mesh, self.scene.paint_rgb, "paint")
        self.floor_id: int = p.loadURDF(PLANE_URDF, physicsClientId=c)
        sim.robot = p.loadURDF(PANDA_URDF, basePosition=[0, 0, 0], useFixedBase=True, physicsClientId=c)
        sim.bodies = {i: n for i, n in ((self.object_id, "object"), (self.paint_id, "paint"), (self.floor_id, "floor"))
                      if i is not None}
        self.robot_id: int = sim.robot
        if self.config.tool is not None:
            sim.tool = self._add_tool(self.config.tool)
            sim.T_flange_tool = self.config.tool.T_flange_tip()
        self.arm = TwinArm(sim, self.config)
        self.camera = TwinCamera(sim, self.arm, self.config)
        if self.scene.appearance is not None:
            self.camera.painter = Painter(self.scene.appearance, self.scene.drawing_polylines, self.scene.drawing_width,
                                          self.scene.object_rgb, self.scene.paint_rgb, self.scene.paint_mesh)
            self.camera.painter_ids = {"object": self.object_id, "paint": self.paint_id}
        faults = self.config.faults
        if faults.arm.active:
            self.arm = FaultyArm(self.arm, faults.arm)
        if faults.camera.active:
            self.camera = FaultyCamera(self.camera, faults.camera)
        self.arm.reset(np.asarray(self.config.home_q))

    def _add_tool(self, tool) -> int:
        """The tool's cylinder: a body that takes part in no simulated collision (it rides on the
        hand, where the dynamics would fight it) and is never drawn; ``_note_contacts`` moves it to
        the hand and asks pybullet for its contacts with the scene."""
        c = self._sim.client
        col = p.createCollisionShape(p.GEOM_MESH, vertices=tool.hull().tolist(), physicsClientId=c)  # its hull
        body = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=col, baseVisualShapeIndex=-1,
                                 physicsClientId=c)
        p.setCollisionFilterGroupMask(body, -1, 0, 0, physicsClientId=c)
        return body

    def _add_static(self, mesh: trimesh.Trimesh, rgb, name: str) -> int | None:
        if mesh is None or len(mesh.faces) == 0:
            return None
        c = self._sim.client
        faces = np.asarray(mesh.faces)
        col_path = os.path.join(self._tmpdir, f"{name}.stl")
        _write_mesh(mesh.vertices, faces, col_path)
        vis_path = col_path
        if self.double_sided:
            vis_path = os.path.join(self._tmpdir, f"{name}_visual.stl")
            _write_mesh(mesh.vertices, np.vstack([faces, faces[:, ::-1]]), vis_path)
        try:
            vis = p.createVisualShape(p.GEOM_MESH, fileName=vis_path, rgbaColor=[*map(float, rgb), 1.0],
                                      physicsClientId=c)
            col = p.createCollisionShape(p.GEOM_MESH, fileName=col_path, flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
                                         physicsClientId=c)
        except p.error as e:
            raise DeviceError(f"pybullet could not load the {name} mesh ({len(faces)} faces): {e}") from e
        if vis < 0 or col < 0:
            raise DeviceError(f"pybullet could not load the {name} mesh ({len(faces)} faces)")
        return p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
                                 physicsClientId=c)

    @property
    def client(self) -> int:
        """The pybullet physicsClientId of this twin."""
        return self._sim.client

    def render_truth(self, T_base_cam: np.ndarray | None = None) -> np.ndarray:
        """Noise-free sensor depth at ``T_base_cam`` (default: the arm's camera pose)."""
        return self.camera.render_truth(T_base_cam)

    def close(self) -> None:
        """Disconnect the pybullet client and remove the temporary mesh files. Idempotent."""
        self._finalizer()

    def __enter__(self) -> "Twin":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
