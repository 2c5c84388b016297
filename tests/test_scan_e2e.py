"""End-to-end scans in the pybullet twin, sensor noise on: camera -> clouds -> grid -> G-NBV -> IK ->
trajectory -> twin, and the run folder a user gets.

Tests of: cellctl.scan.run, cellctl.scan.job, cellctl.scan.cut, cellctl.scan.result, cellctl.scan.artifacts, cellctl.scan.plots, cellctl.scan.recording.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellctl.config import load_cell_config
from cellctl.scan.run import run_job
from cellctl.scan.spec import JobSpec
from sim.scenes import load_scene

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cell():
    return load_cell_config(None)


def _scan(cell, scene, tmp_path, **kw):
    cfg, path = cell
    return run_job(JobSpec(cfg, path, scene, "gnbv", out=str(tmp_path), **kw))


@pytest.mark.parametrize("scene", ["smooth_cylinder", "round_tank"])
def test_gnbv_covers_the_drawing(cell, scene, tmp_path):
    result, run_dir = _scan(cell, scene, tmp_path)
    assert result.error is None
    assert result.coverage_percent >= 95.0, result
    assert result.terminated_by in ("quality", "frontier")
    assert 1 <= result.steps <= 12
    assert result.planning_s > 0 and result.motion_s > 0 and result.capture_s > 0
    assert result.motion_contacts == 0, [r.contacts for r in result.records if r.contacts]
    for name in ("result.json", "drawing.ply", "surface.ply", "scan.rrd"):
        assert (run_dir / name).stat().st_size > 0, name
    rerun_cli = Path(sys.executable).with_name("rerun")
    ok = subprocess.run([str(rerun_cli), "rrd", "verify", str(run_dir / "scan.rrd")], capture_output=True, text=True,
                        timeout=120)
    assert ok.returncode == 0, ok.stderr
    # read back with Rerun's own API: the entities an operator expects to find
    from rerun.chunk import RrdReader

    store = RrdReader(run_dir / "scan.rrd").store()
    paths = set(store.schema().entity_paths())
    for entity in ("/world/captures/0", "/world/camera/image", "/world/camera/image/rgb", "/world/frontier",
                   "/world/viewpoints", "/world/view_path", "/world/drawing", "/world/candidates",
                   "/world/robot/panda_hand", "/world/robot/panda_link4", "/world/cut/cut0", "/world/cut/cut0/torch",
                       "/world/truth/object", "/world/camera/image/paint", "/coverage/percent_of_true_line"):
        assert entity in paths, (entity, sorted(paths))
    assert any(p.startswith("/world/robot/panda_hand/") for p in paths)  # the hand's geometry under its transform
    saved = json.loads((run_dir / "result.json").read_text())
    assert saved["coverage_percent"] == result.coverage_percent and saved["steps"] == result.steps
    assert len(saved["viewpoints"]) == result.steps


def test_the_recording_keeps_the_piece_dims_what_it_stands_on_and_drops_the_rest(tmp_path):
    from cellctl.scan.recording import ROI_MARGIN_M, ScanRecorder

    rec = ScanRecorder(tmp_path / "x.rrd", "x")
    xyz = np.array([[0.2, 0.1, 0.3], [0.2, 0.1, 0.203], [0.2, 0.1, 0.25], [1.5, 0.0, 0.0], [0.2, 0.1, 0.9]])
    rgb = np.tile(np.array([[200, 20, 20]], dtype=np.uint8), (5, 1))
    assert rec.crop(xyz, rgb)[0] is xyz  # the piece is not known yet: everything is kept
    rec.log_scene(np.array([[0.0, 0.0, 0.2], [0.4, 0.3, 0.5]]), np.array([[0, 1, 1]]), np.zeros((0, 3)))
    kept, colours = rec.crop(xyz, rgb)
    assert np.array_equal(kept, xyz[:3])  # 1.5 m off and 0.4 m above the box (margin ROI_MARGIN_M) are gone
    assert ROI_MARGIN_M < 0.4
    assert np.array_equal(colours[[0, 2]], rgb[[0, 2]])  # the piece keeps its colours
    assert colours[1].min() > 150 and np.ptp(colours[1].astype(int)) < 60  # its support plane is pale grey
    rec.close()


@pytest.mark.parametrize("scene", ["sharp_cylinder", "t_piece", "i_beam", "basket"])
def test_every_view_move_is_collision_free_in_the_twin(cell, scene, tmp_path):
    """The planner's FCL model plans the moves; the twin's own contact query (pybullet, the true
    meshes) checks every executed motion, from home to the last view. The I-beam reaches the outer
    flange faces only via waypoints around the object."""
    result, _ = _scan(cell, scene, tmp_path, max_steps=8)
    assert result.error is None, result.error
    assert result.motion_contacts == 0, [r.contacts for r in result.records if r.contacts]
    assert all(r.via for r in result.records[:-1] if r.chosen_rank is not None)
    assert result.coverage_percent >= {"basket": 60.0}.get(scene, 95.0)


def test_home_is_clear_of_every_built_in_scene():
    import pybullet as p

    from sim.scenes import SCENE_NAMES
    from sim.twin import Twin

    for name in SCENE_NAMES:
        with Twin(load_scene(name)) as twin:
            p.performCollisionDetection(physicsClientId=twin.client)
            for body in (twin.object_id, twin.paint_id):
                close = p.getClosestPoints(twin.robot_id, body, 0.1, physicsClientId=twin.client)
                assert not close, (name, [(c[3], round(c[8], 3)) for c in close])


def test_branched_drawing_reconstructed_to_all_four_extremities(cell, tmp_path):
    import open3d as o3d

    result, run_dir = _scan(cell, "branched_cylinder", tmp_path)
    assert result.error is None and result.motion_contacts == 0
    drawing = np.asarray(o3d.io.read_point_cloud(str(run_dir / "drawing.ply")).points)
    ends = load_scene("branched_cylinder").extremities
    assert len(ends) == 4
    gap = np.linalg.norm(drawing[None, :, :] - ends[:, None, :], axis=2).min(axis=1)
    assert np.all(gap < 0.015), f"distance from each extremity to the reconstruction: {gap}"


def test_scan_ends_with_a_cutting_path_the_twin_can_follow(cell, tmp_path):
    """planning-cut after the scan: cuts through the drawing's junctions toward its ends, torch poses on
    the surface within the tilt cone, what is not cut reported with its reason, files in the run
    folder, the cuts measured against the true line, and a dry run whose tip follows the plan."""
    import csv

    from planners.cutpath import CutPath

    result, run_dir = _scan(cell, "branched_cylinder", tmp_path, dry_run_cut=True)
    assert result.error is None and result.cut is not None and result.cut.error is None
    c = result.cut
    # the two painted lines cross: each is one cut straight through the crossing; the arm cannot reach
    # the drawing's far ends: those stretches are gaps with their reason, the rest is cut
    assert c.feasible_branches >= 2 and c.cut_fraction >= 0.65, c
    assert 0.7 < c.drawing_length_m < 1.3  # the two painted lines are about 0.5 m each
    assert all(g.reason in ("out of reach", "joint limits", "collision", "singular", "reconfigure")
               for g in c.gaps), c.gaps
    a = c.accuracy
    assert a.strokes == 2 and a.cut_coverage >= 0.6 and a.path_to_line_mean_mm <= 2.5, a
    path = CutPath.read(run_dir)
    ends = load_scene("branched_cylinder").extremities
    gap = np.linalg.norm(path.endpoints[None, :, :] - ends[:, None, :], axis=2).min(axis=1)
    assert np.all(gap < 0.02), gap
    for b in path.branches:  # the tip stands off the drawing by the standoff, the torch points into it
        tips = b.poses[:, :3, 3]
        assert np.allclose(np.linalg.norm(tips - b.points, axis=1), 0.010, atol=1e-3)
        tilt = np.degrees(np.arccos(np.clip(-np.einsum("ij,ij->i", b.poses[:, :3, 2], b.normals), -1.0, 1.0)))
        assert np.all(tilt <= 20.0 + 0.5), tilt.max()  # within the torch's tolerance cone
    with open(run_dir / "cut_path.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == c.poses
    traj = np.load(run_dir / "cut_trajectory.npz")
    assert any(k.endswith("_cut_q") for k in traj.files)
    d = c.dry_run
    assert d.motions == 3 * c.feasible_branches and d.contacts == 0 and d.contact_log == []
    assert d.tip_error_max_mm < 2.0 and d.path_error_max_mm < 2.0
    # the cut against what the scan saw agrees with the truth, and the executed flame stays on the paint
    p = c.paint
    assert p is not None and abs(p.cut_share - a.cut_coverage) <= 0.05, (p, a)
    assert 0.7 < p.line_length_m < 1.3 and 14 <= p.spray_width_mm <= 26, p
    assert a.path_to_line_max_mm <= 5.0 and a.pose_to_line_max_mm <= 5.0, a
    assert 7.0 <= a.tip_to_metal_min_mm <= a.tip_to_metal_max_mm <= 13.0, a
    assert d.flame_off_paint_max_mm is not None and d.flame_off_paint_max_mm < 5.0, d
    assert d.flame_to_line_max_mm is not None and d.flame_to_line_max_mm <= a.path_to_line_max_mm + 2.0, d


def test_user_yaml_scene_with_obj_mesh_scans(cell, tmp_path):
    import trimesh

    mesh = trimesh.creation.box([0.30, 0.40, 0.12])
    mesh = mesh.subdivide_to_size(0.03)
    (tmp_path / "crate.obj").write_text(trimesh.exchange.obj.export_obj(mesh))
    (tmp_path / "crate.yaml").write_text(
        "name: crate\nmesh: crate.obj\npose: {xyz: [0.5, 0.0, 0.06], rpy_deg: [0, 0, 10]}\n"
        "drawing:\n  width: 0.02\n  polylines:\n    - [[-0.1, -0.17, 0.06], [0.0, 0.0, 0.06], [0.1, 0.17, 0.06]]\n")
    result, run_dir = _scan(cell, str(tmp_path / "crate.yaml"), tmp_path / "runs")
    assert result.error is None and result.scene == "crate"
    assert result.coverage_percent >= 90.0


def test_invalid_scene_file_is_refused_naming_the_field(tmp_path):
    (tmp_path / "bad.yaml").write_text("name: bad\nmesh: nowhere.obj\npose: {xyz: [0.5, 0, 0], rpy_deg: [0, 0, 0]}\n"
                                       "drawing: {width: wide, polylines: [[[0, 0, 0], [0.1, 0, 0]]]}\n")
    out = subprocess.run([sys.executable, "-m", "cellctl.cli", "scan", "--scene", str(tmp_path / "bad.yaml"),
                          "--out", str(tmp_path / "runs")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 2
    assert "bad.yaml" in out.stderr and "drawing.width" in out.stderr
    assert "Traceback" not in out.stderr


def test_invalid_cell_config_is_refused_naming_the_field(tmp_path):
    (tmp_path / "cell.yaml").write_text("cell_id: a\nmotion: {speed_factor: 3}\n")
    out = subprocess.run([sys.executable, "-m", "cellctl.cli", "scan", "--scene", "smooth_cylinder",
                          "--config", str(tmp_path / "cell.yaml")], capture_output=True, text=True, cwd=ROOT,
                         timeout=120)
    assert out.returncode == 2
    assert "cell.yaml: motion.speed_factor" in out.stderr


def test_one_capture_gives_grid_states_and_a_frontier(cell):
    """After the first view of smooth_cylinder: the painted surface is occupied, the air in front of
    the camera free, the pipe's inside unknown, and the drawing's frontier is not empty."""
    from cellctl.scan.job import ScanJob
    from planners.config import load_planners_config
    from planners.metrics import coverage
    from sim.twin import Twin

    cfg, path = cell
    pcfg = load_planners_config(path.parent / cfg.planners_config)
    scene = load_scene("smooth_cylinder")
    with Twin(scene, cfg.twin) as twin:
        twin.arm.reset(cfg.twin.home_q)
        job = ScanJob(twin.arm, twin.camera, "gnbv", pcfg, cfg.motion)
        job.move_to_initial(scene.initial_view_candidates)
        T = twin.arm.camera_pose()
        job.process(twin.camera.capture(), T, twin.arm.joint_positions())
    g = job.grid
    seen = job.drawing.xyz
    assert len(seen) > 100
    ijk, inside = g.index_of(seen)
    occupied_share = g.occupied[tuple(ijk[inside].T)].mean()
    assert occupied_share > 0.8
    # halfway between the camera and a drawing point: free
    mid = (T[:3, 3] + seen.mean(axis=0)) / 2
    assert g.free[tuple(g.index_of(mid[None])[0][0])]
    # the pipe's axis, never observed: unknown
    axis_point = scene.object_mesh.bounds.mean(axis=0)
    assert g.unknown[tuple(g.index_of(axis_point[None])[0][0])]
    assert g.frontier().sum() > 0
    assert coverage(seen, scene.gt_points, 0.01).percent < 90.0  # one view does not see it all


def test_every_job_profile_is_set_up_and_recorded_alike(tmp_path):
    """run_job is the one entry of a scan-drawing job: the initial-view profile (the load test's
    job) is set up by the same `prepare` and writes the same result.json header as a full scan;
    an unknown profile is refused before anything runs."""
    cfg, cfg_path = load_cell_config(None)
    res, run_dir = run_job(JobSpec(cfg, cfg_path, "t_piece", "gnbv", profile="initial_view", run_dir=tmp_path / "iv",
                                   noise=False))
    assert run_dir == tmp_path / "iv" and res.steps == 1 and res.terminated_by == "initial_view" and res.coverage_percent > 0
    doc = json.loads((tmp_path / "iv" / "result.json").read_text())
    assert {k: doc[k] for k in ("schema_version", "cell_id", "mode", "scene_ref", "job_profile")} == {
        "schema_version": 1, "cell_id": cfg.cell_id, "mode": cfg.mode, "scene_ref": "t_piece",
        "job_profile": "initial_view"}
    with pytest.raises(ValueError, match="unknown job profile 'bogus'"):
        run_job(JobSpec(cfg, cfg_path, "t_piece", "gnbv", profile="bogus", run_dir=tmp_path / "bogus"))
    assert not (tmp_path / "bogus").exists()
