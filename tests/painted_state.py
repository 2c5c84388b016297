"""A scan state built from one synthetic view: a surface sampled as points, the part of it that
is painted, and the camera that saw it. Shared by the planner tests that need a state by hand."""

from __future__ import annotations

import numpy as np

from planners.base import ScanState
from planners.clouds import Cloud
from planners.grid import OccupancyGrid
from planners.views import look_at_rotations


def painted_state(grid: OccupancyGrid, pts: np.ndarray, paint: np.ndarray, cam: np.ndarray, aim: np.ndarray,
                  K: np.ndarray, image_size: tuple[int, int], step: int = 0) -> ScanState:
    """The state after ``step + 1`` views all from ``cam`` looking at ``aim``: ``pts`` (already
    integrated into ``grid`` as the caller wants) as the surface, ``paint`` of them the drawing."""
    origin = np.broadcast_to(cam, pts.shape).astype(np.float32).copy()
    rgb = np.where(paint[:, None], [220, 20, 20], [120, 120, 120]).astype(np.uint8)
    surface = Cloud(pts.astype(np.float32), rgb, origin)
    drawing = surface.select(paint)
    grid.set_drawing(drawing.xyz)
    T = np.eye(4)
    T[:3, :3] = look_at_rotations(cam[None], np.asarray(aim, dtype=np.float64)[None])[0]
    T[:3, 3] = cam
    return ScanState(step, grid, surface, drawing, surface, T, T, K, image_size, np.tile(cam, (step + 1, 1)))
