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
