"""A scan job from the command line or the service: open the cell's devices (cellctl.scan.devices: the twin in
mode sim, franky-sim + the twin's renderer in fcisim, the Franka + D435 in real), run the job, write the
run folder."""

from __future__ import annotations

from contextlib import contextmanager

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellctl.config import CellConfig, cell_planners_config
from cellctl.scan.artifacts import new_run_dir, paint_overlay, save_png, write_json, write_ply
from cellctl.scan.cut import clearing_targets, dry_run_cut, plan_cut, true_accuracy, twin_torch, write_trajectory
from cellctl.scan.devices import open_devices
from cellctl.scan.job import ScanJob
from cellctl.scan.plots import coverage_figure, cut_figure
from cellctl.scan.recording import ScanRecorder
from cellctl.scan.result import ResultFile, ScanResult, StepRecord
from cellctl.scan.spec import Hooks, JobSpec
from drivers.interfaces import Arm
from planners.config import PlannersConfig
from sim.config import TwinConfig
from sim.scenes import Scene, load_scene


def _cut_phase(job: ScanJob, pcfg, cfg: CellConfig, arm: Arm, run_dir: Path, recorder: ScanRecorder,
               result: ScanResult, dry_run: bool, progress: bool, truth: tuple | None = None) -> None:
    """planning-cut: the drawing becomes cut_path.json/.csv and cut_trajectory.npz; optionally the
    arm runs it (torch off) and the tip's tracking is measured. ``truth``: (the painted line's true
    centerline polylines, samples of the painted surface, the piece's mesh) of the twin's scene, to
    measure the cuts."""
    viewpoint = np.array(result.viewpoints[0]) if result.viewpoints else None
    job.for_the_cut(result, "the move to park", lambda: job.go_park(result))  # the cut starts clear above the cell
    voxel = pcfg.grid.surface_voxel_m
    path, summary, kin = plan_cut(arm, cfg.motion.collision, pcfg.cutpath, job.grid, job.drawing, job.surface,
                                  viewpoint, park_q=job.motion.park_q, cloud_voxel_m=voxel,
                                  open_edge_radius_m=pcfg.nbv.open_edge_radius_m)
    targets = clearing_targets(path, pcfg.cutpath.max_clearing_views)
    if targets and not job.cancelled():  # the torch's way is unseen: look, then plan again
        views = job.for_the_cut(result, "the views of the torch's way", lambda: job.look_along(targets, result)) or 0
        job.for_the_cut(result, "the move to park", lambda: job.go_park(result))
        if views:
            path, summary, kin = plan_cut(arm, cfg.motion.collision, pcfg.cutpath, job.grid, job.drawing,
                                          job.surface, viewpoint, park_q=job.motion.park_q, cloud_voxel_m=voxel,
                                          open_edge_radius_m=pcfg.nbv.open_edge_radius_m)
        summary.clearing_views = views
    if path is not None:
        path.write(run_dir)
        write_trajectory(path, run_dir / "cut_trajectory.npz")
        recorder.log_cut(len(result.records), path)
        _cut_picture(run_dir, job, path, summary, truth)
        if dry_run:
            summary.dry_run = dry_run_cut(arm, kin, path, job.abilities, paint=job.drawing.xyz,
                                          standoff_m=pcfg.cutpath.standoff_m, line=truth[0] if truth else None)
        if truth:
            summary.accuracy = true_accuracy(path, kin, pcfg.cutpath, truth[0], truth[1], truth[2])
    result.cut = summary
    if progress:
        print(f"cut path: {100 * summary.cut_fraction:.1f} % of the {summary.drawing_length_m:.3f} m drawing "
              f"will be cut, {summary.feasible_branches} cuts ({summary.branches - summary.feasible_branches} "
              f"not runnable), planned in {summary.planning_s:.2f} s"
              + (f" after {summary.clearing_views} more view(s) of the torch's way" if summary.clearing_views else "")
              + (f" ({summary.error})" if summary.error else ""),
              file=sys.stderr, flush=True)
        for g in summary.gaps:
            if g.length_m > 0:
                print(f"  uncut {1000 * g.length_m:.0f} mm of branch {g.branch}: {g.reason}: {g.detail}",
                      file=sys.stderr, flush=True)
        for msg in summary.warnings:
            print(f"  warning: {msg}", file=sys.stderr, flush=True)
        if summary.paint:
            p = summary.paint
            print(f"  against the paint: {100 * summary.told_share:.1f} % of the {1000 * summary.told_length_m:.0f} mm "
                  f"line on the paint cut, the flame over {100 * p.cut_share:.1f} % of the painted area "
                  f"({p.spray_width_mm:.0f} mm wide), at most "
                  f"{p.flame_off_paint_max_mm} mm off it, {p.flame_off_centre_max_mm} mm off its centre",
                  file=sys.stderr, flush=True)
        if summary.accuracy:
            a = summary.accuracy
            print(f"  against the true line: {100 * a.cut_coverage:.1f} % within 5 mm of a cut; flame to line mean "
                  f"{a.path_to_line_mean_mm} mm, max {a.path_to_line_max_mm} mm over the whole lit motion "
                  f"({a.pose_to_line_max_mm} mm at the poses); tip {a.tip_to_metal_min_mm}-{a.tip_to_metal_max_mm} mm "
                  f"off the metal; {a.cuts} cuts for {a.strokes} strokes", file=sys.stderr, flush=True)


def _cut_picture(run_dir: Path, job: ScanJob, path, summary, truth: tuple | None) -> None:
    """cut.png: what will be cut and what not, and why (a picture must never fail the job)."""
    try:
        cuts = [b.points for b in path.branches if b.feasible]
        cut_figure(run_dir / "cut.png", job.surface.xyz, cuts, summary.gaps, truth[0] if truth else None,
                   f"{100 * summary.cut_fraction:.1f} % of the {1000 * summary.drawing_length_m:.0f} mm line "
                   f"will be cut, in {len(cuts)} cuts")
    except Exception as e:  # noqa: BLE001 - reported, the cut itself is written already
        summary.warnings.append(f"could not draw cut.png: {type(e).__name__}: {e}")


@dataclass(frozen=True)
class JobSetup:
    """What every job profile starts from: the planners' config, the scene, the twin's config for
    this job's noise seed, and its run folder (created)."""

    pcfg: PlannersConfig
    scene: Scene
    twin_cfg: TwinConfig
    run_dir: Path


def prepare(spec: JobSpec) -> JobSetup:
    """The set-up of a job, whatever its profile."""
    cfg = spec.cfg
    pcfg = cell_planners_config(cfg, spec.cfg_path)
    if spec.max_steps is not None:
        pcfg = pcfg.model_copy(update={"max_steps": spec.max_steps})
    scene = load_scene(spec.scene)
    seed = {"seed": spec.seed} if spec.seed is not None else {}
    cam_cfg = cfg.twin.camera.model_copy(update={"noise": spec.noise, **seed})
    twin_cfg = cfg.twin.model_copy(update={"camera": cam_cfg, "tool": twin_torch(pcfg.cutpath)})
    if spec.run_dir is None:
        run_dir = new_run_dir(spec.out or cfg.runs_dir, scene.name, spec.planner)
    else:
        run_dir = spec.run_dir
        run_dir.mkdir(parents=True, exist_ok=True)
    return JobSetup(pcfg, scene, twin_cfg, run_dir)


def write_result(run_dir: Path, spec: JobSpec, result: ScanResult) -> None:
    """The job's result.json: the one record of a run folder, whatever the profile."""
    file = ResultFile(cell_id=spec.cfg.cell_id, mode=spec.cfg.mode, scene_ref=spec.scene, job_profile=spec.profile,
                      **result.model_dump())
    write_json(run_dir / "result.json", file.model_dump())


def run_job(spec: JobSpec, hooks: Hooks = Hooks()) -> tuple[ScanResult, Path]:
    """The one runner of a scan-drawing job: (its result, its run folder), by its profile: "scan", on the
    devices of ``cfg.mode`` (cellctl.scan.modes), or "initial_view" (cellctl.scan.initial_view). The run
    folder ends with a result.json whatever happens; an exception is raised after it is written."""
    if spec.profile == "initial_view":
        from cellctl.scan.initial_view import run_initial_view

        return run_initial_view(spec, hooks)
    if spec.profile != "scan":
        raise ValueError(f"unknown job profile {spec.profile!r}; choose scan or initial_view")
    return _run_scan(spec, hooks)


def _run_scan(spec: JobSpec, hooks: Hooks) -> tuple[ScanResult, Path]:
    """The whole job: explore, then (``spec.cut``) plan the cut, optionally run it in the twin."""
    cfg, planner = spec.cfg, spec.planner
    setup = prepare(spec)
    pcfg, scene, twin_cfg, run_dir = setup.pcfg, setup.scene, setup.twin_cfg, setup.run_dir
    recorder = ScanRecorder(run_dir / "scan.rrd", f"{scene.name}-{planner}", cfg.rerun_connect)
    result = ScanResult(scene=scene.name, planner=planner)
    job = None

    def report(rec: StepRecord) -> None:
        if hooks.progress:
            print(f"step {rec.step}: {rec.points} pts, drawing {rec.drawing_points}, frontier {rec.frontier_cells}, "
                  f"{rec.candidates} candidates, planning {rec.planning_s:.3f} s, motion {rec.motion_s:.2f} s",
                  file=sys.stderr, flush=True)
        if hooks.on_step:
            hooks.on_step(rec)

    unsaved: list[str] = []
    try:  # whatever happens, the run folder ends with a result.json and a closed recording
        try:
            with _devices(spec, scene, twin_cfg, run_dir) as dev:
                scene = dev.scene  # as placed in the twin (a fault may have moved it)
                recorder.log_scene(scene.full_mesh.vertices, scene.full_mesh.faces, scene.gt_points)
                job = ScanJob(dev.arm, dev.camera, planner, pcfg, cfg.motion, recorder, report,
                              park_q=twin_cfg.home_q, cancel=hooks.cancel, stopped_as=hooks.stop_label)
                if hooks.on_phase:
                    hooks.on_phase("scanning")
                result = job.run(scene.name, scene.initial_view_candidates, scene.gt_points)
                if spec.cut and result.error is None and not job.cancelled() and len(job.drawing):
                    if hooks.on_phase:
                        hooks.on_phase("planning-cut")
                    truth = ((scene.drawing_polylines, scene.gt_points, scene.full_mesh) if dev.twin is not None
                             else None)
                    _cut_phase(job, pcfg, cfg, dev.arm, run_dir, recorder, result, spec.dry_run_cut, hooks.progress,
                               truth)
        finally:  # what the scan saw is kept, also when the cut phase or the twin failed afterwards
            if job is not None:
                unsaved = _keep_views(job, run_dir, scene, pcfg, planner, result)
        if unsaved:
            raise OSError("; ".join(unsaved))
    except Exception as e:
        result.error = result.error or f"{type(e).__name__}: {e}"
        if unsaved and unsaved[0] not in result.error:
            result.error += "; " + "; ".join(unsaved)
        result.terminated_by = result.terminated_by or "error"
        raise
    finally:
        write_result(run_dir, spec, result)
        recorder.close()
    return result, run_dir


@contextmanager
def _devices(spec: JobSpec, scene: Scene, twin_cfg: TwinConfig, run_dir: Path):
    """The job's devices: its mode's (recorded when ``spec.record``), or a recorded job's (``spec.replay_from``)."""
    if spec.replay_from is not None:
        from cellctl.scan.replay import replay_devices

        with replay_devices(spec.replay_from, scene) as dev:
            yield dev
        return
    with open_devices(spec.cfg, scene, twin_cfg, run_dir=run_dir, arm_host=spec.arm_host) as dev:
        if not spec.record:
            yield dev
            return
        from cellctl.scan.replay import recording

        with recording(dev, run_dir) as rec:
            yield rec


def _keep_views(job: ScanJob, run_dir: Path, scene, pcfg, planner: str, result: ScanResult) -> list[str]:
    """Clouds, coverage figure and first view into the run folder; never raises (it runs while an
    error may be on its way out): returns what could not be written."""
    def write(name: str, fn, *args, **kw) -> None:
        try:
            fn(run_dir / name, *args, **kw)
        except Exception as e:  # noqa: BLE001 - reported by the caller
            unsaved.append(f"could not write {name}: {type(e).__name__}: {e}")

    unsaved: list[str] = []
    for name, cloud in (("drawing.ply", job.drawing), ("surface.ply", job.surface)):
        if len(cloud):  # a scan that ended before its first view has no cloud (and PLY cannot say "empty")
            write(name, write_ply, cloud)
    write("coverage.png", coverage_figure, scene.gt_points, job.drawing.xyz, np.array(result.viewpoints),
          pcfg.coverage_voxel_m, job.surface.xyz,
          f"{scene.name} / {planner}: {result.steps} views, coverage {result.coverage_percent:.1f} %")
    if job.first_color is not None:
        write("view0.png", save_png, job.first_color)
    if job.paint_view is not None:  # what the initial view took as paint (a refused piece: why)
        write("paint_check.png", save_png, paint_overlay(*job.paint_view))
    for k, picture in enumerate(job.paint_views):  # what every view took as paint (the tablet shows them)
        write(f"paint_view{k}.png", save_png, picture)
    return unsaved
