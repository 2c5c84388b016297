"""The `initial_view` job profile (``service.job_profile``): a real but cheap job for load tests.

A full scan costs seconds (twin, motion planning, next-view planning, cut, plots), so 200 of them
cannot run in a CI test. This job keeps the parts of a scan that touch the world: it builds the twin
of the requested scene, renders the D435 frame of the scene's first initial view, turns it into the
base-frame cloud and the painted-line cloud exactly as a scan's first step does, scores coverage
against ground truth and writes result.json and drawing.ply into the job folder. It skips motion,
next-view planning, the cut and the plots. About 0.45 s on one free core at 640x480."""

from __future__ import annotations

import time
from pathlib import Path

from cellctl.scan.artifacts import write_ply
from cellctl.scan.result import ScanResult, StepRecord
from cellctl.scan.run import prepare, write_result
from cellctl.scan.spec import Hooks, JobSpec
from cellctl.scan.job import ScanError
from planners import clouds
from planners.paint_color import PaintSegmenter
from planners.metrics import coverage


def run_initial_view(spec: JobSpec, hooks: Hooks) -> tuple[ScanResult, Path]:
    """One view of ``spec.scene`` from its first initial-view pose (the arm is not moved), set up and
    recorded as every job is (cellctl.scan.run.prepare, write_result). The result has steps=1 and
    terminated_by="initial_view"; result.json is written whatever happens."""
    from sim.twin import Twin

    setup = prepare(spec)
    pcfg, scene, twin_cfg, run_dir = setup.pcfg, setup.scene, setup.twin_cfg, setup.run_dir
    result = ScanResult(scene=scene.name, planner=spec.planner)
    try:
        if hooks.cancel is not None and hooks.cancel.is_set():
            result.terminated_by = hooks.stop_label()
            return result, run_dir
        if len(scene.initial_view_candidates) == 0:
            raise ValueError(f"scene {scene.name} has no initial view")
        T = scene.initial_view_candidates[0]
        with Twin(scene, twin_cfg) as twin:
            twin.arm.reset(twin_cfg.home_q)
            t0 = time.perf_counter()
            frame = twin.camera.capture_at(T)
            K = twin.camera.intrinsics.matrix()
        t1 = time.perf_counter()
        g = pcfg.grid
        cloud = clouds.frame_to_base_cloud(frame.color, frame.depth, K, T, lens=frame.intrinsics.lens)
        surface = clouds.voxel_dedup(cloud, g.surface_voxel_m)
        seg = PaintSegmenter(pcfg.paint)  # as a scan's first step: fitted to the piece, checked
        result.paint = seg.fit_view(surface.rgb, surface.xyz, g.lo_m[2], workspace=(g.lo_m, g.hi_m))
        if not result.paint.ok:
            result.terminated_by = "paint_not_separable"
            raise ScanError(f"paint_not_separable: {result.paint.reason}", "paint_not_separable")
        paint = seg.paint_points(surface.rgb, surface.xyz)
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
        if hooks.on_step:
            hooks.on_step(rec)
    except Exception as e:
        result.error = result.error or f"{type(e).__name__}: {e}"
        result.terminated_by = result.terminated_by or "error"
        raise
    finally:
        write_result(run_dir, spec, result)
    return result, run_dir
