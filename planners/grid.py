"""The probabilistic occupancy grid of §V-B: log-odds per cell over a bounded workspace, unknown
cells at exactly 0.5, free space carved along each pixel ray, and the drawing's frontier."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from planners import raycast
from planners.config import GridConfig

_N26 = np.ones((3, 3, 3), dtype=bool)
_N6 = ndimage.generate_binary_structure(3, 1)


class OccupancyGrid:
    def __init__(self, cfg: GridConfig):
        self.cfg = cfg
        self.voxel = float(cfg.voxel_m)
        self.lo = np.asarray(cfg.lo_m, dtype=np.float64)
        hi = np.asarray(cfg.hi_m, dtype=np.float64)
        self.shape = tuple(int(round(s)) for s in (hi - self.lo) / self.voxel)
        self.hi = self.lo + np.asarray(self.shape) * self.voxel
        self.logodds = np.zeros(self.shape, dtype=np.float32)
        self.drawing = np.zeros(self.shape, dtype=bool)
        self.shadow = np.zeros(self.shape, dtype=bool)  # unknown cells that some ray ended just before
        self._marks = np.zeros(int(np.prod(self.shape)), dtype=np.int8)

    # --- geometry -----------------------------------------------------------------------------
    def index_of(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices (N,3) of points and a mask of those inside the grid."""
        ijk = np.floor((np.asarray(xyz, dtype=np.float64) - self.lo) / self.voxel).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(self.shape)), axis=1)
        return ijk, inside

    def centers(self, ijk: np.ndarray) -> np.ndarray:
        return self.lo + (np.asarray(ijk, dtype=np.float64) + 0.5) * self.voxel

    # --- updates ------------------------------------------------------------------------------
    def integrate(self, origin: np.ndarray, points: np.ndarray, truncation_voxels: float = 1.0) -> None:
        """One scan: every touched cell is updated once (hit wins over free), log-odds clamped."""
        if len(points) == 0:
            return
        marks = self._marks
        marks[:] = 0
        raycast.mark_scan(np.ascontiguousarray(origin, dtype=np.float64), np.ascontiguousarray(points, dtype=np.float64),
                          self.lo, self.voxel, np.asarray(self.shape, dtype=np.int64),
                          float(truncation_voxels), float(self.cfg.shadow_depth_m), marks)
        flat = self.logodds.reshape(-1)
        free = marks == raycast.FREE
        hit = marks == raycast.HIT
        flat[free] = np.maximum(flat[free] + self.cfg.l_miss, self.cfg.l_min)
        flat[hit] = np.minimum(flat[hit] + self.cfg.l_hit, self.cfg.l_max)
        self.shadow.reshape(-1)[marks == raycast.SHADOW] = True

    def set_drawing(self, drawing_xyz: np.ndarray) -> None:
        """Label the cells that hold drawing points (recomputed from D_total every step)."""
        self.drawing[:] = False
        if len(drawing_xyz):
            ijk, inside = self.index_of(drawing_xyz)
            ijk = ijk[inside]
            self.drawing[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True

    # --- states -------------------------------------------------------------------------------
    @property
    def occupied(self) -> np.ndarray:
        return self.logodds > 0

    @property
    def free(self) -> np.ndarray:
        return self.logodds < 0

    @property
    def unknown(self) -> np.ndarray:
        return self.logodds == 0

    def probability(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.logodds))

    def frontier(self, reach: int = 1) -> np.ndarray:
        """Cells with an unknown neighbour and a drawing neighbour (§V-B). Only unknown cells that
        touch observed free space count: the inside of a solid object is unknown forever and
        would otherwise make every drawing cell a frontier. `reach` > 1 lets the unknown be that many
        cells away, so a drawing broken by small gaps (a basket of bars) still has a frontier."""
        out = np.zeros(self.shape, dtype=bool)
        ijk = np.argwhere(self.drawing)
        if len(ijk) == 0:
            return out
        # only cells next to the drawing can qualify: work on its bounding box (+3 cells of context)
        pad = reach + 2
        lo = np.maximum(ijk.min(axis=0) - pad, 0)
        hi = np.minimum(ijk.max(axis=0) + pad + 1, self.shape)
        box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
        L = self.logodds[box]
        unknown = L == 0
        open_unknown = unknown & ndimage.binary_dilation(L < 0, structure=_N6)
        near_unknown = ndimage.binary_dilation(open_unknown, structure=_N26, iterations=reach)
        near_drawing = ndimage.binary_dilation(self.drawing[box], structure=_N26)
        out[box] = near_unknown & near_drawing & ~unknown
        return out


def frontier_clusters(frontier: np.ndarray, min_size: int) -> tuple[np.ndarray, int]:
    """Connected components (26-neighbourhood) of the frontier, small ones dropped as noise.
    Returns (labels with 0 = none, number of clusters) relabelled 1..n."""
    box = ndimage.find_objects(frontier.astype(np.int8))  # label only the box round the frontier
    full = np.zeros(frontier.shape, dtype=np.int32)
    if not box or box[0] is None:
        return full, 0
    labels, n = ndimage.label(frontier[box[0]], structure=_N26)
    if n == 0:
        return full, 0
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= min_size
    keep[0] = False
    remap = np.zeros(n + 1, dtype=np.int32)
    remap[keep] = np.arange(1, int(keep.sum()) + 1)
    full[box[0]] = remap[labels]
    return full, int(keep.sum())
