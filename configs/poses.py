"""A mount written in a config (xyz in metres, fixed-axis roll/pitch/yaw in degrees) as a 4x4 pose:
one convention for the hand-eye extrinsic (sim/) and the torch mount (planners/), which may not
import each other."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial.transform import Rotation

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


def pose_from_xyz_rpy_deg(xyz, rpy_deg) -> np.ndarray:
    """4x4 float64 transform: rotation from fixed-axis x, y, z angles (degrees), then translation."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()
    T[:3, 3] = xyz
    return T



class HandEyeBase(BaseModel):
    """T_flange_cam: the camera optical frame in the flange (``panda_hand``) frame; ``rpy_deg`` are
    fixed-axis roll, pitch, yaw (URDF convention, R = Rz(yaw) Ry(pitch) Rx(roll)). One model for the
    twin's and the real arm's extrinsic, so both are bounded and made a pose the same way."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)

    xyz: Vec3
    rpy_deg: Vec3

    @model_validator(mode="after")
    def _bounded(self) -> "HandEyeBase":
        if any(abs(v) > 0.5 for v in self.xyz):
            raise ValueError(f"hand-eye translation {self.xyz} exceeds 0.5 m per axis")
        if any(abs(v) > 360.0 for v in self.rpy_deg):
            raise ValueError(f"hand-eye rpy_deg {self.rpy_deg} outside [-360, 360]")
        return self

    def T_flange_cam(self) -> np.ndarray:
        """4x4 float64 T_flange_cam."""
        return pose_from_xyz_rpy_deg(self.xyz, self.rpy_deg)
