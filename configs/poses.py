"""A mount written in a config (xyz in metres, fixed-axis roll/pitch/yaw in degrees) as a 4x4 pose:
one convention for the hand-eye extrinsic (sim/) and the torch mount (planners/), which may not
import each other."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def pose_from_xyz_rpy_deg(xyz, rpy_deg) -> np.ndarray:
    """4x4 float64 transform: rotation from fixed-axis x, y, z angles (degrees), then translation."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()
    T[:3, 3] = xyz
    return T
