"""Constrained NBV (§V-B, Alg. 2): a search space around every frontier cell, each candidate position
tried with several orientations (pitch and yaw about the direction to its nearest frontier cell),
all scored by Q in one kernel call. Which frontier still deserves a view is kept as G-NBV keeps it
(planners.targets), per cluster: the target of a view is the centroid of the cluster it looks at."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from planners import nbv
from planners.base import ScanState, ViewPlan
from planners.config import PlannersConfig
from planners.open_edges import EdgeViews
from planners.targets import TargetBook, framing
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
        self.book = TargetBook(cfg)
        self._first_gain: float | None = None
        self._unreachable = np.zeros((0, 3))  # candidate positions the runner could not reach
        self._last: tuple | None = None  # (step, ranked candidate positions, the centroid each looks at)
        self.edges = EdgeViews(self.cfg, cfg.grid.surface_voxel_m) if "cnbv" in self.cfg.open_edge_views else None

    def reject(self, plan: ViewPlan) -> None:
        """The runner reached none of the candidates it tried: those positions are dropped from now on
        (the lattice is fixed, so they come back exactly), not the cluster they looked at; its other
        candidates may be reachable. A cluster with no candidate left is left by itself."""
        k = max(plan.tried, 1)
        tried = plan.poses[:k, :3, 3]
        if len(tried):
            self._unreachable = np.vstack([self._unreachable, tried])
        if self._last is not None:
            self.book.unreachable(self._last[2][:k])

    def _repeats(self, eyes: np.ndarray, owner: np.ndarray, cents: np.ndarray, state: ScanState) -> np.ndarray:
        """Mask of candidates that would look at their cluster from (nearly) the direction of a view
        already planned for it, or of a view whose image held it: that view saw what this one would."""
        out = np.zeros(len(eyes), dtype=bool)
        for c in np.unique(owner):  # a handful of clusters
            m = np.flatnonzero(owner == c)
            past = np.vstack([self.book.views_of(cents[c], state), framing(state, cents[c])])
            out[m] = nbv.repeats(eyes[m], np.broadcast_to(cents[c], (len(m), 3)), past, self.cfg.revisit_angle_deg)
        return out

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
        if self._last is not None and state.step > self._last[0]:
            # the view taken: the candidate of the last plan nearest to where the camera is now
            self.book.taken(state, *self._last[1:])
            self._last = None
        self.book.after_view(state)
        cl = self.book.clusters(state)
        keep = cl.usable[cl.lab]
        ijk, frontier, lab = cl.ijk[keep], cl.centers[keep], cl.lab[keep]
        timings = {"frontier_s": time.perf_counter() - t0}
        if len(frontier) == 0:
            return self._at_edges(state, "frontier", cl.centers, timings)
        eyes = self._search_space(grid, frontier[:: max(1, len(frontier) // cfg.cnbv_max_frontier)])
        # each position looks at its nearest frontier cell, within the cone of that cell's surface
        _, near = cKDTree(frontier).query(eyes, k=1)
        targets, owner = frontier[near], lab[near]
        normals = np.full((len(cl.cents), 3), np.nan)
        for c in np.unique(lab):  # one normal per cluster: a handful of clusters, not points
            nrm = nbv.outward_normal(state.surface, cl.cents[c])
            if nrm is not None:
                normals[c] = nrm
        ok = nbv.feasible_eyes(grid, eyes, targets, normals[owner], cfg, None, cfg.relaxed_view_angle_deg)
        ok &= ~self._repeats(eyes, owner, cl.cents, state)
        # Positions the runner could not reach, and those the camera already looked from: C-NBV's turns
        # of at most a few tens of degrees there would frame much of what that view saw.
        done = np.vstack([self._unreachable, state.viewpoints])
        if len(done):
            d, _ = cKDTree(done).query(eyes, k=1, distance_upper_bound=cfg.cnbv_candidate_spacing_m / 4)
            ok &= ~np.isfinite(d)
        eyes, targets, owner = eyes[ok], targets[ok], owner[ok]
        timings["candidates_s"] = time.perf_counter() - t0
        if len(eyes) == 0:
            return self._at_edges(state, "frontier", frontier, timings)
        base = look_at_rotations(eyes, targets)
        R = np.concatenate([_turn(base, y, p) for y, p in self._turns])
        E = np.tile(eyes, (len(self._turns), 1))
        owner_of = np.tile(owner, len(self._turns))
        if state.reachable is not None and cfg.reach_prefilter:
            keep = state.reachable(E, R[:, :, 2])
            E, R, owner_of = E[keep], R[keep], owner_of[keep]
        if len(E) == 0:
            return self._at_edges(state, "unreachable", frontier, timings)
        weights = nbv.cell_weights(grid, ijk, cfg)
        cost = np.linalg.norm(E - state.camera_pose[:3, 3], axis=1)
        gain = nbv.gains(grid, E, R, weights, nbv.visibility_field(grid, cfg), state.K, state.image_size, cfg, cost)
        q = nbv.quality(gain, cost, cfg.lam)
        rank = np.argsort(-q, kind="stable")
        timings["plan_s"] = time.perf_counter() - t0
        best = float(gain.max())
        if self._first_gain is None:
            self._first_gain = best
        stop = best < max(cfg.min_gain, cfg.cnbv_min_gain_fraction * self._first_gain) or q[rank[0]] < cfg.delta_q
        looked_at = cl.cents[owner_of[rank]]
        target = looked_at[0]
        if stop and self.edges is not None:
            return self._at_edges(state, "quality", frontier, timings)
        if not stop:
            self.book.planned(state, target)
            self._last = (state.step, E[rank], looked_at)
        return ViewPlan(poses_from(E[rank], R[rank]), q[rank], gain[rank], bool(stop), "quality" if stop else "",
                        target=target, frontier=frontier, timings=timings)

    def _at_edges(self, state: ScanState, reason: str, frontier: np.ndarray, timings: dict) -> ViewPlan:
        """The grid's frontier is done: a view of the open paint (planners.open_edges), or the stop."""
        stop = ViewPlan(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), True, reason, frontier=frontier,
                        timings=timings)
        if self.edges is None:
            return stop
        plan, last = self.edges.or_stop(state, self.book, stop)
        if last is not None:
            self._last = last
        return plan
