"""Forward kinematics of a serial chain read from a URDF, for many configurations in one compiled
pass (numba): the one batched FK of the cell. The planners' IK calls it some 500 times per cut plan
on ~15,000 rows; the Franka driver checks every sample of a trajectory against its workspace with it.
It lives here because planners/ and drivers/ may not import each other (tests/test_rooms.py).

Pinocchio only reads the URDF (joint placements, axes, the frame's placement): numpy's way (an
(N,4,4) temporary per joint and per product) spent more time allocating than multiplying."""

from __future__ import annotations

from collections.abc import Sequence

import numba as nb
import numpy as np
import pinocchio as pin

_AXES = {"X": np.array([1.0, 0.0, 0.0]), "Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}


@nb.njit(cache=True, nogil=True)
def fk_kernel(Q, M, axis, iq, revolute, F, T_out, ax_out, org_out, want_axes):
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
    (S,3), their columns of q (S,), revolute or prismatic (S,), and the frame's placement (4,4).
    ``steps``: (placement, "R" or "P", axis, column of q) from the root out, as ``chain_steps`` gives."""

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
        fk_kernel(np.ascontiguousarray(Q, dtype=np.float64), self.M, self.axis, self.iq, self.revolute, self.F,
               T, none, none, False)
        return T

    def poses_axes(self, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(frame poses (N,4,4), joint axes (N,dof,3), joint origins (N,dof,3), NaN for prismatic
        joints) in the base frame: what a Jacobian is made of."""
        n = len(Q)
        T = np.empty((n, 4, 4))
        ax = np.zeros((n, self.dof, 3))
        org = np.full((n, self.dof, 3), np.nan)
        fk_kernel(np.ascontiguousarray(Q, dtype=np.float64), self.M, self.axis, self.iq, self.revolute, self.F,
               T, ax, org, True)
        return T, ax, org

    @classmethod
    def from_urdf(cls, urdf_path: str, joint_names: Sequence[str], frame: str) -> "Chain":
        """The chain of ``frame`` with q ordered as ``joint_names``; every other joint of the URDF (the
        Panda's fingers) is locked at neutral. ValueError for an unknown joint or frame, or a joint the
        kernel cannot move (not 1-DOF revolute or prismatic)."""
        full = pin.buildModelFromUrdf(str(urdf_path))
        names = list(full.names)
        missing = [n for n in joint_names if n not in names]
        if missing:
            raise ValueError(f"joints {missing} not in {urdf_path}")
        lock = [full.getJointId(n) for n in names[1:] if n not in joint_names]
        model = pin.buildReducedModel(full, lock, pin.neutral(full)) if lock else full
        if not model.existFrame(frame):
            raise ValueError(f"frame {frame!r} not in {urdf_path}")
        column = {model.joints[model.getJointId(n)].idx_q: k for k, n in enumerate(joint_names)}
        steps, F = chain_steps(model, model.getFrameId(frame), column)
        if steps is None:
            raise ValueError(f"the chain of {frame!r} in {urdf_path} has a joint that is not 1-DOF revolute or prismatic")
        return cls(steps, F, len(joint_names))


def chain_steps(model: pin.Model, frame_id: int, column: dict[int, int]) -> tuple[list | None, np.ndarray]:
    """(steps, the frame's placement) of the chain root -> ``frame_id`` of a Pinocchio model, each
    joint's q column given by ``column`` (its idx_q -> column); steps is None when a joint on the way
    is not a 1-DOF revolute or prismatic joint."""
    f = model.frames[frame_id]
    joints = []
    j = f.parentJoint
    while j > 0:
        joints.append(j)
        j = model.parents[j]
    steps = []
    for j in reversed(joints):
        jm = model.joints[j]
        short = jm.shortname()
        M = model.jointPlacements[j].homogeneous.copy()
        if short in ("JointModelRX", "JointModelRY", "JointModelRZ", "JointModelPX", "JointModelPY", "JointModelPZ"):
            axis = _AXES[short[-1]]
        elif short in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
            axis = np.asarray(jm.extract().axis, dtype=np.float64).copy()
        else:
            return None, f.placement.homogeneous.copy()
        if jm.idx_q not in column:
            return None, f.placement.homogeneous.copy()
        steps.append((M, "P" if short.startswith("JointModelP") else "R", axis, column[jm.idx_q]))
    return steps, f.placement.homogeneous.copy()
