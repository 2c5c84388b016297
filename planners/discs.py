"""The measured surface round a point: is the point inside it or on its border?

Inside a sampled surface a point's neighbours within a radius lie all round it and their centroid is
the point itself; on the border (a rim, the image's edge, a rod's flank turning away) they lie on one
side and the centroid moves 4r/(3 pi) = 0.42 r off for a half disc. The shift is measured in the
tangent plane of the neighbours (their least-variance axis is the normal), not in 3-D: across a
corner where both faces were seen (a web meeting a flange) the neighbours form an L whose centroid
moves off along the corner's bisector, the normal, not into the plane; and depth noise or a rod's
curvature moves the 3-D centroid off the point as far as a border does."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass
class Discs:
    """Per query point: its neighbours within the radius, their normal (unit, least variance) and
    their centroid's offset from the point in the tangent plane (metres)."""

    count: np.ndarray  # (M,) int
    normals: np.ndarray  # (M,3)
    shift: np.ndarray  # (M,3)


def discs(points: np.ndarray, surface: cKDTree, radius: float, k: int) -> Discs:
    """The disc of measured surface (``surface``'s points, at most ``k`` nearest) round each point."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0 or surface.n == 0:
        z = np.zeros((len(P), 3))
        return Discs(np.zeros(len(P), dtype=np.int64), z, z.copy())
    k = min(k, surface.n)
    d, idx = surface.query(P, k=k, distance_upper_bound=radius, workers=-1)
    d, idx = d.reshape(len(P), k), idx.reshape(len(P), k)
    w = np.isfinite(d)
    cnt = w.sum(axis=1)
    Q = surface.data[np.where(w, idx, 0)] - P[:, None, :]  # neighbours relative to the point
    Wf = w.astype(np.float64)
    c = np.einsum("mk,mkj->mj", Wf, Q) / np.maximum(cnt, 1)[:, None]
    D = Q - c[:, None, :]
    C = np.einsum("mk,mki,mkj->mij", Wf, D, D) / np.maximum(cnt, 1)[:, None, None]
    n = np.linalg.eigh(C)[1][:, :, 0]
    return Discs(cnt, n, c - np.einsum("mj,mj->m", c, n)[:, None] * n)
