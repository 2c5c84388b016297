"""Has the drawing visibly ended here? A frontier cluster at the tip of the drawing whose surface, just
past the tip along the drawing, has been seen and carries no paint needs no view: the paint stops on
a surface that goes on. Without this test G-NBV spends a view per end confirming what the previous
view already showed (the unknown beyond is a pipe's end cap or the far side of a rim, where a line
could in principle go on). Gaps (a basket's rods), edges the line goes round and unseen surface all
leave the tube past the tip empty of surface points, so those ends stay open."""

from __future__ import annotations

import numpy as np

from planners.config import NBVConfig


def ended(drawing: np.ndarray, surface: np.ndarray, center: np.ndarray, cfg: NBVConfig) -> bool:
    """Whether the frontier cluster at `center` sits at a tip of the drawing past which at least
    `end_min_points` unpainted surface points and no drawing point lie in a tube `end_check_m` long."""
    if cfg.end_check_m <= 0 or len(drawing) < 10:
        return False
    r = cfg.end_radius_m
    local = drawing[np.sum((drawing - center) ** 2, axis=1) < r * r]
    if len(local) < 10:
        return False
    mean = local.mean(axis=0)
    _, _, vt = np.linalg.svd(local - mean, full_matrices=False)
    d = vt[0]
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
