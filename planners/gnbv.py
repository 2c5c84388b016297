"""Guided NBV (§V-C, Alg. 3): the frontier reduced to the centroid of its nearest cluster, a sphere of
candidate positions around it, each looking at it, scored by Q in one kernel call."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from planners import nbv
from planners.base import ScanState, ViewPlan
from planners.config import NBVConfig
from planners.grid import frontier_clusters
from planners.views import look_at_rotations, poses_from, sphere_lattice


class GuidedNBV:
    name = "gnbv"

    def __init__(self, cfg: NBVConfig):
        self.cfg = cfg
        self._lattice = sphere_lattice(cfg.search_radius_m, cfg.min_standoff_m, cfg.candidate_spacing_m)
        self._targets: list[np.ndarray] = []  # f̂ of every plan handed out
        self._target_steps: list[int] = []  # the step each was planned at
        self._given_up: list[np.ndarray] = []  # targets that proved unreachable or without gain

    def reject(self, plan: ViewPlan) -> None:
        if plan.target is not None:
            self._given_up.append(np.asarray(plan.target))

    def _clusters(self, state: ScanState):
        """Cluster centroids, their cells, and which are still worth a view."""
        grid = state.grid
        labels, n = frontier_clusters(grid.frontier(), self.cfg.min_frontier_cluster)
        ijk = np.argwhere(labels > 0)
        if n == 0:
            return np.zeros((0, 3)), ijk, np.zeros(0, int), np.zeros(0, bool), np.zeros((0, 3))
        lab = labels[ijk[:, 0], ijk[:, 1], ijk[:, 2]] - 1
        centers = grid.centers(ijk)
        counts = np.bincount(lab, minlength=n)
        cents = np.stack([np.bincount(lab, weights=centers[:, a], minlength=n) for a in range(3)], axis=1)
        cents /= np.maximum(counts, 1)[:, None]
        usable = np.ones(n, dtype=bool)
        near = 3.0 * grid.voxel
        if n and self._given_up:
            d, idx = cKDTree(centers).query(np.asarray(self._given_up), k=1)
            usable[lab[idx[d < near]]] = False
        if n and self._targets:
            T = np.asarray(self._targets)
            visits = (np.linalg.norm(cents[:, None, :] - T[None, :, :], axis=2) < 2 * near).sum(axis=1)
            usable &= visits < self.cfg.max_target_visits
        return cents, ijk, lab, usable, centers

    def _views_of(self, target: np.ndarray, state: ScanState) -> np.ndarray:
        """Viewpoints already spent on (nearly) this target: seeing it again from there is pointless."""
        near = 6.0 * state.grid.voxel
        idx = [s + 1 for t, s in zip(self._targets, self._target_steps)
               if s + 1 < len(state.viewpoints) and np.linalg.norm(t - target) < near]
        return state.viewpoints[idx] if idx else np.zeros((0, 3))

    def next_view(self, state: ScanState) -> ViewPlan:
        cfg, grid = self.cfg, state.grid
        t0 = time.perf_counter()
        cents, ijk, lab, usable, frontier_xyz = self._clusters(state)
        timings = {"frontier_s": time.perf_counter() - t0}
        cam = state.camera_pose[:3, 3]
        empty = np.zeros((0, 4, 4))
        reason = "frontier"
        # Nearest usable cluster first; one whose best view gains nothing is given up and the next
        # nearest tried, so a single unresolvable corner does not end the scan.
        order = np.argsort(np.linalg.norm(cents - cam, axis=1)) if len(cents) else np.zeros(0, int)
        for c in order[usable[order]][:4]:
            target = cents[c]
            normal = nbv.outward_normal(grid, state.surface.xyz, target)
            eyes = target + self._lattice
            eyes = eyes[nbv.feasible_eyes(grid, eyes, target, normal, cfg, self._views_of(target, state))]
            if len(eyes) == 0:
                self._given_up.append(target)
                continue
            R = look_at_rotations(eyes, target)
            w = nbv.cell_weights(grid, ijk[lab == c], cfg)
            gain = nbv.gains(grid, eyes, R, w, nbv.visibility_field(grid, cfg), state.K, state.image_size, cfg)
            q = nbv.quality(gain, np.linalg.norm(eyes - cam, axis=1), cfg.lam)
            rank = np.argsort(-q, kind="stable")
            if gain.max() < cfg.min_gain or q[rank[0]] < cfg.delta_q:
                self._given_up.append(target)
                reason = "quality"
                continue
            self._targets.append(target)
            self._target_steps.append(state.step)
            timings["plan_s"] = time.perf_counter() - t0
            return ViewPlan(poses_from(eyes[rank], R[rank]), q[rank], gain[rank], False, "",
                            target=target, frontier=frontier_xyz, timings=timings)
        timings["plan_s"] = time.perf_counter() - t0
        return ViewPlan(empty, np.zeros(0), np.zeros(0), True, reason, frontier=frontier_xyz, timings=timings)
