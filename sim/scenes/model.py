"""A scene as the twin and the metrics see it, everything already in the robot base frame."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from sim.appearance import Appearance


@dataclass
class Scene:
    name: str
    category: int | None  # the paper's object category 1..6, None for user scenes
    object_mesh: trimesh.Trimesh  # base frame, metres: the unpainted faces
    paint_mesh: trimesh.Trimesh  # base frame: the painted faces (disjoint from object_mesh)
    drawing_polylines: list[np.ndarray]  # base frame, each (K, 3), lying on the surface
    drawing_width: float  # metres
    gt_points: np.ndarray  # (N, 3) float32, dense samples of the painted surface (ground truth)
    extremities: np.ndarray  # (E, 3) free ends of the drawing, base frame
    object_rgb: tuple[float, float, float] = (0.42, 0.40, 0.38)
    paint_rgb: tuple[float, float, float] = (0.85, 0.05, 0.05)
    initial_camera_pose: np.ndarray | None = None  # T_base_cam if the scene file fixes it
    initial_view_candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    # (M, 4, 4) T_base_cam poses that each see part of the drawing, best first; the runner takes
    # the first one the arm can reach (the paper's task #1 is assumed done).
    appearance: Appearance | None = None  # finish, paint and light (sim.appearance); None: the flat colours above

    @property
    def full_mesh(self) -> trimesh.Trimesh:
        return trimesh.util.concatenate([self.object_mesh, self.paint_mesh])
