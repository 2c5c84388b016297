"""Drawing cloud -> CutPath (geometry), and CutPath -> joint motion (IK along each branch with
continuity, the cut timed by the travel speed, approach and retract by Ruckig)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from planners.clouds import Cloud
from planners.cutpath import _checks
from planners.cutpath.config import CutPathConfig
from planners.cutpath.geometry import (Surface, arc_length, band_half_width, center_on_paint, end_caps, on_surface,
                                      pivots, smooth_resample, torch_poses, true_runs)
from planners.cutpath.graph import END, JUNCTION, LOOP, curve_graph, drawing_graph, through_junctions
from planners.cutpath.outline import line_core
from planners.cutpath.ladder import (COLLISION, IK_ITERATIONS, RECONFIGURE, Rungs, cut_spline, every_degree,
                                     plan_ladder, reversal_permutation, solve_rungs, tilt_directions)
from planners.cutpath.nozzle import NozzleCheck
from planners.cutpath.pieces import paint_parts, short_pieces
from planners.cutpath.tips import rebuilt_tips
from planners.cutpath.model import OK, Branch, CutPath, Gap
from planners.motion.ik_batch import solve_axis_ik_batch
from planners.motion.kinematics import Kinematics
from planners.motion.limits import (
    PANDA_JOINT_NAMES,
    PANDA_MAX_ACCELERATION,
    PANDA_MAX_JERK,
    PANDA_MAX_VELOCITY,
    PANDA_Q_MAX,
    PANDA_Q_MIN,
)
from planners.motion.roadmap import roadmap_route
from planners.motion.trajectory import JointPath, plan_through

IsFree = Callable[[np.ndarray], np.ndarray]
#: surface points in the normal that tells an unseen cell in front of the metal from one behind it:
#: a sign, not a direction to aim the torch by, and thousands of cells
IN_FRONT_NEIGHBOURS = 12
#: the paint is one line (not broken) when one piece of it holds this share
UNBROKEN_SHARE = 0.8


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


def _surface(drawing, surface, viewpoint: np.ndarray | None, cfg: CutPathConfig) -> Surface:
    """The surface to cut on, indexed: ``surface`` itself when already a ``Surface``, the drawing's
    own points when None (paint lies on the surface, so it is a surface too, if a narrow one)."""
    if isinstance(surface, Surface):
        return surface
    if surface is None:
        return Surface(*_xyz_origin(drawing, "drawing"), viewpoint, cfg.normal_radius_m, "drawing")
    return Surface(*_xyz_origin(surface, "surface"), viewpoint, cfg.normal_radius_m)


def build_cut_path(drawing: Cloud | np.ndarray, surface: Cloud | np.ndarray | Surface | None = None,
                   cfg: CutPathConfig | None = None, *, viewpoint: np.ndarray | None = None) -> CutPath:
    """Branches, smoothed and evenly spaced on the surface, with torch poses; no joint data yet.

    Args:
        drawing: the drawing cloud D_total (Cloud or (N,3)).
        surface: the surface cloud C_total for normals and snapping, or a ``Surface`` already
            indexed; the drawing itself when None (paint lies on the surface, so it is a surface
            too, if a narrow one).
        cfg: parameters; defaults when None.
        viewpoint: (3,) a point on the outward side, for surface points whose sensor position
            is unknown (an array has none; Cloud.origin may be NaN).

    Raises:
        ValueError: empty or non-finite clouds, bad parameters, normals that cannot be oriented.
    """
    cfg = cfg or CutPathConfig()
    d_xyz = drop_specks(_xyz_origin(drawing, "drawing")[0])
    surf = _surface(drawing, surface, viewpoint, cfg)
    g, band, half = _line_graph(d_xyz, surf, cfg)
    paint_tree = cKDTree(d_xyz)

    counters = {JUNCTION: 0, END: 0, LOOP: 0}
    label = []
    for kind in g.kinds:
        label.append({JUNCTION: "J", END: "E", LOOP: "L"}[kind] + str(counters[kind]))
        counters[kind] += 1
    branches, strokes = [], []
    for poly, a, b in through_junctions(g):  # a handful of strokes: a crossing is cut straight through
        closed = a == b and g.kinds[a] == LOOP
        strokes.append(poly)
        held: list = []  # the corners: the torch pivots on them, resampling keeps them
        if half is None:  # the skeleton's voxel staircase is smoothed away, its corners measured on 3 cm and
            # fitted to the paint beside them
            smoothing, corner_scale, corner_paint = cfg.smoothing_voxels * cfg.voxel_m, cfg.corner_scale_m, band
        else:  # the outline's line is smooth already and keeps its turns: lightly smoothed, a corner (an edge of
            # the metal the line goes over, a tip) fitted to the line itself (the paint beside a tip is both legs')
            smoothing, corner_scale, corner_paint = cfg.outline_smoothing_m, cfg.corner_scale_m, None
        pts = smooth_resample(poly, cfg.spacing_m, smoothing, closed, corner_scale_m=corner_scale,
                              corner_deg=cfg.corner_deg, paint=corner_paint, held=held)
        pts = center_on_paint(pts, band, cfg.spacing_m, closed, normals=surf.normals(pts), band_half_m=half)
        tip_half = half if half is not None else band_half_width(pts, d_xyz, cfg.spacing_m, normals=surf.normals(pts))
        for k, (pts, cut_start, cut_end) in enumerate(on_paint_runs(pts, paint_tree, surf.tree, cfg.spacing_m)):
            start = cut_start or (not closed and g.kinds[a] == END)
            end = cut_end or (not closed and g.kinds[b] == END)
            piece_closed = closed and not (cut_start or cut_end)
            if start or end:  # along the centred line; what it adds centred too
                n = surf.normals(pts)
                hw = band_half_width(pts, d_xyz, cfg.spacing_m, normals=n) if half is None else half
                if cut_start or cut_end:  # where it turned off its paint: half a band width back, then to the cap
                    s_ = arc_length(pts)
                    keep = (s_ >= (hw if cut_start else -1.0)) & (s_ <= s_[-1] - (hw if cut_end else -1.0))
                    if keep.sum() >= 2 and np.ptp(s_[keep]) >= 2.0 * hw:  # a short piece (over a bar) kept whole
                        pts, n = pts[keep], n[keep]
                pts = end_caps(pts, d_xyz, surf.tree, hw, cfg.spacing_m, start=start, end=end, normals=n)
                pts = center_on_paint(pts, band, cfg.spacing_m, piece_closed, normals=surf.normals(pts),
                                      band_half_m=half)
            kept = held if not (cut_start or cut_end) else [  # the corners on this side of a split
                h for h in held if np.min(np.linalg.norm(pts - h, axis=1)) < 2.0 * cfg.spacing_m]
            pts, tips = rebuilt_tips(pts, d_xyz, cfg.spacing_m, tip_half, surf.normals(pts), piece_closed)
            kept = kept + tips
            pts, normals = pivots(*on_surface(pts, surf, cfg.spacing_m, np.array(kept)), cfg.pivot_step_deg)
            poses = torch_poses(pts, normals, cfg.standoff_m, piece_closed)
            first = label[a] if k == 0 and not cut_start else f"{label[a]}~{k}"
            last = label[b] if not cut_end else f"{label[a]}~{k + 1}"
            branches.append(Branch(pts, normals, poses, np.full(len(pts), cfg.travel_speed_mps), first, last,
                                   piece_closed))
    pieces, ignored = short_pieces(d_xyz, strokes, surf, voxel_m=cfg.voxel_m, spacing_m=cfg.spacing_m,
                                   bridge_max_m=cfg.bridge_max_m, min_piece_m=cfg.min_piece_m)
    for j, piece in enumerate(pieces):  # a broken line: a short cut through each piece of paint
        pts, normals = pivots(*on_surface(piece.line, surf, cfg.spacing_m), cfg.pivot_step_deg)
        if len(pts) < 2:
            ignored += 1
            continue
        poses = torch_poses(pts, normals, cfg.standoff_m)
        branches.append(Branch(pts, normals, poses, np.full(len(pts), cfg.travel_speed_mps), f"P{j}a", f"P{j}b"))
    nodes = g.nodes
    if len(nodes):
        nodes = surf.snap(nodes, surf.normals(nodes))
    kinds = np.array(g.kinds)
    path = CutPath(branches, nodes[kinds == JUNCTION].reshape(-1, 3), nodes[kinds == END].reshape(-1, 3),
                   cfg.model_dump(mode="json"), spray_width_m=None if half is None else 2.0 * half)
    if pieces:
        path.notes.append(f"the line is broken: {len(pieces)} separate pieces of paint, each a short cut along it")
    if ignored:
        path.notes.append(f"{ignored} specks of paint too small to be part of a line were left out")
    return path




#: a stroke's point farther than this from any paint, over metal, is off the line (bare metal between
#: two strokes' paint that the skeleton's gap closing joined)
OFF_PAINT_M = 0.005
OFF_PAINT_STEP_M = 0.0005  # the stroke sampled this finely between its poses to measure how long it is off


def on_paint_runs(points: np.ndarray, paint: cKDTree, metal: cKDTree,
                  spacing_m: float) -> list[tuple[np.ndarray, bool, bool]]:
    """The stretches of a stroke that keep on its paint, as (points, split at its start, split at its
    end): a stroke is split where it runs more than ``OFF_PAINT_M`` from any paint, over metal, for a
    spacing or more (sampled every ``OFF_PAINT_STEP_M``). The skeleton's gap closing joins paint up to
    two voxels apart, across bare metal (two strokes sprayed side by side joined by a U-turn: the flame
    19 mm off either line, scrap:0:30); over air (between a grid's bars) there is nothing to cut through
    and the stroke goes on; a point beside a bar's paint is no stretch off it."""
    from planners.metrics import dense_polylines

    s = arc_length(points)
    dense = dense_polylines([points], OFF_PAINT_STEP_M)
    off = paint.query(dense, distance_upper_bound=2.0 * OFF_PAINT_M)[0] > OFF_PAINT_M
    if off.any():
        off &= metal.query(dense, distance_upper_bound=0.5 * spacing_m)[0] < np.inf  # on it: not beside a bar
    a, b = true_runs(off)
    long = (b - a) * OFF_PAINT_STEP_M >= spacing_m
    if not long.any():
        return [(points, False, False)]
    sd = np.linspace(0.0, s[-1], len(dense))  # the dense samples' arc lengths
    keep = np.ones(len(points), bool)
    for i, j in zip(a[long], b[long]):  # a few stretches: the poses within them, and the one each side
        keep[max(int(np.searchsorted(s, sd[i])) - 1, 0):int(np.searchsorted(s, sd[j - 1], side="right")) + 1] = False
    starts, stops = true_runs(keep)
    return [(points[i:j], i > 0, j < len(points)) for i, j in zip(starts, stops) if j - i >= 2]


def _broken(d_xyz: np.ndarray, cfg: CutPathConfig) -> bool:
    """A broken line (paint only where the spray met a bar, a dashed line): no one piece of paint holds
    ``UNBROKEN_SHARE`` of it. Its pieces' outlines are mostly the bars' sides, not the line moved
    aside; the skeleton and its pieces (``pieces.py``) cut it."""
    parts = paint_parts(d_xyz, 2.0 * cfg.voxel_m)
    return max((len(p) for p in parts), default=0) < UNBROKEN_SHARE * len(d_xyz)


SPECK_RADIUS_M = 0.005  # a line is a band of spray: its paint has paint all round it within this
SPECK_MIN = 6  # paint with fewer paint points than this within SPECK_RADIUS_M is overspray, not line


def drop_specks(xyz: np.ndarray) -> np.ndarray:
    """The drawing without its overspray: specks of paint beside the line, too sparse to be part of a
    sprayed band, which draw the line's outline and skeleton off the line (the twin's textured paint: the
    flame 15-23 mm off an I-beam's line against 2 mm in flat colours). Kept whole when it would lose most
    of itself (a drawing seen from far, thin on every side)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if len(xyz) < 4 * SPECK_MIN:
        return xyz
    n = cKDTree(xyz).query_ball_point(xyz, SPECK_RADIUS_M, return_length=True, workers=-1)
    keep = n >= SPECK_MIN
    return xyz[keep] if keep.mean() >= 0.5 else xyz


def _line_graph(d_xyz: np.ndarray, surf: Surface, cfg: CutPathConfig):
    """(the drawing's graph, the paint its corners are fitted to, the band's half width or None): from
    the paint's outline moved onto its line (``outline.py``: sharp tips kept, no chord through merged
    paint; its corners fitted to the line's core, its half width measured between the outline's
    sides), or, with ``cfg.line_from`` "skeleton" or where the outline gives no line, the voxel
    skeleton of the whole paint (then centred on the paint, its half width measured across it)."""
    if cfg.line_from == "outline" and not _broken(d_xyz, cfg):
        metal = surf.tree if surf.name != "drawing" else None  # bare metal beside the paint, where there is a surface
        core, o = line_core(d_xyz, surf.normals(d_xyz), metal)
        if len(o.line) and core is not d_xyz:
            g = curve_graph(o.line, min_branch_m=cfg.min_branch_m, paint=cKDTree(d_xyz), bridge_m=6.0 * o.half_width_m)
            if g.branches:
                return g, core, o.half_width_m
    return (drawing_graph(d_xyz, cfg.voxel_m, cfg.min_branch_m, cfg.closing_iterations, surface=surf.xyz), d_xyz,
            None)


def _stand_off_solutions(kin: Kinematics, T: np.ndarray, q_near: np.ndarray, cfg: CutPathConfig,
                         distances: tuple[float, ...]) -> list[np.ndarray]:
    """Per distance, the configurations holding the torch that far back from pose T, pointing at
    it, along each axis of the tilt cone (the cut's own axis first), nearest to ``q_near`` in joint
    space first; all distances in one batched IK call (a small batch costs its iterations, not its size)."""
    D = tilt_directions(cfg)
    axes = np.einsum("ij,oj->oi", T[:3, :3], D)
    k = len(distances)
    tips = T[:3, 3] - np.repeat(np.asarray(distances, dtype=np.float64), len(D))[:, None] * np.tile(axes, (k, 1))
    Q, ok = solve_axis_ik_batch(kin, tips, np.tile(axes, (k, 1)), np.tile(q_near, (k * len(D), 1)),
                                margin=cfg.ik_margin_rad, max_iter=IK_ITERATIONS,
                                x_axes=None if cfg.free_roll else np.tile(T[:3, 0], (k * len(D), 1)))
    out = []
    for Qd, okd in zip(np.split(Q, k), np.split(ok, k)):
        Qd = Qd[okd]
        out.append(Qd[np.argsort(np.abs(Qd - q_near).max(axis=1), kind="stable")])
    return out


def _stand_offs(kin: Kinematics, T: np.ndarray, q_near: np.ndarray, cfg: CutPathConfig,
                is_free: IsFree | None, distances: tuple[float, ...] | None = None):
    """Configurations holding the torch ``approach_m`` back from the cut's first (or last) pose,
    pointing at it, so that the torch plunges straight in, best first: along the cut's own torch
    axis, then along the other axes of the tilt cone, then half as far back; the free solutions
    nearest to ``q_near`` in joint space first."""
    for Q in _stand_off_solutions(kin, T, q_near, cfg, distances or (cfg.approach_m, 0.5 * cfg.approach_m)):
        for q in Q[_free(is_free, Q)]:  # collision checked a distance at a time: the first usually does
            yield q.copy()


def _air_routes(kin: Kinematics, q_from: np.ndarray, q_to: np.ndarray, cfg: CutPathConfig, is_free: IsFree | None,
                park_q: np.ndarray | None):
    """Waypoint routes for an air move that is not clear straight: both ends lifted further back
    along their torch axes (2x, 4x the approach distance), then via the park pose."""
    ks = (2.0, 4.0)
    ups = []
    for q in (q_from, q_to):
        best = []
        for Q in _stand_off_solutions(kin, kin.fk(q), q, cfg, tuple(k * cfg.approach_m for k in ks)):
            free = Q[_free(is_free, Q)]
            best.append(free[0] if len(free) else None)
        ups.append(best)
    lifts = []
    for up_from, up_to in zip(*ups):
        if up_from is not None and up_to is not None:
            lifts.append((up_from, up_to))
            yield [q_from, up_from, up_to, q_to]
    if park_q is not None:
        yield [q_from, park_q, q_to]
        for up_from, up_to in lifts:
            yield [q_from, up_from, park_q, up_to, q_to]


def _with_nozzle(is_free: IsFree | None, nozzle_free, kin: Kinematics) -> IsFree:
    """is_free that also wants the nozzle clear (``nozzle.NozzleCheck``) at the torch pose of each row."""
    def check(Q: np.ndarray) -> np.ndarray:
        T = kin.fk_batch(Q)
        ok = np.asarray(nozzle_free(T[:, :3, 3], T[:, :3, 2]), dtype=bool)
        return ok & _free(is_free, Q) if is_free is not None else ok
    return check


def _free(is_free: IsFree | None, Q: np.ndarray) -> np.ndarray:
    if is_free is None or len(Q) == 0:
        return np.ones(len(Q), dtype=bool)
    out = np.asarray(is_free(Q))
    if out.shape != (len(Q),):
        raise ValueError(f"is_free must return shape ({len(Q)},), got {out.shape}")
    return out.astype(bool)


def _motion_free(is_free: IsFree | None, Q: np.ndarray) -> bool:
    """A dense joint motion is clear: checked at every degree of joint travel (``every_degree``),
    the resolution the cut's own motion is checked at, not at every control sample."""
    return bool(_free(is_free, Q[every_degree(Q)]).all())


def _cut_trajectory(b: Branch, dt: float) -> JointPath:
    """The cut sampled every dt (``ladder.cut_spline``, the motion the ladder checked)."""
    if len(b) == 1:
        z = np.zeros((1, b.q.shape[1]))
        return JointPath(np.zeros(1), b.q.copy(), z, z.copy(), 0.0)
    spline = cut_spline(b.times, b.q)
    t = np.append(np.arange(0.0, b.times[-1], dt), b.times[-1])
    return JointPath(t, spline(t), spline(t, 1), spline(t, 2), float(t[-1]))


def _runs_of(b: Branch, index: int, kin: Kinematics, q_here: np.ndarray, cfg: CutPathConfig,
             is_free: IsFree | None, max_vel: np.ndarray, nozzle_free=None,
             rungs: Rungs | None = None, explain=None) -> tuple[list[Branch], list[Gap]]:
    """The ladder graph along one branch: its cuttable runs as branches of their own (joint
    solutions chosen, poses tilted as chosen) and its uncut gaps with their reasons."""
    lad = plan_ladder(kin, b.poses, b.times, q_here, cfg, is_free, max_vel, nozzle_free, rungs, explain)
    n = len(b)
    s = arc_length(b.points)
    runs = []
    for r in lad.runs:
        sl = slice(r.first, r.last + 1)
        start = b.start if r.first == 0 else f"{b.start}+{s[r.first]:.3f}m"
        end = b.end if r.last == n - 1 else f"{b.start}+{s[r.last]:.3f}m"
        rb = Branch(b.points[sl].copy(), b.normals[sl].copy(), r.poses, b.speeds[sl].copy(), start, end,
                    closed=b.closed and r.first == 0 and r.last == n - 1, feasibility=[OK] * (r.last - r.first + 1),
                    q=r.q, times=r.times)
        rb.tilt_rad = r.tilt_rad
        rb.qd = np.gradient(rb.q, rb.times, axis=0) if len(rb) > 1 else np.zeros_like(rb.q)
        rb.source = index
        rb.motion_checked = is_free is not None  # the ladder checked this very motion, sample for sample
        runs.append(rb)
    gaps = []
    for g in lad.gaps:
        a = b.points[max(g.after, 0)] if g.after >= 0 else b.points[0]
        z = b.points[min(g.before, n - 1)]
        length = 0.0 if g.reason == RECONFIGURE else float(s[min(g.before, n - 1)] - s[max(g.after, 0)])
        sl = slice(max(g.after, 0), min(g.before, n - 1) + 1)
        nrm = b.normals[sl].mean(axis=0)
        nrm = nrm / max(np.linalg.norm(nrm), 1e-12)
        gaps.append(Gap(index, a.copy(), z.copy(), length, g.reason, g.detail, b.points[sl].copy(), nrm))
    return runs, gaps


def plan_cut(path: CutPath, kin: Kinematics, q_start: np.ndarray, cfg: CutPathConfig | None = None, *,
             is_free: IsFree | None = None, max_vel: np.ndarray = PANDA_MAX_VELOCITY,
             max_acc: np.ndarray = PANDA_MAX_ACCELERATION, max_jerk: np.ndarray = PANDA_MAX_JERK,
             park_q: np.ndarray | None = None, nozzle_free=None, explain=None) -> CutPath:
    """Joint motion for the drawing, in place (and returned). Each branch goes through the ladder
    graph (``ladder.py``: the torch within its tilt tolerances, batched IK, lazy collision checks,
    the cheapest continuous joint path) and becomes its maximal cuttable runs; ``path.branches``
    is then the list of runs in cutting order and ``path.gaps`` what is left uncut and why. Each
    run gets its cut timed by the travel speed, an approach from where the arm is (the start, then
    each retract) through the backed-off pose, and a retract to the backed-off last pose.

    Args:
        kin: kinematics whose tool frame is the torch tip (see `torch_kinematics`).
        q_start: (dof,) configuration the arm is in, inside kin's limits.
        is_free: optional collision check, (N,dof) -> (N,) bool; False marks a configuration in
            collision, and an approach or retract through one an issue.
        max_vel, max_acc, max_jerk: the arm's limits (dof,).
        park_q: a configuration clear above the cell: an air move that collides goes through it.
        nozzle_free: optional (tips (...,3), axes (...,3)) -> (...) bool: the nozzle is clear of the
            metal there (``nozzle.NozzleCheck`` on the scanned surface).
        explain: optional (M,dof) -> M labels of what each configuration hits (None where nothing),
            for the details of the gaps left for a collision.

    Raises:
        ValueError: malformed q_start or limits, q_start outside kin's limits, is_free returning
            the wrong shape.
    """
    cfg = cfg or CutPathConfig()
    q_here = kin._vec(q_start, "q_start")
    if not kin.within_limits(q_here):
        raise ValueError(f"q_start {q_here} is outside the joint limits {kin.lower} .. {kin.upper}")
    if park_q is not None:
        park_q = kin._vec(park_q, "park_q")
    lim = {}
    for name, v in (("max_vel", max_vel), ("max_acc", max_acc), ("max_jerk", max_jerk)):
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (kin.dof,) or not np.all(np.isfinite(a)) or not np.all(a > 0):
            raise ValueError(f"{name} must be {kin.dof} finite positive values, got {v!r}")
        lim[name] = a
    if nozzle_free is not None:  # every configuration checked (cut, pivots, air moves) keeps its nozzle off the metal
        is_free = _with_nozzle(is_free, nozzle_free, kin)
    path.drawing_length_m = path.length_m
    todo = [(i, b) for i, b in enumerate(path.branches) if len(b) > 0]
    cuts = [(i, b) for i, b in todo if len(b) >= 2]  # every branch's rungs in one batched IK
    rungs = dict(zip([i for i, _ in cuts], solve_rungs(kin, [b.poses for _, b in cuts], q_here, cfg)))
    flip = reversal_permutation(cfg)
    runs_out: list[Branch] = []
    path.gaps = []
    while todo:  # nearest branch end next: air moves stay short
        tip = kin.fk(q_here)[:3, 3]
        d = [min(np.linalg.norm(b.poses[0, :3, 3] - tip), np.inf if b.closed else np.linalg.norm(b.poses[-1, :3, 3] - tip))
             for _, b in todo]
        i, b = todo.pop(int(np.argmin(d)))
        r = rungs.get(i)
        if cfg.reverse_branches and not b.closed and len(b) > 1:
            if np.linalg.norm(b.poses[-1, :3, 3] - tip) < np.linalg.norm(b.poses[0, :3, 3] - tip):
                b = b.reversed()  # with a fixed roll the rungs hold the torch the other way round: solved anew
                r = r.reversed(flip) if cfg.free_roll else None
        if len(b) < 2:
            path.gaps.append(Gap(i, b.points[0].copy(), b.points[-1].copy(), 0.0, "too short",
                                 "a single torch pose is not a cut"))
            continue
        runs, gaps = _runs_of(b, i, kin, q_here, cfg, is_free, lim["max_vel"], nozzle_free, r, explain)
        path.gaps += gaps
        for rb in runs:
            _time_run(rb, kin, q_here, cfg, is_free, lim, park_q)
            rb, lost = _clear_ends(rb, kin, q_here, cfg, is_free, lim, park_q)
            path.gaps += lost
            runs_out.append(rb)
            if rb.feasible:
                q_here = rb.retract_q
    path.branches = runs_out
    return path


def _sub_run(b: Branch, first: int, stop: int) -> Branch:
    """Poses first..stop-1 of a run as a run of its own (its motion to be checked again: the cut's
    spline comes to rest at the new ends)."""
    sl = slice(first, stop)
    rb = Branch(b.points[sl].copy(), b.normals[sl].copy(), b.poses[sl].copy(), b.speeds[sl].copy(),
                b.start if first == 0 else f"{b.start}+{float(arc_length(b.points[:first + 1])[-1]):.3f}m",
                b.end if stop == len(b) else f"{b.start}+{float(arc_length(b.points[:stop])[-1]):.3f}m",
                feasibility=[OK] * (stop - first), q=b.q[sl].copy(), times=b.times[sl] - b.times[first])
    rb.tilt_rad = None if b.tilt_rad is None else b.tilt_rad[sl].copy()
    rb.qd = np.gradient(rb.q, rb.times, axis=0) if len(rb) > 1 else np.zeros_like(rb.q)
    rb.source = b.source
    return rb


def _clear_ends(b: Branch, kin: Kinematics, q_here: np.ndarray, cfg: CutPathConfig, is_free: IsFree | None,
                lim: dict, park_q: np.ndarray | None) -> tuple[Branch, list[Gap]]:
    """A run whose torch cannot plunge in at its first pose (or lift off at its last: an edge, a
    wall beside the line) starts (ends) a few poses further in: 1, 2, 4, ... poses are given up,
    as a gap with its reason, not the whole run."""
    blocked_in = any(m.startswith("approach") for m in b.issues)
    blocked_out = any(m.startswith("retract") for m in b.issues)
    if b.feasible or not (blocked_in or blocked_out) or len(b.issues) > blocked_in + blocked_out:
        return b, []
    n = len(b)
    for k in (1, 2, 4, 8, 16):
        first, stop = (k if blocked_in else 0), (n - k if blocked_out else n)
        if stop - first < 2 or arc_length(b.points[first:stop])[-1] < cfg.spacing_m:
            break
        sub = _sub_run(b, first, stop)
        _time_run(sub, kin, q_here, cfg, is_free, lim, park_q)
        if sub.feasible:
            gaps = []
            for a, z, what in ((0, first, "plunge into"), (stop - 1, n - 1, "lift off")):
                if z > a:
                    pts = b.points[a:z + 1].copy()
                    nrm = b.normals[a:z + 1].mean(axis=0)
                    gaps.append(Gap(b.source if b.source is not None else -1, pts[0], pts[-1],
                                    float(arc_length(pts)[-1]), COLLISION,
                                    f"no configuration can {what} the cut here without touching the piece",
                                    pts, nrm / max(np.linalg.norm(nrm), 1e-12)))
            return sub, gaps
    return b, []


def _time_run(b: Branch, kin: Kinematics, q_here: np.ndarray, cfg: CutPathConfig, is_free: IsFree | None,
              lim: dict, park_q: np.ndarray | None = None) -> None:
    """The cut sampled in time, and the approach and retract motions, for one run (issues noted)."""
    b.issues, b.approach, b.cut, b.retract = [], None, None, None
    b.cut = _cut_trajectory(b, cfg.dt_s)
    if np.any(np.abs(b.cut.velocities) > lim["max_vel"] + 1e-9):
        b.issues.append("the timed cut exceeds a joint velocity limit")
    if not getattr(b, "motion_checked", False) and not _motion_free(is_free, b.cut.positions):  # pivots included
        b.issues.append("the cut collides between its poses")
    motion = dict(speed_factor=cfg.approach_speed_factor, dt=cfg.dt_s, lower=kin.lower, upper=kin.upper)

    def timed(waypoints: list[np.ndarray]) -> JointPath:
        return plan_through(np.stack(waypoints), lim["max_vel"], lim["max_acc"], lim["max_jerk"], **motion)

    def sampled(a: np.ndarray, b_: np.ndarray) -> np.ndarray | None:
        """The timed motion a -> b at the resolution it is checked at (None: it leaves the limits)."""
        try:
            Q = timed([a, b_]).positions
        except ValueError:
            return None
        return Q[every_degree(Q)]

    def clear(waypoints: list[np.ndarray]) -> bool:
        try:
            return _motion_free(is_free, timed(waypoints).positions)
        except ValueError:
            return False

    def stand_off(k: int) -> np.ndarray | None:
        """The best stand-off at pose k (0: approach, -1: retract) whose plunge to or lift from
        the cut is clear, else the best one (the issue is then reported below)."""
        best = None
        for q in _stand_offs(kin, b.poses[k], b.q[k], cfg, is_free):
            if clear([q, b.q[k]]):
                return q
            best = q if best is None else best
        return best

    b.approach_q, b.retract_q = stand_off(0), stand_off(-1)
    for what, goal in (("approach", b.approach_q), ("retract", b.retract_q)):
        if goal is None:
            b.issues.append(f"{what} pose unreachable: no collision-free configuration holds the torch "
                            f"{cfg.approach_m:g} m back from the cut's {'first' if what == 'approach' else 'last'} pose")
            continue
        if what == "retract":
            waypoints = [b.q[-1], goal]
        else:  # the air move to the stand-off pose: straight in joint space, else lifted, else via park
            waypoints = [q_here, goal, b.q[0]]
            if not clear([q_here, goal]):
                for via in _air_routes(kin, q_here, goal, cfg, is_free, park_q):
                    if all(clear([u, v]) for u, v in zip(via[:-1], via[1:])):
                        waypoints = via + [b.q[0]]
                        break
                else:  # none of the simple routes: a roadmap through the free space, denser if need be
                    for samples in (150, 600):
                        via = roadmap_route(q_here, goal, lambda Q: _free(is_free, Q), sampled, kin.lower, kin.upper,
                                            samples=samples)
                        if via is not None:
                            waypoints = via + [b.q[0]]
                            break
        try:
            jp = timed(waypoints)
        except ValueError as exc:  # e.g. the time-optimal motion overshoots a joint limit
            b.issues.append(f"{what}: {exc}")
            continue
        if not _motion_free(is_free, jp.positions):
            part = "the plunge to the cut" if what == "approach" and clear(waypoints[:-1]) else (
                "the air move" if what == "approach" else "the lift off the cut")
            b.issues.append(f"{what} collides ({part})")
        setattr(b, what, jp)


def plan_cut_path(drawing: Cloud | np.ndarray, surface: Cloud | np.ndarray | None, kin: Kinematics,
                  q_start: np.ndarray, cfg: CutPathConfig | None = None, *, viewpoint: np.ndarray | None = None,
                  is_free: IsFree | None = None, unseen: np.ndarray | None = None, cell_m: float = 0.0,
                  explain=None, floor_z: float | None = None, **limits) -> CutPath:
    """build_cut_path then plan_cut, the torch's working end (``torch.fine_length_m``) kept
    ``nozzle_margin_m`` off the surface cloud (the drawing's own points when there is no surface),
    off the ``unseen`` cells (centres, side ``cell_m``) in front of it and above the plane z = ``floor_z``
    the piece stands on (``is_free`` checks the rest)."""
    cfg = cfg or CutPathConfig()
    surf = _surface(drawing, surface, viewpoint, cfg)
    path = build_cut_path(drawing, surf, cfg, viewpoint=viewpoint)
    near = _in_front(unseen, surf, path, cfg, cell_m)
    return plan_cut(path, kin, q_start, cfg, is_free=is_free, explain=explain,
                    nozzle_free=NozzleCheck(surf.tree, cfg.torch, cfg.nozzle_margin_m, near, cell_m, floor_z=floor_z),
                    **limits)


def _in_front(unseen: np.ndarray | None, surf: Surface, path: CutPath, cfg: CutPathConfig, cell_m: float) -> np.ndarray:
    """The unseen cells the torch's working end must keep off. Those it could reach while it cuts,
    plunges or lifts off (within ``approach_m`` of a cut pose) count where they lie in front of the
    measured surface: the ones behind it are the metal's inside, which the surface bounds. Farther
    out (the air moves) every one counts, as it does for the rest of the torch."""
    if unseen is None or len(unseen) == 0:
        return np.zeros((0, 3))
    c = np.asarray(unseen, dtype=np.float64).reshape(-1, 3)
    if not path.branches:
        return c
    tips = np.vstack([b.poses[:, :3, 3] for b in path.branches])
    reach = cfg.approach_m + cfg.torch.fine_length_m + cfg.torch.radius_m + cfg.nozzle_margin_m + cell_m
    near = np.isfinite(cKDTree(tips).query(c, distance_upper_bound=reach)[0])
    if not near.any():
        return c
    p = surf.xyz[surf.tree.query(c[near])[1]]
    front = np.einsum("ij,ij->i", c[near] - p, surf.normals(p, IN_FRONT_NEIGHBOURS)) > 0.0
    return np.vstack([c[~near], c[near][front]])
