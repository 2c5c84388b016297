"""The D435 adapter (drivers/realsense) without a camera: .bag fixtures written at test time from twin
frames in librealsense's rosbag layout (pure-Python rosbags), played back by Open3D's real
RSBagReader through our RGBDCamera adapter. No mocks: where no camera exists (here) the live sensor
must say so quickly."""

from __future__ import annotations

import ast
import time
from pathlib import Path

import numpy as np
import pytest

from cellctl.cli import main as cellctl_main
from configs import CONFIG_DIR
from drivers.interfaces import DeviceError, RGBDCamera
from drivers.realsense import (CameraConfigError, RealSenseBag, RealSenseCamera, RealSenseConfig, check_devices,
                               list_devices, load_realsense_config, open_camera)
from drivers.realsense.bag_writer import BagWriter, write_bag
from planners.clouds import frame_to_base_cloud
from sim.config import D435Config, TwinConfig
from sim.scenes import load_scene
from sim.twin import Twin

BOUND_S = 5.0  # every failure must be reported within this


@pytest.fixture(scope="module")
def twin_frames():
    """Three noise-free twin frames from three arm poses, with their camera poses."""
    cfg = TwinConfig(camera=D435Config(noise=False), execution="teleport")
    out = []
    with Twin(load_scene("smooth_cylinder"), cfg) as twin:
        for dq in (0.0, 0.12, -0.12):
            q = np.array(cfg.home_q)
            q[0] += dq
            twin.arm.reset(q)
            out.append((twin.camera.capture(), twin.arm.camera_pose()))
    assert all(np.isfinite(f.depth).sum() > 10_000 for f, _ in out), "the twin must see the object"
    return out


@pytest.fixture(scope="module")
def twin_bag(twin_frames, tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("bags") / "twin.bag", [f for f, _ in twin_frames], serial="123456789012")


def _play_all(path) -> tuple[list, DeviceError]:
    """All frames of a bag, and the DeviceError that ends them (asserted to come within BOUND_S)."""
    frames = []
    t0 = time.monotonic()
    with RealSenseBag(path) as cam:
        with pytest.raises(DeviceError) as err:
            for _ in range(100):
                frames.append(cam.capture())
    assert time.monotonic() - t0 < BOUND_S + 0.4 * len(frames)
    return frames, err.value


# ----------------------------------------------------------------------------- playback contract
def test_bag_plays_back_as_an_rgbd_camera_with_the_bags_own_metadata(twin_frames, twin_bag):
    ref = twin_frames[0][0]
    with RealSenseBag(twin_bag) as cam:
        assert isinstance(cam, RGBDCamera)
        K, Kt = cam.intrinsics, ref.intrinsics
        assert (K.width, K.height) == (Kt.width, Kt.height) == (848, 480)
        np.testing.assert_allclose([K.fx, K.fy, K.cx, K.cy], [Kt.fx, Kt.fy, Kt.cx, Kt.cy], atol=1e-3)
        assert cam.depth_scale == pytest.approx(1000.0, rel=1e-6)  # the bag's Depth_Units option, 1 mm
        assert cam.metadata.serial_number == "123456789012"
        assert cam.frames_expected == 3
        frame = cam.capture()
    assert frame.color.shape == (480, 848, 3) and frame.color.dtype == np.uint8
    assert frame.depth.shape == (480, 848) and frame.depth.dtype == np.float32
    assert frame.intrinsics == K
    finite = np.isfinite(frame.depth)
    assert np.all(frame.depth[finite] > 0), "0 (no return) must become NaN, never 0 m"


def test_cloud_from_the_bag_matches_the_twins_cloud_within_the_depth_unit(twin_frames, twin_bag):
    played, end = _play_all(twin_bag)
    assert len(played) == len(twin_frames)
    assert "end of bag" in str(end)
    for (ref, T_base_cam), got in zip(twin_frames, played):
        np.testing.assert_array_equal(got.color, ref.color)
        np.testing.assert_array_equal(np.isnan(got.depth), np.isnan(ref.depth))  # same pixels return
        assert np.nanmax(np.abs(got.depth - ref.depth)) <= 0.0005 + 1e-6  # rounding to 1 mm units
        c_ref = frame_to_base_cloud(ref.color, ref.depth, ref.intrinsics.matrix(), T_base_cam)
        c_got = frame_to_base_cloud(got.color, got.depth, got.intrinsics.matrix(), T_base_cam)
        assert len(c_got.xyz) == len(c_ref.xyz) > 10_000
        err = np.linalg.norm(c_got.xyz.astype(np.float64) - c_ref.xyz, axis=1)
        assert err.max() <= 1e-3, f"cloud differs by up to {err.max() * 1e3:.2f} mm"
        np.testing.assert_array_equal(c_got.rgb, c_ref.rgb)


def test_bgr8_bag_comes_out_rgb(twin_frames, tmp_path):
    ref = twin_frames[1][0]
    path = write_bag(tmp_path / "bgr.bag", [ref], color_format="BGR8")
    with RealSenseBag(path) as cam:
        np.testing.assert_array_equal(cam.capture().color, ref.color)


# ----------------------------------------------------------------------------- broken recordings
def test_bag_whose_depth_stops_early_serves_the_paired_frames_then_says_so(twin_frames, tmp_path):
    path = tmp_path / "depth_stops.bag"
    frames = [f for f, _ in twin_frames]
    with BagWriter(path, frames[0].intrinsics) as w:
        w.add(frames[0])
        w.add(frames[1], streams=("color",))  # the depth stream stops, colour runs on
        w.add(frames[2], streams=("color",))
    played, err = _play_all(path)
    assert len(played) == 1  # librealsense would pair the later colour frames with stale depth
    np.testing.assert_array_equal(played[0].color, frames[0].color)
    msg = str(err)
    assert "frames stop early" in msg and "depth stream stops after 1 frame" in msg and str(path) in msg


def test_bag_cut_short_is_refused_quickly_with_the_reason(twin_bag, tmp_path):
    data = twin_bag.read_bytes()
    for frac in (0.9, 0.3):
        cut = tmp_path / f"cut_{frac}.bag"
        cut.write_bytes(data[:int(len(data) * frac)])
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match="cut short") as err:
            RealSenseBag(cut)
        assert time.monotonic() - t0 < BOUND_S
        assert str(cut) in str(err.value)


def test_missing_or_foreign_file_is_a_clear_error(tmp_path):
    with pytest.raises(DeviceError, match="no such .bag file"):
        RealSenseBag(tmp_path / "nowhere.bag")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a rosbag\n" * 100)
    with pytest.raises(DeviceError, match="not a readable RealSense bag"):
        RealSenseBag(junk)


def test_bag_without_depth_is_refused(twin_frames, tmp_path):
    path = tmp_path / "colour_only.bag"
    with BagWriter(path, twin_frames[0][0].intrinsics) as w:
        w.add(twin_frames[0][0], streams=("color",))
    with pytest.raises(DeviceError, match="no depth frames"):
        RealSenseBag(path)


def test_a_config_naming_a_bag_opens_the_player(twin_bag):
    with open_camera(RealSenseConfig(bag=twin_bag)) as cam:
        assert isinstance(cam, RealSenseBag) and cam.capture().depth.shape == (480, 848)


def test_closed_player_refuses_to_capture(twin_bag):
    cam = RealSenseBag(twin_bag)
    cam.close()
    with pytest.raises(DeviceError, match="closed"):
        cam.capture()


# ----------------------------------------------------------------------------- live camera, none here
def test_without_a_camera_list_devices_is_empty_and_the_live_adapter_fails_fast():
    assert list_devices() == []
    assert "no RealSense device found" in check_devices(RealSenseConfig())[0]
    t0 = time.monotonic()
    with pytest.raises(DeviceError) as err:
        RealSenseCamera(RealSenseConfig(serial="123456789012"))
    assert time.monotonic() - t0 < BOUND_S
    msg = str(err.value)
    for hint in ("no RealSense device found", "USB3", "99-realsense-libusb.rules", "udev"):
        assert hint in msg


def test_cellctl_record_without_a_camera_exits_nonzero_with_the_reason(tmp_path, capsys):
    out = tmp_path / "rec.bag"
    assert cellctl_main(["record", "--seconds", "1", "--out", str(out)]) == 3
    assert "no RealSense device found" in capsys.readouterr().err
    assert not out.exists()


# ----------------------------------------------------------------------------- config
def test_shipped_camera_config_validates_and_maps_to_open3d_keys():
    cfg = load_realsense_config(CONFIG_DIR / "camera.d435.yaml")
    assert cfg.open3d_config() == {
        "serial": "", "color_format": "RS2_FORMAT_RGB8", "color_resolution": "848,480",
        "depth_format": "RS2_FORMAT_Z16", "depth_resolution": "848,480", "fps": "30",
        "visual_preset": "RS2_RS400_VISUAL_PRESET_DEFAULT"}


@pytest.mark.parametrize("yaml_text, field", [
    ("fps: 25\n", "fps"),
    ("color_width: 800\n", "color_height"),
    ("depth_width: 1280\ndepth_height: 480\n", "depth_height"),
    ("frame_timeout_s: .nan\n", "frame_timeout_s"),
    ("visual_preset: loud\n", "visual_preset"),
    ("align_depth_to_color: false\n", "align_depth_to_color"),
    ("serial: '12 34'\n", "serial"),
    ("bag: session.mp4\n", "bag"),
    ("exposure: 3\n", "exposure"),
    ("camera:\n  fps: 90\n", "camera.fps"),  # a cell config's camera: block
])
def test_config_errors_name_the_file_and_the_field(tmp_path, yaml_text, field):
    path = tmp_path / "cam.yaml"
    path.write_text(yaml_text)
    with pytest.raises(CameraConfigError) as err:
        load_realsense_config(path)
    assert f"{path}: {field}:" in str(err.value)


def test_drivers_never_import_sim_planners_or_cellctl():
    for path in (Path(__file__).resolve().parents[1] / "drivers").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
            for name in names:
                assert name.split(".")[0] not in ("sim", "planners", "cellctl"), f"{path} imports {name}"


def test_a_bag_that_fails_half_way_is_not_left_behind(twin_frames, tmp_path):
    path = tmp_path / "half.bag"
    with pytest.raises(RuntimeError, match="interrupted"):
        with BagWriter(path, twin_frames[0][0].intrinsics) as w:
            w.add(twin_frames[0][0])
            raise RuntimeError("interrupted")
    assert not path.exists()
    write_bag(path, [twin_frames[0][0]])
    with pytest.raises(ValueError, match="exists already"):
        write_bag(path, [twin_frames[0][0]])


def test_relative_bag_paths_resolve_against_the_config_file(tmp_path):
    (tmp_path / "cell.yaml").write_text("cell_id: real-1\ncamera:\n  bag: rec/session.bag\n")
    assert load_realsense_config(tmp_path / "cell.yaml").bag == tmp_path / "rec" / "session.bag"
