"""The batched IK kernel of the cut's ladder, on the cell's one batched FK (configs.chain): a chain
that also solves the free-roll IK row by row in compiled code."""

from __future__ import annotations

import numba as nb
import numpy as np

from configs import chain as _fk
from configs.chain import fk_kernel


class Chain(_fk.Chain):
    """``configs.chain.Chain`` with the free-roll batched IK."""

    def axis_ik(self, P: np.ndarray, Z: np.ndarray, Q: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                tol_pos: float, tol_ang: float, max_iter: int, stall: int, rot_w: float, damp_k: float,
                damp0: float, max_step: float) -> np.ndarray:
        """``axis_ik`` on every row of Q (B,dof), in place; returns ok (B,)."""
        ok = np.zeros(len(Q), dtype=np.bool_)
        axis_ik(np.ascontiguousarray(P, dtype=np.float64), np.ascontiguousarray(Z, dtype=np.float64), Q,
                np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64),
                self.M, self.axis, self.iq, self.revolute, self.F, float(tol_pos), float(tol_ang), int(max_iter),
                int(stall), float(rot_w), float(damp_k), float(damp0), float(max_step), ok)
        return ok


def warmup() -> None:
    """Compile (or load from numba's cache) the kernels before the first timed plan."""
    c = Chain([(np.eye(4), "R", np.array([0.0, 0.0, 1.0]), 0)], np.eye(4), 1)
    c.poses_axes(np.zeros((1, 1)))
    c.axis_ik(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.zeros((1, 1)), np.array([-1.0]), np.array([1.0]),
              1e-4, 1e-3, 1, 1, 0.2, 1.0, 1e-4, 0.4)


@nb.njit(cache=True, nogil=True)
def _fk_axes_row(q, M, axis, iq, revolute, F, T, ax, org):
    """One configuration's frame pose T (4,4), joint axes ax (dof,3) and origins org (dof,3)."""
    Q = q.reshape(1, -1)
    T3 = T.reshape(1, 4, 4)
    fk_kernel(Q, M, axis, iq, revolute, F, T3, ax.reshape(1, ax.shape[0], 3), org.reshape(1, org.shape[0], 3), True)


@nb.njit(cache=True, nogil=True)
def _cholesky_solve(H, e, y):
    """y = H^-1 e for a small symmetric positive definite H (damped normal equations), in place
    on H (its lower triangle becomes the Cholesky factor)."""
    n = H.shape[0]
    for i in range(n):
        for j in range(i + 1):
            acc = H[i, j]
            for k in range(j):
                acc -= H[i, k] * H[j, k]
            if i == j:
                H[i, i] = np.sqrt(acc)
            else:
                H[i, j] = acc / H[j, j]
    for i in range(n):  # forward: L z = e
        acc = e[i]
        for k in range(i):
            acc -= H[i, k] * y[k]
        y[i] = acc / H[i, i]
    for i in range(n - 1, -1, -1):  # back: L^T y = z
        acc = y[i]
        for k in range(i + 1, n):
            acc -= H[k, i] * y[k]
        y[i] = acc / H[i, i]


@nb.njit(cache=True, nogil=True)
def axis_ik(P, Z, Q, lo, hi, M, axis, iq, revolute, F, tol_pos, tol_ang, max_iter, stall,
            rot_w, damp_k, damp0, max_step, ok):
    """Damped least squares per row, in place on Q (B,dof): the tool origin to P[b], its z axis
    along the unit Z[b], roll free (the rotation error along the tool's x and y axes only). The
    numpy loop of ``ik_batch`` row by row: a row stops when both tolerances are met (ok[b]) or its
    error has not fallen 1 % in ``stall`` iterations; joints on a limit whose step points further
    out are frozen and the step solved again."""
    B, dof = Q.shape
    T = np.empty((4, 4))
    ax = np.zeros((dof, 3))
    org = np.zeros((dof, 3))
    A = np.empty((5, dof))
    e = np.empty(5)
    H = np.empty((5, 5))
    y = np.empty(5)
    q = np.empty(dof)
    dq = np.empty(dof)
    for b in range(B):
        for j in range(dof):
            q[j] = Q[b, j]
        best, best_at = np.inf, 0
        for it in range(max_iter + 1):
            _fk_axes_row(q, M, axis, iq, revolute, F, T, ax, org)
            px, py, pz = T[0, 3], T[1, 3], T[2, 3]
            ex, ey, ez = P[b, 0] - px, P[b, 1] - py, P[b, 2] - pz
            zx, zy, zz = T[0, 2], T[1, 2], T[2, 2]
            tx, ty, tz = Z[b, 0], Z[b, 1], Z[b, 2]
            cx, cy, cz = zy * tz - zz * ty, zz * tx - zx * tz, zx * ty - zy * tx
            s = np.sqrt(cx * cx + cy * cy + cz * cz)
            ang = np.arctan2(s, zx * tx + zy * ty + zz * tz)
            if s > 1e-12:
                f = ang / s
                wx, wy, wz = cx * f, cy * f, cz * f
            elif ang > 1.0:  # pointing the opposite way: turn about the tool's x axis
                wx, wy, wz = T[0, 0] * ang, T[1, 0] * ang, T[2, 0] * ang
            else:
                wx, wy, wz = 0.0, 0.0, 0.0
            epos = np.sqrt(ex * ex + ey * ey + ez * ez)
            err = epos + rot_w * ang
            if err < 0.99 * best:
                best, best_at = err, it
            if epos < tol_pos and ang < tol_ang:
                ok[b] = True
                break
            if it - best_at >= stall:
                break
            for j in range(dof):
                a0, a1, a2 = ax[j, 0], ax[j, 1], ax[j, 2]
                if np.isnan(org[j, 0]):  # prismatic: moves the tool along its axis, turns nothing
                    A[0, j], A[1, j], A[2, j] = a0, a1, a2
                    g0, g1, g2 = 0.0, 0.0, 0.0
                else:
                    lx, ly, lz = px - org[j, 0], py - org[j, 1], pz - org[j, 2]
                    A[0, j], A[1, j], A[2, j] = a1 * lz - a2 * ly, a2 * lx - a0 * lz, a0 * ly - a1 * lx
                    g0, g1, g2 = a0, a1, a2
                A[3, j] = rot_w * (T[0, 0] * g0 + T[1, 0] * g1 + T[2, 0] * g2)
                A[4, j] = rot_w * (T[0, 1] * g0 + T[1, 1] * g1 + T[2, 1] * g2)
            e[0], e[1], e[2] = ex, ey, ez
            e[3] = rot_w * (T[0, 0] * wx + T[1, 0] * wy + T[2, 0] * wz)
            e[4] = rot_w * (T[0, 1] * wx + T[1, 1] * wy + T[2, 1] * wz)
            lam2 = damp_k * (e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4]) + damp0
            for _ in range(2):
                for r in range(5):
                    for c in range(5):
                        acc = lam2 if r == c else 0.0
                        for j in range(dof):
                            acc += A[r, j] * A[c, j]
                        H[r, c] = acc
                _cholesky_solve(H, e, y)
                blocked = False
                for j in range(dof):
                    acc = 0.0
                    for r in range(5):
                        acc += A[r, j] * y[r]
                    dq[j] = acc
                for j in range(dof):
                    if (q[j] <= lo[j] + 1e-9 and dq[j] < 0) or (q[j] >= hi[j] - 1e-9 and dq[j] > 0):
                        blocked = True
                        for r in range(5):
                            A[r, j] = 0.0
                if not blocked:
                    break
            step = 0.0
            for j in range(dof):
                step = max(step, abs(dq[j]))
            k = min(1.0, max_step / max(step, 1e-12))
            for j in range(dof):
                q[j] = min(max(q[j] + k * dq[j], lo[j]), hi[j])
            if it == max_iter:
                break
        for j in range(dof):
            Q[b, j] = q[j]
