"""Paint where the measured surface ends: the frontier finer than the grid's cells. On thin stock (a
basket's 16 mm rods) one 1 cm cell holds a rod's front, seen square-on, and its flanks, never seen:
the grid calls the cell known and no frontier points at the flanks. The point cloud does know: the
paint seen so far stops where the surface seen so far stops, not where the paint does. A point on
the edge of a sampled surface has its neighbours on one side: their centroid, in the tangent plane,
lies 4r/(3 pi) = 0.42 r inward for a half disc of radius r, and near 0 inside the surface.
``ends.sealed`` asks the same of the centroid in 3-D over the end tube's 12 mm; over the few
millimetres that tell a rod's flank, depth noise and the rod's curvature move the 3-D centroid off
the point as far as a border does (on t_piece's flat, fully seen plate, 983 of 7098 paint points
were unsealed at 5 mm), so here the shift is measured in the tangent plane."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from planners import nbv, raycast
from planners.base import ScanState, ViewPlan
from planners.discs import discs
from planners.growth import EdgeYield
from planners.config import NBVConfig
from planners.views import in_image, look_at_rotations, poses_from, quarter_turn, sphere_lattice

#: centroid shift (share of the radius) halfway between a surface's inside (0) and its edge (0.42)
EDGE_SHIFT = 2.0 / (3.0 * np.pi)
#: neighbours at most in a point's disc (the nearest of those within the radius)
NEIGHBOURS = 32
#: fewer neighbours than this in the disc: too sparse to tell an edge (isolated points are noise)
MIN_NEIGHBOURS = 6
#: a view sees an open point usefully when it looks at least this much further round its border
EDGE_TURN = np.pi / 6
#: open points scored at most in a joint plan (a fixed thinning of them)
JOINT_POINTS = 2000
#: the resultant of the open points' unit normals at least this for them to lie on one face
#: (normals within about 25 deg of their mean); a rod's front, its normals spread round its
#: curve, has no one face to look round from
ONE_FACE = 0.9
#: how high above an open point measured surface is looked for that stands over its border (a
#: wall the paint runs up, a flange overhead): within the reach of a view's standoff
WALL_PROBE_M = 0.15


@dataclass
class OpenEdges:
    """Drawing points on the edge of the measured surface: where they are, their surface normal
    (toward the sensors that saw them) and the tangent pointing away from what was seen, along
    which the surface, and maybe the paint, goes on unseen."""

    xyz: np.ndarray  # (M,3)
    normals: np.ndarray  # (M,3)
    outward: np.ndarray  # (M,3), unit, orthogonal to the normal
    index: np.ndarray  # (M,) rows of the drawing
    wall: np.ndarray | None = None  # (M,) m: height of measured wall over the border (wall_heights), 0 at a rim

    def __post_init__(self):
        if self.wall is None:
            self.wall = np.zeros(len(self.xyz))

    def rows(self, keep: np.ndarray) -> "OpenEdges":
        return OpenEdges(self.xyz[keep], self.normals[keep], self.outward[keep], self.index[keep], self.wall[keep])


def open_paint_edges(drawing: np.ndarray, drawing_origin: np.ndarray, surface: np.ndarray,
                     radius_m: float) -> OpenEdges:
    """The drawing points whose disc of measured surface (radius ``radius_m``: a few point spacings)
    is one-sided (``EDGE_SHIFT``). ``drawing_origin``: the sensor position each drawing point was
    seen from (normals face it)."""
    P = np.asarray(drawing, dtype=np.float64).reshape(-1, 3)
    S = np.asarray(surface, dtype=np.float64).reshape(-1, 3)
    O = np.asarray(drawing_origin, dtype=np.float64).reshape(-1, 3)
    if radius_m <= 0:
        raise ValueError(f"radius_m must be positive, got {radius_m}")
    empty = OpenEdges(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
    if len(P) == 0 or len(S) == 0:
        return empty
    lo, hi = P.min(axis=0) - radius_m, P.max(axis=0) + radius_m  # the surface near the drawing only
    S = S[np.all((S >= lo) & (S <= hi), axis=1)]
    if len(S) < MIN_NEIGHBOURS:
        return empty
    disc = discs(P, cKDTree(S), radius_m, NEIGHBOURS)
    cnt, n = disc.count, disc.normals
    toward = O - P
    seen = np.all(np.isfinite(toward), axis=1)
    flip = seen & (np.einsum("mj,mj->m", n, np.where(seen[:, None], toward, 0.0)) < 0)
    n[flip] *= -1.0
    c_t = disc.shift  # the centroid's offset in the tangent plane (a flip of n leaves it)
    shift = np.linalg.norm(c_t, axis=1)
    edge = (cnt >= MIN_NEIGHBOURS) & (shift > EDGE_SHIFT * radius_m)
    if not edge.any():
        return empty
    out = -c_t[edge] / shift[edge, None]
    wall = wall_heights(P[edge], n[edge], out, surface, radius_m)
    out[wall > 0] *= -1.0
    return OpenEdges(P[edge], n[edge], out, np.flatnonzero(edge), wall)


def wall_heights(P: np.ndarray, n: np.ndarray, out: np.ndarray, surface: np.ndarray, radius_m: float) -> np.ndarray:
    """(M,) m: how high measured surface stands over each open point's border (the highest probe,
    up to ``WALL_PROBE_M`` along the point's normal, at the border or just past it, with surface
    within ``radius_m``); 0 where none does (a rim). Where it does, the
    surface does not turn away past the border as at a rim: a wall rises (an angle's other leg, a
    web, a pipe standing on a plate) or a flange overhangs it, and the unseen surface is the wall's
    face turned back toward the paint, or the shadow under the overhang. It is seen from the
    paint's own side, so for these points the way round the border is reversed: a view from past
    the border sees the wall's back (on thin stock, through one grid cell, the paint counts as
    seen from there and the line is lost). The height says how much unseen face may carry the
    paint on: a whole wall, not a rim's one-cell flank (``EdgeViews._gain``)."""
    S = np.asarray(surface, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0 or len(S) == 0:
        return np.zeros(len(P))
    lo, hi = P.min(axis=0) - WALL_PROBE_M, P.max(axis=0) + WALL_PROBE_M
    S = S[np.all((S >= lo) & (S <= hi), axis=1)]
    if len(S) == 0:
        return np.zeros(len(P))
    step = 2.0 * radius_m
    heights = np.arange(2.0 * radius_m, WALL_PROBE_M + 1e-9, step)  # clear of the paint's own face
    ahead = np.array([0.0, 2.0 * radius_m])  # at the border, and just past it
    probes = (P[:, None, None, :] + heights[None, :, None, None] * n[:, None, None, :]
              + ahead[None, None, :, None] * out[:, None, None, :])  # (M, H, A, 3)
    d, _ = cKDTree(S).query(probes.reshape(-1, 3), k=1, distance_upper_bound=radius_m, workers=-1)
    hit = np.isfinite(d).reshape(len(P), len(heights), len(ahead)).any(axis=2)  # (M, H)
    return np.where(hit, heights[None, :], 0.0).max(axis=1)


def round_edge_axis(drawing: np.ndarray, drawing_origin: np.ndarray, surface: np.ndarray, target: np.ndarray,
                    near_m: float, radius_m: float) -> np.ndarray | None:
    """Where to look from at the paint within ``near_m`` of ``target`` when it lies on the border of
    the measured surface: halfway round that border, between the surface's mean normal and the mean
    way out past it (unit). The surface past a border was not seen by the views that saw up to it,
    so it turns away from them: at a rim the outer face is round the corner, not under the top's
    normal. None when fewer than ``MIN_NEIGHBOURS`` open points lie there, their ways out
    disagree (points all round a patch: no one way round), or they lie on no one face
    (``ONE_FACE``: on thin round stock every point is near a border, and the mean way out would
    turn the cone off the views that look down on the stock)."""
    P = np.asarray(drawing, dtype=np.float64).reshape(-1, 3)
    near = np.sum((P - target) ** 2, axis=1) < near_m * near_m
    if near.sum() < MIN_NEIGHBOURS:
        return None
    edges = open_paint_edges(P[near], np.asarray(drawing_origin)[near], surface, radius_m)
    if len(edges.xyz) < MIN_NEIGHBOURS:
        return None
    n, out = edges.normals.mean(axis=0), edges.outward.mean(axis=0)
    if np.linalg.norm(out) < 0.5 or np.linalg.norm(n) < ONE_FACE:  # resultants of unit vectors: agreement
        return None
    axis = n / np.linalg.norm(n) + out / np.linalg.norm(out)
    return axis / np.linalg.norm(axis)


def edge_clusters(edges: OpenEdges, link_m: float, min_cells: int, voxel: float) -> list[np.ndarray]:
    """Open points in groups (linked within ``link_m`` when their unseen sides face the same way),
    each as its rows of ``edges``, largest
    first; a group spanning fewer than ``min_cells`` grid cells is left out, as the grid's frontier
    leaves its small clusters out (a stray point of noise at a border is not a place to look)."""
    if len(edges.xyz) == 0:
        return []
    pairs = cKDTree(edges.xyz).query_pairs(link_m, output_type="ndarray")
    same_way = np.einsum("ij,ij->i", edges.outward[pairs[:, 0]], edges.outward[pairs[:, 1]]) > 0
    pairs = pairs[same_way]  # a rod's two flanks, 14 mm apart, are two borders facing two ways
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(edges.xyz),) * 2)
    n, lab = connected_components(graph, directed=False)
    cells = np.floor(edges.xyz / voxel).astype(np.int64)
    groups = []
    for c in range(n):  # a handful of groups
        rows = np.flatnonzero(lab == c)
        if len(np.unique(cells[rows], axis=0)) >= min_cells:
            groups.append(rows)
    return sorted(groups, key=len, reverse=True)


@dataclass
class UnseenPaint:
    """A border where the paint the scan saw runs into surface it did not measure: the line may go on
    there, unseen (or the paint runs off a real edge: from the cloud alone the two look alike)."""

    centre: np.ndarray  # (3,) an open point of the border, nearest the group's centroid
    border_m: float  # the border's length (its open points' extent along it)
    wall_m: float  # the height of measured wall over it (``wall_heights``), 0 at a rim


def unseen_paint(drawing: np.ndarray, drawing_origin: np.ndarray, surface: np.ndarray, radius_m: float,
                 voxel_m: float, min_cells: int = 1) -> list[UnseenPaint]:
    """The borders where the paint runs on past what was measured (``open_paint_edges`` grouped as
    the edge views group them, ``edge_clusters``), longest first: what a scan left unresolved, so a
    share of "the paint seen" is a share of less than all the paint."""
    edges = open_paint_edges(drawing, drawing_origin, surface, radius_m)
    out = []
    for rows in edge_clusters(edges, 1.5 * voxel_m, min_cells, voxel_m):
        if len(rows) < MIN_NEIGHBOURS:
            continue
        P = edges.xyz[rows]
        c = P.mean(axis=0)
        _, _, vt = np.linalg.svd(P - c, full_matrices=False)
        along = (P - c) @ vt[0]
        out.append(UnseenPaint(P[np.argmin(np.linalg.norm(P - c, axis=1))], float(np.ptp(along)),
                               float(np.median(edges.wall[rows]))))
    return sorted(out, key=lambda u: -u.border_m)


def round_the_edge(eyes: np.ndarray, edges: OpenEdges, origins: np.ndarray) -> np.ndarray:
    """(C, M) radians: how much further round each open point's edge a camera at ``eyes`` (C,3)
    looks than the view that saw it (from ``origins`` (M,3)). In the plane of the point's normal
    n and outward tangent t a view from direction w reaches the surface turning away up to the
    same grazing limit past its own angle atan2(w.t, w.n); so it shows as much more as its angle
    exceeds the old view's, in the share of it that looks across the edge (not along it). 0 where
    it is no further round or sees the point from behind."""
    def angle(w):
        return np.arctan2(np.einsum("...j,...j->...", w, edges.outward), np.einsum("...j,...j->...", w, edges.normals))

    w = eyes[:, None, :] - edges.xyz[None, :, :]
    w /= np.maximum(np.linalg.norm(w, axis=2, keepdims=True), 1e-12)
    w0 = origins - edges.xyz
    ok0 = np.all(np.isfinite(w0), axis=1)
    w0 = np.where(ok0[:, None], w0, edges.normals)  # no origin kept: as if seen square-on
    more = angle(w) - angle(w0 / np.maximum(np.linalg.norm(w0, axis=1, keepdims=True), 1e-12))[None, :]
    wn, wt = np.einsum("cmj,mj->cm", w, edges.normals), np.einsum("cmj,mj->cm", w, edges.outward)
    across = np.hypot(wn, wt)  # a view along the edge (out of the n-t plane) sees its flank edge-on
    return np.where((wn > -np.sin(np.radians(10.0))) & (more > 0), across * np.minimum(more, np.pi / 2), 0.0)


class EdgeViews:
    """Views at the open paint, for when the grid's frontier has nothing left worth a view: one
    view per group of open points (then the group counts as looked at, whatever it showed), from
    the candidates round it that look furthest round the edges (``round_the_edge``) of the group's
    points they frame and see past the occupied cells."""

    def __init__(self, cfg: NBVConfig, surface_voxel: float = 0.002, joint: bool = False):
        self.cfg = cfg
        self.surface_voxel = surface_voxel
        self.joint = joint  # plan_joint, not one view per group
        self._lattice = sphere_lattice(cfg.search_radius_m, cfg.min_standoff_m, cfg.candidate_spacing_m)
        self.looked_at: list[tuple[np.ndarray, np.ndarray]] = []  # (centre, way out) of each group planned for
        self.edge_yield = EdgeYield(surface_voxel)  # joint plans: drawing found per point counted on

    def or_stop(self, state: ScanState, book, stop: ViewPlan, occupied: nbv.OccupiedIndex | None = None,
                failed=None) -> tuple[ViewPlan, tuple | None]:
        """The planner's grid frontier is done (its ``stop`` plan): a view of the open paint, booked
        on ``book`` (planners.targets.TargetBook) like any target, or ``stop`` itself. Returns the
        plan and, for a view, the planner's record of it (step, ranked eyes, the point each looks at).
        ``failed(eyes, centre)``: mask of positions the runner could not reach for that centre."""
        t0 = time.perf_counter()
        planned = (self.plan_joint(state, occupied, failed) if self.joint
                   else self.plan(state, occupied))
        stop.timings["edges_s"] = time.perf_counter() - t0
        if planned is None:
            return stop, None
        poses, q, gain, target = planned
        book.planned(state, target)
        last = (state.step, poses[:, :3, 3], np.broadcast_to(target, (len(poses), 3)))
        return ViewPlan(poses, q, gain, False, "", target=target, frontier=stop.frontier, timings=stop.timings), last

    def plan(self, state: ScanState, occupied: nbv.OccupiedIndex | None = None):
        """(poses, Q, gain, target) ranked best first, or None when no group is left to look at."""
        cfg, grid = self.cfg, state.grid
        if len(state.drawing) == 0:
            return None
        edges = open_paint_edges(state.drawing.xyz, state.drawing.origin, state.surface.xyz, cfg.open_edge_radius_m)
        groups = edge_clusters(edges, 1.5 * grid.voxel, cfg.min_frontier_cluster, grid.voxel)
        cents = [edges.xyz[g].mean(axis=0) for g in groups]
        ways = [edges.outward[g].mean(axis=0) for g in groups]
        todo = [i for i in range(len(groups)) if not self._looked_at(cents[i], ways[i], grid.voxel)]
        if not todo:
            return None
        occupied = occupied or nbv.OccupiedIndex(grid)
        cam = state.camera_pose[:3, 3]
        for i in todo:  # the largest group first: the view budget may end before the last
            c = cents[i]
            self.looked_at.append((c, ways[i]))
            eyes = c + self._lattice  # no viewing cone: which way round the edge is for the gain to say
            eyes = eyes[nbv.feasible_eyes(grid, eyes, c, None, cfg, None, occupied=occupied)]
            if len(eyes) == 0:
                continue
            R = look_at_rotations(eyes, c)
            if state.reachable is not None and cfg.reach_prefilter:
                keep = state.reachable(eyes, R[:, :, 2])
                eyes, R = eyes[keep], R[keep]
            if len(eyes) == 0:
                continue
            rows = groups[i]
            own = edges.rows(rows)
            gain = self._gain(state, eyes, R, own, state.drawing.origin[own.index].astype(np.float64), occupied)
            if gain.max() <= 0:
                continue
            cost = np.linalg.norm(eyes - cam, axis=1)
            q = nbv.quality(gain, cost, cfg.lam)
            rank = np.argsort(-q, kind="stable")
            return poses_from(eyes[rank], R[rank]), q[rank], gain[rank], c
        return None

    def _looked_at(self, centre: np.ndarray, way: np.ndarray, voxel: float) -> bool:
        """A group planned for before: near one, its unseen side facing the same way."""
        return any(np.linalg.norm(c - centre) <= 3 * voxel and float(w @ way) > 0 for c, w in self.looked_at)

    def _gain(self, state: ScanState, eyes: np.ndarray, R: np.ndarray, pts: OpenEdges, origins: np.ndarray,
              occupied: nbv.OccupiedIndex, counted: bool = False):
        """(C,) summed ``round_the_edge`` over the open points each candidate frames and sees; with
        ``counted`` also (C,) how many of them it sees at least ``EDGE_TURN`` further round, each
        counted as the cells of unseen face behind it: one for a rim's flank, a walled border's
        wall height in cells (the paint may run on up the whole wall)."""
        grid = state.grid
        more = round_the_edge(eyes, pts, origins)  # (C, M)
        z, framed = in_image(eyes, R, pts.xyz, state.K, state.image_size)
        framed &= z < self.cfg.max_range_m
        seen = raycast.clear_sight(eyes, pts.xyz, framed & (more > 0), 1.5 * grid.voxel, grid.lo, grid.voxel,
                                   grid.shape, occupied.flat)  # short of the point's own cell
        gain = np.where(seen, more, 0.0).sum(axis=1)
        if not counted:
            return gain
        return gain, (seen & (more >= EDGE_TURN)) @ np.maximum(1.0, pts.wall / grid.voxel)

    def plan_joint(self, state: ScanState, occupied: nbv.OccupiedIndex | None = None, failed=None):
        """All the open paint at once: candidates round its centre, looking at it at both rolls,
        each scored on every open point (``round_the_edge``), so one view that sees round many
        borders (a cage's rods seen from above past their flanks) beats one per border. Worth a
        view only when it sees as many points ``EDGE_TURN`` further round as line a border
        ``min_view_growth_voxels`` cells long (points ``self.surface_voxel`` apart); never from a
        direction already taken (``revisit_angle_deg``), nor from where ``failed(eyes, centre)`` says the
        runner could not reach. (poses, Q, gain, centre) or None."""
        cfg, grid = self.cfg, state.grid
        self.edge_yield.measure(state.step, state.camera_pose, grid)
        if len(state.drawing) == 0:
            return None
        edges = open_paint_edges(state.drawing.xyz, state.drawing.origin, state.surface.xyz, cfg.open_edge_radius_m)
        if len(edges.xyz) < MIN_NEIGHBOURS:
            return None
        if len(edges.xyz) > JOINT_POINTS:  # a fixed thinning: the score is a sum over borders
            keep = np.linspace(0, len(edges.xyz) - 1, JOINT_POINTS).astype(np.int64)
            edges = edges.rows(keep)
        occupied = occupied or nbv.OccupiedIndex(grid)
        c = edges.xyz.mean(axis=0)
        eyes = c + self._lattice
        eyes = eyes[nbv.feasible_eyes(grid, eyes, c, None, cfg, state.viewpoints, occupied=occupied)]
        if failed is not None and len(eyes):
            eyes = eyes[~failed(eyes, c)]
        if len(eyes) == 0:
            return None
        R = look_at_rotations(eyes, c)
        eyes, R = np.concatenate([eyes, eyes]), np.concatenate([R, quarter_turn(R)])
        if state.reachable is not None and cfg.reach_prefilter:
            keep = state.reachable(eyes, R[:, :, 2])
            eyes, R = eyes[keep], R[keep]
        if len(eyes) == 0:
            return None
        gain, count = self._gain(state, eyes, R, edges, state.drawing.origin[edges.index].astype(np.float64),
                                 occupied, counted=True)
        worth = self.edge_yield.expected(count, grid) >= cfg.min_view_growth_voxels
        if not worth.any():
            return None
        eyes, R, gain, count = eyes[worth], R[worth], gain[worth], count[worth]
        q = nbv.quality(gain, np.linalg.norm(eyes - state.camera_pose[:3, 3], axis=1), cfg.lam)
        rank = np.argsort(-q, kind="stable")
        poses = poses_from(eyes[rank], R[rank])
        self.edge_yield.planned(state.step, poses, count[rank], grid)
        return poses, q[rank], gain[rank], c
