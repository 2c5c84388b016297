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


def back_project(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) depth along the optical axis -> (H, W, 3) float32 points in the optical frame."""
    h, w = depth.shape
    z = np.asarray(depth, dtype=np.float32)
    u = ((np.arange(w, dtype=np.float32) - np.float32(K[0, 2])) / np.float32(K[0, 0]))[None, :]
    v = ((np.arange(h, dtype=np.float32) - np.float32(K[1, 2])) / np.float32(K[1, 1]))[:, None]
    return np.stack([u * z, v * z, z], axis=-1)


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
    rel = np.float32(1.5 / (min(K[0, 0], K[1, 1]) * math.cos(theta)))
    zp = np.pad(z, 1, mode="edge")
    centre = zp[1:-1, 1:-1]
    thresh = rel * centre
    jump = np.zeros(z.shape, dtype=bool)
    for nb in (zp[:-2, 1:-1], zp[2:, 1:-1], zp[1:-1, :-2], zp[1:-1, 2:]):
        with np.errstate(invalid="ignore"):
            jump |= ~(np.abs(nb - centre) <= thresh)  # NaN neighbour counts as a jump

    # Incidence from normals of the back-projected points.
    P = back_project(z, K)
    Pp = np.pad(P, ((1, 1), (1, 1), (0, 0)), mode="edge")
    du = Pp[1:-1, 2:] - Pp[1:-1, :-2]
    dv = Pp[2:, 1:-1] - Pp[:-2, 1:-1]
    n = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_inc = np.abs(np.einsum("hwk,hwk->hw", n, P)) / (np.linalg.norm(n, axis=-1) * np.linalg.norm(P, axis=-1))
        grazing = ~(cos_inc >= np.float32(math.cos(math.radians(max_incidence_deg))))
    return grazing | jump | ~finite
