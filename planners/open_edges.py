"""Paint where the measured surface ends: the frontier finer than the grid's cells. On thin stock (a
basket's 16 mm rods) one 1 cm cell holds a rod's front, seen square-on, and its flanks, never seen:
the grid calls the cell known and no frontier points at the flanks. The point cloud does know: the
paint seen so far stops where the surface seen so far stops, not where the paint does. A point on
the edge of a sampled surface has its neighbours on one side: their centroid, in the tangent plane,
lies 4r/(3 pi) = 0.42 r inward for a half disc of radius r, and near 0 inside the surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: centroid shift (share of the radius) halfway between a surface's inside (0) and its edge (0.42)
EDGE_SHIFT = 2.0 / (3.0 * np.pi)
#: neighbours at most in a point's disc (the nearest of those within the radius)
NEIGHBOURS = 32
#: fewer neighbours than this in the disc: too sparse to tell an edge (isolated points are noise)
MIN_NEIGHBOURS = 6


@dataclass
class OpenEdges:
    """Drawing points on the edge of the measured surface: where they are, their surface normal
    (toward the sensors that saw them) and the tangent pointing away from what was seen, along
    which the surface, and maybe the paint, goes on unseen."""

    xyz: np.ndarray  # (M,3)
    normals: np.ndarray  # (M,3)
    outward: np.ndarray  # (M,3), unit, orthogonal to the normal
    index: np.ndarray  # (M,) rows of the drawing


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
    k = min(NEIGHBOURS, len(S))
    d, idx = cKDTree(S).query(P, k=k, distance_upper_bound=radius_m)
    d, idx = d.reshape(len(P), k), idx.reshape(len(P), k)
    w = np.isfinite(d)
    cnt = w.sum(axis=1)
    Q = S[np.where(w, idx, 0)] - P[:, None, :]  # neighbours relative to the point
    Wf = w.astype(np.float64)
    c = np.einsum("mk,mkj->mj", Wf, Q) / np.maximum(cnt, 1)[:, None]
    D = Q - c[:, None, :]
    C = np.einsum("mk,mki,mkj->mij", Wf, D, D) / np.maximum(cnt, 1)[:, None, None]
    n = np.linalg.eigh(C)[1][:, :, 0]  # least variance: the normal
    toward = O - P
    seen = np.all(np.isfinite(toward), axis=1)
    flip = seen & (np.einsum("mj,mj->m", n, np.where(seen[:, None], toward, 0.0)) < 0)
    n[flip] *= -1.0
    c_t = c - np.einsum("mj,mj->m", c, n)[:, None] * n  # the centroid's offset in the tangent plane
    shift = np.linalg.norm(c_t, axis=1)
    edge = (cnt >= MIN_NEIGHBOURS) & (shift > EDGE_SHIFT * radius_m)
    if not edge.any():
        return empty
    out = -c_t[edge] / shift[edge, None]
    return OpenEdges(P[edge], n[edge], out, np.flatnonzero(edge))
