"""Cut path from the drawing: skeleton graph, smoothing and spacing, torch poses on the surface,
IK along the path, files. Synthetic clouds whose answer is known, and two catalog scenes.

Tests of: planners.cutpath.plan, planners.cutpath.pieces, planners.cutpath._checks, planners.cutpath.config,
planners.cutpath.model.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time

import numpy as np
import pybullet_data
import pytest

from planners.clouds import Cloud
from planners.cutpath import (
    GAP_REASONS,
    CutPath,
    CutPathConfig,
    TorchConfig,
    build_cut_path,
    drawing_graph,
    plan_cut,
    smooth_resample,
    torch_kinematics,
    torch_poses,
)
from planners.motion.limits import PANDA_Q_READY
from sim.scenes import load_scene

URDF = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
CFG = CutPathConfig()
PLATE_Z = 0.1
EYE = np.array([0.45, 0.0, 0.6])  # a sensor position above the plate


@pytest.fixture(scope="module")
def kin():
    return torch_kinematics(URDF, CFG)


@pytest.fixture(scope="module")
def branched():
    return load_scene("branched_cylinder")


@pytest.fixture(scope="module")
def cylinder():
    return load_scene("smooth_cylinder")


def plate(x=(0.25, 0.65), y=(-0.25, 0.25), step=0.002) -> np.ndarray:
    g = np.mgrid[x[0]:x[1]:step, y[0]:y[1]:step].reshape(2, -1).T
    return np.column_stack([g, np.full(len(g), PLATE_Z)])


def sprayed(points: np.ndarray, a, b, width=0.02) -> np.ndarray:
    """Mask of the points within width/2 of segment ab: a sprayed line with round caps."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = points - a
    t = np.clip(d @ (b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return np.linalg.norm(d - t[:, None] * (b - a), axis=1) <= width / 2


def cloud(xyz: np.ndarray, eye=EYE) -> Cloud:
    xyz = np.asarray(xyz, np.float32)
    return Cloud(xyz, np.zeros(xyz.shape, np.uint8), np.broadcast_to(np.float32(eye), xyz.shape).copy())


def line_on_plate(a, b):
    """(drawing cloud, surface cloud) of a line sprayed on the plate z = PLATE_Z."""
    surf = plate()
    return cloud(surf[sprayed(surf, a, b)]), cloud(surf)


def nearest_ends_error(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(found[:, None] - truth[None], axis=2)
    assert sorted(d.argmin(axis=1).tolist()) == list(range(len(truth))), "two found ends match one true end"
    return d.min(axis=1)


# ---------------------------------------------------------------------------- graph


def test_branched_drawing_has_its_junctions_and_four_ends(branched):
    t0 = time.perf_counter()
    g = drawing_graph(branched.gt_points, CFG.voxel_m, CFG.min_branch_m)
    elapsed = time.perf_counter() - t0
    assert 1 <= len(g.junctions) <= 2
    assert len(g.endpoints) == 4
    assert nearest_ends_error(g.endpoints, branched.extremities).max() < 0.015
    assert len(g.branches) == len(g.endpoints) + len(g.junctions) - 1  # a tree
    for p, (a, b) in zip(g.branches, g.ends):  # each branch runs between its two nodes
        np.testing.assert_allclose(p[0], g.nodes[a])
        np.testing.assert_allclose(p[-1], g.nodes[b])
    print(f"graph of the branched drawing ({len(branched.gt_points)} points): {1e3 * elapsed:.1f} ms")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_branched_drawing_survives_noise_and_holes(branched, seed):
    rng = np.random.default_rng(seed)
    pts = branched.gt_points[rng.random(len(branched.gt_points)) < 0.5].astype(np.float64)
    pts += rng.normal(0.0, 0.001, pts.shape)
    pts = np.vstack([pts, pts[rng.integers(0, len(pts), 20)] + rng.normal(0, 0.02, (20, 3))])  # specks
    g = drawing_graph(pts, CFG.voxel_m, CFG.min_branch_m)
    assert 1 <= len(g.junctions) <= 2
    assert len(g.endpoints) == 4
    assert nearest_ends_error(g.endpoints, branched.extremities).max() < 0.015


@pytest.mark.parametrize("width,offset", [(0.02, 0.0), (0.02, 0.0025), (0.016, 0.001), (0.024, 0.003)])
def test_flat_axis_aligned_lines_are_not_lost_to_thinning(width, offset):
    """skimage's 3-D thinning erases some flat, grid-aligned pieces whole (scikit-image#3757)."""
    surf = plate() + [offset, offset, 0.0]
    for a, b in (((0.35, -0.1, PLATE_Z), (0.55, -0.1, PLATE_Z)), ((0.45, -0.2, PLATE_Z), (0.45, 0.15, PLATE_Z))):
        a, b = np.add(a, [offset, offset, 0]), np.add(b, [offset, offset, 0])
        g = drawing_graph(surf[sprayed(surf, a, b, width)], CFG.voxel_m, CFG.min_branch_m)
        assert len(g.branches) == 1 and len(g.endpoints) == 2
        assert nearest_ends_error(g.endpoints, np.stack([a, b])).max() < 0.01


def test_straight_line_length_and_spacing():
    a, b = np.array([0.35, -0.12, PLATE_Z]), np.array([0.55, 0.12, PLATE_Z])  # 0.312 m, slanted
    drawing, surface = line_on_plate(a, b)
    path = build_cut_path(drawing, surface, CFG)
    assert len(path.branches) == 1 and len(path.junctions) == 0 and len(path.endpoints) == 2
    br = path.branches[0]
    true = float(np.linalg.norm(b - a))
    assert abs(br.length_m - true) / true < 0.02
    step = np.linalg.norm(np.diff(br.points, axis=0), axis=1)
    assert np.all(np.abs(step - CFG.spacing_m) <= 0.1 * CFG.spacing_m)
    # on the line: every point within 2 mm of the segment
    d = np.linalg.norm(np.cross(br.points - a, b - a), axis=1) / true
    assert d.max() < 0.002


def test_spurs_are_pruned_and_a_t_keeps_its_junction():
    surf = plate()
    c = np.array([0.45, 0.0, PLATE_Z])
    t_shape = sprayed(surf, c - [0.12, 0, 0], c + [0.12, 0, 0]) | sprayed(surf, c, c + [0, 0.15, 0])
    g = drawing_graph(surf[t_shape], CFG.voxel_m, CFG.min_branch_m)
    assert len(g.junctions) == 1 and len(g.endpoints) == 3
    assert np.linalg.norm(g.junctions[0] - c) < 0.015
    hair = t_shape | sprayed(surf, c - [0.06, 0, 0], c - [0.06, -0.02, 0], 0.006)  # a 2 cm blob on the side
    g2 = drawing_graph(surf[hair], CFG.voxel_m, CFG.min_branch_m)
    assert len(g2.junctions) == 1 and len(g2.endpoints) == 3


def test_a_ring_is_one_closed_branch():
    surf = plate()
    c = np.array([0.45, 0.0, PLATE_Z])
    ring = np.abs(np.linalg.norm(surf - c, axis=1) - 0.1) <= 0.01
    path = build_cut_path(cloud(surf[ring]), cloud(surf), CFG)
    assert len(path.branches) == 1 and len(path.endpoints) == 0 and len(path.junctions) == 0
    br = path.branches[0]
    assert br.closed and br.start == br.end
    np.testing.assert_allclose(br.points[0], br.points[-1], atol=1e-9)
    assert abs(br.length_m - 2 * math.pi * 0.1) / (2 * math.pi * 0.1) < 0.02


def test_smooth_resample_spacing():
    s = np.linspace(0, 1, 40)
    noisy = np.column_stack([0.3 * s, 0.05 * np.sin(3 * s), np.zeros_like(s)])
    p = smooth_resample(noisy, 0.005, 0.002)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.ptp(step) < 0.02 * 0.005 and abs(step.mean() - 0.005) < 0.5e-3
    np.testing.assert_allclose(p[[0, -1]], noisy[[0, -1]], atol=1e-4)  # ends held


# ---------------------------------------------------------------------------- poses


def _cylinder_check(path, centre, radius):
    for br in path.branches:
        R = br.poses[:, :3, :3]
        np.testing.assert_allclose(np.einsum("kji,kjl->kil", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
        assert np.all(np.linalg.det(R) > 0)
        x, z = R[:, :, 0], R[:, :, 2]
        assert np.abs(np.einsum("kj,kj->k", x, z)).max() < 1e-9
        rad = br.points - centre
        rad[:, 1] = 0.0  # the axis is along y
        inward = -rad / np.linalg.norm(rad, axis=1, keepdims=True)
        assert np.einsum("kj,kj->k", z, inward).min() > 0.95
        tip = br.poses[:, :3, 3] - centre
        tip[:, 1] = 0.0
        assert np.abs(np.linalg.norm(tip, axis=1) - radius - CFG.standoff_m).max() < 0.001
        travel = np.gradient(br.points, axis=0)
        assert np.all(np.einsum("kj,kj->k", x, travel) > 0)  # x along the direction of travel


def test_torch_poses_on_the_smooth_cylinder(cylinder):
    centre, radius = np.array([0.43, 0.0, 0.12]), 0.12  # the pipe of catalog.smooth_cylinder, axis along y
    t0 = time.perf_counter()
    path = build_cut_path(cylinder.gt_points, None, CFG, viewpoint=[0.43, 0.0, 1.0])
    elapsed = time.perf_counter() - t0
    assert len(path.branches) == 1
    _cylinder_check(path, centre, radius)
    step = np.linalg.norm(np.diff(path.branches[0].points, axis=0), axis=1)
    assert np.all(np.abs(step - CFG.spacing_m) <= 0.1 * CFG.spacing_m)
    print(f"smooth_cylinder drawing -> {len(path.branches[0])} torch poses: {1e3 * elapsed:.1f} ms")


def test_normals_are_oriented_by_the_sensor_positions():
    """A cylinder seen from above and from below: each side's normals face its own sensor."""
    rng = np.random.default_rng(3)
    centre, radius = np.array([0.45, 0.0, 0.3]), 0.1
    th, y = rng.uniform(0, 2 * np.pi, 60000), rng.uniform(-0.2, 0.2, 60000)
    xyz = centre + np.column_stack([radius * np.sin(th), y, radius * np.cos(th)])
    eyes = np.where((np.cos(th) > 0)[:, None], centre + [0, 0, 0.5], centre - [0, 0, 0.5])
    surface = Cloud(xyz.astype(np.float32), np.zeros(xyz.shape, np.uint8), eyes.astype(np.float32))
    line_th = np.radians(35) * np.sin(np.pi * (y + 0.2) / 0.4)  # a wavy line over the top
    on_top = (np.abs(th - line_th) * radius < 0.01) & (np.abs(y) < 0.15)
    for drawing in (surface.select(on_top), surface.select(np.abs(th - np.pi) * radius < 0.01)):  # top, bottom
        path = build_cut_path(drawing, surface, CFG)
        assert len(path.branches) == 1
        _cylinder_check(path, centre, radius)


def test_bent_plate_path_stays_on_the_metal():
    """A line over the 90-degree edge of a bent plate: smoothing would cut the corner."""
    u, v = np.mgrid[-0.15:0.15:0.002, 0:0.2:0.002].reshape(2, -1)
    top = np.column_stack([0.5 - v, u, np.full(u.size, PLATE_Z)])
    side = np.column_stack([np.full(u.size, 0.5), u, PLATE_Z - v])
    surf = np.vstack([top, side])
    line = (np.abs(surf[:, 1]) <= 0.01) & (surf[:, 0] > 0.38) & (surf[:, 2] > -0.02)
    path = build_cut_path(cloud(surf[line], eye=[0.8, 0.0, 0.4]), cloud(surf, eye=[0.8, 0.0, 0.4]), CFG)
    assert len(path.branches) == 1
    p = path.branches[0].points
    dx, dz = 0.5 - p[:, 0], PLATE_Z - p[:, 2]
    inside = (dx >= 0) & (dz >= 0)
    off = np.where(inside, np.minimum(dx, dz), np.hypot(np.minimum(dx, 0), np.minimum(dz, 0)))
    assert off.max() < CFG.voxel_m / 5  # well within a voxel of the surface, corner included
    assert path.branches[0].length_m > 0.2


def test_torch_frames(kin):
    torch = TorchConfig(xyz_m=(0.0, 0.05, 0.22), rpy_deg=(30.0, 0.0, 0.0), length_m=0.15)
    T = torch.T_flange_torch()
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.05, 0.22])
    np.testing.assert_allclose(torch.T_flange_mount()[:3, 3], T[:3, 3] - 0.15 * T[:3, 2], atol=1e-12)
    q = PANDA_Q_READY + 0.1
    np.testing.assert_allclose(kin.fk(q), kin.fk(q, "flange") @ CFG.torch.T_flange_torch(), atol=1e-12)


def test_torch_poses_direct():
    p = np.column_stack([np.linspace(0.4, 0.5, 21), np.zeros(21), np.full(21, PLATE_Z)])
    n = np.tile([0.0, 0.0, 1.0], (21, 1))
    T = torch_poses(p, n, 0.01)
    np.testing.assert_allclose(T[:, :3, 2], np.tile([0, 0, -1.0], (21, 1)), atol=1e-12)
    np.testing.assert_allclose(T[:, :3, 0], np.tile([1.0, 0, 0], (21, 1)), atol=1e-12)
    np.testing.assert_allclose(T[:, :3, 3], p + [0, 0, 0.01], atol=1e-12)


# ---------------------------------------------------------------------------- joint motion


def test_ik_along_a_reachable_line(kin):
    drawing, surface = line_on_plate((0.45, -0.15, PLATE_Z), (0.45, 0.15, PLATE_Z))
    path = build_cut_path(drawing, surface, CFG)
    t0 = time.perf_counter()
    plan_cut(path, kin, PANDA_Q_READY, CFG)
    elapsed = time.perf_counter() - t0
    br = path.branches[0]
    assert br.feasible and set(br.feasibility) == {"ok"} and not br.issues
    assert np.abs(np.diff(br.q, axis=0)).max() <= CFG.max_joint_jump_rad
    T = kin.fk_batch(br.q)
    assert np.linalg.norm(T[:, :3, 3] - br.poses[:, :3, 3], axis=1).max() < 0.001
    assert np.einsum("kj,kj->k", T[:, :3, 2], br.poses[:, :3, 2]).min() > math.cos(math.radians(0.5))
    # timed by the travel speed
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(br.points, axis=0), axis=1))])
    np.testing.assert_allclose(br.times, s / CFG.travel_speed_mps)
    assert br.cut.duration == pytest.approx(br.length_m / CFG.travel_speed_mps, rel=1e-6)
    np.testing.assert_allclose(br.cut.positions[-1], br.q[-1], atol=1e-9)
    # approach starts where the arm is and ends on the first pose; retract starts on the last
    np.testing.assert_allclose(br.approach.positions[0], PANDA_Q_READY, atol=1e-9)
    np.testing.assert_allclose(br.approach.positions[-1], br.q[0], atol=1e-9)
    np.testing.assert_allclose(br.retract.positions[0], br.q[-1], atol=1e-9)
    back = kin.fk(br.approach_q)[:3, 3] - br.poses[0, :3, 3]
    np.testing.assert_allclose(back, -CFG.approach_m * br.poses[0, :3, 2], atol=0.001)
    print(f"IK along a {br.length_m:.2f} m line ({len(br)} poses) + approach/retract: {1e3 * elapsed:.1f} ms")


def test_fixed_roll_follows_the_travel_direction(kin):
    cfg = CutPathConfig(free_roll=False)
    drawing, surface = line_on_plate((0.4, -0.05, PLATE_Z), (0.5, 0.05, PLATE_Z))
    path = plan_cut(build_cut_path(drawing, surface, cfg), kin, PANDA_Q_READY, cfg)
    br = path.branches[0]
    assert br.feasible
    T = kin.fk_batch(br.q)
    np.testing.assert_allclose(T[:, :3, :3], br.poses[:, :3, :3], atol=0.002)


def test_an_unreachable_line_is_one_gap_with_its_reason(kin):
    drawing, surface = line_on_plate((0.45, -0.1, PLATE_Z), (0.45, 0.1, PLATE_Z))
    far = [3.0, 0.0, 0.0]
    drawing = Cloud(drawing.xyz + np.float32(far), drawing.rgb, drawing.origin + np.float32(far))
    surface = Cloud(surface.xyz + np.float32(far), surface.rgb, surface.origin + np.float32(far))
    path = plan_cut(build_cut_path(drawing, surface, CFG), kin, PANDA_Q_READY, CFG)
    assert path.branches == [] and not path.feasible and path.cut_fraction == 0.0
    assert [g.reason for g in path.gaps] == ["out of reach"]
    assert path.gaps[0].length_m == pytest.approx(path.drawing_length_m, rel=1e-6)
    assert path.drawing_length_m == pytest.approx(0.2, abs=0.02)


def test_branched_scene_plans_every_branch(branched, kin):
    t0 = time.perf_counter()
    path = build_cut_path(branched.gt_points, None, CFG, viewpoint=[0.45, 0.0, 1.0])
    t1 = time.perf_counter()
    plan_cut(path, kin, PANDA_Q_READY, CFG)
    t2 = time.perf_counter()
    assert len(path.branches) >= 2
    ends = {e.split("+")[0] for b in path.branches for e in (b.start, b.end)}
    assert len(ends & {f"E{i}" for i in range(4)}) >= 2  # the two lines are cut through their crossings
    for b in path.branches:  # every run is a joint path through all its poses
        assert b.feasibility == ["ok"] * len(b) and np.isfinite(b.q).all()
        assert np.abs(np.diff(b.q, axis=0)).max() <= CFG.max_joint_jump_rad + 2.0 * np.radians(40)
    assert all(g.reason in GAP_REASONS + ("too short",) for g in path.gaps)
    # nothing is dropped in silence: what is not cut is a reported gap
    cut = sum(b.length_m for b in path.branches)
    uncut = sum(g.length_m for g in path.gaps)
    assert cut + uncut == pytest.approx(path.drawing_length_m, rel=0.03)
    assert path.cut_fraction >= 0.7
    print(f"branched_cylinder: geometry {1e3 * (t1 - t0):.0f} ms, IK+trajectories {1e3 * (t2 - t1):.0f} ms, "
          f"{sum(len(b) for b in path.branches)} poses")


# ---------------------------------------------------------------------------- files


def test_write_and_read_back(kin, tmp_path):
    drawing, surface = line_on_plate((0.45, -0.05, PLATE_Z), (0.45, 0.05, PLATE_Z))
    path = plan_cut(build_cut_path(drawing, surface, CFG), kin, PANDA_Q_READY, CFG)
    far = build_cut_path(Cloud(drawing.xyz + np.float32([3, 0, 0]), drawing.rgb, drawing.origin), None, CFG)
    plan_cut(far, kin, PANDA_Q_READY, CFG)
    path.gaps += far.gaps  # one cut, one stretch out of reach
    path.drawing_length_m += far.drawing_length_m
    jpath, cpath = path.write(tmp_path / "out")
    d = json.loads(jpath.read_text())  # strict JSON
    assert d["schema_version"] == 2 and len(d["branches"]) == 1
    assert [g["reason"] for g in d["gaps"]] == ["out of reach"]
    assert d["cut_fraction"] == pytest.approx(0.5, abs=0.05)
    back = CutPath.read(tmp_path / "out")
    for a, b in zip(path.branches, back.branches):
        np.testing.assert_allclose(b.points, a.points)
        np.testing.assert_allclose(b.poses, a.poses)
        np.testing.assert_allclose(b.q, a.q, equal_nan=True)
        assert b.feasibility == a.feasibility and b.start == a.start and b.feasible == a.feasible
    assert back.cut_fraction == pytest.approx(path.cut_fraction, abs=1e-4)
    np.testing.assert_allclose(back.gaps[0].points, path.gaps[0].points)
    with cpath.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == sum(len(b) for b in path.branches)
    r = rows[0]
    assert r["branch"] == "0" and r["index"] == "0" and r["feasible"] == "1" and r["reason"] == "ok"
    quat = np.array([float(r[k]) for k in ("qx", "qy", "qz", "qw")])
    assert abs(np.linalg.norm(quat) - 1) < 1e-6
    np.testing.assert_allclose([float(r[k]) for k in ("tip_x", "tip_y", "tip_z")], path.branches[0].poses[0, :3, 3],
                               atol=1e-6)
    assert all(r["reason"] == "ok" and r["q1"] != "" for r in rows)


# ---------------------------------------------------------------------------- bad input


def test_invalid_inputs_raise(kin):
    good = plate()[:100]
    with pytest.raises(ValueError, match="drawing is empty"):
        build_cut_path(np.zeros((0, 3)), None, CFG, viewpoint=EYE)
    with pytest.raises(ValueError, match="drawing.xyz contains NaN"):
        build_cut_path(cloud(np.vstack([good, [np.nan, 0, 0]])), None, CFG)
    with pytest.raises(ValueError, match=r"drawing must have shape \(N, 3\)"):
        build_cut_path(np.zeros((5, 2)), None, CFG, viewpoint=EYE)
    with pytest.raises(ValueError, match="drawing.origin has no finite"):
        build_cut_path(good, None, CFG)  # no sensor positions and no viewpoint: normals unoriented
    with pytest.raises(ValueError, match="surface is empty"):
        build_cut_path(good, np.zeros((0, 3)), CFG, viewpoint=EYE)
    with pytest.raises(ValueError, match="viewpoint"):
        build_cut_path(good, None, CFG, viewpoint=[0.0, 1.0])
    with pytest.raises(ValueError, match="voxel_m"):
        drawing_graph(good, voxel_m=0.0)
    with pytest.raises(ValueError, match="min_branch_m"):
        drawing_graph(good, min_branch_m=-1.0)
    with pytest.raises(ValueError, match="spacing_m"):
        smooth_resample(good[:10], 0.0, 0.001)
    with pytest.raises(ValueError, match="spacing_m"):
        CutPathConfig(spacing_m=0.0)
    with pytest.raises(ValueError, match="travel_speed_mps"):
        CutPathConfig(travel_speed_mps=-0.005)
    with pytest.raises(ValueError, match="standoff_m"):
        CutPathConfig(standoff_m=float("nan"))
    with pytest.raises(ValueError, match="rpy_deg"):
        TorchConfig(rpy_deg=(0.0, 400.0, 0.0))
    with pytest.raises(ValueError, match="normals must match"):
        torch_poses(good[:5], np.tile([0, 0, 1.0], (4, 1)), 0.01)
    drawing, surface = line_on_plate((0.45, -0.05, PLATE_Z), (0.45, 0.05, PLATE_Z))
    path = build_cut_path(drawing, surface, CFG)
    with pytest.raises(ValueError, match="q_start"):
        plan_cut(path, kin, np.zeros(6), CFG)
    with pytest.raises(ValueError, match="q_start"):
        plan_cut(path, kin, np.full(7, 3.5), CFG)
    with pytest.raises(ValueError, match="max_vel"):
        plan_cut(path, kin, PANDA_Q_READY, CFG, max_vel=np.zeros(7))
    with pytest.raises(ValueError, match="is_free"):
        plan_cut(path, kin, PANDA_Q_READY, CFG, is_free=lambda Q: np.ones(3, bool))
