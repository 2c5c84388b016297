"""Hand-eye calibration (`cellctl calibrate hand-eye`) in the twin: a ChArUco board textured at a
known pose is found where it is, the extrinsic recovered from a dozen views is within 2 mm and
0.5 deg of the twin's true one, the file written round-trips into the cell config, and a missing
board or too few views fail with a clear message. One calibration for the whole module (teleport
execution): about 10-20 s."""

from __future__ import annotations

import contextlib
import io

import cv2
import numpy as np
import pytest
import yaml

from cellctl.cli import build_parser, main
from cellctl.commissioning.handeye import _empty_scene, calibrate_hand_eye, run_hand_eye_in_twin
from cellctl.config import CellConfig, MotionConfig, load_cell_config
from configs.charuco import CharucoBoardConfig
from configs.poses import pose_from_xyz_rpy_deg
from planners.config import ConfigError
from planners.handeye import (METHODS, HandEyeError, calibrate, calibration_views, corners_in_view, detect_board,
                              pose_error, solve_hand_eye, xyz_rpy_deg)
from sim.board import add_board, face_up_pose
from sim.config import HandEyeConfig, TwinConfig
from sim.twin import Twin

TRUE_XYZ = [0.065, -0.01, 0.048]
TRUE_RPY = [1.0, -2.0, 0.5]
T_TRUE = pose_from_xyz_rpy_deg(TRUE_XYZ, TRUE_RPY)
BOARD = CharucoBoardConfig()


def twin_config(**kw) -> TwinConfig:
    return TwinConfig(execution="teleport", hand_eye=HandEyeConfig(xyz=TRUE_XYZ, rpy_deg=TRUE_RPY), **kw)


def look_at(position, target, down_hint) -> np.ndarray:
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    y = np.asarray(down_hint, float) - np.dot(down_hint, z) * z
    y /= np.linalg.norm(y)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([np.cross(y, z), y, z])
    T[:3, 3] = position
    return T


# ----------------------------------------------------------------------------- the board in the twin
@pytest.fixture(scope="module")
def board_twin():
    with Twin(_empty_scene(), twin_config()) as twin:
        board = add_board(twin.client, face_up_pose((0.48, 0.05), yaw_deg=20.0), BOARD)
        yield twin, board


def test_rendered_board_is_where_it_was_put(board_twin):
    """The texture maps onto the board frame exactly: OpenCV finds every corner within a pixel of
    where the known pose projects it (mean offset ~0: no shift or flip), and PnP gives the pose."""
    twin, board = board_twin
    T_cam = look_at(np.array([0.40, 0.12, 0.45]), board.corners_base().mean(axis=0), (1.0, 0.3, 0.0))
    frame = twin.camera.capture_at(T_cam)
    K = frame.intrinsics.matrix()
    view = detect_board(frame.color, K, BOARD)
    assert view is not None
    assert len(view.ids) >= 20 and view.markers >= 12
    truth = board.corners_base()[view.ids]
    Tcb = np.linalg.inv(T_cam)
    pc = truth @ Tcb[:3, :3].T + Tcb[:3, 3]
    uv = pc[:, :2] / pc[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    err = view.corners_px - uv
    assert np.abs(err).max() < 1.0
    assert np.all(np.abs(err.mean(axis=0)) < 0.1)
    mm, deg = pose_error(T_cam @ view.T_cam_board, board.T_base_board)
    assert mm < 2.0 and deg < 0.3, (mm, deg)


def test_no_board_in_an_empty_view(board_twin):
    twin, _ = board_twin
    frame = twin.camera.capture_at(look_at(np.array([0.0, -0.5, 0.5]), [-0.3, -0.9, 0.0], (1.0, 0.0, 0.0)))
    assert detect_board(frame.color, frame.intrinsics.matrix(), BOARD) is None
    assert detect_board(np.full((480, 848, 3), 255, np.uint8), frame.intrinsics.matrix(), BOARD) is None


def test_views_look_at_the_board_from_varied_poses():
    Tb = face_up_pose((0.5, 0.0))
    K = np.array([[612.0, 0, 423.5], [0, 612.0, 239.5], [0, 0, 1]])
    P = calibration_views(Tb, BOARD, K, (848, 480), 12, seed=3)
    again = calibration_views(Tb, BOARD, K, (848, 480), 12, seed=3)
    np.testing.assert_array_equal(P, again)  # deterministic
    normal = -Tb[:3, 2]
    tilt = np.degrees(np.arccos(np.clip(-P[:, :3, 2] @ normal, -1, 1)))
    assert tilt.max() <= 25.0 + 1e-6 and tilt.max() > 15.0
    for T in P:
        assert corners_in_view(T, Tb, BOARD, K, (848, 480)) >= 0.9
    # rotations about several axes: relative rotation axes are not all parallel
    axes = [cv2.Rodrigues(P[0, :3, :3].T @ T[:3, :3])[0].ravel() for T in P[1:]]
    axes = np.array([a / np.linalg.norm(a) for a in axes])
    assert np.linalg.svd(axes, compute_uv=False)[1] > 0.3


# ----------------------------------------------------------------------------- the command in the twin
@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """`cellctl calibrate hand-eye` on a twin whose true extrinsic is not the default."""
    d = tmp_path_factory.mktemp("handeye")
    cell = CellConfig(twin=twin_config()).model_dump(mode="json")
    (d / "cell.yaml").write_text(yaml.safe_dump(cell))
    out = d / "hand_eye.yaml"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(io.StringIO()):
        rc = main(["calibrate", "hand-eye", "--config", str(d / "cell.yaml"), "--out", str(out), "--poses", "12"])
    return rc, d, out, stdout.getvalue()


def test_recovers_the_true_extrinsic(calibrated):
    rc, _, out, text = calibrated
    assert rc == 0, text
    rec = yaml.safe_load(out.read_text())
    X = pose_from_xyz_rpy_deg(rec["hand_eye"]["xyz"], rec["hand_eye"]["rpy_deg"])
    mm, deg = pose_error(X, T_TRUE)
    assert mm < 2.0, f"translation off by {mm:.3f} mm"
    assert deg < 0.5, f"rotation off by {deg:.4f} deg"
    assert rec["n_views"] == 12 and rec["method"] in METHODS
    assert set(rec["by_method"]) == set(METHODS)
    r = rec["residual"]
    assert r["translation_rms_mm"] < 2.0 and r["rotation_rms_deg"] < 0.5 and r["reproj_rms_px"] < 1.0
    assert rec["twin_truth_error"]["mm"] == pytest.approx(mm, abs=0.01)
    assert "twin truth" in text and "residual" in text


def test_written_file_round_trips_into_the_config(calibrated):
    rc, d, out, _ = calibrated
    assert rc == 0
    rec = yaml.safe_load(out.read_text())
    cell = yaml.safe_load((d / "cell.yaml").read_text())
    cell["hand_eye_file"] = out.name  # relative to the cell config
    (d / "cell_calibrated.yaml").write_text(yaml.safe_dump(cell))
    cfg, _ = load_cell_config(d / "cell_calibrated.yaml")
    assert cfg.twin.hand_eye.xyz == rec["hand_eye"]["xyz"]
    assert cfg.twin.hand_eye.rpy_deg == rec["hand_eye"]["rpy_deg"]
    mm, deg = pose_error(cfg.twin.hand_eye.T_flange_cam(), T_TRUE)
    assert mm < 2.0 and deg < 0.5
    assert HandEyeConfig.from_file(out) == cfg.twin.hand_eye


def test_missing_or_broken_hand_eye_file_is_a_config_error(tmp_path):
    (tmp_path / "cell.yaml").write_text("hand_eye_file: nowhere.yaml\n")
    with pytest.raises(ConfigError, match="nowhere.yaml"):
        load_cell_config(tmp_path / "cell.yaml")
    (tmp_path / "he.yaml").write_text("hand_eye: {xyz: [0.07, 0.0], rpy_deg: [0, 0, 0]}\n")
    (tmp_path / "cell.yaml").write_text("hand_eye_file: he.yaml\n")
    with pytest.raises(ConfigError, match=r"he.yaml: hand_eye.xyz"):
        load_cell_config(tmp_path / "cell.yaml")


# ----------------------------------------------------------------------------- clear failures
def test_too_few_poses_is_refused():
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        assert main(["calibrate", "hand-eye", "--poses", "3"]) == 2
    assert "at least 5 views" in stderr.getvalue()
    with Twin(_empty_scene(), twin_config()) as twin:
        with pytest.raises(HandEyeError, match="at least 5 views"):
            calibrate_hand_eye(twin.arm, twin.camera, BOARD, MotionConfig(), n_poses=3)


def test_too_few_or_degenerate_views_are_refused(board_twin):
    twin, board = board_twin
    K = twin.camera.K
    A, views = [], []
    for x in (0.40, 0.44, 0.48, 0.52):  # four views, all the same orientation
        T_cam = look_at(np.array([x, 0.05, 0.5]), [x, 0.05, 0.0], (1.0, 0.0, 0.0))
        view = detect_board(twin.camera.capture_at(T_cam).color, K, BOARD)
        assert view is not None
        A.append(T_cam @ np.linalg.inv(T_TRUE))
        views.append(view)
    with pytest.raises(HandEyeError, match="only 4 views"):
        calibrate(np.array(A), views, K, BOARD)
    with pytest.raises(HandEyeError, match="turned at most"):
        calibrate(np.array(A), views, K, BOARD, min_views=4)
    with pytest.raises(HandEyeError, match="at least 3"):
        solve_hand_eye(np.array(A[:2]), np.array([v.T_cam_board for v in views[:2]]))


def test_board_not_in_view_is_a_clear_error():
    cfg = CellConfig(twin=twin_config())
    with pytest.raises(HandEyeError, match="not in view from the start pose"):
        run_hand_eye_in_twin(cfg, n_poses=5, add_board=False)


def test_cli_method_choices_are_the_solver_methods():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "cmd").choices["calibrate"]
    he = next(a for a in sub._actions if a.dest == "what").choices["hand-eye"]
    method = next(a for a in he._actions if a.dest == "method")
    assert set(method.choices) == {"best", *METHODS}


def test_printable_board_has_its_size_and_is_detected(tmp_path):
    from PIL import Image

    out = tmp_path / "board.png"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert main(["calibrate", "board", "--out", str(out)]) == 0
    assert "A3" in stdout.getvalue()
    im = Image.open(out)
    px_per_square = 472  # 40 mm at about 300 dpi
    assert 25.4 * px_per_square / im.info["dpi"][0] == pytest.approx(40.0, abs=1e-3)
    gray = np.asarray(im)
    small = cv2.resize(gray, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    K = np.array([[1000.0, 0, small.shape[1] / 2], [0, 1000.0, small.shape[0] / 2], [0, 0, 1]])
    view = detect_board(small, K, BOARD)
    assert view is not None and len(view.ids) == (BOARD.squares_x - 1) * (BOARD.squares_y - 1)


def test_a_cell_whose_robot_does_not_answer_fails_clearly_and_writes_nothing(tmp_path):
    """Outside the twin the command drives the cell's own arm: with no robot at arm.host it says so (exit 1)
    at once, and no file appears."""
    from arm_contract import free_loopback_address

    host = free_loopback_address()
    (tmp_path / "cell.yaml").write_text(
        f"mode: fcisim\nfcisim: {{simulator: external}}\narm: {{host: {host}, model: fr3, realtime: false, "
        f"connect_timeout_s: 1.0,\n      hand_eye: {{xyz: [0.07, 0.0, 0.05], rpy_deg: [0.0, 0.0, 0.0]}}}}\n")
    load_cell_config(tmp_path / "cell.yaml")  # a valid config
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        assert main(["calibrate", "hand-eye", "--config", str(tmp_path / "cell.yaml")]) == 1
    assert f"Franka at {host}" in stderr.getvalue() and "FCI is not active" in stderr.getvalue(), stderr.getvalue()
    assert not (tmp_path / "hand_eye.yaml").exists()


# ----------------------------------------------------------------------------- the cell's own arm: fcisim
def _fcisim_cell(d, **arm):
    """configs/cell.fcisim.yaml with the camera mounted at T_TRUE (the twin renders with the arm's extrinsic
    in fcisim, so that is the truth the calibration must find; the default mount would not tell a copied
    value from a measured one)."""
    from configs import CONFIG_DIR

    cell = yaml.safe_load((CONFIG_DIR / "cell.fcisim.yaml").read_text())
    cell["arm"]["hand_eye"] = {"xyz": list(TRUE_XYZ), "rpy_deg": list(TRUE_RPY)}
    cell["arm"].update(arm)
    cell["planners_config"] = str(CONFIG_DIR / "planners.yaml")
    cell["twin"]["camera"]["noise"] = True
    path = d / "cell.yaml"
    path.write_text(yaml.safe_dump(cell))
    return path


@pytest.mark.timeout(900)
def test_on_fcisim_the_franky_arm_finds_the_true_mount_and_a_bad_board_is_not_written(tmp_path):
    """`cellctl calibrate hand-eye --config <fcisim>`: the arm is the Franka adapter on franky-sim, the camera the
    twin's renderer posed from the arm's measured joints, a board lies in the twin. The result is within
    2 mm / 0.5 deg of the mount the twin renders with, and is written (the old file kept). Told the wrong
    square size (10 % off, a mis-measured printout), the run is refused (the depth camera sees the board
    9 % smaller than told, and the board scatters) and nothing is written."""
    cfg = _fcisim_cell(tmp_path)
    out = tmp_path / "hand_eye.yaml"
    out.write_text("# an older calibration\nhand_eye: {xyz: [0.07, 0.0, 0.05], rpy_deg: [0.0, 0.0, 0.0]}\n")
    old = out.read_text()
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(["calibrate", "hand-eye", "--config", str(cfg), "--out", str(out), "--poses", "8", "--quiet"])
    assert rc == 0, stderr.getvalue()
    rec = yaml.safe_load(out.read_text())
    mm, deg = pose_error(pose_from_xyz_rpy_deg(rec["hand_eye"]["xyz"], rec["hand_eye"]["rpy_deg"]), T_TRUE)
    assert mm < 2.0 and deg < 0.5, (mm, deg)
    assert rec["source"] == "fcisim" and rec["twin_truth_error"]["mm"] == pytest.approx(mm, abs=0.01)
    assert rec["depth_scale"] == pytest.approx(1.0, abs=0.01)  # the depth finds the board its printed size
    backups = list(tmp_path.glob("hand_eye.yaml.*.bak"))
    assert len(backups) == 1 and backups[0].read_text() == old
    assert "method spread" in stdout.getvalue() and "kept as" in stdout.getvalue()
    # the cell's config now reads the calibration (it named none), the one before is kept
    assert "now reads it" in stdout.getvalue() and len(list(tmp_path.glob("cell.yaml.*.bak"))) == 1
    loaded, _ = load_cell_config(cfg)
    assert loaded.arm.hand_eye.xyz == pytest.approx(rec["hand_eye"]["xyz"])

    written = out.read_text()
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(["calibrate", "hand-eye", "--config", str(cfg), "--out", str(out), "--poses", "8", "--quiet",
                   "--square-mm", str(1.1 * 1000 * BOARD.square_m), "--marker-mm", str(1.1 * 1000 * BOARD.marker_m)])
    assert rc == 1
    assert "not written" in stderr.getvalue() and "measures the board -9" in stderr.getvalue(), stderr.getvalue()
    assert out.read_text() == written and len(list(tmp_path.glob("hand_eye.yaml.*.bak"))) == 1


def test_a_board_pose_given_aims_the_views_without_locating_it(tmp_path):
    """--board-pose: the views are aimed at the pose given (no locating view from the start pose)."""
    from cellctl.commissioning.handeye import TWIN_BOARD_XY

    cell = CellConfig(twin=twin_config()).model_dump(mode="json")
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell))
    given = face_up_pose(TWIN_BOARD_XY, config=BOARD)
    xyz, rpy = xyz_rpy_deg(given)
    out = tmp_path / "hand_eye.yaml"
    stderr = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(stderr):
        rc = main(["calibrate", "hand-eye", "--config", str(tmp_path / "cell.yaml"), "--out", str(out), "--poses", "6",
                   "--board-pose", *map(str, [*xyz, *rpy])])
    assert rc == 0, stderr.getvalue()
    assert "board located" not in stderr.getvalue()  # not looked for: it was given
    rec = yaml.safe_load(out.read_text())
    found = pose_from_xyz_rpy_deg(rec["board_in_base"]["xyz"], rec["board_in_base"]["rpy_deg"])
    mm, deg = pose_error(found, given)
    assert mm < 5 and deg < 1, (mm, deg)
