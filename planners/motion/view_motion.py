"""From "look from one of these poses" to a collision-free, jerk-limited joint motion.

The paper executes "the first viable" of its ranked views with MoveIt. Here a candidate is viable
when IK finds a collision-free configuration for it and a Ruckig motion to that configuration
stays clear of the floor, the robot itself and the scene as scanned so far, checked densely. The
candidates are first tried in rank order with a straight joint-space motion; only if none is clear do
the best-ranked ones get waypoint routes: the camera backed off along its optical axis at the start
and/or before the goal, and last via the park configuration above the cell. A time budget bounds it."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from planners.motion.collision import Collision, CollisionChecker
from planners.motion.ik import Unreachable, solve_camera_ik
from planners.motion.kinematics import Kinematics
from planners.motion.trajectory import JointPath, plan_through


ESCAPE_M = 0.05  # a start in collision must come free within this much camera travel
HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])  # a roll of 180 deg about the optical axis


@dataclass
class ViewMotion:
    index: int  # which of the ranked poses is reached
    q_goal: np.ndarray
    path: JointPath
    via: str  # "direct", "retract", "approach", "retract+approach", "park"
    tried: int  # candidates tried, this one included
    ik_s: float = 0.0
    check_s: float = 0.0
    rejected: dict[str, int] = field(default_factory=dict)  # why earlier candidates failed, by reason


def _backed_off(T: np.ndarray, d: float) -> np.ndarray:
    B = T.copy()
    B[:3, 3] -= d * T[:3, 2]
    return B


class ViewMotionPlanner:
    """Plans camera moves for one arm; owns no device. ``checker`` None means no collision model
    (then only joint limits and reach are checked)."""

    def __init__(self, kin: Kinematics, max_velocity, max_acceleration, max_jerk, checker: CollisionChecker | None,
                 *, speed_factor: float = 0.5, ik_margin_rad: float = 0.05, ik_seeds: int = 6,
                 retract_m: float = 0.10, park_q: np.ndarray | None = None, max_joint_step_rad: float = math.radians(1.0),
                 max_tcp_step_m: float = 0.01, via_candidates: int = 8, budget_s: float = 60.0,
                 free_roll: bool = True, framed: bool = False):
        if not (math.isfinite(retract_m) and 0 <= retract_m <= 0.5):
            raise ValueError(f"retract_m must be in [0, 0.5] m, got {retract_m!r}")
        self.kin, self.checker = kin, checker
        self.limits = (np.asarray(max_velocity, float), np.asarray(max_acceleration, float), np.asarray(max_jerk, float))
        self.speed_factor, self.margin, self.seeds = speed_factor, ik_margin_rad, ik_seeds
        self.retract_m = retract_m
        self.park_q = None if park_q is None else kin._vec(park_q, "park_q")
        self.step_rad, self.step_m = max_joint_step_rad, max_tcp_step_m
        # Waypoint routes cost several IK solves and path checks each: only the best-ranked candidates
        # get them. budget_s is a safety net only: a tight wall-clock budget (5 s was tried) made a
        # scan's outcome depend on the machine's load.
        self.via_candidates, self.budget_s = int(via_candidates), float(budget_s)
        self.last_collision: Collision | None = None
        # a calibration view needs the roll as asked (free_roll False). A scan view (framed) asks for
        # the planned roll or its half turn, which frame the same rectangle, and else any roll:
        # the D435's image is 87 x 58 deg, so the roll decides how much of a line fits in it.
        self.free_roll = bool(free_roll)
        self.framed = bool(framed) and self.free_roll

    # ------------------------------------------------------------------ pieces
    def _free(self, q: np.ndarray) -> bool:
        return self.checker is None or not self.checker.in_collision(q)

    def _ik(self, T: np.ndarray, seed: np.ndarray, scored_roll: bool = False) -> np.ndarray | None:
        """A collision-free configuration for camera pose T: with ``scored_roll`` at T's own roll or
        its half turn (the image frames the same rectangle), else as the planner was built (any roll
        for a scan view, T's roll for a calibration view)."""
        tries = [(T, False), (T @ HALF_TURN, False)] if scored_roll else [(T, self.free_roll)]
        for T_try, free in tries:
            try:
                return solve_camera_ik(self.kin, T_try, seed, free_roll=free, margin=self.margin, seeds=self.seeds,
                                       accept=self._free).q
            except Unreachable:
                continue
        return None

    def _path(self, waypoints: list[np.ndarray]) -> JointPath:
        v, a, j = self.limits
        return plan_through(np.asarray(waypoints), v, a, j, speed_factor=self.speed_factor,
                            lower=self.kin.lower, upper=self.kin.upper)

    def _clear(self, path: JointPath, start_blocked: bool) -> bool:
        """Is the motion collision-free? A start already in collision (the scan just found an obstacle
        at the arm) may move out within ESCAPE_M of camera travel; everything after it first comes
        free is checked."""
        if self.checker is None:
            return True
        if not start_blocked:
            self.last_collision = self.checker.check_path(path.positions, self.step_rad, self.step_m)
            return self.last_collision is None
        samples, _ = self.checker.path_samples(path.positions, self.step_rad, self.step_m)
        cam = self.kin.fk_positions(samples)
        n_escape = int(np.argmax(np.linalg.norm(cam - cam[0], axis=1) > ESCAPE_M)) or len(samples)
        k = 0
        while k < n_escape and self.checker.in_collision(samples[k]):
            k += 1
        if k == len(samples) or k == n_escape:
            self.last_collision = self.checker.check(samples[k - 1])
            return False
        self.last_collision = self.checker.check_all(samples[k:])
        return self.last_collision is None

    # ------------------------------------------------------------------ the plan
    def _routes(self) -> tuple[str, ...]:
        if self.checker is None:
            return ("direct",)
        routes = ("direct", "retract", "approach", "retract+approach") if self.retract_m > 0 else ("direct",)
        return routes + (("park",) if self.park_q is not None else ())

    def _waypoints(self, route: str, q_now, q_goal, T_goal, memo: dict,
                   scored_roll: bool = False) -> list[np.ndarray] | None:
        """Joint waypoints of a route, or None when one of its poses has no collision-free IK. The
        retract pose depends only on the start and is solved once per plan."""
        wps = [q_now]
        if "retract" in route:
            if "retract" not in memo:
                memo["retract"] = self._ik(_backed_off(self.kin.fk(q_now), self.retract_m), q_now)
            if memo["retract"] is None:
                return None
            wps.append(memo["retract"])
        if route == "park":
            wps.append(self.park_q)
        if "approach" in route:
            q_app = self._ik(_backed_off(T_goal, self.retract_m), q_goal, scored_roll)
            if q_app is None:
                return None
            wps.append(q_app)
        return wps + [q_goal]

    def plan(self, q_now: np.ndarray, poses: np.ndarray) -> ViewMotion:
        """The first of the ranked ``poses`` (M, 4, 4) with a clear motion from ``q_now``. A framed
        planner first looks for one at the roll it was scored at (or its half turn): the planner's
        ranking holds for that image, not for another roll of a better-ranked pose. Only if none
        is reached so is any roll taken.

        Raises:
            Unreachable: no candidate has one; the message counts the reasons and names the first
                collision found.
        """
        memo: dict = {}  # the retract pose depends only on the start: solved once for both passes
        if self.framed:
            try:
                return self._plan(q_now, poses, memo, scored_roll=True)
            except Unreachable:
                pass
        return self._plan(q_now, poses, memo)

    def _plan(self, q_now: np.ndarray, poses: np.ndarray, memo: dict, scored_roll: bool = False) -> ViewMotion:
        q_now = self.kin._vec(q_now, "q_now")
        P = np.asarray(poses, dtype=np.float64)
        if P.ndim != 3 or P.shape[1:] != (4, 4) or len(P) == 0:
            raise ValueError(f"poses must have shape (M, 4, 4) with M >= 1, got {P.shape}")
        center, radius = self.kin.reach_sphere("cam")
        in_reach = np.linalg.norm(P[:, :3, 3] - center, axis=1) <= radius
        rejected = {"beyond reach": int((~in_reach).sum()), "no collision-free IK": 0, "motion collides": 0}
        start_blocked = not self._free(q_now)
        clock = {"ik": 0.0, "check": 0.0}
        first_hit: list[str] = []
        t_start = time.perf_counter()

        def over_budget() -> bool:
            return time.perf_counter() - t_start > self.budget_s

        def attempt(i: int, q_goal: np.ndarray, route: str) -> ViewMotion | None:
            t0 = time.perf_counter()
            wps = self._waypoints(route, q_now, q_goal, P[i], memo, scored_roll)
            clock["ik"] += time.perf_counter() - t0
            if wps is None:
                return None
            t0 = time.perf_counter()
            ok = self._clear(path := self._path(wps), start_blocked)
            clock["check"] += time.perf_counter() - t0
            if ok:
                return ViewMotion(int(i), q_goal, path, route, int(i) + 1, clock["ik"], clock["check"],
                                  {k: v for k, v in rejected.items() if v})
            if not first_hit and self.last_collision is not None:
                first_hit.append(f"pose {i} ({route}): {self.last_collision}")
            return None

        # Pass 1, in rank order: IK and the straight motion (cheap, and most moves are straight).
        # Pass 2, only if none is straight: waypoint routes for the best-ranked candidates with an IK
        # solution, within the time budget.
        solved: list[tuple[int, np.ndarray]] = []
        for n_tried, i in enumerate(np.flatnonzero(in_reach)):
            if over_budget():
                rejected["not tried (time budget)"] = int(in_reach.sum()) - n_tried
                break
            t0 = time.perf_counter()
            q_goal = self._ik(P[i], q_now, scored_roll)
            clock["ik"] += time.perf_counter() - t0
            if q_goal is None:
                rejected["no collision-free IK"] += 1
                continue
            if (mv := attempt(i, q_goal, "direct")) is not None:
                return mv
            solved.append((int(i), q_goal))
        for i, q_goal in solved[: self.via_candidates]:
            if over_budget():
                break
            for route in self._routes()[1:]:
                if (mv := attempt(i, q_goal, route)) is not None:
                    return mv
        rejected["motion collides"] = len(solved)
        reasons = ", ".join(f"{v} {k}" for k, v in rejected.items() if v)
        raise Unreachable(f"none of {len(P)} candidate views has a collision-free motion ({reasons})"
                          + (f"; first collision: {first_hit[0]}" if first_hit else ""))
