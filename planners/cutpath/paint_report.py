"""The cut measured against what the cell saw, never against its own skeleton alone.

The skeleton's length is the planner's own belief: where it cuts a chord across a sharp tip it still
says "100 %". The paint (the drawing cloud) and the flame's path are independent of it: the flame
spot (where the torch axis meets the metal, ``standoff`` ahead of the tip) is computed at every
sample of the planned joint motion with the flame lit, so a flip of the arm between two poses shows,
and the paint is cut where it lies within half a spray width (plus the line tolerance) of that path.
What paint is left is grouped into pieces, each with where it is and why it is not cut.

The share told to the operator (``line_share``) is the line the paint gives, counted only where it
lies on the paint's band centre, within the tolerance of that flame path, as the truth is judged; the
paint no line follows counts uncut. The painted area under the flame (``cut_share``) is the second,
independent check: it over-counts where a face was measured sparsely (seen obliquely, its uncut paint
looks small), so the two are compared and a disagreement is reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

#: uncut paint smaller than this many square half-widths is a speck at the band's edge (sensor noise)
SPECK_HALF_WIDTHS_SQ = 2.0
#: a cut over at least this share of the paint measures the paint's area per metre of line itself (the
#: cloud's density depends on the sensor's noise); below it the area is divided by the spray width
MEASURED_SHARE = 0.2
#: the reason of uncut paint no gap of the plan explains: the cut's own line does not go there
NOT_IN_CUT = "not followed"
#: paint points at least this many in the slab across a flame spot for the band's two edges to count
CENTRE_MIN_POINTS = 4
#: a slab wider than this many spray widths crosses more than one band (a junction, a sharp tip's other
#: leg, a crossing): the band's centre is not measured there
CENTRE_MAX_WIDTHS = 1.5


@dataclass
class FlamePath:
    """The torch along one planned (or executed) motion: tips, axes and flame spots, (N,3) each."""

    tips: np.ndarray
    axes: np.ndarray
    spots: np.ndarray


def flame_path(kin, Q: np.ndarray, standoff_m: float) -> FlamePath:
    """FK of every joint sample (N,dof) of a motion with the torch as the tool frame: the flame spot
    is ``standoff_m`` ahead of the tip along its axis (the torch's z, into the metal)."""
    Q = np.asarray(Q, dtype=np.float64)
    if Q.ndim != 2 or len(Q) == 0:
        z = np.zeros((0, 3))
        return FlamePath(z, z.copy(), z.copy())
    T = kin.fk_batch(Q)
    tips, axes = T[:, :3, 3].copy(), T[:, :3, 2].copy()
    return FlamePath(tips, axes, tips + standoff_m * axes)


@dataclass
class UncutPaint:
    """A connected piece of paint no cut passes over."""

    centre: np.ndarray  # (3,) its paint point nearest its mean, base frame
    length_m: float  # its area over the spray width: the line's length it holds
    reason: str  # a gap's reason when one of the plan's gaps lies in it, else NOT_IN_CUT
    detail: str = ""

    def to_json_dict(self) -> dict:
        return {"centre": [round(float(v), 4) for v in self.centre], "length_m": round(self.length_m, 4),
                "reason": self.reason, "detail": self.detail}


@dataclass
class PaintReport:
    """The cut against the paint. ``cut_share`` is the share of the painted area within
    ``half_width + tolerance`` of a runnable cut's flame path."""

    half_width_m: float
    paint_area_m2: float
    line_length_m: float  # the flame's travel on the paint over the share it cuts (the painted area over the
    # spray width where little is cut)
    cut_share: float
    uncut: list[UncutPaint] = field(default_factory=list)
    line_share: float | None = None  # the measured line on the band's centre within tolerance of a centred flame
    line_on_paint_m: float = 0.0  # that line's length, plus the paint no line follows
    flame_off_paint_max_mm: float | None = None  # flame spot to the nearest paint, over every lit sample
    flame_off_paint_m: float = 0.0  # flame travel farther than the tolerance from any paint
    flame_off_centre_max_mm: float | None = None  # flame spot to the paint band's centre across its travel
    flame_off_centre_m: float = 0.0  # flame travel farther than the tolerance from the band's centre
    tip_to_surface_min_mm: float | None = None  # the tip's clearance from the measured surface, lit samples
    tip_to_surface_max_mm: float | None = None
    samples: int = 0


def paint_area(paint_normals: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) area each point of a voxel-deduplicated cloud stands for: a plane with unit normal n
    crosses ``|n|_1 / voxel**2`` cells per unit area (1 when it is axis aligned, up to sqrt 3)."""
    n = np.asarray(paint_normals, dtype=np.float64)
    return voxel_m**2 / np.maximum(np.abs(n).sum(axis=1), 1.0)


def _pieces(xyz: np.ndarray, link_m: float) -> tuple[int, np.ndarray]:
    pairs = cKDTree(xyz).query_pairs(link_m, output_type="ndarray")
    from scipy.sparse import coo_matrix

    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(xyz), len(xyz)))
    return connected_components(g, directed=False)


def off_centre(paint: np.ndarray, paint_normals: np.ndarray, spots: np.ndarray, half_width_m: float,
               slab_m: float, tree: cKDTree | None = None) -> np.ndarray:
    """(S,) m: how far each flame spot of one path lies from the centre of the paint band across its
    travel, NaN where the band's two edges are not both measured there. The paint within two half
    widths of the spot, in a slab ``slab_m`` thick along the travel and on the spot's face: its
    extent across, from one edge of the band to the other; the centre is halfway. A flame inside the
    band but beside its centre is near paint everywhere, so only this tells it leaves the line."""
    spots = np.asarray(spots, dtype=np.float64).reshape(-1, 3)
    if len(spots) < 2 or len(paint) == 0:
        return np.full(len(spots), np.nan)
    # measured once per slab of travel (a motion's samples lie far closer, and a pivot stays on one spot)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(spots, axis=0), axis=1))])
    _, first, per_sample = np.unique(np.floor(arc / slab_m).astype(np.int64), return_index=True, return_inverse=True)
    if len(first) < 2:
        return np.full(len(spots), np.nan)
    return _off_centre_at(paint, paint_normals, spots[first], half_width_m, slab_m, tree or cKDTree(paint))[per_sample.ravel()]


def _off_centre_at(paint: np.ndarray, paint_normals: np.ndarray, spots: np.ndarray, half_width_m: float,
                   slab_m: float, tree: cKDTree) -> np.ndarray:
    """``off_centre`` at spots ``slab_m`` or more apart along their travel."""
    off = np.full(len(spots), np.nan)
    t = np.gradient(spots, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    n = np.asarray(paint_normals, dtype=np.float64)[tree.query(spots)[1]]
    a = np.cross(t, n)
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    reach = 2.0 * half_width_m + 3.0 * slab_m
    pairs = cKDTree(spots).sparse_distance_matrix(tree, reach, output_type="coo_matrix")
    i, j = pairs.row, pairs.col
    v = paint[j] - spots[i]
    keep = (np.abs(np.einsum("kj,kj->k", v, t[i])) <= slab_m) & (np.abs(np.einsum("kj,kj->k", v, n[i])) <= slab_m)
    i, x = i[keep], np.einsum("kj,kj->k", v[keep], a[i[keep]])
    lo, hi = np.full(len(spots), np.inf), np.full(len(spots), -np.inf)
    np.minimum.at(lo, i, x)
    np.maximum.at(hi, i, x)
    count = np.bincount(i, minlength=len(spots))
    inner = reach - 2.0 * slab_m  # an edge found at the search's rim may lie beyond it
    ok = ((count >= CENTRE_MIN_POINTS) & (hi - lo <= CENTRE_MAX_WIDTHS * 2.0 * half_width_m)
          & (lo > -inner) & (hi < inner))
    off[ok] = np.abs(0.5 * (lo[ok] + hi[ok]))
    return off


def beside_centre(f: FlamePath, c: np.ndarray, tolerance_m: float, min_run_m: float) -> np.ndarray:
    """(S,) bool: the samples of a flame path beside the band's centre (``off_centre`` above
    ``tolerance_m``) in runs at least ``min_run_m`` of travel long; a shorter blip (a sharp tip's
    apex, where the band rounds off, or noise at its edge) is no stretch of cut off the line."""
    off = c > tolerance_m
    if not off.any():
        return off
    step = np.concatenate([[0.0], np.linalg.norm(np.diff(f.spots, axis=0), axis=1)])
    cuts = np.flatnonzero(np.diff(off.astype(np.int8))) + 1
    for rows in np.split(np.arange(len(off)), cuts):
        if off[rows[0]] and step[rows[1:]].sum() < min_run_m:
            off[rows] = False
    return off


def _centred(flames: list[FlamePath], beside: list[np.ndarray]) -> list[FlamePath]:
    """The stretches of each flame path not ``beside`` the band's centre, as paths of their own."""
    out = []
    for f, b in zip(flames, beside):
        cuts = np.flatnonzero(np.diff(b.astype(np.int8))) + 1
        for rows in np.split(np.arange(len(b)), cuts):
            if len(rows) and not b[rows[0]]:
                out.append(FlamePath(f.tips[rows], f.axes[rows], f.spots[rows]))
    return out


def _under(paint: np.ndarray, flames: list[FlamePath], half_width_m: float, tolerance_m: float,
           step_m: float) -> np.ndarray:
    """(N,) bool: paint beside a flame path, across its travel within half the spray width plus the
    tolerance, and along it within the tolerance of where the flame passed: paint past a cut's end is
    cut only as far as the tolerance reaches, as the line is (not half a spray width further)."""
    from planners.metrics import dense_polylines

    covered = np.zeros(len(paint), dtype=bool)
    tree = cKDTree(paint)
    for f in flames:  # a few cuts
        s = dense_polylines([f.spots], step_m) if len(f.spots) > 1 else f.spots
        t = np.gradient(s, axis=0) if len(s) > 1 else np.zeros_like(s)
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        pairs = cKDTree(s).sparse_distance_matrix(tree, half_width_m + tolerance_m, output_type="coo_matrix")
        i, j = pairs.row, pairs.col
        v = paint[j] - s[i]
        along = np.abs(np.einsum("kj,kj->k", v, t[i]))
        across = np.linalg.norm(v - np.einsum("kj,kj->k", v, t[i])[:, None] * t[i], axis=1)
        ok = (along <= tolerance_m) & (across <= half_width_m + tolerance_m)
        covered[j[ok]] = True
    return covered


def paint_report(paint: np.ndarray, paint_normals: np.ndarray, voxel_m: float, half_width_m: float,
                 tolerance_m: float, flames: list[FlamePath], surface: np.ndarray | cKDTree | None = None,
                 gaps: list | None = None, line: list[np.ndarray] | None = None) -> PaintReport:
    """The runnable cuts' flame paths (``flames``, one per cut, lit samples only) against the paint.

    Args:
        paint: (N,3) the drawing cloud, deduplicated at ``voxel_m``; ``paint_normals`` (N,3) its surface normals.
        half_width_m: half the spray width, as measured from the paint.
        tolerance_m: how far from the paint's centre line a cut still counts as on it.
        surface: the measured surface (points or their k-d tree), for the tip's clearance.
        gaps: the plan's gaps (``model.Gap``), to say why a piece of paint is left.
        line: the line's polylines before planning split it (cut and uncut), for ``line_share``.
    """
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    if len(paint) == 0:
        raise ValueError("no paint to measure the cut against")
    area = paint_area(paint_normals, voxel_m)
    total = float(area.sum())
    per_metre = max(2.0 * half_width_m, voxel_m)  # painted area per metre of line
    rep = PaintReport(float(half_width_m), total, total / per_metre, 0.0)
    spots = np.vstack([f.spots for f in flames]) if flames else np.zeros((0, 3))
    centred: list[FlamePath] = []
    paint_tree = cKDTree(paint)
    if len(spots):
        rep.samples = len(spots)
        centre = [off_centre(paint, paint_normals, f.spots, half_width_m, voxel_m, paint_tree) for f in flames]
        beside = [beside_centre(f, c, tolerance_m, half_width_m) for f, c in zip(flames, centre)]
        # paint is cut where the flame passes it on the band's centre, not beside it
        centred = _centred(flames, beside)
        covered = _under(paint, centred, half_width_m, tolerance_m, voxel_m)
        specks = _specks(paint, ~covered, area, half_width_m, voxel_m)
        rep.cut_share = float(area[covered].sum() / max(total - area[specks].sum(), 1e-12))
        offs = [paint_tree.query(f.spots)[0] for f in flames]  # a few cuts
        off = np.concatenate(offs)
        rep.flame_off_paint_max_mm = round(1e3 * float(off.max()), 2)
        steps = [(np.linalg.norm(np.diff(f.spots, axis=0), axis=1), o[1:] > tolerance_m) for f, o in zip(flames, offs)]
        rep.flame_off_paint_m = round(sum(float(d[far].sum()) for d, far in steps), 4)
        measured = np.concatenate(centre)
        measured = measured[np.isfinite(measured)]
        if len(measured):
            rep.flame_off_centre_max_mm = round(1e3 * float(measured.max()), 2)
        rep.flame_off_centre_m = round(sum(float(d[b[1:]].sum()) for (d, _), b in zip(steps, beside)), 4)
        on_paint = sum(float(d[~far].sum()) for d, far in steps)
        if rep.cut_share >= MEASURED_SHARE and on_paint > 0:  # as measured where it is cut
            per_metre = float(area[covered].sum()) / on_paint
            rep.line_length_m = total / per_metre
        if surface is not None:
            tree = surface if isinstance(surface, cKDTree) else cKDTree(np.asarray(surface, dtype=np.float64))
            tips = np.vstack([f.tips for f in flames])
            d = tree.query(tips)[0]
            rep.tip_to_surface_min_mm = round(1e3 * float(d.min()), 2)
            rep.tip_to_surface_max_mm = round(1e3 * float(d.max()), 2)
    else:
        covered = np.zeros(len(paint), dtype=bool)
    rep.uncut = _uncut(paint[~covered], area[~covered], half_width_m, per_metre, voxel_m, gaps or [])
    if line is not None:
        rep.line_share, rep.line_on_paint_m = line_share(line, paint, paint_normals, centred, half_width_m,
                                                         tolerance_m, voxel_m, rep.uncut, paint_tree)
    return rep


def line_share(line: list[np.ndarray], paint: np.ndarray, paint_normals: np.ndarray, centred: list[FlamePath],
               half_width_m: float, tolerance_m: float, voxel_m: float, uncut: list[UncutPaint],
               tree: cKDTree) -> tuple[float, float]:
    """(share, length): the line's samples (every voxel along ``line``, a place listed twice once) on
    the paint (within 1.5 cells of it, ``tree`` its k-d tree) and not beside the band's centre
    (``off_centre``, where measured), the share of them within ``tolerance_m`` of a ``centred`` flame
    spot, of their length plus the ``uncut`` paint no line follows nor passes by (the line beside it
    is counted uncut already). The truth's own measure (the true centreline within the tolerance of
    the flame) on what the scan measured: the line alone would count a loop inside the band as line
    and miss a tip it cut short; the paint's band and the paint left over say where."""
    from planners.metrics import dense_polylines

    polys = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in line if p is not None]
    dense = [dense_polylines([p], voxel_m) for p in polys if len(p)]  # a single point stays itself
    strays = [u for u in uncut if u.reason == NOT_IN_CUT]
    if strays and dense:
        far = cKDTree(np.vstack(dense)).query(np.array([u.centre for u in strays]))[0] > half_width_m + voxel_m
        strays = [u for u, f in zip(strays, far) if f]
    missed_m = sum(u.length_m for u in strays)
    runs = [d for p, d in zip([p for p in polys if len(p)], dense) if len(p) >= 2]
    if not runs:
        return 0.0, float(missed_m)
    samples = np.vstack(runs)
    on = tree.query(samples)[0] <= 1.5 * voxel_m
    on &= ~_listed_before(samples, np.repeat(np.arange(len(runs)), [len(r) for r in runs]), 1.5 * voxel_m)
    off = np.concatenate([off_centre(paint, paint_normals, r, half_width_m, voxel_m, tree) for r in runs])
    on &= ~(off > tolerance_m)  # NaN (not measured): kept
    length = voxel_m * float(on.sum()) + float(missed_m)
    spots = [dense_polylines([f.spots], voxel_m) for f in centred if len(f.spots)]
    if not spots or not on.any():
        return 0.0, length
    near = cKDTree(np.vstack(spots)).query(samples[on])[0] <= tolerance_m
    return float(voxel_m * near.sum() / max(length, 1e-12)), length


def _listed_before(samples: np.ndarray, run: np.ndarray, link_m: float) -> np.ndarray:
    """(N,) bool: samples within ``link_m`` of a sample of an earlier run (``run`` (N,) its index):
    a stretch of metal the line lists twice (one out-of-reach stretch a gap of two branches, the
    ends of branches at a junction) is one stretch of line, counted once."""
    pairs = cKDTree(samples).query_pairs(link_m, output_type="ndarray")
    pairs = pairs[run[pairs[:, 0]] != run[pairs[:, 1]]]
    later = np.where(run[pairs[:, 0]] > run[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
    out = np.zeros(len(samples), dtype=bool)
    out[later] = True
    return out


def _specks(xyz: np.ndarray, uncut: np.ndarray, area: np.ndarray, half_width_m: float, voxel_m: float) -> np.ndarray:
    """(N,) bool: uncut paint in pieces too small to hold any line: the round end of a stroke past
    where its line ends (the spray reaches half a width further), the outside of a sharp tip, noise
    at the band's edge. Counted neither cut nor uncut."""
    out = np.zeros(len(xyz), dtype=bool)
    idx = np.flatnonzero(uncut)
    if len(idx) == 0:
        return out
    n, label = _pieces(xyz[idx], 2.0 * voxel_m)
    sums = np.bincount(label, weights=area[idx], minlength=n)
    out[idx[sums[label] < SPECK_HALF_WIDTHS_SQ * max(half_width_m, voxel_m) ** 2]] = True
    return out


def _uncut(xyz: np.ndarray, area: np.ndarray, half_width_m: float, per_metre: float, voxel_m: float,
           gaps: list) -> list[UncutPaint]:
    """Pieces of uncut paint (linked within two cells), specks dropped, longest first, each with the
    reason of the plan's gap that lies in it (the longest such), else NOT_IN_CUT."""
    if len(xyz) == 0:
        return []
    n, label = _pieces(xyz, 2.0 * voxel_m)
    sums = np.bincount(label, weights=area, minlength=n)
    keep = np.flatnonzero(sums >= SPECK_HALF_WIDTHS_SQ * max(half_width_m, voxel_m) ** 2)
    gap_pts = [(g, np.asarray(g.points, dtype=np.float64).reshape(-1, 3)) for g in gaps
               if getattr(g, "points", None) is not None and len(g.points)]
    out = []
    for k in keep:  # a handful of pieces
        pts = xyz[label == k]
        centre = pts[np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1))]
        tree = cKDTree(pts)
        hits = [(g.length_m, g) for g, gp in gap_pts
                if np.isfinite(tree.query(gp, distance_upper_bound=half_width_m + voxel_m)[0]).any()]
        if hits:
            g = max(hits, key=lambda h: h[0])[1]
            out.append(UncutPaint(centre, float(sums[k] / per_metre), g.reason, g.detail))
        else:
            out.append(UncutPaint(centre, float(sums[k] / per_metre), NOT_IN_CUT,
                                  "no cut follows this paint (a sharp turn cut short, or paint the line missed)"))
    return sorted(out, key=lambda u: -u.length_m)


def lit_flames(path, kin, standoff_m: float) -> list[FlamePath]:
    """The flame's path along every runnable cut of a planned ``CutPath``: every sample of its cut
    motion (the flame is lit from the first cut pose to the last; approach and retract are not lit)."""
    return [flame_path(kin, b.cut.positions, standoff_m) for b in path.branches if b.feasible and b.cut is not None]


def cut_against_paint(path, kin, paint: np.ndarray, surface, cfg, voxel_m: float) -> PaintReport:
    """``paint_report`` of a planned ``CutPath``: the spray's half width as the outline measured it
    (``CutPath.spray_width_m``), else measured across the planned line (the median reach of the paint
    beside it, robust to a stretch the line gets wrong), the normals and the tip's clearance from the
    measured ``surface`` (a ``geometry.Surface``)."""
    from planners.cutpath.geometry import band_half_width

    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    line = [b.points for b in path.branches] + [g.points for g in path.gaps if g.points is not None]
    if path.spray_width_m:  # measured between the outline's sides: the paint of a sharp tip's other leg is not in it
        return paint_report(paint, surface.normals(paint), voxel_m, 0.5 * path.spray_width_m, cfg.line_tolerance_m,
                            lit_flames(path, kin, cfg.standoff_m), surface.tree, path.gaps, line)
    widths = [(b.length_m, band_half_width(b.points, paint, cfg.spacing_m, b.closed, normals=b.normals))
              for b in path.branches if len(b) >= 2]
    widths = [(w, h) for w, h in widths if h > 0]
    if widths:  # the longest runs weigh most
        w, h = np.array(widths).T
        order = np.argsort(h)
        cum = np.cumsum(w[order])
        half = float(h[order][np.searchsorted(cum, 0.5 * cum[-1])])
    else:
        half = 0.5 * cfg.spray_width_m  # no line to measure across: nothing is cut anyway
    return paint_report(paint, surface.normals(paint), voxel_m, half, cfg.line_tolerance_m,
                        lit_flames(path, kin, cfg.standoff_m), surface.tree, path.gaps, line)
