"""Faults injected in the twin (sim/faults.py, the `faults:` section of the twin config) and the state
each one ends in: recovered, `failed` with a clear reason, or `interrupted`; the arm stopped, what was
recorded kept, the service ready for the next job. The table in docs/RELIABILITY.md ("Faults") names
these tests. Real pybullet, real Zenoh on loopback, nothing mocked; short scans (smooth_cylinder, no
sensor noise, teleport execution unless the arm's motion itself matters, the fastest planner)."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pybullet as p
import pytest
import yaml
from pydantic import ValidationError

from cellctl.config import CellConfig, load_cell_config
from cellctl.scan.job import ScanJob
from cellctl.scan.run import run_job
from cellctl.scan.spec import JobSpec
from cellctl.service.loopback import ServiceProcess
from configs import CONFIG_DIR
from drivers.interfaces import Arm, DeviceError, JointTrajectory, RGBDCamera, TrajectoryError
from planners.config import load_planners_config
from sim.config import D435Config, TwinConfig
from sim.faults import OUT_OF_REACH_M, FaultsConfig, FaultyArm, FaultyCamera
from sim.scenes import load_scene
from sim.twin import Twin

CFG, CFG_PATH = load_cell_config(None)
PLANNER = "global"  # the fastest planner; no fault depends on which one plans
SCENE = "smooth_cylinder"
SMALL_CAMERA = {"width": 640, "height": 480, "hfov_deg": 55.0, "noise": False}  # a quarter fewer pixels to render


def cell(faults: dict, execution: str = "teleport") -> CellConfig:
    twin = CFG.twin.model_copy(update={"execution": execution, "faults": FaultsConfig.model_validate(faults),
                                       "camera": D435Config.model_validate(SMALL_CAMERA)})
    return CFG.model_copy(update={"twin": twin})


def scan(tmp_path: Path, faults: dict, max_steps: int = 3):
    """The job as the service runs it (run folder and all), without the cut."""
    return run_job(JobSpec(cell(faults), CFG_PATH, SCENE, PLANNER, noise=False, max_steps=max_steps, cut=False,
                           run_dir=tmp_path / "run"))


def job(faults: dict, max_steps: int = 3, execution: str = "teleport") -> tuple[Twin, ScanJob]:
    """The scan loop alone on a twin the test keeps (to look at the arm afterwards)."""
    cfg = cell(faults, execution)
    pcfg = load_planners_config(CFG_PATH.parent / CFG.planners_config).model_copy(update={"max_steps": max_steps})
    twin = Twin(load_scene(SCENE), cfg.twin)
    return twin, ScanJob(twin.arm, twin.camera, PLANNER, pcfg, cfg.motion, park_q=cfg.twin.home_q)


def run(twin: Twin, scan_job: ScanJob):
    return scan_job.run(SCENE, twin.scene.initial_view_candidates, twin.scene.gt_points)


def rrd_entities(path: Path) -> set[str]:
    """Entity paths of a recording, also one cut short by a kill (no footer: read as a stream)."""
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "legacy RRD without footer" for a killed job's recording
        return set(RrdReader(path).stream().collect().schema().entity_paths())


def assert_kept(run_dir: Path, res) -> None:
    """result.json says what happened; the recording and the clouds of every view so far are there."""
    saved = json.loads((run_dir / "result.json").read_text())
    assert saved["error"] == res.error and saved["steps"] == res.steps
    assert saved["incidents"] == json.loads(json.dumps(res.incidents))
    entities = rrd_entities(run_dir / "scan.rrd")
    assert "/world/truth/object" in entities
    for k in range(res.steps):
        assert f"/world/captures/{k}" in entities, (k, sorted(entities))
    if res.steps:
        for name in ("drawing.ply", "surface.ply", "view0.png", "coverage.png"):
            assert (run_dir / name).stat().st_size > 0, name


def kinds(res, step: int | None = None) -> list[str]:
    return [i["what"] for i in res.incidents if step is None or i["step"] == step]


# ----------------------------------------------------------------------------- config and wrappers
def test_faults_config_defaults_to_none_and_refuses_bad_values():
    assert not TwinConfig().faults.active and not CFG.twin.faults.active
    with Twin(load_scene(SCENE)) as twin:  # no faults: the plain twin devices
        assert type(twin.camera).__name__ == "TwinCamera" and type(twin.arm).__name__ == "TwinArm"
    ok = FaultsConfig.model_validate({"camera": {"drop_frames": [3, 1, 3], "noise_sigma_m": 0.5},
                                      "arm": {"reflex_on_motion": [2], "reflex_after_s": 0.2}})
    assert ok.camera.drop_frames == [1, 3] and ok.active
    for bad, field in [({"camera": {"noise_sigma_m": float("nan")}}, "noise_sigma_m"),
                       ({"camera": {"drop_probability": 1.0}}, "drop_probability"),
                       ({"camera": {"drop_frames": [-1]}}, "drop_frames"),
                       ({"camera": {"stale_timestamp_frames": [0]}}, "stale_timestamp_frames"),
                       ({"camera": {"dropped": [1]}}, "dropped"),
                       ({"arm": {"reflex_after_s": 0}}, "reflex_after_s"),
                       ({"arm": {"stop_after_s": float("inf")}}, "stop_after_s"),
                       ({"network": {}}, "network")]:
        with pytest.raises(ValidationError, match=field):
            FaultsConfig.model_validate(bad)
    with pytest.raises(ValidationError, match="faults"):
        CellConfig.model_validate({"twin": {"faults": {"camera": {"nan_frames": [1]}}}})


def test_faulty_camera_damages_exactly_the_chosen_captures():
    faults = {"camera": {"drop_frames": [1], "nan_depth_frames": [2], "zero_depth_frames": [3],
                         "stale_timestamp_frames": [4], "disconnect_at": 6}}
    with Twin(load_scene(SCENE), cell(faults).twin) as twin:
        cam = twin.camera
        assert isinstance(cam, FaultyCamera) and isinstance(cam, RGBDCamera) and isinstance(twin.arm, Arm)
        f0 = cam.capture()
        assert np.isfinite(f0.depth).any()
        with pytest.raises(DeviceError, match="didn't arrive"):
            cam.capture()
        assert np.isnan(cam.capture().depth).all()
        f3 = cam.capture()
        assert (f3.depth == 0).all() and f3.depth.dtype == np.float32
        f4 = cam.capture()
        assert f4.timestamp == f3.timestamp  # the last frame again
        f5 = cam.capture()
        assert f5.timestamp > f4.timestamp and np.isfinite(f5.depth).any()
        for _ in range(2):
            with pytest.raises(DeviceError, match="disconnected"):
                cam.capture()
        assert [k for _, k in cam.injected] == ["dropped", "nan_depth", "zero_depth", "stale", "disconnected",
                                                "disconnected"]
        # random drops: the same seed drops the same captures (p = 0.75: few frames are rendered)
        patterns = []
        for _ in range(2):
            lossy = FaultyCamera(twin.camera._camera, FaultsConfig.model_validate(
                {"camera": {"drop_probability": 0.75, "seed": 1}}).camera)
            patterns.append([_dropped(lossy) for _ in range(12)])
        assert patterns[0] == patterns[1] and 0 < sum(patterns[0]) < 12, patterns


def _dropped(camera) -> bool:
    try:
        camera.capture()
    except DeviceError as e:
        assert "didn't arrive" in str(e)
        return True
    return False


def test_extreme_depth_noise_is_seeded_and_only_on_valid_pixels():
    faults = {"camera": {"noise_sigma_m": 0.5, "seed": 7}}
    with Twin(load_scene(SCENE), cell(faults).twin) as a, Twin(load_scene(SCENE), cell(faults).twin) as b:
        fa, fb = a.camera.capture(), b.camera.capture()
        truth = a.camera.last_truth
        valid = np.isfinite(truth)
        assert np.array_equal(np.isfinite(fa.depth), valid) and np.array_equal(fa.depth, fb.depth, equal_nan=True)
        assert 0.4 < float(np.std(fa.depth[valid] - truth[valid])) < 0.6
        assert (fa.depth[valid] < 0).any()  # extreme indeed: some returns land behind the camera


# ----------------------------------------------------------------------------- camera faults in a scan
def test_transient_camera_faults_are_retried_and_the_scan_completes():
    """Recovered by capturing again: zero depth at the initial view (capture 0); a dropped frame, then
    an all-NaN one at view 1 (captures 2, 3); a stale frame (the last one re-served) at view 2 (capture 5)."""
    twin, scan_job = job({"camera": {"zero_depth_frames": [0], "drop_frames": [2], "nan_depth_frames": [3],
                                     "stale_timestamp_frames": [5]}})
    with twin:
        res = run(twin, scan_job)
        assert twin.camera.captures == 7
    assert res.error is None and res.terminated_by == "max_steps" and res.steps == 3, res.error
    assert kinds(res, 0) == ["no_valid_depth", "recovered"]
    assert kinds(res, 1) == ["no_frame", "no_valid_depth", "recovered"]
    assert kinds(res, 2) == ["stale_frame", "recovered"]
    assert res.coverage_percent > 30 and res.arm_stopped is None


@pytest.mark.parametrize("faults, max_steps, steps, reason", [
    ({"camera": {"stale_timestamp_frames": [1, 2, 3]}}, 3, 1,
     r"^DeviceError: camera gave no usable frame for view 1 in 3 attempts: 3 x stale frame"),
    ({"camera": {"drop_frames": [0], "nan_depth_frames": list(range(1, 50))}}, 3, 0,
     r"^DeviceError: camera returned no valid depth in 2 frames at the initial view: 1 x no frame .*; "
     r"2 x no valid depth"),
    ({"camera": {"zero_depth_frames": list(range(1, 50))}}, 5, 3,
     r"^DeviceError: camera returned no valid depth in 9 frames \(3 views in a row"),
], ids=["stale_always", "nan_always", "zero_after_first_view"])
def test_a_camera_fault_that_persists_fails_the_scan_with_its_reason(faults, max_steps, steps, reason):
    twin, scan_job = job(faults, max_steps)
    with twin:
        res = run(twin, scan_job)
    assert res.error is not None and "Traceback" not in res.error
    assert re.match(reason, res.error), res.error
    assert res.terminated_by == "error" and res.steps == steps and res.arm_stopped is True
    assert kinds(res)[-1] == "error"


def test_a_missing_camera_fails_the_scan_and_keeps_its_run_folder(tmp_path):
    """The camera disconnects after two views: failed with the reason, the two views' clouds, the
    recording and result.json kept in the run folder."""
    res, run_dir = scan(tmp_path, {"camera": {"disconnect_at": 2}})
    assert re.match(r"^DeviceError: camera gave no usable frame for view 2 in 3 attempts: 3 x no frame \(last: "
                    r"camera disconnected", res.error), res.error
    assert res.terminated_by == "error" and res.steps == 2 and res.arm_stopped is True
    assert_kept(run_dir, res)


def test_extreme_depth_noise_ends_the_scan_without_a_crash():
    twin, scan_job = job({"camera": {"noise_sigma_m": 0.5}}, max_steps=2)
    with twin:
        res = run(twin, scan_job)
    # the noise makes the scan poor, not broken: it ends by a planner's reason or a clear error
    assert res.error is None or "Traceback" not in res.error, res.error
    assert res.terminated_by in ("max_steps", "quality", "frontier", "no_candidates", "unreachable", "error")
    assert res.steps >= 1


# ----------------------------------------------------------------------------- arm faults in a scan

def _assert_holds(twin: Twin) -> None:
    """Stopped part way and holding: the joints stay where they are while the simulation runs on."""
    q0 = twin.arm.joint_positions()
    assert np.max(np.abs(q0 - twin.arm.last_motion_desired[-1])) > 0.01  # short of the motion's goal
    for _ in range(240):  # 1 s
        p.stepSimulation(physicsClientId=twin.client)
    q1 = twin.arm.joint_positions()
    qd = twin.arm.joint_velocities()
    assert np.max(np.abs(q1 - q0)) < 0.02 and np.max(np.abs(qd)) < 1e-2, (q1 - q0, qd)


@pytest.mark.parametrize("kind, faults, expect", [
    ("reflex", {"reflex_on_motion": [1], "reflex_after_s": 0.2},
     r"^TrajectoryError: reflex: motion 1 aborted at t = 0\.20 s of \d+\.\d\d s \(joint_reflex"),
    ("stop", {"stop_on_motion": [1]},
     r"^TrajectoryError: stop requested during motion 1 at t = .*; execution stopped at t="),
])
def test_a_motion_aborted_part_way_fails_the_scan_and_the_arm_holds(kind, faults, expect):
    """A reflex (libfranka aborts the motion) or a stop requested by someone else during the move to
    the second view (dynamics on: "step" execution): the scan ends failed with the reason and the arm
    stopped where it was. It is not re-planned: a reflex means something pushed back, which calls for an
    operator."""
    twin, scan_job = job({"arm": faults}, execution="step")
    with twin:
        assert isinstance(twin.arm, FaultyArm) and isinstance(twin.arm, Arm)
        res = run(twin, scan_job)
        assert re.match(expect, res.error), res.error
        assert res.terminated_by == "error" and res.steps == 1 and res.arm_stopped is True
        assert [(i, k) for i, k, _ in twin.arm.injected] == [(1, kind)]
        assert res.coverage_percent > 0 and len(scan_job.drawing) > 0  # the first view is kept
        _assert_holds(twin)
        # the arm still takes a motion afterwards
        q = twin.arm.joint_positions()
        home = np.asarray(CFG.twin.home_q)
        tr = JointTrajectory(np.linspace(0.0, 3.0, 31), q + np.linspace(0.0, 1.0, 31)[:, None] * (home - q))
        assert twin.arm.execute(tr) < 0.05


def test_the_arm_refuses_and_reports_when_every_view_is_out_of_reach(tmp_path):
    """ik_failure: the workpiece lies OUT_OF_REACH_M further away; the planners' own reach and IK checks
    refuse every view, and the scan says so instead of moving."""
    faults = {"arm": {"ik_failure": True}}
    with Twin(load_scene(SCENE), cell(faults).twin) as twin:
        moved = twin.scene.initial_view_candidates[:, :3, 3] - load_scene(SCENE).initial_view_candidates[:, :3, 3]
        assert np.allclose(moved, [OUT_OF_REACH_M, 0.0, 0.0])
    res, run_dir = scan(tmp_path, faults)
    assert res.terminated_by == "unreachable" and res.steps == 0 and res.arm_stopped is True
    assert res.error.startswith("ScanError: no initial view is reachable: none of ") and "beyond reach" in res.error
    saved = json.loads((run_dir / "result.json").read_text())
    assert saved["terminated_by"] == "unreachable" and saved["coverage_total"] > 0
    assert not (run_dir / "drawing.ply").exists()  # nothing was seen; nothing pretends otherwise
    assert_kept(run_dir, res)


def test_a_trajectory_error_outside_the_fault_plan_is_not_swallowed():
    """The wrapper only rewrites the error of the motion it aborted: a refused trajectory stays as it is."""
    with Twin(load_scene(SCENE), cell({"arm": {"reflex_on_motion": [0]}}).twin) as twin:
        q = twin.arm.joint_positions()
        with pytest.raises(TrajectoryError, match="starts .* away from the current joints"):
            twin.arm.execute(JointTrajectory(np.array([0.0, 1.0]), np.array([q + 0.3, q + 0.4])))
        assert twin.arm.injected == []


# ----------------------------------------------------------------------------- through the service
def service(tmp_path: Path, faults: dict | None = None) -> ServiceProcess:
    """`cellctl serve` on loopback with the twin's faults set in its config file."""
    svc = ServiceProcess(tmp_path)
    doc = yaml.safe_load(svc.config.read_text())
    doc["twin"] = {**doc.get("twin", {}), "execution": "teleport", "camera": SMALL_CAMERA, "faults": faults or {}}
    svc.config.write_text(yaml.safe_dump(doc))
    return svc.start()


def job_request(max_steps: int) -> dict:
    return {"scene": SCENE, "planner": PLANNER, "max_steps": max_steps, "noise": False}


def assert_failed_and_kept(rec, reason: str, steps: int) -> None:
    assert rec.state == "failed" and rec.error.startswith(reason), rec.error
    assert [t.state for t in rec.transitions] == ["queued", "running", "failed"]
    assert rec.result is not None and rec.result.steps == steps and rec.result.error == rec.error
    d = Path(rec.artifacts.dir)
    for name in ("result.json", "scan.rrd", "drawing.ply", "surface.ply"):
        assert name in rec.artifacts.files and (d / name).stat().st_size > 0, name
    saved = json.loads((d / "result.json").read_text())
    assert saved["arm_stopped"] is True and saved["error"] == rec.error and saved["steps"] == steps
    assert {f"/world/captures/{k}" for k in range(steps)} <= rrd_entities(d / "scan.rrd")


def assert_next_job_done(c, max_steps: int) -> None:
    rec = c.wait(c.submit(job_request(max_steps)).job_id, 120)
    assert rec.state == "done" and rec.error is None and rec.result.steps == max_steps, rec.error
    assert rec.result.cut is not None and "result.json" in rec.artifacts.files
    st = c.status()
    assert st.accepting_jobs and st.running_job is None and st.queue_length == 0


def test_service_fails_a_job_on_a_reflex_keeps_its_artifacts_and_runs_the_next(tmp_path):
    """Every job of this service meets a reflex on its motion 2 (the move after view 1): a three-view
    job fails there; a one-view job (motions 0 and 1) then runs to done in the same process."""
    svc = service(tmp_path, {"arm": {"reflex_on_motion": [2]}})
    try:
        with svc.client() as c:
            failed = c.wait(c.submit(job_request(3)).job_id, 120)
            assert_failed_and_kept(failed, "TrajectoryError: reflex: motion 2 aborted", steps=2)
            assert_next_job_done(c, 1)
        rc, _ = svc.stop(signal.SIGTERM)
        assert rc == 0
    finally:
        svc.kill()


def test_service_killed_mid_job_restarts_then_a_missing_camera_fails_a_job_and_the_next_runs(tmp_path):
    """One service life, its camera gone from capture 3 on in every job.
    1. SIGKILL during a long job (extends tests/test_service.py::
       test_a_job_running_when_the_service_dies_is_interrupted_and_the_queued_ones_run_after_it): after the restart the job is
       `interrupted`, its folder and recording (readable up to the kill) are kept and listed.
    2. A four-view job loses its camera at view 3: `failed` with the reason, artifacts kept, arm stopped.
    3. A two-view job runs to done."""
    svc = service(tmp_path, {"camera": {"disconnect_at": 3}})
    try:
        with svc.client() as c:
            stepped = threading.Event()
            killed = c.submit(job_request(12), on_event=lambda ev: ev.step == 0 and stepped.set()).job_id
            assert stepped.wait(120)
        svc.proc.send_signal(signal.SIGKILL)  # views 1-2 and their moves still to go: mid-job
        svc.proc.wait(10)
        d = svc.data_dir / "jobs" / killed
        written = sorted(x.name for x in d.iterdir())
        assert "scan.rrd" in written and "result.json" not in written  # killed: no chance to write more
        svc.start()
        with svc.client() as c:
            rec = c.job(killed)
            assert rec.state == "interrupted" and rec.error.startswith("interrupted:")
            assert [t.state for t in rec.transitions] == ["queued", "running", "interrupted"]
            assert rec.progress.step in (0, 1) and rec.artifacts.files == written
            assert "/world/truth/object" in rrd_entities(d / "scan.rrd")

            failed = c.wait(c.submit(job_request(4)).job_id, 120)
            assert_failed_and_kept(failed, "DeviceError: camera gave no usable frame for view 3 in 3 attempts: "
                                           "3 x no frame (last: camera disconnected", steps=3)
            assert_next_job_done(c, 2)
        rc, _ = svc.stop(signal.SIGTERM)
        assert rc == 0
    finally:
        svc.kill()


def test_the_sim_config_documents_the_faults_section():
    doc = yaml.safe_load((CONFIG_DIR / "cell.sim.yaml").read_text())
    assert "faults" in doc["twin"] and not FaultsConfig.model_validate(doc["twin"]["faults"]).active


def _job_worker(service_pid: int) -> int:
    """The pid of the service's job worker (cellctl.service.worker): its child started by
    multiprocessing's spawn, not the resource tracker."""
    found = []
    for task in Path(f"/proc/{service_pid}/task").iterdir():
        for pid in (task / "children").read_text().split():
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
            if b"multiprocessing" in cmd and b"resource_tracker" not in cmd:
                found.append(int(pid))
    assert len(found) == 1, found
    return found[0]


def test_a_job_whose_worker_crashes_fails_with_its_artifacts_and_the_cell_serves_on(tmp_path):
    """A real SIGSEGV in the job's worker process mid-scan (as a crash in pybullet, Open3D or
    numba would raise): the job ends `failed` saying how its worker died, its folder and recording
    so far are kept and listed, the service answers throughout and runs the next job to done.
    Then a SIGKILL of the service itself takes its running worker with it (no orphan moves on)."""
    svc = service(tmp_path)
    try:
        with svc.client() as c:
            stepped = threading.Event()
            crashed = c.submit(job_request(12), on_event=lambda ev: ev.step == 0 and stepped.set()).job_id
            assert stepped.wait(120)
            worker = _job_worker(svc.proc.pid)
            os.kill(worker, signal.SIGSEGV)
            rec = c.wait(crashed, 120)
            assert rec.state == "failed" and "SIGSEGV" in rec.error and "worker process" in rec.error, rec.error
            assert [t.state for t in rec.transitions] == ["queued", "running", "failed"]
            assert rec.transitions[-1].note == "the job's worker process died"
            d = Path(rec.artifacts.dir)
            assert "scan.rrd" in rec.artifacts.files and "/world/captures/0" in rrd_entities(d / "scan.rrd")
            st = c.status()
            assert st.accepting_jobs and st.running_job is None
            assert_next_job_done(c, 2)

            stepped.clear()
            running = c.submit(job_request(12), on_event=lambda ev: ev.step == 0 and stepped.set()).job_id
            assert stepped.wait(120)
            worker = _job_worker(svc.proc.pid)
        svc.proc.send_signal(signal.SIGKILL)
        svc.proc.wait(10)
        deadline = time.monotonic() + 30
        while Path(f"/proc/{worker}").exists() and b"zombie" not in Path(f"/proc/{worker}/status").read_bytes():
            assert time.monotonic() < deadline, "the worker outlived its service"
            time.sleep(0.05)
        # killed with its service, it wrote nothing more (an orphan would end its scan and write its result)
        assert not (svc.data_dir / "jobs" / running / "result.json").exists()
    finally:
        svc.kill()
