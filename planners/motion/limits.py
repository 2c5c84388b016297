"""Franka Emika Panda joint limits for motion planning, from the one description of the arm
(configs/panda.py, where the published and the URDF limits are explained). Motion planning for the
real arm uses the published ones (``Kinematics(..., lower=PANDA_Q_MIN, upper=PANDA_Q_MAX)``); the
kinematics class intersects them with whatever the URDF says."""

from __future__ import annotations

from configs.panda import JOINT_NAMES as PANDA_JOINT_NAMES
from configs.panda import (PANDA_MAX_ACCELERATION, PANDA_MAX_JERK, PANDA_MAX_VELOCITY, PANDA_Q_MAX, PANDA_Q_MAX_URDF,
                           PANDA_Q_MIN, PANDA_Q_MIN_URDF, PANDA_Q_READY)

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
