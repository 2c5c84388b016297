"""One "scan drawing" job: the exploration loop of §IV wiring an arm, a camera and a planner.

capture -> cloud in base frame -> C_total, D_total -> grid -> planner -> IK -> trajectory -> move,
until the planner says stop. Planning, capture, motion planning and motion are timed apart.

Faults end in a defined state (docs/RELIABILITY.md, "Faults"): a dropped, stale or empty frame is
captured again (at most CAPTURE_ATTEMPTS per view) and noted in ``ScanResult.incidents``; what cannot
be recovered ends the scan with ``error`` set, the arm stopped and everything seen so far kept."""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass
from typing import Callable, TypeVar

import numpy as np

from cellctl.config import MotionConfig
from cellctl.scan.artifacts import paint_overlay
from cellctl.scan.cut import torch_shape
from cellctl.scan.result import ScanResult, StepRecord
from drivers.interfaces import (Arm, ArmAbilities, DeviceError, JointTrajectory, RGBDCamera, RGBDFrame,
                                TrajectoryError)
from planners import clouds, raycast
from planners.base import ScanState, ViewPlan
from planners.clouds import Cloud
from planners.config import PlannersConfig
from planners.grid import OccupancyGrid
from planners.metrics import coverage, displacement
from planners.motion import chain_kernel
from planners.motion import collision
from planners.motion.collision import CollisionChecker, RobotCollisionModel
from planners.motion.ik import Unreachable
from planners.motion.kinematics import Kinematics
from planners.motion.reach_map import reach_map_for
from planners.motion.view_motion import ViewMotionPlanner
from planners.paint_color import PaintSegmenter
from planners.registry import make_planner
from planners.views import look_at_rotations, poses_from

PAINT_VIEW_STEP = 2  # the per-view paint pictures at half the camera's resolution (424 x 240 of a D435)

Out = TypeVar("Out")

REACH_TOL_M = 0.02  # a camera further than this from its planned pose did not reach the view
REACH_TOL_DEG = 5.0
CAPTURE_ATTEMPTS = 3  # captures per view before a camera fault ends the scan
EMPTY_VIEWS = 3  # views in a row with no valid depth before the scan fails


class ScanError(RuntimeError):
    """The scan could not go on; the partial result is kept. ``terminated_by`` names why."""

    def __init__(self, message: str, terminated_by: str = "error"):
        super().__init__(message)
        self.terminated_by = terminated_by


@dataclass(frozen=True)
class Move:
    """One move of the arm to a view: which of the ranked poses it reached, what planning and moving
    took, how it went and how close the camera came to the planned pose."""

    rank: int
    planning_s: float  # IK, collision checks, trajectory
    motion_s: float
    tracking_error_rad: float
    via: str  # direct, retract, approach, retract+approach, park
    contacts: list[dict]  # robot-scene contacts the twin saw on this move
    reach_error_m: float
    reach_error_deg: float


class ScanJob:
    def __init__(self, arm: Arm, camera: RGBDCamera, planner_name: str, pcfg: PlannersConfig,
                 mcfg: MotionConfig, recorder=None, progress: Callable[[StepRecord], None] | None = None,
                 park_q: np.ndarray | None = None, cancel: threading.Event | None = None,
                 stopped_as: Callable[[], str] = lambda: "cancelled"):
        self.arm, self.camera, self.pcfg, self.mcfg = arm, camera, pcfg, mcfg
        self.abilities = ArmAbilities.of(arm)  # the arm's optional abilities, checked once here
        self.cancel = cancel  # set by another thread: the scan ends after the current step, the arm at once
        self.stopped_as = stopped_as  # why, in terminated_by's words: cancelled (operator), timeout, interrupted
        self.planner = make_planner(planner_name, pcfg)
        m = arm.model
        self.kin = Kinematics.from_arm_model(m)
        self.reach = reach_map_for(self.kin)  # which candidate views the arm can take at all
        # the torch rides on the hand through the scan too: its moves keep it clear like any link
        self.robot = RobotCollisionModel.from_arm_model(m, mcfg.collision, torch=torch_shape(pcfg.cutpath))
        self.checker = CollisionChecker(self.robot, mcfg.collision) if mcfg.check_collisions else None
        if recorder is not None:
            recorder.log_robot_geometry(self.robot)
        park = mcfg.park_q if mcfg.park_q is not None else park_q
        self.motion = ViewMotionPlanner(self.kin, m.max_velocity, m.max_acceleration, m.max_jerk, self.checker,
                                        speed_factor=mcfg.speed_factor, ik_margin_rad=mcfg.ik_margin_rad,
                                        ik_seeds=mcfg.ik_seeds, retract_m=mcfg.retract_m,
                                        via_candidates=mcfg.via_candidates, budget_s=mcfg.motion_budget_s,
                                        framed=mcfg.framed_views, park_q=None if park is None else np.asarray(park, dtype=np.float64))
        self._scene_stale = True  # the collision scene lags the grid until the next move
        self.recorder = recorder
        self.progress = progress
        raycast.warmup()  # compile before the clock starts, like any service would at boot
        chain_kernel.warmup()
        clouds.warmup()
        collision.warmup()
        self.grid = OccupancyGrid(pcfg.grid)
        self._surface_total = clouds.CloudTotal(pcfg.grid.surface_voxel_m)
        self._drawing_total = clouds.CloudTotal(pcfg.grid.surface_voxel_m)
        self.surface = self._surface_total.cloud
        self.drawing = self._drawing_total.cloud
        self.paint = PaintSegmenter(pcfg.paint)  # fitted on the initial view, then the paint mask of every view
        self.view_paint: np.ndarray | None = None  # (H, W) bool: the last view's paint on its picture
        self.paint_views: list[np.ndarray] = []  # each view's picture with its paint, halved: paint_view<k>.png
        self.paint_view: tuple[np.ndarray, np.ndarray] | None = None  # the initial image and what was paint in it
        self.empty_frames = 0
        self.frames_without_depth = 0  # captures with no valid depth pixel since the last view that had one
        self.last_stamp: float | None = None  # timestamp of the last frame accepted or refused as empty
        self.incidents: list[dict] = []
        log = self.abilities.events  # the arm's own log (Franka: reflexes, recoveries)
        self._arm_events_from = len(log.events) if log is not None else 0
        self.self_filtered = 0  # points dropped because they lay on the arm
        self.tracking_errors: list[float] = []  # what arm.execute() returned, per move
        self.first_color: np.ndarray | None = None  # the initial view, for the run folder's picture
        intr = camera.intrinsics
        self.K = intr.matrix()
        self.image_size = (intr.width, intr.height)

    # --- motion ---------------------------------------------------------------------------------
    def _move(self, poses: np.ndarray) -> Move:
        """Reach the first of the ranked poses with a clear motion. The collision scene is the grid as
        scanned so far."""
        t0 = time.perf_counter()
        if self.checker is not None and self._scene_stale:
            self.checker.set_scene_from_grid(self.grid)
            self._scene_stale = False
        mv = self.motion.plan(self.arm.joint_positions(), poses)
        plan_s = time.perf_counter() - t0
        path = mv.path
        err = float(self.arm.execute(JointTrajectory(path.times, path.positions, path.velocities)))
        self.tracking_errors.append(err)
        contacts = self.abilities.contacts  # the twin's own check
        # Did the camera get there? A view from elsewhere (the arm stopped or deflected on the way)
        # must not count as the planned one.
        T, goal = self.arm.camera_pose(), poses[mv.index]
        return Move(mv.index, plan_s, float(path.duration), err, mv.via,
                    list(contacts.last_motion_contacts) if contacts is not None else [],
                    float(np.linalg.norm(T[:3, 3] - goal[:3, 3])),
                    float(np.degrees(np.arccos(np.clip(T[:3, 2] @ goal[:3, 2], -1.0, 1.0)))))

    @staticmethod
    def _count(res: ScanResult, mv: Move) -> None:
        """A move outside the views' steps (the initial one, park, the cut's views) into the job's totals."""
        res.motion_planning_s += mv.planning_s
        res.motion_s += mv.motion_s
        res.motion_contacts += len(mv.contacts)

    def look_along(self, targets: list[tuple[np.ndarray, np.ndarray]], res: "ScanResult") -> int:
        """Views for the cut, after the scan: for each (point, outward normal) the camera looks at the
        point from where the torch would come, so the space the torch needs is seen, not assumed solid
        (the collision model counts unseen space near the object as metal). Returns the views taken;
        an unreachable one is skipped."""
        taken = 0
        for point, normal in targets:  # one or two views
            n = normal / np.linalg.norm(normal)
            a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
            a /= np.linalg.norm(a)
            b = np.cross(n, a)
            dirs = [n] + [np.cos(t) * n + np.sin(t) * (np.cos(f) * a + np.sin(f) * b)
                          for t in np.radians([15.0, 30.0]) for f in np.radians(np.arange(0, 360, 60))]
            eyes = np.array([point + d * u for d in (0.35, 0.45) for u in dirs])
            poses = poses_from(eyes, look_at_rotations(eyes, point))
            try:
                mv = self._move(poses)
            except Unreachable:
                continue
            k = len(res.records) + taken
            frame = self._capture(k)
            self.process(frame, self.arm.camera_pose(), self.arm.joint_positions())
            self._count(res, mv)
            taken += 1
        return taken

    def for_the_cut(self, res: "ScanResult", what: str, fn: Callable[[], Out]) -> Out | None:
        """A move or a view after the scan, for the cut: optional, so a fault there (a reflex, a lost
        camera, no clear motion) is an incident, the arm is stopped (and recovered if it must be), and
        the cut is planned from what was seen."""
        try:
            return fn()
        except (DeviceError, TrajectoryError, Unreachable, ScanError) as e:
            self._incident(len(res.records), "cut-move", f"{what} skipped: {type(e).__name__}: {e}")
            _, notes = stop_and_recover(self.arm, self.abilities)
            for kind, detail in notes:
                self._incident(len(res.records), kind, detail)
            return None

    def go_park(self, res: "ScanResult") -> bool:
        """Move to the park configuration's camera pose (clear above the cell): the cut starts from
        a known clear configuration, not from wherever the last view left the arm and its torch."""
        park = self.motion.park_q
        if park is None:
            return False
        if np.max(np.abs(self.arm.joint_positions() - park)) < 1e-3:
            return True
        try:
            self._count(res, self._move(self.kin.fk(park)[None]))
        except Unreachable:
            return False
        return True

    def move_to_initial(self, candidates: np.ndarray) -> Move:
        if len(candidates) == 0:
            raise ScanError("no initial view: the scene gives no pose that sees the drawing")
        try:
            return self._move(candidates)
        except Unreachable as e:
            raise ScanError(f"no initial view is reachable: {e}", "unreachable") from None

    # --- faults ---------------------------------------------------------------------------------
    def _incident(self, step: int, what: str, detail: str) -> None:
        self.incidents.append({"step": step, "what": what, "detail": detail[:500]})

    def _capture(self, k: int) -> RGBDFrame:
        """A frame for view ``k``. A capture that fails (dropped frame), repeats the last timestamp
        (stale: the view it shows may be from before the move) or has no valid depth pixel is taken
        again, at most CAPTURE_ATTEMPTS times. Then: DeviceError, except for a view after the first
        whose frames arrived but held no depth, which goes on as an empty view (a view of nothing is
        not a fault, EMPTY_VIEWS of them in a row are)."""
        problems: dict[str, list[str]] = {}  # kind -> details, in order
        empty: RGBDFrame | None = None
        for attempt in range(CAPTURE_ATTEMPTS):
            try:
                frame = self.camera.capture()
            except DeviceError as e:
                self._refuse(k, problems, "no frame", str(e))
                continue
            stamp = float(frame.timestamp)
            if not np.isfinite(stamp) or (self.last_stamp is not None and stamp <= self.last_stamp):
                self._refuse(k, problems, "stale frame", f"timestamp {stamp:.6f} s did not advance past the "
                                                         f"last frame's ({self.last_stamp} s)")
                continue
            self.last_stamp = stamp
            d = frame.depth
            if not np.any(np.isfinite(d) & (d > 0)):
                self.frames_without_depth += 1
                self._refuse(k, problems, "no valid depth", "every depth pixel is NaN, zero or negative")
                empty = frame
                continue
            if attempt:
                self._incident(k, "recovered", f"usable frame at attempt {attempt + 1} of {CAPTURE_ATTEMPTS}")
            return frame
        if empty is not None and k > 0:
            return empty  # frames arrive but hold no depth: an empty view (counted by process)
        why = "; ".join(f"{len(v)} x {kind} (last: {v[-1]})" for kind, v in problems.items())
        if empty is not None:  # the initial view was chosen to see the drawing: no depth there is a fault
            raise DeviceError(f"camera returned no valid depth in {self.frames_without_depth} frames at the "
                              f"initial view: {why}")
        raise DeviceError(f"camera gave no usable frame for view {k} in {CAPTURE_ATTEMPTS} attempts: {why}")

    def _refuse(self, k: int, problems: dict[str, list[str]], kind: str, detail: str) -> None:
        problems.setdefault(kind, []).append(detail)
        self._incident(k, kind.replace(" ", "_"), detail)

    def _stop_arm(self, res: ScanResult) -> None:
        """After an error the arm must not be left moving: stop it and record that it answered."""
        res.arm_stopped, notes = stop_and_recover(self.arm, self.abilities)
        for what, detail in notes:
            self._incident(len(res.records), what, detail)

    # --- perception -----------------------------------------------------------------------------
    def process(self, frame, T_base_cam: np.ndarray, q: np.ndarray) -> Cloud:
        """ProcessClouds of §IV-B plus the grid update. Returns on the arm itself (at joints q) are
        dropped first: the arm must not become an obstacle to itself."""
        g = self.pcfg.grid
        cloud, pixels = clouds.frame_to_base_cloud(frame.color, frame.depth, self.K, T_base_cam, pixels=True,
                                                   lens=frame.intrinsics.lens)
        self.view_paint = None
        keep = self._off_robot(cloud, q)
        if keep is not None:
            cloud, pixels = cloud.select(keep), pixels[keep]
        if len(cloud) == 0:
            # A view of nothing (everything nearer than the sensor's minimum range, or empty space)
            # teaches nothing but is not a fault; several in a row are.
            self.empty_frames += 1
            if self.empty_frames >= EMPTY_VIEWS:
                raise DeviceError(f"camera returned no valid depth in {max(self.frames_without_depth, EMPTY_VIEWS)} "
                                  f"frames ({EMPTY_VIEWS} views in a row with no depth left after the range and "
                                  f"self filters: all NaN, zero or out of range)")
            return cloud
        self.empty_frames = 0
        self.frames_without_depth = 0
        self.surface = self._surface_total.add(cloud)
        if not self.paint.fitted:
            self._check_paint(frame, cloud, pixels)
        paint = self.paint.paint_points(cloud.rgb, cloud.xyz)
        h, w = frame.color.shape[:2]
        on = np.zeros(h * w, dtype=bool)
        on[pixels[paint]] = True
        self.view_paint = on.reshape(h, w)  # what this view took as paint, on its picture (Rerun, the tablet)
        self.paint_views.append(paint_overlay(frame.color[::PAINT_VIEW_STEP, ::PAINT_VIEW_STEP],
                                              self.view_paint[::PAINT_VIEW_STEP, ::PAINT_VIEW_STEP]))
        self.drawing = self._drawing_total.add(cloud.select(paint))
        # the rays that carve free space: every integrate_stride_px-th pixel of the same filtered frame
        rays = cloud.select(clouds.on_stride(pixels, frame.depth.shape[1], g.integrate_stride_px))
        self.grid.integrate(T_base_cam[:3, 3], rays.xyz)
        self.grid.set_drawing(self.drawing.xyz)
        self._scene_stale = True
        return cloud

    def _check_paint(self, frame, cloud: Cloud, pixels: np.ndarray) -> None:
        """The first view with depth fits the paint's colour to this piece and checks that what looks like
        paint is a line apart from its metal (rule 1: where the cell cannot tell paint from metal it refuses).
        A refusal ends the scan here, before any further motion, with the picture of what was paint."""
        check = self.paint.fit_view(cloud.rgb, cloud.xyz, self.pcfg.grid.lo_m[2],
                                     workspace=(self.pcfg.grid.lo_m, self.pcfg.grid.hi_m))
        h, w = frame.color.shape[:2]
        on = np.zeros(h * w, dtype=bool)
        on[pixels] = self.paint.paint_points(cloud.rgb, cloud.xyz)
        self.paint_view = (frame.color, on.reshape(h, w))
        if not check.ok:
            raise ScanError(f"paint_not_separable: {check.reason}", "paint_not_separable")
        for wtext in check.warnings:
            self._incident(0, "paint_warning", wtext)

    def _off_robot(self, cloud: Cloud, q: np.ndarray) -> np.ndarray | None:
        """Mask of the points not on the arm at joints q, or None when all are kept."""
        if self.mcfg.self_filter_pad_m <= 0 or len(cloud) == 0:
            return None
        on = self.robot.on_robot(cloud.xyz, q, self.mcfg.self_filter_pad_m)
        self.self_filtered += int(on.sum())
        return ~on if on.any() else None

    # --- cancellation ---------------------------------------------------------------------------
    def cancelled(self) -> bool:
        return self.cancel is not None and self.cancel.is_set()


    def _stop_arm_on_cancel(self, done: threading.Event) -> None:
        """A move takes seconds: an operator's cancel stops the arm mid-way, not at the next view."""
        while not done.wait(0.05):
            if self.cancelled():
                self.arm.stop()
                return

    # --- the loop -------------------------------------------------------------------------------
    def run(self, scene_name: str, initial_candidates: np.ndarray, gt_points: np.ndarray) -> ScanResult:
        res = ScanResult(scene=scene_name, planner=self.planner.name)
        done = threading.Event()
        if self.cancel is not None:
            threading.Thread(target=self._stop_arm_on_cancel, args=(done,), name="scan-cancel", daemon=True).start()
        try:
            if self.cancelled():
                res.terminated_by = self.stopped_as()
                return res
            self._count(res, self.move_to_initial(initial_candidates))
            initial_pose = self.arm.camera_pose()
            self._explore(res, initial_pose, gt_points)
        except Exception as e:  # noqa: BLE001 - any failure ends the scan, never loses what was recorded
            if self.cancelled():  # the stopped arm's TrajectoryError is the cancel itself, not a fault
                res.terminated_by = self.stopped_as()
                return res
            self._stop_arm(res)
            res.error = f"{type(e).__name__}: {e}"
            if not isinstance(e, (ScanError, DeviceError, TrajectoryError, Unreachable, ValueError)):
                res.error += "\n" + traceback.format_exc(limit=6)
            res.terminated_by = res.terminated_by or getattr(e, "terminated_by", "error")
            self._incident(len(res.records), "error", res.error)
        finally:
            done.set()
            res.incidents = self.incidents
            res.paint = self.paint.check
            log = self.abilities.events
            res.arm_events = [dict(e) for e in log.events[self._arm_events_from:]] if log is not None else []
            cov = coverage(self.drawing.xyz, gt_points, self.pcfg.coverage_voxel_m)
            res.coverage_hit, res.coverage_total, res.coverage_percent = cov.hit, cov.total, round(cov.percent, 2)
            res.steps = len(res.records)
            res.displacement_m = displacement(np.array(res.viewpoints)) if res.viewpoints else 0.0
            res.step_s = res.planning_s / max(res.steps - 1, 1) if res.steps else 0.0  # eq. 11: per viewpoint
            if self.tracking_errors:
                res.tracking_error_max_rad = round(float(np.max(self.tracking_errors)), 5)
                res.tracking_error_median_rad = round(float(np.median(self.tracking_errors)), 5)
        return res

    def _explore(self, res: ScanResult, initial_pose: np.ndarray, gt_points: np.ndarray | None) -> None:
        last_plan: ViewPlan | None = None
        for k in range(self.pcfg.max_steps):
            if self.cancelled():
                res.terminated_by = self.stopped_as()
                return
            t0 = time.perf_counter()
            frame = self._capture(k)
            T = self.arm.camera_pose()
            q = self.arm.joint_positions()
            if self.first_color is None:
                self.first_color = frame.color
            t1 = time.perf_counter()
            try:
                cloud = self.process(frame, T, q)
            except ScanError:
                if self.recorder and self.paint_view is not None:  # the refused view, with what was taken as paint
                    self.recorder.log_view(k, T, self.K, self.image_size, frame.color, frame.depth, np.zeros((0, 3)),
                                           np.zeros((0, 3), np.uint8), self.paint_view[1])
                raise
            t_proc = time.perf_counter() - t1
            if len(cloud) == 0 and last_plan is not None:
                self.planner.reject(last_plan)  # that view saw nothing: do not aim there again
            state = ScanState(k, self.grid, self.surface, self.drawing, cloud, T, initial_pose, self.K, self.image_size,
                              np.array(res.viewpoints + [T[:3, 3].tolist()]), self.reach.reachable)
            plan = self.planner.next_view(state)
            t2 = time.perf_counter()
            rec = StepRecord(step=k, camera_position=T[:3, 3].round(4).tolist(), points=len(self.surface),
                             drawing_points=len(self.drawing), frontier_cells=len(plan.frontier),
                             candidates=len(plan.poses), best_quality=_first(plan.quality), best_gain=_first(plan.gain),
                             planning_s=t2 - t1, capture_s=t1 - t0, process_s=t_proc)
            if gt_points is not None and len(gt_points):
                rec.coverage_percent = round(coverage(self.drawing.xyz, gt_points, self.pcfg.coverage_voxel_m).percent, 2)
            res.viewpoints.append(T[:3, 3].tolist())
            res.records.append(rec)
            res.capture_s += rec.capture_s
            if self.recorder:
                self.recorder.log_robot_pose(k, self.robot.links, self.robot.link_poses(q))
                # what the scan took for paint: the paint's colour, on the piece
                paint = self.view_paint if self.view_paint is not None else np.zeros(frame.color.shape[:2], bool)
                self.recorder.log_view(k, T, self.K, self.image_size, frame.color, frame.depth, cloud.xyz, cloud.rgb,
                                       paint)
                self.recorder.log_coverage(k, len(self.drawing), rec.coverage_percent)
                self.recorder.log_plan(k, plan.frontier, self.grid.voxel, plan.poses, plan.quality, plan.target,
                                       self.drawing.xyz)
            last = k == self.pcfg.max_steps - 1  # the step limit: no view will be captured there, so no move
            if not plan.stop and not last and not self.cancelled():  # a cancel during planning: no new move
                plan = self._go(plan, state, rec)
            last_plan = plan
            res.planning_s += rec.planning_s
            res.motion_planning_s += rec.motion_planning_s
            res.motion_s += rec.motion_s
            res.motion_contacts += len(rec.contacts)
            if self.recorder is not None:
                self.recorder.flush()  # what a step's event reports is on disk before the event goes out
            if self.progress:
                self.progress(rec)
            if plan.stop:
                res.terminated_by = plan.reason
                return
        res.terminated_by = "max_steps"

    def _go(self, plan: ViewPlan, state: ScanState, rec: StepRecord) -> ViewPlan:
        """Execute the first reachable candidate; if none is, the planner gives that target up and
        plans again (time counted as planning)."""
        n = self.pcfg.nbv.ik_candidates
        for _ in range(4):
            if plan.stop:
                return plan
            t_move = time.perf_counter()
            try:
                if len(plan.poses) == 0:
                    raise Unreachable("planner offered no candidate for this target")
                mv = self._move(plan.poses[:n])
                rec.chosen_rank, rec.motion_s, rec.tracking_error_rad = mv.rank, mv.motion_s, mv.tracking_error_rad
                rec.motion_planning_s += mv.planning_s
                rec.reach_error_m, rec.reach_error_deg = mv.reach_error_m, mv.reach_error_deg
                rec.contacts, rec.via = mv.contacts, mv.via
                if rec.reach_error_m > REACH_TOL_M or rec.reach_error_deg > REACH_TOL_DEG:
                    plan.tried = mv.rank + 1
                    self.planner.reject(plan)  # the view will not be where it was planned: give the target up
                return plan
            except Unreachable:
                rec.motion_planning_s += time.perf_counter() - t_move
                plan.tried = min(n, len(plan.poses))
                self.planner.reject(plan)
                rec.replans += 1
                t = time.perf_counter()
                plan = self.planner.next_view(state)
                rec.planning_s += time.perf_counter() - t
        plan.stop, plan.reason = True, "unreachable"
        return plan


def stop_and_recover(arm: Arm, abilities: ArmAbilities | None = None) -> tuple[bool, list[tuple[str, str]]]:
    """Stop the arm; a ``Recoverable`` arm that then needs recovery (a Franka after a reflex or a lost
    connection: it refuses every motion until ``recover_from_errors``) is recovered now, so the cell can
    take the next job, and the job records it. ``abilities``: the arm's, as checked where it was wired
    (default: checked now). Returns (stopped, [(incident, detail)])."""
    notes: list[tuple[str, str]] = []
    try:
        arm.stop()
        stopped = True
    except Exception as e:  # noqa: BLE001 - the error being reported matters more; note this one
        stopped = False
        notes.append(("arm_stop_failed", f"{type(e).__name__}: {e}"))
    recovery = (abilities if abilities is not None else ArmAbilities.of(arm)).recovery
    pending = recovery.needs_recovery if recovery is not None else None
    if pending:
        try:
            event = recovery.recover()
            notes.append(("arm_recovered", f"after {pending}: {event.get('message', '') if isinstance(event, dict) else ''}"
                          .rstrip(": ")))
        except Exception as e:  # noqa: BLE001 - recorded; the next job's execute() refuses clearly
            notes.append(("arm_recovery_failed", f"after {pending}: {type(e).__name__}: {e}"))
    return stopped, notes


def _first(a: np.ndarray) -> float | None:
    return float(a[0]) if len(a) else None
