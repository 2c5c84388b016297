"""Camera inverse kinematics: joint angles that put the eye-in-hand camera at a requested pose.

Solver: Levenberg–Marquardt / damped least squares on the camera frame (Pinocchio Jacobian,
world-aligned at the camera origin), damping ``lambda^2 = |e|^2 + 1e-4`` (Sugihara 2011), step
capped at ``MAX_STEP`` rad, and joint limits shrunk by ``margin`` enforced as an active set: a
joint sitting on a bound whose step would push it further out is frozen for that iteration (its
column removed and the step re-solved), then the result is clamped. Restarts from deterministic
random seeds inside the shrunk limits when the current configuration does not converge.

With ``free_roll=True`` (the default, right for a viewpoint) the residual is 5-D: camera position
(3) and the direction of the optical axis (2: the rotation that aligns the current z axis with
the target z, expressed along the current x and y axes); the roll about the optical axis is free.
With ``free_roll=False`` the full 6-D pose is matched (rotation residual ``log(R_t R^T)``).

Collisions are not considered here; callers check the returned configuration separately.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .kinematics import Kinematics

MAX_STEP = 0.4  # rad: largest joint change per iteration (keeps the linearisation honest)
ROT_WEIGHT = 0.2  # m/rad: 1 rad of orientation error weighs like 0.2 m of position error
_DAMP_K = 1.0  # LM damping lambda^2 = _DAMP_K * |e|^2 + _DAMP0 (weighted residual, m^2)
_DAMP0 = 1e-4
_STALL_WINDOW = 25  # iterations without >1 % improvement before a seed is abandoned


class Unreachable(Exception):
    """No joint configuration within limits puts the camera at the requested pose.

    Attributes:
        reason: human-readable explanation (also ``str(exc)``).
        position: requested camera position (3,) in the base frame, or None.
        axis: requested optical axis (3,) in the base frame, or None.
        best_position_error_m, best_angle_error_rad: best residual reached over all seeds
            (inf when no solve was attempted, e.g. the target is out of reach).
    """

    def __init__(
        self,
        reason: str,
        *,
        position: np.ndarray | None = None,
        axis: np.ndarray | None = None,
        best_position_error_m: float = math.inf,
        best_angle_error_rad: float = math.inf,
    ) -> None:
        super().__init__(reason)
        self.reason = reason
        self.position = position
        self.axis = axis
        self.best_position_error_m = best_position_error_m
        self.best_angle_error_rad = best_angle_error_rad


@dataclass(frozen=True)
class IKResult:
    q: np.ndarray  # (dof,) joint angles, inside [lower + margin, upper - margin]
    position_error_m: float  # |p_target - p_cam|
    angle_error_rad: float  # optical-axis angle (free_roll) or full rotation angle
    iterations: int  # iterations of the successful seed
    seed_index: int  # 0 = q_seed, k >= 1 = k-th random seed


def _fmt(v: np.ndarray, nd: int = 3) -> str:
    return "[" + " ".join(f"{x:.{nd}f}" for x in v) + "]"


def _check_pose(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} contains NaN or inf")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ValueError(f"{name} rotation is not a proper orthonormal matrix")
    return T


def _shrunk_limits(kin: Kinematics, margin: float) -> tuple[np.ndarray, np.ndarray]:
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin must be a finite non-negative angle, got {margin}")
    lo = kin.lower + margin
    hi = kin.upper - margin
    if not np.all(lo < hi):
        raise ValueError(f"margin {margin} rad leaves an empty range for joints {np.nonzero(lo >= hi)[0].tolist()}")
    return lo, hi


def _solve_from(
    kin: Kinematics,
    q: np.ndarray,
    p_t: np.ndarray,
    R_t: np.ndarray,
    free_roll: bool,
    lo: np.ndarray,
    hi: np.ndarray,
    tol_pos: float,
    tol_ang: float,
    max_iter: int,
) -> tuple[bool, np.ndarray, float, float, int]:
    """One LM run from q (already inside [lo, hi]). Returns (ok, q, pos_err, ang_err, iters)."""
    z_t = R_t[:, 2]
    cam_id = kin._cam_id
    m = 5 if free_roll else 6
    e = np.empty(m)
    A = np.empty((m, kin.dof))
    eye_m = np.eye(m)
    best_cost = math.inf
    best = (q.copy(), math.inf, math.inf)
    since_best = 0
    for it in range(max_iter + 1):
        T, J = kin._pose_jac(q, cam_id)
        R = T[:3, :3]
        e[:3] = p_t - T[:3, 3]
        pos_err = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        if free_roll:
            z = R[:, 2]
            c = np.cross(z, z_t)
            s = math.sqrt(c @ c)
            ang = math.atan2(s, float(z @ z_t))
            if s > 1e-12:
                w = c * (ang / s)
            elif ang > 1.0:  # exactly opposite: rotate about the current x axis
                w = R[:, 0] * ang
            else:
                w = np.zeros(3)
            Rxy = R[:, :2].T  # rotation error along current x, y (the z component is ~0)
            e[3:] = ROT_WEIGHT * (Rxy @ w)
            A[:3] = J[:3]
            A[3:] = ROT_WEIGHT * (Rxy @ J[3:])
        else:
            w = pin.log3(R_t @ R.T)
            ang = math.sqrt(w @ w)
            e[3:] = ROT_WEIGHT * w
            A[:3] = J[:3]
            A[3:] = ROT_WEIGHT * J[3:]
        if pos_err < tol_pos and ang < tol_ang:
            return True, q, pos_err, ang, it
        cost = float(e @ e)
        if cost < best_cost * 0.99:
            best_cost = cost
            best = (q.copy(), pos_err, ang)
            since_best = 0
        else:
            since_best += 1
            if since_best >= _STALL_WINDOW:
                break
        if it == max_iter:
            break
        lam2 = _DAMP_K * cost + _DAMP0
        # active set: freeze joints on a bound whose step points further out, re-solve
        at_lo = q <= lo + 1e-9
        at_hi = q >= hi - 1e-9
        Aw = A
        for _ in range(3):
            dq = Aw.T @ np.linalg.solve(Aw @ Aw.T + lam2 * eye_m, e)
            blocked = (at_lo & (dq < 0)) | (at_hi & (dq > 0))
            if not blocked.any():
                break
            Aw = A.copy() if Aw is A else Aw
            Aw[:, blocked] = 0.0
            at_lo = at_lo & ~blocked
            at_hi = at_hi & ~blocked
        dq[(q <= lo + 1e-9) & (dq < 0)] = 0.0
        dq[(q >= hi - 1e-9) & (dq > 0)] = 0.0
        step = np.abs(dq).max()
        if step > MAX_STEP:
            dq *= MAX_STEP / step
        q = np.minimum(np.maximum(q + dq, lo), hi)
    return False, best[0], best[1], best[2], it


def solve_camera_ik(
    kin: Kinematics,
    T_target_cam: np.ndarray,
    q_seed: np.ndarray,
    *,
    free_roll: bool = True,
    margin: float = 0.05,
    seeds: int = 8,
    rng_seed: int = 0,
    tol_pos: float = 1e-4,
    tol_ang: float = 1e-3,
    max_iter: int = 200,
    accept: Callable[[np.ndarray], bool] | None = None,
) -> IKResult:
    """Joint angles that put the camera at ``T_target_cam`` (T_base_cam wanted).

    Args:
        kin: the arm's kinematics (camera frame included).
        T_target_cam: 4x4 wanted camera pose in the base frame.
        q_seed: current configuration (dof,); tried first (clamped into the shrunk limits).
        free_roll: leave the roll about the optical axis free (5-D task) or match the full pose.
        margin: rad kept from every joint limit; the solution satisfies lower+margin <= q <= upper-margin.
        seeds: total number of starts: q_seed, then ``seeds - 1`` random configurations drawn
            (deterministically from ``rng_seed``) uniformly inside the shrunk limits.
        tol_pos: m, tol_ang: rad, convergence tolerances (angle of the optical axis when
            free_roll, of the full rotation otherwise).
        max_iter: iterations per seed (a seed also stops early when it stalls).
        accept: optional test of a converged configuration (e.g. collision-free); a solution it
            rejects does not count and the next seed is tried.

    Returns:
        IKResult of the first seed that converges (seed 0 = q_seed, so the solution stays near
        the current configuration whenever that is possible).

    Raises:
        Unreachable: no seed converged, or the target is beyond the arm's reach.
        ValueError: malformed inputs (shapes, NaN, non-rigid pose, bad margin/tolerances).
    """
    T_t = _check_pose(T_target_cam, "T_target_cam")
    q0 = kin._vec(q_seed, "q_seed")
    lo, hi = _shrunk_limits(kin, margin)
    if seeds < 1:
        raise ValueError(f"seeds must be >= 1, got {seeds}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if not (tol_pos > 0 and tol_ang > 0):
        raise ValueError(f"tol_pos and tol_ang must be positive, got {tol_pos}, {tol_ang}")
    p_t = T_t[:3, 3].copy()
    R_t = T_t[:3, :3].copy()
    z_t = R_t[:, 2]
    what = f"camera at {_fmt(p_t)} looking along {_fmt(z_t)}"

    center, radius = kin.reach_sphere("cam")
    dist = float(np.linalg.norm(p_t - center))
    if dist > radius + tol_pos:
        raise Unreachable(
            f"no IK solution for {what}: it is {dist:.3f} m from the first joint at {_fmt(center)}, "
            f"beyond the arm's reach of {radius:.3f} m",
            position=p_t,
            axis=z_t,
        )

    rng = np.random.default_rng(rng_seed)
    starts = np.empty((seeds, kin.dof))
    starts[0] = np.minimum(np.maximum(q0, lo), hi)
    if seeds > 1:
        starts[1:] = rng.uniform(lo, hi, size=(seeds - 1, kin.dof))

    best_pos, best_ang, best_cost = math.inf, math.inf, math.inf
    refused = 0
    for k in range(seeds):
        ok, q, pe, ae, its = _solve_from(
            kin, starts[k].copy(), p_t, R_t, free_roll, lo, hi, tol_pos, tol_ang, max_iter
        )
        if ok and accept is not None and not accept(q):
            refused += 1
            continue
        if ok:
            return IKResult(q=q, position_error_m=pe, angle_error_rad=ae, iterations=its, seed_index=k)
        cost = pe * pe + (ROT_WEIGHT * ae) ** 2
        if cost < best_cost:
            best_pos, best_ang, best_cost = pe, ae, cost
    task = "optical axis" if free_roll else "full pose"
    if refused:
        raise Unreachable(f"{refused} IK solution(s) for {what} ({task}, {seeds} seeds), all refused "
                          "(in collision)", position=p_t, axis=z_t, best_position_error_m=0.0,
                          best_angle_error_rad=0.0)
    raise Unreachable(
        f"no IK solution within joint limits (margin {margin:g} rad) for {what} ({task}, {seeds} seeds): "
        f"best residual {best_pos:.4f} m / {math.degrees(best_ang):.2f} deg",
        position=p_t,
        axis=z_t,
        best_position_error_m=best_pos,
        best_angle_error_rad=best_ang,
    )


def solve_camera_ik_many(
    kin: Kinematics,
    poses: np.ndarray | Sequence[np.ndarray],
    q_seed: np.ndarray,
    **kwargs,
) -> tuple[int, IKResult]:
    """First reachable pose of a ranked list: tries ``poses`` (M, 4, 4) in order and returns
    ``(index, IKResult)`` of the first one ``solve_camera_ik`` solves; keyword arguments are
    passed on to it. Poses whose position is beyond the arm's reach are skipped without a solve
    (one vectorized test for all M).

    Raises:
        Unreachable: none of the M poses is reachable (message gives counts and the reason for
            the best-ranked pose).
        ValueError: malformed inputs.
    """
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (M, 4, 4), got {P.shape}")
    if P.shape[0] == 0:
        raise Unreachable("no candidate camera poses given")
    center, radius = kin.reach_sphere("cam")
    tol_pos = kwargs.get("tol_pos", 1e-4)
    in_reach = np.linalg.norm(P[:, :3, 3] - center, axis=1) <= radius + tol_pos
    first_reason = None
    for i in np.flatnonzero(in_reach):
        try:
            return int(i), solve_camera_ik(kin, P[i], q_seed, **kwargs)
        except Unreachable as exc:
            if first_reason is None:
                first_reason = f"pose {i}: {exc.reason}"
    n_far = int((~in_reach).sum())
    if first_reason is None:  # every pose was out of reach: report the first one
        try:
            solve_camera_ik(kin, P[0], q_seed, **kwargs)
        except Unreachable as exc:
            first_reason = f"pose 0: {exc.reason}"
    raise Unreachable(
        f"none of {P.shape[0]} candidate camera poses is reachable ({n_far} beyond reach, "
        f"{P.shape[0] - n_far} failed IK); first: {first_reason}"
    )
