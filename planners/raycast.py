"""Compiled voxel-traversal kernels (Amanatides-Woo DDA). Every per-ray and per-candidate loop of the
planners lives here, in numba, never in Python."""

from __future__ import annotations

import numba as nb
import numpy as np

FREE = np.int8(1)
HIT = np.int8(2)
SHADOW = np.int8(3)  # just behind a hit: unseen, and likely solid or occluded


@nb.njit(cache=True, inline="always")
def _flat(i, j, k, ny, nz):
    return (i * ny + j) * nz + k


@nb.njit(cache=True, inline="always")
def _clip(ox, oy, oz, dx, dy, dz, t0, t1, blo, bhi):
    """Slab test: the part [t0, t1] of the ray inside the box [blo, bhi] (empty when t0 >= t1)."""
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    for a in range(3):
        if abs(d[a]) < 1e-12:
            if o[a] < blo[a] or o[a] >= bhi[a]:
                return 1.0, 0.0
        else:
            ta = (blo[a] - o[a]) / d[a]
            tb = (bhi[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            if ta > t0:
                t0 = ta
            if tb < t1:
                t1 = tb
    return t0, t1


@nb.njit(cache=True, inline="always")
def _dda_start(ox, oy, oz, dx, dy, dz, t0, lo, voxel, nx, ny, nz):
    """Amanatides-Woo set-up at distance t0: the cell, the steps, and the distances to the next
    cell boundary on each axis and between boundaries."""
    eps = 1e-7
    i = min(max(int(np.floor((ox + dx * (t0 + eps) - lo[0]) / voxel)), 0), nx - 1)
    j = min(max(int(np.floor((oy + dy * (t0 + eps) - lo[1]) / voxel)), 0), ny - 1)
    k = min(max(int(np.floor((oz + dz * (t0 + eps) - lo[2]) / voxel)), 0), nz - 1)
    si = 1 if dx > 0 else -1
    sj = 1 if dy > 0 else -1
    sk = 1 if dz > 0 else -1
    inf = 1e30
    tdx = voxel / abs(dx) if abs(dx) > 1e-12 else inf
    tdy = voxel / abs(dy) if abs(dy) > 1e-12 else inf
    tdz = voxel / abs(dz) if abs(dz) > 1e-12 else inf
    tx = (lo[0] + (i + (1 if si > 0 else 0)) * voxel - ox) / dx if abs(dx) > 1e-12 else inf
    ty = (lo[1] + (j + (1 if sj > 0 else 0)) * voxel - oy) / dy if abs(dy) > 1e-12 else inf
    tz = (lo[2] + (k + (1 if sk > 0 else 0)) * voxel - oz) / dz if abs(dz) > 1e-12 else inf
    return i, j, k, si, sj, sk, tx, ty, tz, tdx, tdy, tdz


@nb.njit(cache=True, inline="always")
def _dda_next(i, j, k, si, sj, sk, tx, ty, tz, tdx, tdy, tdz, nx, ny, nz):
    """One step to the neighbouring cell the ray enters next; inside is False once it leaves."""
    if tx <= ty and tx <= tz:
        i += si
        tx += tdx
        inside = 0 <= i < nx
    elif ty <= tz:
        j += sj
        ty += tdy
        inside = 0 <= j < ny
    else:
        k += sk
        tz += tdz
        inside = 0 <= k < nz
    return i, j, k, tx, ty, tz, inside


@nb.njit(cache=True, parallel=True)
def mark_scan(origin, points, lo, voxel, shape, truncation, shadow_depth, marks):
    """Mark the cells one scan touches: HIT where a point lands, FREE along each ray before it
    (stopping `truncation` cells short of the hit so noise does not carve the surface), SHADOW for
    `shadow_depth` metres behind it."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    n = points.shape[0]
    for r in nb.prange(n):
        i = int(np.floor((points[r, 0] - lo[0]) / voxel))
        j = int(np.floor((points[r, 1] - lo[1]) / voxel))
        k = int(np.floor((points[r, 2] - lo[2]) / voxel))
        if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
            marks[_flat(i, j, k, ny, nz)] = HIT
    for r in nb.prange(n):
        ox = origin[0]
        oy = origin[1]
        oz = origin[2]
        dx = points[r, 0] - ox
        dy = points[r, 1] - oy
        dz = points[r, 2] - oz
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        if length < 1e-9:
            continue
        # stop short of the hit by `truncation` voxels
        tmax_len = length - truncation * voxel
        if tmax_len <= 0:
            continue
        dx /= length
        dy /= length
        dz /= length
        _traverse_mark(ox, oy, oz, dx, dy, dz, 0.0, tmax_len, lo, voxel, nx, ny, nz, marks, FREE)
        if shadow_depth > 0:
            _traverse_mark(ox, oy, oz, dx, dy, dz, length + voxel, length + shadow_depth, lo, voxel,
                           nx, ny, nz, marks, SHADOW)


@nb.njit(cache=True, inline="always")
def _traverse_mark(ox, oy, oz, dx, dy, dz, t_start, t_end, lo, voxel, nx, ny, nz, marks, value):
    hi = (lo[0] + nx * voxel, lo[1] + ny * voxel, lo[2] + nz * voxel)
    t0, t1 = _clip(ox, oy, oz, dx, dy, dz, t_start, t_end, lo, hi)
    if t0 >= t1:
        return
    i, j, k, si, sj, sk, tx, ty, tz, tdx, tdy, tdz = _dda_start(ox, oy, oz, dx, dy, dz, t0, lo, voxel, nx, ny, nz)
    inside = True
    while inside:
        f = _flat(i, j, k, ny, nz)
        if marks[f] == 0:
            marks[f] = value
        if min(tx, ty, tz) >= t1:
            return
        i, j, k, tx, ty, tz, inside = _dda_next(i, j, k, si, sj, sk, tx, ty, tz, tdx, tdy, tdz, nx, ny, nz)


@nb.njit(cache=True, parallel=True)
def view_gains(positions, rotations, ray_dirs, max_range, lo, voxel, shape, p_free, cells, box_lo, facing, n_chunks,
               patch=0.0):
    """gain(s) of eq. 5 for every candidate in one call: along each ray of the candidate's
    (subsampled) image, sum the weight h(g)·p_φ(g) of each cell of the box times the visibility of
    eq. 8 (product of P[o=0] of the cells before g, p_free over the whole grid); each cell counts
    once per candidate. `cells` (bx, by, bz, 4) holds per box cell the weight and, with `facing`, the
    outward normal of the surface that may be there: the weight is scaled by the cosine at which
    the ray meets it (0 from behind), or by 1/2, the mean over orientations, where no normal is
    known. Rays that miss the box are skipped and the others stop where they leave it.
    `patch` > 0 is the solid angle one ray stands for over a cell's face (sr / voxel²): a ray at
    distance t then counts each cell as the max(1, patch·t²) cells its footprint covers there, so a
    sparse bundle still estimates the cells a far view sees (0: each ray counts the cells it crosses)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    bx, by, bz = cells.shape[0], cells.shape[1], cells.shape[2]
    roi_lo = np.empty(3)
    roi_hi = np.empty(3)
    for a in range(3):
        roi_lo[a] = lo[a] + box_lo[a] * voxel
        roi_hi[a] = lo[a] + (box_lo[a] + cells.shape[a]) * voxel
    m = positions.shape[0]
    gains = np.zeros(m, dtype=np.float64)
    stamps = np.zeros((n_chunks, bx * by * bz), dtype=np.int32)
    per = (m + n_chunks - 1) // n_chunks
    for c in nb.prange(n_chunks):
        stamp = stamps[c]
        for s in range(c * per, min(m, (c + 1) * per)):
            tag = s + 1
            ox = positions[s, 0]
            oy = positions[s, 1]
            oz = positions[s, 2]
            R = rotations[s]
            total = 0.0
            for r in range(ray_dirs.shape[0]):
                cx = ray_dirs[r, 0]
                cy = ray_dirs[r, 1]
                cz = ray_dirs[r, 2]
                dx = R[0, 0] * cx + R[0, 1] * cy + R[0, 2] * cz
                dy = R[1, 0] * cx + R[1, 1] * cy + R[1, 2] * cz
                dz = R[2, 0] * cx + R[2, 1] * cy + R[2, 2] * cz
                t_end = _box_exit(ox, oy, oz, dx, dy, dz, roi_lo, roi_hi, max_range)
                if t_end > 0.0:
                    total += _ray_gain(ox, oy, oz, dx, dy, dz, t_end, lo, voxel, nx, ny, nz,
                                       p_free, cells, box_lo, facing, stamp, tag, patch)
            gains[s] = total
    return gains


@nb.njit(cache=True, inline="always")
def _box_exit(ox, oy, oz, dx, dy, dz, blo, bhi, max_range):
    """Distance at which the ray leaves the box, or -1 if it never enters it within max_range."""
    t0, t1 = _clip(ox, oy, oz, dx, dy, dz, 0.0, max_range, blo, bhi)
    return t1 if t0 < t1 else -1.0


@nb.njit(cache=True, inline="always")
def _ray_gain(ox, oy, oz, dx, dy, dz, max_range, lo, voxel, nx, ny, nz, p_free, cells, box_lo, facing, stamp, tag,
              patch):
    hi = (lo[0] + nx * voxel, lo[1] + ny * voxel, lo[2] + nz * voxel)
    t0, t1 = _clip(ox, oy, oz, dx, dy, dz, 0.0, max_range, lo, hi)
    if t0 >= t1:
        return 0.0
    i, j, k, si, sj, sk, tx, ty, tz, tdx, tdy, tdz = _dda_start(ox, oy, oz, dx, dy, dz, t0, lo, voxel, nx, ny, nz)
    bx, by, bz = cells.shape[0], cells.shape[1], cells.shape[2]
    vis = 1.0
    g = 0.0
    inside = True
    while inside:
        a = i - box_lo[0]
        b = j - box_lo[1]
        c = k - box_lo[2]
        if 0 <= a < bx and 0 <= b < by and 0 <= c < bz:
            q = (a * by + b) * bz + c
            if stamp[q] != tag:
                stamp[q] = tag
                w = cells[a, b, c, 0]
                if w > 0.0:
                    if facing:
                        fx = cells[a, b, c, 1]
                        fy = cells[a, b, c, 2]
                        fz = cells[a, b, c, 3]
                        if fx != 0.0 or fy != 0.0 or fz != 0.0:
                            w *= max(0.0, -(dx * fx + dy * fy + dz * fz))
                        else:
                            w *= 0.5
                    if patch > 0.0:
                        t = min(tx, ty, tz)
                        w *= max(1.0, patch * t * t)
                    g += vis * w
        vis *= p_free[_flat(i, j, k, ny, nz)]
        if vis < 1e-4 or min(tx, ty, tz) >= t1:
            return g
        i, j, k, tx, ty, tz, inside = _dda_next(i, j, k, si, sj, sk, tx, ty, tz, tdx, tdy, tdz, nx, ny, nz)
    return g


@nb.njit(cache=True, parallel=True)
def segments_blocked(starts, ends, lo, voxel, shape, blocked):
    """For each segment, whether it crosses a cell flagged in `blocked` (uint8, flat)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    m = starts.shape[0]
    out = np.zeros(m, dtype=np.bool_)
    for s in nb.prange(m):
        dx = ends[s, 0] - starts[s, 0]
        dy = ends[s, 1] - starts[s, 1]
        dz = ends[s, 2] - starts[s, 2]
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        if length < 1e-9:
            continue
        steps = int(length / (0.5 * voxel)) + 1
        for q in range(steps + 1):
            t = q / steps
            i = int(np.floor((starts[s, 0] + dx * t - lo[0]) / voxel))
            j = int(np.floor((starts[s, 1] + dy * t - lo[1]) / voxel))
            k = int(np.floor((starts[s, 2] + dz * t - lo[2]) / voxel))
            if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
                if blocked[_flat(i, j, k, ny, nz)]:
                    out[s] = True
                    break
    return out


def clear_sight(eyes: np.ndarray, points: np.ndarray, pairs: np.ndarray, short_m: float, lo: np.ndarray,
                voxel: float, shape, occupied_flat: np.ndarray) -> np.ndarray:
    """``pairs`` (C, M, bool: eye c sees point m) less those whose segment, stopped ``short_m``
    before the point (its own surface's cells), crosses an occupied cell."""
    out = pairs.copy()
    ci, mi = np.nonzero(out)
    if len(ci):
        start = eyes[ci]
        d = points[mi] - start
        L = np.linalg.norm(d, axis=1, keepdims=True)
        stop = start + d * np.clip((L - short_m) / np.maximum(L, 1e-9), 0, 1)
        blocked = segments_blocked(np.ascontiguousarray(start), np.ascontiguousarray(stop), lo, voxel,
                                   np.asarray(shape, dtype=np.int64), occupied_flat)
        out[ci[blocked], mi[blocked]] = False
    return out


def warmup() -> None:
    """Compile (or load from numba's cache) every kernel before the first timed planning step."""
    lo = np.zeros(3)
    shape = np.array([4, 4, 4], dtype=np.int64)
    marks = np.zeros(64, dtype=np.int8)
    mark_scan(np.array([0.5, 0.5, 3.5]) * 0.01, np.array([[0.02, 0.02, 0.005]]), lo, 0.01, shape, 1.0, 0.02, marks)
    cells = np.ones((4, 4, 4, 4), np.float32)
    for facing in (False, True):
        view_gains(np.array([[0.02, 0.02, 0.035]]), np.eye(3)[None], np.array([[0.0, 0.0, 1.0]]), 0.1, lo, 0.01, shape,
                   np.ones(64, np.float32), cells, np.zeros(3, np.int64), facing, 1, 0.0)
    segments_blocked(np.zeros((1, 3)), np.full((1, 3), 0.03), lo, 0.01, shape, np.zeros(64, np.uint8))
