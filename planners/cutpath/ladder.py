"""A branch's torch poses -> joint solutions by a ladder graph, as Descartes and Tesseract plan
process paths: the torch is held within a tolerance, not at one exact pose.

Every path point gets rungs: the torch axis sampled in a cone about the surface normal (lead/lag
along the travel, side tilt across it; roll about the axis is free for a round nozzle), each solved
by batched IK from several seeds, so each seed tends to stay on one arm configuration ("track").
Consecutive rungs are joined where no joint moves more than ``max_joint_jump_rad`` and the joint
speed at travel speed stays under the arm's limit. Collision checks are lazy (the expensive part):
only rungs on a chosen path are checked, and where one collides its whole layer and the layers
beside it are, before the search runs again.

Where no continuous path exists the branch splits into maximal cuttable runs (greedy from the start:
each run as long as the graph allows, which gives the fewest runs), and every uncut stretch is a gap
with its reason. Within a run the cheapest path (tilt away from the normal, joint motion) is found
by scipy's Dijkstra on the layered graph."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicHermiteSpline, PchipInterpolator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from planners.config import CutPathConfig
from planners.motion.ik_batch import solve_axis_ik_batch, spread_seeds
from planners.motion.kinematics import Kinematics

IsFree = Callable[[np.ndarray], np.ndarray]
Explain = Callable[[np.ndarray], list]
NozzleFree = Callable[[np.ndarray, np.ndarray], np.ndarray]

OUT_OF_REACH, JOINT_LIMITS, COLLISION = "out of reach", "joint limits", "collision"
SINGULAR, RECONFIGURE = "singular", "reconfigure"
GAP_REASONS = (OUT_OF_REACH, JOINT_LIMITS, COLLISION, SINGULAR, RECONFIGURE)
#: joint change allowed per radian the torch axis turns between two path points (a pivot)
PIVOT_GAIN = 2.0
#: share of each joint's speed limit a pivot may use (the timed spline overshoots the secant a little, and
#: the arm's tracking lags in proportion to speed: at 0.5 the twin's tip lagged 1.1 mm at a collar's edge)
PIVOT_SPEED = 0.3
#: colliding motions tried between two layers before the cut is split there (a reconfiguration: the
#: torch lifts and lands again, nothing is left uncut); bounds the lazy search near a tight corner
MOTION_TRIES = 8
#: IK iterations per rung: from a neighbouring layer's or the normal's solution IK converges within a
#: dozen, from a random seed within 50; on t_piece and the basket 0.1 % more rungs were solved between
#: 50 and 150 iterations, and those last iterations, for a few dozen creeping targets, cost a third
IK_ITERATIONS = 60
#: IK starts spread over the joint space for a pose none of the ladder's starts reached, before it is
#: called out of reach: the ladder's few starts follow the arm's tracks and can all miss a solution
REACH_SEEDS = 48
#: layers of a gap whose colliding configurations are asked what they hit
EXPLAINED_LAYERS = 6
_WHY = {OUT_OF_REACH: "the torch pose is beyond the arm's reach at every tilt",
        JOINT_LIMITS: "in reach, but no configuration within the joint limits holds the torch there",
        COLLISION: "every configuration that holds the torch there collides with the scanned piece or the arm",
        SINGULAR: "reachable, but no configuration joins its neighbours within the joint jump and speed limits "
                  "(near a singularity or a configuration change)",
        RECONFIGURE: "the arm lifts the torch and changes configuration here; nothing is left uncut"}


@dataclass
class Run:
    """Layers first..last (inclusive) cut in one go: the chosen rung per layer."""

    first: int
    last: int
    q: np.ndarray  # (L, dof)
    poses: np.ndarray  # (L, 4, 4) the tilted torch poses chosen
    tilt_rad: np.ndarray  # (L,) angle between the torch axis and the inward normal
    times: np.ndarray  # (L,) s from the first pose (``pivot_times``): the motion that was checked


@dataclass
class Gap:
    """Not cut between layer ``after`` (the last cut pose before it, -1 at the branch start) and
    layer ``before`` (the first cut pose after it, N at the branch end). ``after == before`` is a
    reconfiguration: the torch lifts and lands again at the same pose, nothing is left uncut."""

    after: int
    before: int
    reason: str
    detail: str = ""

    @property
    def uncut_layers(self) -> range:
        return range(self.after + 1, self.before)


@dataclass
class Ladder:
    runs: list[Run] = field(default_factory=list)
    gaps: list[Gap] = field(default_factory=list)
    layer_reason: list[str] = field(default_factory=list)  # per layer: "" if it has a free rung


def tilt_directions(cfg: CutPathConfig) -> np.ndarray:
    """(O, 3) torch axes in the nominal pose's frame (x travel, y across, z into the metal): the
    normal first, then an elliptic grid of lead/lag and side tilts within the cone."""
    a = np.radians(cfg.lead_lag_max_deg)
    b = np.radians(cfg.side_tilt_max_deg)
    n = cfg.tilt_steps
    f = np.linspace(-1.0, 1.0, 2 * n + 1) if n > 0 else np.zeros(1)
    u, v = np.meshgrid(f * a, f * b, indexing="ij")
    u, v = u.ravel(), v.ravel()
    inside = (u / max(a, 1e-12)) ** 2 + (v / max(b, 1e-12)) ** 2 <= 1.0 + 1e-9
    u, v = u[inside], v[inside]
    order = np.argsort(np.hypot(u, v), kind="stable")  # the normal (0, 0) first
    u, v = u[order], v[order]
    d = np.stack([np.sin(u) * np.cos(v), np.sin(v), np.cos(u) * np.cos(v)], axis=1)
    keep = np.unique(np.round(d, 9), axis=0, return_index=True)[1]
    return d[np.sort(keep)]


@dataclass
class Rungs:
    """A branch's IK solutions: every layer (path point) x tilt x seed."""

    tips: np.ndarray  # (N,O,3) torch tip per layer and tilt (tilted about the paint point)
    axes: np.ndarray  # (N,O,3) torch axis in the base frame
    in_reach: np.ndarray  # (N,O) inside the arm's reach sphere
    Q: np.ndarray  # (N,O,S,dof) the solutions (best attempts where not ok)
    ok: np.ndarray  # (N,O,S)

    def reversed(self, perm: np.ndarray) -> "Rungs":
        """The same rungs for the branch run the other way (``Branch.reversed``: layers reversed,
        each pose turned half a turn about its axis, so tilt o is tilt perm[o] of the other way)."""
        return Rungs(self.tips[::-1][:, perm], self.axes[::-1][:, perm], self.in_reach[::-1][:, perm],
                     self.Q[::-1][:, perm], self.ok[::-1][:, perm])


def reversal_permutation(cfg: CutPathConfig) -> np.ndarray:
    """perm[o]: the tilt of the reversed pose frame (x and y negated) that points where tilt o does."""
    D = tilt_directions(cfg)
    flipped = D * [-1.0, -1.0, 1.0]
    d = np.linalg.norm(flipped[:, None] - D[None], axis=2)
    return d.argmin(axis=1)


def solve_rungs(kin: Kinematics, branch_poses: list[np.ndarray], q_start: np.ndarray,
                cfg: CutPathConfig) -> list[Rungs]:
    """The rungs of several branches in one batched IK (a basket's dozen short cuts cost one call,
    not a dozen): each seed solved at the normal of every layer, then from there at every tilt,
    then gaps in a track filled from the neighbouring layer's solution in the same track (never
    across two branches)."""
    sizes = [len(P) for P in branch_poses]
    if not sizes or sum(sizes) == 0:
        return []
    poses = np.concatenate(branch_poses)
    N = len(poses)
    D = tilt_directions(cfg)  # (O,3)
    O, S, dof = len(D), cfg.ik_seeds, kin.dof
    axes = np.einsum("nij,oj->noi", poses[:, :3, :3], D)  # (N,O,3) torch axis in base
    tips = poses[:, None, :3, 3] + cfg.standoff_m * (poses[:, None, :3, 2] - axes)  # tilt about the paint point
    centre, radius = kin.reach_sphere("cam")
    in_reach = np.linalg.norm(tips - centre, axis=2) <= radius  # (N,O)
    seeds = spread_seeds(kin, q_start, S, cfg.ik_margin_rad)
    # a fixed roll keeps the torch's x along the travel (the nominal pose's x made orthogonal to the axis)
    xs = None if cfg.free_roll else np.broadcast_to(poses[:, None, :3, 0], axes.shape)
    Qn, okn = solve_axis_ik_batch(kin, np.repeat(tips[:, 0], S, 0), np.repeat(axes[:, 0], S, 0),
                                  np.tile(seeds, (N, 1)), margin=cfg.ik_margin_rad, max_iter=IK_ITERATIONS,
                                  x_axes=None if xs is None else np.repeat(xs[:, 0], S, 0))
    Qn, okn = Qn.reshape(N, S, dof), okn.reshape(N, S)
    Q = np.full((N, O, S, dof), np.nan)
    ok = np.zeros((N, O, S), dtype=bool)
    seed = np.broadcast_to(Qn[:, None], (N, O, S, dof))
    Q[:], ok[:] = _solve(kin, tips, axes, seed, np.broadcast_to(okn[:, None], (N, O, S)), cfg, xs)
    first = np.zeros(N, dtype=bool)
    first[np.cumsum([0] + sizes[:-1])] = True  # each branch's first layer
    last = np.roll(first, -1)  # each branch's last layer
    for direction in (1, -1, 1):  # sweeps: a track that failed takes its neighbour's solution as seed
        src = np.roll(Q, direction, axis=0)
        src_ok = np.roll(ok, direction, axis=0)
        src_ok[first if direction == 1 else last] = False
        todo = ~ok & src_ok
        if not todo.any():
            continue
        Qs, oks = _solve(kin, tips, axes, src, todo, cfg, xs)
        Q[todo], ok[todo] = Qs[todo], oks[todo]
    cuts = np.cumsum(sizes)[:-1]
    return [Rungs(*parts) for parts in zip(*(np.split(x, cuts) for x in (tips, axes, in_reach, Q, ok)))]


def plan_ladder(kin: Kinematics, poses: np.ndarray, times: np.ndarray, q_start: np.ndarray, cfg: CutPathConfig,
                is_free: IsFree | None, max_vel: np.ndarray, nozzle_free: NozzleFree | None = None,
                rungs: Rungs | None = None, explain: Explain | None = None) -> Ladder:
    """Runs and gaps along one branch's nominal torch poses (N,4,4) timed by ``times`` (N,).
    ``nozzle_free(tips, axes)``: whether the nozzle is clear of the metal at each tilt (``nozzle.py``);
    a tilt whose nozzle is not is no rung. ``rungs``: this branch's from ``solve_rungs`` (solved here
    from ``q_start`` when None). ``explain(Q)``: what each colliding configuration hits (the floor,
    the piece, the arm itself ...), for the gaps' details; a pose no IK start reached is tried from
    ``REACH_SEEDS`` more before it is called out of reach."""
    N = len(poses)
    D = tilt_directions(cfg)  # (O,3)
    O, S, dof = len(D), cfg.ik_seeds, kin.dof
    if rungs is None:
        rungs = solve_rungs(kin, [poses], q_start, cfg)[0]
    if rungs.Q.shape[:3] != (N, O, S):
        raise ValueError(f"rungs for {rungs.Q.shape[:3]} layers x tilts x seeds, the branch needs {(N, O, S)}")
    tips, axes, in_reach, Q, ok = rungs.tips, rungs.axes, rungs.in_reach, rungs.Q, rungs.ok

    # nodes: (layer, rung) with rung = o*S + s
    Qf = Q.reshape(N, O * S, dof)
    solved = ok.reshape(N, O * S) & np.repeat(in_reach, S, axis=1)  # the arm holds the torch there
    clear = np.ones((N, O), dtype=bool) if nozzle_free is None else np.asarray(nozzle_free(tips, axes), dtype=bool)
    valid = solved & np.repeat(clear, S, axis=1)
    tilt = np.repeat(np.arccos(np.clip(D[:, 2], -1.0, 1.0)), S)  # (O*S,)
    checked = np.zeros_like(valid)
    free = np.ones_like(valid)

    joinable, motion_cost = _joins(Qf, np.repeat(axes, S, axis=1), cfg)
    blocked = np.zeros_like(joinable)  # edges whose motion collides

    def edges(k: int, usable: np.ndarray) -> np.ndarray:
        """(R,R) bool: rung i of layer k joins rung j of layer k+1 (both usable, motion not blocked)."""
        return joinable[k] & ~blocked[k] & usable[k][:, None] & usable[k + 1][None, :]

    flame = OnLine(kin, poses[:, :3, 3] + cfg.standoff_m * poses[:, :3, 2], cfg.standoff_m, cfg.flame_deviation_m)
    seg_free: set = set()  # spline segments found free, keyed by their four rungs
    motion_hits = np.zeros(max(N - 1, 0), dtype=np.int64)  # colliding motions found per layer pair
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))])
    least = cfg.min_cut_m if s[-1] >= cfg.min_cut_m else cfg.spacing_m
    while True:
        usable = valid & free
        runs = _balanced(_split(N, usable, edges), usable, edges, s, least)
        chosen = [_cheapest(r, usable, joinable & ~blocked, motion_cost, tilt, cfg) for r in runs]
        # lazy collision check of the chosen rungs; a hit checks its layer and two either side
        hit_layers = set()
        if is_free is not None and runs:  # every run's unchecked chosen rungs in one call
            lay = np.concatenate([np.arange(first, last + 1) for first, last in runs])
            rung = np.concatenate(chosen)
            need = ~checked[lay, rung]
            if need.any():
                lay, rung = lay[need], rung[need]
                res = _free(is_free, Qf[lay, rung])
                checked[lay, rung] = True
                free[lay, rung] = res
                hit_layers.update(lay[~res].tolist())
        if not hit_layers:
            # the rungs are free: now the motion between them (joint-space steps of at most 1 degree),
            # clear of the piece and with the flame on the line; once it is so segment by segment, the
            # runs once more as wholes: the samples of a whole run (what the cut will be checked at)
            # fall elsewhere than those of the segments
            hit_edges = _check_motion(runs, chosen, Qf, tips, S, cfg, max_vel, is_free, seg_free, flame)
            if not hit_edges:
                hit_edges = _check_motion(runs, chosen, Qf, tips, S, cfg, max_vel, is_free, set(), flame)
            for k, a, b in hit_edges:
                blocked[k, a, b] = True
                motion_hits[k] += 1
                if motion_hits[k] >= MOTION_TRIES:  # no clear motion found here: the torch lifts and lands again
                    blocked[k] = True
            if hit_edges:
                continue
        if not hit_layers:
            break
        near = np.array(sorted({j for k in hit_layers for j in range(k - 2, k + 3) if 0 <= j < N}))
        lay, rung = np.nonzero(valid[near] & ~checked[near])  # every rung there, in one call
        if len(lay):
            lay = near[lay]
            free[lay, rung] = _free(is_free, Qf[lay, rung])
            checked[lay, rung] = True

    out = Ladder()
    usable = valid & free
    # how close the best failed attempt got the tip: beyond 1 cm the point is out of the arm's
    # reach (with its joint limits), within it the limits or the axis stop it
    lost = ~solved.any(axis=1)
    near_miss = np.zeros(N, dtype=bool)
    found = _reach_anyway(kin, tips, axes, in_reach, lost, cfg)  # layer -> configurations another start found
    for k in found:
        lost[k] = False
    if lost.any():
        tries = Qf[lost].reshape(-1, dof)
        err = np.linalg.norm(kin.fk_batch(np.nan_to_num(tries))[:, :3, 3]
                             - np.repeat(tips[lost], S, axis=1).reshape(-1, 3), axis=1)
        near_miss[lost] = (err.reshape(lost.sum(), O * S) <= 0.01).any(axis=1)
    for k in range(N):  # a reason per layer, from whole-layer masks
        if usable[k].any():
            out.layer_reason.append("")
        elif k in found:  # reachable from other starts: the ladder's tracks do not get there
            out.layer_reason.append(COLLISION if is_free is not None and not _free(is_free, found[k]).any()
                                    else SINGULAR)
        elif not in_reach[k].any() or (not solved[k].any() and not near_miss[k]):
            out.layer_reason.append(OUT_OF_REACH)
        elif solved[k].any():  # held there, but the arm, the torch or its nozzle touches
            out.layer_reason.append(COLLISION)
        else:
            out.layer_reason.append(JOINT_LIMITS)
    short = _stubs(runs, s, least, cfg.spacing_m)  # pierces for nothing: they join the gap beside them
    for (first, last), drop in zip(runs, short):
        if drop:
            beside = [r for r in out.layer_reason[max(first - 1, 0):last + 2] if r] or [SINGULAR]
            out.layer_reason[first:last + 1] = [beside[0]] * (last - first + 1)
    runs = [r for r, drop in zip(runs, short) if not drop]
    chosen = [c for c, drop in zip(chosen, short) if not drop]
    for (first, last), rungs in zip(runs, chosen):
        lay = np.arange(first, last + 1)
        o = rungs // S
        T = poses[lay].copy()
        z = axes[lay, o]
        x = T[:, :3, 0] - np.einsum("ij,ij->i", T[:, :3, 0], z)[:, None] * z
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, np.cross(z, x), z, tips[lay, o]
        q = Qf[lay, rungs].copy()
        out.runs.append(Run(first, last, q, T, tilt[rungs].copy(),
                            pivot_times(tips[lay, o], q, cfg.travel_speed_mps, max_vel)))
    out.gaps = _gaps(N, runs, out.layer_reason)
    if explain is not None:
        for g in out.gaps:
            if g.reason == COLLISION:
                g.detail = _blockers(g, out.layer_reason, Qf, solved, valid, found, explain) or g.detail
    return out


def _reach_anyway(kin: Kinematics, tips: np.ndarray, axes: np.ndarray, in_reach: np.ndarray, lost: np.ndarray,
                  cfg: CutPathConfig) -> dict[int, np.ndarray]:
    """For the layers none of the ladder's starts solved (at any tilt) but inside the reach sphere:
    their normal-tilt pose from ``REACH_SEEDS`` starts spread over the joint space, one batch.
    Returns layer -> the configurations found (within the joint limits and margin)."""
    todo = np.flatnonzero(lost & in_reach[:, 0])
    if len(todo) == 0:
        return {}
    seeds = spread_seeds(kin, 0.5 * (kin.lower + kin.upper), REACH_SEEDS, cfg.ik_margin_rad)
    n = len(todo)
    Q, ok = solve_axis_ik_batch(kin, np.repeat(tips[todo, 0], len(seeds), 0), np.repeat(axes[todo, 0], len(seeds), 0),
                                np.tile(seeds, (n, 1)), margin=cfg.ik_margin_rad, max_iter=2 * IK_ITERATIONS)
    Q, ok = Q.reshape(n, len(seeds), -1), ok.reshape(n, len(seeds))
    return {int(k): Q[i][ok[i]] for i, k in enumerate(todo) if ok[i].any()}


def _blockers(g: Gap, layer_reason: list[str], Qf: np.ndarray, solved: np.ndarray, valid: np.ndarray,
              found: dict[int, np.ndarray], explain: Explain) -> str:
    """What the configurations holding the torch in a collision gap hit, counted over a handful of its
    layers: "every configuration ... collides: the piece (12), the floor (3); the nozzle touches the metal or the table (4)"."""
    lay = [k for k in g.uncut_layers if layer_reason[k] == COLLISION]
    if not lay:
        return ""
    lay = lay[::max(1, len(lay) // EXPLAINED_LAYERS)][:EXPLAINED_LAYERS]
    counts: dict[str, int] = {}
    for k in lay:  # a handful of layers, each one batch
        nozzle = solved[k] & ~valid[k]
        if nozzle.any():
            what = "the nozzle touches the metal or the table"
            counts[what] = counts.get(what, 0) + int(nozzle.sum())
        Q = Qf[k][solved[k] & valid[k]] if (solved[k] & valid[k]).any() else found.get(k, np.zeros((0, Qf.shape[2])))
        for what in explain(Q[:8]):
            if what:
                counts[what] = counts.get(what, 0) + 1
    if not counts:
        return ""
    parts = ", ".join(f"{w} ({n})" for w, n in sorted(counts.items(), key=lambda kv: -kv[1]))
    return f"every configuration that holds the torch there is blocked: {parts}, over {len(lay)} of its poses"


def _joins(Qf: np.ndarray, rung_axis: np.ndarray, cfg: CutPathConfig) -> tuple[np.ndarray, np.ndarray]:
    """For every pair of consecutive layers, (N-1,R,R): may rung i of layer k join rung j of layer
    k+1, and the joint motion between them (squared, the search's cost). The joints may move
    ``max_joint_jump_rad`` plus what turning the torch between the two rungs needs (PIVOT_GAIN per
    radian): at a sharp corner of the line the torch pivots about its tip, the joints turn with it,
    and the cut slows down there (``pivot_times``); a jump without such a turn is a change of arm
    configuration, which needs the torch lifted. The torch's axis may turn by the normal's turn between
    the two poses plus one ``pivot_step_deg`` (rung 0 of each layer holds the normal). Computed once: the
    lazy search asks for it often."""
    cos = np.einsum("kid,kjd->kij", rung_axis[:-1], rung_axis[1:])
    turn = np.arccos(np.clip(cos, -1.0, 1.0))
    limit = cfg.max_joint_jump_rad + PIVOT_GAIN * turn
    # the torch turns between two poses by the normal's turn and one pivot step more at most: a tilt
    # thrown from one side of the cone to the other between two poses swings the flame off the line
    nominal = np.arccos(np.clip(np.einsum("kd,kd->k", rung_axis[:-1, 0], rung_axis[1:, 0]), -1.0, 1.0))
    steady = turn <= nominal[:, None, None] + np.radians(cfg.pivot_step_deg) + 1e-9
    jump = np.zeros_like(limit)
    cost = np.zeros_like(limit)
    for j in range(Qf.shape[2]):  # per joint: keeps the temporaries at (N-1,R,R)
        d = Qf[1:, None, :, j] - Qf[:-1, :, None, j]
        np.maximum(jump, np.abs(d), out=jump)  # NaN (no solution) stays NaN: never joins
        cost += d * d
    with np.errstate(invalid="ignore"):
        return (jump <= limit) & steady, cost


def pivot_times(points: np.ndarray, q: np.ndarray, travel_speed: float, max_vel: np.ndarray) -> np.ndarray:
    """Times (L,) along a run: each step takes its length at the travel speed, or longer where the
    joints must turn faster than PIVOT_SPEED of their limits (the torch pivoting at a corner)."""
    ds = np.linalg.norm(np.diff(points, axis=0), axis=1) / travel_speed
    dq = (np.abs(np.diff(q, axis=0)) / (PIVOT_SPEED * np.asarray(max_vel))[None, :]).max(axis=1)
    return np.concatenate([[0.0], np.cumsum(np.maximum(ds, dq))])


def _solve(kin, tips, axes, seed, todo, cfg, xs=None) -> tuple[np.ndarray, np.ndarray]:
    """Batched IK for the (N,O,S) entries marked ``todo`` from ``seed`` (N,O,S,dof)."""
    N, O, S = todo.shape
    Q = np.full((N, O, S, kin.dof), np.nan)
    ok = np.zeros((N, O, S), dtype=bool)
    idx = np.nonzero(todo)
    if len(idx[0]) == 0:
        return Q, ok
    q, good = solve_axis_ik_batch(kin, tips[idx[0], idx[1]], axes[idx[0], idx[1]], seed[idx],
                                  margin=cfg.ik_margin_rad, max_iter=IK_ITERATIONS,
                                  x_axes=None if xs is None else xs[idx[0], idx[1]])
    Q[idx], ok[idx] = q, good
    return Q, ok


def cut_spline(times: np.ndarray, q: np.ndarray):
    """The cut's joint motion through the rungs: a shape-preserving cubic (PCHIP slopes), at rest
    at both ends (the arm arrives from the approach and leaves for the retract stopped). Between two
    rungs no joint goes beyond them; a natural cubic overshot by enough to touch the piece at a 5 mm
    margin."""
    slopes = PchipInterpolator(times, q, axis=0).derivative()(times)
    slopes[[0, -1]] = 0.0
    return CubicHermiteSpline(times, q, slopes, axis=0)


def every_degree(Q: np.ndarray) -> np.ndarray:
    """Indices of the rows of a dense joint path where some joint has moved another degree (ends
    kept): what a collision check of the motion needs, not every sample of it."""
    if len(Q) <= 2:
        return np.arange(len(Q))
    travel = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(Q, axis=0)).max(axis=1))])
    step = np.floor(travel / np.radians(1.0))
    keep = np.ones(len(Q), dtype=bool)
    keep[1:-1] = step[1:-1] != step[:-2]
    return np.flatnonzero(keep)


@dataclass
class OnLine:
    """The lit flame stays on the line between two poses: the flame spot (``standoff`` ahead of the tip
    along the torch axis) at a sample of the motion from layer k to k+1 lies within ``deviation`` of
    the segment between their paint points. A joint move that swings the torch (a change of arm
    configuration passed off as a pivot) takes the flame off the line, through metal nobody marked."""

    kin: Kinematics
    points: np.ndarray  # (N,3) the paint point of each layer
    standoff: float
    deviation: float

    def off(self, Q: np.ndarray, seg: np.ndarray) -> np.ndarray:
        """(M,) bool: sample Q[m], on its way from layer seg[m] to seg[m]+1, has the flame off the line."""
        if len(Q) == 0:
            return np.zeros(0, dtype=bool)
        T = self.kin.fk_batch(Q)
        spot = T[:, :3, 3] + self.standoff * T[:, :3, 2]
        a, b = self.points[seg], self.points[seg + 1]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", spot - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18), 0.0, 1.0)
        return np.linalg.norm(spot - (a + t[:, None] * ab), axis=1) > self.deviation


def _check_motion(runs, chosen, Qf: np.ndarray, tips: np.ndarray, S: int, cfg: CutPathConfig, max_vel,
                  is_free: IsFree | None, known_free: set, flame: OnLine | None = None) -> list[tuple[int, int, int]]:
    """Check of the motion the cut will execute along each chosen path (the timed spline, a sample
    per degree of joint travel), in one call: clear of the piece (``is_free``) and the flame on the
    line (``flame``); returns the (layer, rung, next rung) edges during which either fails. The
    spline between layers k and k+1 depends on rungs k-1 .. k+2 only (their slopes and times), so a
    segment found good under those four rungs is remembered in ``known_free`` and not checked again
    when the search changes the path elsewhere."""
    samples, owner, segs = [], [], []
    for (first, last), rungs in zip(runs, chosen):
        lay = np.arange(first, last + 1)
        q = Qf[lay, rungs]
        t = pivot_times(tips[lay, rungs // S], q, cfg.travel_speed_mps, max_vel)
        tt = np.append(np.arange(0.0, t[-1], cfg.dt_s), t[-1])
        Q = cut_spline(t, q)(tt)
        keep = every_degree(Q)
        seg = np.clip(np.searchsorted(t, tt[keep], side="right") - 1, 0, len(t) - 2)
        padded = np.concatenate([[-1], rungs, [-1]])  # run ends: no neighbour
        keys = [(first + int(k), *padded[k:k + 4].tolist()) for k in range(len(rungs) - 1)]
        todo = np.array([keys[k] not in known_free for k in seg], dtype=bool)
        samples.append(Q[keep][todo])
        segs.append(first + seg[todo])
        owner += [(keys[k], first + int(k), int(rungs[k]), int(rungs[k + 1])) for k in seg[todo]]
    if not owner:
        return []
    Qs = np.vstack(samples)
    ok = _free(is_free, Qs) if is_free is not None else np.ones(len(Qs), dtype=bool)
    if flame is not None:
        ok &= ~flame.off(Qs, np.concatenate(segs))
    bad = {(k, a, b) for (_, k, a, b), good in zip(owner, ok) if not good}
    hit = {o[0] for o, good in zip(owner, ok) if not good}
    known_free.update({o[0] for o in owner} - hit)
    return sorted(bad)


def _free(is_free: IsFree, Q: np.ndarray) -> np.ndarray:
    out = np.asarray(is_free(Q))
    if out.shape != (len(Q),):
        raise ValueError(f"is_free must return shape ({len(Q)},), got {out.shape}")
    return out.astype(bool)


def _split(N: int, usable: np.ndarray, edges) -> list[tuple[int, int]]:
    """Maximal runs from the start: a run goes on while some rung it can reach joins the next
    layer; the next run starts again at the layer where one stopped (the torch lifts, the arm
    changes configuration, the cut goes on from the same point). A run needs two layers at least:
    one pose is not a cut."""
    runs = []
    k = 0
    while k < N:
        if not usable[k].any():
            k += 1
            continue
        first, reach = k, usable[k].copy()
        while k + 1 < N:
            nxt = (reach[:, None] & edges(k, usable)).any(axis=0)
            if not nxt.any():
                break
            reach, k = nxt, k + 1
        if k > first:
            runs.append((first, k))
            if k == N - 1:
                break
        else:
            k += 1
    return runs


def _stubs(runs: list[tuple[int, int]], s: np.ndarray, least: float, spacing_m: float) -> list[bool]:
    """Which runs are no cut (arc lengths ``s`` per layer). One shorter than a spacing along the line (a
    pivot in place at an inside corner) is a pierce, not a cut; so is one shorter than ``least`` between
    two stretches left uncut or the branch's ends (a stub: a pierce for a few millimetres). One the
    torch lands on beside another run (a reconfiguration: nothing is left uncut between them) cuts its
    paint and stays: dropping it beside a gap too (scrap:0:8's 5 mm between a collision and a
    reconfiguration) cost the cut oracle 1.5 points of its median over the generated pieces, the pieces
    of paint on a grid's bars and a basket's rods among them (15 points on scrap:0:18)."""
    lands = {last for _, last in runs} & {first for first, _ in runs}  # layers where a run hands over to the next
    return [s[last] - s[first] < 0.999 * spacing_m
            or (s[last] - s[first] < 0.999 * least and first not in lands and last not in lands)
            for first, last in runs]


def _balanced(runs: list[tuple[int, int]], usable: np.ndarray, edges, s: np.ndarray,
              least: float) -> list[tuple[int, int]]:
    """The split's runs with each one shorter than ``least`` (arc lengths ``s`` per layer) that the run
    before hands over to (a reconfiguration) started earlier, where its configurations reach back:
    the hand-over moves back as far as leaves it ``least`` long and the run before as long. The
    greedy split makes the fewest runs but hands over as late as it can, which can leave a stub of a
    few millimetres between two reconfigurations (a pierce for it: scrap:0:36, two 15 mm cuts on a
    tank head); the runs and their count stay, only where they meet moves."""
    out = list(runs)
    for i in range(1, len(out)):  # a handful of runs
        (pf, pl), (f, l) = out[i - 1], out[i]
        if pl != f or s[l] - s[f] >= 0.999 * least:  # the short rule's own tolerance
            continue
        back, k = usable[l].copy(), l
        while k - 1 > pf:  # back from its last layer while some configuration still joins on
            prev = (edges(k - 1, usable) & back[None, :]).any(axis=1)
            if not prev.any():
                break
            back, k = prev, k - 1
        h = np.arange(k, f + 1)
        h = h[(s[l] - s[h] >= 0.999 * least) & (s[h] - s[pf] >= 0.999 * least)]
        if len(h):
            out[i - 1], out[i] = (pf, int(h[-1])), (int(h[-1]), l)
    return out


def _cheapest(run: tuple[int, int], usable: np.ndarray, joins: np.ndarray, motion_cost: np.ndarray,
              tilt: np.ndarray, cfg: CutPathConfig) -> np.ndarray:
    """Rung per layer of the cheapest path through the run: Dijkstra on the layered graph from a
    virtual source before its first layer to a virtual sink after its last."""
    first, last = run
    L, R = last - first + 1, usable.shape[1]
    node_cost = cfg.tilt_cost_weight * tilt ** 2  # (R,)
    src, sink = L * R, L * R + 1
    e = joins[first:last] & usable[first:last, :, None] & usable[first + 1:last + 1, None, :]
    i, a, b = np.nonzero(e)
    start, end = np.flatnonzero(usable[first]), np.flatnonzero(usable[last])
    rows = np.concatenate([np.full(len(start), src), i * R + a, (L - 1) * R + end])
    cols = np.concatenate([start, (i + 1) * R + b, np.full(len(end), sink)])
    w = np.concatenate([node_cost[start], motion_cost[first + i, a, b] + node_cost[b], np.zeros(len(end))]) + 1e-9
    G = coo_matrix((w, (rows, cols)), shape=(L * R + 2,) * 2).tocsr()
    dist, pred = dijkstra(G, directed=True, indices=src, return_predecessors=True)
    if not np.isfinite(dist[sink]):
        raise RuntimeError("a run found by the split has no path: the graph changed under it")
    path = []
    node = pred[sink]
    while node != src:  # one step per layer of the run
        path.append(node % R)
        node = pred[node]
    return np.array(path[::-1], dtype=np.int64)


def _gaps(N: int, runs: list[tuple[int, int]], reason: list[str]) -> list[Gap]:
    """Every stretch between runs (and before the first, after the last), with the most common
    reason of its uncut layers; layers that have free rungs but no joinable ones are 'singular'."""
    gaps = []
    prev = -1
    for first, last in runs + [(N, N)]:
        if first == prev:
            gaps.append(Gap(prev, prev, RECONFIGURE, _WHY[RECONFIGURE]))
        elif first > prev + 1:
            seg = [r or SINGULAR for r in reason[prev + 1:first]] or [SINGULAR]
            why = max(sorted(set(seg)), key=seg.count)
            counts = ", ".join(f"{seg.count(r)} {r}" for r in sorted(set(seg)))
            gaps.append(Gap(prev, first, why, f"{_WHY[why]} ({counts}; {len(seg)} pose{'s' * (len(seg) != 1)} in all)"))
        prev = last
    return gaps
