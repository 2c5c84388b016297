"""The end of a scan job: the reconstructed drawing becomes a cutting path for the torch, checked
against what was scanned, and (on request) run in the twin to see how well the tip follows it."""

from __future__ import annotations

import time
import numpy as np
from scipy.spatial import cKDTree

from cellctl.scan.result import CutSummary, DryRun, GapRecord, PaintCheck, UncutPaintSummary, UnseenPaintSummary
from drivers.interfaces import Arm, ArmAbilities, JointTrajectory
from planners.clouds import Cloud
from planners.config import CutPathConfig
from planners.cutpath import CutPath, Surface, plan_cut_path, torch_kinematics
from planners.cutpath.paint_report import cut_against_paint, flame_path
from planners.grid import OccupancyGrid
from planners.motion.collision import FLOOR_Z_M, CollisionChecker, CollisionConfig, RobotCollisionModel, TorchShape
from planners.motion.kinematics import Kinematics
from planners.open_edges import unseen_paint
from sim.config import TwinToolConfig


def twin_torch(cut: CutPathConfig) -> TwinToolConfig:
    """The torch as the twin's tool: the dry run then sees the torch's own contacts, not only the arm's."""
    t = cut.torch
    return TwinToolConfig(xyz=list(t.xyz_m), rpy_deg=list(t.rpy_deg), radius_m=t.radius_m, length_m=t.length_m,
                          nozzle_radius_m=t.nozzle_radius_m, nozzle_length_m=t.nozzle_length_m)


def torch_shape(cut: CutPathConfig, *, nozzle: bool = True) -> TorchShape:
    """The torch as a cylinder on the flange for the collision model: its whole length (the scan's
    moves keep it clear like any link), or without its working end (the cut's check, see torch_checker)."""
    t = cut.torch
    return TorchShape(t.radius_m, t.length_m - (0.0 if nozzle else t.fine_length_m), t.T_flange_mount())


def torch_checker(arm_model, ccfg: CollisionConfig, cut: CutPathConfig,
                  grid: OccupancyGrid) -> tuple[CollisionChecker, np.ndarray]:
    """Arm + camera + torch against the scan, with the cut's own (small) margin, and the centres of
    the unseen cells it counts as solid. The torch's working end (``torch.fine_length_m`` from the
    tip) is left to the cut planner's finer check against the surface cloud and those cells
    (planners.cutpath.nozzle): it works ``standoff_m`` off the metal, closer than a cell."""
    cfg = ccfg.model_copy(update={"margin_m": cut.cut_margin_m})
    checker = CollisionChecker(RobotCollisionModel.from_arm_model(arm_model, cfg, torch=torch_shape(cut, nozzle=False)),
                               cfg)
    return checker, checker.set_scene_from_grid(grid)


def what_blocks(checker: CollisionChecker, piece: str = "the piece"):
    """``explain`` for the cut planner: what each configuration (M,dof) hits, in the operator's words."""
    def label(c) -> str | None:
        if c is None:
            return None
        who = "the camera" if c.part == "camera" else "the torch" if c.part == "torch" else "the arm"
        if c.kind == "floor":
            return f"{who} against the floor or table"
        if c.kind == "static":
            return f"{who} against {c.other}"
        if c.kind == "scene":
            return f"{who} against {piece}"
        return "the arm against itself" if c.other not in ("camera", "torch") else f"the arm against {c.other}"

    return lambda Q: [label(checker.check(q)) for q in np.asarray(Q).reshape(-1, checker.robot.kin.dof)]


def plan_cut(arm: Arm, ccfg: CollisionConfig, cut: CutPathConfig, grid: OccupancyGrid, drawing: Cloud,
             surface: Cloud, viewpoint: np.ndarray,
             park_q: np.ndarray | None = None, cloud_voxel_m: float = 0.002,
             open_edge_radius_m: float = 0.005) -> tuple[CutPath | None, CutSummary, Kinematics]:
    """Cut path from the scan, checked against the paint it saw (``check_against_paint``; the clouds are
    deduplicated at ``cloud_voxel_m``); a drawing that gives no path is reported, not raised."""
    m = arm.model
    t0 = time.perf_counter()
    kin = torch_kinematics(m.urdf_path, cut, joint_names=m.joint_names, flange_link=m.flange_link,
                           lower=m.lower, upper=m.upper)
    summary = CutSummary()
    try:
        checker, unseen = torch_checker(m, ccfg, cut, grid)
        path = plan_cut_path(drawing, surface, kin, arm.joint_positions(), cut, viewpoint=viewpoint,
                             is_free=checker.free, unseen=unseen, cell_m=grid.voxel,
                             explain=what_blocks(checker, "the scanned piece (or space not seen yet)"), max_vel=m.max_velocity,
                             max_acc=m.max_acceleration, max_jerk=m.max_jerk, park_q=park_q, floor_z=FLOOR_Z_M)
    except ValueError as e:
        summary.error = str(e)
        summary.planning_s = time.perf_counter() - t0
        return None, summary, kin
    summary.planning_s = time.perf_counter() - t0
    summary.branches = len(path.branches)
    summary.feasible_branches = sum(b.feasible for b in path.branches)
    summary.poses = sum(len(b) for b in path.branches)
    reasons = [f for b in path.branches for f in b.feasibility]
    summary.feasible_poses = sum(f == "ok" for f in reasons)
    summary.infeasible = {r: reasons.count(r) for r in sorted(set(reasons)) if r != "ok"}
    summary.length_m = round(float(path.length_m), 4)
    summary.warnings = list(path.notes) + [f"cut {i}: {msg}" for i, b in enumerate(path.branches) for msg in b.issues]
    summary.cut_fraction = round(float(path.cut_fraction), 4)
    summary.cut_lengths_m = [round(b.length_m, 4) for b in path.branches if b.feasible]
    summary.drawing_length_m = round(float(path.drawing_length_m or 0.0), 4)
    summary.gaps = [GapRecord.model_validate(g.to_json_dict()) for g in path.gaps]
    if not path.branches:
        summary.warnings.append("nothing on the drawing can be cut: " + (
            "; ".join(sorted({f"{g.reason}: {g.detail}" for g in summary.gaps})) or "no drawing branch"))
    check_against_paint(summary, path, kin, cut, drawing, surface, viewpoint, cloud_voxel_m)
    note_unseen_paint(summary, drawing, surface, open_edge_radius_m, grid.voxel)
    return path, summary, kin


def note_unseen_paint(summary: CutSummary, drawing: Cloud, surface: Cloud, radius_m: float, voxel_m: float) -> None:
    """``summary.paint.unseen``: where the paint the scan saw runs into surface it never measured
    (planners.open_edges.unseen_paint), and a warning: the share of the paint seen is then a share of
    less than the whole line, and the cell cannot say how much less."""
    if summary.paint is None or len(drawing) == 0 or len(surface) == 0:
        return
    found = unseen_paint(drawing.xyz, drawing.origin, surface.xyz, radius_m, voxel_m)
    summary.paint.unseen = [UnseenPaintSummary(centre=[round(float(v), 4) for v in u.centre],
                                               border_m=round(u.border_m, 4), wall_m=round(u.wall_m, 4))
                            for u in found[:100]]
    if found:
        top = found[0]
        summary.warnings.append(
            f"the paint runs on past what the scan measured at {len(found)} border{'s' if len(found) > 1 else ''} "
            f"({1e3 * sum(u.border_m for u in found):.0f} mm in all, the longest near "
            f"{', '.join(f'{v:.3f}' for v in top.centre)} m{', at the foot of a wall' if top.wall_m > 0 else ''}): "
            f"the line may go on there unseen, and the {100 * summary.told_share:.0f} % is of the paint seen; "
            "look at the piece there")


def check_against_paint(summary: CutSummary, path: CutPath, kin: Kinematics, cut: CutPathConfig, drawing: Cloud,
                        surface: Cloud, viewpoint: np.ndarray | None, cloud_voxel_m: float) -> None:
    """``summary.paint``: the planned flame path against the paint the scan saw, and a warning wherever
    it and the cut's own figures disagree, the flame leaves the paint or paint is left uncut."""
    if len(drawing) == 0:
        return
    surf = Surface(surface.xyz if len(surface) else drawing.xyz, surface.origin if len(surface) else drawing.origin,
                   viewpoint, cut.normal_radius_m)
    rep = cut_against_paint(path, kin, drawing.xyz, surf, cut, cloud_voxel_m)
    summary.paint = PaintCheck(
        line_share=None if rep.line_share is None else round(min(max(rep.line_share, 0.0), 1.0), 4),
        line_on_paint_m=round(rep.line_on_paint_m, 4),
        cut_share=round(min(max(rep.cut_share, 0.0), 1.0), 4), line_length_m=round(rep.line_length_m, 4),
        spray_width_mm=round(2e3 * rep.half_width_m, 1), uncut=[UncutPaintSummary(**u.to_json_dict()) for u in rep.uncut],
        flame_off_paint_max_mm=rep.flame_off_paint_max_mm, flame_off_paint_m=rep.flame_off_paint_m,
        flame_off_centre_max_mm=rep.flame_off_centre_max_mm, flame_off_centre_m=rep.flame_off_centre_m,
        tip_to_surface_min_mm=rep.tip_to_surface_min_mm, tip_to_surface_max_mm=rep.tip_to_surface_max_mm)
    told, area = summary.told_share, summary.paint.cut_share
    if abs(told - area) > cut.share_disagreement:
        summary.warnings.append(f"the line on the paint is {100 * told:.0f} % cut, but the flame passes over "
                                f"{100 * area:.0f} % of the painted area the scan saw: the two checks disagree, "
                                "look at the cut against the paint")
    if rep.flame_off_paint_m > 0:
        summary.warnings.append(f"the lit flame leaves the paint for {1e3 * rep.flame_off_paint_m:.0f} mm (up to "
                                f"{rep.flame_off_paint_max_mm:.0f} mm off it): it would cut unmarked metal")
    if rep.flame_off_centre_m > 0:
        summary.warnings.append(f"the lit flame runs beside the paint's centre for {1e3 * rep.flame_off_centre_m:.0f} mm "
                                f"(up to {rep.flame_off_centre_max_mm:.0f} mm off it, inside the paint): the cut "
                                "there is off the line")
    missed = [u for u in rep.uncut if u.reason == "not followed"]
    if missed:
        summary.warnings.append(f"{1e3 * sum(u.length_m for u in missed):.0f} mm of paint lies off every cut's line "
                                f"({len(missed)} piece{'s' if len(missed) > 1 else ''}, the largest near "
                                f"{', '.join(f'{v:.3f}' for v in missed[0].centre)} m)")


def true_accuracy(path: CutPath, kin: Kinematics, cut: CutPathConfig, polylines: list[np.ndarray],
                  painted: np.ndarray, metal=None) -> dict:
    """The cut against the twin's truth: the flame spot at every lit sample of the planned motion against
    the true centerline (``planners.metrics.cut_accuracy``), the poses alone beside it, and the tip's
    distance from the true surface (``metal``: a trimesh of the piece)."""
    from planners.cutpath.paint_report import lit_flames
    from planners.metrics import cut_accuracy

    flames = lit_flames(path, kin, cut.standoff_m)
    acc = cut_accuracy(polylines, [f.spots for f in flames], painted=painted)
    poses = cut_accuracy(polylines, [b.points for b in path.branches if b.feasible], painted=painted)
    acc["pose_to_line_max_mm"] = poses["path_to_line_max_mm"]
    if metal is not None and flames:
        from sim.scenes.paint import distance_to_mesh

        d = distance_to_mesh(metal, np.vstack([f.tips for f in flames]))
        acc["tip_to_metal_min_mm"], acc["tip_to_metal_max_mm"] = round(1e3 * float(d.min()), 2), round(1e3 * float(d.max()), 2)
    return acc


def clearing_targets(path: CutPath | None, most: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Where a view could open the torch's way: the longest stretches left uncut for a collision
    (the scan may not have seen the space in front of them, which then counts as solid), as
    (middle point, outward normal), longest first."""
    if path is None or most <= 0:
        return []
    gaps = sorted((g for g in path.gaps if g.reason == "collision" and g.length_m > 0 and g.normal is not None),
                  key=lambda g: -g.length_m)
    return [(g.points[len(g.points) // 2].copy(), g.normal.copy()) for g in gaps[:most]]


def write_trajectory(path: CutPath, file) -> None:
    """The joint motion of every feasible branch (approach, cut, retract: times and positions)."""
    arrays = {}
    for i, b in enumerate(path.branches):
        for phase in ("approach", "cut", "retract"):
            jp = getattr(b, phase)
            if b.feasible and jp is not None:
                arrays[f"branch{i}_{phase}_t"] = jp.times
                arrays[f"branch{i}_{phase}_q"] = jp.positions
    np.savez_compressed(file, **arrays)


def dry_run_cut(arm: Arm, kin: Kinematics, path: CutPath, abilities: ArmAbilities | None = None, *,
                paint: np.ndarray | None = None, standoff_m: float = 0.0,
                line: list[np.ndarray] | None = None) -> DryRun:
    """Run every feasible branch (approach, cut, retract) on the arm, torch off, and measure the
    torch tip against the plan: at the same instant, and as distance from the planned path; and the
    flame spot (``standoff_m`` ahead of the tip) of the executed cut against the ``paint`` the scan
    saw and, in the twin, the true centerline ``line``. The contacts come from a ``ContactLog`` arm,
    the tip's tracking from a ``MotionLog`` arm (``abilities``: the arm's, as checked where it was
    wired; default: checked now)."""
    abilities = abilities if abilities is not None else ArmAbilities.of(arm)
    contact_log, motion_log = abilities.contacts, abilities.motion_log
    planned_tip, errors_t, errors_path, contacts, moved, spots = [], [], [], [], 0, []
    for i, b in enumerate(path.branches):
        if not b.feasible:
            continue
        for phase in ("approach", "cut", "retract"):
            jp = getattr(b, phase)
            jq = jp.positions
            q_now = arm.joint_positions()
            if np.max(np.abs(jq[0] - q_now)) > 1e-3:  # the arm settled a hair away from the plan's start
                jq = np.vstack([q_now, jq[1:]])
            arm.execute(JointTrajectory(jp.times, jq, jp.velocities))
            moved += 1
            if contact_log is not None:
                contacts += [{**c, "cut": i, "phase": phase} for c in contact_log.last_motion_contacts]
            if phase != "cut" or motion_log is None:
                continue
            desired, actual = motion_log.last_motion_desired, motion_log.last_motion_actual
            if len(actual) == 0:
                continue
            ok = np.all(np.isfinite(actual), axis=1)
            tip_des = kin.fk_positions(desired[ok])
            tip_act = kin.fk_positions(actual[ok])
            errors_t.append(np.linalg.norm(tip_act - tip_des, axis=1))
            dense = kin.fk_positions(jp.positions)
            d, _ = cKDTree(dense).query(tip_act)
            errors_path.append(d)
            planned_tip.append(dense)
            spots.append(flame_path(kin, actual[ok], standoff_m).spots)
    run = DryRun(motions=moved, contacts=len(contacts), contact_log=contacts)
    if spots and paint is not None and len(paint):
        run.flame_off_paint_max_mm = round(1e3 * float(cKDTree(paint).query(np.vstack(spots))[0].max()), 2)
    if spots and line:
        from planners.metrics import dense_polylines

        run.flame_to_line_max_mm = round(1e3 * float(cKDTree(dense_polylines(line, 0.001)).query(np.vstack(spots))[0].max()), 2)
    if errors_t:
        e_t, e_p = np.concatenate(errors_t), np.concatenate(errors_path)
        run.tip_error_max_mm, run.tip_error_median_mm = round(1e3 * e_t.max(), 3), round(1e3 * np.median(e_t), 3)
        run.path_error_max_mm, run.path_error_median_mm = round(1e3 * e_p.max(), 3), round(1e3 * np.median(e_p), 3)
    return run
