"""The cut measured against what the cell saw, never against its own skeleton.

The skeleton's length is the planner's own belief: where it cuts a chord across a sharp tip it still
says "100 %". The paint (the drawing cloud) and the flame's path are independent of it: the flame
spot (where the torch axis meets the metal, ``standoff`` ahead of the tip) is computed at every
sample of the planned joint motion with the flame lit, so a flip of the arm between two poses shows,
and the paint is cut where it lies within half a spray width (plus the line tolerance) of that path.
What paint is left is grouped into pieces, each with where it is and why it is not cut.
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
    flame_off_paint_max_mm: float | None = None  # flame spot to the nearest paint, over every lit sample
    flame_off_paint_m: float = 0.0  # flame travel farther than the tolerance from any paint
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
                 gaps: list | None = None) -> PaintReport:
    """The runnable cuts' flame paths (``flames``, one per cut, lit samples only) against the paint.

    Args:
        paint: (N,3) the drawing cloud, deduplicated at ``voxel_m``; ``paint_normals`` (N,3) its surface normals.
        half_width_m: half the spray width, as measured from the paint.
        tolerance_m: how far from the paint's centre line a cut still counts as on it.
        surface: the measured surface (points or their k-d tree), for the tip's clearance.
        gaps: the plan's gaps (``model.Gap``), to say why a piece of paint is left.
    """
    paint = np.asarray(paint, dtype=np.float64).reshape(-1, 3)
    if len(paint) == 0:
        raise ValueError("no paint to measure the cut against")
    area = paint_area(paint_normals, voxel_m)
    total = float(area.sum())
    per_metre = max(2.0 * half_width_m, voxel_m)  # painted area per metre of line
    rep = PaintReport(float(half_width_m), total, total / per_metre, 0.0)
    spots = np.vstack([f.spots for f in flames]) if flames else np.zeros((0, 3))
    if len(spots):
        rep.samples = len(spots)
        covered = _under(paint, flames, half_width_m, tolerance_m, voxel_m)
        specks = _specks(paint, ~covered, area, half_width_m, voxel_m)
        rep.cut_share = float(area[covered].sum() / max(total - area[specks].sum(), 1e-12))
        paint_tree = cKDTree(paint)
        offs = [paint_tree.query(f.spots)[0] for f in flames]  # a few cuts
        off = np.concatenate(offs)
        rep.flame_off_paint_max_mm = round(1e3 * float(off.max()), 2)
        steps = [(np.linalg.norm(np.diff(f.spots, axis=0), axis=1), o[1:] > tolerance_m) for f, o in zip(flames, offs)]
        rep.flame_off_paint_m = round(sum(float(d[far].sum()) for d, far in steps), 4)
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
    return rep


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
    if path.spray_width_m:  # measured between the outline's sides: the paint of a sharp tip's other leg is not in it
        return paint_report(paint, surface.normals(paint), voxel_m, 0.5 * path.spray_width_m, cfg.line_tolerance_m,
                            lit_flames(path, kin, cfg.standoff_m), surface.tree, path.gaps)
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
                        lit_flames(path, kin, cfg.standoff_m), surface.tree, path.gaps)
