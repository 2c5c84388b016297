"""Franka Emika Panda joint limits, as published by Franka (FCI docs, "Robot and interface
specifications", limits for the Panda arm). Radians, rad/s, rad/s^2, rad/s^3; joint order 1..7.

The URDF shipped in ``pybullet_data/franka_panda/panda.urdf`` declares the *hard* (mechanical)
position limits ``PANDA_Q_MIN_URDF`` / ``PANDA_Q_MAX_URDF``; Franka's controller enforces the
narrower published limits ``PANDA_Q_MIN`` / ``PANDA_Q_MAX`` (the URDF's ``safety_controller``
soft limits). Commanding a real Panda outside the published limits aborts the motion, so motion
planning for the real arm should use the published ones (``Kinematics(..., lower=PANDA_Q_MIN,
upper=PANDA_Q_MAX)``); the kinematics class intersects them with whatever the URDF says.

All constants are read-only float64 arrays of shape (7,).
"""

from __future__ import annotations

import numpy as np


def _const(values: list[float]) -> np.ndarray:
    a = np.array(values, dtype=np.float64)
    a.setflags(write=False)
    return a


PANDA_JOINT_NAMES: tuple[str, ...] = tuple(f"panda_joint{i}" for i in range(1, 8))

# Published (controller-enforced) position limits, rad.
PANDA_Q_MIN = _const([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
PANDA_Q_MAX = _const([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])

# Hard limits as written in pybullet_data's franka_panda/panda.urdf, rad.
PANDA_Q_MIN_URDF = _const([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
PANDA_Q_MAX_URDF = _const([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])

# Published joint-space velocity, acceleration and jerk limits.
PANDA_MAX_VELOCITY = _const([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])  # rad/s
PANDA_MAX_ACCELERATION = _const([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])  # rad/s^2
PANDA_MAX_JERK = _const([7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0])  # rad/s^3

# A comfortable "ready" configuration (Franka's default home pose), well inside all limits.
PANDA_Q_READY = _const([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])

__all__ = [
    "PANDA_JOINT_NAMES",
    "PANDA_Q_MIN",
    "PANDA_Q_MAX",
    "PANDA_Q_MIN_URDF",
    "PANDA_Q_MAX_URDF",
    "PANDA_MAX_VELOCITY",
    "PANDA_MAX_ACCELERATION",
    "PANDA_MAX_JERK",
    "PANDA_Q_READY",
]
