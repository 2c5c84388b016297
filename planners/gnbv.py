"""Guided NBV (§V-C, Alg. 3): the frontier reduced to the centroid of its nearest cluster, a sphere of
candidate positions around it, each looking at it (or just past it, along the drawing), scored by Q
in one kernel call."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from planners import ends, nbv
from planners.base import ScanState, ViewPlan
from planners.config import PlannersConfig
from planners.grid import frontier_clusters
from planners.growth import GrowthWatch
from planners.views import look_at_rotations, poses_from, sphere_lattice


def _framing(state: ScanState, target: np.ndarray) -> np.ndarray:
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


class GuidedNBV:
    name = "gnbv"

    def __init__(self, cfg: PlannersConfig):
        self._surface_voxel = cfg.grid.surface_voxel_m
        self.cfg = cfg = cfg.nbv
        self._lattice = sphere_lattice(cfg.search_radius_m, cfg.min_standoff_m, cfg.candidate_spacing_m)
        self._targets: list[np.ndarray] = []  # f̂ of every plan handed out
        self._target_steps: list[int] = []  # the step each was planned at
        self._given_up: list[np.ndarray] = []  # targets that proved unreachable or without gain
        self._first_gain: float | None = None  # the scale of a useful view, for the stop rule
        self._growth = GrowthWatch(cfg.min_view_growth_voxels)
        self._fruitless: list[np.ndarray] = []  # targets whose view found no drawing

    def reject(self, plan: ViewPlan) -> None:
        if plan.target is not None:
            self._given_up.append(np.asarray(plan.target))

    def _clusters(self, state: ScanState):
        """Cluster centroids, their cells, and which are still worth a view."""
        grid = state.grid
        labels, n = frontier_clusters(grid.frontier(self.cfg.frontier_reach_voxels), self.cfg.min_frontier_cluster)
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
            G = np.asarray(self._given_up)
            d, idx = cKDTree(centers).query(G, k=1)
            usable[lab[idx[d < near]]] = False
            # a centroid can lie off its cells (a curved cluster): near a given-up centroid counts too
            usable &= np.linalg.norm(cents[:, None, :] - G[None, :, :], axis=2).min(axis=1) >= 2 * near
        for c in np.flatnonzero(usable):  # a handful of clusters
            if ends.ended(state.drawing.xyz, state.surface.xyz, cents[c], self.cfg):
                usable[c] = False
        usable &= ~self._sealed_clusters(state, centers, lab, n)
        if n and self._targets:
            T = np.asarray(self._targets)
            visits = (np.linalg.norm(cents[:, None, :] - T[None, :, :], axis=2) < 2 * near).sum(axis=1)
            usable &= visits < self.cfg.max_target_visits
        return cents, ijk, lab, usable, centers

    def _sealed_clusters(self, state: ScanState, centers: np.ndarray, lab: np.ndarray, n: int) -> np.ndarray:
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

    def _aim_point(self, state: ScanState, target: np.ndarray) -> np.ndarray:
        """Where the candidates look: the frontier centroid, or a little past it in the direction the
        drawing leaves the explored part, so a view spends less of its image on what is known."""
        ahead = self.cfg.aim_ahead_m
        if ahead <= 0 or len(state.drawing) == 0:
            return target
        d2 = np.sum((state.drawing.xyz - target) ** 2, axis=1)
        near = state.drawing.xyz[d2 < 0.1 ** 2]
        if len(near) < 10:
            return target
        d = target - near.mean(axis=0)
        n = np.linalg.norm(d)
        return target + ahead * d / n if n > 0.01 else target

    def _views_of(self, target: np.ndarray, state: ScanState) -> np.ndarray:
        """Viewpoints already spent on (nearly) this target: seeing it again from there is pointless."""
        near = 6.0 * state.grid.voxel
        idx = [s + 1 for t, s in zip(self._targets, self._target_steps)
               if s + 1 < len(state.viewpoints) and np.linalg.norm(t - target) < near]
        return state.viewpoints[idx] if idx else np.zeros((0, 3))

    def _score(self, state: ScanState, target: np.ndarray, normal: np.ndarray | None, cone_deg: float,
               weights, p_free: np.ndarray, occupied: "nbv.OccupiedIndex"):
        """Ranked (poses, Q, gain) of the candidates around one target, or None if none is worth it."""
        cfg, grid = self.cfg, state.grid
        eyes = target + self._lattice
        past = np.vstack([self._views_of(target, state), _framing(state, target)])
        eyes = eyes[nbv.feasible_eyes(grid, eyes, target, normal, cfg, past, cone_deg,
                                      occupied=occupied)]
        if len(eyes) == 0:
            return None
        R = look_at_rotations(eyes, self._aim_point(state, target))
        cost = np.linalg.norm(eyes - state.camera_pose[:3, 3], axis=1)
        gain = nbv.gains(grid, eyes, R, weights, p_free, state.K, state.image_size, cfg, cost)
        q = nbv.quality(gain, cost, cfg.lam)
        rank = np.argsort(-q, kind="stable")
        best = float(gain.max())
        if self._first_gain is None:
            self._first_gain = best
        if best < max(cfg.min_gain, cfg.min_gain_fraction * self._first_gain) or q[rank[0]] < cfg.delta_q:
            return None
        return poses_from(eyes[rank], R[rank]), q[rank], gain[rank]

    def next_view(self, state: ScanState) -> ViewPlan:
        cfg, grid = self.cfg, state.grid
        t0 = time.perf_counter()
        # A view that found no drawing: its target gets one last try without a viewing cone (at an edge
        # the drawing goes on round the corner), and is given up if that finds nothing either.
        fruitless = self._growth.fruitless(state.step, grid)
        if fruitless is not None:
            again = any(np.linalg.norm(f - fruitless) < 6 * grid.voxel for f in self._fruitless)
            (self._given_up if again else self._fruitless).append(fruitless)
        cents, ijk, lab, usable, frontier_xyz = self._clusters(state)
        timings = {"frontier_s": time.perf_counter() - t0}
        cam = state.camera_pose[:3, 3]
        empty = np.zeros((0, 4, 4))
        reason = "frontier"
        # Nearest usable cluster first; one whose best view gains nothing is given up and the next
        # nearest tried, so a single unresolvable corner does not end the scan.
        order = np.argsort(np.linalg.norm(cents - cam, axis=1)) if len(cents) else np.zeros(0, int)
        p_free = nbv.visibility_field(grid, cfg)
        occupied = nbv.OccupiedIndex(grid)
        for c in order[usable[order]][:4]:
            target = cents[c]
            scored = None
            normal = nbv.outward_normal(state.surface, target)
            weights = nbv.cell_weights(grid, ijk[lab == c], cfg)
            # Square-on views first (the D435 returns nothing at grazing incidence); only if none of
            # them gains anything a relaxed cone, and last no cone at all: at an edge the normal
            # describes the side already seen while the drawing goes on round the corner.
            # A target already looked at without being resolved starts further down that list.
            tiers = (cfg.max_view_angle_deg, cfg.relaxed_view_angle_deg, None)
            start = len(self._views_of(target, state))
            if any(np.linalg.norm(f - target) < 6 * grid.voxel for f in self._fruitless):
                start = len(tiers) - 1
            for cone in tiers[min(start, len(tiers) - 1):]:
                scored = self._score(state, target, None if cone is None else normal, cone or 90.0, weights, p_free,
                                     occupied)
                if scored is not None:
                    break
            if scored is None:
                self._given_up.append(target)
                reason = "quality"
                continue
            poses, q, gain = scored
            self._targets.append(target)
            self._target_steps.append(state.step)
            self._growth.planned(state.step, target, grid)
            timings["plan_s"] = time.perf_counter() - t0
            return ViewPlan(poses, q, gain, False, "", target=target, frontier=frontier_xyz, timings=timings)
        timings["plan_s"] = time.perf_counter() - t0
        return ViewPlan(empty, np.zeros(0), np.zeros(0), True, reason, frontier=frontier_xyz, timings=timings)
