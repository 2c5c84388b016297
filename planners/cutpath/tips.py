"""A sharp turn of the line rebuilt from its legs. Within a band's width of a tip or a crossing the
paint is both stretches' at once (inside a sharp tip the legs' spray overlaps for half a width over the
tangent of half the tip angle: 52 mm for a 20-degree tip of a 18 mm band), so whatever follows the paint
there (the outline's line points linked into a curve, the skeleton, centring on the paint) takes a
chord across the tip or swerves into the metal between the legs: the flame 7 mm off scrap:0:43's line,
and 10 mm off a crossing's corner. Each leg further out is a single band the line follows well, and a
sprayed line holds its direction into a turn, so the legs are carried on straight to where they meet,
and the turn is put there (a corner rounded more tightly than the band is wide sprays the same paint as
a sharp one)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from planners.cutpath.geometry import _beside, arc_length, corners, resample, tangents

#: the legs are fitted between these many half widths of the turn, along the line, on either side
NEAR, FAR = 2.0, 6.0
#: a turn of less than this (degrees) is left as it is: a curve, not a tip
MIN_TURN_DEG = 45.0
#: paint across the line beyond this many half widths (and within MERGED_REACH of them) is another
#: stretch's: the band is wider than one spray there
MERGED_FROM, MERGED_REACH = 1.4, 3.0
#: legs whose surface normals part by more than this (degrees) lie on two faces: an edge, not a tip
EDGE_DEG = 30.0
#: the normal turning by more than this (degrees) between two points of the line one spacing apart is a
#: crease of the metal (a fold, a flange's edge) the legs' fit would reach over; a pipe or an elbow
#: curves by a few degrees a spacing, and its legs are laid in the tangent plane
CREASE_DEG = 15.0
#: the sharpest tip looked for (degrees): its legs' paint merges for a half width over tan of half of it
#: (7.6 half widths at 15), the furthest a tip can lie beyond what followed the paint
SHARPEST_TIP_DEG = 15.0


def _merged(p: np.ndarray, paint: np.ndarray, spacing_m: float, half_m: float, normals: np.ndarray) -> bool:
    """Whether any of the line points ``p`` has paint across the line, on its face, beyond
    ``MERGED_FROM`` half widths (within ``MERGED_REACH``): another stretch's spray. A curve wider than
    the band has none; a tip's legs and a crossing's arms do."""
    if len(p) < 2:
        return False
    i, _, r, _ = _beside(p, tangents(p), paint, spacing_m, MERGED_REACH * half_m, normals)
    return bool((np.bincount(i[(r > MERGED_FROM * half_m) & (r <= MERGED_REACH * half_m)], minlength=len(p)) >= 3).any())


def _leg(p: np.ndarray, s: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(the fitted leg's point level with its end nearest the turn, its unit direction toward the turn)
    from the points with arc length between ``lo`` (the end nearest the turn) and ``hi``; lo > hi is
    the leg after the turn, its direction taken backward."""
    a, b = min(lo, hi), max(lo, hi)
    q = p[(s >= a) & (s <= b)]
    if len(q) < 3 or np.linalg.norm(q[-1] - q[0]) < 0.5 * (b - a):
        return None
    c = q.mean(axis=0)
    d = np.linalg.svd(q - c, full_matrices=False)[2][0]
    near = q[-1] if lo > hi else q[0]
    far = q[0] if lo > hi else q[-1]
    if d @ (near - far) < 0:
        d = -d
    return c + ((near - c) @ d) * d, d


def _meet(a: np.ndarray, da: np.ndarray, b: np.ndarray, db: np.ndarray) -> tuple[float, float] | None:
    """(s, u): the closest points a + s da and b + u db of two lines (unit directions); None when
    parallel."""
    w = a - b
    B = da @ db
    den = 1.0 - B * B
    if den < 1e-9:
        return None
    s = (B * (db @ w) - (da @ w)) / den
    u = ((db @ w) - B * (da @ w)) / den
    return s, u


def _in_cap(c: np.ndarray, toward: np.ndarray, n: np.ndarray, paint: np.ndarray, tree: cKDTree,
            half_m: float) -> np.ndarray:
    """The tip moved back along the bisector ``toward`` it (in the surface, normal ``n``) to a half
    width inside the paint's end there, where it lies further out: the spray rounds a tip's outside
    with the band's half width about it. Two legs 20 degrees apart meet 6 mm further on for each
    millimetre one of them is fitted off, and overshot into bare metal (scrap:0:43); the cap does not
    depend on them. Never forward: past a crossing's centre the paint goes on for more than a half
    width (between its other arms), and a tip short of its end is still on the line."""
    b = toward / np.linalg.norm(toward)
    v = paint[tree.query_ball_point(c, 3.0 * half_m)] - c
    v = v - np.outer(v @ n, n)
    along = v @ b
    along = along[np.linalg.norm(v - along[:, None] * b, axis=1) < 0.5 * half_m]
    if len(along) < 3:
        return c
    end = float(along.max())
    return c + min(end - half_m, 0.0) * b


def rebuilt_tips(points: np.ndarray, paint: np.ndarray, spacing_m: float, half_m: float,
                 normals: np.ndarray, closed: bool = False) -> tuple[np.ndarray, list[np.ndarray]]:
    """(points, the tips made): each turn of an open stroke by ``MIN_TURN_DEG`` or more (measured
    over ``FAR`` half widths) where another stretch's paint lies beside the line (``_merged``: a
    tip's legs, a crossing's arms; a curve wider than the band has none) and the legs lie on one face
    (their surface ``normals`` (K,3) part by less than ``EDGE_DEG``, and turn by less than
    ``CREASE_DEG`` from one point to the next along all the fit looks at: over an edge of the metal
    the line bends in space, not on the metal; a pipe's curve is no edge), replaced within ``NEAR``
    half widths of it by its two legs carried on straight to where they meet. The legs are fitted between ``NEAR`` and ``FAR`` half
    widths out, or, where the tip they make is so sharp that their paint merges further out than
    that, as far beyond the merge; and laid in the surface's tangent plane at the turn (a pipe curves
    away from straight legs). They must meet ahead of both, no further on than a
    ``SHARPEST_TIP_DEG`` tip's merge is long, at a point of the paint; the tip is then kept a half
    width inside the paint's end cap (``_in_cap``). The rest of the stroke is kept."""
    p = np.asarray(points, dtype=np.float64)
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    if closed or len(p) < 8 or len(paint) < 10 or half_m <= 0:
        return p, []
    s = arc_length(p)
    near, far = NEAR * half_m, FAR * half_m
    reach = half_m / np.tan(np.radians(SHARPEST_TIP_DEG / 2.0))
    tree = cKDTree(paint)
    out, tips, at = [], [], 0
    n = np.asarray(normals, dtype=np.float64)
    for k in corners(p, far, MIN_TURN_DEG):  # a few turns per stroke
        before = _leg(p, s, s[k] - near, s[k] - far)
        after = _leg(p, s, s[k] + near, s[k] + far)
        turn = (s >= s[k] - near) & (s <= s[k] + near)
        if before is None or after is None or not _merged(p[turn], paint, spacing_m, half_m, n[turn]):
            continue
        (pa, da), (pb, db) = before, after
        start = near
        tip_deg = 180.0 - np.degrees(np.arccos(np.clip(da @ -db, -1.0, 1.0)))
        merge = half_m / np.tan(np.radians(max(tip_deg, SHARPEST_TIP_DEG) / 2.0))
        if merge > near:  # the legs' paint merges further out than the first fit: fitted beyond the merge
            before = _leg(p, s, s[k] - merge, s[k] - merge - (far - near))
            after = _leg(p, s, s[k] + merge, s[k] + merge + (far - near))
            if before is not None and after is not None:
                (pa, da), (pb, db), start = before, after, merge
        span = np.flatnonzero((s >= s[k] - start - (far - near)) & (s <= s[k] + start + (far - near)))  # all the fit saw
        na, nb = n[np.argmin(np.abs(s - (s[k] - near)))], n[np.argmin(np.abs(s - (s[k] + near)))]
        step = np.einsum("ij,ij->i", n[span[:-1]], n[span[1:]])
        if na @ nb < np.cos(np.radians(EDGE_DEG)) or (len(step) and step.min() < np.cos(np.radians(CREASE_DEG))):
            continue
        # the turn within the surface: legs and meeting point in the tangent plane at the turn
        nk = (na + nb) / np.linalg.norm(na + nb)
        flat = np.eye(3) - np.outer(nk, nk)
        pa, pb = p[k] + flat @ (pa - p[k]), p[k] + flat @ (pb - p[k])
        da, db = flat @ da, flat @ db
        if min(np.linalg.norm(da), np.linalg.norm(db)) < 0.5:
            continue
        da, db = da / np.linalg.norm(da), db / np.linalg.norm(db)
        met = _meet(pa, da, pb, db)
        if met is None:
            continue
        u, v = met
        c = _in_cap(0.5 * (pa + u * da + pb + v * db), da + db, nk, paint, tree, half_m)
        near_paint = paint[tree.query(c, k=min(8, len(paint)))[1]]
        c = c + ((near_paint.mean(axis=0) - c) @ nk) * nk  # back onto the painted surface's level
        if not (0 < u < start + reach and 0 < v < start + reach and tree.query(c)[0] < 0.5 * half_m):
            continue
        i, j = int(np.searchsorted(s, s[k] - near)), int(np.searchsorted(s, s[k] + near, side="right"))
        if i < at:  # overlaps the turn before it
            continue
        out += [p[at:i], resample(np.vstack([p[i - 1] if i > 0 else pa, c]), spacing_m)[1:-1], c[None],
                resample(np.vstack([c, p[j] if j < len(p) else pb]), spacing_m)[1:-1]]
        tips.append(c)
        at = j
    if not tips:
        return p, []
    out.append(p[at:])
    return np.vstack([q.reshape(-1, 3) for q in out if len(q)]), tips
