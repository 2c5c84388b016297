"""The quality metric Q shared by the probabilistic NBV planners (eq. 4-8), scored for all
candidates of a step in one compiled call."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from planners import raycast
from planners.clouds import Cloud
from planners.config import NBVConfig
from planners.grid import OccupancyGrid
from planners.views import ray_bundle, surface_normal


def feature_probability(grid: OccupancyGrid, frontier_ijk: np.ndarray, cfg: NBVConfig) -> tuple[np.ndarray, tuple]:
    """p_φ of eq. 7 on the box of cells where it is not negligible: exp(-α (d/ℓ)²), d the distance to
    the nearest frontier cell. Returns (values on the box, box slices)."""
    cutoff = cfg.phi_length_m * np.sqrt(np.log(1e3) / cfg.alpha_phi)
    pad = int(np.ceil(cutoff / grid.voxel)) + 1
    lo = np.maximum(frontier_ijk.min(axis=0) - pad, 0)
    hi = np.minimum(frontier_ijk.max(axis=0) + pad + 1, grid.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    seed = np.ones(tuple(hi - lo), dtype=bool)
    local = frontier_ijk - lo
    seed[local[:, 0], local[:, 1], local[:, 2]] = False
    d = ndimage.distance_transform_edt(seed) * grid.voxel
    return np.exp(-cfg.alpha_phi * (d / cfg.phi_length_m) ** 2).astype(np.float32), box


def entropy_decrease(grid: OccupancyGrid, box: tuple) -> np.ndarray:
    """h(g) of eq. 6 on a box of cells."""
    c = grid.cfg
    return _entropy_decrease(grid.logodds[box], c.l_hit, c.l_miss, c.l_min, c.l_max)


@dataclass
class CellWeights:
    """What a view can gain, on the box of cells where it is not negligible: per cell h(g)·p_φ(g) and
    the outward normal of the surface that may be there (zero: none known or not used), packed as
    (bx, by, bz, 4) so the kernel reads both from one place; the box starts at cell `lo`."""

    cells: np.ndarray  # (bx, by, bz, 4) float32: weight, normal x, y, z
    lo: np.ndarray  # (3,) int64 first cell of the box
    facing: bool  # scale each cell by the cosine at which a ray meets its normal

    @classmethod
    def on_box(cls, grid: OccupancyGrid, box: tuple, w: np.ndarray, facing: bool) -> "CellWeights":
        cells = np.zeros(w.shape + (4,), dtype=np.float32)
        cells[..., 0] = w
        if facing:
            cells[..., 1:] = facing_normals(grid, box)
        return cls(cells, np.array([s.start for s in box], dtype=np.int64), facing)


def cell_weights(grid: OccupancyGrid, frontier_ijk: np.ndarray, cfg: NBVConfig) -> CellWeights:
    """h(g)·p_φ(g) on the box round the frontier where p_φ is not negligible, with the surface
    normals of `facing_normals` when cfg.facing_gain. With cfg.observed_known only unknown cells
    weigh: a cell already hit had its colour seen (paint or not) and a free one holds no paint, so
    seeing either again tells nothing about the drawing (eq. 6 would still count their occupancy
    entropy, which drew views back to the surfaces already seen)."""
    phi, box = feature_probability(grid, frontier_ijk, cfg)
    if cfg.observed_known:  # h(g) of an unknown cell is one number: no per-cell entropy pass
        c = grid.cfg
        h0 = _entropy_decrease(np.zeros(1), c.l_hit, c.l_miss, c.l_min, c.l_max)[0]
        w = np.where(grid.logodds[box] == 0, h0 * phi, np.float32(0.0))
    else:
        w = entropy_decrease(grid, box) * phi
    return CellWeights.on_box(grid, box, w, cfg.facing_gain)


def facing_normals(grid: OccupancyGrid, box: tuple) -> np.ndarray:
    """Per cell of the box, the outward normal of a surface there as far as the map tells: a surface
    can only be seen from observed free space, so it faces up the gradient of the (smoothed) free
    indicator. Zero where no free space is near (deep inside the unknown: no orientation known)."""
    free = ndimage.gaussian_filter((grid.logodds[box] < 0).astype(np.float32), sigma=1.0)
    g = np.stack(np.gradient(free), axis=-1)
    n = np.linalg.norm(g, axis=-1, keepdims=True)
    return np.where(n > 0.05, g / np.maximum(n, 1e-9), 0.0).astype(np.float32)


def _entropy_decrease(L: np.ndarray, l_hit: float, l_miss: float, l_min: float, l_max: float) -> np.ndarray:
    L = L.astype(np.float64)

    def H(l):
        p = np.clip(1.0 / (1.0 + np.exp(-l)), 1e-12, 1 - 1e-12)
        return -(p * np.log(p) + (1 - p) * np.log(1 - p))

    p = 1.0 / (1.0 + np.exp(-L))
    h = H(L) - (p * H(np.minimum(L + l_hit, l_max)) + (1 - p) * H(np.maximum(L + l_miss, l_min)))
    # With clamped, fixed increments a confident cell can "expect" more entropy after a surprising
    # hit than it has now; information does not go negative, so neither may h.
    return np.maximum(h, 0.0).astype(np.float32)


def visibility_field(grid: OccupancyGrid, cfg: NBVConfig, unknown_visibility: float | None = None) -> np.ndarray:
    """P[o_r = 0] per cell for eq. 8, flat: 1 for free cells, 1 - p for occupied ones, a prior for
    unknown ones (`unknown_visibility`, default cfg's; lower behind observed surfaces)."""
    p_free = (1.0 / (1.0 + np.exp(grid.logodds))).astype(np.float32)  # 1 - sigmoid(L)
    # A cell the map calls free does not occlude: with clamped log-odds (p >= 0.12) the product would
    # otherwise fade every ray through known air and favour candidates nearest the target.
    p_free[grid.logodds < 0] = 1.0
    unknown = grid.unknown
    p_free[unknown] = cfg.unknown_visibility if unknown_visibility is None else unknown_visibility
    p_free[unknown & grid.shadow] = cfg.shadow_visibility
    return p_free.reshape(-1)


def gains(grid: OccupancyGrid, eyes: np.ndarray, rotations: np.ndarray, weights: CellWeights,
          p_free: np.ndarray, K: np.ndarray, image_size: tuple[int, int], cfg: NBVConfig,
          cost: np.ndarray | None = None, footprint: bool = False) -> np.ndarray:
    """gain(s) of eq. 5 for all candidates; `weights` is what cell_weights returns. With `footprint`
    each ray counts the cells its share of the image covers where it crosses them (`ray_patch`).

    With the candidates' travel `cost`, scoring is coarse to fine: every candidate is cast with a
    ray bundle `coarse_ray_factor` times sparser per axis, and only the `refine_top` best by Q are
    cast with the full bundle. The others keep their coarse gain, scaled to the fine one's units by
    the refined candidates' ratio: their rank only matters if every refined one proves unreachable."""
    f = cfg.coarse_ray_factor
    full = (cfg.rays_w, cfg.rays_h)
    if cost is None or f <= 1 or len(eyes) <= cfg.refine_top:
        return _cast(grid, eyes, rotations, weights, p_free, K, image_size, full, cfg, footprint)
    coarse = _cast(grid, eyes, rotations, weights, p_free, K, image_size,
                   (max(cfg.rays_w // f, 2), max(cfg.rays_h // f, 2)), cfg, footprint)
    top = np.argpartition(-quality(coarse, cost, cfg.lam), cfg.refine_top - 1)[:cfg.refine_top]
    fine = _cast(grid, eyes[top], rotations[top], weights, p_free, K, image_size, full, cfg, footprint)
    cs = coarse[top].sum()
    out = coarse * (fine.sum() / cs if cs > 0 else 0.0)
    out[top] = fine
    return out


def ray_patch(K: np.ndarray, image_size: tuple[int, int], bundle: tuple[int, int], voxel: float) -> float:
    """Solid angle one ray of a `bundle` (n_w, n_h) stands for, over a cell's face (sr / voxel²)."""
    (w, h), (n_w, n_h) = image_size, bundle
    return float((w / n_w) / K[0, 0] * (h / n_h) / K[1, 1] / voxel**2)


def _cast(grid: OccupancyGrid, eyes: np.ndarray, rotations: np.ndarray, weights: CellWeights,
          p_free: np.ndarray, K: np.ndarray, image_size: tuple[int, int], bundle: tuple[int, int],
          cfg: NBVConfig, footprint: bool) -> np.ndarray:
    patch = ray_patch(K, image_size, bundle, grid.voxel) if footprint else 0.0
    return raycast.view_gains(np.ascontiguousarray(eyes, dtype=np.float64),
                              np.ascontiguousarray(rotations, dtype=np.float64),
                              ray_bundle(K, image_size, *bundle), float(cfg.max_range_m), grid.lo, grid.voxel,
                              np.asarray(grid.shape, dtype=np.int64), p_free, weights.cells, weights.lo,
                              weights.facing, int(numba.get_num_threads()), patch)


def quality(gain: np.ndarray, cost: np.ndarray, lam: float) -> np.ndarray:
    """Eq. 4: convex combination of the normalized gain and the normalized travel cost."""
    gs = gain.sum()
    cs = cost.sum()
    g = gain / gs if gs > 0 else np.zeros_like(gain)
    c = cost / cs if cs > 0 else np.zeros_like(cost)
    return lam * g - (1.0 - lam) * c


class OccupiedIndex:
    """The occupied cells of one grid state, indexed once per planning step rather than per query."""

    def __init__(self, grid: OccupancyGrid):
        occ = grid.occupied
        self.flat = occ.reshape(-1).view(np.uint8)
        ijk = np.argwhere(occ)
        self.tree = cKDTree(grid.centers(ijk)) if len(ijk) else None


def feasible_eyes(grid: OccupancyGrid, eyes: np.ndarray, target: np.ndarray, normal: np.ndarray | None,
                  cfg: NBVConfig, past_views: np.ndarray | None = None, cone_deg: float | None = None,
                  line_of_sight: bool = True, occupied: OccupiedIndex | None = None) -> np.ndarray:
    """Mask of candidate positions a camera may occupy and see its target from: inside the grid,
    above the floor limit, clear of occupied cells, not inside what was seen to be behind a surface,
    on the observed side of the surface within the viewing cone, not a repeat of a past viewing
    direction onto the target, and with no occupied cell on the line of sight. `target` and
    `normal` are one (3,) for all eyes or one row per eye; a NaN normal row means no cone."""
    targets = np.broadcast_to(np.asarray(target, dtype=np.float64), eyes.shape)
    margin = cfg.clearance_m
    ok = np.all((eyes >= grid.lo + margin) & (eyes <= grid.hi - margin), axis=1)
    ok &= eyes[:, 2] >= cfg.min_camera_z_m
    if normal is not None:
        normals = np.broadcast_to(np.asarray(normal, dtype=np.float64), eyes.shape)
        v = eyes - targets
        cosang = np.einsum("ij,ij->i", v, normals) / np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        limit = np.cos(np.deg2rad(cfg.max_view_angle_deg if cone_deg is None else cone_deg))
        ok &= ~(cosang < limit)  # NaN normal: no constraint
    if ok.any():
        ijk, inside = grid.index_of(eyes)
        behind = np.zeros(len(eyes), dtype=bool)
        behind[inside] = grid.shadow[tuple(ijk[inside].T)] & grid.unknown[tuple(ijk[inside].T)]
        ok &= ~behind
    if past_views is not None:
        ok &= ~repeats(eyes, targets, past_views, cfg.revisit_angle_deg)
    occupied = occupied or OccupiedIndex(grid)
    if occupied.tree is not None and ok.any() and margin > 0:
        d, _ = occupied.tree.query(eyes[ok], k=1, distance_upper_bound=margin)
        idx = np.flatnonzero(ok)
        ok[idx[np.isfinite(d)]] = False
    if ok.any() and line_of_sight:
        idx = np.flatnonzero(ok)
        e = eyes[idx]
        v = targets[idx] - e
        L = np.linalg.norm(v, axis=1, keepdims=True)
        stop_short = e + v * np.clip((L - 3 * grid.voxel) / np.maximum(L, 1e-9), 0, 1)
        blocked = raycast.segments_blocked(np.ascontiguousarray(e), np.ascontiguousarray(stop_short), grid.lo,
                                           grid.voxel, np.asarray(grid.shape, dtype=np.int64), occupied.flat)
        ok[idx[blocked]] = False
    return ok


def repeats(eyes: np.ndarray, targets: np.ndarray, past_views: np.ndarray, angle_deg: float) -> np.ndarray:
    """Mask of eyes that see their target (one row per eye) from within `angle_deg` of the direction
    of a past view (P, 3) onto it: that view saw what they would. None with no past view or angle 0."""
    if len(past_views) == 0 or angle_deg <= 0:
        return np.zeros(len(eyes), dtype=bool)
    u = eyes - targets
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
    pv = past_views[None, :, :] - targets[:, None, :]
    pv /= np.maximum(np.linalg.norm(pv, axis=2, keepdims=True), 1e-9)
    return np.einsum("mj,mpj->mp", u, pv).max(axis=1) >= np.cos(np.deg2rad(angle_deg))


def outward_normal(surface: Cloud, target: np.ndarray, radius: float = 0.03) -> np.ndarray | None:
    """Surface normal at the target, on the side of the sensors that saw the patch (not the camera
    that happens to be there now). None at edges and corners, or with too few points."""
    d2 = np.sum((surface.xyz - target) ** 2, axis=1)
    near = d2 < radius * radius
    if near.sum() < 10:
        return None
    toward = target + np.nanmean(surface.origin[near] - surface.xyz[near], axis=0)
    if not np.all(np.isfinite(toward)):
        return None
    return surface_normal(surface.xyz[near], target, radius, toward)
