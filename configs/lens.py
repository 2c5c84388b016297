"""The D435's lens models (librealsense's ``rs2_project_point_to_pixel`` / ``rs2_deproject_pixel_to_point``
formulas), on normalized image coordinates x = (u - cx) / fx, y = (v - cy) / fy. Shared by the RealSense
driver (depth-to-colour alignment) and the planners (a frame's pixels back to rays), which may not import
each other. Brown-Conrady distorts on projection and is inverted by fixed-point iteration on deprojection;
Inverse Brown-Conrady the other way round."""

from __future__ import annotations

import numpy as np

#: librealsense's distortion model names (rs2_distortion_to_string) that are pinhole-plus-polynomial.
DISTORTION_MODELS = ("None", "Brown Conrady", "Modified Brown Conrady", "Inverse Brown Conrady")
INVERT_ITERATIONS = 10  # librealsense's count for its iterative undistortion
NO_DISTORTION = (0.0, 0.0, 0.0, 0.0, 0.0)


def distorted(model: str, k: tuple[float, ...]) -> bool:
    return model != "None" and any(c != 0.0 for c in k)


def _distort(x: np.ndarray, y: np.ndarray, model: str, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    r2 = x * x + y * y
    f = 1 + k[0] * r2 + k[1] * r2 * r2 + k[4] * r2 * r2 * r2
    if model == "Modified Brown Conrady":
        x, y = x * f, y * f
        return x + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x), y + 2 * k[3] * x * y + k[2] * (r2 + 2 * y * y)
    return x * f + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x), y * f + 2 * k[3] * x * y + k[2] * (r2 + 2 * y * y)


def _undistort(xd: np.ndarray, yd: np.ndarray, model: str, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    x, y = xd.copy(), yd.copy()
    for _ in range(INVERT_ITERATIONS):
        dx, dy = _distort(x, y, model, k)
        x, y = x + (xd - dx), y + (yd - dy)
    return x, y


def project(x: np.ndarray, y: np.ndarray, model: str, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A ray's pinhole coordinates to where the lens puts it in the image (still normalized)."""
    if not distorted(model, k):
        return x, y
    return (_undistort if model == "Inverse Brown Conrady" else _distort)(x, y, model, k)


def deproject(x: np.ndarray, y: np.ndarray, model: str, k: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A pixel's normalized coordinates to its ray's pinhole coordinates (z = 1)."""
    if not distorted(model, k):
        return x, y
    return (_distort if model == "Inverse Brown Conrady" else _undistort)(x, y, model, k)
