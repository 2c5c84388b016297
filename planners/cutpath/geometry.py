"""Branch polyline -> smooth, evenly spaced points on the surface -> torch poses. The skeleton
is quantized to voxel centres; the torch must follow the paint on the metal, so the curve is
smoothed, then pushed back onto the measured surface."""

from __future__ import annotations

import numpy as np
from scipy.interpolate import splev, splprep
from scipy.spatial import cKDTree

from planners.cutpath import _checks

#: nearest surface points whose centroid a path point is snapped to (a local level, not a fit)
SNAP_NEIGHBOURS = 8
#: surface points in a normal's PCA at most (the nearest of those within the radius)
NORMAL_NEIGHBOURS = 64
_MIN_NORMAL_NEIGHBOURS = 6
_END_WEIGHT = 10.0
END_FIT_DEGREE = 3  # the polynomial through a stroke's end's paint: follows a line that bends or twists there
FACE_DEG = 20.0  # paint further out of a line's tangent plane is on another face (_same_face)
#: two sides of a corner that turn by less than this, or by more than 180 minus this, do not meet at
#: a well-defined point (the intersection of near-parallel lines moves by 1/sin of their angle)
MEET_DEG = 30.0  # keeps the spline's ends on the junction/end nodes that branches share


def arc_length(p: np.ndarray) -> np.ndarray:
    """Cumulative length along a polyline (K,), starting at 0."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def resample(p: np.ndarray, spacing: float) -> np.ndarray:
    """Evenly spaced points along a polyline, both ends kept; the step is the length divided
    into round(length / spacing) equal parts, so it is within half a step of `spacing`."""
    s = arc_length(p)
    if s[-1] <= 0:
        return p[:1].copy()
    n = max(int(round(s[-1] / spacing)), 1) + 1
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, p[:, k]) for k in range(3)])


def resample_holding(p: np.ndarray, spacing: float, held: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``resample`` that keeps the vertices ``held`` (indices, a corner the torch pivots at): each
    stretch between them evenly spaced on its own. Returns (points, the held vertices' new indices)."""
    held = np.unique(np.asarray(held, dtype=np.int64))
    held = held[(held > 0) & (held < len(p) - 1)]
    bounds = [0, *held.tolist(), len(p) - 1]
    parts = [resample(p[a:b + 1], spacing) for a, b in zip(bounds[:-1], bounds[1:])]
    at = np.cumsum([len(q) - 1 for q in parts])[:-1]
    return np.vstack([parts[0]] + [q[1:] for q in parts[1:]]), at.astype(np.int64)


def corners(p: np.ndarray, scale_m: float, min_turn_deg: float) -> np.ndarray:
    """Indices of the sharp corners of a polyline: points where the direction over ``scale_m``
    before and after turns by more than ``min_turn_deg`` (the scale sees through the skeleton's
    voxel staircase), the sharpest point of each such stretch."""
    if len(p) < 5:
        return np.zeros(0, dtype=np.int64)
    s = arc_length(p)
    back = np.clip(np.searchsorted(s, s - scale_m), 0, len(p) - 1)
    ahead = np.clip(np.searchsorted(s, s + scale_m), 0, len(p) - 1)
    d_in, d_out = p - p[back], p[ahead] - p
    n_in, n_out = np.linalg.norm(d_in, axis=1), np.linalg.norm(d_out, axis=1)
    ok = (n_in > 0.5 * scale_m) & (n_out > 0.5 * scale_m)
    cos = np.einsum("ij,ij->i", d_in, d_out) / np.maximum(n_in * n_out, 1e-12)
    turn = np.where(ok, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), 0.0)
    sharp = turn > min_turn_deg
    if not sharp.any():
        return np.zeros(0, dtype=np.int64)
    starts, stops = true_runs(sharp)
    return np.array([a + int(np.argmax(turn[a:b])) for a, b in zip(starts, stops)], dtype=np.int64)


def true_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, stops) of the runs of True in a bool array, each run ``mask[start:stop]``."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask).astype(np.int8), [0]]))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def smooth_resample(poly: np.ndarray, spacing_m: float, smoothing_m: float, closed: bool = False, *,
                    corner_scale_m: float = 0.0, corner_deg: float = 180.0,
                    paint: np.ndarray | None = None, held: list | None = None) -> np.ndarray:
    """The polyline split at its sharp corners (``corners``; none when ``corner_scale_m`` is 0), each
    piece smoothed and resampled on its own (``_smooth_piece``) with the corner points held: a
    smoothing spline would cut a painted corner, the torch pivots there instead. The corner points
    are appended to ``held`` when given (``on_surface`` keeps them as vertices)."""
    p = _checks.points(poly, "poly", 2)
    cut = corners(p, corner_scale_m, corner_deg) if corner_scale_m > 0 and not closed else np.zeros(0, np.int64)
    if len(cut) == 0:
        return _smooth_piece(p, spacing_m, smoothing_m, closed)
    p = p.copy()
    s = arc_length(p)
    at = np.concatenate([[-np.inf], s[cut], [np.inf]])
    half = band_half_width(p, paint, spacing_m) if paint is not None and len(paint) else 0.0
    for k, i in enumerate(cut):  # a few corners; each side fitted up to the next corner at most
        p[i] = _corner_point(p, int(i), corner_scale_m, paint, (at[k], at[k + 2]), half or corner_scale_m / 3)
    if held is not None:
        held.extend(p[cut])
    bounds = [0, *cut.tolist(), len(p) - 1]
    pieces = [_smooth_piece(p[a:b + 1], spacing_m, smoothing_m, False) for a, b in zip(bounds[:-1], bounds[1:])
              if b > a]
    return np.vstack([pieces[0]] + [q[1:] for q in pieces[1:]])


def _beside(p: np.ndarray, t: np.ndarray, paint: np.ndarray, spacing_m: float,
            reach_m: float, normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The paint beside each point: for the paint within ``reach_m`` in a slab one spacing thick
    across the line, (point index, offset across the line, its length), and the band's half width:
    the median over the points of how far the paint reaches (0 when none is beside the line). With
    the surface ``normals`` (K,3), paint on another face (``_same_face``) is not beside the line."""
    pairs = cKDTree(p).sparse_distance_matrix(cKDTree(paint), reach_m, output_type="coo_matrix")
    i, j = pairs.row, pairs.col
    v = paint[j] - p[i]
    along = np.einsum("kj,kj->k", v, t[i])
    slab = np.abs(along) <= 0.5 * spacing_m
    if normals is not None:
        slab &= _same_face(v, np.asarray(normals, dtype=np.float64)[i], spacing_m)
    i, v, along = i[slab], v[slab], along[slab]
    across = v - along[:, None] * t[i]
    r = np.linalg.norm(across, axis=1)
    reach = np.zeros(len(p))
    np.maximum.at(reach, i, r)
    return i, across, r, float(np.median(reach[reach > 0])) if (reach > 0).any() else 0.0


def _same_face(v: np.ndarray, n: np.ndarray, spacing_m: float) -> np.ndarray:
    """(M,) bool: offsets ``v`` from a point of the line with surface normal ``n`` lie on its face:
    within FACE_DEG of its tangent plane (half a spacing of noise allowed). A pipe curves far less
    within a band's width; the far face of a plate the line wraps over lies at 45 deg or more."""
    off = np.einsum("kj,kj->k", v, n)
    flat = np.linalg.norm(v - off[:, None] * n, axis=1)
    return np.abs(off) <= np.tan(np.radians(FACE_DEG)) * flat + 0.5 * spacing_m


def band_half_width(points: np.ndarray, paint: np.ndarray, spacing_m: float, closed: bool = False,
                    reach_m: float = 0.03, normals: np.ndarray | None = None) -> float:
    """Half the width of the sprayed band along a line (m): how far the paint reaches across it
    (on the line's own face when the surface ``normals`` (K,3) are given)."""
    p = _checks.points(points, "points", 1)
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2 or len(paint) == 0:
        return 0.0
    return _beside(p, tangents(p, closed), paint, spacing_m, reach_m, normals)[3]


def painted_over(loop: np.ndarray, paint: np.ndarray, spacing_m: float) -> bool:
    """A closed stroke no worker drew: a loop narrower than the band of paint around it would have
    its hole painted over. The skeleton makes such rings where paint wraps a thin bar (a basket's
    rod seen from several sides); that paint is a short cut across the bar (``pieces``), not a ring."""
    p = _checks.points(loop, "loop", 1)
    if len(p) < 3:
        return False
    span = float(np.max(np.linalg.norm(p[:, None] - p[None], axis=2)))  # a loop is a few dozen points
    return span < 2.0 * band_half_width(p, paint, spacing_m, closed=True)


#: center_on_paint(band_half_m=...): the largest move, in half widths of the band
SINGLE_BAND_MOVE = 0.25


def center_on_paint(points: np.ndarray, paint: np.ndarray, spacing_m: float, closed: bool = False,
                    reach_m: float = 0.03, max_turn_deg: float = 20.0, normals: np.ndarray | None = None,
                    band_half_m: float | None = None) -> np.ndarray:
    """Each point moved across the line to the middle of the paint beside it: the centroid of the
    paint in a slab one spacing thick across the line, within the band's half width (the median
    over the points of how far the paint reaches, at most ``reach_m``), the move across the line
    only. A sprayed band is symmetric about its centre line; the voxel skeleton and its smoothing
    are not (up to half a voxel off, more where thinning leans). Points where the line turns by
    more than ``max_turn_deg`` within the band stay: a corner's slab holds both of its sides. With
    the surface ``normals`` (K,3) the move stays in the surface, and paint off it by more than a
    third of the half width (the far face of a thin plate the line wraps over) is not counted. With
    the band's half width ``band_half_m`` known (a line from the outline, centred already up to the
    outline's own noise), points whose paint goes on beyond the band (another stretch of the line's
    paint merged with it: a sharp tip) stay too, as their centroid lies between the two stretches; and
    none moves further than ``SINGLE_BAND_MOVE`` of that half width (the median reach of paint merged
    along a zigzag is wider than the band: a cap of it let a point swerve 5 mm into the metal between
    two legs, scrap:0:43)."""
    p = _checks.points(points, "points", 1)
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3 or len(paint) < 10:
        return p
    t = tangents(p, closed)
    i, across, r, half = _beside(p, t, paint, spacing_m, reach_m, normals)
    if len(r) == 0:
        return p
    single_band = band_half_m is not None
    half *= 1.2  # the band's half width, with a little room
    inside = r <= half
    if normals is not None:  # across the line within the surface: along t x n
        n = np.asarray(normals, dtype=np.float64)[i]
        side = np.cross(t[i], n)
        norm = np.linalg.norm(side, axis=1)
        good = norm > 0.5  # a normal far from the travel direction
        side = side / np.maximum(norm, 1e-12)[:, None]
        off = np.einsum("kj,kj->k", across, n)
        inside &= ~good | (np.abs(off) <= half / 3.0)
        across = np.where(good[:, None], np.einsum("kj,kj->k", across, side)[:, None] * side, across)
    count = np.bincount(i[inside], minlength=len(p))
    shift = np.stack([np.bincount(i[inside], across[inside, k], minlength=len(p)) for k in range(3)], axis=1)
    shift = shift.astype(np.float64)  # bincount of no points, weights or not, is int64
    shift /= np.maximum(count, 1)[:, None]
    k = max(1, int(round(half / spacing_m)))
    a, b = np.clip(np.arange(len(p)) - k, 0, len(p) - 1), np.clip(np.arange(len(p)) + k, 0, len(p) - 1)
    straight = np.einsum("kj,kj->k", t[a], t[b]) >= np.cos(np.radians(max_turn_deg))
    move = straight & (count >= 5)
    if single_band:
        merged = np.bincount(i[(r > half) & (r <= 2.0 * half)], minlength=len(p))
        move &= merged < 3
        size = np.linalg.norm(shift, axis=1)
        shift *= np.minimum(1.0, SINGLE_BAND_MOVE * band_half_m / np.maximum(size, 1e-12))[:, None]
    out = p.copy()
    out[move] += shift[move]
    return out


def end_caps(points: np.ndarray, paint: np.ndarray, metal: cKDTree, half_m: float, spacing_m: float,
             start: bool = True, end: bool = True, normals: np.ndarray | None = None) -> np.ndarray:
    """A free end of a stroke placed at the centre of the paint's end cap. A sprayed stroke ends
    in a round cap half a band width beyond the line the worker drew: the medial axis of the band
    ends at the cap's centre, the voxel skeleton reaches into the cap or stops short of it, and
    within a band width of its end it leans towards a side of the cap (thinning eats the cap from
    its rim). So the line's last two band widths (4 ``half_m``) are rebuilt from their paint
    (``_end_from_paint``), to half a width back from where the paint stops; a short line, or one
    whose paint there is no single band, is trimmed or extended along its own end instead.
    Where the metal stops with the paint (the line runs off an edge: no surface in ``metal`` half a
    width beyond the paint) the end goes to the edge: the cut must leave the metal. The surface
    ``normals`` (K,3) at the points keep paint on another face out of the fit."""
    p = _checks.points(points, "points", 1)
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3 or len(paint) == 0 or not half_m > 0:
        return p
    n = None if normals is None else np.asarray(normals, dtype=np.float64)
    tree = cKDTree(paint)
    if start:
        p = _end_cap(p[::-1], paint, tree, metal, half_m, spacing_m, None if n is None else n[::-1])[::-1]
        if n is not None:  # the far end's points are as they were: their normals, counted from that end
            n = n[max(len(n) - len(p), 0):]
            n = np.vstack([np.repeat(n[:1], len(p) - len(n), axis=0), n])
    if end:
        p = _end_cap(p, paint, tree, metal, half_m, spacing_m, n)
    return p


def paint_stops(along: np.ndarray, start: float, gap_m: float, metal_at=None) -> float:
    """Where a stroke's paint stops along its line: the farthest of the paint's positions ``along``
    it reached from ``start`` without crossing bare metal longer than ``gap_m`` (-inf with no paint).
    The paint beyond such a break is another stroke's (the next dash of a dashed line): carried across,
    the cut runs over metal nobody marked. A break over air (between a grid's bars) is no break: the
    line goes on over the next bar. ``metal_at(positions)`` says where along the line there is metal
    (every break counts as bare metal without it)."""
    a = np.sort(np.asarray(along, dtype=np.float64).ravel())
    ahead = a[a > start]
    steps = np.concatenate([[start], ahead])
    big = np.flatnonzero(np.diff(steps) > gap_m)
    if metal_at is not None and len(big):  # metal in the middle of the break (beside a bar's edge is no sign)
        big = big[np.asarray(metal_at(0.5 * (steps[big] + steps[big + 1])), dtype=bool)]
    reached = ahead[:big[0]] if len(big) else ahead
    if len(reached):
        return float(reached[-1])
    behind = a[a <= start]
    return float(behind[-1]) if len(behind) else -np.inf


def _metal_along(metal: cKDTree, e: np.ndarray, t: np.ndarray, half: float):
    """``metal_at`` for ``paint_stops``: whether there is metal within half a half width of the points
    at the given positions along ``t`` from ``e``."""
    return lambda u: metal.query(e + u[:, None] * t, distance_upper_bound=0.5 * half)[0] < np.inf


def _rounded_end(along: np.ndarray, across: np.ndarray, tip: float, half: float) -> bool:
    """Whether the paint narrows into a round cap at its ``tip`` (positions ``along`` the line and
    ``across`` it): a sprayed stroke's end is a half disc, 0.76 of the band's half width at most in its
    last 0.35 half widths; paint cut off by the metal's edge keeps its width to the tip."""
    band = across <= 1.5 * half
    last = band & (along > tip - 0.35 * half) & (along <= tip)
    body = band & (along > tip - 2.0 * half) & (along <= tip - half)
    if last.sum() < 4 or body.sum() < 4:
        return False
    return float(np.percentile(across[last], 90)) < 0.85 * float(np.percentile(across[body], 90))


def _metal_goes_on(metal: cKDTree, e: np.ndarray, t: np.ndarray, tip: float, half: float, spacing: float,
                   normal: np.ndarray | None, rounded: bool = False) -> bool:
    """Whether the metal goes on half a width past where the paint stops (``tip`` along ``t`` from
    ``e``): then the paint ends in a sprayed cap, else at the metal's edge. Where the paint's end is
    ``rounded`` (``_rounded_end``) and the surface ``normal`` at the end is known, any metal ahead on
    the line's own face counts (``_same_face``: a pipe curves away from the straight probe, 7 mm below
    it on a 50 mm pipe, and was taken for an edge, the cut 8 mm past the line's end); paint cut square
    by a thin bar's edge is the edge still, whatever metal the probe finds beyond."""
    probe = e + (tip + half) * t
    if len(metal.query_ball_point(probe, 0.5 * half)) > 0:
        return True
    if normal is None or not rounded:
        return False
    near = metal.query_ball_point(probe, half)
    if not near:
        return False
    w = metal.data[near] - e
    ahead = w @ t > tip + 0.25 * half
    return bool(np.any(ahead & _same_face(w, np.broadcast_to(normal, w.shape), spacing)))


#: a line's normals turning more than this within half a band width: a fold of the metal (a pipe's
#: curve turns far less), beyond which the line's end is not fitted
END_FACE_DEG = 30.0
FLAT_DEG = 15.0  # a face's normals within a half width of each other


def _end_cap(p: np.ndarray, paint: np.ndarray, tree: cKDTree, metal: cKDTree, half: float,
             spacing: float, normals: np.ndarray | None) -> np.ndarray:
    s = arc_length(p)
    width = 2.0 * half
    face = 0  # the end's own face: the line's end is fitted on it, not over the fold before it
    if normals is not None:
        k = max(1, int(np.ceil(half / max(spacing, 1e-6))))  # a fold turns the normal within a half width
        if len(p) > 3 * k:  # between two faces, each flat for a half width (noise on a narrow bar is no fold)
            c = np.einsum("ij,ij->i", normals[:-k], normals[k:])
            flat = c[: len(c) - 2 * k] >= np.cos(np.radians(FLAT_DEG))
            fold = np.flatnonzero((c[k: len(c) - k] < np.cos(np.radians(END_FACE_DEG))) & flat
                                  & (c[2 * k:] >= np.cos(np.radians(FLAT_DEG)))) + k
            face = int(fold[-1]) + k if len(fold) else 0
    if s[-1] >= 3.0 * width and s[-1] - s[face] >= 2.0 * half:
        fitted = _end_from_paint(p, s, paint, tree, metal, half, spacing, normals, face)
        if fitted is not None:
            return fitted
    e = p[-1]  # short, or its paint is no single band there: from the skeleton's own end
    back = p[min(max(int(np.searchsorted(s, s[-1] - width)), face), len(p) - 2)]  # its direction over a band width
    t = e - back
    t /= max(np.linalg.norm(t), 1e-12)
    v = paint[tree.query_ball_point(e, 3.0 * half)] - e
    if len(v) == 0:
        return p
    along = v @ t
    across = np.linalg.norm(v - along[:, None] * t, axis=1)
    tip = paint_stops(along[across <= half], 0.0, 2.0 * spacing,  # where this stroke's paint stops, along the line
                      _metal_along(metal, e, t, half))
    if not np.isfinite(tip):
        return p
    on_metal = _metal_goes_on(metal, e, t, tip, half, spacing, None if normals is None else normals[-1],
                              _rounded_end(along, across, tip, half))
    goal = tip - half if on_metal else tip  # the cap's centre, or the edge the metal and the paint stop at
    if goal < 0.0:  # the skeleton reached into the cap: its last stretch beyond the centre trimmed off
        short = np.flatnonzero((p - e) @ t < goal)  # (a line that curves back further on stays whole)
        return np.vstack([p[: (short[-1] if len(short) else 0) + 1], e + goal * t])
    steps = np.arange(spacing, goal - 0.25 * spacing, spacing)  # it stopped short: extended along its direction
    return np.vstack([p, e + np.append(steps, goal)[:, None] * t]) if goal > 0.25 * spacing else p


def _end_from_paint(p: np.ndarray, s: np.ndarray, paint: np.ndarray, tree: cKDTree, metal: cKDTree, half: float,
                    spacing: float, normals: np.ndarray | None, first: int = 0) -> np.ndarray | None:
    """The stroke's last two band widths rebuilt from their paint: the band's centre line is the
    polynomial curve nearest to its paint (a band is symmetric about it; a cubic follows a line
    that bends or twists there; each point's parameter its foot on the curve, a first guess along
    the stretch's chord), from where the stretch starts to the cap's centre (or the metal's edge).
    None where the paint is no single band there (another stroke's paint joins it, a corner): the
    skeleton's own end then stands.
    With the surface ``normals`` only the paint on the line's own face (``_same_face``) counts."""
    j = max(int(np.searchsorted(s, s[-1] - 4.0 * half)), first)
    pairs = cKDTree(p[j:]).sparse_distance_matrix(tree, 1.5 * half, output_type="coo_matrix")
    keep = np.ones(len(pairs.col), dtype=bool)
    if normals is not None:
        keep = _same_face(paint[pairs.col] - p[j + pairs.row], normals[j + pairs.row], 0.5 * half)
    v = paint[np.unique(pairs.col[keep])]
    if len(v) < 20:
        return None
    t = p[-1] - p[j]
    t /= max(np.linalg.norm(t), 1e-12)
    u = (v - p[j]) @ t
    powers = np.arange(END_FIT_DEGREE, 0, -1)[:, None]

    def x(uu: np.ndarray) -> np.ndarray:
        return np.vander(uu, END_FIT_DEGREE + 1) @ coef

    for _ in range(3):  # fit, then each paint point's parameter moved to its foot on the curve, refit
        coef = np.polyfit(u, v, END_FIT_DEGREE)  # (degree + 1, 3), highest power first
        slope = coef[:-1] * powers  # dx/du, highest power first
        dx = np.vander(u, END_FIT_DEGREE) @ slope
        u = u + np.einsum("ij,ij->i", v - x(u), dx) / np.maximum(np.einsum("ij,ij->i", dx, dx), 1e-12)

    res = np.linalg.norm(v - x(u), axis=1)
    if np.percentile(res, 90) > 1.2 * half:  # wider than one band: not a single stroke's end
        return None
    on_band = res <= half
    band = v[on_band]
    goal = float(u[on_band].max())  # where the paint stops, along the chord: a first guess
    for _ in range(3):  # then along the line's own direction there (the chord leans where the line turns)
        d = (np.vander(np.array([goal]), END_FIT_DEGREE) @ slope)[0]
        speed = max(float(np.linalg.norm(d)), 1e-12)
        d = d / speed
        xe = x(np.array([goal]))[0]
        along = (band - xe) @ d
        ahead = paint_stops(along, 0.0, 2.0 * spacing, _metal_along(metal, xe, d, half))  # this stroke's paint beyond
        on_metal = _metal_goes_on(metal, xe, d, ahead, half, spacing, None if normals is None else normals[-1],
                                  _rounded_end(along, res[on_band], ahead, half))
        goal += (ahead - (half if on_metal else 0.0)) / speed  # the cap's centre, or the metal's edge
    if goal <= spacing:
        return None
    return np.vstack([p[:j], x(np.append(np.arange(0.0, goal - 0.25 * spacing, spacing), goal))])


def _corner_point(p: np.ndarray, i: int, scale_m: float, paint: np.ndarray | None = None,
                  within: tuple[float, float] = (-np.inf, np.inf), half_m: float | None = None) -> np.ndarray:
    """Where the two sides of a corner meet: thinning rounds a painted corner off (by up to a line
    width at an acute one), so the corner is put where straight fits of the two sides, from one
    scale to three scales away, come closest; kept as it is when they do not nearly meet. With the
    ``paint`` cloud, each side is fitted to the paint along it (a sprayed band is symmetric about
    its centre line), not to the voxel skeleton. The sides end at the neighbouring corners (arc
    lengths ``within``): a fit across one would rebuild this corner from the next side over. The
    paint fitted lies within the band's half width ``half_m`` of a side, and the corner moves at most
    as far as thinning can round it off: half_m / sin(half the corner's inside angle)."""
    half_m = scale_m / 3 if half_m is None else half_m
    s = arc_length(p)
    before = (s < s[i] - scale_m) & (s > max(s[i] - 3.0 * scale_m, within[0]))
    after = (s > s[i] + scale_m) & (s < min(s[i] + 3.0 * scale_m, within[1]))
    if before.sum() < 3 or after.sum() < 3 or min(np.ptp(s[before]), np.ptp(s[after])) < scale_m:
        return p[i]  # a side shorter than the scale (the next corner is near) gives no direction to trust
    lines = []
    for m in (before, after):
        c = p[m].mean(axis=0)
        d = np.linalg.svd(p[m] - c, full_matrices=False)[2][0]
        if paint is not None and len(paint):
            v = paint - c
            along = v @ d
            half = 0.5 * float(np.ptp(p[m] @ d))
            near = (np.abs(along) <= half) & (np.linalg.norm(v - along[:, None] * d, axis=1) <= 1.2 * half_m)
            if near.sum() >= 10:
                c_p = paint[near].mean(axis=0)
                d_p = np.linalg.svd(paint[near] - c_p, full_matrices=False)[2][0]
                if abs(d_p @ d) >= np.cos(np.radians(0.5 * MEET_DEG)):  # else paint from beyond the side
                    c, d = c_p, d_p                                       # (a hairpin's other leg) bent it
        lines.append((c, d))
    (c1, d1), (c2, d2) = lines
    d1 = d1 if d1 @ (p[i] - c1) >= 0 else -d1  # both along the travel
    d2 = d2 if d2 @ (c2 - p[i]) >= 0 else -d2
    if abs(float(np.linalg.norm(np.cross(d1, d2)))) < np.sin(np.radians(MEET_DEG)):
        return p[i]  # nearly parallel sides (a hairpin over a plate's rim, a slight bend): no point where they meet
    w = c1 - c2
    a, b, e = d1 @ d1, d1 @ d2, d2 @ d2
    den = a * e - b * b
    t1 = (b * (d2 @ w) - e * (d1 @ w)) / den
    t2 = (a * (d2 @ w) - b * (d1 @ w)) / den
    if t1 < 0 or t2 > 0:  # the sides would meet behind where they come from
        return p[i]
    q1, q2 = c1 + t1 * d1, c2 + t2 * d2
    q = 0.5 * (q1 + q2)
    inside = np.arccos(np.clip(-d1 @ d2, -1.0, 1.0))  # the corner's inside angle
    if np.linalg.norm(q1 - q2) > 0.25 * scale_m or np.linalg.norm(q - p[i]) > half_m / np.sin(0.5 * inside):
        return p[i]
    return q


def _smooth_piece(poly: np.ndarray, spacing_m: float, smoothing_m: float, closed: bool = False) -> np.ndarray:
    """B-spline through a branch polyline (RMS deviation about `smoothing_m`, ends held), then
    evenly spaced at `spacing_m` of arc length. A closed branch repeats its first point last."""
    p = _checks.points(poly, "poly", 2)
    spacing = _checks.positive(spacing_m, "spacing_m")
    smoothing = _checks.non_negative(smoothing_m, "smoothing_m")
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9  # splprep rejects repeated points
    p = p[keep]
    if closed and np.linalg.norm(p[-1] - p[0]) > 1e-9:
        p = np.vstack([p, p[:1]])
    m = len(p)
    if m < 2:
        return p.copy()
    k = min(3, m - 1 - (1 if closed else 0))
    if k < 1 or (closed and m < 4):
        return resample(p, spacing)
    w = np.ones(m)
    if not closed:
        w[[0, -1]] = _END_WEIGHT
    tck, _ = splprep(p.T, w=w, k=k, s=m * smoothing ** 2, per=int(closed), quiet=2)
    dense = np.array(splev(np.linspace(0.0, 1.0, max(20 * m, 200)), tck)).T
    if not closed:
        dense[0], dense[-1] = p[0], p[-1]
    return resample(dense, spacing)


class Surface:
    """The measured surface around the drawing, indexed once: PCA normals oriented toward the
    sensors that saw each patch, and snapping onto it."""

    def __init__(self, xyz: np.ndarray, origin: np.ndarray | None, viewpoint: np.ndarray | None,
                 radius_m: float, name: str = "surface") -> None:
        self.name = name
        self.xyz = _checks.points(xyz, f"{name}.xyz", 3)
        self.radius = _checks.positive(radius_m, "normal_radius_m")
        if origin is None:
            origin = np.full_like(self.xyz, np.nan)
        origin = np.asarray(origin, dtype=np.float64)
        if origin.shape != self.xyz.shape:
            raise ValueError(f"{name}.origin must have shape {self.xyz.shape}, got {origin.shape}")
        self.origin = origin
        if viewpoint is not None:
            viewpoint = np.asarray(viewpoint, dtype=np.float64)
            if viewpoint.shape != (3,) or not np.all(np.isfinite(viewpoint)):
                raise ValueError(f"viewpoint must be a finite (3,) point, got {viewpoint!r}")
        self.viewpoint = viewpoint
        seen = np.all(np.isfinite(origin), axis=1)
        self._mean_origin = origin[seen].mean(axis=0) if seen.any() else None
        if self._mean_origin is None and self.viewpoint is None:
            raise ValueError(f"{name}.origin has no finite sensor position and no viewpoint was given: "
                             "normals cannot be oriented")
        self.tree = cKDTree(self.xyz, balanced_tree=False, compact_nodes=False)  # built per cut: half the time

    def normals(self, at: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS) -> np.ndarray:
        """Outward unit normals (M,3) at points near the surface: the least-variance direction of
        the nearest surface points within the radius (all ``neighbours`` nearest where fewer
        than a handful lie inside), on the side of the sensors that saw them."""
        at = np.asarray(at, dtype=np.float64)
        k = min(neighbours, len(self.xyz))
        d, idx = self.tree.query(at, k=k, workers=-1)
        d, idx = d.reshape(len(at), k), idx.reshape(len(at), k)
        w = (d <= self.radius).astype(np.float64)
        sparse = w.sum(axis=1) < _MIN_NORMAL_NEIGHBOURS
        w[sparse] = 1.0
        P = self.xyz[idx]  # (M,k,3)
        W = w.sum(axis=1)
        c = np.einsum("mk,mkj->mj", w, P) / W[:, None]
        D = P - c[:, None, :]
        C = np.einsum("mk,mki,mkj->mij", w, D, D) / W[:, None, None]
        n = np.linalg.eigh(C)[1][:, :, 0]  # eigenvalues ascending: the smallest is the normal
        O = self.origin[idx] - P
        ok = np.isfinite(O).all(axis=2) & (w > 0)
        cnt = ok.sum(axis=1)
        toward = np.einsum("mk,mkj->mj", ok.astype(np.float64), np.where(ok[..., None], O, 0.0))
        toward = toward / np.maximum(cnt, 1)[:, None]
        if (cnt == 0).any():
            fallback = self.viewpoint if self.viewpoint is not None else self._mean_origin
            toward[cnt == 0] = fallback - at[cnt == 0]
        flip = np.einsum("mj,mj->m", n, toward) < 0
        n[flip] *= -1.0
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def snap(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Move each point along its normal to the level of the nearest surface points: smoothing
        cuts the corners of a bent plate, this puts the path back on the metal without moving it
        along the surface."""
        k = min(SNAP_NEIGHBOURS, len(self.xyz))
        idx = self.tree.query(p, k=k)[1].reshape(len(p), k)
        c = self.xyz[idx].mean(axis=1)
        return p - np.einsum("mj,mj->m", p - c, n)[:, None] * n


def on_surface(points: np.ndarray, surface: Surface, spacing_m: float,
               corners: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Snap evenly spaced points onto the surface and even them out again, thrice (snapping
    stretches the steps where it pushes a cut corner back out); the points nearest to ``corners``
    (M,3) stay vertices. Returns (points, outward normals)."""
    p = points
    held = np.zeros(0, dtype=np.int64)
    if corners is not None and len(corners) and len(p) > 2:
        held = cKDTree(p).query(np.asarray(corners, dtype=np.float64).reshape(-1, 3))[1]
    for _ in range(3):
        n = surface.normals(p)
        if len(p) > 1:
            p, held = resample_holding(surface.snap(p, n), spacing_m, held)
        else:
            p = surface.snap(p, n)
    n = surface.normals(p)
    return surface.snap(p, n), n


def pivots(points: np.ndarray, normals: np.ndarray, max_step_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses inserted where the normal turns by more than ``max_step_deg`` between two points (a
    sharp edge of the metal, a thin rod): the torch turns there in steps, its tip moving on along
    the chord, so the joints follow the pivot instead of swinging freely between two far-apart
    configurations. Returns (points, normals) with the inserted ones in order."""
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    if len(points) < 2:
        return points, n
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n[:-1], n[1:]), -1.0, 1.0)))
    steps = np.maximum(np.ceil(turn / max_step_deg).astype(int), 1)  # (K-1,) sub-steps per segment
    seg = np.repeat(np.arange(len(points) - 1), steps)
    f = (np.arange(len(seg)) - np.repeat(np.cumsum(steps) - steps, steps)) / steps[seg]  # 0, 1/m, ...
    p = points[seg] + f[:, None] * (points[seg + 1] - points[seg])
    th = np.radians(turn)[seg]  # slerp: equal turns per step
    sin_th = np.sin(th)
    slerp = sin_th > 1e-6
    w0 = np.where(slerp, np.sin((1 - f) * th) / np.where(slerp, sin_th, 1.0), 1 - f)
    w1 = np.where(slerp, np.sin(f * th) / np.where(slerp, sin_th, 1.0), f)
    v = w0[:, None] * n[seg] + w1[:, None] * n[seg + 1]
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    return np.vstack([p, points[-1:]]), np.vstack([v, n[-1:]])


def tangents(p: np.ndarray, closed: bool = False) -> np.ndarray:
    """Unit travel directions (K,3) by central differences (one-sided at open ends)."""
    if len(p) < 2:
        return np.tile([1.0, 0.0, 0.0], (len(p), 1))
    if closed:  # the last point repeats the first
        nxt = np.vstack([p[1:], p[1:2]])
        prv = np.vstack([p[-2:-1], p[:-1]])
        t = nxt - prv
    else:
        t = np.gradient(p, axis=0)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


def torch_poses(points: np.ndarray, normals: np.ndarray, standoff_m: float, closed: bool = False) -> np.ndarray:
    """Torch tip poses (K,4,4) in the base frame: z into the material (against the outward
    normal), tip `standoff_m` off the surface, x along the travel direction made orthogonal to z."""
    p = _checks.points(points, "points")
    n = _checks.points(normals, "normals")
    if len(n) != len(p):
        raise ValueError(f"normals must match points, got {len(n)} and {len(p)}")
    standoff = _checks.non_negative(standoff_m, "standoff_m")
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    z = -n
    x = tangents(p, closed)
    x = x - np.einsum("kj,kj->k", x, z)[:, None] * z
    bad = np.linalg.norm(x, axis=1) < 1e-6  # travel along the normal: any x will do
    if bad.any():
        helper = np.where(np.abs(z[bad, 0:1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        x[bad] = helper - np.einsum("kj,kj->k", helper, z[bad])[:, None] * z[bad]
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, z
    T[:, :3, 3] = p + standoff * n
    return T
