"""Where the unseen line most likely lies, when the seen surface is a cylinder.

Eq. 7's p_φ only reaches a few centimetres past the frontier, so after one view G-NBV cannot tell
a view that frames the rest of the line from one that frames the seen line's shadows
(docs/BENCHMARKS.md, the first-step table of `cellctl bench --oracle`). Scrap is mostly pipes,
tanks and cages: where the surface round the drawing is one cylinder (nine in ten of its points
within a grid cell of the fit), the surface beyond the seen part is known, and a sprayed line on
it goes on as it went: straight in the unrolled cylinder, the way a hand sweeps a can. Those points
of the continuation that still lie in unknown cells, with the cylinder's normal, are what a view
can be scored on: how many it would image, square enough to return paint, with nothing in between.
Where the surface is no cylinder (planes, junctions, collars) there is no prior and eq. 4 decides."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from planners import raycast
from planners.cutpath.geometry import Surface
from planners.grid import OccupancyGrid
from planners.views import in_image

#: surface points (within ``reach`` of the drawing) the fit uses, at most; a fixed draw, repeatable
FIT_POINTS = 4000
#: the surface the line lies on: points this close to the drawing (not the whole piece: a tank's
#: dome, a pipe's collar are other shapes)
FIT_REACH_M = 0.08
#: share of them within one grid cell of the fitted cylinder for it to count as the surface
MIN_INLIERS = 0.9


@dataclass
class Cylinder:
    centre: np.ndarray  # (3,) a point on the axis
    axis: np.ndarray  # (3,) unit
    e1: np.ndarray  # (3,) unit, with e2 spanning the cross-section
    e2: np.ndarray
    radius: float

    def unroll(self, xyz: np.ndarray, theta0: float) -> np.ndarray:
        """(N,2): arc length round the axis from angle ``theta0``, and position along the axis."""
        rel = xyz - self.centre
        th = np.angle(np.exp(1j * (np.arctan2(rel @ self.e2, rel @ self.e1) - theta0)))
        return np.column_stack([self.radius * th, rel @ self.axis])

    def roll(self, uv: np.ndarray, theta0: float) -> tuple[np.ndarray, np.ndarray]:
        """Points (N,3) and outward normals (N,3) of unrolled coordinates."""
        th = uv[:, 0] / self.radius + theta0
        radial = np.outer(np.cos(th), self.e1) + np.outer(np.sin(th), self.e2)
        return self.centre + np.outer(uv[:, 1], self.axis) + self.radius * radial, radial


def fit_cylinder(xyz: np.ndarray, normals: np.ndarray) -> tuple[Cylinder, float]:
    """The cylinder whose axis is square to all normals (least eigenvector of Σ n nᵀ) and whose
    cross-section is the least-squares circle (Kåsa) of the points projected along it; with the
    share of points within one centimetre of it."""
    w, V = np.linalg.eigh(normals.T @ normals)
    axis, e1, e2 = V[:, 0], V[:, 1], V[:, 2]
    p = np.column_stack([xyz @ e1, xyz @ e2])
    A = np.column_stack([2 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(A, (p ** 2).sum(axis=1), rcond=None)
    c2 = sol[:2]
    radius = float(np.sqrt(max(sol[2] + c2 @ c2, 0.0)))
    share = float(np.mean(np.abs(np.linalg.norm(p - c2, axis=1) - radius) < 0.01))
    return Cylinder(c2[0] * e1 + c2[1] * e2, axis, e1, e2, radius), share


def continuation(drawing: np.ndarray, cyl: Cylinder, length_m: float, step_m: float, window_m: float) -> list[tuple]:
    """Per end of the drawing, points (and normals) ``step_m`` apart up to ``length_m`` past it,
    along the straight line that fits its last ``window_m`` in the unrolled cylinder."""
    rel = drawing - cyl.centre
    theta0 = float(np.angle(np.mean(np.exp(1j * np.arctan2(rel @ cyl.e2, rel @ cyl.e1)))))
    U = cyl.unroll(drawing, theta0)
    mu = U.mean(axis=0)
    d = np.linalg.eigh(np.cov((U - mu).T))[1][:, 1]  # the line's main direction in the unrolled plane
    s = (U - mu) @ d
    ahead = np.arange(step_m, length_m + 1e-9, step_m)
    out = []
    for sign in (1.0, -1.0):
        end = s.max() if sign > 0 else s.min()
        last = sign * (s - end) > -window_m
        if last.sum() < 3:
            continue
        A = np.column_stack([s[last], np.ones(last.sum())])
        coef, *_ = np.linalg.lstsq(A, U[last], rcond=None)  # (2,2): slope and offset of u and v in s
        uv = np.column_stack([end + sign * ahead, np.ones(len(ahead))]) @ coef
        out.append(cyl.roll(uv, theta0))
    return out


@dataclass
class LinePrior:
    """Points where the line most likely goes on (unknown cells only), with their outward normals."""

    xyz: np.ndarray  # (K,3)
    normals: np.ndarray  # (K,3)
    inliers: float  # the cylinder fit's share of surface points within a cell
    spacing: float  # metres of line per point


def line_prior(drawing: np.ndarray, surface: np.ndarray, origin: np.ndarray, grid: OccupancyGrid,
               length_m: float, ends_near: np.ndarray | None = None) -> LinePrior | None:
    """The prior, or None where the surface near the drawing is no cylinder.
    ``ends_near``: frontier cells still worth a view; a continuation counts only from an end
    within two cells of one (an end that visibly ended has none; its first point lies half a cell
    past the end)."""
    if len(drawing) < 10 or len(surface) < 50:
        return None
    lo, hi = drawing.min(axis=0) - FIT_REACH_M, drawing.max(axis=0) + FIT_REACH_M
    box = np.flatnonzero(np.all((surface >= lo) & (surface <= hi), axis=1))  # the same points, fewer queries
    d, _ = cKDTree(drawing).query(surface[box], k=1, distance_upper_bound=FIT_REACH_M, workers=-1)
    near = box[np.isfinite(d)]
    S, O = surface[near], origin[near]
    if len(S) < 50:
        return None
    if len(S) > FIT_POINTS:
        pick = np.random.default_rng(0).choice(len(S), FIT_POINTS, replace=False)
        S, O = S[pick], O[pick]
    n = Surface(S, O, None, grid.voxel).normals(S)
    cyl, share = fit_cylinder(S, n)
    if share < MIN_INLIERS or cyl.radius < 2 * grid.voxel:
        return None
    out_side = np.sign(np.mean(np.einsum("ij,ij->i", n, S - cyl.centre - np.outer((S - cyl.centre) @ cyl.axis, cyl.axis))))
    parts = continuation(drawing, cyl, length_m, grid.voxel / 2, 2 * length_m / 3)
    if ends_near is not None:
        tree = cKDTree(ends_near) if len(ends_near) else None
        parts = [p for p in parts if tree is not None and tree.query(p[0][0])[0] <= 2.5 * grid.voxel]
    parts = [_until_refuted(P, N, grid) for P, N in parts]
    parts = [p for p in parts if len(p[0])]
    if not parts:
        return None
    P = np.vstack([p[0] for p in parts])
    N = np.vstack([p[1] for p in parts]) * (out_side or 1.0)
    return LinePrior(P, N, share, grid.voxel / 2)


def _until_refuted(P: np.ndarray, N: np.ndarray, grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray]:
    """The continuation's points in unknown cells not just behind a seen surface (inside a solid),
    up to the first surface seen without paint on its way (had the line gone there, the paint
    would have been seen: a pipe's line that turns up a branch does not run on into it). Seen free
    cells do not end it: on a cage the paint is only where the spray met a rod. The first cells
    past the end are the end's own and skipped."""
    ijk, inside = grid.index_of(P)
    ijk = np.clip(ijk, 0, np.asarray(grid.shape) - 1)
    occ = grid.occupied[tuple(ijk.T)] & ~grid.drawing[tuple(ijk.T)] & inside
    occ[: int(np.ceil(2 * grid.voxel / (grid.voxel / 2)))] = False
    stop = int(np.argmax(occ)) if occ.any() else len(P)
    keep = inside[:stop] & grid.unknown[tuple(ijk[:stop].T)] & ~grid.shadow[tuple(ijk[:stop].T)]
    return P[:stop][keep], N[:stop][keep]


def seen_counts(eyes: np.ndarray, rotations: np.ndarray, prior: LinePrior, K: np.ndarray,
                image_size: tuple[int, int], max_range: float, max_incidence_deg: float,
                grid: OccupancyGrid, occupied_flat: np.ndarray) -> np.ndarray:
    """Per candidate (eyes (C,3), R_base_cam (C,3,3)): how many prior points it would image, in
    frame and range, within ``max_incidence_deg`` of their normal, with no occupied cell on the
    way (the last two cells before a point are its own surface)."""
    P, N = prior.xyz, prior.normals
    _, framed = in_image(eyes, rotations, P, K, image_size)
    view = eyes[:, None, :] - P[None, :, :]
    dist = np.linalg.norm(view, axis=2)
    facing = np.einsum("cpj,pj->cp", view, N) > np.cos(np.deg2rad(max_incidence_deg)) * dist
    seen = raycast.clear_sight(eyes, P, framed & (dist < max_range) & facing, 2 * grid.voxel, grid.lo, grid.voxel,
                               grid.shape, occupied_flat)
    return seen.sum(axis=1)
