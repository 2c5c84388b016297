"""Time-optimal, jerk-limited joint motions with Ruckig (offline: computed once, then sampled).

A motion starts and ends at rest. All joints are time-synchronized (they start and finish
together), and the duration is a whole number of ``dt`` steps, so the samples are exactly
``times = k * dt`` and the last sample is the target. ``speed_factor`` scales the velocity,
acceleration and jerk limits alike (like franky's relative dynamics factor).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
import ruckig


@dataclass
class JointPath:
    """Sampled joint trajectory; same fields as ``drivers.interfaces.JointTrajectory``
    (``JointTrajectory(p.times, p.positions, p.velocities)``) plus accelerations."""

    times: np.ndarray  # (T,) s, times[0] == 0, strictly increasing, uniform step dt
    positions: np.ndarray  # (T, dof) rad
    velocities: np.ndarray  # (T, dof) rad/s
    accelerations: np.ndarray  # (T, dof) rad/s^2
    duration: float  # s, == times[-1]


def _vec(x, name: str, dof: int | None = None) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1 or (dof is not None and a.shape[0] != dof) or a.shape[0] == 0:
        want = f"({dof},)" if dof is not None else "(dof,)"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf: {a}")
    return a


def _check_common(max_vel, max_acc, max_jerk, speed_factor, dt, dof):
    limits = []
    for name, v in (("max_vel", max_vel), ("max_acc", max_acc), ("max_jerk", max_jerk)):
        a = _vec(v, name, dof)
        if not np.all(a > 0):
            raise ValueError(f"{name} must be strictly positive, got {a}")
        limits.append(a)
    real = isinstance(speed_factor, numbers.Real) and not isinstance(speed_factor, bool)
    if not (real and math.isfinite(speed_factor)):
        raise ValueError(f"speed_factor must be a finite number in (0, 1], got {speed_factor!r}")
    if not (0.0 < speed_factor <= 1.0):
        raise ValueError(f"speed_factor must be in (0, 1], got {speed_factor}")
    if not (isinstance(dt, numbers.Real) and not isinstance(dt, bool) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite positive number of seconds, got {dt!r}")
    return [a * float(speed_factor) for a in limits]


def _segment(q0, q1, vel, acc, jerk, dt, lower, upper) -> JointPath:
    dof = q0.shape[0]
    if np.array_equal(q0, q1):
        z = np.zeros((1, dof))
        return JointPath(np.zeros(1), q0[None].copy(), z, z.copy(), 0.0)
    otg = ruckig.Ruckig(dof, dt)
    inp = ruckig.InputParameter(dof)
    inp.current_position = q0.tolist()
    inp.current_velocity = [0.0] * dof
    inp.current_acceleration = [0.0] * dof
    inp.target_position = q1.tolist()
    inp.target_velocity = [0.0] * dof
    inp.target_acceleration = [0.0] * dof
    inp.max_velocity = vel.tolist()
    inp.max_acceleration = acc.tolist()
    inp.max_jerk = jerk.tolist()
    inp.duration_discretization = ruckig.DurationDiscretization.Discrete
    traj = ruckig.Trajectory(dof)
    try:
        result = otg.calculate(inp, traj)
    except RuntimeError as exc:  # ruckig.RuckigError derives from RuntimeError
        raise ValueError(f"ruckig rejected the motion {q0} -> {q1}: {exc}") from exc
    if result not in (ruckig.Result.Working, ruckig.Result.Finished):
        raise RuntimeError(f"ruckig failed to plan {q0} -> {q1}: {result}")

    n = max(1, int(round(traj.duration / dt)))
    times = np.arange(n + 1) * dt
    pos = np.empty((n + 1, dof))
    vel_s = np.empty((n + 1, dof))
    acc_s = np.empty((n + 1, dof))
    for i, t in enumerate(times):  # per time sample, not per point: ~1 us each
        p, v, a = traj.at_time(min(float(t), traj.duration))
        pos[i], vel_s[i], acc_s[i] = p, v, a
    pos[-1], vel_s[-1], acc_s[-1] = q1, 0.0, 0.0  # exact target, at rest
    if lower is not None or upper is not None:
        ext = traj.position_extrema
        pmin = np.array([e.min for e in ext])
        pmax = np.array([e.max for e in ext])
        if (lower is not None and np.any(pmin < lower - 1e-9)) or (upper is not None and np.any(pmax > upper + 1e-9)):
            raise ValueError(f"motion {q0} -> {q1} leaves the joint limits (extrema {pmin} .. {pmax})")
    return JointPath(times, pos, vel_s, acc_s, float(times[-1]))


def _check_limits_arg(lower, upper, dof):
    lo = None if lower is None else _vec(lower, "lower", dof)
    hi = None if upper is None else _vec(upper, "upper", dof)
    return lo, hi


def _check_inside(q, name, lo, hi):
    if lo is not None and np.any(q < lo):
        raise ValueError(f"{name} is below the lower joint limits at joints {np.nonzero(q < lo)[0].tolist()}: {q}")
    if hi is not None and np.any(q > hi):
        raise ValueError(f"{name} is above the upper joint limits at joints {np.nonzero(q > hi)[0].tolist()}: {q}")


def plan_joint_motion(
    q0: np.ndarray,
    q1: np.ndarray,
    max_vel: np.ndarray,
    max_acc: np.ndarray,
    max_jerk: np.ndarray,
    speed_factor: float = 1.0,
    dt: float = 0.01,
    *,
    lower: np.ndarray | None = None,
    upper: np.ndarray | None = None,
) -> JointPath:
    """Time-optimal rest-to-rest motion q0 -> q1 within velocity/acceleration/jerk limits.

    Args:
        q0, q1: start and goal joint positions (dof,), rad.
        max_vel, max_acc, max_jerk: per-joint limits (dof,), strictly positive.
        speed_factor: in (0, 1]; scales all three limits.
        dt: sample period, s; the duration is rounded up to a multiple of it.
        lower, upper: optional joint position limits; q0/q1 outside them, or a motion that
            leaves them, raise ValueError.

    Returns:
        JointPath sampled at ``k * dt``; a single sample (duration 0) when q0 == q1.

    Raises:
        ValueError: shapes, NaN/inf, non-positive limits, speed_factor outside (0, 1], dt <= 0,
            or a position limit violation; the message names the argument.
    """
    q0 = _vec(q0, "q0")
    dof = q0.shape[0]
    q1 = _vec(q1, "q1", dof)
    vel, acc, jerk = _check_common(max_vel, max_acc, max_jerk, speed_factor, dt, dof)
    lo, hi = _check_limits_arg(lower, upper, dof)
    _check_inside(q0, "q0", lo, hi)
    _check_inside(q1, "q1", lo, hi)
    return _segment(q0, q1, vel, acc, jerk, float(dt), lo, hi)


def plan_through(
    waypoints: np.ndarray,
    max_vel: np.ndarray,
    max_acc: np.ndarray,
    max_jerk: np.ndarray,
    speed_factor: float = 1.0,
    dt: float = 0.01,
    *,
    lower: np.ndarray | None = None,
    upper: np.ndarray | None = None,
) -> JointPath:
    """Chain of rest-to-rest motions through ``waypoints`` (K, dof), stopping at each one.

    Consecutive identical waypoints are merged. Same limits, arguments and errors as
    ``plan_joint_motion``; the result is one JointPath on a uniform ``dt`` grid.
    """
    W = np.asarray(waypoints, dtype=np.float64)
    if W.ndim != 2 or W.shape[0] == 0 or W.shape[1] == 0:
        raise ValueError(f"waypoints must have shape (K, dof) with K >= 1, got {W.shape}")
    if not np.all(np.isfinite(W)):
        bad = np.nonzero(~np.all(np.isfinite(W), axis=1))[0].tolist()
        raise ValueError(f"waypoints contain NaN or inf (rows {bad})")
    dof = W.shape[1]
    vel, acc, jerk = _check_common(max_vel, max_acc, max_jerk, speed_factor, dt, dof)
    lo, hi = _check_limits_arg(lower, upper, dof)
    for k, w in enumerate(W):
        _check_inside(w, f"waypoints[{k}]", lo, hi)

    segs = [_segment(W[k], W[k + 1], vel, acc, jerk, float(dt), lo, hi) for k in range(len(W) - 1)]
    segs = [s for s in segs if s.duration > 0.0]
    if not segs:
        z = np.zeros((1, dof))
        return JointPath(np.zeros(1), W[:1].copy(), z, z.copy(), 0.0)
    pos = [segs[0].positions]
    v = [segs[0].velocities]
    a = [segs[0].accelerations]
    n = len(segs[0].times) - 1
    for s in segs[1:]:  # drop each segment's first sample: it repeats the previous last one
        pos.append(s.positions[1:])
        v.append(s.velocities[1:])
        a.append(s.accelerations[1:])
        n += len(s.times) - 1
    times = np.arange(n + 1) * float(dt)
    return JointPath(times, np.concatenate(pos), np.concatenate(v), np.concatenate(a), float(times[-1]))
