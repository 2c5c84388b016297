"""Scenes: catalog geometry, ground truth, reachability, initial views, user YAML files.

Tests of: sim.scenes.catalog, sim.scenes.model, sim.scenes.scene_file, configs.loading.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from sim.scenes import SCENE_NAMES, SceneError, load_scene
from sim.scenes.paint import closest_points, resample_polyline
from sim.scenes.views import look_at, sight_blocked

REPO = Path(__file__).resolve().parents[1]
SHOULDER = np.array([0.0, 0.0, 0.333])
FOOTPRINT = (0.48, 0.27)  # m seen by the D435 colour camera from 0.35 m


@pytest.fixture(scope="module", params=SCENE_NAMES)
def scene(request):
    return load_scene(request.param)


def _face_keys(mesh):
    """Faces as bytes of their vertex coordinates in a canonical order."""
    tri = np.round(mesh.triangles, 9) + 0.0
    order = np.lexsort((tri[:, :, 2], tri[:, :, 1], tri[:, :, 0]))
    tri = np.take_along_axis(tri, order[:, :, None], axis=1)
    return set(map(bytes, tri.reshape(len(tri), -1)))


def test_names_and_categories():
    assert SCENE_NAMES == ("smooth_cylinder", "sharp_cylinder", "round_tank", "t_piece", "i_beam",
                           "basket", "branched_cylinder")


def test_meshes_nonempty_disjoint_and_closed(scene):
    assert len(scene.object_mesh.faces) and len(scene.paint_mesh.faces)
    assert not (_face_keys(scene.object_mesh) & _face_keys(scene.paint_mesh))
    full = scene.full_mesh
    assert len(full.faces) < 300_000
    full.merge_vertices()
    assert full.is_watertight  # painting split faces without opening cracks
    expected = {"branched_cylinder": None}.get(scene.name, SCENE_NAMES.index(scene.name) + 1)
    assert scene.category == expected


def test_polylines_on_surface(scene):
    for line in scene.drawing_polylines:
        assert line.ndim == 2 and line.shape[1] == 3 and len(line) >= 2
        assert closest_points(scene.full_mesh, line)[1].max() < 1e-3


def test_ground_truth_follows_the_line(scene):
    gt = scene.gt_points
    assert gt.dtype == np.float32 and gt.ndim == 2 and gt.shape[1] == 3 and len(gt) > 500
    from scipy.spatial import cKDTree

    line = np.vstack(scene.drawing_polylines)
    d_gt = cKDTree(line).query(gt)[0]
    assert d_gt.max() <= scene.drawing_width / 2 + 0.003
    d_line = cKDTree(gt).query(line)[0]
    assert d_line.max() < 0.004  # the cloud covers the whole length
    # every GT point lies on a paint face
    assert closest_points(scene.paint_mesh, gt[::7])[1].max() < 1e-5


def test_extremities(scene):
    expected = 4 if scene.name == "branched_cylinder" else 2
    assert scene.extremities.shape == (expected, 3)
    ends = np.vstack([line[[0, -1]] for line in scene.drawing_polylines])
    assert np.linalg.norm(ends[:, None] - scene.extremities[None], axis=2).min(axis=0).max() < 1e-9


def test_reachable_by_the_panda(scene):
    pts = np.vstack(scene.drawing_polylines)
    assert np.linalg.norm(pts - SHOULDER, axis=1).max() < 0.66
    assert 0.3 <= pts[:, 0].min() and pts[:, 0].max() <= 0.76
    assert np.abs(pts[:, 1]).max() < 0.35
    assert 0.04 <= pts[:, 2].min() and pts[:, 2].max() <= 0.56
    assert scene.full_mesh.bounds[0, 2] >= -1e-9


def _fits_one_view(points, normals, standoff=0.35, half_fov_deg=(34.5, 21.0), max_incidence_deg=70.0):
    """Could one pinhole camera `standoff` from the drawing's centroid (any direction, any roll)
    see every point inside the colour FOV at <= max incidence? Lenient: the camera may also turn
    to centre the drawing."""
    n = 800
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    dirs = np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)])  # to the eye
    rel = points[None] - (points.mean(axis=0) + standoff * dirs)[:, None]  # (D, N, 3) eye -> point
    depth = -np.einsum("dnk,dk->dn", rel, dirs)
    cos_inc = -np.einsum("dnk,nk->dn", rel, normals) / np.linalg.norm(rel, axis=2)
    ok = ((depth > 0.1) & (cos_inc >= np.cos(np.radians(max_incidence_deg)))).all(axis=1)
    dirs, rel, depth = dirs[ok], rel[ok], depth[ok]
    if not len(dirs):
        return False
    u = np.cross(dirs, [0.0, 0.0, 1.0]) + np.cross(dirs, [1.0, 0.0, 0.0]) * 1e-3
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(dirs, u)
    a = np.einsum("dnk,dk->dn", rel, u) / depth  # tangent-plane image coordinates
    b = np.einsum("dnk,dk->dn", rel, v) / depth
    wx, wy = 2 * np.tan(np.radians(half_fov_deg[0])), 2 * np.tan(np.radians(half_fov_deg[1]))
    for ang in np.radians(np.arange(0.0, 180.0, 3.0)):
        x, y = a * np.cos(ang) + b * np.sin(ang), -a * np.sin(ang) + b * np.cos(ang)
        if np.any((np.ptp(x, axis=1) <= wx) & (np.ptp(y, axis=1) <= wy)):
            return True
    return False


def test_fit_check_sanity():
    flat = np.column_stack([np.linspace(0, 0.4, 50), np.zeros(50), np.zeros(50)])
    up = np.tile([0.0, 0.0, 1.0], (50, 1))
    assert _fits_one_view(flat, up)  # 0.4 m seen from 0.35 m above
    assert not _fits_one_view(flat * 1.5, up)
    wrapped = np.vstack([flat[:25] * 0.5, flat[:25] * 0.5 - [0, 0, 0.005]])  # on both sides of a sheet
    assert not _fits_one_view(wrapped, np.vstack([up[:25], -up[:25]]))


def test_drawing_needs_more_than_one_view(scene):
    if scene.category is None or scene.category > 5:
        pytest.skip("only categories 1-5 must exceed one view")
    pts = scene.gt_points[:: max(1, len(scene.gt_points) // 400)].astype(np.float64)
    normals = scene.paint_mesh.face_normals[closest_points(scene.paint_mesh, pts)[2]]
    assert not _fits_one_view(pts, normals)


def test_initial_views(scene):
    views = scene.initial_view_candidates
    assert views.ndim == 3 and views.shape[1:] == (4, 4) and len(views) >= 3
    line = np.vstack(scene.drawing_polylines)
    for i, T in enumerate(views):
        R = T[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)
        assert abs(R[2, 0]) < 1e-9  # image x horizontal
        assert T[2, 3] >= 0.15
        cam = (line - T[:3, 3]) @ R  # drawing in the camera frame
        on_axis = np.hypot(cam[:, 0], cam[:, 1]) < 0.005
        assert np.any(on_axis & (cam[:, 2] > 0.2) & (cam[:, 2] < 0.6)), f"view {i} does not look at the drawing"
        if i == 0:  # the first view sees a part, not all, of the drawing (colour FOV 69 x 42 deg)
            visible = (cam[:, 2] > 0) & (np.abs(cam[:, 0]) < cam[:, 2] * np.tan(np.radians(34.5))) \
                & (np.abs(cam[:, 1]) < cam[:, 2] * np.tan(np.radians(21)))
            assert 0 < visible.mean() < 1


def test_look_at_frame_convention():
    T = look_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0])  # looking along +x, horizontally
    assert np.allclose(T[:3, 2], [1, 0, 0]) and np.allclose(T[:3, 0], [0, -1, 0]) and np.allclose(T[:3, 1], [0, 0, -1])
    T = look_at([0.5, 0.0, 0.5], [0.5, 0.0, 0.0])  # straight down still gives a proper frame
    assert np.allclose(T[:3, 2], [0, 0, -1]) and np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_a_sight_line_is_blocked_only_by_metal_between_its_ends():
    """sim.scenes.views.sight_blocked, which keeps initial views that see their point: a segment
    through a 0.1 m box is blocked; one passing beside it, one stopping short of it, one starting past
    it and a zero-length one are not."""
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    starts = np.array([[-0.3, 0, 0], [-0.3, 0.08, 0], [-0.3, 0, 0], [0.06, 0, 0], [0.2, 0.2, 0.2]])
    ends = np.array([[0.3, 0, 0], [0.3, 0.08, 0], [-0.06, 0, 0], [0.3, 0, 0], [0.2, 0.2, 0.2]])
    assert sight_blocked(box, starts, ends).tolist() == [True, False, False, False, False]
    # stopped 0.56 m short of its end, the line through the box ends 0.21 m before it
    assert not sight_blocked(box, starts[:1], ends[:1], 0.56)[0]
    assert sight_blocked(box, np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_load_scene_returns_independent_copies():
    a = load_scene("i_beam")
    a.object_mesh.apply_translation([1.0, 0.0, 0.0])
    a.gt_points[:] = 0
    b = load_scene("i_beam")
    assert b.object_mesh.bounds[0, 0] < 1.0 and np.abs(b.gt_points).max() > 0


def test_unknown_scene_name_lists_valid_ones():
    with pytest.raises(SceneError, match="smooth_cylinder"):
        load_scene("no_such_scene")


def test_example_plate():
    path = REPO / "configs" / "scenes" / "example_plate.yaml"
    s = load_scene(str(path))
    assert s.name == "example_plate" and s.category is None
    assert len(s.paint_mesh.faces) > 0 and len(s.gt_points) > 100 and len(s.extremities) == 2
    assert np.allclose(s.initial_view_candidates[0], s.initial_camera_pose)
    assert (REPO / "configs" / "scenes" / "example_plate.obj").stat().st_size < 200_000


# --- user scene files ---------------------------------------------------------------------------

PLATE_YAML = """\
name: tmp_plate
mesh: plate.obj
pose: {xyz: [0.5, 0.0, 0.1], rpy_deg: [0.0, 0.0, 30.0]}
drawing:
  width: 0.02
  polylines:
    - [[-0.15, -0.05, 0.005], [0.0, 0.02, 0.005], [0.15, 0.06, 0.005]]
"""


@pytest.fixture
def plate_dir(tmp_path):
    trimesh.creation.box(extents=[0.4, 0.3, 0.01]).export(tmp_path / "plate.obj")
    return tmp_path


def _write(dirpath: Path, text: str) -> str:
    path = dirpath / "scene.yaml"
    path.write_text(text)
    return str(path)


def test_user_scene_loads(plate_dir):
    s = load_scene(_write(plate_dir, PLATE_YAML))
    assert s.name == "tmp_plate" and s.category is None
    assert len(s.paint_mesh.faces) > 0 and len(s.extremities) == 2 and len(s.initial_view_candidates)
    assert s.paint_mesh.bounds[0, 2] > 0.1  # the top face, not the underside
    start = s.drawing_polylines[0][0]
    c, sn = np.cos(np.radians(30)), np.sin(np.radians(30))
    assert np.allclose(start, [0.5 + c * -0.15 - sn * -0.05, sn * -0.15 + c * -0.05, 0.105], atol=1e-6)


@pytest.mark.parametrize("edit, field, message", [
    (("width: 0.02", "width: wide"), "drawing.width", "valid number"),
    (("width: 0.02", "width: 0.001"), "drawing.width", "greater than or equal to 0.005"),
    (("xyz: [0.5, 0.0, 0.1]", "xyz: [.nan, 0.0, 0.1]"), "pose.xyz[0]", "finite"),
    (("rpy_deg: [0.0, 0.0, 30.0]", "rpy_deg: [0.0, .inf, 30.0]"), "pose.rpy_deg[1]", "finite"),
    (("mesh: plate.obj", "mesh: missing.obj"), "mesh", "not found"),
    (("name: tmp_plate", "name: tmp_plate\ncolour: red"), "colour", "Extra inputs"),
    (("pose: {", "pose: {scale: 2, "), "pose.scale", "Extra inputs"),
    (("[0.15, 0.06, 0.005]]", "[0.15, 0.06, 0.2]]"), "drawing.polylines[0][2]", "from the mesh surface"),
    (("[[-0.15, -0.05, 0.005], [0.0, 0.02, 0.005], [0.15, 0.06, 0.005]]", "[[0.0, 0.0, 0.005]]"),
     "drawing.polylines[0]", "at least 2"),
    (("name: tmp_plate", "name: [oops"), "invalid YAML", ""),
    (("name: tmp_plate", "name: tmp_plate\nname: other_plate"), "invalid YAML", "duplicate key 'name'"),
])
def test_invalid_user_scene(plate_dir, edit, field, message):
    text = PLATE_YAML.replace(*edit)
    assert text != PLATE_YAML
    path = _write(plate_dir, text)
    with pytest.raises(SceneError) as err:
        load_scene(path)
    assert path in str(err.value) and field in str(err.value) and message in str(err.value)


def test_missing_drawing_named(plate_dir):
    path = _write(plate_dir, PLATE_YAML.split("drawing:")[0])
    with pytest.raises(SceneError, match=r"scene\.yaml: drawing: Field required"):
        load_scene(path)


def test_missing_mesh_names_the_path(plate_dir):
    path = _write(plate_dir, PLATE_YAML.replace("plate.obj", "sub/none.obj"))
    with pytest.raises(SceneError, match=str(plate_dir / "sub" / "none.obj")):
        load_scene(path)


def test_empty_mesh_and_non_mapping(plate_dir):
    (plate_dir / "empty.obj").write_text("# nothing\n")
    with pytest.raises(SceneError, match="mesh: .*no triangles"):
        load_scene(_write(plate_dir, PLATE_YAML.replace("plate.obj", "empty.obj")))
    with pytest.raises(SceneError, match=r"\(top level\)"):
        load_scene(_write(plate_dir, "- just\n- a list\n"))


def test_resample_keeps_ends():
    p = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.1, 0.05, 0]])
    r = resample_polyline(p, 0.001)
    assert np.allclose(r[[0, -1]], p[[0, -1]]) and np.linalg.norm(np.diff(r, axis=0), axis=1).max() <= 0.001 + 1e-12
