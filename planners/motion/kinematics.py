"""Forward kinematics and camera Jacobian of a serial arm, from its URDF, with Pinocchio.

The model is reduced to the listed arm joints (every other joint, e.g. the Panda's fingers, is
locked at its neutral value) and an operational frame ``camera`` is attached to the flange link
with the hand-eye extrinsic ``T_flange_cam``. Poses are 4x4 float64 ``T_base_<frame>`` where
"base" is the URDF root link (pinocchio's universe frame).

Not thread-safe: one ``Kinematics`` owns one ``pinocchio.Data`` scratch buffer; give each thread
its own instance (construction takes a few ms).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from configs.chain import chain_steps

from .chain_kernel import Chain

CAM_FRAME_NAME = "scrapcell_camera_optical"

_AXES = {"X": np.array([1.0, 0.0, 0.0]), "Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}


def _as_pose(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 homogeneous transform, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} is not a rigid transform (rotation not orthonormal or bad last row)")
    return T


class Kinematics:
    """Kinematics of the arm joints ``joint_names`` up to ``flange_link`` and the camera on it.

    Args:
        urdf_path: URDF file (meshes are not loaded).
        joint_names: the actuated 1-DOF joints, in the order of the ``q`` vectors used everywhere
            else (the arm's driver order). All other joints of the URDF are locked at neutral.
        flange_link: URDF link the camera is mounted on (e.g. ``"panda_hand"``).
        T_flange_cam: 4x4 hand-eye extrinsic, camera optical frame -> flange link frame.
        lower, upper: optional position limits (7,) to intersect with the URDF's, e.g. the
            Panda's published controller limits (see ``limits.py``).

    Raises:
        ValueError: unknown joint or link name, a joint that is not 1-DOF, bad extrinsic/limits.
    """

    @classmethod
    def from_arm_model(cls, model) -> Kinematics:
        """The camera's kinematics of a driver's arm model (``drivers.interfaces.ArmModel``: its URDF,
        joints, flange, hand-eye and limits), one constructor for every part that moves that arm."""
        return cls(model.urdf_path, model.joint_names, model.flange_link, model.T_flange_cam,
                   lower=model.lower, upper=model.upper)

    def __init__(
        self,
        urdf_path: str,
        joint_names: Sequence[str],
        flange_link: str,
        T_flange_cam: np.ndarray,
        *,
        lower: np.ndarray | None = None,
        upper: np.ndarray | None = None,
    ) -> None:
        self.urdf_path = str(urdf_path)
        self.joint_names = tuple(joint_names)
        self.flange_link = flange_link
        self.T_flange_cam = _as_pose(T_flange_cam, "T_flange_cam").copy()

        full = pin.buildModelFromUrdf(self.urdf_path)
        full_names = list(full.names)
        missing = [n for n in self.joint_names if n not in full_names]
        if missing:
            raise ValueError(f"joints {missing} not in URDF {self.urdf_path}; it has {full_names[1:]}")
        if len(set(self.joint_names)) != len(self.joint_names):
            raise ValueError(f"duplicate joint names in {self.joint_names}")
        lock = [full.getJointId(n) for n in full_names[1:] if n not in self.joint_names]
        model = pin.buildReducedModel(full, lock, pin.neutral(full)) if lock else full

        if not model.existFrame(flange_link):
            links = [f.name for f in model.frames if f.type == pin.FrameType.BODY]
            raise ValueError(f"flange link {flange_link!r} not in URDF {self.urdf_path}; links: {links}")
        flange_id = model.getFrameId(flange_link)
        flange = model.frames[flange_id]

        self.dof = len(self.joint_names)
        if model.nq != self.dof or model.nv != self.dof:
            raise ValueError(f"reduced model has nq={model.nq}, nv={model.nv}; only 1-DOF joints are supported")
        jids = [model.getJointId(n) for n in self.joint_names]
        for n, j in zip(self.joint_names, jids):
            if model.joints[j].nq != 1:
                raise ValueError(f"joint {n!r} is {model.joints[j].shortname()}, only 1-DOF joints are supported")
        # q (driver order) -> pinocchio q order; identity for the Panda.
        self._idx = np.array([model.joints[j].idx_q for j in jids], dtype=np.intp)
        self._identity_order = bool(np.array_equal(self._idx, np.arange(self.dof)))

        cam_placement = flange.placement * pin.SE3(self.T_flange_cam[:3, :3].copy(), self.T_flange_cam[:3, 3].copy())
        self._cam_id = model.addFrame(
            pin.Frame(CAM_FRAME_NAME, flange.parentJoint, flange_id, cam_placement, pin.FrameType.OP_FRAME)
        )
        self._flange_id = flange_id
        self.model = model
        self.data = model.createData()
        self._frame_ids = {"cam": self._cam_id, "flange": self._flange_id}
        self._link_ids: dict[tuple[str, ...], list[int]] = {}

        lo = np.empty(self.dof)
        hi = np.empty(self.dof)
        lo[:] = model.lowerPositionLimit[self._idx]
        hi[:] = model.upperPositionLimit[self._idx]
        if lower is not None:
            lo = np.maximum(lo, self._vec(lower, "lower"))
        if upper is not None:
            hi = np.minimum(hi, self._vec(upper, "upper"))
        if not np.all(lo < hi):
            raise ValueError(f"empty joint range: lower={lo}, upper={hi}")
        self.lower = lo
        self.upper = hi
        self.lower.setflags(write=False)
        self.upper.setflags(write=False)

        self._build_chain()

    # ------------------------------------------------------------------ helpers

    def _vec(self, q: np.ndarray, name: str = "q") -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.dof,):
            raise ValueError(f"{name} must have shape ({self.dof},), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"{name} contains NaN or inf: {q}")
        return q

    def _to_pin(self, q: np.ndarray) -> np.ndarray:
        if self._identity_order:
            return q
        qp = np.empty(self.dof)
        qp[self._idx] = q
        return qp

    def _frame_id(self, frame: str) -> int:
        try:
            return self._frame_ids[frame]
        except KeyError:
            raise ValueError(f"frame must be 'cam' or 'flange', got {frame!r}") from None

    def within_limits(self, q: np.ndarray, margin: float = 0.0) -> bool:
        """True if lower + margin <= q <= upper - margin for every joint."""
        q = self._vec(q)
        return bool(np.all(q >= self.lower + margin) and np.all(q <= self.upper - margin))

    # ------------------------------------------------------------------ single configuration

    def fk(self, q: np.ndarray, frame: str = "cam") -> np.ndarray:
        """T_base_<frame> (4x4) at configuration q; frame is ``"cam"`` or ``"flange"``."""
        fid = self._frame_id(frame)
        q = self._vec(q)
        pin.framesForwardKinematics(self.model, self.data, self._to_pin(q))
        return self.data.oMf[fid].homogeneous.copy()

    def link_poses(self, q: np.ndarray, links: Sequence[str]) -> np.ndarray:
        """T_base_<link> (len(links), 4, 4) at q, in one FK pass: collision geometry hangs on every
        link, not just the flange. Locked joints (the fingers) sit at their neutral value."""
        q = self._vec(q)
        key = tuple(links)
        ids = self._link_ids.get(key)
        if ids is None:
            ids = self._link_ids[key] = [self.link_frame_id(n) for n in key]
        pin.framesForwardKinematics(self.model, self.data, self._to_pin(q))
        oMf = self.data.oMf
        return np.stack([oMf[i].homogeneous for i in ids]) if ids else np.empty((0, 4, 4))

    def link_frame_id(self, link: str) -> int:
        """Pinocchio frame id of a URDF link (ValueError naming the links if unknown)."""
        model = self.model
        if not isinstance(link, str) or not model.existFrame(link, pin.FrameType.BODY):
            links = [f.name for f in model.frames if f.type == pin.FrameType.BODY]
            raise ValueError(f"link {link!r} not in URDF {self.urdf_path}; links: {links}")
        return model.getFrameId(link, pin.FrameType.BODY)

    def jacobian_cam(self, q: np.ndarray) -> np.ndarray:
        """6x7 Jacobian of the camera frame: rows [v; w] of the camera origin, world-aligned axes."""
        return self.pose_and_jacobian(q)[1]

    def pose_and_jacobian(self, q: np.ndarray, frame: str = "cam") -> tuple[np.ndarray, np.ndarray]:
        """(T_base_<frame>, J) in one pass; J is 6xdof, LOCAL_WORLD_ALIGNED, columns in q order."""
        fid = self._frame_id(frame)
        return self._pose_jac(self._vec(q), fid)

    def _pose_jac(self, q: np.ndarray, fid: int) -> tuple[np.ndarray, np.ndarray]:
        # No validation: the IK inner loop calls this with already-checked arrays.
        model, data = self.model, self.data
        pin.computeJointJacobians(model, data, self._to_pin(q))
        pin.updateFramePlacement(model, data, fid)
        J = pin.getFrameJacobian(model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        if not self._identity_order:
            J = J[:, self._idx]
        return data.oMf[fid].homogeneous, J

    # ------------------------------------------------------------------ batched

    def _build_chain(self) -> None:
        """The serial chain root -> frame of each frame for the compiled FK (configs.chain)."""
        model = self.model
        column = {int(q): k for k, q in enumerate(self._idx)}
        chains = {name: chain_steps(model, fid, column) for name, fid in self._frame_ids.items()}
        self._chain_ok = all(steps is not None for steps, _ in chains.values())
        self._chains = chains
        self._kernels = {name: Chain(steps, F, self.dof) for name, (steps, F) in chains.items()} if self._chain_ok else {}
        # every joint in tree order (parents first), for the link poses of many configurations at once
        self._tree = []
        for j in range(1, model.njoints):
            jm = model.joints[j]
            short = jm.shortname()
            if jm.nq != 1 or jm.idx_q not in self._idx:
                self._chain_ok = False
                break
            iq = int(np.nonzero(self._idx == jm.idx_q)[0][0])
            axis = _AXES.get(short[-1]) if short[-2:-1] in ("R", "P") and short[-1] in _AXES else (
                np.asarray(jm.extract().axis, dtype=np.float64).copy() if "Unaligned" in short else None)
            if axis is None:
                self._chain_ok = False
                break
            kind = "P" if short.startswith("JointModelP") else "R"
            self._tree.append((j, model.parents[j], model.jointPlacements[j].homogeneous.copy(), kind, axis, iq))

    def fk_batch(self, Q: np.ndarray, frame: str = "cam") -> np.ndarray:
        """T_base_<frame> for every row of Q (N, dof) -> (N, 4, 4); vectorized over N in numpy."""
        self._frame_id(frame)
        Q = self._rows(Q)
        n = Q.shape[0]
        if not self._chain_ok:  # exotic joint types: fall back to one pinocchio call per row
            return np.stack([self.fk(q, frame) for q in Q]) if n else np.empty((0, 4, 4))
        return self._kernels[frame].poses(Q)

    def link_poses_batch(self, Q: np.ndarray, links: Sequence[str]) -> np.ndarray:
        """``link_poses`` for every row of Q (N, dof) -> (N, len(links), 4, 4), vectorized over N: a
        collision check of a whole motion needs every link at every sample."""
        Q = self._rows(Q)
        key = tuple(links)
        ids = self._link_ids.get(key)
        if ids is None:
            ids = self._link_ids[key] = [self.link_frame_id(n) for n in key]
        n = len(Q)
        if not self._chain_ok:
            return np.stack([self.link_poses(q, links) for q in Q]) if n else np.empty((0, len(ids), 4, 4))
        T = {0: np.broadcast_to(np.eye(4), (n, 4, 4))}
        for j, parent, M, kind, axis, iq in self._tree:  # a handful of joints, each vectorized over N
            T[j] = T[parent] @ M @ _joint_motion(kind, axis, Q[:, iq])
        frames = self.model.frames
        out = np.empty((n, len(ids), 4, 4))
        for k, fid in enumerate(ids):
            out[:, k] = T[frames[fid].parentJoint] @ frames[fid].placement.homogeneous
        return out

    def _rows(self, Q: np.ndarray) -> np.ndarray:
        Q = np.asarray(Q, dtype=np.float64)
        if Q.ndim != 2 or Q.shape[1] != self.dof:
            raise ValueError(f"Q must have shape (N, {self.dof}), got {Q.shape}")
        if not np.all(np.isfinite(Q)):
            raise ValueError("Q contains NaN or inf")
        return Q

    def fk_positions(self, Q: np.ndarray, frame: str = "cam") -> np.ndarray:
        """Origins of <frame> in the base frame for every row of Q (N, dof) -> (N, 3)."""
        return self.fk_batch(Q, frame)[:, :3, 3].copy()

    # ------------------------------------------------------------------ reach

    def reach_sphere(self, frame: str = "cam") -> tuple[np.ndarray, float]:
        """(center, radius): a sphere that contains every reachable origin of <frame>.

        Center is the origin of the first joint (fixed in the base frame); the radius is the
        sum of the link offsets after it (triangle inequality), so it is conservative: a
        target outside the sphere is certainly unreachable, one inside may still be.
        """
        fid = self._frame_id(frame)
        F = self._chains[frame][1]
        model = self.model
        j = model.frames[fid].parentJoint
        joints = []
        while j > 0:
            joints.append(j)
            j = model.parents[j]
        joints.reverse()
        if not joints:
            return model.frames[fid].placement.translation.copy(), 0.0
        # the first joint hangs off the root, so its origin does not depend on q
        center = model.jointPlacements[joints[0]].translation
        radius = sum(float(np.linalg.norm(model.jointPlacements[j].translation)) for j in joints[1:])
        radius += float(np.linalg.norm(F[:3, 3]))
        # prismatic joints extend the reach by their stroke
        for j in joints:
            if model.joints[j].shortname().startswith("JointModelP"):
                iq = int(np.nonzero(self._idx == model.joints[j].idx_q)[0][0])
                radius += float(max(abs(self.lower[iq]), abs(self.upper[iq])))
        return np.array(center, dtype=np.float64), radius


def _joint_motion(kind: str, axis: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(N, 4, 4) motion of a 1-DOF joint at values x (N,): Rodrigues for "R", a shift for "P"."""
    J = np.broadcast_to(np.eye(4), (len(x), 4, 4)).copy()
    if kind == "R":
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        s, c = np.sin(x)[:, None, None], np.cos(x)[:, None, None]
        J[:, :3, :3] = np.eye(3) + s * K + (1 - c) * (K @ K)
    else:
        J[:, :3, 3] = x[:, None] * axis
    return J
