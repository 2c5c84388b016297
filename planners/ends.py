"""Has the drawing visibly ended here? A frontier cluster at the tip of the drawing whose surface, just
past the tip along the drawing, has been seen and carries no paint needs no view: the paint stops on
a surface that goes on. Without this test G-NBV spends a view per end confirming what the previous
view already showed (the unknown beyond is a pipe's end cap or the far side of a rim, where a line
could in principle go on). Gaps (a basket's rods), edges the line goes round and unseen surface all
leave the tube past the tip empty of surface points, so those ends stay open.

The same holds all round: a cluster whose every drawing point has seen surface on all sides
(`sealed`) is paint whose border was observed, painted or not, so no line can leave it there
unseen; the unknown next to it is a pipe's flank curving away behind a stripe whose edge was seen.
A border of the seen surface (a rim, the far edge of a stripe curving away, a gap between rods)
leaves its points unsealed, so those clusters stay open."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from planners.config import NBVConfig
from planners.discs import discs


def sealed(points: np.ndarray, surface: cKDTree, radius: float, surface_voxel: float, k: int = 160) -> np.ndarray:
    """Per drawing point: is it surrounded by observed surface (painted or not) within `radius`?
    Inside the seen surface its disc (planners.discs) is full and the neighbours' centroid lies on
    the point's normal; at the border of what was seen (a rim, a flank curving away, a gap between
    rods, the image's edge) half the disc is empty and the centroid moves about 0.42 radius off in
    the tangent plane; there the paint may go on. Sealed: that shift under 0.2 radius and at least
    a quarter of the disc's surface voxels present (k nearest neighbours at most, so dense clouds
    cost no more)."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    disc = discs(points, surface, radius, k)
    shift = np.linalg.norm(disc.shift, axis=1)
    return (shift < 0.2 * radius) & (disc.count >= np.pi * (radius / surface_voxel) ** 2 / 4)


def local_axis(points: np.ndarray, center: np.ndarray, radius: float,
               min_points: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The drawing's direction near ``center``: (its points within ``radius``, their mean, their
    principal axis, either sign), or None with fewer than ``min_points`` there."""
    local = points[np.sum((points - center) ** 2, axis=1) < radius * radius]
    if len(local) < min_points:
        return None
    mean = local.mean(axis=0)
    _, _, vt = np.linalg.svd(local - mean, full_matrices=False)
    return local, mean, vt[0]


def ended(drawing: np.ndarray, surface: np.ndarray, center: np.ndarray, cfg: NBVConfig) -> bool:
    """Whether the frontier cluster at `center` sits at a tip of the drawing past which at least
    `end_min_points` unpainted surface points and no drawing point lie in a tube `end_check_m` long."""
    if cfg.end_check_m <= 0 or len(drawing) < 10:
        return False
    axis = local_axis(drawing, center, cfg.end_radius_m)
    if axis is None:
        return False
    local, mean, d = axis
    if np.dot(center - mean, d) < 0:
        d = -d
    proj = (local - mean) @ d
    tip = proj.max()
    if np.dot(center - mean, d) < tip - cfg.end_radius_m / 2:
        return False  # the cluster lies along the drawing's side, not at its tip
    tip_point = mean + tip * d
    lo, hi = 0.005, 0.005 + cfg.end_check_m

    def in_tube(p: np.ndarray) -> np.ndarray:
        box = np.all(np.abs(p - tip_point) < hi + cfg.end_width_m, axis=1)  # cheap cut before the exact test
        q = p[box] - tip_point
        s = q @ d
        lateral = np.linalg.norm(q - s[:, None] * d, axis=1)
        return (s > lo) & (s < hi) & (lateral < cfg.end_width_m)

    if np.any(in_tube(drawing)):
        return False
    return int(np.count_nonzero(in_tube(surface))) >= cfg.end_min_points
