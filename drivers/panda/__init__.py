"""The real Franka arm (Panda or FR3) through franky (libfranka + Ruckig): `arm.FrankaArm` implements
``drivers.interfaces.Arm``; `safety.SafetyChecker` refuses a trajectory before anything moves;
`config.FrankaConfig` is the ``arm:`` block of configs/cell.real.yaml. Never imports planners/,
cellctl/ or sim/."""

from drivers.panda.arm import ArmStatus, FrankaArm, preflight, probe
from drivers.panda.config import FrankaConfig, JointLimits
from drivers.panda.safety import SafetyChecker

__all__ = ["ArmStatus", "FrankaArm", "FrankaConfig", "JointLimits", "SafetyChecker",
           "preflight", "probe"]
