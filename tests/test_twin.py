"""The pybullet twin: config validation, the D435 depth model, the simulated camera (noise, frames,
grazing, colour) and arm (execution, refusal, stop, camera pose). Small scenes built here from
trimesh primitives; the whole module runs in well under a minute."""

from __future__ import annotations

import ast
import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import pybullet as p
import pytest
import trimesh
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from drivers.interfaces import Arm, DeviceError, JointTrajectory, RGBDCamera, RGBDFrame, TrajectoryError
from planners.clouds import color_mask, frame_to_base_cloud, rgb_to_hsv
from sim.config import D435Config, HandEyeConfig, TwinConfig
from sim.d435 import apply_depth_noise, depth_focal_px, depth_rms, grazing_mask, intrinsics_for
from sim.scenes.model import Scene
from sim.twin import Twin

ROOT = Path(__file__).resolve().parents[1]
HOME_Q = np.array(TwinConfig().home_q)


# ----------------------------------------------------------------------------- helpers
def make_scene(object_mesh: trimesh.Trimesh, paint_mesh: trimesh.Trimesh | None = None, **kw) -> Scene:
    paint = paint_mesh if paint_mesh is not None else trimesh.Trimesh()
    return Scene(name="test", category=None, object_mesh=object_mesh, paint_mesh=paint,
                 drawing_polylines=[], drawing_width=0.02, gt_points=np.zeros((0, 3), np.float32),
                 extremities=np.zeros((0, 3)), **kw)


def box(extents, center, yaw_deg: float = 0.0) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = center
    return trimesh.creation.box(extents=extents, transform=T)


def look_pose(position, forward, down_hint=(0.0, 0.0, -1.0)) -> np.ndarray:
    """T_base_cam at ``position`` with optical z along ``forward`` and image y (down) as close to
    ``down_hint`` as possible."""
    z = np.asarray(forward, float) / np.linalg.norm(forward)
    y = np.asarray(down_hint, float) - np.dot(down_hint, z) * z
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([np.cross(y, z), y, z])
    T[:3, 3] = position
    return T


def quad(center, normal, size: float) -> trimesh.Trimesh:
    """A single square (two triangles) facing ``normal``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    c = np.asarray(center, float)
    h = size / 2
    V = np.array([c - h * a - h * b, c + h * a - h * b, c + h * a + h * b, c - h * a + h * b])
    m = trimesh.Trimesh(V, [[0, 1, 2], [0, 2, 3]], process=False)
    if np.dot(m.face_normals[0], n) < 0:
        m.faces = m.faces[:, ::-1]
    return m


def smooth_trajectory(q0, q1, duration: float, rate: float = 100.0) -> JointTrajectory:
    """Straight line in joint space with a quintic (minimum-jerk) time law."""
    t = np.linspace(0.0, duration, int(round(duration * rate)) + 1)
    s = t / duration
    s = 10 * s**3 - 15 * s**4 + 6 * s**5
    return JointTrajectory(times=t, positions=np.asarray(q0) + s[:, None] * (np.asarray(q1) - np.asarray(q0)))


def base_points(depth: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H*W, 3) base-frame points of every pixel (NaN where no depth) and their validity."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    z = depth.astype(np.float64)
    P = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1).reshape(-1, 3)
    X = P @ T_base_cam[:3, :3].T + T_base_cam[:3, 3]
    return X, np.isfinite(z).ravel()


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def wall_twin():
    """A large wall whose face is the plane x = 2.0 (normal -x), far from the robot."""
    with Twin(make_scene(box([0.1, 3.0, 3.0], [2.05, 0.0, 1.5]))) as twin:
        yield twin


@pytest.fixture(scope="module")
def step_twin():
    with Twin(make_scene(box([0.1, 0.1, 0.1], [-0.6, 0.6, 0.05])), TwinConfig(execution="step")) as twin:
        yield twin


# ----------------------------------------------------------------------------- config
def test_config_defaults_and_validation():
    cfg = TwinConfig()
    assert (cfg.camera.width, cfg.camera.height) == (848, 480)
    assert cfg.execution == "step" and cfg.sim_hz == 240 and len(cfg.home_q) == 7
    with pytest.raises(ValidationError):
        D435Config(bogus=1)
    with pytest.raises(ValidationError):
        D435Config(baseline_m=float("nan"))
    with pytest.raises(ValidationError):
        D435Config(max_range_m=float("inf"))
    with pytest.raises(ValidationError):
        D435Config(min_range_m=1.5, max_range_m=1.0)
    with pytest.raises(ValidationError):
        D435Config(width=1280, height=720)
    with pytest.raises(ValidationError):  # 640x480 with the 16:9 FOV gives non-square pixels
        D435Config(width=640, height=480)
    small = D435Config(width=640, height=480, hfov_deg=55.0)
    assert abs(intrinsics_for(small).fx / intrinsics_for(small).fy - 1) < 0.05
    with pytest.raises(ValidationError):
        HandEyeConfig(xyz=[0.0, 0.0])
    with pytest.raises(ValidationError):
        TwinConfig(home_q=[0.0] * 6)
    with pytest.raises(ValidationError):
        TwinConfig(home_q=[0.0] * 6 + [float("nan")])
    with pytest.raises(ValidationError):
        TwinConfig(execution="fly")
    with pytest.raises(ValidationError):
        TwinConfig(camera={"width": 848, "extra": 1})
    T = HandEyeConfig(rpy_deg=[0, 0, 90]).T_flange_cam()
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0]) and np.allclose(T[:3, 3], [0.07, 0.0, 0.05])


# ----------------------------------------------------------------------------- d435 model (pure numpy)
def test_d435_intrinsics_and_noise_formula():
    cfg = D435Config()
    K = intrinsics_for(cfg)
    assert (K.width, K.height, K.cx, K.cy) == (848, 480, 423.5, 239.5)
    assert K.fx == pytest.approx(424 / math.tan(math.radians(34.7)))
    assert K.fy == pytest.approx(240 / math.tan(math.radians(21.25)))
    f = depth_focal_px(cfg)
    assert f == pytest.approx(424 / math.tan(math.radians(43.5)))
    assert depth_rms(1.0, cfg) == pytest.approx(0.08 / (f * 0.05))  # ~3.6 mm at 1 m
    assert depth_rms(2.0, cfg) == pytest.approx(4 * depth_rms(1.0, cfg))
    depth = np.full((100, 100), 1.0, np.float32)
    depth[0, 0] = np.nan
    noisy = apply_depth_noise(depth, cfg, np.random.default_rng(1))
    assert noisy.dtype == np.float32 and np.isnan(noisy[0, 0])
    assert np.nanstd(noisy - depth) == pytest.approx(depth_rms(1.0, cfg), rel=0.05)
    assert np.array_equal(apply_depth_noise(depth, D435Config(noise=False), np.random.default_rng(1)), depth,
                          equal_nan=True)


def _plane_depth(K: np.ndarray, shape, normal_cam, distance: float) -> np.ndarray:
    """Analytic depth image of the plane n.X = distance (optical frame), NaN where not in front."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w]
    r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    with np.errstate(divide="ignore"):
        z = distance / (r @ np.asarray(normal_cam, float))
    return np.where(z > 0, z, np.nan).astype(np.float32)


def test_grazing_mask_on_analytic_planes():
    K = intrinsics_for(D435Config()).matrix()
    facing = _plane_depth(K, (480, 848), [0, 0, 1], 1.0)
    assert grazing_mask(facing, K, 80.0).mean() == 0.0
    # tilted 60 deg about the image x axis: incidence 60 +- 21 deg (vertical FOV), the rows beyond 80 go
    tilt = math.radians(60)
    tilted = _plane_depth(K, (480, 848), [0, -math.sin(tilt), math.cos(tilt)], 0.8)
    m = grazing_mask(tilted, K, 80.0)
    v, u = np.mgrid[0:480, 0:848]
    r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    n = np.array([0, -math.sin(tilt), math.cos(tilt)])
    inc = np.degrees(np.arccos(np.abs(r @ n) / np.linalg.norm(r, axis=-1)))
    clear = np.abs(inc - 80.0) > 0.5
    assert np.array_equal(m[clear], inc[clear] > 80.0)
    # a depth step: a thin band along the edge, nothing else
    step = facing.copy()
    step[:, 424:] = 1.3
    ms = grazing_mask(step, K, 80.0)
    assert ms[:, 423:425].all() and ms[:, :423].sum() == 0 and ms[:, 425:].sum() == 0
    # no return next to a pixel invalidates it, the hole itself is invalid
    hole = facing.copy()
    hole[200:210, 300:310] = np.nan
    mh = grazing_mask(hole, K, 80.0)
    assert mh[199:211, 299:311].sum() == 12 * 12 - 4 and mh.sum() == 12 * 12 - 4


# ----------------------------------------------------------------------------- camera
def test_protocols_and_frame_contract(wall_twin):
    assert isinstance(wall_twin.arm, Arm)
    assert isinstance(wall_twin.camera, RGBDCamera)
    frame = wall_twin.camera.capture()
    assert isinstance(frame, RGBDFrame)
    assert frame.color.shape == (480, 848, 3) and frame.color.dtype == np.uint8
    assert frame.depth.shape == (480, 848) and frame.depth.dtype == np.float32
    assert frame.intrinsics == wall_twin.camera.intrinsics
    d = frame.depth[np.isfinite(frame.depth)]
    assert d.size > 0 and d.min() >= 0.2 - 0.01 and d.max() <= 2.0 + 0.05


@pytest.mark.parametrize("distance", [0.5, 1.0])
def test_depth_noise_matches_datasheet(wall_twin, distance):
    T = look_pose([2.0 - distance, 0.0, 1.2], [1.0, 0.0, 0.0])
    frame = wall_twin.camera.capture_at(T)
    truth = wall_twin.camera.last_truth
    both = np.isfinite(frame.depth) & np.isfinite(truth)
    assert both.mean() > 0.99
    assert np.allclose(truth[both], distance, atol=1e-4)  # the wall is square to the camera
    err = (frame.depth - truth)[both].astype(np.float64)
    expected = depth_rms(distance, wall_twin.config.camera)
    rms = math.sqrt(np.mean(err**2))
    assert abs(rms / expected - 1.0) < 0.10, (rms, expected)
    assert abs(err.mean()) < 0.05 * expected
    # render_truth does not draw from the noise generator and matches last_truth
    assert np.array_equal(wall_twin.render_truth(T), truth, equal_nan=True)


def test_noise_is_seeded_and_advances():
    scene = make_scene(box([0.1, 3.0, 3.0], [2.05, 0.0, 1.5]))
    T = look_pose([1.2, 0.0, 1.2], [1.0, 0.0, 0.0])
    with Twin(scene, TwinConfig(camera=D435Config(seed=7))) as a, Twin(scene, TwinConfig(camera=D435Config(seed=7))) as b:
        assert a.client != b.client
        fa1, fb1 = a.camera.capture_at(T), b.camera.capture_at(T)
        assert np.array_equal(fa1.depth, fb1.depth, equal_nan=True)
        fa2 = a.camera.capture_at(T)
        assert not np.array_equal(fa1.depth, fa2.depth, equal_nan=True)
        assert fa2.timestamp >= fa1.timestamp


def test_frame_cloud_lands_on_the_box():
    """(b) the cloud of a frame taken from the arm's own pose lies on the box and the floor."""
    extents, center, yaw = np.array([0.22, 0.16, 0.12]), np.array([0.72, 0.07, 0.06]), 20.0
    q = HOME_Q + np.array([0.1, 0.05, 0.0, 0.05, 0.0, 0.0, 0.0])
    with Twin(make_scene(box(extents, center, yaw))) as twin:
        twin.arm.reset(q)
        assert np.allclose(twin.arm.joint_positions(), q)
        frame = twin.camera.capture()
        T = twin.arm.camera_pose()
        K = frame.intrinsics.matrix()
        cloud = frame_to_base_cloud(frame.color, frame.depth, K, T)
        X = cloud.xyz.astype(np.float64)
        assert len(X) > 0.8 * frame.depth.size
        cfg = twin.config.camera
        zc = (X - T[:3, 3]) @ T[:3, 2]  # depth along the optical axis
        sigma = depth_rms(zc, cfg)
        # distance to the box surface (box frame) and to the floor
        R = Rotation.from_euler("z", yaw, degrees=True).as_matrix()
        L = (X - center) @ R
        qd = np.abs(L) - extents / 2
        d_box = np.abs(np.linalg.norm(np.maximum(qd, 0), axis=1) + np.minimum(qd.max(axis=1), 0))
        dist = np.minimum(d_box, np.abs(X[:, 2]))
        # noise is along the ray; the ray is at most ~40 deg off the optical axis
        tol = 1.3 * sigma
        assert np.mean(dist < 3 * tol) > 0.99
        assert np.all(dist < 6 * tol + 1e-3)
        above = X[:, 2] > 3 * sigma.max() + 1e-3
        assert above.sum() > 20000  # the box is well in view
        margin = 3 * 1.3 * sigma.max() + 1e-3
        assert np.all(np.abs(L[above, :2]) <= extents[:2] / 2 + margin)
        assert np.all(X[above, 2] <= extents[2] + margin)


def _quad_pixels(raw_depth, K, T, center, normal, size):
    X, ok = base_points(raw_depth, K, T)
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    rel = X - center
    on = ok & (np.abs(rel @ n) < 2e-3) & (np.linalg.norm(rel, axis=1) < size / 2 * 1.5)
    return on.reshape(raw_depth.shape)


@pytest.mark.parametrize("incidence_deg, expect", [(85.0, "mostly_nan"), (0.0, "valid")])
def test_grazing_plane(incidence_deg, expect):
    center, size = np.array([2.8, 0.0, 1.5]), 1.0
    view = np.array([1.0, 0.0, 0.0])  # camera looks along +x from 1 m in front of the quad
    a = math.radians(incidence_deg)
    normal = -np.array([math.cos(a), 0.0, math.sin(a)])  # tilted about the base y axis
    with Twin(make_scene(quad(center, normal, size))) as twin:
        T = look_pose(center - view, view)
        _, raw = twin.camera.render(T)
        on = _quad_pixels(raw, twin.camera.K, T, center, normal, size)
        assert on.sum() > 2000
        frame = twin.camera.capture_at(T)
        nan_frac = np.isnan(frame.depth[on]).mean()
        if expect == "mostly_nan":
            assert nan_frac > 0.9, nan_frac
        else:
            assert nan_frac < 0.02, nan_frac


def test_single_sided_sheet_is_seen_from_both_sides():
    sheet = quad([2.8, 0.0, 1.5], [-1.0, 0.0, 0.0], 1.0)
    with Twin(make_scene(sheet)) as twin:
        assert twin.double_sided
        front = twin.camera.render(look_pose([1.8, 0.0, 1.5], [1.0, 0.0, 0.0]))[1]
        back = twin.camera.render(look_pose([3.8, 0.0, 1.5], [-1.0, 0.0, 0.0]))[1]
        assert np.isfinite(front).mean() > 0.5 and np.isfinite(back).mean() > 0.5
    with Twin(make_scene(box([0.1, 0.1, 0.1], [0.7, 0.0, 0.05]))) as twin:
        assert not twin.double_sided


def test_paint_is_red_where_it_should_be():
    top = 0.10
    grey = box([0.4, 0.4, top], [1.5, 0.8, top / 2])
    p_center, p_size = np.array([1.55, 0.82, top + 0.0005]), 0.06
    paint = quad(p_center, [0, 0, 1], p_size)
    with Twin(make_scene(grey, paint)) as twin:
        T = look_pose([1.5, 0.8, top + 0.6], [0.0, 0.0, -1.0], down_hint=(-1.0, 0.0, 0.0))
        frame = twin.camera.capture_at(T)
        K = twin.camera.K
        corners = p_center + np.array([[sx, sy, 0.0] for sx in (-1, 1) for sy in (-1, 1)]) * p_size / 2
        c_cam = (corners - T[:3, 3]) @ T[:3, :3]
        uv = c_cam[:, :2] / c_cam[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        u0, v0 = np.ceil(uv.min(axis=0) + 3).astype(int)
        u1, v1 = np.floor(uv.max(axis=0) - 3).astype(int)
        inside = frame.color[v0:v1 + 1, u0:u1 + 1].reshape(-1, 3)
        hsv = rgb_to_hsv(inside)
        hue_dist = np.minimum(hsv[:, 0], 360.0 - hsv[:, 0])
        assert len(inside) > 500
        assert np.all(hue_dist < 10.0) and np.all(hsv[:, 1] > 0.8) and np.all(hsv[:, 2] > 0.4)
        # the red area of the image is the square's projected area (no red elsewhere)
        red = color_mask(frame.color.reshape(-1, 3), 0.0, 15.0, 0.6, 0.2)
        area = (uv[:, 0].max() - uv[:, 0].min()) * (uv[:, 1].max() - uv[:, 1].min())
        assert abs(red.sum() / area - 1.0) < 0.1
        # the grey box around it is not red
        ring = frame.color[v1 + 20:v1 + 60, u0:u1 + 1].reshape(-1, 3)
        assert rgb_to_hsv(ring)[:, 1].max() < 0.2
        # and the red pixels land on the painted square in the base frame
        cloud = frame_to_base_cloud(frame.color, frame.depth, K, T)
        red_xyz = cloud.xyz[color_mask(cloud.rgb, 0.0, 15.0, 0.6, 0.2)]
        assert len(red_xyz) > 500
        assert np.all(np.abs(red_xyz[:, :2] - p_center[:2]) <= p_size / 2 + 2e-3)
        assert np.all(np.abs(red_xyz[:, 2] - p_center[2]) < 5 * depth_rms(0.6, twin.config.camera))


# ----------------------------------------------------------------------------- arm
def test_arm_model(step_twin):
    m = step_twin.arm.model
    assert m.base_link == "panda_link0" and m.flange_link == "panda_hand"
    assert m.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
    assert os.path.exists(m.urdf_path)
    assert np.allclose(m.lower[[3, 5]], [-3.1416, -0.0873]) and np.allclose(m.upper[[3, 5]], [0.0, 3.8223])
    assert np.allclose(m.max_velocity, [2.175] * 4 + [2.61] * 3)
    assert np.allclose(m.max_acceleration, [15, 7.5, 10, 12.5, 15, 20, 20])
    assert np.allclose(m.max_jerk, [7500, 3750, 5000, 6250, 7500, 10000, 10000])
    assert np.allclose(m.T_flange_cam, step_twin.config.hand_eye.T_flange_cam())


def test_execute_follows_smooth_trajectory(step_twin):
    arm = step_twin.arm
    arm.reset(HOME_Q)
    q1 = HOME_Q + np.array([0.4, 0.3, -0.3, 0.4, 0.5, -0.3, 0.6])
    err = arm.execute(smooth_trajectory(HOME_Q, q1, 2.0))
    assert 0.0 < err < 0.02
    assert np.allclose(arm.joint_positions(), q1, atol=2e-3)
    # with explicit velocities too, and back
    tr = smooth_trajectory(q1, HOME_Q, 1.5)
    tr.velocities = np.gradient(tr.positions, tr.times, axis=0)
    assert arm.execute(tr) < 0.02
    assert np.allclose(arm.joint_positions(), HOME_Q, atol=2e-3)


def test_execute_refuses_bad_trajectories_without_moving(step_twin):
    arm = step_twin.arm
    arm.reset(HOME_Q)
    q_before = arm.joint_positions()
    pose_before = arm.camera_pose()
    good = smooth_trajectory(HOME_Q, HOME_Q + 0.2, 1.0)

    def variant(**kw) -> JointTrajectory:
        d = dict(times=good.times.copy(), positions=good.positions.copy(), velocities=None)
        d.update(kw)
        return JointTrajectory(**d)

    nan = good.positions.copy()
    nan[50, 2] = np.nan
    beyond = good.positions.copy()
    beyond[-10:, 3] = 0.05  # joint 4 upper limit is 0
    times_back = good.times.copy()
    times_back[10] = times_back[9]
    bad = [
        variant(positions=nan),
        variant(positions=beyond),
        variant(times=times_back),
        variant(times=good.times + 0.1),
        variant(positions=good.positions[:, :6]),
        variant(positions=good.positions + 0.3),  # starts away from the current joints
        variant(times=good.times * 0.05),  # far too fast
        variant(velocities=np.full_like(good.positions, np.inf)),
    ]
    for tr in bad:
        with pytest.raises(TrajectoryError):
            arm.execute(tr)
        assert np.array_equal(arm.joint_positions(), q_before)
    assert np.array_equal(arm.camera_pose(), pose_before)


def test_stop_aborts_execution(step_twin):
    arm = step_twin.arm
    arm.reset(HOME_Q)
    q1 = HOME_Q + np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    tr = smooth_trajectory(HOME_Q, q1, 60.0, rate=20.0)  # ~14k simulation steps
    errors: list[BaseException] = []
    th = threading.Thread(target=lambda: errors.append(_catch(arm.execute, tr)))
    th.start()
    deadline = time.monotonic() + 60.0  # a liveness bound: the motion starts at once
    while np.max(np.abs(arm.joint_positions() - HOME_Q)) < 1e-4:
        assert time.monotonic() < deadline and th.is_alive(), "the arm never started moving"
        time.sleep(0.001)
    arm.stop()
    th.join(60.0)  # a liveness bound
    assert not th.is_alive()
    assert isinstance(errors[0], TrajectoryError)
    assert np.max(np.abs(arm.joint_positions() - q1)) > 0.1  # stopped well before the end
    # the arm still works afterwards
    q = arm.joint_positions()
    assert arm.execute(smooth_trajectory(q, HOME_Q, 1.0)) < 0.02


def _catch(fn, *args):
    try:
        fn(*args)
    except BaseException as e:  # noqa: BLE001 - handed to the test thread
        return e
    return None


def test_teleport_mode():
    with Twin(make_scene(box([0.1, 0.1, 0.1], [-0.6, 0.6, 0.05])), TwinConfig(execution="teleport")) as twin:
        q1 = HOME_Q + 0.2
        assert twin.arm.execute(smooth_trajectory(HOME_Q, q1, 1.0)) == 0.0
        assert np.allclose(twin.arm.joint_positions(), q1)
        with pytest.raises(ValueError):
            twin.arm.reset(HOME_Q + np.array([0, 0, 0, 5.0, 0, 0, 0]))


def test_camera_pose_agrees_with_independent_kinematics(step_twin):
    import pinocchio as pin

    arm = step_twin.arm
    pmodel = pin.buildModelFromUrdf(arm.model.urdf_path)
    pdata = pmodel.createData()
    fid = pmodel.getFrameId(arm.model.flange_link)
    rng = np.random.default_rng(3)
    T_fc = step_twin.config.hand_eye.T_flange_cam()
    for _ in range(5):
        q = arm.model.lower + rng.uniform(0.1, 0.9, 7) * (arm.model.upper - arm.model.lower)
        arm.reset(q)
        T = arm.camera_pose()
        # pybullet's link frame of panda_hand (worldLinkFramePosition/Orientation, indices 4 and 5)
        st = p.getLinkState(step_twin.robot_id, arm.flange_index, computeForwardKinematics=True,
                            physicsClientId=step_twin.client)
        T_link = np.eye(4)
        T_link[:3, :3] = Rotation.from_quat(st[5]).as_matrix()
        T_link[:3, 3] = st[4]
        assert np.allclose(T, T_link @ T_fc, atol=1e-9)
        # and Pinocchio's FK of the same URDF (joint order of the URDF = panda_joint1..7, then fingers)
        qp = np.concatenate([q, np.full(pmodel.nq - 7, 0.02)])
        pin.framesForwardKinematics(pmodel, pdata, qp)
        T_pin = pdata.oMf[fid].homogeneous @ T_fc
        assert np.allclose(T, T_pin, atol=1e-5)
    # home looks forward-down at the workspace in front of the robot
    arm.reset(HOME_Q)
    T = arm.camera_pose()
    assert T[2, 2] < -0.7 and T[0, 2] > 0.3


def test_close_releases_everything():
    twin = Twin(make_scene(box([0.1, 0.1, 0.1], [0.7, 0.0, 0.05]), box([0.02, 0.02, 0.002], [0.7, 0.0, 0.101])))
    tmp = twin._tmpdir
    assert os.path.isdir(tmp) and len(os.listdir(tmp)) >= 2
    client = twin.client
    twin.close()
    twin.close()  # idempotent
    assert not os.path.exists(tmp)
    assert not p.isConnected(physicsClientId=client)
    with pytest.raises(DeviceError):
        twin.arm.joint_positions()
    with pytest.raises(DeviceError):
        twin.camera.capture()


# ----------------------------------------------------------------------------- import rule
def test_sim_and_drivers_never_import_planners_or_cellctl():
    for folder in ("sim", "drivers"):
        for path in (ROOT / folder).rglob("*.py"):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    names = [node.module]
                for name in names:
                    assert name.split(".")[0] not in ("planners", "cellctl"), f"{path} imports {name}"


@pytest.mark.parametrize("execution", ["step", "teleport"])
def test_contacts_with_the_scene_are_recorded_per_motion(execution):
    """The twin's own contact query, independent of the planner's collision model: a swing through a
    block in front of the robot is reported with the link that hit it; a free motion reports nothing."""
    scene = make_scene(box([0.2, 0.6, 0.4], [0.55, 0.0, 0.2]))
    with Twin(scene, TwinConfig(execution=execution)) as twin:
        arm = twin.arm
        q0 = arm.joint_positions()
        free = q0.copy()
        free[0] += 0.3
        arm.execute(smooth_trajectory(q0, free, 1.0))
        assert arm.last_motion_contacts == []
        into = free.copy()
        into[0], into[1], into[3] = 0.0, 1.2, -1.0  # reach forward and down, through the block
        arm.execute(smooth_trajectory(free, into, 2.0))
        hits = arm.last_motion_contacts
        assert hits and {h["body"] for h in hits} <= {"object", "paint", "floor"}
        assert any(h["body"] == "object" and h["link"].startswith("panda_") for h in hits), hits
        assert all(h["distance_m"] < 0.05 for h in hits)


# ----------------------------------------------------------------------------- the tool
def test_the_torch_on_the_hand_has_contacts_of_its_own_and_is_never_drawn():
    """The twin's torch (TwinConfig.tool) is what lets the dry run see the nozzle touch the metal:
    a tip 3 mm into a plate is a contact of "tool", 5 mm above it none; the camera's picture is
    the same with or without it."""
    from sim.config import TwinToolConfig
    from planners.config import CutPathConfig
    from planners.cutpath import torch_kinematics
    from planners.motion.ik_batch import solve_axis_ik_batch

    t = CutPathConfig().torch
    tool = TwinToolConfig(xyz=list(t.xyz_m), rpy_deg=list(t.rpy_deg), radius_m=t.radius_m, length_m=t.length_m,
                          nozzle_radius_m=t.nozzle_radius_m, nozzle_length_m=t.nozzle_length_m)
    plate = make_scene(box([0.3, 0.3, 0.1], [0.5, 0.0, 0.15]))  # top face at z = 0.2
    with Twin(plate, TwinConfig(execution="teleport", tool=tool)) as twin, \
            Twin(plate, TwinConfig(execution="teleport")) as bare:
        pose = look_pose([0.5, 0.0, 0.55], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
        assert np.array_equal(twin.camera.render(pose)[0], bare.camera.render(pose)[0])
        kin = torch_kinematics(twin.arm.model.urdf_path, CutPathConfig())
        seen = {}
        for depth in (0.005, -0.003):
            Q, ok = solve_axis_ik_batch(kin, np.array([[0.5, 0.0, 0.2 + depth]]), np.array([[0.0, 0.0, -1.0]]),
                                        HOME_Q[None])
            assert ok[0]
            for name, tw in (("tool", twin), ("bare", bare)):
                tw.arm.reset(HOME_Q)
                tw.arm.execute(smooth_trajectory(HOME_Q, Q[0], 2.0))
                seen[name, depth] = {(c["link"], c["body"]) for c in tw.arm.last_motion_contacts}
        assert seen["tool", 0.005] == set() and seen["bare", -0.003] == set()
        assert seen["tool", -0.003] == {("tool", "object")}
    with pytest.raises(ValidationError):
        TwinToolConfig(xyz=[0, 0, 0.2], radius_m=0.01, length_m=0.1, nozzle_length_m=0.2)
