"""Forward kinematics of a serial chain for many configurations in one compiled pass (numba): the
batched IK of a cut's ladder calls it some 500 times per plan on ~15,000 rows, and numpy's way
(a (N,4,4) temporary per joint and per matrix product) spent more time allocating than multiplying."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def _chain(Q, M, axis, iq, revolute, F, T_out, ax_out, org_out, want_axes):
    n, S = Q.shape[0], M.shape[0]
    T = np.empty((4, 4))
    A = np.empty((4, 4))
    J = np.empty((4, 4))
    for b in range(n):
        for r in range(4):
            for c in range(4):
                T[r, c] = 1.0 if r == c else 0.0
        for k in range(S):
            for r in range(4):  # A = T @ M[k]
                for c in range(4):
                    A[r, c] = T[r, 0] * M[k, 0, c] + T[r, 1] * M[k, 1, c] + T[r, 2] * M[k, 2, c] + T[r, 3] * M[k, 3, c]
            a0, a1, a2 = axis[k, 0], axis[k, 1], axis[k, 2]
            j = iq[k]
            if want_axes:
                for r in range(3):
                    ax_out[b, j, r] = A[r, 0] * a0 + A[r, 1] * a1 + A[r, 2] * a2
                    org_out[b, j, r] = A[r, 3] if revolute[k] else np.nan
            x = Q[b, j]
            for r in range(4):
                for c in range(4):
                    J[r, c] = 1.0 if r == c else 0.0
            if revolute[k]:  # Rodrigues: I + sin K + (1 - cos) K^2, K the axis' cross-product matrix
                s, v = np.sin(x), 1.0 - np.cos(x)
                J[0, 0] = 1.0 - v * (a1 * a1 + a2 * a2)
                J[1, 1] = 1.0 - v * (a0 * a0 + a2 * a2)
                J[2, 2] = 1.0 - v * (a0 * a0 + a1 * a1)
                J[0, 1], J[1, 0] = -s * a2 + v * a0 * a1, s * a2 + v * a0 * a1
                J[0, 2], J[2, 0] = s * a1 + v * a0 * a2, -s * a1 + v * a0 * a2
                J[1, 2], J[2, 1] = -s * a0 + v * a1 * a2, s * a0 + v * a1 * a2
            else:
                J[0, 3], J[1, 3], J[2, 3] = x * a0, x * a1, x * a2
            for r in range(4):  # T = A @ J
                for c in range(4):
                    T[r, c] = A[r, 0] * J[0, c] + A[r, 1] * J[1, c] + A[r, 2] * J[2, c] + A[r, 3] * J[3, c]
        for r in range(4):
            for c in range(4):
                T_out[b, r, c] = T[r, 0] * F[0, c] + T[r, 1] * F[1, c] + T[r, 2] * F[2, c] + T[r, 3] * F[3, c]


class Chain:
    """A serial chain root -> frame as arrays for the kernel: joint placements (S,4,4), unit axes
    (S,3), their columns of q (S,), revolute or prismatic (S,), and the frame's placement (4,4)."""

    def __init__(self, steps, F: np.ndarray, dof: int) -> None:
        self.M = np.ascontiguousarray([s[0] for s in steps], dtype=np.float64).reshape(-1, 4, 4)
        self.axis = np.ascontiguousarray([s[2] for s in steps], dtype=np.float64).reshape(-1, 3)
        self.iq = np.array([s[3] for s in steps], dtype=np.int64)
        self.revolute = np.array([s[1] == "R" for s in steps], dtype=np.bool_)
        self.F = np.ascontiguousarray(F, dtype=np.float64)
        self.dof = dof

    def poses(self, Q: np.ndarray) -> np.ndarray:
        """Frame poses (N,4,4) for configurations Q (N,dof)."""
        T = np.empty((len(Q), 4, 4))
        none = np.empty((0, 0, 0))
        _chain(np.ascontiguousarray(Q, dtype=np.float64), self.M, self.axis, self.iq, self.revolute, self.F,
               T, none, none, False)
        return T

    def poses_axes(self, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(frame poses (N,4,4), joint axes (N,dof,3), joint origins (N,dof,3), NaN for prismatic
        joints) in the base frame: what a Jacobian is made of."""
        n = len(Q)
        T = np.empty((n, 4, 4))
        ax = np.zeros((n, self.dof, 3))
        org = np.full((n, self.dof, 3), np.nan)
        _chain(np.ascontiguousarray(Q, dtype=np.float64), self.M, self.axis, self.iq, self.revolute, self.F,
               T, ax, org, True)
        return T, ax, org


def warmup() -> None:
    """Compile (or load from numba's cache) the kernel before the first timed plan."""
    Chain([(np.eye(4), "R", np.array([0.0, 0.0, 1.0]), 0)], np.eye(4), 1).poses_axes(np.zeros((1, 1)))
