"""Did the last view find drawing? A view that added (almost) no drawing voxels resolved nothing at its
target, whatever its predicted gain said (a grazing surface, a gap the sensor drops): that target is
given up at once instead of being looked at again from the next cone."""

from __future__ import annotations

import numpy as np

from planners.grid import OccupancyGrid


class GrowthWatch:
    def __init__(self, min_growth_voxels: int):
        self.min_growth = int(min_growth_voxels)
        self._pending: tuple[int, np.ndarray, int] | None = None  # (step, target, drawing voxels then)

    def planned(self, step: int, target: np.ndarray, grid: OccupancyGrid) -> None:
        self._pending = (step, np.asarray(target, dtype=np.float64), int(np.count_nonzero(grid.drawing)))

    def retarget(self, target: np.ndarray) -> None:
        if self._pending is not None:
            step, _, before = self._pending
            self._pending = (step, np.asarray(target, dtype=np.float64), before)

    def fruitless(self, step: int, grid: OccupancyGrid) -> np.ndarray | None:
        """The target of the previous step's view if that view grew the drawing by less than the
        threshold. Replans within one step (no view taken yet) never count."""
        if self._pending is None or self.min_growth <= 0 or step <= self._pending[0]:
            return None
        _, target, before = self._pending
        self._pending = None
        return target if int(np.count_nonzero(grid.drawing)) - before < self.min_growth else None


class EdgeYield:
    """Drawing cells an edge view (planners.open_edges) finds per open point it was counted on to
    see further round. Before any edge view is measured, a border's points lie ``surface_voxel``
    apart, so one cell per cell-long border. After each one, what that view found. On thin stock
    whose flanks the sensor returns only in part, the count of points a view would see round stays
    high while what views find there dries up: the measured yield says so, and a view expected to
    grow the drawing by less than ``GrowthWatch`` asks of a view is not taken."""

    def __init__(self, surface_voxel: float):
        self.surface_voxel = float(surface_voxel)
        self.per_point: float | None = None  # measured; None: the prior
        self._pending: tuple[int, np.ndarray, np.ndarray, np.ndarray, int] | None = None

    def expected(self, counts: np.ndarray, grid: OccupancyGrid) -> np.ndarray:
        """Drawing cells views counted on ``counts`` open points each are expected to add."""
        per_point = self.surface_voxel / grid.voxel if self.per_point is None else self.per_point
        return np.asarray(counts, dtype=np.float64) * per_point

    def planned(self, step: int, poses: np.ndarray, counts: np.ndarray, grid: OccupancyGrid) -> None:
        """An edge plan (ranked poses (C,4,4) and each one's count of points): the runner takes one."""
        self._pending = (step, poses[:, :3, 3].copy(), poses[:, :3, 0].copy(), np.asarray(counts, dtype=np.float64),
                         int(np.count_nonzero(grid.drawing)))

    def measure(self, step: int, camera_pose: np.ndarray, grid: OccupancyGrid) -> None:
        """At the step after an edge plan: the yield of the candidate the camera now stands at (by
        position, then roll). Another view in between, or none of the candidates reached within
        two cells: no measurement, the last yield stands."""
        if self._pending is None or step <= self._pending[0]:
            return
        planned_at, eyes, x_axes, counts, before = self._pending
        self._pending = None
        d = np.linalg.norm(eyes - camera_pose[:3, 3], axis=1)
        if step != planned_at + 1 or d.min() > 2 * grid.voxel:
            return
        at = np.flatnonzero(d <= d.min() + 1e-9)
        taken = at[np.argmax(x_axes[at] @ camera_pose[:3, 0])]
        found = max(int(np.count_nonzero(grid.drawing)) - before, 0)
        self.per_point = found / max(counts[taken], 1.0)
