"""Drawing cloud -> CutPath (geometry), and CutPath -> joint motion (IK along each branch with
continuity, the cut timed by the travel speed, approach and retract by Ruckig)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.interpolate import CubicSpline

from planners.clouds import Cloud
from planners.cutpath import _checks
from planners.cutpath.config import CutPathConfig
from planners.cutpath.geometry import Surface, on_surface, smooth_resample, torch_poses
from planners.cutpath.graph import END, JUNCTION, LOOP, drawing_graph
from planners.cutpath.model import COLLISION, JUMP, OK, UNREACHABLE, VELOCITY, Branch, CutPath
from planners.motion.ik import Unreachable, solve_camera_ik
from planners.motion.kinematics import Kinematics
from planners.motion.limits import (
    PANDA_JOINT_NAMES,
    PANDA_MAX_ACCELERATION,
    PANDA_MAX_JERK,
    PANDA_MAX_VELOCITY,
    PANDA_Q_MAX,
    PANDA_Q_MIN,
)
from planners.motion.trajectory import JointPath, plan_through

IsFree = Callable[[np.ndarray], np.ndarray]


def torch_kinematics(urdf_path: str, cfg: CutPathConfig | None = None, *,
                     joint_names: Sequence[str] = PANDA_JOINT_NAMES, flange_link: str = "panda_hand",
                     lower: np.ndarray | None = PANDA_Q_MIN, upper: np.ndarray | None = PANDA_Q_MAX) -> Kinematics:
    """The arm's kinematics with the torch tip as its tool frame (Kinematics calls it "cam")."""
    cfg = cfg or CutPathConfig()
    return Kinematics(urdf_path, joint_names, flange_link, cfg.torch.T_flange_torch(), lower=lower, upper=upper)


def _xyz_origin(cloud, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    if isinstance(cloud, Cloud):
        return _checks.points(cloud.xyz, f"{name}.xyz"), cloud.origin
    return _checks.points(cloud, name), None


def build_cut_path(drawing: Cloud | np.ndarray, surface: Cloud | np.ndarray | None = None,
                   cfg: CutPathConfig | None = None, *, viewpoint: np.ndarray | None = None) -> CutPath:
    """Branches, smoothed and evenly spaced on the surface, with torch poses; no joint data yet.

    Args:
        drawing: the drawing cloud D_total (Cloud or (N,3)).
        surface: the surface cloud C_total for normals and snapping; the drawing itself when None
            (paint lies on the surface, so it is a surface too, if a narrow one).
        cfg: parameters; defaults when None.
        viewpoint: (3,) a point on the outward side, for surface points whose sensor position
            is unknown (an array has none; Cloud.origin may be NaN).

    Raises:
        ValueError: empty or non-finite clouds, bad parameters, normals that cannot be oriented.
    """
    cfg = cfg or CutPathConfig()
    d_xyz, d_origin = _xyz_origin(drawing, "drawing")
    if surface is None:
        surf = Surface(d_xyz, d_origin, viewpoint, cfg.normal_radius_m, "drawing")
    else:
        surf = Surface(*_xyz_origin(surface, "surface"), viewpoint, cfg.normal_radius_m)
    g = drawing_graph(d_xyz, cfg.voxel_m, cfg.min_branch_m, cfg.closing_iterations)

    counters = {JUNCTION: 0, END: 0, LOOP: 0}
    label = []
    for kind in g.kinds:
        label.append({JUNCTION: "J", END: "E", LOOP: "L"}[kind] + str(counters[kind]))
        counters[kind] += 1
    branches = []
    for i, poly in enumerate(g.branches):  # a handful of branches
        closed = g.closed(i)
        pts = smooth_resample(poly, cfg.spacing_m, cfg.smoothing_voxels * cfg.voxel_m, closed)
        pts, normals = on_surface(pts, surf, cfg.spacing_m)
        poses = torch_poses(pts, normals, cfg.standoff_m, closed)
        a, b = g.ends[i]
        branches.append(Branch(pts, normals, poses, np.full(len(pts), cfg.travel_speed_mps), label[a], label[b], closed))
    nodes = g.nodes
    if len(nodes):
        nodes = surf.snap(nodes, surf.normals(nodes))
    kinds = np.array(g.kinds)
    return CutPath(branches, nodes[kinds == JUNCTION].reshape(-1, 3), nodes[kinds == END].reshape(-1, 3),
                   cfg.model_dump(mode="json"))


def _ik(kin: Kinematics, T: np.ndarray, seed: np.ndarray, cfg: CutPathConfig, seeds: int) -> np.ndarray | None:
    try:
        return solve_camera_ik(kin, T, seed, free_roll=cfg.free_roll, margin=cfg.ik_margin_rad, seeds=seeds).q
    except Unreachable:
        return None


def _backed_off(T: np.ndarray, distance: float) -> np.ndarray:
    out = T.copy()
    out[:3, 3] -= distance * T[:3, 2]
    return out


def _free(is_free: IsFree | None, Q: np.ndarray) -> np.ndarray:
    if is_free is None or len(Q) == 0:
        return np.ones(len(Q), dtype=bool)
    out = np.asarray(is_free(Q))
    if out.shape != (len(Q),):
        raise ValueError(f"is_free must return shape ({len(Q)},), got {out.shape}")
    return out.astype(bool)


def solve_branch(kin: Kinematics, b: Branch, q_seed: np.ndarray, cfg: CutPathConfig,
                 is_free: IsFree | None = None, max_vel: np.ndarray = PANDA_MAX_VELOCITY) -> None:
    """Joint solutions pose by pose, each seeded from the one before (so the arm follows the
    path instead of jumping between IK branches), and the per-pose verdict: unreachable, jump
    (a joint moves more than max_joint_jump_rad between neighbours), collision, velocity (the
    cut at travel speed needs more than the joint limit), else ok."""
    n = len(b)
    Q = np.full((n, kin.dof), np.nan)
    why = [OK] * n
    seed, fresh = q_seed, True
    for k in range(n):  # sequential by nature: pose k is seeded from pose k-1
        q = _ik(kin, b.poses[k], seed, cfg, cfg.ik_seeds if fresh else 1)
        if q is None and not fresh:
            q = _ik(kin, b.poses[k], seed, cfg, cfg.ik_seeds)
        if q is None:
            why[k] = UNREACHABLE
            continue
        Q[k] = q
        if k > 0 and np.isfinite(Q[k - 1]).all() and np.abs(q - Q[k - 1]).max() > cfg.max_joint_jump_rad:
            why[k] = JUMP
        seed, fresh = q, False
    solved = np.isfinite(Q).all(axis=1)
    if n > 1:
        qd = np.gradient(Q, b.times, axis=0)
    else:
        qd = np.zeros_like(Q)
    too_fast = np.any(np.abs(qd) > np.asarray(max_vel)[None, :], axis=1)
    free = np.ones(n, dtype=bool)
    free[solved] = _free(is_free, Q[solved])
    for k in np.flatnonzero(solved & ~free):
        if why[k] == OK:
            why[k] = COLLISION
    for k in np.flatnonzero(solved & too_fast):
        if why[k] == OK:
            why[k] = VELOCITY
    b.q, b.qd, b.feasibility = Q, qd, why


def _cut_trajectory(b: Branch, dt: float) -> JointPath:
    """The cut sampled every dt: a cubic through the pose solutions at their times, at rest at
    both ends (the arm arrives from the approach and leaves for the retract stopped)."""
    if len(b) == 1:
        z = np.zeros((1, b.q.shape[1]))
        return JointPath(np.zeros(1), b.q.copy(), z, z.copy(), 0.0)
    spline = CubicSpline(b.times, b.q, axis=0, bc_type="clamped")
    t = np.append(np.arange(0.0, b.times[-1], dt), b.times[-1])
    return JointPath(t, spline(t), spline(t, 1), spline(t, 2), float(t[-1]))


def plan_cut(path: CutPath, kin: Kinematics, q_start: np.ndarray, cfg: CutPathConfig | None = None, *,
             is_free: IsFree | None = None, max_vel: np.ndarray = PANDA_MAX_VELOCITY,
             max_acc: np.ndarray = PANDA_MAX_ACCELERATION, max_jerk: np.ndarray = PANDA_MAX_JERK) -> CutPath:
    """Joint motion for every branch in turn, in place (and returned): IK along the poses, the
    cut timed by the travel speed, an approach from where the arm is (the start, then each
    retract) through the backed-off pose down to the first pose, and a retract to the backed-off
    last pose. A branch that cannot be run leaves the arm where it was for the next one.

    Args:
        kin: kinematics whose tool frame is the torch tip (see `torch_kinematics`).
        q_start: (dof,) configuration the arm is in, inside kin's limits.
        is_free: optional collision check, (N,dof) -> (N,) bool; False marks a pose 'collision'
            and an approach or retract through such a configuration an issue.
        max_vel, max_acc, max_jerk: the arm's limits (dof,).

    Raises:
        ValueError: malformed q_start or limits, q_start outside kin's limits, is_free returning
            the wrong shape.
    """
    cfg = cfg or CutPathConfig()
    q_here = kin._vec(q_start, "q_start")
    if not kin.within_limits(q_here):
        raise ValueError(f"q_start {q_here} is outside the joint limits {kin.lower} .. {kin.upper}")
    lim = {}
    for name, v in (("max_vel", max_vel), ("max_acc", max_acc), ("max_jerk", max_jerk)):
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (kin.dof,) or not np.all(np.isfinite(a)) or not np.all(a > 0):
            raise ValueError(f"{name} must be {kin.dof} finite positive values, got {v!r}")
        lim[name] = a
    for i, b in enumerate(path.branches):  # a handful of branches
        if len(b) == 0:
            continue
        if cfg.reverse_branches and not b.closed and len(b) > 1:
            tip = kin.fk(q_here)[:3, 3]
            if np.linalg.norm(b.poses[-1, :3, 3] - tip) < np.linalg.norm(b.poses[0, :3, 3] - tip):
                b = path.branches[i] = b.reversed()
        solve_branch(kin, b, q_here, cfg, is_free, lim["max_vel"])
        b.issues, b.approach, b.cut, b.retract = [], None, None, None
        if any(f != OK for f in b.feasibility):
            bad = sum(f != OK for f in b.feasibility)
            b.issues.append(f"{bad} of {len(b)} poses infeasible")
            continue
        b.cut = _cut_trajectory(b, cfg.dt_s)
        if np.any(np.abs(b.cut.velocities) > lim["max_vel"] + 1e-9):
            b.issues.append("the timed cut exceeds a joint velocity limit")
        b.approach_q = _ik(kin, _backed_off(b.poses[0], cfg.approach_m), b.q[0], cfg, cfg.ik_seeds)
        b.retract_q = _ik(kin, _backed_off(b.poses[-1], cfg.approach_m), b.q[-1], cfg, cfg.ik_seeds)
        motion = dict(speed_factor=cfg.approach_speed_factor, dt=cfg.dt_s, lower=kin.lower, upper=kin.upper)
        for what, goal in (("approach", b.approach_q), ("retract", b.retract_q)):
            if goal is None:
                b.issues.append(f"{what} pose unreachable")
                continue
            waypoints = np.stack([q_here, goal, b.q[0]]) if what == "approach" else np.stack([b.q[-1], goal])
            try:
                jp = plan_through(waypoints, lim["max_vel"], lim["max_acc"], lim["max_jerk"], **motion)
            except ValueError as exc:  # e.g. the time-optimal motion overshoots a joint limit
                b.issues.append(f"{what}: {exc}")
                continue
            if not _free(is_free, jp.positions).all():
                b.issues.append(f"{what} collides")
            setattr(b, what, jp)
        if b.feasible:
            q_here = b.retract_q
    return path


def plan_cut_path(drawing: Cloud | np.ndarray, surface: Cloud | np.ndarray | None, kin: Kinematics,
                  q_start: np.ndarray, cfg: CutPathConfig | None = None, *, viewpoint: np.ndarray | None = None,
                  is_free: IsFree | None = None, **limits) -> CutPath:
    """build_cut_path then plan_cut."""
    cfg = cfg or CutPathConfig()
    return plan_cut(build_cut_path(drawing, surface, cfg, viewpoint=viewpoint), kin, q_start, cfg,
                    is_free=is_free, **limits)
