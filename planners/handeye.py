"""Hand-eye calibration math: find a ChArUco board in an image, its pose in the camera, the camera
in the flange (``T_flange_cam``) from many (flange pose, board pose) pairs, and how well that
explains the data. Also where to look from. No devices: images, poses and intrinsics go in.

OpenCV does the work: ``aruco.CharucoDetector`` finds the corners, ``solvePnP`` (IPPE, then
Levenberg-Marquardt refinement) gives T_cam_board, ``calibrateHandEye`` solves AX = XB with each of
its methods, and the solution whose board-in-base poses agree best (reprojection RMS) wins.

Why the residual is the spread of the board in the base frame: the board does not move, so
T_base_flange_i @ X @ T_cam_board_i must be the same pose for every view i; what varies is the
error of X (and of the detections, and of the arm's kinematics), in millimetres and degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from configs.charuco import CharucoBoardConfig

MIN_CORNERS = 8  # fewer ChArUco corners give a weak pose (and none off a single line)
MIN_VIEWS = 5  # calibrateHandEye solves from 3, but its result is only trustworthy with more
MAX_REPROJ_PX = 2.0  # a view whose own PnP fit is worse than this is a bad detection, not data

#: calibrateHandEye's methods, by the name used in configs and reports
METHODS: dict[str, int] = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}


class HandEyeError(RuntimeError):
    """Calibration impossible with the data given (board not seen, too few or degenerate views)."""


@dataclass(frozen=True)
class BoardView:
    """One detection: the ChArUco corners found and the board pose they give."""

    ids: np.ndarray  # (n,) int, OpenCV chessboard corner ids
    corners_px: np.ndarray  # (n, 2) float64, pixel (column, row), centres at integers
    T_cam_board: np.ndarray  # 4x4
    reproj_rms_px: float  # of this view's own PnP fit
    markers: int  # ArUco markers found


@dataclass(frozen=True)
class Residual:
    """How consistent the views are under one extrinsic X: the board pose in the base frame per
    view against their mean, and the board corners reprojected from that mean pose."""

    translation_rms_mm: float
    translation_max_mm: float
    rotation_rms_deg: float
    rotation_max_deg: float
    reproj_rms_px: float
    reproj_max_px: float
    T_base_board: np.ndarray  # the mean board pose (4x4)

    def summary(self) -> dict:
        return {k: round(float(getattr(self, k)), 4) for k in
                ("translation_rms_mm", "translation_max_mm", "rotation_rms_deg", "rotation_max_deg",
                 "reproj_rms_px", "reproj_max_px")}


@dataclass(frozen=True)
class HandEyeSolution:
    T_flange_cam: np.ndarray
    method: str
    residual: Residual
    n_views: int
    by_method: dict[str, dict] = field(default_factory=dict)  # every method tried: its X and residual


# ----------------------------------------------------------------------------- small helpers
def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    return _pose(R.T, -R.T @ T[:3, 3])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees (numerically safe near 0 and 180)."""
    return float(np.degrees(Rotation.from_matrix(R).magnitude()))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error mm, rotation error deg) between two poses."""
    return (float(1000.0 * np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])),
            rotation_angle_deg(T_true[:3, :3].T @ T_est[:3, :3]))


def xyz_rpy_deg(T: np.ndarray) -> tuple[list[float], list[float]]:
    """The config convention of configs/poses.py (fixed-axis x, y, z angles in degrees)."""
    return (T[:3, 3].tolist(), Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True).tolist())


# ----------------------------------------------------------------------------- detection
def depth_scale(view: BoardView, depth: np.ndarray, board: CharucoBoardConfig) -> float | None:
    """The depth camera's distance to the board's corners over the distance the board's printed size gives
    (PnP): 1 when the square size told is right. PnP's scale comes only from that size, so a mis-measured
    printout scales every board pose, and hand-eye absorbs part of it into the extrinsic; the depth is
    metric on its own. The median over the corners with a depth return; None with fewer than 4."""
    P = (view.T_cam_board[:3, :3] @ board.corners_m[view.ids].T).T + view.T_cam_board[:3, 3]
    h, w = depth.shape
    col = np.clip(np.rint(view.corners_px[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.rint(view.corners_px[:, 1]).astype(int), 0, h - 1)
    ratio = depth[row, col] / P[:, 2]
    ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
    return float(np.median(ratio)) if len(ratio) >= 4 else None


def detect_board(color: np.ndarray, K: np.ndarray, board: CharucoBoardConfig, dist: np.ndarray | None = None,
                 min_corners: int = MIN_CORNERS) -> BoardView | None:
    """The board in an RGB (or grey) image and its pose T_cam_board, or None when fewer than
    ``min_corners`` corners are found, they lie on one line, or the PnP fit is worse than
    MAX_REPROJ_PX (a misread marker). ``dist``: OpenCV distortion coefficients (None: none)."""
    img = np.asarray(color)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    K = np.asarray(K, dtype=np.float64)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    cb = board.board()
    params = cv2.aruco.CharucoParameters()
    params.cameraMatrix, params.distCoeffs = K, dist  # corners interpolated with the camera model
    detector = cv2.aruco.CharucoDetector(cb, params)
    corners, ids, _, marker_ids = detector.detectBoard(gray)
    if ids is None or len(ids) < min_corners:
        return None
    if cb.checkCharucoCornersCollinear(ids):
        return None
    obj, imgp = cb.matchImagePoints(corners, ids)
    obj = obj.reshape(-1, 3).astype(np.float64)
    imgp = imgp.reshape(-1, 2).astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, imgp, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, imgp, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - imgp, axis=1)
    rms = float(np.sqrt(np.mean(err ** 2)))
    if rms > MAX_REPROJ_PX or tvec[2, 0] <= 0:
        return None
    return BoardView(ids=ids.ravel().astype(int), corners_px=imgp, T_cam_board=_pose(cv2.Rodrigues(rvec)[0], tvec),
                     reproj_rms_px=rms, markers=0 if marker_ids is None else len(marker_ids))


# ----------------------------------------------------------------------------- solving
def solve_hand_eye(T_base_flange: list[np.ndarray] | np.ndarray, T_cam_board: list[np.ndarray] | np.ndarray,
                   method: str = "tsai") -> np.ndarray:
    """T_flange_cam from pairs (flange in base from the arm's FK, board in camera from PnP) by
    OpenCV's calibrateHandEye. Needs at least 3 pairs with rotations about different axes."""
    A = np.asarray(T_base_flange, dtype=np.float64)
    B = np.asarray(T_cam_board, dtype=np.float64)
    if A.shape != B.shape or A.ndim != 3 or A.shape[1:] != (4, 4):
        raise ValueError(f"need (n, 4, 4) flange and board poses of equal n, got {A.shape} and {B.shape}")
    if len(A) < 3:
        raise HandEyeError(f"hand-eye needs at least 3 views, got {len(A)}")
    if method not in METHODS:
        raise ValueError(f"unknown hand-eye method {method!r}; choose one of {', '.join(METHODS)}")
    R, t = cv2.calibrateHandEye(list(A[:, :3, :3]), list(A[:, :3, 3:]), list(B[:, :3, :3]), list(B[:, :3, 3:]),
                                method=METHODS[method])
    X = _pose(R, t)
    if not np.all(np.isfinite(X)):
        raise HandEyeError(f"calibrateHandEye ({method}) returned no finite solution: degenerate views")
    return X


def board_in_base(T_base_flange: np.ndarray, X: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """(n, 4, 4) T_base_board seen by each view under extrinsic X."""
    return np.asarray(T_base_flange) @ X @ np.asarray(T_cam_board)


def residual(T_base_flange: np.ndarray, X: np.ndarray, views: list[BoardView], K: np.ndarray,
             board: CharucoBoardConfig, dist: np.ndarray | None = None) -> Residual:
    """Consistency of the board's pose in the base frame across views under X (see module doc)."""
    A = np.asarray(T_base_flange, dtype=np.float64)
    P = board_in_base(A, X, np.array([v.T_cam_board for v in views]))
    rot = Rotation.from_matrix(P[:, :3, :3])
    mean = _pose(rot.mean().as_matrix(), P[:, :3, 3].mean(axis=0))
    dt = 1000.0 * np.linalg.norm(P[:, :3, 3] - mean[:3, 3], axis=1)
    dr = np.degrees((rot * Rotation.from_matrix(mean[:3, :3]).inv()).magnitude())
    K = np.asarray(K, dtype=np.float64)
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    corners = board.corners_m
    errs = []
    for Ai, v in zip(A, views):  # a dozen views
        T_cb = _inv(Ai @ X) @ mean
        proj, _ = cv2.projectPoints(corners[v.ids], cv2.Rodrigues(T_cb[:3, :3])[0], T_cb[:3, 3], K, dist)
        errs.append(np.linalg.norm(proj.reshape(-1, 2) - v.corners_px, axis=1))
    e = np.concatenate(errs)
    return Residual(translation_rms_mm=float(np.sqrt(np.mean(dt ** 2))), translation_max_mm=float(dt.max()),
                    rotation_rms_deg=float(np.sqrt(np.mean(dr ** 2))), rotation_max_deg=float(dr.max()),
                    reproj_rms_px=float(np.sqrt(np.mean(e ** 2))), reproj_max_px=float(e.max()),
                    T_base_board=mean)


def calibrate(T_base_flange: list[np.ndarray] | np.ndarray, views: list[BoardView], K: np.ndarray,
              board: CharucoBoardConfig, methods: list[str] | tuple[str, ...] | None = None,
              dist: np.ndarray | None = None, min_views: int = MIN_VIEWS) -> HandEyeSolution:
    """Solve with each method (default: all of METHODS) and keep the one with the smallest
    reprojection RMS of the board under its X: the methods differ in how they weigh rotation
    against translation noise, and which one fits best depends on the views."""
    A = np.asarray(T_base_flange, dtype=np.float64)
    if len(A) != len(views):
        raise ValueError(f"{len(A)} flange poses for {len(views)} board views")
    if len(views) < min_views:
        raise HandEyeError(f"only {len(views)} views with the board found; hand-eye needs at least {min_views} "
                           f"(move the board into view or add poses)")
    spread = max(rotation_angle_deg(A[0, :3, :3].T @ Ai[:3, :3]) for Ai in A[1:])
    if spread < 5.0:
        raise HandEyeError(f"the flange turned at most {spread:.1f} deg between views; hand-eye needs rotations "
                           f"of tens of degrees about different axes")
    by_method: dict[str, dict] = {}
    best: tuple[float, str, np.ndarray, Residual] | None = None
    B = np.array([v.T_cam_board for v in views])
    for name in methods or tuple(METHODS):
        try:
            X = solve_hand_eye(A, B, name)
        except (HandEyeError, cv2.error) as e:
            by_method[name] = {"error": str(e).strip()[:200]}
            continue
        r = residual(A, X, views, K, board, dist)
        xyz, rpy = xyz_rpy_deg(X)
        by_method[name] = {"xyz": [round(v, 6) for v in xyz], "rpy_deg": [round(v, 4) for v in rpy], **r.summary()}
        if best is None or r.reproj_rms_px < best[0]:
            best = (r.reproj_rms_px, name, X, r)
    if best is None:
        raise HandEyeError(f"every hand-eye method failed: {by_method}")
    _, name, X, r = best
    return HandEyeSolution(T_flange_cam=X, method=name, residual=r, n_views=len(views), by_method=by_method)


# ----------------------------------------------------------------------------- where to look from
def board_center(T_base_board: np.ndarray, board: CharucoBoardConfig) -> np.ndarray:
    w, h = board.size_m
    return (T_base_board @ np.array([w / 2.0, h / 2.0, 0.0, 1.0]))[:3]


def corners_in_view(T_base_cam: np.ndarray, T_base_board: np.ndarray, board: CharucoBoardConfig, K: np.ndarray,
                    size: tuple[int, int], border_px: float = 10.0) -> float:
    """Fraction of the board's chessboard corners that project inside the image (``size`` = (W, H)),
    at least ``border_px`` from its edge and in front of the camera, facing it."""
    T = _inv(T_base_cam) @ T_base_board
    if T[2, 2] <= 0:  # board z (into the plate) must point away from the camera
        return 0.0
    p = board.corners_m @ T[:3, :3].T + T[:3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    ok = (z > 0.05) & (u >= border_px) & (u <= size[0] - 1 - border_px) & (v >= border_px) & (v <= size[1] - 1 - border_px)
    return float(ok.mean())


def calibration_views(T_base_board: np.ndarray, board: CharucoBoardConfig, K: np.ndarray, size: tuple[int, int],
                      n: int, *, seed: int = 0, tilt_deg: float = 25.0, roll_deg: float = 45.0,
                      distance_m: tuple[float, float] = (0.35, 0.6), min_visible: float = 0.9,
                      max_tries: int = 50) -> np.ndarray:
    """``n`` camera poses T_base_cam (n, 4, 4) looking at the board, diverse in the ways hand-eye
    needs: the optical axis tilted up to ``tilt_deg`` from the board normal (azimuths spread by the
    golden angle), rolled up to ``roll_deg`` about itself (roll 0: image axes along the board's),
    ``distance_m`` from the board, aimed a little off its centre. Every pose sees at least
    ``min_visible`` of the corners (intrinsics ``K``, image ``size`` (W, H)). Deterministic in ``seed``."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    lo, hi = distance_m
    if not 0.05 < lo <= hi:
        raise ValueError(f"distance_m must be (near, far) with 0.05 < near <= far, got {distance_m}")
    rng = np.random.default_rng(seed)
    Tb = np.asarray(T_base_board, dtype=np.float64)
    ex, ey, normal = Tb[:3, 0], Tb[:3, 1], -Tb[:3, 2]  # the printed face looks along -z of the board
    w, h = board.size_m
    golden = math.pi * (3.0 - math.sqrt(5.0))
    out = []
    for i in range(n):
        for _ in range(max_tries):
            # tilt biased towards the outer half: large rotations between views make X observable
            tilt = math.radians(tilt_deg) * math.sqrt(rng.uniform(0.2, 1.0))
            azim = i * golden + rng.uniform(-0.3, 0.3)
            d = lo + (hi - lo) * ((i * 0.618034 + rng.uniform(0.0, 0.2)) % 1.0)
            roll = math.radians(rng.uniform(-roll_deg, roll_deg))
            aim = Tb @ np.array([w * rng.uniform(0.35, 0.65), h * rng.uniform(0.35, 0.65), 0.0, 1.0])
            back = math.cos(tilt) * normal + math.sin(tilt) * (math.cos(azim) * ex + math.sin(azim) * ey)
            z = -back
            y = ey - (ey @ z) * z
            y /= np.linalg.norm(y)
            x = np.cross(y, z)
            R = np.column_stack([x, y, z]) @ Rotation.from_euler("z", roll).as_matrix()
            T = _pose(R, aim[:3] + d * back)
            if corners_in_view(T, Tb, board, K, size) >= min_visible:
                out.append(T)
                break
        else:
            raise ValueError(f"no view {i} sees {min_visible:.0%} of the board within {max_tries} tries: "
                             f"distance {distance_m} m too short for the board, or the field of view too narrow")
    return np.array(out)
