"""Inverse kinematics for many targets at once: the damped-least-squares step of ``ik.py``, with the
roll about the tool axis free, vectorized over targets in numpy (one FK chain and one batched 5x5
solve per iteration for all of them). A cut's ladder graph needs thousands of solutions (every path
point x every tilt in the tolerance cone x several seeds); one call solves them all."""

from __future__ import annotations

import numpy as np

from .ik import MAX_STEP, ROT_WEIGHT, _DAMP0, _DAMP_K, _shrunk_limits
from .kinematics import Kinematics

#: iterations without progress after which a target is given up
STALL = 20


def _chain(kin: Kinematics, Q: np.ndarray, frame: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tool pose (B,4,4), joint axes (B,dof,3) and joint origins (B,dof,3, NaN for prismatic
    joints) in the base frame (``chain_kernel``)."""
    return kin._kernels[frame].poses_axes(Q)


def spread_seeds(kin: Kinematics, q_start: np.ndarray, count: int, margin: float) -> np.ndarray:
    """(count, dof) starts for a batch: ``q_start`` (clamped into the limits shrunk by ``margin``),
    then configurations drawn uniformly inside them, the same on every call (seed 0)."""
    lo, hi = kin.lower + margin, kin.upper - margin
    rng = np.random.default_rng(0)
    seeds = [np.clip(q_start, lo, hi)]
    if count > 1:
        seeds += list(rng.uniform(lo, hi, size=(count - 1, kin.dof)))
    return np.array(seeds)


def solve_axis_ik_batch(kin: Kinematics, positions: np.ndarray, axes: np.ndarray, Q0: np.ndarray, *,
                        margin: float = 0.05, tol_pos: float = 1e-4, tol_ang: float = 1e-3,
                        max_iter: int = 150, frame: str = "cam",
                        x_axes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Joint angles putting the tool origin at ``positions[i]`` with its z axis along ``axes[i]``
    (roll free), started from ``Q0[i]``, for all i at once. With ``x_axes`` the roll is fixed too
    (the tool's x axis along ``x_axes[i]``, made orthogonal to z): the full 6-D pose.

    Returns (Q (B,dof), ok (B,) bool): ok where both tolerances were met inside the joint limits
    shrunk by ``margin``; Q rows where not ok hold the best attempt."""
    if not kin._chain_ok:
        raise ValueError("batched IK needs a chain of 1-DOF revolute/prismatic joints")
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    Z = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    Q = np.array(Q0, dtype=np.float64).reshape(-1, kin.dof)
    if not (len(P) == len(Z) == len(Q)):
        raise ValueError(f"positions, axes and Q0 must have the same length, got {len(P)}, {len(Z)}, {len(Q)}")
    Z = Z / np.linalg.norm(Z, axis=1, keepdims=True)
    Rt = None
    if x_axes is not None:  # target rotations for the full pose
        X = np.asarray(x_axes, dtype=np.float64).reshape(-1, 3)
        X = X - np.einsum("ij,ij->i", X, Z)[:, None] * Z
        X /= np.linalg.norm(X, axis=1, keepdims=True)
        Rt = np.stack([X, np.cross(Z, X), Z], axis=2)
    lo, hi = _shrunk_limits(kin, margin)
    Q = np.ascontiguousarray(np.clip(Q, lo, hi))
    if Rt is None:  # the roll free: every row in one compiled pass (chain_kernel.axis_ik)
        ok = kin._kernels[frame].axis_ik(P, Z, Q, lo, hi, tol_pos, tol_ang, max_iter, STALL, ROT_WEIGHT, _DAMP_K,
                                         _DAMP0, MAX_STEP)
        return Q, ok
    ok = np.zeros(len(Q), dtype=bool)
    active = np.arange(len(Q))
    best = np.full(len(Q), np.inf)  # lowest error so far, and the iteration it was reached
    best_at = np.zeros(len(Q), dtype=np.int64)
    for it in range(max_iter + 1):
        if len(active) == 0:
            break
        q = Q[active]
        T, ax, org = _chain(kin, q, frame)
        p, R = T[:, :3, 3], T[:, :3, :3]
        z_t = Z[active]
        e_pos = P[active] - p
        if Rt is None:
            z = R[:, :, 2]
            c = np.cross(z, z_t)
            s = np.linalg.norm(c, axis=1)
            ang = np.arctan2(s, np.einsum("ij,ij->i", z, z_t))
            w = np.where((s > 1e-12)[:, None], c * (ang / np.maximum(s, 1e-12))[:, None],
                         np.where((ang > 1.0)[:, None], R[:, :, 0] * ang[:, None], 0.0))
        else:  # rotation vector of R_t R^T
            w, ang = _log3(Rt[active] @ R.transpose(0, 2, 1))
        err = np.linalg.norm(e_pos, axis=1) + ROT_WEIGHT * ang
        better = err < 0.99 * best[active]
        best[active[better]], best_at[active[better]] = err[better], it
        done = (np.linalg.norm(e_pos, axis=1) < tol_pos) & (ang < tol_ang)
        ok[active[done]] = True
        # a target whose error has not fallen 1 % in STALL iterations is stuck (out of reach, on a limit)
        keep = ~done & (it - best_at[active] < STALL)
        if not keep.any():
            break
        active, q, p, R, ax, org, e_pos, w = (a[keep] for a in (active, q, p, R, ax, org, e_pos, w))
        lever = p[:, None, :] - org
        J_lin = np.where(np.isnan(lever), ax, np.cross(ax, np.nan_to_num(lever)))  # prismatic: the axis itself
        J_ang = np.where(np.isnan(org), 0.0, ax)
        # free roll: the rotation error along the current x and y axes only; fixed: all three
        Rxy = R[:, :, :2].transpose(0, 2, 1) if Rt is None else np.broadcast_to(np.eye(3), (len(q), 3, 3))
        A = np.concatenate([J_lin.transpose(0, 2, 1), ROT_WEIGHT * (Rxy @ J_ang.transpose(0, 2, 1))], axis=1)
        e = np.concatenate([e_pos, ROT_WEIGHT * np.einsum("bij,bj->bi", Rxy, w)], axis=1)
        m = A.shape[1]
        cost = np.einsum("bi,bi->b", e, e)
        lam2 = _DAMP_K * cost + _DAMP0
        for _ in range(2):  # freeze joints on a bound whose step points further out, then re-solve
            H = A @ A.transpose(0, 2, 1) + lam2[:, None, None] * np.eye(m)
            dq = np.einsum("bji,bj->bi", A, np.linalg.solve(H, e[:, :, None])[:, :, 0])
            blocked = ((q <= lo + 1e-9) & (dq < 0)) | ((q >= hi - 1e-9) & (dq > 0))
            if not blocked.any():
                break
            A = A * ~blocked[:, None, :]
        step = np.abs(dq).max(axis=1)
        dq *= np.minimum(1.0, MAX_STEP / np.maximum(step, 1e-12))[:, None]
        Q[active] = np.clip(q + dq, lo, hi)
    return Q, ok


def _log3(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vectors (B,3) and angles (B,) of rotation matrices (B,3,3)."""
    from scipy.spatial.transform import Rotation

    w = Rotation.from_matrix(R).as_rotvec()
    return w, np.linalg.norm(w, axis=1)
