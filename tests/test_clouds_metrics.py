"""Cloud processing and the paper's metrics on hand-made data (known answers)."""

import numpy as np
import pytest

from planners import clouds
from planners.clouds import Cloud
from planners.metrics import coverage, displacement


def test_back_projection_of_a_flat_wall_lands_at_its_depth():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    depth = np.full((480, 640), 0.7, np.float32)
    depth[:10] = np.nan  # no return
    depth[10:20] = 0.0  # no return, RealSense style
    pts, idx = clouds.depth_to_camera_points(depth, K)
    assert len(pts) == 460 * 640
    assert np.allclose(pts[:, 2], 0.7)
    # the principal point maps onto the optical axis
    centre = pts[idx == 240 * 640 + 320][0]
    assert np.allclose(centre, [0, 0, 0.7], atol=1e-6)


def test_frame_cloud_is_transformed_into_the_base_frame():
    K = np.array([[500.0, 0, 32], [0, 500.0, 24], [0, 0, 1]])
    depth = np.full((48, 64), 0.5, np.float32)
    color = np.zeros((48, 64, 3), np.uint8)
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # looking straight down
    T[:3, 3] = [0.4, 0.1, 0.8]
    c = clouds.frame_to_base_cloud(color, depth, K, T)
    assert np.allclose(c.xyz[:, 2], 0.3, atol=1e-6)
    assert abs(c.xyz[:, 0].mean() - 0.4) < 1e-3 and abs(c.xyz[:, 1].mean() - 0.1) < 1e-3


def test_concatenate_deduplicates_per_voxel_and_keeps_old_points():
    a = Cloud(np.array([[0.0001, 0, 0], [0.5, 0, 0]], np.float32), np.array([[1, 1, 1], [2, 2, 2]], np.uint8))
    b = Cloud(np.array([[0.0002, 0, 0], [0.9, 0, 0]], np.float32), np.array([[9, 9, 9], [3, 3, 3]], np.uint8))
    c = clouds.concatenate(a, b, 0.002)
    assert len(c) == 3
    assert [1, 1, 1] in c.rgb.tolist() and [9, 9, 9] not in c.rgb.tolist()


def test_every_strided_pixel_is_a_selection_of_the_full_cloud():
    """The rays the grid integrates (every 2nd or 3rd pixel) taken from the full frame's cloud by
    pixel index are exactly the cloud a strided back-projection gives, holes included."""
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.3, 1.0, (48, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = np.nan
    color = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.4, 0.1, 0.8]
    full, pixels = clouds.frame_to_base_cloud(color, depth, K, T, pixels=True)
    for stride in (2, 3):
        sub = full.select(clouds.on_stride(pixels, 64, stride))
        ref = clouds.frame_to_base_cloud(color, depth, K, T, stride=stride)
        assert len(ref) > 0 and np.array_equal(sub.xyz, ref.xyz) and np.array_equal(sub.rgb, ref.rgb)


def test_cloud_total_equals_repeated_concatenate():
    """The running total with sorted keys gives exactly the points, colours and order of eq. 1
    recomputed from scratch every view, over views that overlap, repeat points and add new ones."""
    rng = np.random.default_rng(3)
    total, ref = clouds.CloudTotal(0.002), Cloud.empty()
    for k in range(6):
        xyz = (rng.random((4000, 3)) * 0.05 + 0.01 * k).astype(np.float32)  # each view overlaps the last
        xyz[:500] = xyz[500:1000]  # repeats within a view: the first one per voxel wins
        view = Cloud(xyz, rng.integers(0, 255, (4000, 3), dtype=np.uint8),
                     np.broadcast_to(np.float32(k), (4000, 3)).copy())
        got, ref = total.add(view), clouds.concatenate(ref, view, 0.002)
        assert np.array_equal(got.xyz, ref.xyz) and np.array_equal(got.rgb, ref.rgb)
        assert np.array_equal(got.origin, ref.origin)
    assert total.add(Cloud.empty()) is got


def test_colour_filter_keeps_shaded_red_and_rejects_grey_and_orange():
    rgb = np.array([[220, 20, 20], [90, 8, 10], [200, 10, 60], [120, 118, 115], [230, 140, 20], [30, 30, 200]], np.uint8)
    m = clouds.color_mask(rgb, 0.0, 20.0, 0.5, 0.15)
    assert m.tolist() == [True, True, True, False, False, False]


def test_coverage_on_hand_made_clouds():
    gt = np.stack(np.meshgrid(np.arange(0, 0.1, 0.002), np.arange(0, 0.02, 0.002), [0.5]), -1).reshape(-1, 3) + 0.0005
    assert coverage(gt, gt, 0.01).fraction == 1.0
    half = gt[gt[:, 0] < 0.05]
    cov = coverage(half, gt, 0.01)
    assert cov.total == 10 * 2 and cov.hit == 10 and cov.percent == pytest.approx(50.0)
    far = gt + [0, 0, 0.2]
    assert coverage(far, gt, 0.01).hit == 0
    assert coverage(np.zeros((0, 3)), gt, 0.01).hit == 0
    with pytest.raises(ValueError, match="ground truth"):
        coverage(gt, np.zeros((0, 3)), 0.01)


def test_displacement_sums_straight_moves():
    assert displacement(np.array([[0, 0, 0], [0.3, 0, 0], [0.3, 0.4, 0]])) == pytest.approx(0.7)
    assert displacement(np.array([[1.0, 2, 3]])) == 0.0


def test_compiled_colour_filter_matches_the_hsv_definition():
    """color_mask runs rgb_to_hsv's arithmetic per pixel in compiled code: the same mask, hue wrap included."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (200_000, 3), dtype=np.uint8)
    for hue, half, s_min, v_min in [(0.0, 20.0, 0.5, 0.15), (350.0, 25.0, 0.5, 0.15), (120.0, 30.0, 0.3, 0.1)]:
        hsv = clouds.rgb_to_hsv(rgb)
        dh = np.abs((hsv[:, 0] - hue + 180.0) % 360.0 - 180.0)
        ref = (dh <= half) & (hsv[:, 1] >= s_min) & (hsv[:, 2] >= v_min)
        assert ref.sum() > 1000
        assert np.array_equal(clouds.color_mask(rgb, hue, half, s_min, v_min), ref)
