"""The D435 adapter (drivers/realsense) without a camera: .bag fixtures written at test time from twin
frames in librealsense's rosbag layout (pure-Python rosbags), played back through our RGBDCamera
adapter, which reads the bag in its own order (never on a clock) and aligns depth to colour. No
mocks: where no camera exists (here) the live sensor must say so quickly.

Tests of: drivers.realsense.sensor, drivers.realsense.bag, drivers.realsense.frames, drivers.realsense.config.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cellctl.cli import main as cellctl_main
from configs import CONFIG_DIR
from drivers.interfaces import DeviceError, Intrinsics, RGBDCamera
from drivers.realsense import (CameraConfigError, RealSenseBag, RealSenseCamera, RealSenseConfig, check_devices,
                               list_devices, load_realsense_config, open_camera)
from drivers.realsense.bag_writer import BagWriter, write_bag
from drivers.realsense.align import align_depth
from drivers.realsense.bag_format import StreamModel
from planners.clouds import frame_to_base_cloud
from sim.config import D435Config, TwinConfig
from sim.scenes import load_scene
from sim.twin import Twin

BOUND_S = 5.0  # the live adapter's open timeout is well under this; not a speed figure


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
    """All frames of a bag, and the DeviceError that ends them."""
    frames = []
    with RealSenseBag(path) as cam:
        with pytest.raises(DeviceError) as err:
            for _ in range(100):
                frames.append(cam.capture())
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


# ----------------------------------------------------------------------------- determinism
def test_a_bag_replays_identically_twenty_times_beside_two_cpu_bound_processes(twin_frames, tmp_path):
    """A recording replayed on a busy cell PC must give the same frames, same order, same pairing,
    every time: playback is paced by the reader, not by the bag clock."""
    frames = [f for f, _ in twin_frames] * 2  # six frames at the D435's real 30 fps spacing
    path = write_bag(tmp_path / "six.bag", frames)
    busy = [subprocess.Popen([sys.executable, "-c", "import time\nend = time.monotonic() + 120\n"
                              "while time.monotonic() < end: pass"]) for _ in range(2)]
    try:
        replays = []
        for _ in range(20):
            played, end = _play_all(path)
            assert "end of bag: all 6 frames served" in str(end)
            replays.append(played)
    finally:
        for proc in busy:
            proc.kill()
            proc.wait(timeout=10)
    assert all(proc.returncode is not None for proc in busy)
    for played in replays:
        assert len(played) == len(frames)
        for got, ref in zip(played, frames):
            np.testing.assert_array_equal(got.color, ref.color)
            np.testing.assert_array_equal(np.isnan(got.depth), np.isnan(ref.depth))
        for got, first in zip(played, replays[0]):
            np.testing.assert_array_equal(got.depth, first.depth)


def test_colour_without_its_own_depth_is_refused_and_playback_goes_on(twin_frames, tmp_path):
    """Pairing comes from the bag's index: each colour frame takes the depth frame nearest in bag
    time within half a period; a colour frame whose depth was dropped is refused, never served with
    its neighbour's depth, and the next capture plays on."""
    f = [fr for fr, _ in twin_frames]
    path = tmp_path / "dropped.bag"
    with BagWriter(path, f[0].intrinsics) as w:
        w.add(f[0])
        w.add(f[1], streams=("color",))  # its depth frame was dropped
        w.add(f[2], offset_s=0.3 / 30)  # depth 0.3 periods late: unsynchronised, still its own
        w.add(f[0], offset_s=-0.3 / 30)
    with RealSenseBag(path) as cam:
        assert cam.frames_expected == 3
        first = cam.capture()
        with pytest.raises(DeviceError, match=r"colour frame 2 at .* has no depth frame within half a frame period"):
            cam.capture()
        third = cam.capture()
        fourth = cam.capture()
        with pytest.raises(DeviceError, match="end of bag"):
            cam.capture()
    for got, ref in ((first, f[0]), (third, f[2]), (fourth, f[0])):
        np.testing.assert_array_equal(got.color, ref.color)
        np.testing.assert_array_equal(np.isnan(got.depth), np.isnan(ref.depth))
        assert np.nanmax(np.abs(got.depth - ref.depth)) <= 0.0005 + 1e-6


@pytest.fixture(scope="module")
def depth_imager_frames(twin_frames):
    """The D435's layout: a wide depth imager 15 mm left of the colour camera, slightly turned, with
    its own intrinsics. The twin renders both views of the same scene; the colour view's truth depth
    is what alignment must reproduce."""
    wide = TwinConfig(camera=D435Config(noise=False, hfov_deg=87.0, vfov_deg=56.5), execution="teleport")
    from scipy.spatial.transform import Rotation

    T_cd = np.eye(4)  # depth frame -> colour frame
    T_cd[:3, :3] = Rotation.from_euler("yz", [0.6, -0.3], degrees=True).as_matrix()
    T_cd[:3, 3] = [-0.015, 0.0003, 0.0002]
    out = []
    with Twin(load_scene("smooth_cylinder"), wide) as twin:
        for ref, T_base_cam in twin_frames:
            out.append((ref, twin.camera.render_truth(T_base_cam @ T_cd)))
        Kd = twin.camera.intrinsics
    return out, Kd, T_cd


def test_a_depth_imager_apart_from_the_colour_camera_is_aligned_onto_the_colour_grid(depth_imager_frames, twin_frames,
                                                                                  tmp_path):
    pairs, Kd, T_cd = depth_imager_frames
    assert Kd != twin_frames[0][0].intrinsics
    path = tmp_path / "d435_layout.bag"
    with BagWriter(path, pairs[0][0].intrinsics, depth_intrinsics=Kd, T_color_depth=T_cd) as w:
        for ref, depth in pairs:
            w.add(ref, depth_m=depth)
    played, _ = _play_all(path)
    assert len(played) == len(pairs)
    for got, (ref, _) in zip(played, pairs):
        truth = ref.depth  # the twin's colour-view depth (noise off)
        np.testing.assert_array_equal(got.color, ref.color)
        both = np.isfinite(truth) & np.isfinite(got.depth)
        assert both.sum() >= 0.97 * np.isfinite(truth).sum(), "alignment leaves holes where the surface was seen"
        err = np.abs(got.depth[both] - truth[both])
        assert np.median(err) <= 0.001, f"median {np.median(err) * 1e3:.2f} mm"
        assert np.percentile(err, 99) <= 0.005, f"99th percentile {np.percentile(err, 99) * 1e3:.2f} mm"


def test_alignment_with_equal_grids_and_no_extrinsic_is_the_identity():
    s = StreamModel(Intrinsics(width=8, height=6, fx=5.0, fy=5.0, cx=3.5, cy=2.5))
    raw = np.random.default_rng(0).integers(0, 3000, size=(6, 8)).astype(np.uint16)
    # the general path (a zero but present extrinsic) must give the same as the shortcut
    moved = StreamModel(s.intrinsics, R=np.eye(3), t=np.array([0.0, 0.0, 1e-12]))
    np.testing.assert_array_equal(align_depth(raw, 0.001, s, s), raw)
    np.testing.assert_array_equal(align_depth(raw, 0.001, s, moved), raw)


def test_alignment_keeps_the_nearer_surface_where_footprints_overlap():
    """A 2x wider colour grid: each depth pixel covers 2x2 colour pixels; a near pixel beside a far
    one must win the pixels both reach, and the far one keeps the rest."""
    d = StreamModel(Intrinsics(width=4, height=2, fx=2.0, fy=2.0, cx=1.5, cy=0.5))
    c = StreamModel(Intrinsics(width=8, height=4, fx=4.0, fy=4.0, cx=3.5, cy=1.5))
    raw = np.full((2, 4), 2000, dtype=np.uint16)
    raw[0, 1] = 500
    out = align_depth(raw, 0.001, d, c)
    assert out[0:2, 2:4].tolist() == [[500, 500], [500, 500]]
    assert (out[2:, :] == 2000).all() and out[0, 0] == 2000
    assert (out > 0).all(), "upsampling must not leave holes"


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
        with pytest.raises(DeviceError, match="cut short") as err:
            RealSenseBag(cut)
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


def _through_lens(frame, model: str, coeffs: tuple[float, ...]):
    """The twin's pinhole frame as a camera with this lens would have taken it: each pixel of the new image
    looks along its own ray (``configs.lens.deproject``) and takes the pinhole image's nearest pixel there
    (colour, and depth along the optical axis, which the lens does not change)."""
    from configs.lens import deproject
    from drivers.interfaces import RGBDFrame

    K = frame.intrinsics
    v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float64)
    x, y = deproject((u - K.cx) / K.fx, (v - K.cy) / K.fy, model, coeffs)
    up, vp = np.rint(x * K.fx + K.cx).astype(int), np.rint(y * K.fy + K.cy).astype(int)
    inside = (up >= 0) & (up < K.width) & (vp >= 0) & (vp < K.height)
    up, vp = np.clip(up, 0, K.width - 1), np.clip(vp, 0, K.height - 1)
    depth = np.where(inside, frame.depth[vp, up], np.nan).astype(np.float32)
    color = np.where(inside[..., None], frame.color[vp, up], 0).astype(np.uint8)
    lensed = Intrinsics(K.width, K.height, K.fx, K.fy, K.cx, K.cy, model=model, coeffs=coeffs)
    return RGBDFrame(color, depth, lensed, frame.timestamp)


@pytest.mark.parametrize("model", ["Brown Conrady", "Inverse Brown Conrady"])
def test_a_bag_whose_stream_carries_distortion_gives_the_true_surface(twin_frames, tmp_path, model):
    """The lens's model and coefficients go from the bag's camera_info into every frame's intrinsics, and the
    cloud is made through them: the points lie on the surface the pinhole twin saw. Ignoring them (taking
    the intrinsics on trust as a pinhole) bends the surface by centimetres at the image's edge."""
    from scipy.spatial import cKDTree

    coeffs = (0.12, -0.05, 0.001, -0.0008, 0.01)
    ref, T_base_cam = twin_frames[0]
    bag = write_bag(tmp_path / "lens.bag", [_through_lens(ref, model, coeffs)])
    with RealSenseBag(bag) as cam:
        got = cam.capture()
    assert got.intrinsics.model == model and got.intrinsics.coeffs == pytest.approx(coeffs)
    assert got.intrinsics.lens == (model, got.intrinsics.coeffs)
    truth = cKDTree(frame_to_base_cloud(ref.color, ref.depth, ref.intrinsics.matrix(), T_base_cam).xyz)
    with_lens = frame_to_base_cloud(got.color, got.depth, got.intrinsics.matrix(), T_base_cam,
                                    lens=got.intrinsics.lens)
    as_pinhole = frame_to_base_cloud(got.color, got.depth, got.intrinsics.matrix(), T_base_cam)
    d_lens, _ = truth.query(with_lens.xyz)
    d_pinhole, _ = truth.query(as_pinhole.xyz)
    assert len(with_lens.xyz) > 10_000
    # nearest-pixel resampling and 1 mm depth units: within a few mm everywhere
    assert np.median(d_lens) < 0.001 and np.percentile(d_lens, 99) < 0.004, (np.median(d_lens), d_lens.max())
    assert np.percentile(d_pinhole, 99) > 3 * np.percentile(d_lens, 99), (np.percentile(d_pinhole, 99),
                                                                          np.percentile(d_lens, 99))
