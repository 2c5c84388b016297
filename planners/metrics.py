"""The paper's benchmarking metrics (§VI-C): coverage (eq. 13) and displacement (eq. 12)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planners.clouds import voxel_keys


@dataclass
class Coverage:
    hit: int
    total: int

    @property
    def fraction(self) -> float:
        return self.hit / self.total if self.total else 0.0

    @property
    def percent(self) -> float:
        return 100.0 * self.fraction


def coverage(reconstruction: np.ndarray, ground_truth: np.ndarray, voxel: float) -> Coverage:
    """card(vox(C) ∩ vox(G)) / card(vox(G)) on one common grid anchored at the base-frame origin."""
    if len(ground_truth) == 0:
        raise ValueError("ground truth cloud is empty: coverage is undefined")
    g = np.unique(voxel_keys(np.asarray(ground_truth, dtype=np.float64), voxel))
    if len(reconstruction) == 0:
        return Coverage(0, len(g))
    c = np.unique(voxel_keys(np.asarray(reconstruction, dtype=np.float64), voxel))
    return Coverage(int(np.isin(g, c, assume_unique=True).sum()), len(g))


def displacement(positions: np.ndarray) -> float:
    """Eq. 12: summed straight-line distance between consecutive viewpoints, initial one included."""
    p = np.asarray(positions, dtype=np.float64)
    if len(p) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
