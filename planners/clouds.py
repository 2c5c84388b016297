"""Cloud processing of the paper's §IV-B: back-projection, base-frame transform, voxel-deduplicated
accumulation (C_total) and the colour filter ξ that yields the drawing cloud (D_total)."""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from configs.lens import deproject


@dataclass
class Cloud:
    """Points (N,3) float32 with colours (N,3) uint8 and the sensor position that saw each point
    (N,3) float32, which orients normals; never Python lists."""

    xyz: np.ndarray
    rgb: np.ndarray
    origin: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.origin is None:
            self.origin = np.full(self.xyz.shape, np.nan, np.float32)

    @staticmethod
    def empty() -> "Cloud":
        return Cloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.float32))

    def __len__(self) -> int:
        return len(self.xyz)

    def select(self, mask: np.ndarray) -> "Cloud":
        return Cloud(self.xyz[mask], self.rgb[mask], self.origin[mask])


def depth_to_camera_points(depth: np.ndarray, K: np.ndarray, stride: int = 1,
                           lens: tuple[str, tuple[float, ...]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Back-project valid depth pixels into the optical frame. Returns (points (N,3) float32,
    flat pixel indices (N,) into the full image). Non-finite and non-positive depths are no return.
    ``lens``: the camera's (distortion model, coefficients) (``Intrinsics.lens``); None for a pinhole."""
    if depth.ndim != 2:
        raise ValueError(f"depth must be a 2-D image, got shape {depth.shape}")
    h, w = depth.shape
    vs, us = np.mgrid[0:h:stride, 0:w:stride]
    z = depth[vs, us]
    ok = np.isfinite(z) & (z > 0)
    z = z[ok].astype(np.float32)
    u = us[ok].astype(np.float32)
    v = vs[ok].astype(np.float32)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x, y = (u - cx) / fx, (v - cy) / fy
    if lens is not None:
        x, y = deproject(x.astype(np.float64), y.astype(np.float64), *lens)
    pts = np.stack([x * z, y * z, z], axis=1).astype(np.float32)
    return pts, (vs[ok] * w + us[ok]).astype(np.int64)


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N,3) points, keeping float32."""
    return (pts @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)).astype(np.float32)


def frame_to_base_cloud(color: np.ndarray, depth: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray,
                        stride: int = 1, pixels: bool = False, lens: tuple[str, tuple[float, ...]] | None = None):
    """The paper's ^bT_k ^cC_k: one frame's coloured cloud in the base frame; with `pixels`, also
    the flat pixel index of each point, so a sparser set of the same frame's rays is a selection
    (`on_stride`), not a second back-projection."""
    if not np.all(np.isfinite(T_base_cam)):
        raise ValueError("camera pose contains NaN/inf")
    pts, idx = depth_to_camera_points(depth, K, stride, lens)
    rgb = color.reshape(-1, 3)[idx]
    origin = np.broadcast_to(T_base_cam[:3, 3].astype(np.float32), pts.shape)
    cloud = Cloud(transform_points(T_base_cam, pts), rgb, origin)
    return (cloud, idx) if pixels else cloud


def on_stride(pixels: np.ndarray, width: int, stride: int) -> np.ndarray:
    """Mask of the points whose pixel lies on every `stride`-th row and column: the points
    `frame_to_base_cloud(..., stride)` would return."""
    return ((pixels // width) % stride == 0) & ((pixels % width) % stride == 0)


def voxel_keys(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """Integer voxel coordinates packed into one int64 key (21 bits per axis, ±10 km at 1 mm)."""
    ijk = np.floor(xyz / voxel).astype(np.int64) + (1 << 20)
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def voxel_dedup(cloud: Cloud, voxel: float) -> Cloud:
    """Keep the first point per voxel so repeated views do not grow the cloud without bound."""
    if len(cloud) == 0:
        return cloud
    _, first = np.unique(voxel_keys(cloud.xyz, voxel), return_index=True)
    return cloud.select(np.sort(first))


def concatenate(total: Cloud, new: Cloud, voxel: float) -> Cloud:
    """Eq. (1): C_total,k = C_total,k-1 ∪ C_k, voxel de-duplicated (old points win)."""
    merged = Cloud(np.concatenate([total.xyz, new.xyz]), np.concatenate([total.rgb, new.rgb]),
                   np.concatenate([total.origin, new.origin]))
    return voxel_dedup(merged, voxel)


class CloudTotal:
    """C_total (or D_total) of eq. 1 kept with its voxel keys sorted: adding a view sorts only the
    view's points and looks them up in the total, instead of re-sorting the whole accumulated cloud
    every step (it grows to most of a million points). Same points, same order as `concatenate`."""

    def __init__(self, voxel: float):
        self.voxel = float(voxel)
        self.cloud = Cloud.empty()
        self._keys = np.zeros(0, dtype=np.int64)  # sorted, one per voxel of `cloud`

    def add(self, new: Cloud) -> Cloud:
        """C_total ∪ new, voxel de-duplicated (old points win, then the first new one per voxel)."""
        if len(new) == 0:
            return self.cloud
        keys, first = np.unique(voxel_keys(new.xyz, self.voxel), return_index=True)
        at = np.searchsorted(self._keys, keys)
        known = np.zeros(len(keys), dtype=bool)
        inside = at < len(self._keys)
        known[inside] = self._keys[at[inside]] == keys[inside]
        fresh = ~known
        self._keys = np.insert(self._keys, at[fresh], keys[fresh])
        add = new.select(np.sort(first[fresh]))
        c = self.cloud
        self.cloud = Cloud(np.concatenate([c.xyz, add.xyz]), np.concatenate([c.rgb, add.rgb]),
                           np.concatenate([c.origin, add.origin]))
        return self.cloud


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """uint8 RGB (N,3) -> HSV with H in degrees [0,360), S and V in [0,1]."""
    c = rgb.astype(np.float32) / 255.0
    r, g, b = c[:, 0], c[:, 1], c[:, 2]
    mx = c.max(axis=1)
    mn = c.min(axis=1)
    d = mx - mn
    h = np.zeros_like(mx)
    nz = d > 1e-6
    rm = nz & (mx == r)
    gm = nz & (mx == g) & ~rm
    bm = nz & ~rm & ~gm
    h[rm] = (60.0 * ((g[rm] - b[rm]) / d[rm])) % 360.0
    h[gm] = 60.0 * ((b[gm] - r[gm]) / d[gm]) + 120.0
    h[bm] = 60.0 * ((r[bm] - g[bm]) / d[bm]) + 240.0
    s = np.where(mx > 1e-6, d / np.maximum(mx, 1e-6), 0.0)
    return np.stack([h, s, mx], axis=1)


def color_mask(rgb: np.ndarray, hue_center_deg: float, hue_halfwidth_deg: float, s_min: float, v_min: float) -> np.ndarray:
    """The filter ξ: an admissible HSV range (hue wraps around 360); `rgb_to_hsv`'s arithmetic per
    pixel in one compiled pass (a D435 frame is 400 k pixels, every view)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8).reshape(-1, 3)
    return _color_mask(rgb, np.float32(hue_center_deg), np.float32(hue_halfwidth_deg), np.float32(s_min),
                       np.float32(v_min))


@nb.njit(cache=True, parallel=True)
def _color_mask(rgb, hue_center, halfwidth, s_min, v_min):
    n = rgb.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for i in nb.prange(n):
        r = np.float32(rgb[i, 0]) / np.float32(255.0)
        g = np.float32(rgb[i, 1]) / np.float32(255.0)
        b = np.float32(rgb[i, 2]) / np.float32(255.0)
        mx = max(r, g, b)
        mn = min(r, g, b)
        d = mx - mn
        h = np.float32(0.0)
        if d > 1e-6:
            if mx == r:
                h = (np.float32(60.0) * ((g - b) / d)) % np.float32(360.0)
            elif mx == g:
                h = np.float32(60.0) * ((b - r) / d) + np.float32(120.0)
            else:
                h = np.float32(60.0) * ((r - g) / d) + np.float32(240.0)
        s = d / max(mx, np.float32(1e-6)) if mx > 1e-6 else np.float32(0.0)
        dh = abs((h - hue_center + np.float32(180.0)) % np.float32(360.0) - np.float32(180.0))
        out[i] = (dh <= halfwidth) and (s >= s_min) and (mx >= v_min)
    return out


def warmup() -> None:
    """Compile (or load from numba's cache) the colour filter before the first timed step."""
    color_mask(np.zeros((1, 3), np.uint8), 0.0, 20.0, 0.5, 0.15)
