"""How a piece looks to the twin's camera: metal finishes with texture (rust in patches, mill scale,
galvanized spangle, primer, dirt), marking paints with faded edges and overspray, and light that varies
(level, colour temperature, a shadow across the piece, glints on bare steel).

pybullet's TinyRenderer draws one flat colour per body; it gives the shading and which body each pixel
shows. ``shade`` then paints the colour of each pixel from its 3D point on the piece, so a rust patch
stays where it is from view to view. Real scrap is rarely grey: the cell's paint detection is only
trustworthy if it is tried on these.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class Finish:
    """A metal surface: ``base`` colour with ``patch`` colour over ``share`` of it, in blotches about
    ``scale_m`` across; ``grain`` is the fine brightness variation, ``glint`` the specular strength."""

    base: RGB
    patch: RGB
    share: float
    scale_m: float
    grain: float
    glint: float
    rust: bool = False  # iron oxide (hue 5-30 degrees)


FINISHES: dict[str, Finish] = {
    "grey_steel": Finish((0.42, 0.40, 0.38), (0.36, 0.35, 0.34), 0.30, 0.05, 0.04, 0.35),
    "mill_scale": Finish((0.21, 0.22, 0.24), (0.33, 0.33, 0.34), 0.25, 0.03, 0.05, 0.25),
    "galvanized": Finish((0.64, 0.66, 0.68), (0.55, 0.57, 0.60), 0.50, 0.008, 0.03, 0.50),
    "primer_grey": Finish((0.56, 0.57, 0.56), (0.50, 0.50, 0.50), 0.20, 0.06, 0.02, 0.05),
    "primer_red_oxide": Finish((0.46, 0.17, 0.13), (0.40, 0.16, 0.12), 0.30, 0.05, 0.03, 0.05),
    "dirty_steel": Finish((0.42, 0.40, 0.38), (0.29, 0.26, 0.21), 0.40, 0.04, 0.06, 0.15),
    "rust_patchy": Finish((0.42, 0.40, 0.38), (0.45, 0.22, 0.10), 0.45, 0.04, 0.05, 0.25, rust=True),
    "rust_brown": Finish((0.45, 0.22, 0.10), (0.36, 0.19, 0.10), 0.40, 0.04, 0.06, 0.0, rust=True),
    "rust_red": Finish((0.50, 0.18, 0.10), (0.42, 0.17, 0.11), 0.35, 0.04, 0.06, 0.0, rust=True),
    "rust_orange": Finish((0.62, 0.34, 0.12), (0.48, 0.25, 0.10), 0.40, 0.04, 0.06, 0.0, rust=True),
    "rust_dark": Finish((0.35, 0.20, 0.12), (0.28, 0.17, 0.11), 0.40, 0.04, 0.06, 0.0, rust=True),
}

PAINTS: dict[str, RGB] = {
    "red": (0.85, 0.05, 0.05),
    "orange": (0.95, 0.42, 0.05),
    "pink": (0.95, 0.38, 0.62),
    "white": (0.92, 0.92, 0.90),
    "yellow": (0.93, 0.82, 0.10),
    "green": (0.10, 0.62, 0.22),
    "blue": (0.12, 0.30, 0.78),
}


@dataclass(frozen=True)
class Light:
    """``level`` scales all light (1 = the built-in scenes'), ``white`` is the light's colour as channel
    gains (a colour temperature), ``shadow`` darkens one side of a plane across the piece to this share."""

    level: float = 1.0
    white: RGB = (1.0, 1.0, 1.0)
    shadow: float | None = None


LIGHTS: dict[str, Light] = {
    "dim": Light(0.5),
    "normal": Light(1.0),
    "bright": Light(1.35),
    "warm": Light(1.0, (1.10, 1.0, 0.80)),  # tungsten, about 3200 K
    "cool": Light(1.0, (0.90, 1.0, 1.12)),  # overcast daylight, about 7500 K
    "shadow": Light(1.0, shadow=0.45),
}


@dataclass(frozen=True)
class Appearance:
    """A scene's finish, paint and light by name (``FINISHES``, ``PAINTS``, ``LIGHTS``); ``seed`` places
    the patches, the overspray and the shadow."""

    finish: str = "grey_steel"
    paint: str = "red"
    light: str = "normal"
    seed: int = 0

    def __post_init__(self) -> None:
        for kind, name, table in (("finish", self.finish, FINISHES), ("paint", self.paint, PAINTS),
                                  ("light", self.light, LIGHTS)):
            if name not in table:
                raise ValueError(f"unknown {kind} {name!r}; one of {', '.join(table)}")

    @property
    def metal(self) -> Finish:
        return FINISHES[self.finish]

    @property
    def paint_rgb(self) -> RGB:
        return PAINTS[self.paint]

    @property
    def lighting(self) -> Light:
        return LIGHTS[self.light]

    def mean_metal_rgb(self) -> np.ndarray:
        """The finish's average colour (base and patch by their shares)."""
        f = self.metal
        return (1 - f.share) * np.asarray(f.base) + f.share * np.asarray(f.patch)


LOOK = re.compile(r"^(?:(drawn)|([a-z_]+),([a-z_]+),([a-z_]+)(?:,(\d+))?)$")


def drawn_appearance(key) -> Appearance:
    """An appearance drawn at random (every finish, paint and light equally likely) from its own stream
    ``key`` (a list of ints), so drawing one changes nothing else a generator draws."""
    rng = np.random.default_rng([*map(int, key), 4243])
    return Appearance(str(rng.choice(list(FINISHES))), str(rng.choice(list(PAINTS))), str(rng.choice(list(LIGHTS))),
                      int(rng.integers(0, 1000)))


def split_look(ref: str) -> tuple[str, str | None]:
    """A scene reference and its look: ``t_piece@rust_red,pink,dim[,seed]`` or ``scrap:0:8@drawn`` ->
    (``t_piece``, ``rust_red,pink,dim``); a reference without one -> (ref, None)."""
    base, at, look = ref.rpartition("@")
    if at and base and LOOK.match(look):
        return base, look
    return ref, None


def parse_look(look: str, key) -> Appearance:
    """The appearance a look names; ``drawn``: drawn from the stream ``key``."""
    m = LOOK.match(look)
    if m is None:
        raise ValueError(f"bad look {look!r}: write <finish>,<paint>,<light>[,<seed>] or drawn")
    if m.group(1):
        return drawn_appearance(key)
    return Appearance(m.group(2), m.group(3), m.group(4), int(m.group(5) or 0))


# --- procedural texture --------------------------------------------------------------------------

@nb.njit(cache=True, inline="always")
def _hash01(ix, iy, iz, seed):
    """A reproducible value in [0, 1) per integer lattice point (splitmix64 of the packed coordinates)."""
    h = (np.uint64(ix) * np.uint64(73856093)) ^ (np.uint64(iy) * np.uint64(19349663)) \
        ^ (np.uint64(iz) * np.uint64(83492791)) ^ (np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15))
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    h = h ^ (h >> np.uint64(31))
    return np.float64(h >> np.uint64(11)) / 9007199254740992.0


@nb.njit(cache=True, parallel=True)
def _value_noise(points, inv_scale, seed):
    out = np.empty(points.shape[0])
    for i in nb.prange(points.shape[0]):
        gx = points[i, 0] * inv_scale + 1000.0
        gy = points[i, 1] * inv_scale + 1000.0
        gz = points[i, 2] * inv_scale + 1000.0
        ix, iy, iz = np.floor(gx), np.floor(gy), np.floor(gz)
        fx, fy, fz = gx - ix, gy - iy, gz - iz
        fx, fy, fz = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy), fz * fz * (3 - 2 * fz)
        jx, jy, jz = np.int64(ix), np.int64(iy), np.int64(iz)
        acc = 0.0
        for dx in range(2):
            wx = fx if dx else 1.0 - fx
            for dy in range(2):
                wy = fy if dy else 1.0 - fy
                for dz in range(2):
                    wz = fz if dz else 1.0 - fz
                    acc += wx * wy * wz * _hash01(jx + dx, jy + dy, jz + dz, seed)
        out[i] = acc
    return out


def value_noise(points: np.ndarray, scale_m: float, seed: int) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at (N, 3) points, features about ``scale_m`` across."""
    return _value_noise(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3), 1.0 / scale_m, int(seed))


def _blotches(points: np.ndarray, scale_m: float, seed: int) -> np.ndarray:
    """Two octaves of value noise, in [0, 1]."""
    return 0.7 * value_noise(points, scale_m, seed) + 0.3 * value_noise(points, scale_m / 3.1, seed + 1)


_QUANTILES: dict[float, float] = {}


def _threshold(share: float) -> float:
    """The blotch value above which ``share`` of the surface lies (measured once on random points)."""
    if share not in _QUANTILES:
        pts = np.random.default_rng(7).uniform(0, 50, size=(20000, 3))
        _QUANTILES[share] = float(np.quantile(_blotches(pts, 1.0, 0), 1.0 - share))
    return _QUANTILES[share]


def metal_albedo(points: np.ndarray, finish: Finish, seed: int) -> np.ndarray:
    """(N, 3) colour in [0, 1] of the finish at the points."""
    b = _blotches(points, finish.scale_m, seed)
    t = _threshold(finish.share) if 0 < finish.share < 1 else (2.0 if finish.share <= 0 else -1.0)
    w = np.clip((b - t) / 0.04 + 0.5, 0.0, 1.0)[:, None]  # soft patch edge
    rgb = (1 - w) * np.asarray(finish.base) + w * np.asarray(finish.patch)
    grain = 1.0 + finish.grain * (2.0 * value_noise(points, 0.002, seed + 2) - 1.0)
    return np.clip(rgb * grain[:, None], 0.0, 1.0)


# --- the shading pass ----------------------------------------------------------------------------

@dataclass
class Painter:
    """Colours a TinyRenderer frame of a scene with its ``Appearance``. Built once per twin camera."""

    appearance: Appearance
    lines: list[np.ndarray]  # the drawing's polylines, base frame
    width_m: float
    object_rgb: RGB  # the flat colours pybullet drew, to read the shading back out
    paint_flat_rgb: RGB
    paint_mesh: object = None  # trimesh.Trimesh of the painted faces: overspray lands only on faces turned as they are

    def __post_init__(self) -> None:
        dense = [_resample(np.asarray(l, dtype=np.float64), 0.001) for l in self.lines if len(l) >= 2]
        self._tree = cKDTree(np.vstack(dense)) if dense else None
        self._line_normals = None  # per dense line point: the painted face's normal there (the spray's side)
        m = self.paint_mesh
        if dense and m is not None and len(getattr(m, "faces", ())):
            _, face = cKDTree(m.triangles_center).query(np.vstack(dense), workers=-1)
            self._line_normals = np.asarray(m.face_normals)[face]
        rng = np.random.default_rng(self.appearance.seed + 11)
        pts = np.vstack(dense) if dense else np.zeros((1, 3))
        d = rng.normal(size=3)
        d[2] = 0.0
        self._shadow_normal = d / (np.linalg.norm(d) or 1.0)
        self._shadow_origin = pts.mean(axis=0) + self._shadow_normal * rng.uniform(-0.03, 0.03)

    def shade(self, color: np.ndarray, depth: np.ndarray, seg: np.ndarray, K: np.ndarray, T_base_cam: np.ndarray,
              ids: dict[str, int | None], light_dir: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The frame's colour (H, W, 3) uint8 from the flat render ``color``, its depth (m, NaN: none),
        its segmentation ``seg`` (pybullet body ids) and the camera."""
        a = self.appearance
        light = a.lighting
        H, W = depth.shape
        rgb = color.reshape(-1, 3).astype(np.float32) * np.float32(1.0 / 255.0)
        seg = seg.reshape(-1)
        on_obj = seg == (ids.get("object") if ids.get("object") is not None else -99)
        on_paint = seg == (ids.get("paint") if ids.get("paint") is not None else -99)
        piece = (on_obj | on_paint) & np.isfinite(depth.reshape(-1))
        out = rgb.copy()
        if piece.any():
            idx = np.flatnonzero(piece)
            P_cam = _backproject(depth, K, idx)
            P = P_cam @ T_base_cam[:3, :3].T + T_base_cam[:3, 3]
            flat = np.where(on_paint[idx, None], np.asarray(self.paint_flat_rgb), np.asarray(self.object_rgb))
            shading = rgb[idx].max(axis=1) / np.maximum(flat.max(axis=1), 1e-3)  # what pybullet's light gave
            albedo = metal_albedo(P, a.metal, a.seed)
            alpha = self._paint_alpha(P, on_paint[idx], rng, depth, K, idx, T_base_cam)
            paint = np.asarray(a.paint_rgb) * (1.0 + 0.03 * (2.0 * value_noise(P, 0.003, a.seed + 5) - 1.0))[:, None]
            albedo = (1.0 - alpha[:, None]) * albedo + alpha[:, None] * np.clip(paint, 0, 1)
            lit = albedo * shading[:, None]
            glint = a.metal.glint * (1.0 - alpha)
            if glint.max() > 0:
                n = _normals(depth, K, idx) @ T_base_cam[:3, :3].T
                view = T_base_cam[:3, 3] - P
                view /= np.linalg.norm(view, axis=1, keepdims=True)
                h = view + light_dir / np.linalg.norm(light_dir)
                h /= np.linalg.norm(h, axis=1, keepdims=True)
                spec = np.abs(np.einsum("ij,ij->i", n, h)) ** 60  # a sharp highlight on bare steel
                lit = lit + (glint * spec)[:, None]
            if light.shadow is not None:
                dark = (P - self._shadow_origin) @ self._shadow_normal > 0.0
                lit[dark] *= light.shadow
            out[idx] = lit
        out *= (light.level * np.asarray(light.white)).astype(np.float32)
        out += rng.standard_normal(size=out.shape, dtype=np.float32) * np.float32(1.5 / 255.0)  # the sensor's colour noise
        return (np.clip(out, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).reshape(H, W, 3)

    def _paint_alpha(self, P: np.ndarray, on_paint: np.ndarray, rng: np.random.Generator, depth=None, K=None,
                     idx=None, T_base_cam=None) -> np.ndarray:
        """How much paint covers each point: full in the stroke's core, fading at its edge, speckles of
        overspray beyond it, on faces turned the way the painted face is (no spray through a plate onto
        its back, nor onto a face turned from the can)."""
        alpha = on_paint.astype(np.float64)
        if self._tree is None:
            return alpha
        hw = 0.5 * self.width_m
        d, _ = self._tree.query(P, distance_upper_bound=2.0 * hw, workers=-1)
        d = np.where(np.isfinite(d), d, np.inf)
        edge = on_paint & (d > 0.7 * hw)
        alpha[edge] = 1.0 - 0.4 * np.clip((d[edge] - 0.7 * hw) / (0.3 * hw), 0.0, 1.0)  # faded edge
        near = ~on_paint & (d < 1.6 * hw)
        if near.any() and self._line_normals is not None and depth is not None:
            k = np.flatnonzero(near)
            _, j = self._tree.query(P[k], workers=-1)
            n = _normals(depth, K, idx[k]) @ np.asarray(T_base_cam)[:3, :3].T
            n *= np.sign(np.einsum("ij,ij->i", n, np.asarray(T_base_cam)[:3, 3] - P[k]))[:, None]  # a seen face faces the camera
            facing = np.einsum("ij,ij->i", n, self._line_normals[j]) > 0.7
            near[k[~facing]] = False
        if near.any():
            speck = value_noise(P[near], 0.0015, self.appearance.seed + 9)
            keep = speck > 0.55 + 0.4 * np.clip((d[near] - hw) / (0.6 * hw), 0.0, 1.0)  # sparser farther out
            alpha[np.flatnonzero(near)[keep]] = 0.8
        return alpha


def _resample(line: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step)) + 1))
    return np.column_stack([np.interp(t, s, line[:, k]) for k in range(3)])


def _backproject(depth: np.ndarray, K: np.ndarray, idx: np.ndarray) -> np.ndarray:
    H, W = depth.shape
    v, u = np.divmod(idx, W)
    z = depth.reshape(-1)[idx].astype(np.float64)
    return np.column_stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])


def _normals(depth: np.ndarray, K: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit normals (camera frame) at the pixels ``idx`` from their neighbours in the depth image."""
    H, W = depth.shape
    v, u = np.divmod(idx, W)

    def at(du: int, dv: int) -> np.ndarray:
        return _backproject(depth, K, np.clip(v + dv, 0, H - 1) * W + np.clip(u + du, 0, W - 1))

    n = np.cross(at(1, 0) - at(-1, 0), at(0, 1) - at(0, -1))
    n = np.nan_to_num(n)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
