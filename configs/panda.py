"""The Franka Emika Panda, described once for every room: the URDF the twin and the planners load,
its joint and link names, and Franka's published joint limits. drivers/, sim/ and planners/ may
not import each other, and each needs the arm; they all may read configs/.

Limits as published by Franka (FCI docs, "Robot and interface specifications", Panda): radians,
rad/s, rad/s^2, rad/s^3, joint order 1..7. The URDF declares the hard (mechanical) position limits
``PANDA_Q_MIN_URDF`` / ``PANDA_Q_MAX_URDF``; Franka's controller enforces the narrower published
``PANDA_Q_MIN`` / ``PANDA_Q_MAX`` (the URDF's ``safety_controller`` soft limits). Its kinematics
equal the FR3's (same DH parameters; panda_hand = FR3 link8 rotated -45 deg about z), so one file
serves both models. All arrays are read-only float64 of shape (7,)."""

from __future__ import annotations

import os
from importlib.util import find_spec

import numpy as np


def _const(values: list[float]) -> np.ndarray:
    a = np.array(values, dtype=np.float64)
    a.setflags(write=False)
    return a


def _data_dir() -> str:
    """pybullet_data's folder, found without importing it (planners/ loads no simulator)."""
    spec = find_spec("pybullet_data")
    if spec is None or spec.origin is None:
        raise RuntimeError("pybullet_data is not installed: the Panda's URDF ships with it")
    return os.path.dirname(spec.origin)


PANDA_URDF = os.path.join(_data_dir(), "franka_panda", "panda.urdf")
JOINT_NAMES: tuple[str, ...] = tuple(f"panda_joint{i}" for i in range(1, 8))
BASE_LINK = "panda_link0"
FLANGE_LINK = "panda_hand"  # where the camera and the torch are mounted

# Published (controller-enforced) position limits, rad.
PANDA_Q_MIN = _const([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
PANDA_Q_MAX = _const([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
# Hard limits as written in the URDF, rad.
PANDA_Q_MIN_URDF = _const([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
PANDA_Q_MAX_URDF = _const([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
# Published joint-space velocity, acceleration and jerk limits.
PANDA_MAX_VELOCITY = _const([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])  # rad/s
PANDA_MAX_ACCELERATION = _const([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])  # rad/s^2
PANDA_MAX_JERK = _const([7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0])  # rad/s^3
PANDA_MAX_TORQUE = _const([87.0] * 4 + [12.0] * 3)  # Nm
# A comfortable "ready" configuration (Franka's default home pose), well inside all limits.
PANDA_Q_READY = _const([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])
