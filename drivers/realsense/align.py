"""Depth aligned to colour, as librealsense's ``rs2::align`` does it, vectorized: every depth pixel's
footprint (its two corners, at its own depth) is carried into the colour image through the
depth-to-colour extrinsic, and the colour pixels whose centres it covers take its depth along the
colour camera's axis; where two footprints overlap, the nearer surface wins. A footprint covers the centres in [corner0, corner1),
so equal intrinsics and an identity extrinsic map every pixel onto itself, bit for bit.

Distortion follows librealsense's formulas for its models (configs/lens.py)."""

from __future__ import annotations

import numpy as np

from configs import lens
from drivers.realsense.bag_format import StreamModel

#: A footprint wider than this many colour pixels is a surface nearer than any the D435 measures
#: (depth resolution far below colour resolution); its extra pixels are not filled.
MAX_FOOTPRINT_PX = 8


def project(points: np.ndarray, s: StreamModel) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points in the stream's frame -> pixel coordinates (u, v)."""
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = points[:, 0] / z, points[:, 1] / z
    x, y = lens.project(x, y, s.model, s.coeffs)
    K = s.intrinsics
    return x * K.fx + K.cx, y * K.fy + K.cy


def deproject(u: np.ndarray, v: np.ndarray, z: np.ndarray, s: StreamModel) -> np.ndarray:
    """Pixel coordinates and depth along the optical axis -> (N, 3) points in the stream's frame."""
    K = s.intrinsics
    x, y = (u - K.cx) / K.fx, (v - K.cy) / K.fy
    x, y = lens.deproject(x, y, s.model, s.coeffs)
    return np.stack([x * z, y * z, z], axis=1)


def align_depth(raw: np.ndarray, unit_m: float, depth: StreamModel, color: StreamModel) -> np.ndarray:
    """Raw uint16 depth on the depth stream's grid -> raw uint16 depth on the colour grid (0 = no
    return). ``unit_m`` is the metres per depth unit, for the metric extrinsic."""
    raw = np.asarray(raw)
    Kd, Kc = depth.intrinsics, color.intrinsics
    if raw.shape != (Kd.height, Kd.width) or raw.dtype != np.uint16:
        raise ValueError(f"depth image must be ({Kd.height}, {Kd.width}) uint16, got {raw.shape} {raw.dtype}")
    T = color.from_reference() @ np.linalg.inv(depth.from_reference())  # depth -> colour
    if Kd == Kc and not depth.distorted and not color.distorted and np.array_equal(T, np.eye(4)):
        return raw.copy()  # the footprint rule maps every pixel onto itself
    vs, us = np.nonzero(raw)
    z = raw[vs, us].astype(np.float64) * unit_m
    corners = []
    for off in (-0.5, 0.5):
        p = deproject(us + off, vs + off, z, depth)
        p = p @ T[:3, :3].T + T[:3, 3]
        cu, cv = project(p, color)
        corners.append((np.ceil(cu), np.ceil(cv), p[:, 2]))
    (u0, v0, z0), (u1, v1, z1) = corners
    lo_u, hi_u = np.minimum(u0, u1), np.maximum(u0, u1)  # a mirrored extrinsic swaps the corners
    lo_v, hi_v = np.minimum(v0, v1), np.maximum(v0, v1)
    ok = (np.isfinite(lo_u) & np.isfinite(lo_v) & np.isfinite(hi_u) & np.isfinite(hi_v) & (z0 > 0) & (z1 > 0)
          & (lo_u >= 0) & (lo_v >= 0) & (hi_u <= Kc.width) & (hi_v <= Kc.height))
    lo_u, lo_v = lo_u[ok].astype(np.int64), lo_v[ok].astype(np.int64)
    nu = np.minimum(hi_u[ok].astype(np.int64) - lo_u, MAX_FOOTPRINT_PX)
    nv = np.minimum(hi_v[ok].astype(np.int64) - lo_v, MAX_FOOTPRINT_PX)
    # the depth the colour camera sees: z in the colour frame (librealsense carries the depth
    # frame's z, off by x*sin(angle) when the two imagers are not parallel)
    zc = np.rint(0.5 * (z0[ok] + z1[ok]) / unit_m)
    values = np.clip(zc, 1, np.iinfo(np.uint16).max).astype(np.uint32)
    empty = np.iinfo(np.uint32).max  # above every uint16 depth, so 65535 survives
    out = np.full(Kc.height * Kc.width, empty, dtype=np.uint32)
    span_u, span_v = int(nu.max(initial=0)), int(nv.max(initial=0))
    for dv in range(span_v):  # loops over footprint offsets (a few), never over pixels
        for du in range(span_u):
            m = (du < nu) & (dv < nv)
            np.minimum.at(out, (lo_v[m] + dv) * Kc.width + lo_u[m] + du, values[m])
    out[out == empty] = 0
    return out.astype(np.uint16).reshape(Kc.height, Kc.width)
