"""Extrapolated NVP (§V-A, Alg. 1): explore the drawing as a path. Fit a curve to D_total, step
δ_distance past the end being explored and look at that point square-on from the standoff along the
surface normal. A view that adds (almost) nothing to D_total means that end is an extremity; after
the first, backtrack to the initial view and explore the other way; stop after the second.

No grid, no scoring: a step is one skeleton fit, which is why E-NVP iterates fast, and also why it
cannot tell a drawing's end from an edge that hides it (§VII) and knows of two ends only."""

from __future__ import annotations

import time

import numpy as np

from planners.base import ScanState, ViewPlan
from planners.clouds import voxel_keys
from planners.config import PlannersConfig
from planners.nbv import outward_normal
from planners.skeleton import order_curve
from planners.views import WORLD_UP, look_at_rotations, poses_from

TANGENT_SPAN_M = 0.05  # the end tangent is fitted to this much of the curve
TILTS_DEG = (0.0, 15.0, -15.0, 30.0, -30.0)  # fallbacks: the camera swung about the tangent axis
FALLBACK_STANDOFFS_M = (0.30, 0.45)  # fallbacks: nearer / farther along the same line of sight
# in-view extremity test: surface seen this far past where the paint ends (within this radius, at
# least this fraction of the density of a fully seen patch)
PROBE_GAP_M, PROBE_RADIUS_M, PROBE_FILL = 0.03, 0.02, 0.4
AT_INITIAL_M = 0.02  # a camera this near the initial view need not backtrack to it


def _end_tangent(curve: np.ndarray, span: float) -> np.ndarray:
    """Unit direction in which the curve leaves its first point: PCA of its first `span` metres,
    oriented outward (the voxel path is jagged; one step would be a poor tangent)."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    seg = curve[: max(int(np.searchsorted(arc, span, side="right")), 2)]
    c = seg - seg.mean(axis=0)
    t = np.linalg.svd(c, full_matrices=False)[2][0]
    if np.dot(t, curve[0] - seg.mean(axis=0)) < 0:
        t = -t
    return t / np.linalg.norm(t)


def _rotate(v: np.ndarray, axis: np.ndarray, deg: float) -> np.ndarray:
    a = np.radians(deg)
    return v * np.cos(a) + np.cross(axis, v) * np.sin(a) + axis * np.dot(axis, v) * (1 - np.cos(a))


class ExtrapolatedNVP:
    name = "enpv"

    def __init__(self, cfg: PlannersConfig):
        self.cfg = cfg.enpv
        self.voxel = cfg.grid.voxel_m
        self.size_voxel = cfg.coverage_voxel_m
        self.surface_voxel = cfg.grid.surface_voxel_m
        self.found: list[np.ndarray] = []  # extremities: the curve end explored when each was declared
        self._heading: np.ndarray | None = None  # the curve end being explored
        self._aim: np.ndarray | None = None  # the last extrapolated target d
        self._prev_size: int | None = None  # size of D_total (coverage voxels) at the last step
        self._last_step = -1
        self._check = False  # compare growth at the next step: only after an executed exploration view
        self._backtrack = False  # the next view is the initial one
        self._initial: np.ndarray | None = None

    # --- the state machine of Alg. 1 ------------------------------------------------------------
    def _extremity(self) -> None:
        """The end being explored is done; after the first, go back to the initial view."""
        self.found.append(self._heading)
        self._heading = self._aim = None
        self._backtrack = len(self.found) == 1

    def reject(self, plan: ViewPlan) -> None:
        """None of the poses at this end was reachable, or its view saw nothing. As in the paper,
        E-NVP then counts that end as an extremity (it terminates prematurely there) and turns to
        the other end, backtracking first if this was the first one. A rejected backtrack is skipped."""
        self._check = False  # the rejection already decided this end; the next step's growth must not again
        if self._is_backtrack(plan):
            self._backtrack = False
        elif self._heading is not None and len(self.found) < 2:
            self._extremity()

    def _is_backtrack(self, plan: ViewPlan) -> bool:
        return (self._initial is not None and len(plan.poses) == 1
                and np.allclose(plan.poses[0], self._initial, atol=1e-9))

    def _size(self, xyz: np.ndarray) -> int:
        return int(np.unique(voxel_keys(xyz, self.size_voxel)).size)

    # --- planning -------------------------------------------------------------------------------
    def next_view(self, state: ScanState) -> ViewPlan:
        t0 = time.perf_counter()
        self._initial = np.asarray(state.initial_pose, dtype=np.float64)
        xyz = state.drawing.xyz
        if len(xyz) == 0:
            return self._stop("no drawing", np.zeros((0, 3)), t0, {})
        if state.step != self._last_step:  # a replan after reject() sees the same state: no growth
            size = self._size(xyz)
            if self._check and self._prev_size is not None and size - self._prev_size <= self.cfg.delta_size_voxels:
                self._extremity()
            self._prev_size, self._last_step = size, state.step
        curve = order_curve(xyz, self.voxel)
        timings = {"fit_s": time.perf_counter() - t0}
        if len(self.found) >= 2:
            return self._stop("extremities", curve, t0, timings)
        if len(curve) < 2:
            return self._stop("no drawing", curve, t0, timings)  # one voxel of paint: no direction
        if self._backtrack:
            self._backtrack = False
            if np.linalg.norm(state.camera_pose[:3, 3] - self._initial[:3, 3]) > AT_INITIAL_M:
                self._check = False  # returning adds nothing new: not the second extremity
                return self._plan([self._initial], self._initial[:3, 3] + self.cfg.standoff_m * self._initial[:3, 2],
                                  curve, t0, timings)
        ends = curve[[0, -1]]
        if self.found:
            first = int(np.argmax(np.linalg.norm(ends - self.found[0], axis=1)))  # away from the found one
        elif self._aim is not None:
            first = int(np.argmin(np.linalg.norm(ends - self._aim, axis=1)))  # keep following this end
        else:
            first = self._initial_end(curve, state)
            if len(self.found) >= 2:
                return self._stop("extremities", curve, t0, timings)
        oriented = curve if first == 0 else curve[::-1]
        self._heading = oriented[0]
        tangent = _end_tangent(oriented, TANGENT_SPAN_M)
        d = oriented[0] + self.cfg.delta_distance_voxels * self.voxel * tangent
        poses = self._views(state, d, oriented[0], tangent)
        self._aim, self._check = d, True
        return self._plan(poses, d, curve, t0, timings)

    def _initial_end(self, curve: np.ndarray, state: ScanState) -> int:
        """The paper's choice at the initial view: if an extremity is already in view, explore toward
        the other end (recording it in `found`); otherwise the end nearest the camera. An end is an
        extremity in view when the surface was seen going on past it with no paint there (a cut by
        the image border or an occluding edge leaves no surface there; a gap, paint beyond it). Not
        tried on a curve too short for a trustworthy tangent: exploring that end costs one view."""
        ends = curve[[0, -1]]
        nearest = int(np.argmin(np.linalg.norm(ends - state.camera_pose[:3, 3], axis=1)))
        if np.linalg.norm(np.diff(curve, axis=0), axis=1).sum() < 2 * TANGENT_SPAN_M:
            return nearest
        closed = []
        for i, oriented in enumerate((curve, curve[::-1])):  # the two ends
            end, t = oriented[0], _end_tangent(oriented, TANGENT_SPAN_M)
            # thinning shortens the curve by ~2 cm: measure from the last paint point along t
            rel = state.drawing.xyz - end
            near = np.sum(rel**2, axis=1) < TANGENT_SPAN_M**2
            probe = end + (max(float((rel[near] @ t).max(initial=0.0)), 0.0) + PROBE_GAP_M) * t
            seen = np.count_nonzero(np.sum((state.surface.xyz - probe) ** 2, axis=1) < PROBE_RADIUS_M**2)
            paint = np.any(np.sum((state.drawing.xyz - probe) ** 2, axis=1) < PROBE_RADIUS_M**2)
            if not paint and seen >= PROBE_FILL * np.pi * (PROBE_RADIUS_M / self.surface_voxel) ** 2:
                closed.append(i)
        self.found.extend(ends[i] for i in closed)
        return 1 - closed[0] if len(closed) == 1 else nearest

    def _views(self, state: ScanState, d: np.ndarray, end: np.ndarray, tangent: np.ndarray) -> list[np.ndarray]:
        """Square-on views of d (§V-A: orthogonal to the surface there), best first: the configured
        standoff along the outward normal, then nearer/farther, then swung about the tangent."""
        r = self.cfg.normal_radius_m
        n = outward_normal(state.surface, d, r)
        if n is None:
            n = outward_normal(state.surface, end, r)
        if n is None:
            n = WORLD_UP
        axis = tangent - np.dot(tangent, n) * n  # the tangent within the surface: the tilt axis
        if np.linalg.norm(axis) < 1e-6:  # a line leaving the surface: any axis across n will do
            axis = np.cross(n, WORLD_UP if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0]))
        axis /= np.linalg.norm(axis)
        standoffs = list(dict.fromkeys((self.cfg.standoff_m, *FALLBACK_STANDOFFS_M)))
        eyes = np.array([d + s * _rotate(n, axis, tilt) for tilt in TILTS_DEG for s in standoffs])
        return list(poses_from(eyes, look_at_rotations(eyes, d)))

    def _plan(self, poses, target, curve, t0, timings) -> ViewPlan:
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        m = len(poses)
        timings["plan_s"] = time.perf_counter() - t0
        # E-NVP scores nothing: `quality` is only the rank (1, then descending), gain is zero
        return ViewPlan(poses, 1.0 - np.arange(m) / m, np.zeros(m), False, "", target=np.asarray(target),
                        frontier=curve, timings=timings)

    @staticmethod
    def _stop(reason: str, curve: np.ndarray, t0: float, timings: dict) -> ViewPlan:
        timings["plan_s"] = time.perf_counter() - t0
        return ViewPlan(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), True, reason, frontier=curve, timings=timings)
