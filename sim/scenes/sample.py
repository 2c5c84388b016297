"""The paint sample of `cellctl calibrate paint` in the twin: a plate of the yard's scrap with a stroke of
its paint across the middle, held square in front of the camera as an operator holds it."""

from __future__ import annotations

import numpy as np
import trimesh

from sim.appearance import Appearance
from sim.scenes.model import Scene
from sim.scenes.paint import paint_surface, sample_painted

SAMPLE_DISTANCE_M = 0.35  # from the camera: the D435 sees 0.48 x 0.27 m there
SAMPLE_SIZE_M = (0.6, 0.4, 0.008)  # bigger than the picture: bare metal on every side of it
STROKE_M, STROKE_WIDTH_M = 0.11, 0.045  # the sprayed patch, along the picture's width


def paint_sample(T_base_cam: np.ndarray, appearance: Appearance, *, painted: bool = True,
                 distance_m: float = SAMPLE_DISTANCE_M) -> Scene:
    """The sample facing the camera at ``T_base_cam`` (optical frame: z forward), ``distance_m`` away,
    in ``appearance``'s finish, paint and light; ``painted`` False: bare metal only."""
    T_cam_sample = np.diag([1.0, -1.0, -1.0, 1.0])  # the plate's top (+z) faces the camera
    T_cam_sample[2, 3] = distance_m
    T = np.asarray(T_base_cam, dtype=np.float64) @ T_cam_sample
    sx, sy, sz = SAMPLE_SIZE_M
    plate = trimesh.creation.box(extents=(sx, sy, sz))
    plate.apply_translation((0.0, 0.0, -sz / 2))
    lines: list[np.ndarray] = []
    paint = trimesh.Trimesh()
    obj = plate
    if painted:
        x = np.linspace(-STROKE_M / 2, STROKE_M / 2, 12)
        stroke = np.column_stack([x, 0.006 * np.sin(x / STROKE_M * np.pi), np.zeros_like(x)])
        obj, paint, lines = paint_surface(plate, [stroke], STROKE_WIDTH_M)
        paint.apply_transform(T)
    obj.apply_transform(T)
    lines = [p @ T[:3, :3].T + T[:3, 3] for p in lines]
    return Scene(name="paint-sample", category=None, object_mesh=obj, paint_mesh=paint, drawing_polylines=lines,
                 drawing_width=STROKE_WIDTH_M,
                 gt_points=sample_painted(paint) if painted else np.zeros((0, 3), np.float32),
                 extremities=np.zeros((0, 3)), appearance=appearance)
