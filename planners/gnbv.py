"""Guided NBV (§V-C, Alg. 3): the frontier reduced to the centroid of its nearest cluster, a sphere of
candidate positions around it, each looking at it (or just past it, along the drawing), scored by Q
in one kernel call."""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from planners import nbv
from planners.base import ScanState, ViewPlan
from planners.config import PlannersConfig
from planners.ends import local_axis
from planners.line_prior import LinePrior, line_prior, seen_counts
from planners.open_edges import EdgeViews, round_edge_axis
from planners.targets import TargetBook, framing
from planners.views import look_at_rotations, poses_from, roll_along, sphere_lattice


#: the patch round a target whose normal (or border) sets its viewing cone
NORMAL_RADIUS_M = 0.03


class GuidedNBV:
    name = "gnbv"

    def __init__(self, cfg: PlannersConfig):
        self.cfg = cfg.nbv
        self._lattice = sphere_lattice(self.cfg.search_radius_m, self.cfg.min_standoff_m, self.cfg.candidate_spacing_m)
        self.book = TargetBook(cfg)
        self._first_gain: float | None = None  # the scale of a useful view, for the stop rule
        self._last: tuple | None = None  # (step, ranked eyes, their targets) of a joint plan
        self._prior: LinePrior | None = None  # this step's line prior, when the surface is a cylinder
        self.edges = (EdgeViews(self.cfg, cfg.grid.surface_voxel_m, self.cfg.joint_edge_views)
                      if "gnbv" in self.cfg.open_edge_views else None)
        self._unreachable_eyes = np.zeros((0, 3))  # candidate positions the runner could not reach...
        self._unreachable_for = np.zeros((0, 3))  # ...and the target each looked at

    def reject(self, plan: ViewPlan) -> None:
        """The runner reached none of the candidates it tried (the capability map does not know the
        piece: an arm behind a camera that looks past a pipe's branch hits the branch). Those poses
        are not offered again, not the target: its candidates from other sides may be reachable.
        The book gives a target up when a second plan on it fails (``TargetBook.unreachable``)."""
        if plan.target is None:
            return
        k = max(plan.tried, 1)
        eyes = plan.poses[:k, :3, 3]
        owners = self._last[2][:k] if self._last is not None else np.broadcast_to(plan.target, eyes.shape)
        self._unreachable_eyes = np.vstack([self._unreachable_eyes, eyes])
        self._unreachable_for = np.vstack([self._unreachable_for, owners])
        self.book.unreachable(owners)

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

    def _cone_axis(self, state: ScanState, target: np.ndarray) -> np.ndarray | None:
        """The axis of the target's viewing cone: the surface normal there, or with ``edge_cone`` the
        way round the border of the measured surface where the paint next to it meets one."""
        if self.cfg.edge_cone and len(state.drawing):
            axis = round_edge_axis(state.drawing.xyz, state.drawing.origin, state.surface.xyz, target,
                                   NORMAL_RADIUS_M, self.cfg.open_edge_radius_m)
            if axis is not None:
                return axis
        return nbv.outward_normal(state.surface, target, NORMAL_RADIUS_M)

    def _past(self, state: ScanState, target: np.ndarray) -> np.ndarray:
        """Where the target was already seen from: candidates from there are not offered again."""
        return np.vstack([self.book.views_of(target, state), framing(state, target)])

    def _candidates(self, state: ScanState, target: np.ndarray, normal: np.ndarray | None, cone_deg: float,
                    past: np.ndarray, occupied: "nbv.OccupiedIndex") -> tuple[np.ndarray, np.ndarray]:
        """(eyes, rotations) of the sphere round one target that pass feasible_eyes within the cone,
        look at its aim point and, when the runner gives a reach map, are reachable."""
        cfg, grid = self.cfg, state.grid
        eyes = target + self._lattice
        eyes = eyes[nbv.feasible_eyes(grid, eyes, target, normal, cfg, past, cone_deg, occupied=occupied)]
        eyes = eyes[~self._failed_here(eyes, target, grid.voxel)]
        if len(eyes) == 0:
            return eyes, np.zeros((0, 3, 3))
        R = look_at_rotations(eyes, self._aim_point(state, target))
        if cfg.frame_line:  # the image's wide axis along the paint within 10 cm
            along = local_axis(state.drawing.xyz.astype(np.float64), target, 0.1)
            if along is not None:
                R = roll_along(R, along[2])
        if state.reachable is not None and cfg.reach_prefilter:
            keep = state.reachable(eyes, R[:, :, 2])
            eyes, R = eyes[keep], R[keep]
        return eyes, R

    def _failed_here(self, eyes: np.ndarray, target: np.ndarray, voxel: float) -> np.ndarray:
        """Mask of candidate positions the runner could not reach for (nearly) this target."""
        same = np.linalg.norm(self._unreachable_for - target, axis=1) < 6 * voxel
        if not same.any() or len(eyes) == 0:
            return np.zeros(len(eyes), dtype=bool)
        d, _ = cKDTree(self._unreachable_eyes[same]).query(eyes, k=1)
        return d < 1e-3

    def _score(self, state: ScanState, target: np.ndarray, normal: np.ndarray | None, cone_deg: float,
               weights, p_free: np.ndarray, occupied: "nbv.OccupiedIndex"):
        """Ranked (poses, Q, gain) of the candidates around one target, or None if none is worth it."""
        cfg, grid = self.cfg, state.grid
        eyes, R = self._candidates(state, target, normal, cone_deg, self._past(state, target), occupied)
        if len(eyes) == 0:
            return None
        cost = np.linalg.norm(eyes - state.camera_pose[:3, 3], axis=1)
        gain = nbv.gains(grid, eyes, R, weights, p_free, state.K, state.image_size, cfg, cost, cfg.footprint_gain)
        q = nbv.quality(gain, cost, cfg.lam)
        rank, shows_line = self._rank(state, eyes, R, q, occupied)
        best = float(gain.max())
        if self._first_gain is None:
            self._first_gain = best
        spent = best < max(cfg.min_gain, cfg.min_gain_fraction * self._first_gain) or q.max() < cfg.delta_q
        if spent and not shows_line:
            return None
        return poses_from(eyes[rank], R[rank]), q[rank], gain[rank]

    def next_view(self, state: ScanState) -> ViewPlan:
        cfg, grid = self.cfg, state.grid
        t0 = time.perf_counter()
        if self._last is not None and state.step > self._last[0]:
            # the view taken: the candidate of the last plan nearest to where the camera is now
            self.book.taken(state, *self._last[1:])
            self._last = None
        # A view that found no drawing: its target gets one last try without a viewing cone (at an edge
        # the drawing goes on round the corner), and is given up if that finds nothing either.
        self.book.after_view(state)
        cl = self.book.clusters(state)
        cents, ijk, lab, usable, frontier_xyz = cl.cents, cl.ijk, cl.lab, cl.usable, cl.centers
        timings = {"frontier_s": time.perf_counter() - t0}
        cam = state.camera_pose[:3, 3]
        empty = np.zeros((0, 4, 4))
        reason = "frontier"
        # Nearest usable cluster first; one whose best view gains nothing is given up and the next
        # nearest tried, so a single unresolvable corner does not end the scan.
        order = np.argsort(np.linalg.norm(cents - cam, axis=1)) if len(cents) else np.zeros(0, int)
        p_free = nbv.visibility_field(grid, cfg)
        occupied = nbv.OccupiedIndex(grid)
        self._prior = None
        if cfg.line_prior_m > 0 and usable.any():
            self._prior = line_prior(state.drawing.xyz, state.surface.xyz, state.surface.origin, grid,
                                     cfg.line_prior_m, frontier_xyz[usable[lab]])
        if cfg.gain_all_frontier and usable.any():
            ranked = order[usable[order]]
            weights = nbv.cell_weights(grid, ijk[usable[lab]], cfg)  # every usable cluster's frontier
            n = cfg.joint_clusters
            for k in range(0, len(ranked), n):  # the nearest n clusters; the next n if all of them are given up
                plan = self._joint(state, cl, ranked[k:k + n], weights, p_free, occupied, t0, timings)
                if not plan.stop:
                    break
            return self._at_edges(state, plan, occupied) if plan.stop else plan
        for c in order[usable[order]][:4]:
            target = cents[c]
            scored = None
            normal = self._cone_axis(state, target)
            weights = nbv.cell_weights(grid, ijk[lab == c], cfg)
            # Square-on views first (the D435 returns nothing at grazing incidence); only if none of
            # them gains anything a relaxed cone, and last no cone at all: at an edge the normal
            # describes the side already seen while the drawing goes on round the corner.
            # A target already looked at without being resolved starts further down that list.
            tiers = (cfg.max_view_angle_deg, cfg.relaxed_view_angle_deg, None)
            start = len(self.book.views_of(target, state))
            if self.book.was_fruitless(target, grid.voxel):
                start = len(tiers) - 1
            for cone in tiers[min(start, len(tiers) - 1):]:
                scored = self._score(state, target, None if cone is None else normal, cone or 90.0, weights, p_free,
                                     occupied)
                if scored is not None:
                    break
            if scored is None:
                self.book.give_up(target)
                reason = "quality"
                continue
            poses, q, gain = scored
            self.book.planned(state, target)
            timings["plan_s"] = time.perf_counter() - t0
            return ViewPlan(poses, q, gain, False, "", target=target, frontier=frontier_xyz, timings=timings)
        timings["plan_s"] = time.perf_counter() - t0
        return self._at_edges(state, ViewPlan(empty, np.zeros(0), np.zeros(0), True, reason, frontier=frontier_xyz,
                                              timings=timings), occupied)

    def _prior_seen(self, state: ScanState, eyes: np.ndarray, R: np.ndarray,
                    occupied: "nbv.OccupiedIndex") -> np.ndarray | None:
        """Per candidate: how many points of this step's line prior it would image (None: no prior)."""
        if self._prior is None or len(eyes) == 0:
            return None
        return seen_counts(eyes, R, self._prior, state.K, state.image_size, self.cfg.max_range_m,
                           self.cfg.max_view_angle_deg, state.grid, occupied.flat)

    def _worth(self, seen: np.ndarray, state: ScanState) -> np.ndarray:
        """As much of the line as a view must find to count as one that found drawing
        (planners.growth): such a view is worth taking even when eq. 5's gain is spent, which
        knows nothing of the line past p_φ's reach."""
        return seen * self._prior.spacing >= self.cfg.min_view_growth_voxels * state.grid.voxel

    def _shows_line(self, state: ScanState, eyes: np.ndarray, R: np.ndarray, occupied: "nbv.OccupiedIndex") -> np.ndarray:
        seen = self._prior_seen(state, eyes, R, occupied)
        return np.zeros(len(eyes), dtype=bool) if seen is None else self._worth(seen, state)

    def _rank(self, state: ScanState, eyes: np.ndarray, R: np.ndarray, q: np.ndarray,
              occupied: "nbv.OccupiedIndex") -> tuple[np.ndarray, bool]:
        """Candidates best first: by Q (eq. 4); with a line prior (planners.line_prior), first by
        how much of the line's likely continuation they would image, then by Q. And whether the
        first one is worth taking for the line alone (``_worth``)."""
        seen = self._prior_seen(state, eyes, R, occupied)
        if seen is None:
            return np.argsort(-q, kind="stable"), False
        rank = np.lexsort((-q, -seen))
        return rank, bool(self._worth(seen[rank[0]], state))

    def _at_edges(self, state: ScanState, stop: ViewPlan, occupied: "nbv.OccupiedIndex") -> ViewPlan:
        """The grid's frontier is done: a view of the open paint (planners.open_edges), or the stop."""
        if self.edges is None:
            return stop
        plan, last = self.edges.or_stop(state, self.book, stop, occupied,
                                        lambda eyes, centre: self._failed_here(eyes, centre, state.grid.voxel))
        if last is not None:
            self._last = last
        return plan

    def _joint(self, state: ScanState, cl, clusters: np.ndarray, weights: "nbv.CellWeights", p_free: np.ndarray,
               occupied: "nbv.OccupiedIndex", t0: float, timings: dict) -> ViewPlan:
        """The candidate spheres of the nearest usable clusters compete in one ranking, each candidate
        scored on every usable cluster's frontier: a view is worth all the unseen drawing it may
        show, and the one that resolves two ends at once beats two views of one end each. Per
        cluster the viewing cones are tried square-on first, as in the one-target plan."""
        cfg, grid = self.cfg, state.grid
        empty = np.zeros((0, 4, 4))
        tiers = (cfg.max_view_angle_deg, cfg.relaxed_view_angle_deg, None)
        todo = {}
        for c in clusters:
            target = cl.cents[c]
            start = len(tiers) - 1 if self.book.was_fruitless(target, grid.voxel) else len(self.book.views_of(target, state))
            todo[int(c)] = (min(start, len(tiers) - 1), self._cone_axis(state, target),
                            self._past(state, target))
        first = self._first_gain
        done = []  # per settled cluster: its candidates' (eyes, rotations, owner, gain, cost)
        while todo:
            E, R, owner = [], [], []
            for c, (tier, normal, past) in list(todo.items()):
                cone = tiers[tier]
                eyes, rot = self._candidates(state, cl.cents[c], None if cone is None else normal, cone or 90.0,
                                             past, occupied)
                E.append(eyes)
                R.append(rot)
                owner.append(np.full(len(eyes), c))
            E, R, owner = np.concatenate(E), np.concatenate(R), np.concatenate(owner)
            cost = np.linalg.norm(E - state.camera_pose[:3, 3], axis=1)
            gain = (nbv.gains(grid, E, R, weights, p_free, state.K, state.image_size, cfg, cost, cfg.footprint_gain)
                    if len(E) else np.zeros(0))
            if first is None and len(gain):
                first = float(gain.max())
            floor = max(cfg.min_gain, cfg.joint_min_gain_fraction * (first or 0.0))
            shows = self._shows_line(state, E, R, occupied)
            for c in list(todo):
                m = owner == c
                tier, normal, past = todo.pop(c)
                if m.any() and (gain[m].max() >= floor or shows[m].any()):
                    done.append((E[m], R[m], owner[m], gain[m], cost[m]))
                elif tier + 1 < len(tiers):
                    todo[c] = (tier + 1, normal, past)
                else:
                    self.book.give_up(cl.cents[c])
        self._first_gain = first
        frontier_xyz = cl.centers
        timings["plan_s"] = time.perf_counter() - t0
        if not done:
            return ViewPlan(empty, np.zeros(0), np.zeros(0), True, "quality", frontier=frontier_xyz, timings=timings)
        E, R, owner, gain, cost = (np.concatenate(parts) for parts in zip(*done))
        q = nbv.quality(gain, cost, cfg.lam)
        rank, _ = self._rank(state, E, R, q, occupied)
        looked_at = cl.cents[owner[rank]]
        self.book.planned(state, looked_at[0])
        self._last = (state.step, E[rank], looked_at)
        return ViewPlan(poses_from(E[rank], R[rank]), q[rank], gain[rank], False, "", target=looked_at[0],
                        frontier=frontier_xyz, timings=timings)
