"""A feature-agnostic information-gain NBV (the approach of the paper's refs [12]-[13]): candidates on
a view sphere around the observed object, gain over all unknown cells near it (no feature
probability), stop when the gain is exhausted. What a user would pick without feature guidance."""

from __future__ import annotations

import time

import numpy as np

from planners import nbv
from planners.base import ScanState, ViewPlan
from planners.config import PlannersConfig
from planners.views import fibonacci_sphere, look_at_rotations, poses_from


class GlobalNBV:
    name = "global"

    def __init__(self, cfg: PlannersConfig):
        self.cfg = cfg.nbv
        self._dirs = fibonacci_sphere(self.cfg.global_view_directions)
        self._first_best: float | None = None
        self._given_up: list[np.ndarray] = []

    def reject(self, plan: ViewPlan) -> None:
        self._given_up.extend(plan.poses[: max(plan.tried, 1), :3, 3].copy())

    def next_view(self, state: ScanState) -> ViewPlan:
        cfg, grid = self.cfg, state.grid
        t0 = time.perf_counter()
        empty = np.zeros((0, 4, 4))
        occ = np.argwhere(grid.occupied)
        pts = grid.centers(occ)
        pts = pts[pts[:, 2] > cfg.floor_z_m]  # the object, not the floor it stands on
        if len(pts) == 0:
            return ViewPlan(empty, np.zeros(0), np.zeros(0), True, "quality", timings={"plan_s": 0.0})
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        center = (lo + hi) / 2
        # the sphere just encloses the object's footprint plus the standoff, within the arm's reach
        radius = float(np.clip(np.linalg.norm((hi - lo)[:2]) / 2 + cfg.global_standoff_m, 0.4, 0.7))
        eyes = center + radius * self._dirs
        spent = np.concatenate([np.asarray(self._given_up).reshape(-1, 3), state.viewpoints.reshape(-1, 3)])
        if len(spent):  # never the same viewpoint twice, nor one that proved unreachable
            d = np.linalg.norm(eyes[:, None, :] - spent[None], axis=2).min(axis=1)
            eyes = eyes[d > 0.05]
        # gain over every unknown cell around the observed object: the object box, grown
        box_lo = np.maximum(np.floor((lo - cfg.global_margin_m - grid.lo) / grid.voxel).astype(int), 0)
        box_hi = np.minimum(np.ceil((hi + cfg.global_margin_m - grid.lo) / grid.voxel).astype(int), grid.shape)
        box = tuple(slice(int(a), int(b)) for a, b in zip(box_lo, box_hi))
        weights = nbv.CellWeights.on_box(grid, box, nbv.entropy_decrease(grid, box), cfg.facing_gain)
        ok = nbv.feasible_eyes(grid, eyes, center, None, cfg, line_of_sight=False)  # it looks at the whole object
        eyes = eyes[ok]
        # no candidate left (all spent or unreachable) is a different end from exhausted gain
        if len(eyes) == 0:
            return ViewPlan(empty, np.zeros(0), np.zeros(0), True, "no_candidates",
                            timings={"plan_s": time.perf_counter() - t0})
        R = look_at_rotations(eyes, center)
        cost = np.linalg.norm(eyes - state.camera_pose[:3, 3], axis=1)
        gain = nbv.gains(grid, eyes, R, weights, nbv.visibility_field(grid, cfg, cfg.global_unknown_visibility), state.K,
                         state.image_size, cfg, cost)
        q = nbv.quality(gain, cost, cfg.lam)
        rank = np.argsort(-q, kind="stable")
        best = float(gain.max())
        if self._first_best is None:
            self._first_best = best
        stop = best < cfg.global_stop_fraction * self._first_best
        return ViewPlan(poses_from(eyes[rank], R[rank]), q[rank], gain[rank], bool(stop), "quality" if stop else "",
                        target=center, timings={"plan_s": time.perf_counter() - t0})
