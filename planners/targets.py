"""Which parts of the frontier still deserve a view, kept the same way for G-NBV and C-NBV: the
frontier in clusters; a cluster is dropped once given up (unreachable, or two views that found no
drawing there), once its drawing visibly ended (`ends.ended`) or is sealed all round (`ends.sealed`),
or after `max_target_visits` views at it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from planners import ends
from planners.base import ScanState
from planners.config import PlannersConfig
from planners.grid import frontier_clusters
from planners.growth import GrowthWatch


@dataclass
class Clusters:
    """The frontier of one step: cell centres, their cluster label, per cluster the centroid and
    whether it still deserves a view."""

    centers: np.ndarray  # (M, 3) frontier cell centres
    ijk: np.ndarray  # (M, 3) their cell indices
    lab: np.ndarray  # (M,) cluster of each cell, 0..n-1
    cents: np.ndarray  # (n, 3) centroids
    usable: np.ndarray  # (n,) bool


class TargetBook:
    def __init__(self, cfg: PlannersConfig):
        self.cfg = cfg.nbv
        self._surface_voxel = cfg.grid.surface_voxel_m
        self.targets: list[np.ndarray] = []  # the target of every plan handed out
        self.target_steps: list[int] = []  # the step each was planned at
        self.given_up: list[np.ndarray] = []  # targets that proved unreachable or without gain
        self.fruitless: list[np.ndarray] = []  # targets whose view found no drawing (once)
        self._growth = GrowthWatch(self.cfg.min_view_growth_voxels)
        self._failed: dict[tuple, int] = {}  # target -> plans on it the runner could not reach

    def give_up(self, target: np.ndarray) -> None:
        self.given_up.append(np.asarray(target, dtype=np.float64))

    def unreachable(self, targets: np.ndarray) -> None:
        """The runner reached none of a plan's candidates, which looked at ``targets`` (one row per
        candidate tried). A target whose candidates failed in two plans is given up: what is left
        of it is seen only from where the arm does not go."""
        for c in np.unique(np.asarray(targets, dtype=np.float64).reshape(-1, 3), axis=0):
            key = tuple(np.round(c, 4))
            self._failed[key] = self._failed.get(key, 0) + 1
            if self._failed[key] >= 2:
                self.give_up(c)

    def planned(self, state: ScanState, target: np.ndarray) -> None:
        """Book the plan's target. A replan within the same step (the runner reached none of the
        previous plan's candidates) supersedes the previous booking: only a view taken is a visit."""
        if self.target_steps and self.target_steps[-1] == state.step:
            self.targets.pop()
            self.target_steps.pop()
        self.targets.append(np.asarray(target, dtype=np.float64))
        self.target_steps.append(state.step)
        self._growth.planned(state.step, target, state.grid)

    def retarget(self, target: np.ndarray) -> None:
        """The view actually taken looked at another target than the plan's first candidate (the
        runner took a lower-ranked one): book the view on that target."""
        if self.targets:
            self.targets[-1] = np.asarray(target, dtype=np.float64)
            self._growth.retarget(target)

    def taken(self, state: ScanState, eyes: np.ndarray, owners: np.ndarray) -> None:
        """The last plan ranked candidates `eyes` looking at targets `owners`: the view taken is the
        one nearest to where the camera is now, and is booked on its target."""
        self.retarget(owners[int(np.argmin(np.linalg.norm(eyes - state.camera_pose[:3, 3], axis=1)))])

    def after_view(self, state: ScanState) -> None:
        """A view that found no drawing: its target is marked fruitless (G-NBV then tries it once more
        without a viewing cone: at an edge the drawing goes on round the corner) and given up if it
        was fruitless before."""
        fruitless = self._growth.fruitless(state.step, state.grid)
        if fruitless is not None:
            again = self.was_fruitless(fruitless, state.grid.voxel)
            (self.given_up if again else self.fruitless).append(fruitless)

    def was_fruitless(self, target: np.ndarray, voxel: float) -> bool:
        return any(np.linalg.norm(f - target) < 6 * voxel for f in self.fruitless)

    def views_of(self, target: np.ndarray, state: ScanState) -> np.ndarray:
        """Viewpoints already spent on (nearly) this target: seeing it again from there is pointless."""
        near = 6.0 * state.grid.voxel
        idx = [s + 1 for t, s in zip(self.targets, self.target_steps)
               if s + 1 < len(state.viewpoints) and np.linalg.norm(t - target) < near]
        return state.viewpoints[idx] if idx else np.zeros((0, 3))

    def clusters(self, state: ScanState) -> Clusters:
        cfg, grid = self.cfg, state.grid
        labels, n = frontier_clusters(grid.frontier(cfg.frontier_reach_voxels), cfg.min_frontier_cluster)
        ijk = np.argwhere(labels > 0)
        if n == 0:
            return Clusters(np.zeros((0, 3)), ijk, np.zeros(0, int), np.zeros((0, 3)), np.zeros(0, bool))
        lab = labels[ijk[:, 0], ijk[:, 1], ijk[:, 2]] - 1
        centers = grid.centers(ijk)
        counts = np.bincount(lab, minlength=n)
        cents = np.stack([np.bincount(lab, weights=centers[:, a], minlength=n) for a in range(3)], axis=1)
        cents /= np.maximum(counts, 1)[:, None]
        usable = np.ones(n, dtype=bool)
        near = 3.0 * grid.voxel
        if self.given_up:
            G = np.asarray(self.given_up)
            d, idx = cKDTree(centers).query(G, k=1)
            usable[lab[idx[d < near]]] = False
            # a centroid can lie off its cells (a curved cluster): near a given-up centroid counts too
            usable &= np.linalg.norm(cents[:, None, :] - G[None, :, :], axis=2).min(axis=1) >= 2 * near
        for c in np.flatnonzero(usable):  # a handful of clusters
            if ends.ended(state.drawing.xyz, state.surface.xyz, cents[c], cfg):
                usable[c] = False
        usable &= ~self._sealed(state, centers, lab, n)
        if self.targets:
            T = np.asarray(self.targets)
            visits = (np.linalg.norm(cents[:, None, :] - T[None, :, :], axis=2) < 2 * near).sum(axis=1)
            usable &= visits < cfg.max_target_visits
        return Clusters(centers, ijk, lab, cents, usable)

    def _sealed(self, state: ScanState, centers: np.ndarray, lab: np.ndarray, n: int) -> np.ndarray:
        """Per cluster: is every drawing point next to its cells sealed (ends.sealed), so the paint's
        whole border there was seen and no view can find more of the line there?"""
        out = np.zeros(n, dtype=bool)
        drawing, surface = state.drawing.xyz, state.surface.xyz
        if n == 0 or len(drawing) == 0 or self.cfg.end_check_m <= 0:
            return out
        reach = 1.5 * state.grid.voxel  # a frontier cell touches drawing cells (26-neighbourhood)
        d, j = cKDTree(centers).query(drawing, k=1, distance_upper_bound=reach)
        near = np.isfinite(d)
        if not near.any():
            return out
        pts, owner = drawing[near], lab[j[near]]
        radius = self.cfg.end_width_m
        lo, hi = pts.min(axis=0) - radius, pts.max(axis=0) + radius
        local = surface[np.all((surface >= lo) & (surface <= hi), axis=1)]
        ok = ends.sealed(pts, cKDTree(local), radius, self._surface_voxel)
        count = np.bincount(owner, minlength=n)
        open_ = np.bincount(owner, weights=~ok, minlength=n)
        return (count > 0) & (open_ == 0)


def framing(state: ScanState, target: np.ndarray) -> np.ndarray:
    """Positions of the views whose image holds the target (the first view and the latest one, whose
    poses the state keeps): a candidate looking at it from nearly there would see it again."""
    out = []
    for T in (state.initial_pose, state.camera_pose):
        p = T[:3, :3].T @ (target - T[:3, 3])
        if p[2] <= 0:
            continue
        u, v, _ = state.K @ (p / p[2])
        if 0 <= u < state.image_size[0] and 0 <= v < state.image_size[1]:
            out.append(T[:3, 3])
    return np.array(out).reshape(-1, 3)
