"""Constrained NBV (§V-B, Alg. 2): a search space around every frontier cell, each candidate position
tried with several orientations (pitch and yaw about the direction to its nearest frontier cell),
all scored by Q in one kernel call."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from planners import nbv
from planners.base import ScanState, ViewPlan
from planners.config import PlannersConfig
from planners.grid import frontier_clusters
from planners.growth import GrowthWatch
from planners.views import look_at_rotations, poses_from


def _turn(R: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """Rotate camera frames about their own y (yaw) then x (pitch) axes."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return R @ (Ry @ Rx)


class ConstrainedNBV:
    name = "cnbv"

    def __init__(self, cfg: PlannersConfig):
        self.cfg = cfg.nbv
        a = np.deg2rad(self.cfg.cnbv_angle_step_deg)
        n = self.cfg.cnbv_angle_steps
        offs = (np.arange(n) - (n - 1) / 2) * a
        self._turns = [(y, p) for y in offs for p in offs]
        self._given_up: list[np.ndarray] = []  # targets that proved unreachable or without gain
        self._targets: list[np.ndarray] = []  # the target of every plan handed out
        self._target_steps: list[int] = []  # the step each was planned at
        self._first_gain: float | None = None
        self._growth = GrowthWatch(self.cfg.min_view_growth_voxels)

    def reject(self, plan: ViewPlan) -> None:
        if plan.target is not None:
            self._given_up.append(np.asarray(plan.target))

    def _repeats(self, eyes: np.ndarray, targets: np.ndarray, state: ScanState, near: float) -> np.ndarray:
        """Mask of candidates that would look at their target from (nearly) the direction of a view
        already planned for a target there: that view saw what this one would."""
        past = [(t, state.viewpoints[s + 1]) for t, s in zip(self._targets, self._target_steps)
                if s + 1 < len(state.viewpoints)]
        out = np.zeros(len(eyes), dtype=bool)
        if not past or self.cfg.revisit_angle_deg <= 0:
            return out
        T = np.array([t for t, _ in past])
        V = np.array([v for _, v in past])
        same = np.linalg.norm(targets[:, None, :] - T[None, :, :], axis=2) < near  # (M, P)
        u = eyes - targets
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
        pv = V[None, :, :] - targets[:, None, :]
        pv /= np.maximum(np.linalg.norm(pv, axis=2, keepdims=True), 1e-9)
        close = np.einsum("mj,mpj->mp", u, pv) >= np.cos(np.deg2rad(self.cfg.revisit_angle_deg))
        return np.any(same & close, axis=1)

    def _search_space(self, grid, frontier: np.ndarray) -> np.ndarray:
        """S_k = ∪ S(f): lattice positions in the shell [min_standoff, search_radius] of any frontier
        cell (one lattice for all, so overlapping shells do not duplicate candidates)."""
        cfg = self.cfg
        sp = cfg.cnbv_candidate_spacing_m
        lo = np.floor((frontier.min(axis=0) - cfg.search_radius_m) / sp) * sp
        hi = frontier.max(axis=0) + cfg.search_radius_m
        axes = [np.arange(lo[i], hi[i] + sp / 2, sp) for i in range(3)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        tree = cKDTree(frontier)
        d_near, _ = tree.query(pts, k=1, distance_upper_bound=cfg.search_radius_m)
        pts = pts[np.isfinite(d_near)]
        d_near = d_near[np.isfinite(d_near)]
        return pts[d_near >= cfg.min_standoff_m]

    def next_view(self, state: ScanState) -> ViewPlan:
        cfg, grid = self.cfg, state.grid
        t0 = time.perf_counter()
        # G-NBV's growth watch: a view that found no drawing gives its target up (C-NBV has no cone
        # tiers to try it again with)
        fruitless = self._growth.fruitless(state.step, grid)
        if fruitless is not None:
            self._given_up.append(fruitless)
        labels, n = frontier_clusters(grid.frontier(cfg.frontier_reach_voxels), cfg.min_frontier_cluster)
        ijk = np.argwhere(labels > 0)
        frontier = grid.centers(ijk)
        # the same bookkeeping as G-NBV: frontier given up, or looked at often enough, is dropped
        near = 6 * grid.voxel
        if n and self._given_up:
            d, _ = cKDTree(np.asarray(self._given_up)).query(frontier, k=1)
            keep = d > near
            ijk, frontier = ijk[keep], frontier[keep]
        if len(frontier) and self._targets:
            visits = np.array([len(v) for v in cKDTree(np.asarray(self._targets)).query_ball_point(frontier, near)])
            keep = visits < cfg.max_target_visits
            ijk, frontier = ijk[keep], frontier[keep]
        timings = {"frontier_s": time.perf_counter() - t0}
        empty = np.zeros((0, 4, 4))
        if len(frontier) == 0:
            return ViewPlan(empty, np.zeros(0), np.zeros(0), True, "frontier", timings=timings)
        eyes = self._search_space(grid, frontier[:: max(1, len(frontier) // cfg.cnbv_max_frontier)])
        # each position looks at its nearest frontier cell, within the cone of that cell's surface
        _, near = cKDTree(frontier).query(eyes, k=1)
        targets = frontier[near]
        lab = labels[tuple(ijk.T)]
        normals = np.full((len(frontier), 3), np.nan)
        for c in np.unique(lab):  # one normal per cluster: a handful of clusters, not points
            m = lab == c
            nrm = nbv.outward_normal(state.surface, frontier[m].mean(axis=0))
            if nrm is not None:
                normals[m] = nrm
        ok = nbv.feasible_eyes(grid, eyes, targets, normals[near], cfg, None, cfg.relaxed_view_angle_deg)
        ok &= ~self._repeats(eyes, targets, state, 6 * grid.voxel)
        eyes, targets = eyes[ok], targets[ok]
        timings["candidates_s"] = time.perf_counter() - t0
        if len(eyes) == 0:
            return ViewPlan(empty, np.zeros(0), np.zeros(0), True, "frontier", frontier=frontier, timings=timings)
        base = look_at_rotations(eyes, targets)
        R = np.concatenate([_turn(base, y, p) for y, p in self._turns])
        E = np.tile(eyes, (len(self._turns), 1))
        weights = nbv.cell_weights(grid, ijk, cfg)
        cost = np.linalg.norm(E - state.camera_pose[:3, 3], axis=1)
        gain = nbv.gains(grid, E, R, weights, nbv.visibility_field(grid, cfg), state.K, state.image_size, cfg, cost)
        q = nbv.quality(gain, cost, cfg.lam)
        rank = np.argsort(-q, kind="stable")
        timings["plan_s"] = time.perf_counter() - t0
        best = float(gain.max())
        if self._first_gain is None:
            self._first_gain = best
        stop = best < max(cfg.min_gain, cfg.min_gain_fraction * self._first_gain) or q[rank[0]] < cfg.delta_q
        target = np.tile(targets, (len(self._turns), 1))[rank[0]]
        if not stop:
            self._targets.append(target)
            self._target_steps.append(state.step)
            self._growth.planned(state.step, target, grid)
        return ViewPlan(poses_from(E[rank], R[rank]), q[rank], gain[rank], bool(stop), "quality" if stop else "",
                        target=target, frontier=frontier, timings=timings)
