"""The D435 depth model of the twin as pure numpy functions: intrinsics, the datasheet RMS error,
per-pixel Gaussian depth noise and the invalidation of grazing and discontinuous pixels.

Pixel coordinates follow planners/clouds.py: pixel (u, v) = (column, row) has its centre at the
integer coordinates, so the image centre is ((W-1)/2, (H-1)/2)."""

from __future__ import annotations

import math

import numpy as np

from drivers.interfaces import Intrinsics
from sim.config import D435Config


def intrinsics_for(cfg: D435Config) -> Intrinsics:
    """Pinhole intrinsics of the colour-aligned depth image: fx from the horizontal FOV, fy from the
    vertical FOV, principal point at the image centre."""
    fx = 0.5 * cfg.width / math.tan(math.radians(cfg.hfov_deg) / 2.0)
    fy = 0.5 * cfg.height / math.tan(math.radians(cfg.vfov_deg) / 2.0)
    return Intrinsics(width=cfg.width, height=cfg.height, fx=fx, fy=fy,
                      cx=(cfg.width - 1) / 2.0, cy=(cfg.height - 1) / 2.0)


def depth_focal_px(cfg: D435Config) -> float:
    """Focal length (pixels) of the depth imager at ``cfg.width`` from its horizontal FOV."""
    return 0.5 * cfg.width / math.tan(math.radians(cfg.depth_hfov_deg) / 2.0)


def depth_rms(z: np.ndarray | float, cfg: D435Config) -> np.ndarray | float:
    """Intel D400 datasheet RMS depth error (metres) at depth ``z`` (metres):
    z^2 * subpixel / (focal_px * baseline)."""
    return np.square(z) * (cfg.subpixel / (depth_focal_px(cfg) * cfg.baseline_m))


def apply_depth_noise(depth: np.ndarray, cfg: D435Config, rng: np.random.Generator) -> np.ndarray:
    """Return a float32 copy of ``depth`` with zero-mean Gaussian noise of std ``depth_rms(z)`` added
    independently per pixel. NaN stays NaN. Draws from ``rng`` (advancing it) only when
    ``cfg.noise`` is set."""
    depth = np.asarray(depth, dtype=np.float32)
    if not cfg.noise:
        return depth.copy()
    sigma = depth_rms(depth, cfg).astype(np.float32)
    return (depth + rng.standard_normal(depth.shape, dtype=np.float32) * sigma).astype(np.float32)


def grazing_mask(depth: np.ndarray, K: np.ndarray, max_incidence_deg: float) -> np.ndarray:
    """Pixels a D435 would not return: True where the viewing ray meets the surface more obliquely
    than ``max_incidence_deg``, at depth discontinuities (a 4-neighbour jumps further than a surface
    at that incidence could, or has no return), and where ``depth`` itself is not finite.

    ``depth`` is the noise-free (H, W) depth along the optical axis, NaN = nothing hit. Normals come
    from the cross product of central differences of the back-projected points (one-sided at the
    image border)."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be a 2-D image, got shape {depth.shape}")
    finite = np.isfinite(depth) & (depth > 0)
    z = np.where(finite, depth, np.float32(np.nan))

    # Discontinuities. A plane at incidence theta changes depth between neighbouring pixels by at
    # most z / (f cos theta); a bigger jump (with a 1.5x margin) is an edge between two surfaces.
    theta = math.radians(min(max_incidence_deg, 85.0))
    thresh = np.float32(1.5 / (min(K[0, 0], K[1, 1]) * math.cos(theta))) * z
    zp = np.pad(z, 1, mode="edge")
    invalid = ~finite
    with np.errstate(invalid="ignore"):
        for nb in (zp[:-2, 1:-1], zp[2:, 1:-1], zp[1:-1, :-2], zp[1:-1, 2:]):
            invalid |= ~(np.abs(nb - z) <= thresh)  # a NaN neighbour counts as a jump

    # Incidence: normals from central differences of the back-projected points P = z (a_u, b_v, 1);
    # edge padding of z, a and b makes them one-sided at the image border.
    h, w = z.shape
    a = np.pad((np.arange(w, dtype=np.float32) - np.float32(K[0, 2])) / np.float32(K[0, 0]), 1, mode="edge")
    b = np.pad((np.arange(h, dtype=np.float32) - np.float32(K[1, 2])) / np.float32(K[1, 1]), 1, mode="edge")
    Xp = zp * a[None, :]
    Yp = zp * b[:, None]
    dux, duy, duz = (A[1:-1, 2:] - A[1:-1, :-2] for A in (Xp, Yp, zp))
    dvx, dvy, dvz = (A[2:, 1:-1] - A[:-2, 1:-1] for A in (Xp, Yp, zp))
    nx = duy * dvz - duz * dvy
    ny = duz * dvx - dux * dvz
    nz = dux * dvy - duy * dvx
    X, Y = Xp[1:-1, 1:-1], Yp[1:-1, 1:-1]
    dot = nx * X + ny * Y + nz * z
    cos_max = np.float32(math.cos(math.radians(max_incidence_deg)))
    with np.errstate(invalid="ignore", over="ignore"):
        # cos(incidence) >= cos_max  <=>  dot^2 >= cos_max^2 |n|^2 |P|^2  (NaN compares False)
        ok = dot * dot >= (cos_max * cos_max) * (nx * nx + ny * ny + nz * nz) * (X * X + Y * Y + z * z)
    return invalid | ~ok
