"""Checks a JointTrajectory against the FrankaConfig before anything is sent to the robot.

Pure numpy: joint-limit margin, velocity, acceleration and jerk from divided differences, and the
workspace box of the flange and the camera through the cell's one batched forward kinematics
(configs.chain). Every refusal is a TrajectoryError that names the limit, the sample and the joint
(or axis), so an operator can see what the planner got wrong.

Why divided differences bound the motion: the k-th divided difference of samples of a smooth path
equals its k-th derivative (divided by k!) somewhere between the samples, so samples within the
limits are necessary for any execution that passes through them on time. The arm is at rest before
and after a trajectory, so rest samples are padded at both ends: a trajectory that starts or stops
moving abruptly is refused for the acceleration or jerk step it implies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from configs.chain import Chain
from drivers.interfaces import JointTrajectory, TrajectoryError
from drivers.panda.config import FLANGE_LINK, JOINT_NAMES, FrankaConfig

MAX_SAMPLES = 200_000  # ~30 min at 100 Hz: anything longer is a planner bug, not a motion
_PAD = 3  # rest samples added at each end (enough for the third difference)


def derivatives(times: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Velocity, acceleration and jerk bounds from k! x the k-th divided differences of the samples,
    with rest padded at both ends (see the module docstring); entry i of the k-th spans padded
    samples i..i+k. Needs at least 2 samples."""
    h0, h1 = times[1] - times[0], times[-1] - times[-2]
    pad = np.arange(1, _PAD + 1, dtype=np.float64)
    t = np.concatenate([times[0] - h0 * pad[::-1], times, times[-1] + h1 * pad])
    x = np.concatenate([np.repeat(q[:1], _PAD, 0), q, np.repeat(q[-1:], _PAD, 0)])
    v = np.diff(x, axis=0) / np.diff(t)[:, None]
    a = 2.0 * np.diff(v, axis=0) / (t[2:] - t[:-2])[:, None]
    j = 3.0 * np.diff(a, axis=0) / (t[3:] - t[:-3])[:, None]
    return v, a, j


@dataclass
class CheckedTrajectory:
    """A trajectory that passed every check: float64 copies, safe to hand to the robot."""

    times: np.ndarray  # (T,)
    positions: np.ndarray  # (T, 7)


class SafetyChecker:
    """The refusals of drivers/panda: built once per config (reads the URDF), then ``check()``."""

    def __init__(self, config: FrankaConfig) -> None:
        self.config = config
        lim = config.active_limits
        m = config.joint_limit_margin_rad
        self.lower = np.asarray(lim.q_min) + m
        self.upper = np.asarray(lim.q_max) - m
        slack = 1.0 + config.limit_tolerance
        self.limits = {
            "velocity": (np.asarray(lim.max_velocity), slack, "rad/s"),
            "acceleration": (np.asarray(lim.max_acceleration), slack, "rad/s^2"),
            "jerk": (np.asarray(lim.max_jerk), slack, "rad/s^3"),
        }
        self.kin = Chain.from_urdf(config.urdf_path, JOINT_NAMES, FLANGE_LINK)
        self.T_flange_cam = config.T_flange_cam()

    # ------------------------------------------------------------------ public
    def check(self, trajectory: JointTrajectory) -> CheckedTrajectory:
        """Raise TrajectoryError on the first violated limit; otherwise the validated arrays."""
        times, q, qd = self._structure(trajectory)
        self._joint_margin(times, q)
        if qd is not None:
            self._given_velocities(times, qd)
        self._dynamics(times, q)
        self._workspace(times, q)
        return CheckedTrajectory(times, q)

    def flange_poses(self, q: np.ndarray) -> np.ndarray:
        return self.kin.poses(q)

    def camera_poses(self, q: np.ndarray) -> np.ndarray:
        return self.kin.poses(q) @ self.T_flange_cam

    # ------------------------------------------------------------------ checks
    @staticmethod
    def _structure(tr: JointTrajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        try:
            times = np.array(tr.times, dtype=np.float64)
            q = np.array(tr.positions, dtype=np.float64)
            qd = None if tr.velocities is None else np.array(tr.velocities, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise TrajectoryError(f"trajectory is not numeric: {e}") from e
        if times.ndim != 1 or len(times) < 1 or q.shape != (len(times), 7):
            raise TrajectoryError(f"need times (T,) and positions (T, 7) with T >= 1, got {times.shape} and {q.shape}")
        if len(times) > MAX_SAMPLES:
            raise TrajectoryError(f"trajectory has {len(times)} samples, more than {MAX_SAMPLES}")
        if qd is not None and qd.shape != q.shape:
            raise TrajectoryError(f"velocities must have shape {q.shape}, got {qd.shape}")
        for name, a in (("times", times), ("positions", q), ("velocities", qd)):
            if a is not None and not np.all(np.isfinite(a)):
                k = int(np.argwhere(~np.isfinite(a))[0][0])
                raise TrajectoryError(f"{name} contain NaN or inf (sample {k})")
        if abs(times[0]) > 1e-9:
            raise TrajectoryError(f"times must start at 0, got {times[0]:.6f} s")
        steps = np.diff(times)
        if np.any(steps <= 0.0):
            k = int(np.argmax(steps <= 0.0)) + 1
            raise TrajectoryError(f"times must strictly increase (sample {k}: {times[k]:.6f} s "
                                  f"after {times[k - 1]:.6f} s)")
        return times, q, qd

    def _joint_margin(self, times: np.ndarray, q: np.ndarray) -> None:
        bad = (q < self.lower) | (q > self.upper)
        if np.any(bad):
            k, j = (int(v) for v in np.argwhere(bad)[0])
            lim = self.config.active_limits
            raise TrajectoryError(
                f"joint-limit margin: sample {k} (t={times[k]:.3f} s), joint {j + 1}: {q[k, j]:.4f} rad is outside "
                f"[{self.lower[j]:.4f}, {self.upper[j]:.4f}] (the {self.config.model} limits "
                f"[{lim.q_min[j]}, {lim.q_max[j]}] less the {self.config.joint_limit_margin_rad} rad margin)")

    def _given_velocities(self, times: np.ndarray, qd: np.ndarray) -> None:
        vmax, slack, unit = self.limits["velocity"]
        self._refuse_above("velocity", np.abs(qd), vmax, slack, unit, np.arange(len(times)), times, "given ")

    def _dynamics(self, times: np.ndarray, q: np.ndarray) -> None:
        if len(times) < 2:
            return  # one sample: hold where the arm is
        v, a, j = derivatives(times, q)
        n = len(times)
        for name, d, first in (("velocity", v, 1), ("acceleration", a, 1), ("jerk", j, 2)):
            # entry i of the k-th difference spans padded samples i..i+k; name the original sample
            # at its (upper) middle, clamped to the trajectory
            sample = np.clip(np.arange(len(d)) + first - _PAD, 0, n - 1)
            limit, slack, unit = self.limits[name]
            self._refuse_above(name, np.abs(d), limit, slack, unit, sample, times)

    @staticmethod
    def _refuse_above(name, value, limit, slack, unit, sample, times, what="") -> None:
        ratio = value / limit
        if np.any(ratio > slack):
            i, jj = np.unravel_index(int(np.argmax(ratio)), ratio.shape)  # the worst offender
            k = int(sample[i])
            raise TrajectoryError(
                f"{name} limit: sample {k} (t={times[k]:.3f} s), joint {jj + 1}: {what}{value[i, jj]:.3f} {unit} "
                f"exceeds {limit[jj]:.3f} {unit} ({ratio[i, jj]:.2f} x the limit)")

    def _workspace(self, times: np.ndarray, q: np.ndarray) -> None:
        ws = self.config.workspace
        # the path between samples too: linear in joint space, steps <= check_step_rad
        dq = np.diff(q, axis=0)
        steps = np.maximum(1, np.ceil(np.max(np.abs(dq), axis=1, initial=0.0) / ws.check_step_rad)).astype(int)
        seg = np.repeat(np.arange(len(dq)), steps)
        start = np.repeat(np.cumsum(steps) - steps, steps)
        frac = (np.arange(len(seg)) - start) / np.repeat(steps, steps)
        Q = np.vstack([q[seg] + frac[:, None] * dq[seg], q[-1:]])
        sample = np.concatenate([seg, [len(q) - 1]])
        F = self.kin.poses(Q)
        boxes = [("flange", F[:, :3, 3], ws.flange)]
        if ws.camera is not None:
            boxes.append(("camera", (F @ self.T_flange_cam)[:, :3, 3], ws.camera))
        for what, P, box in boxes:
            lo, hi = np.asarray(box.min_m), np.asarray(box.max_m)
            out = (P < lo) | (P > hi)
            if np.any(out):
                i, ax = (int(v) for v in np.argwhere(out)[0])
                k = int(sample[i])
                between = f" on the way to sample {k + 1}" if i < len(frac) and frac[i] > 0.0 else ""
                raise TrajectoryError(
                    f"workspace: sample {k} (t={times[k]:.3f} s){between}: the {what} at "
                    f"({P[i, 0]:.3f}, {P[i, 1]:.3f}, {P[i, 2]:.3f}) m leaves the {what} box on {'xyz'[ax]} "
                    f"[{lo[ax]:.3f}, {hi[ax]:.3f}] m")
