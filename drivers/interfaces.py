"""The contracts every arm and camera honours, so the twin and real devices are interchangeable.

Frames and units: SI everywhere; poses are 4x4 float64 ``T_<to>_<from>``; camera optical frame is
z forward, x right, y down. Depth is float32 metres with NaN where the sensor gave no return.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


class DeviceError(RuntimeError):
    """A device is missing, disconnected or returned something unusable."""


class TrajectoryError(RuntimeError):
    """A trajectory was refused or its execution failed."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the (color-aligned) depth image."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass
class RGBDFrame:
    """One aligned color + depth capture."""

    color: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 metres, NaN = no return
    intrinsics: Intrinsics
    timestamp: float  # seconds, monotonic clock of the producer

    def __post_init__(self) -> None:
        h, w = self.intrinsics.height, self.intrinsics.width
        if self.color.shape != (h, w, 3) or self.color.dtype != np.uint8:
            raise DeviceError(f"color image must be ({h}, {w}, 3) uint8, got {self.color.shape} {self.color.dtype}")
        if self.depth.shape != (h, w) or self.depth.dtype != np.float32:
            raise DeviceError(f"depth image must be ({h}, {w}) float32, got {self.depth.shape} {self.depth.dtype}")


@dataclass
class JointTrajectory:
    """Time-parameterized joint path, sampled densely enough to follow by position control."""

    times: np.ndarray  # (T,) seconds from start, strictly increasing, times[0] == 0
    positions: np.ndarray  # (T, 7) radians
    velocities: np.ndarray | None = None  # (T, 7) rad/s

    @property
    def duration(self) -> float:
        return float(self.times[-1]) if len(self.times) else 0.0


@dataclass(frozen=True)
class ArmModel:
    """What planners need to know about an arm: its kinematics file and its limits."""

    urdf_path: str
    base_link: str
    flange_link: str  # the link the camera (and later the torch) is mounted on
    joint_names: tuple[str, ...]
    lower: np.ndarray = field(repr=False)
    upper: np.ndarray = field(repr=False)
    max_velocity: np.ndarray = field(repr=False)
    max_acceleration: np.ndarray = field(repr=False)
    max_jerk: np.ndarray = field(repr=False)
    T_flange_cam: np.ndarray = field(repr=False)  # hand-eye extrinsic


@runtime_checkable
class Arm(Protocol):
    model: ArmModel

    def joint_positions(self) -> np.ndarray:
        """Current joint angles (7,), radians. Non-blocking."""

    def execute(self, trajectory: JointTrajectory) -> float:
        """Follow a trajectory; blocks until done. Returns the max joint tracking error (rad).
        Raises TrajectoryError if refused or aborted."""

    def stop(self) -> None:
        """Stop any motion as soon as possible."""

    def camera_pose(self) -> np.ndarray:
        """T_base_cam from the arm's own forward kinematics and the hand-eye extrinsic."""


@runtime_checkable
class RGBDCamera(Protocol):
    intrinsics: Intrinsics

    def capture(self) -> RGBDFrame:
        """Block until the next frame; raises DeviceError on timeout or a broken device."""
