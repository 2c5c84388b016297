"""One "scan drawing" job: the exploration loop of §IV wiring an arm, a camera and a planner.

capture -> cloud in base frame -> C_total, D_total -> grid -> planner -> IK -> trajectory -> move,
until the planner says stop. Planning, capture, motion planning and motion are timed apart."""

from __future__ import annotations

import importlib
import time
import traceback
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from cellctl.config import MotionConfig
from drivers.interfaces import Arm, DeviceError, JointTrajectory, RGBDCamera
from planners import clouds, raycast
from planners.base import ScanState, ViewPlan
from planners.clouds import Cloud
from planners.config import PlannersConfig
from planners.grid import OccupancyGrid
from planners.metrics import coverage, displacement
from planners.motion.ik import Unreachable, solve_camera_ik_many
from planners.motion.kinematics import Kinematics
from planners.motion.trajectory import plan_joint_motion

# name -> "module:class"; imported on demand so one planner's dependencies never load another's
PLANNERS = {
    "enpv": "planners.enpv:ExtrapolatedNVP",
    "cnbv": "planners.cnbv:ConstrainedNBV",
    "gnbv": "planners.gnbv:GuidedNBV",
    "global": "planners.global_nbv:GlobalNBV",
}


REACH_TOL_M = 0.02  # a camera further than this from its planned pose did not reach the view
REACH_TOL_DEG = 5.0


class ScanError(RuntimeError):
    """The scan could not go on; the partial result is kept."""


def make_planner(name: str, cfg: PlannersConfig):
    """A fresh planner for one scan (planners keep per-scan memory)."""
    try:
        module, cls = PLANNERS[name].split(":")
    except KeyError:
        raise ValueError(f"unknown planner {name!r}; choose one of {', '.join(PLANNERS)}") from None
    return getattr(importlib.import_module(module), cls)(cfg)


@dataclass
class StepRecord:
    step: int
    camera_position: list[float]
    points: int
    drawing_points: int
    frontier_cells: int
    candidates: int
    best_quality: float | None
    best_gain: float | None
    planning_s: float  # eq. 10's share of this step: cloud processing + grid update + view planning
    capture_s: float
    process_s: float = 0.0  # of planning_s: clouds, colour filter, grid update
    ik_s: float = 0.0
    motion_s: float = 0.0
    tracking_error_rad: float = 0.0
    chosen_rank: int | None = None
    replans: int = 0
    coverage_percent: float | None = None  # against ground truth, when the scene has one (twin)
    reach_error_m: float = 0.0  # camera position reached vs planned
    reach_error_deg: float = 0.0  # optical axis reached vs planned
    contacts: list[dict] = field(default_factory=list)  # robot-scene contacts the twin saw on this move


@dataclass
class ScanResult:
    scene: str
    planner: str
    steps: int = 0
    planning_s: float = 0.0
    step_s: float = 0.0
    capture_s: float = 0.0
    motion_planning_s: float = 0.0
    motion_s: float = 0.0
    displacement_m: float = 0.0
    coverage_hit: int = 0
    coverage_total: int = 0
    coverage_percent: float = 0.0
    terminated_by: str = ""
    motion_contacts: int = 0  # robot-scene contacts the twin reported over all moves (twin only)
    error: str | None = None
    viewpoints: list[list[float]] = field(default_factory=list)
    records: list[StepRecord] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


class ScanJob:
    def __init__(self, arm: Arm, camera: RGBDCamera, planner_name: str, pcfg: PlannersConfig,
                 mcfg: MotionConfig, recorder=None, progress: Callable[[StepRecord], None] | None = None):
        self.arm, self.camera, self.pcfg, self.mcfg = arm, camera, pcfg, mcfg
        self.planner = make_planner(planner_name, pcfg)
        m = arm.model
        self.kin = Kinematics(m.urdf_path, m.joint_names, m.flange_link, m.T_flange_cam, lower=m.lower, upper=m.upper)
        self.recorder = recorder
        self.progress = progress
        raycast.warmup()  # compile before the clock starts, like any service would at boot
        self.grid = OccupancyGrid(pcfg.grid)
        self.surface = Cloud.empty()
        self.drawing = Cloud.empty()
        self.empty_frames = 0
        self.last_reach_error_m = self.last_reach_error_deg = 0.0
        self.last_contacts: list[dict] = []
        self.first_color: np.ndarray | None = None  # the initial view, for the run folder's picture
        intr = camera.intrinsics
        self.K = intr.matrix()
        self.image_size = (intr.width, intr.height)

    # --- motion ---------------------------------------------------------------------------------
    def _move(self, poses: np.ndarray) -> tuple[int, float, float, float]:
        """Reach the first reachable of the ranked poses: (rank, ik_s, motion_s, tracking error)."""
        t0 = time.perf_counter()
        q_now = self.arm.joint_positions()
        idx, ik = solve_camera_ik_many(self.kin, poses, q_now, margin=self.mcfg.ik_margin_rad,
                                       seeds=self.mcfg.ik_seeds)
        m = self.arm.model
        path = plan_joint_motion(q_now, ik.q, m.max_velocity, m.max_acceleration, m.max_jerk,
                                 speed_factor=self.mcfg.speed_factor)
        ik_s = time.perf_counter() - t0
        err = self.arm.execute(JointTrajectory(path.times, path.positions, path.velocities))
        self.last_contacts = list(getattr(self.arm, "last_motion_contacts", []))  # the twin's own check
        # Did the camera get there? Without collision checking yet (issue 4) the arm can be stopped
        # by the object on the way; a view from elsewhere must not count as the planned one.
        T = self.arm.camera_pose()
        self.last_reach_error_m = float(np.linalg.norm(T[:3, 3] - poses[idx][:3, 3]))
        self.last_reach_error_deg = float(np.degrees(np.arccos(np.clip(T[:3, 2] @ poses[idx][:3, 2], -1.0, 1.0))))
        return idx, ik_s, float(path.duration), float(err)

    def move_to_initial(self, candidates: np.ndarray) -> tuple[int, float, float]:
        if len(candidates) == 0:
            raise ScanError("no initial view: the scene gives no pose that sees the drawing")
        try:
            idx, ik_s, motion_s, _ = self._move(candidates)
        except Unreachable as e:
            raise ScanError(f"no initial view is reachable: {e}") from None
        return idx, ik_s, motion_s

    # --- perception -----------------------------------------------------------------------------
    def _process(self, frame, T_base_cam: np.ndarray) -> Cloud:
        """ProcessClouds of §IV-B plus the grid update."""
        g = self.pcfg.grid
        cloud = clouds.frame_to_base_cloud(frame.color, frame.depth, self.K, T_base_cam)
        if len(cloud) == 0:
            # A view of nothing (everything nearer than the sensor's minimum range, or empty space)
            # teaches nothing but is not a fault; several in a row are.
            self.empty_frames += 1
            if self.empty_frames >= 3:
                raise DeviceError("camera returned 3 frames in a row with no valid depth (all NaN, zero or out of range)")
            return cloud
        self.empty_frames = 0
        self.surface = clouds.concatenate(self.surface, cloud, g.surface_voxel_m)
        c = self.pcfg.color
        paint = clouds.color_mask(cloud.rgb, c.hue_center_deg, c.hue_halfwidth_deg, c.s_min, c.v_min)
        self.drawing = clouds.concatenate(self.drawing, cloud.select(paint), g.surface_voxel_m)
        rays = clouds.frame_to_base_cloud(frame.color, frame.depth, self.K, T_base_cam, stride=g.integrate_stride_px)
        self.grid.integrate(T_base_cam[:3, 3], rays.xyz)
        self.grid.set_drawing(self.drawing.xyz)
        return cloud

    # --- the loop -------------------------------------------------------------------------------
    def run(self, scene_name: str, initial_candidates: np.ndarray, gt_points: np.ndarray) -> ScanResult:
        res = ScanResult(scene=scene_name, planner=self.planner.name)
        try:
            _, ik_s, motion_s = self.move_to_initial(initial_candidates)
            res.motion_contacts += len(self.last_contacts)
            res.motion_planning_s += ik_s
            res.motion_s += motion_s
            initial_pose = self.arm.camera_pose()
            self._explore(res, initial_pose, gt_points)
        except Exception as e:  # noqa: BLE001 - any failure ends the scan, never loses what was recorded
            res.error = f"{type(e).__name__}: {e}"
            if not isinstance(e, (ScanError, DeviceError, Unreachable, ValueError)):
                res.error += "\n" + traceback.format_exc(limit=6)
            res.terminated_by = res.terminated_by or "error"
        finally:
            cov = coverage(self.drawing.xyz, gt_points, self.pcfg.coverage_voxel_m)
            res.coverage_hit, res.coverage_total, res.coverage_percent = cov.hit, cov.total, round(cov.percent, 2)
            res.steps = len(res.records)
            res.displacement_m = displacement(np.array(res.viewpoints)) if res.viewpoints else 0.0
            res.step_s = res.planning_s / res.steps if res.steps else 0.0
        return res

    def _explore(self, res: ScanResult, initial_pose: np.ndarray, gt_points: np.ndarray | None) -> None:
        last_plan: ViewPlan | None = None
        for k in range(self.pcfg.max_steps):
            t0 = time.perf_counter()
            frame = self.camera.capture()
            T = self.arm.camera_pose()
            if self.first_color is None:
                self.first_color = frame.color
            t1 = time.perf_counter()
            cloud = self._process(frame, T)
            t_proc = time.perf_counter() - t1
            if len(cloud) == 0 and last_plan is not None:
                self.planner.reject(last_plan)  # that view saw nothing: do not aim there again
            state = ScanState(k, self.grid, self.surface, self.drawing, cloud, T, initial_pose, self.K, self.image_size,
                              np.array(res.viewpoints + [T[:3, 3].tolist()]))
            plan = self.planner.next_view(state)
            t2 = time.perf_counter()
            rec = StepRecord(k, T[:3, 3].round(4).tolist(), len(self.surface), len(self.drawing), len(plan.frontier),
                             len(plan.poses), _first(plan.quality), _first(plan.gain), t2 - t1, t1 - t0,
                             process_s=t_proc)
            if gt_points is not None and len(gt_points):
                rec.coverage_percent = round(coverage(self.drawing.xyz, gt_points, self.pcfg.coverage_voxel_m).percent, 2)
            res.viewpoints.append(T[:3, 3].tolist())
            res.records.append(rec)
            res.capture_s += rec.capture_s
            if self.recorder:
                self.recorder.log_view(k, T, self.K, self.image_size, frame.color, frame.depth, cloud.xyz, cloud.rgb)
                self.recorder.log_plan(k, plan.frontier, self.grid.voxel, plan.poses, plan.quality, plan.target,
                                       self.drawing.xyz)
            if not plan.stop:
                plan = self._go(plan, state, rec)
            last_plan = plan
            res.planning_s += rec.planning_s
            res.motion_planning_s += rec.ik_s
            res.motion_s += rec.motion_s
            res.motion_contacts += len(rec.contacts)
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
            try:
                if len(plan.poses) == 0:
                    raise Unreachable("planner offered no candidate for this target")
                rank, ik_s, motion_s, err = self._move(plan.poses[:n])
                rec.chosen_rank, rec.ik_s, rec.motion_s, rec.tracking_error_rad = rank, rec.ik_s + ik_s, motion_s, err
                rec.reach_error_m, rec.reach_error_deg = self.last_reach_error_m, self.last_reach_error_deg
                rec.contacts = self.last_contacts
                if rec.reach_error_m > REACH_TOL_M or rec.reach_error_deg > REACH_TOL_DEG:
                    plan.tried = rank + 1
                    self.planner.reject(plan)  # the view will not be where it was planned: give the target up
                return plan
            except Unreachable:
                plan.tried = min(n, len(plan.poses))
                self.planner.reject(plan)
                rec.replans += 1
                t = time.perf_counter()
                plan = self.planner.next_view(state)
                rec.planning_s += time.perf_counter() - t
        plan.stop, plan.reason = True, "unreachable"
        return plan


def _first(a: np.ndarray) -> float | None:
    return float(a[0]) if len(a) else None
