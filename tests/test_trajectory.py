"""Ruckig joint motions: endpoints, limits, speed factor, validation."""

from __future__ import annotations

import numpy as np
import pytest

from planners.motion.limits import (
    PANDA_MAX_ACCELERATION,
    PANDA_MAX_JERK,
    PANDA_MAX_VELOCITY,
    PANDA_Q_MAX,
    PANDA_Q_MIN,
    PANDA_Q_READY,
)
from planners.motion.trajectory import JointPath, plan_joint_motion, plan_through

LIMITS = (PANDA_MAX_VELOCITY, PANDA_MAX_ACCELERATION, PANDA_MAX_JERK)
Q1 = PANDA_Q_READY + np.array([1.0, 0.5, -1.0, 0.5, 2.0, -1.0, 1.5])


def random_pairs(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield rng.uniform(PANDA_Q_MIN, PANDA_Q_MAX), rng.uniform(PANDA_Q_MIN, PANDA_Q_MAX)


def check_path(path: JointPath, q0, q1, speed_factor: float, dt: float) -> None:
    T = len(path.times)
    assert path.positions.shape == (T, 7) and path.velocities.shape == (T, 7)
    assert path.times[0] == 0.0 and np.all(np.diff(path.times) > 0)
    np.testing.assert_allclose(np.diff(path.times), dt, atol=1e-12)
    assert path.duration == pytest.approx(path.times[-1])
    np.testing.assert_allclose(path.positions[0], q0, atol=1e-9)
    np.testing.assert_allclose(path.positions[-1], q1, atol=1e-12)
    np.testing.assert_allclose(path.velocities[[0, -1]], 0.0, atol=1e-9)
    # finite differences of the samples stay within the scaled limits
    v_fd = np.diff(path.positions, axis=0) / dt
    a_fd = np.diff(path.velocities, axis=0) / dt
    a_fd2 = np.diff(path.positions, n=2, axis=0) / dt**2
    assert np.all(np.abs(v_fd) <= PANDA_MAX_VELOCITY * speed_factor * (1 + 1e-6) + 1e-9)
    assert np.all(np.abs(a_fd) <= PANDA_MAX_ACCELERATION * speed_factor * (1 + 1e-6) + 1e-9)
    assert np.all(np.abs(a_fd2) <= PANDA_MAX_ACCELERATION * speed_factor * (1 + 1e-6) + 1e-9)
    # the analytic samples too
    assert np.all(np.abs(path.velocities) <= PANDA_MAX_VELOCITY * speed_factor * (1 + 1e-9))
    assert np.all(np.abs(path.accelerations) <= PANDA_MAX_ACCELERATION * speed_factor * (1 + 1e-9))
    # rest-to-rest: no overshoot beyond the segment's endpoints
    lo, hi = np.minimum(q0, q1), np.maximum(q0, q1)
    assert np.all(path.positions >= lo - 1e-9) and np.all(path.positions <= hi + 1e-9)


@pytest.mark.parametrize("speed_factor", [1.0, 0.5, 0.1])
def test_endpoints_and_limits(speed_factor):
    for q0, q1 in random_pairs(10, seed=int(speed_factor * 10)):
        path = plan_joint_motion(q0, q1, *LIMITS, speed_factor=speed_factor, dt=0.01)
        check_path(path, q0, q1, speed_factor, 0.01)


def test_fine_sampling_1khz():
    path = plan_joint_motion(PANDA_Q_READY, Q1, *LIMITS, speed_factor=1.0, dt=0.001)
    check_path(path, PANDA_Q_READY, Q1, 1.0, 0.001)


def test_speed_factor_shrinks_duration():
    fast = plan_joint_motion(PANDA_Q_READY, Q1, *LIMITS, speed_factor=1.0)
    slow = plan_joint_motion(PANDA_Q_READY, Q1, *LIMITS, speed_factor=0.5)
    assert fast.duration < slow.duration
    assert slow.duration >= 1.5 * fast.duration  # limited by velocity/accel: roughly x2


def test_time_optimal_lower_bound():
    # no joint may beat its own bang-bang (velocity-limited) minimum time
    path = plan_joint_motion(PANDA_Q_READY, Q1, *LIMITS)
    d = np.abs(Q1 - PANDA_Q_READY)
    assert path.duration >= np.max(d / PANDA_MAX_VELOCITY)


def test_zero_motion():
    path = plan_joint_motion(PANDA_Q_READY, PANDA_Q_READY, *LIMITS)
    assert path.duration == 0.0 and path.positions.shape == (1, 7)
    np.testing.assert_allclose(path.positions[0], PANDA_Q_READY)


def test_plan_through_rests_at_waypoints():
    W = np.stack([PANDA_Q_READY, Q1, Q1, PANDA_Q_READY + 0.3, PANDA_Q_READY])
    path = plan_through(W, *LIMITS, speed_factor=0.8, dt=0.01)
    np.testing.assert_allclose(np.diff(path.times), 0.01, atol=1e-12)
    np.testing.assert_allclose(path.positions[-1], W[-1])
    total = sum(plan_joint_motion(a, b, *LIMITS, speed_factor=0.8).duration for a, b in zip(W[:-1], W[1:]))
    assert path.duration == pytest.approx(total)
    for w in W:  # every waypoint is visited, at rest
        k = np.argmin(np.linalg.norm(path.positions - w, axis=1))
        assert np.linalg.norm(path.positions[k] - w) < 1e-9
        assert np.abs(path.velocities[k]).max() < 1e-9
    v_fd = np.diff(path.positions, axis=0) / 0.01
    assert np.all(np.abs(v_fd) <= PANDA_MAX_VELOCITY * 0.8 * (1 + 1e-6))


def test_position_limits_checked():
    with pytest.raises(ValueError, match="q1"):
        plan_joint_motion(PANDA_Q_READY, PANDA_Q_MAX + 0.1, *LIMITS, lower=PANDA_Q_MIN, upper=PANDA_Q_MAX)
    path = plan_joint_motion(PANDA_Q_READY, PANDA_Q_MAX, *LIMITS, lower=PANDA_Q_MIN, upper=PANDA_Q_MAX)
    assert np.all(path.positions <= PANDA_Q_MAX + 1e-12)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"q0": np.full(7, np.nan)}, "q0"),
        ({"q1": np.array([0, 0, 0, np.inf, 0, 0, 0.0])}, "q1"),
        ({"q1": np.zeros(6)}, "q1"),
        ({"max_vel": np.full(7, np.nan)}, "max_vel"),
        ({"max_acc": -PANDA_MAX_ACCELERATION}, "max_acc"),
        ({"max_jerk": np.zeros(7)}, "max_jerk"),
        ({"speed_factor": 0.0}, "speed_factor"),
        ({"speed_factor": 1.5}, "speed_factor"),
        ({"speed_factor": -0.5}, "speed_factor"),
        ({"speed_factor": float("nan")}, "speed_factor"),
        ({"dt": 0.0}, "dt"),
        ({"dt": float("inf")}, "dt"),
    ],
)
def test_invalid_input(kwargs, name):
    args = dict(q0=PANDA_Q_READY, q1=Q1, max_vel=PANDA_MAX_VELOCITY, max_acc=PANDA_MAX_ACCELERATION,
                max_jerk=PANDA_MAX_JERK, speed_factor=1.0, dt=0.01)
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        plan_joint_motion(**args)


def test_plan_through_invalid():
    with pytest.raises(ValueError, match="waypoints"):
        plan_through(np.array([PANDA_Q_READY, np.full(7, np.nan)]), *LIMITS)
    with pytest.raises(ValueError, match="waypoints"):
        plan_through(np.zeros((0, 7)), *LIMITS)
    with pytest.raises(ValueError, match="speed_factor"):
        plan_through(np.stack([PANDA_Q_READY, Q1]), *LIMITS, speed_factor=2.0)
