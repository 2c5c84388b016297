"""The cut oracle: the cell's own cut planner given the truth, to say what this arm, this torch and
these tolerances can cut of a piece at all.

The cell plans from what it scanned: a noisy paint cloud, a partial surface, unseen space counted as
solid. The oracle hands the same planner (``planners.cutpath.plan_cut_path``, the same config and
collision model of arm and torch) the true paint (the twin's ground-truth samples), the whole true
surface (sampled every ``SURFACE_STEP_M``, normals from the mesh) and the true piece as the collision
scene (its surface cells at the scan grid's pitch). What the oracle cannot cut is physics (reach,
joint limits, the torch against the piece); what the cell cuts less than the oracle is the planner's
and the scan's weakness. Measured the same way as the cell's cut (``cellctl.scan.cut.true_accuracy``)."""

from __future__ import annotations

import time

import numpy as np
import trimesh

from cellctl.scan.cut import torch_shape, true_accuracy, what_blocks
from planners.clouds import Cloud
from planners.config import PlannersConfig
from planners.cutpath import plan_cut_path, torch_kinematics
from planners.motion.collision import FLOOR_Z_M, CollisionChecker, CollisionConfig, RobotCollisionModel

SURFACE_STEP_M = 0.002  # the true surface's samples: as fine as the scan's de-duplicated cloud
SENSOR_OFF_M = 0.3  # each true surface sample is "seen" from this far out along its normal


def true_surface(mesh: trimesh.Trimesh, step_m: float = SURFACE_STEP_M) -> Cloud:
    """The whole true surface as a cloud, about one point per ``step_m`` cell, each with a sensor
    position in front of it (so the planner orients its normals outward, as it does for a scan)."""
    n = max(20_000, int(4.0 * mesh.area / step_m**2))
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=0)
    _, first = np.unique(np.floor(pts / step_m).astype(np.int64), axis=0, return_index=True)
    pts, face = pts[first], face[first]
    origin = pts + SENSOR_OFF_M * mesh.face_normals[face]
    return Cloud(pts.astype(np.float32), np.zeros((len(pts), 3), np.uint8), origin.astype(np.float32))


def oracle_cut(scene, arm_model, q_start: np.ndarray, ccfg: CollisionConfig, pcfg: PlannersConfig,
               park_q: np.ndarray | None = None) -> dict:
    """The cut the planner makes from the truth of ``scene``: accuracy against the true line (as the
    cell's cut is measured), the share it says it cuts, the gaps by reason and the planning time."""
    cut = pcfg.cutpath
    m = arm_model
    kin = torch_kinematics(m.urdf_path, cut, joint_names=m.joint_names, flange_link=m.flange_link,
                           lower=m.lower, upper=m.upper)
    cfg = ccfg.model_copy(update={"margin_m": cut.cut_margin_m})
    checker = CollisionChecker(RobotCollisionModel.from_arm_model(m, cfg, torch=torch_shape(cut, nozzle=False)), cfg)
    mesh = scene.full_mesh
    surface = true_surface(mesh)
    v = pcfg.grid.voxel_m
    checker.set_scene(np.unique(np.floor(surface.xyz / v).astype(np.int64), axis=0) * v + v / 2, v)
    paint = Cloud(scene.gt_points.astype(np.float32), np.zeros((len(scene.gt_points), 3), np.uint8))
    viewpoint = scene.initial_view_candidates[0][:3, 3] if len(scene.initial_view_candidates) else None
    t0 = time.perf_counter()
    path = plan_cut_path(paint, surface, kin, np.asarray(q_start, dtype=np.float64), cut, viewpoint=viewpoint,
                         is_free=checker.free, explain=what_blocks(checker), max_vel=m.max_velocity, max_acc=m.max_acceleration,
                         max_jerk=m.max_jerk, park_q=park_q, floor_z=FLOOR_Z_M)
    planning = time.perf_counter() - t0
    gaps: dict[str, float] = {}
    for g in path.gaps:
        if g.length_m > 0:
            gaps[g.reason] = round(gaps.get(g.reason, 0.0) + g.length_m, 4)
    acc = true_accuracy(path, kin, cut, scene.drawing_polylines, scene.gt_points, mesh)
    return {"cut_coverage": acc["cut_coverage"], "accuracy": acc, "fraction": round(path.cut_fraction, 4),
            "cuts": sum(b.feasible for b in path.branches), "uncut_m_by_reason": gaps,
            "planning_s": round(planning, 3)}
