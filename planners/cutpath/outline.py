"""The line as the worker drew it, from the paint's outline.

A sprayed stroke is its line widened by half the spray width on every side, so the paint's outline
is the line offset outward by that half width, and the outline offset back inward by it is the line
itself. The paint's skeleton (its medial axis) is the line only where the band is a single band:
where two stretches of the line come closer than a spray width (a zigzag's sharp tip, a hairpin)
their paint merges into one blob, whose medial axis cuts a chord through metal nobody marked. The
outline still knows both stretches: each side of the blob is half a width from one of them.

So: the outline points (paint points with an empty sector of neighbours in the surface's tangent
plane, ``BOUNDARY_GAP_DEG`` or more: the standard test of point-cloud boundary estimation), each
moved inward, along the sector's bisector, by the band's half width (measured between opposite sides
of the outline); the paint within ``CORE_M`` of those points is the line's core, a narrow band on the
line whose skeleton follows the line into sharp tips. Where the outline cannot be read (too few
points, no opposite sides) the paint itself is the core, as before."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: a paint point whose neighbours in the tangent plane leave an empty sector this wide is on the outline
BOUNDARY_GAP_DEG = 100.0
#: neighbours looked at per paint point (the 2 mm cloud: a disc of about 5 mm)
NEIGHBOURS = 24
#: the line's core: paint within this of the outline moved inward (the skeleton's 5 mm voxel needs ~2 cells)
CORE_M = 0.004
#: bare metal this many surface cells beyond an outline point: the spray drew it there
BEYOND_CELLS = 2.0
#: opposite sides of the outline: their inward directions at least this far apart (cosine)
OPPOSITE_COS = -0.7
#: a walk inward over the paint that turns more than this in one step, or in all, has gone round a rim
WALK_STEP_DEG = 60.0
WALK_TURN_DEG = 120.0


@dataclass
class Outline:
    points: np.ndarray  # (B,3) paint points on the outline
    inward: np.ndarray  # (B,3) unit, in the tangent plane, into the paint
    half_width_m: float  # half the band's width, between opposite sides (0: not measured)
    line: np.ndarray  # (B,3) the outline moved inward by the half width over the paint: points on the line


def _tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(normals, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(normals, e1)


def outline(paint: np.ndarray, normals: np.ndarray, half_width_m: float | None = None,
            metal: cKDTree | None = None) -> Outline:
    """The paint's outline, its inward directions, the band's half width (measured unless given) and
    the outline moved inward by it. With the surface's k-d tree ``metal``, only the outline the spray
    drew counts: where bare metal lies just beyond it (``BEYOND_CELLS`` of the cloud's spacing out). Where the paint
    stops because the metal does (a bar's side, a plate's edge) or the scan does, the outline is not
    the line moved aside and is left out; and so is a gap in a sparse cloud (paint beyond it)."""
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    k = min(NEIGHBOURS, len(paint) - 1)
    empty = Outline(np.zeros((0, 3)), np.zeros((0, 3)), 0.0, np.zeros((0, 3)))
    if k < 6:
        return empty
    paint_tree = cKDTree(paint)
    dist, idx = paint_tree.query(paint, k=k + 1)
    cell_m = float(np.median(dist[:, -1])) * np.sqrt(np.pi / k)  # the cloud's spacing: k points per disc
    v = paint[idx[:, 1:]] - paint[:, None]
    e1, e2 = _tangent_frames(n)
    ang = np.sort(np.arctan2(np.einsum("nkj,nj->nk", v, e2), np.einsum("nkj,nj->nk", v, e1)), axis=1)
    gaps = np.diff(np.concatenate([ang, ang[:, :1] + 2 * np.pi], axis=1), axis=1)
    g = np.argmax(gaps, axis=1)
    rows = np.arange(len(paint))
    widest = gaps[rows, g]
    mid = ang[rows, g] + 0.5 * widest  # the empty sector's bisector: outward
    on = widest >= np.radians(BOUNDARY_GAP_DEG)
    if on.sum() < 6:
        return empty
    out = np.cos(mid[on])[:, None] * e1[on] + np.sin(mid[on])[:, None] * e2[on]
    pts, inward, pn = paint[on], -out, n[on]
    if metal is not None:
        beyond = pts - BEYOND_CELLS * cell_m * inward
        drawn = (np.isfinite(metal.query(beyond, distance_upper_bound=1.5 * cell_m)[0])  # metal there,
                 & ~np.isfinite(paint_tree.query(beyond, distance_upper_bound=0.75 * cell_m)[0]))  # bare
        pts, inward, pn = pts[drawn], inward[drawn], pn[drawn]
        if len(pts) < 6:
            return empty
    half = _half_width(pts, inward) if half_width_m is None else float(half_width_m)
    line = walk_on_paint(pts, inward, pn, half, paint, n, paint_tree, cell_m) if half > 0 else np.zeros((0, 3))
    return Outline(pts, inward, half, line)


def _turned(v: np.ndarray, n_from: np.ndarray, n_to: np.ndarray) -> np.ndarray:
    """Vectors (M,3) turned as the unit normals turn from ``n_from`` to ``n_to`` (about their cross
    product, Rodrigues): a direction on one face carried over a fold onto the next."""
    k = np.cross(n_from, n_to)
    s2 = np.einsum("ij,ij->i", k, k)
    c = np.einsum("ij,ij->i", n_from, n_to)
    f = np.where(s2 > 1e-12, (1.0 - c) / np.maximum(s2, 1e-12), 0.5)
    return v * c[:, None] + np.cross(k, v) + k * (np.einsum("ij,ij->i", k, v) * f)[:, None]


def walk_on_paint(pts: np.ndarray, inward: np.ndarray, pts_normals: np.ndarray, dist_m: float, paint: np.ndarray,
                  normals: np.ndarray, tree: cKDTree, cell_m: float) -> np.ndarray:
    """(B,3) the points ``dist_m`` from ``pts`` along ``inward`` over the painted surface, not in a
    straight line: in steps of about a cloud cell, each laid back onto the plane of the nearest paint
    point and its direction turned with the surface. A band that crosses a fold or a pipe's bend
    obliquely has its line beyond the bend; a straight move would leave the metal there and land
    beside the line (7 mm on an angle's ridge crossed at 25 deg). A walk that leaves the paint, turns
    past ``WALK_STEP_DEG`` in one step or ``WALK_TURN_DEG`` in all (round a plate's rim onto its far
    face, where the line wraps the rim and the straight move lands nearer it) gives the straight move,
    and so does one that lands within half a cell of it (a flat face, a pipe's gentle curve)."""
    x, d, m = pts.copy(), inward.copy(), pts_normals.copy()
    steps = max(1, int(np.ceil(dist_m / max(cell_m, 1e-4))))
    ok = np.ones(len(x), dtype=bool)
    for _ in range(steps):  # a few steps, every point at once
        x = x + (dist_m / steps) * d
        gap, j = tree.query(x)
        n_new = normals[j]
        ok &= (gap <= 2.0 * cell_m + dist_m / steps) & (np.einsum("ij,ij->i", n_new, m) >= np.cos(np.radians(WALK_STEP_DEG)))
        x = x - np.einsum("ij,ij->i", x - paint[j], n_new)[:, None] * n_new
        d = _turned(d, m, n_new)
        d = d - np.einsum("ij,ij->i", d, n_new)[:, None] * n_new
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        m = n_new
    ok &= np.einsum("ij,ij->i", m, pts_normals) >= np.cos(np.radians(WALK_TURN_DEG))
    straight = pts + dist_m * inward
    ok &= np.linalg.norm(x - straight, axis=1) > 0.5 * cell_m  # on a flat or gently curved face they agree
    return np.where(ok[:, None], x, straight)


def _half_width(pts: np.ndarray, inward: np.ndarray, reach_m: float = 0.05) -> float:
    """Half the band's width: the median over outline points of half the distance, along their inward
    direction, to the nearest outline point on the opposite side in front of them (0 if none)."""
    tree = cKDTree(pts)
    pairs = tree.sparse_distance_matrix(tree, reach_m, output_type="coo_matrix")
    i, j = pairs.row, pairs.col
    v = pts[j] - pts[i]
    ahead = np.einsum("kj,kj->k", v, inward[i])
    across = np.linalg.norm(v - ahead[:, None] * inward[i], axis=1)
    ok = (np.einsum("kj,kj->k", inward[j], inward[i]) <= OPPOSITE_COS) & (ahead > 0) & (across <= 0.5 * ahead)
    width = np.full(len(pts), np.inf)
    np.minimum.at(width, i[ok], ahead[ok])
    width = width[np.isfinite(width)]
    return 0.5 * float(np.median(width)) if len(width) >= 6 else 0.0


def line_core(paint: np.ndarray, normals: np.ndarray, metal: cKDTree | None = None,
              core_m: float = CORE_M) -> tuple[np.ndarray, Outline]:
    """(the paint within ``core_m`` of the line the outline gives, the outline; ``metal`` as for
    ``outline``). The paint itself where the outline gives no line or its core would lose most of
    the paint's length."""
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    o = outline(paint, normals, metal=metal)
    if len(o.line) == 0:
        return paint, o
    near = np.isfinite(cKDTree(o.line).query(paint, distance_upper_bound=core_m)[0])
    core = paint[near]
    # a core much thinner than expected (a blob, no band) is no line: keep the paint
    expected = (2 * core_m) / max(2 * o.half_width_m, 2 * core_m)
    if len(core) < 0.3 * expected * len(paint):
        return paint, o
    return core, o
