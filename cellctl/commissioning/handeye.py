"""`cellctl calibrate hand-eye`: the arm visits poses looking at a ChArUco board, the board is found
in each frame, T_flange_cam is solved (planners/handeye.py) and written where the cell config
reads it (``hand_eye_file``).

``calibrate_hand_eye`` takes any ``Arm`` and ``RGBDCamera`` (drivers/interfaces.py): the twin's
(``run_hand_eye_in_twin``, mode sim) or the cell's own (``run_hand_eye_on_cell``: the Franka adapter with
the D435, or on franky-sim with the twin's renderer). It only trusts what a real cell has: the arm's joints (flange pose by our own FK, which does not involve the extrinsic) and the
images; the extrinsic the arm carries is only used to aim the views, so a rough one is enough.
``run_hand_eye_in_twin`` builds the twin with a board at a known pose and also reports the error
against the twin's true extrinsic.
"""

from __future__ import annotations

import datetime
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from cellctl.config_files import backup, point_config_at, write_record
from cellctl.config import CellConfig, MotionConfig
from cellctl.scan.modes import MODES
from configs.charuco import CharucoBoardConfig
from configs.poses import pose_from_xyz_rpy_deg
from drivers.interfaces import Arm, DeviceError, JointTrajectory, RGBDCamera, RGBDFrame, TrajectoryError
from planners.handeye import (MIN_VIEWS, BoardView, HandEyeError, HandEyeSolution, board_center, calibrate,
                              calibration_views, depth_scale, detect_board, pose_error, xyz_rpy_deg)
from planners.motion.collision import CollisionChecker, RobotCollisionModel, StaticBox
from planners.motion.ik import Unreachable
from planners.motion.kinematics import Kinematics
from planners.motion.view_motion import ViewMotionPlanner

DEFAULT_POSES = 12
MISSES_BEFORE_ABORT = 3  # the first views all without the board: it is not where it was located
BOARD_CLEARANCE_M = 0.01  # the board's collision box is grown by this much each side
TWIN_BOARD_XY = (0.50, 0.0)  # the twin's board: face up on the floor in front of the robot
TWIN_BOARD_YAW_DEG = 0.0


@dataclass
class HandEyeRun:
    solution: HandEyeSolution
    T_base_board_guess: np.ndarray  # where the views were aimed
    visits: list[dict] = field(default_factory=list)  # one per pose tried: reached, corners, why not
    truth_error: tuple[float, float] | None = None  # twin only: (mm, deg) against the true extrinsic
    T_flange_cam_true: np.ndarray | None = None  # twin only
    duration_s: float = 0.0
    depth_scale: float | None = None  # median over the views of planners.handeye.depth_scale (1: the size is right)

    def record(self, cell_id: str, source: str) -> dict:
        """What the written file holds: the ``hand_eye`` block the config reads and its record."""
        s = self.solution
        xyz, rpy = xyz_rpy_deg(s.T_flange_cam)
        b_xyz, b_rpy = xyz_rpy_deg(s.residual.T_base_board)
        out = {
            "hand_eye": {"xyz": [round(v, 6) for v in xyz], "rpy_deg": [round(v, 5) for v in rpy]},
            "method": s.method,
            "n_views": s.n_views,
            "residual": s.residual.summary(),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "cell_id": cell_id,
            "source": source,
            "board_in_base": {"xyz": [round(v, 5) for v in b_xyz], "rpy_deg": [round(v, 3) for v in b_rpy]},
            "depth_scale": None if self.depth_scale is None else round(self.depth_scale, 5),
            "by_method": s.by_method,
        }
        if self.truth_error is not None:
            out["twin_truth_error"] = {"mm": round(self.truth_error[0], 4), "deg": round(self.truth_error[1], 5)}
        return out


def write_hand_eye_file(path: str | Path, record: dict) -> Path:
    header = ("# T_flange_cam from `cellctl calibrate hand-eye` (camera optical frame in panda_hand; xyz m, fixed-axis\n"
              "# roll/pitch/yaw deg). Point the cell config's hand_eye_file here; the rest is the calibration's record.\n")
    return write_record(path, record, header)


# ----------------------------------------------------------------------------- the pose-visiting loop
def _capture(camera: RGBDCamera, settle_s: float, flush_frames: int) -> RGBDFrame:
    """A frame taken after the arm came to rest: a real camera may hand out frames exposed during the
    move, so the first ``flush_frames`` are dropped."""
    if settle_s > 0:
        time.sleep(settle_s)
    for _ in range(flush_frames):
        camera.capture()
    return camera.capture()


def _motion_planner(arm: Arm, mcfg: MotionConfig, T_base_board: np.ndarray, board: CharucoBoardConfig,
                    park_q: np.ndarray | None) -> tuple[Kinematics, ViewMotionPlanner]:
    """IK, Ruckig and collision checks as for scan views, with the board a static obstacle and the
    roll about the optical axis as asked (calibration needs rotation about every axis)."""
    m = arm.model
    kin = Kinematics.from_arm_model(m)
    checker = None
    if mcfg.check_collisions:
        w, h = board.size_m
        pad = board.margin_m + BOARD_CLEARANCE_M
        plate = 0.01  # the board's print and plate behind it (+z of the board frame)
        local = np.array([[x, y, z] for x in (-pad, w + pad) for y in (-pad, h + pad) for z in (-0.002, plate)])
        pts = local @ T_base_board[:3, :3].T + T_base_board[:3, 3]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        box = StaticBox(name="charuco_board", center_m=tuple((lo + hi) / 2), size_m=tuple(np.maximum(hi - lo, 1e-3)))
        ccfg = mcfg.collision.model_copy(update={"static_boxes": [*mcfg.collision.static_boxes, box]})
        checker = CollisionChecker(RobotCollisionModel.from_arm_model(m, ccfg), ccfg)
    park = mcfg.park_q if mcfg.park_q is not None else park_q
    planner = ViewMotionPlanner(kin, m.max_velocity, m.max_acceleration, m.max_jerk, checker,
                                speed_factor=mcfg.speed_factor, ik_margin_rad=mcfg.ik_margin_rad,
                                ik_seeds=mcfg.ik_seeds, retract_m=mcfg.retract_m, via_candidates=mcfg.via_candidates,
                                budget_s=mcfg.motion_budget_s, free_roll=False,
                                park_q=None if park is None else np.asarray(park, dtype=np.float64))
    return kin, planner


def locate_board(arm: Arm, camera: RGBDCamera, board: CharucoBoardConfig, *, settle_s: float = 0.0,
                 flush_frames: int = 0, dist: np.ndarray | None = None) -> np.ndarray:
    """T_base_board seen from where the arm is now, through the extrinsic the arm carries (good
    enough to aim the views). Raises HandEyeError when the board is not in view."""
    kin = Kinematics.from_arm_model(arm.model)
    frame = _capture(camera, settle_s, flush_frames)
    view = detect_board(frame.color, frame.intrinsics.matrix(), board, dist)
    if view is None:
        raise HandEyeError(f"the ChArUco board ({board.squares_x}x{board.squares_y} squares, {board.dictionary}) "
                           f"is not in view from the start pose: put it in front of the camera, flat and lit, "
                           f"0.3-0.9 m away, and run again")
    return kin.fk(arm.joint_positions(), "cam") @ view.T_cam_board


def calibrate_hand_eye(arm: Arm, camera: RGBDCamera, board: CharucoBoardConfig, mcfg: MotionConfig, *,
                       n_poses: int = DEFAULT_POSES, T_base_board: np.ndarray | None = None, seed: int = 0,
                       park_q: np.ndarray | None = None, methods: list[str] | None = None, settle_s: float = 0.0,
                       flush_frames: int = 0, dist: np.ndarray | None = None,
                       progress: Callable[[str], None] | None = None) -> HandEyeRun:
    """Visit ``n_poses`` views of the board, solve T_flange_cam and measure its residual.

    ``T_base_board``: where to aim (None: located from the start pose). ``settle_s``/``flush_frames``:
    wait and drop frames after each move (a real camera); ``dist``: the colour camera's OpenCV
    distortion coefficients (the twin has none). Views that cannot be
    reached or do not show the board are replaced by spare ones; raises HandEyeError when fewer
    than MIN_VIEWS views show the board, or the first MISSES_BEFORE_ABORT all miss it."""
    if n_poses < MIN_VIEWS:
        raise HandEyeError(f"--poses {n_poses}: hand-eye needs at least {MIN_VIEWS} views (12 or more recommended)")
    t0 = time.perf_counter()
    say = progress or (lambda _msg: None)
    if T_base_board is None:
        T_base_board = locate_board(arm, camera, board, settle_s=settle_s, flush_frames=flush_frames, dist=dist)
        say(f"board located at {np.round(board_center(T_base_board, board), 3).tolist()} m (base frame)")
    T_base_board = np.asarray(T_base_board, dtype=np.float64)
    intr = camera.intrinsics
    K = intr.matrix()
    kin, motion = _motion_planner(arm, mcfg, T_base_board, board, park_q)
    # spares: a view may be out of reach or blocked; the first n are the most diverse
    targets = calibration_views(T_base_board, board, K, (intr.width, intr.height), 2 * n_poses + 4, seed=seed)
    flanges: list[np.ndarray] = []
    views: list[BoardView] = []
    visits: list[dict] = []
    scales: list[float] = []
    for k, T in enumerate(targets):
        if len(views) == n_poses:
            break
        visit: dict = {"target": k, "camera_xyz": np.round(T[:3, 3], 4).tolist()}
        visits.append(visit)
        try:
            mv = motion.plan(arm.joint_positions(), T[None])
            arm.execute(JointTrajectory(mv.path.times, mv.path.positions, mv.path.velocities))
        except Unreachable as e:
            visit.update(reached=False, why=str(e)[:300])
            say(f"view {k}: skipped, unreachable ({str(e)[:120]})")
            continue
        except TrajectoryError as e:
            arm.stop()
            visit.update(reached=False, why=f"motion failed: {e}"[:300])
            say(f"view {k}: skipped, motion failed ({e})")
            continue
        frame = _capture(camera, settle_s, flush_frames)
        q = arm.joint_positions()
        view = detect_board(frame.color, frame.intrinsics.matrix(), board, dist)
        visit.update(reached=True, q=np.round(q, 5).tolist(), via=mv.via)
        if view is None:
            visit.update(corners=0, why="board not found")
            say(f"view {k}: board not found")
            if not views and sum(v.get("reached", False) for v in visits) >= MISSES_BEFORE_ABORT:
                raise HandEyeError(f"the board was not found in the first {MISSES_BEFORE_ABORT} views aimed at "
                                   f"{np.round(board_center(T_base_board, board), 3).tolist()} m: it moved, or it is "
                                   f"not the configured {board.squares_x}x{board.squares_y} {board.dictionary} board")
            continue
        flanges.append(kin.fk(q, "flange"))
        views.append(view)
        scale = depth_scale(view, frame.depth, board)
        if scale is not None:
            scales.append(scale)
        w, h = board.size_m
        visit.update(corners=len(view.ids), reproj_rms_px=round(view.reproj_rms_px, 3),
                     distance_m=round(float(np.linalg.norm(view.T_cam_board @ [w / 2, h / 2, 0, 1] - [0, 0, 0, 1])), 3))
        say(f"view {len(views)}/{n_poses}: {len(view.ids)} corners, {view.markers} markers, "
            f"board {visit['distance_m']:.2f} m away, PnP {view.reproj_rms_px:.2f} px")
    if len(views) < MIN_VIEWS:
        raise HandEyeError(f"the board was found in only {len(views)} of {len(visits)} views "
                           f"({sum(not v['reached'] for v in visits)} unreachable); hand-eye needs at least {MIN_VIEWS}")
    if len(views) < n_poses:
        say(f"only {len(views)} of {n_poses} views usable (all {len(targets)} targets tried)")
    solution = calibrate(np.array(flanges), views, K, board, methods=methods, dist=dist)
    return HandEyeRun(solution=solution, T_base_board_guess=T_base_board, visits=visits,
                      duration_s=time.perf_counter() - t0, depth_scale=float(np.median(scales)) if scales else None)


# ----------------------------------------------------------------------------- the twin
def _empty_scene():
    from sim.scenes.model import Scene

    return Scene(name="hand-eye", category=None, object_mesh=trimesh.Trimesh(), paint_mesh=trimesh.Trimesh(),
                 drawing_polylines=[], drawing_width=0.02, gt_points=np.zeros((0, 3), np.float32),
                 extremities=np.zeros((0, 3)))


def run_hand_eye_in_twin(cfg: CellConfig, *, n_poses: int = DEFAULT_POSES, board: CharucoBoardConfig | None = None,
                         board_xy: tuple[float, float] = TWIN_BOARD_XY, board_yaw_deg: float = TWIN_BOARD_YAW_DEG,
                         seed: int = 0, methods: list[str] | None = None, add_board: bool = True,
                         T_base_board: np.ndarray | None = None,
                         progress: Callable[[str], None] | None = None) -> HandEyeRun:
    """The twin of ``cfg`` with nothing in it but a board lying face up at ``board_xy``; the arm
    starts at home and the board is located from there, as on the real cell. The twin's own
    extrinsic (``cfg.twin.hand_eye``) is the truth the result is compared with. ``add_board``
    False: no board (to see the failure)."""
    from sim.board import add_board as place_board, face_up_pose
    from sim.twin import Twin

    board = board or CharucoBoardConfig()
    with Twin(_empty_scene(), cfg.twin) as twin:
        if add_board:
            place_board(twin.client, face_up_pose(board_xy, yaw_deg=board_yaw_deg, config=board), board)
        twin.arm.reset(cfg.twin.home_q)
        run = calibrate_hand_eye(twin.arm, twin.camera, board, cfg.motion, n_poses=n_poses, seed=seed,
                                 T_base_board=T_base_board, park_q=np.asarray(cfg.twin.home_q), methods=methods,
                                 progress=progress)
        truth = np.asarray(twin.arm.model.T_flange_cam)
    run.T_flange_cam_true = truth
    run.truth_error = pose_error(run.solution.T_flange_cam, truth)
    for r in run.solution.by_method.values():
        if "xyz" in r:
            mm, deg = pose_error(pose_from_xyz_rpy_deg(r["xyz"], r["rpy_deg"]), truth)
            r["truth_error_mm"], r["truth_error_deg"] = round(mm, 4), round(deg, 5)
    return run


def run_hand_eye_on_cell(cfg: CellConfig, *, n_poses: int = DEFAULT_POSES, board: CharucoBoardConfig | None = None,
                         seed: int = 0, methods: list[str] | None = None, settle_s: float = 0.5, flush_frames: int = 3,
                         twin_board: CharucoBoardConfig | None = None, T_base_board: np.ndarray | None = None,
                         progress: Callable[[str], None] | None = None) -> HandEyeRun:
    """Hand-eye on the cell's own arm and camera (``cfg.mode``'s devices, opened as a job opens them): the
    Franka adapter, and the D435 (real) or the twin's renderer posed from the arm's measured joints
    (fcisim, where a board is laid in the twin at TWIN_BOARD_XY and the twin's extrinsic is the truth the
    result is compared with). The rough extrinsic in the config only aims the views; the board is located
    from the arm's start pose. ``board``: the board as the operator describes it; ``twin_board`` (fcisim): the
    one lying in the twin, by default as `cellctl calibrate board` prints it, so a mis-told size shows."""
    mode = MODES[cfg.mode]
    board = board or CharucoBoardConfig()
    twin_cfg = mode.twin_config(cfg, cfg.twin)
    with mode.open(cfg, _empty_scene(), twin_cfg) as dev:
        if dev.twin is not None:
            from sim.board import add_board as place_board, face_up_pose

            laid = twin_board or CharucoBoardConfig()
            place_board(dev.twin.client, face_up_pose(TWIN_BOARD_XY, yaw_deg=TWIN_BOARD_YAW_DEG, config=laid), laid)
        run = calibrate_hand_eye(dev.arm, dev.camera, board, cfg.motion, n_poses=n_poses, seed=seed,
                                 T_base_board=T_base_board, park_q=np.asarray(twin_cfg.home_q), methods=methods,
                                 settle_s=settle_s,
                                 flush_frames=flush_frames, dist=opencv_dist(dev.camera.intrinsics, progress),
                                 progress=progress)
        truth = np.asarray(dev.twin.arm.model.T_flange_cam) if dev.twin is not None else None
    if truth is not None:
        run.T_flange_cam_true = truth
        run.truth_error = pose_error(run.solution.T_flange_cam, truth)
    return run


def opencv_dist(intr, progress: Callable[[str], None] | None = None) -> np.ndarray | None:
    """The camera's distortion as OpenCV's (k1, k2, p1, p2, k3): librealsense's Brown-Conrady has the same
    model and order. Other models have no OpenCV equivalent: the board is then detected as if through a
    pinhole, and said so."""
    if not intr.distorted:
        return None
    if intr.model == "Brown Conrady":
        return np.asarray(intr.coeffs, dtype=np.float64)
    if progress:
        progress(f"the colour stream's {intr.model} distortion {intr.coeffs} has no OpenCV equivalent: the board "
                 f"is detected as through a pinhole")
    return None


@dataclass(frozen=True)
class Acceptance:
    """What a calibration must show before it is written where the cell reads it: the board, seen from every
    view through the solved extrinsic, stays put in the base frame (a wrong extrinsic, a board that moved or
    warped scatter it), its corners reproject, and the depth camera finds it the size it was told (a
    mis-measured printout scales every board pose; hand-eye absorbs part of that into the extrinsic, so the
    residual grows with it only in part, while the depth measures the scale itself)."""

    max_translation_rms_mm: float = 2.0
    max_rotation_rms_deg: float = 0.5
    max_reproj_rms_px: float = 1.0
    max_scale_error: float = 0.01  # the board's size by depth against the size told (a mis-measured printout)

    def problems(self, run: HandEyeRun) -> list[str]:
        r = run.solution.residual
        out = []
        if r.translation_rms_mm > self.max_translation_rms_mm:
            out.append(f"the board moves {r.translation_rms_mm:.2f} mm RMS between views (at most "
                       f"{self.max_translation_rms_mm:g})")
        if r.rotation_rms_deg > self.max_rotation_rms_deg:
            out.append(f"the board turns {r.rotation_rms_deg:.3f} deg RMS between views (at most "
                       f"{self.max_rotation_rms_deg:g})")
        if r.reproj_rms_px > self.max_reproj_rms_px:
            out.append(f"the corners reproject {r.reproj_rms_px:.2f} px RMS off (at most {self.max_reproj_rms_px:g})")
        if run.depth_scale is not None and abs(run.depth_scale - 1) > self.max_scale_error:
            out.append(f"the depth camera measures the board {100 * (run.depth_scale - 1):+.1f} % off the size "
                       f"--square-mm gives (at most {100 * self.max_scale_error:g} %): measure the printed squares")
        return out


def method_spread(run: HandEyeRun) -> tuple[float, float] | None:
    """The largest distance (mm, deg) between the chosen solution and another method's."""
    others = [pose_from_xyz_rpy_deg(m["xyz"], m["rpy_deg"]) for m in run.solution.by_method.values() if "xyz" in m]
    if len(others) < 2:
        return None
    errs = np.array([pose_error(T, run.solution.T_flange_cam) for T in others])
    return float(errs[:, 0].max()), float(errs[:, 1].max())


def cli_hand_eye(args) -> int:
    """`cellctl calibrate hand-eye`: 0 written, 1 calibration failed or refused (the message says why)."""
    from cellctl.config import load_cell_config

    if args.poses < MIN_VIEWS:
        raise ValueError(f"--poses {args.poses}: hand-eye needs at least {MIN_VIEWS} views (12 or more recommended)")
    cfg, cfg_path = load_cell_config(args.config)
    out = Path(args.out) if args.out else cfg_path.parent / "hand_eye.yaml"
    methods = None if args.method == "best" else [args.method]
    board = _board_from_args(args)
    accept = Acceptance(args.max_residual_mm, args.max_residual_deg, args.max_reproj_px,
                        args.max_scale_error_percent / 100)
    say = (lambda msg: print(msg, file=sys.stderr, flush=True)) if not args.quiet else None
    given = pose_from_xyz_rpy_deg(args.board_pose[:3], args.board_pose[3:]) if args.board_pose else None
    try:
        if MODES[cfg.mode].twin_arm:
            run = run_hand_eye_in_twin(cfg, n_poses=args.poses, board=board, seed=args.seed, methods=methods,
                                       T_base_board=given, progress=say)
        else:
            run = run_hand_eye_on_cell(cfg, n_poses=args.poses, board=board, seed=args.seed, methods=methods,
                                       T_base_board=given, progress=say)
    except (HandEyeError, DeviceError) as e:
        print(f"cellctl calibrate hand-eye: {e}", file=sys.stderr)
        return 1
    problems = accept.problems(run)
    if problems:
        _print_result(run, None, cfg_path)
        print(f"cellctl calibrate hand-eye: not written ({out} is unchanged): " + "; ".join(problems)
              + ". Check that the board lies still and flat, that --square-mm/--marker-mm are what the printout "
                "measures, and run again.", file=sys.stderr)
        return 1
    old = backup(out)
    write_hand_eye_file(out, run.record(cfg.cell_id, source="twin" if MODES[cfg.mode].twin_arm else cfg.mode))
    _print_result(run, out, cfg_path, old)
    if not MODES[cfg.mode].twin_arm:  # a real cell's config reads its calibration; the twin's demo config is left
        print(f"  config         {point_config_at(cfg_path, out, 'hand_eye_file', 'calibrate hand-eye')}")
    return 0


def _board_from_args(args) -> CharucoBoardConfig:
    """The board as printed: ``--square-mm``/``--marker-mm`` are what the printout measures."""
    return CharucoBoardConfig(square_m=args.square_mm / 1000.0, marker_m=args.marker_mm / 1000.0)


def write_board_image(path: str | Path, board: CharucoBoardConfig, dpi: int = 300) -> tuple[Path, int]:
    """The printable board as a PNG whose DPI tag makes "actual size" printing come out at exactly
    ``square_m`` per square (the tag is the whole pixels per square over the square's inches, about
    ``dpi``). Returns the path and the pixels per square."""
    from PIL import Image

    px = int(round(board.square_m / 0.0254 * dpi))
    exact = px * 0.0254 / board.square_m
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(board.image(px_per_square=px)).save(path, dpi=(exact, exact))
    return path, px


def cli_board(args) -> int:
    """`cellctl calibrate board`: write the board to print."""
    board = _board_from_args(args)
    path, px = write_board_image(args.out, board, args.dpi)
    w, h = board.size_m
    m = board.margin_px(px) * board.square_m / px
    size = sorted((1000 * (w + 2 * m), 1000 * (h + 2 * m)), reverse=True)
    paper = "A4" if size[0] <= 297 and size[1] <= 210 else "A3" if size[0] <= 420 and size[1] <= 297 else "a sheet"
    print(f"{path}: {board.squares_x}x{board.squares_y} squares of {1000 * board.square_m:g} mm, "
          f"{1000 * board.marker_m:g} mm {board.dictionary} markers; print at 100 % (actual size) on {paper} or "
          f"larger: {size[0]:.0f} x {size[1]:.0f} mm. Measure a square; if it is not "
          f"{1000 * board.square_m:g} mm, pass what you measure as --square-mm (and --marker-mm) to hand-eye.")
    return 0


def _print_result(run: HandEyeRun, out: Path | None, cfg_path: Path, old: Path | None = None) -> None:
    s = run.solution
    r = s.residual
    xyz, rpy = xyz_rpy_deg(s.T_flange_cam)
    rows = [("T_flange_cam", f"xyz {np.round(xyz, 5).tolist()} m, rpy {np.round(rpy, 3).tolist()} deg"),
            ("method", f"{s.method} (lowest reprojection RMS of {len(s.by_method)} tried)"),
            ("views", f"{s.n_views} with the board, {len(run.visits)} poses tried"),
            ("residual", f"board in base: {r.translation_rms_mm:.2f} mm RMS (max {r.translation_max_mm:.2f}), "
                         f"{r.rotation_rms_deg:.3f} deg RMS (max {r.rotation_max_deg:.3f}); "
                         f"reprojection {r.reproj_rms_px:.2f} px RMS (max {r.reproj_max_px:.2f})")]
    if run.depth_scale is not None:
        rows.append(("board size", f"by depth {100 * (run.depth_scale - 1):+.2f} % off the size told"))
    spread = method_spread(run)
    if spread is not None:
        rows.append(("method spread", f"the methods agree within {spread[0]:.2f} mm, {spread[1]:.3f} deg"))
    if run.truth_error is not None:
        rows.append(("twin truth", f"error {run.truth_error[0]:.2f} mm, {run.truth_error[1]:.3f} deg"))
    if out is not None:
        rel = os.path.relpath(out.resolve(), cfg_path.parent.resolve())
        rows.append(("written", f"{out}  (the config reads it with hand_eye_file: "
                                f"{out.resolve() if rel.startswith('..') else rel} in {cfg_path.name})"))
    if old is not None:
        rows.append(("previous", f"kept as {old}"))
    for name, m in s.by_method.items():
        if "xyz" in m:
            extra = (f", truth {m['truth_error_mm']:.2f} mm / {m['truth_error_deg']:.3f} deg"
                     if "truth_error_mm" in m else "")
            rows.append((f"  {name}", f"{m['translation_rms_mm']:.2f} mm, {m['rotation_rms_deg']:.3f} deg, "
                                      f"{m['reproj_rms_px']:.2f} px{extra}"))
        else:
            rows.append((f"  {name}", m["error"]))
    w = max(len(k) for k, _ in rows)
    print()
    for k, v in rows:
        print(f"  {k:<{w}}  {v}")
