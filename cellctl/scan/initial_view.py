"""The `initial_view` job profile (``service.job_profile``): a real but cheap job for load tests.

A full scan costs seconds (twin, motion planning, next-view planning, cut, plots), so 200 of them
cannot run in a CI test. This job keeps the parts of a scan that touch the world: it builds the twin
of the requested scene, renders the D435 frame of the scene's first initial view, turns it into the
base-frame cloud and the painted-line cloud exactly as a scan's first step does, scores coverage
against ground truth and writes result.json and drawing.ply into the job folder. It skips motion,
next-view planning, the cut and the plots. About 0.3 s on one free core at 640x480."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Callable

from cellctl.config import CellConfig
from cellctl.scan.artifacts import write_ply
from cellctl.scan.result import ScanResult, StepRecord
from cellctl.scan.run import prepare, write_result
from planners import clouds
from planners.metrics import coverage


def run_initial_view(cfg: CellConfig, cfg_path: Path, scene_ref: str, planner: str, *, seed: int | None = None,
                     noise: bool = True, run_dir: Path, cancel: threading.Event | None = None,
                     on_step: Callable[[StepRecord], None] | None = None) -> ScanResult:
    """One view of ``scene_ref`` from its first initial-view pose (the arm is not moved), set up and
    recorded as every job is (cellctl.scan.run.prepare, write_result). The result has steps=1 and
    terminated_by="initial_view"; result.json is written whatever happens."""
    from sim.twin import Twin

    setup = prepare(cfg, cfg_path, scene_ref, planner, seed=seed, noise=noise, run_dir=run_dir)
    pcfg, scene, twin_cfg = setup.pcfg, setup.scene, setup.twin_cfg
    result = ScanResult(scene=scene.name, planner=planner)
    try:
        if cancel is not None and cancel.is_set():
            result.terminated_by = "cancelled"
            return result
        if len(scene.initial_view_candidates) == 0:
            raise ValueError(f"scene {scene.name} has no initial view")
        T = scene.initial_view_candidates[0]
        with Twin(scene, twin_cfg) as twin:
            twin.arm.reset(twin_cfg.home_q)
            t0 = time.perf_counter()
            frame = twin.camera.capture_at(T)
            K = twin.camera.intrinsics.matrix()
        t1 = time.perf_counter()
        g, c = pcfg.grid, pcfg.color
        cloud = clouds.frame_to_base_cloud(frame.color, frame.depth, K, T)
        surface = clouds.voxel_dedup(cloud, g.surface_voxel_m)
        paint = clouds.color_mask(surface.rgb, c.hue_center_deg, c.hue_halfwidth_deg, c.s_min, c.v_min)
        drawing = surface.select(paint)
        cov = coverage(drawing.xyz, scene.gt_points, pcfg.coverage_voxel_m)
        t2 = time.perf_counter()
        rec = StepRecord(step=0, camera_position=T[:3, 3].round(4).tolist(), points=len(surface),
                         drawing_points=len(drawing), planning_s=t2 - t1, capture_s=t1 - t0, process_s=t2 - t1,
                         coverage_percent=round(cov.percent, 2))
        result.records.append(rec)
        result.viewpoints.append(rec.camera_position)
        result.steps, result.capture_s, result.planning_s = 1, rec.capture_s, rec.planning_s
        result.coverage_hit, result.coverage_total, result.coverage_percent = cov.hit, cov.total, round(cov.percent, 2)
        result.terminated_by = "initial_view"
        write_ply(run_dir / "drawing.ply", drawing)
        if on_step:
            on_step(rec)
    except Exception as e:
        result.error = result.error or f"{type(e).__name__}: {e}"
        result.terminated_by = result.terminated_by or "error"
        raise
    finally:
        write_result(run_dir, cfg, scene_ref, result, "initial_view")
    return result
