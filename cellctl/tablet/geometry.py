"""A finished job's 3-D picture for the tablet: the scanned surface (thinned), the drawing and the cut
with its torch axes, fetched through the job API's files keys (as any client would) and cached by SHA-256."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from cellctl.service.client import CellClient
from planners.clouds import voxel_keys

FILES = ("cut_path.json", "drawing.ply", "surface.ply")
PAINT_PICTURE = re.compile(r"^paint_(?:view(\d+)|check)\.png$")
TORCH_AXES = 24  # torch axes drawn along all cuts together: enough to read the tilt, few enough to read at all
TORCH_LEN_M = 0.05


@dataclass
class JobGeometry:
    surface: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (N,3) m, robot base
    surface_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (N,3) 0..1
    drawing: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    cuts: list[np.ndarray] = field(default_factory=list)  # one (K,3) polyline per runnable cut
    blocked: list[np.ndarray] = field(default_factory=list)  # planned runs the arm cannot follow
    gaps: list[np.ndarray] = field(default_factory=list)  # uncut stretches
    torches: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (tip, tip + axis * len)
    missing: list[str] = field(default_factory=list)  # files the job does not have

    def frame(self) -> tuple[np.ndarray, float]:
        """Centre and radius that frame the drawing and the cut (the surface if there is neither)."""
        pts = [self.drawing, *self.cuts, *self.gaps]
        pts = [p for p in pts if len(p)] or [self.surface]
        allp = np.concatenate(pts) if any(len(p) for p in pts) else np.zeros((1, 3))
        lo, hi = allp.min(0), allp.max(0)
        return (lo + hi) / 2, float(max(0.1, np.linalg.norm(hi - lo) / 2))


def thin(xyz: np.ndarray, n_max: int, *extra: np.ndarray) -> tuple[np.ndarray, ...]:
    """At most ``n_max`` points, one per voxel of a grid made coarser until they fit: an even spread,
    unlike a random subset that keeps the dense near side and loses the far one."""
    if len(xyz) <= n_max:
        return (xyz, *extra)
    lo, hi = xyz.min(0), xyz.max(0)
    voxel = max(float(np.max(hi - lo)) / np.sqrt(n_max), 1e-4)  # a surface: points ~ (extent / voxel)^2
    while True:
        _, keep = np.unique(voxel_keys(xyz - lo, voxel), return_index=True)
        if len(keep) <= n_max:
            keep.sort()
            return (xyz[keep], *(e[keep] for e in extra))
        voxel *= 1.25


def fetch(client: CellClient, job_id: str, cache: Path, names=FILES) -> dict[str, Path]:
    """The job's files of ``names`` (default: its 3-D files; a callable picks them from the job's list) in
    ``cache``, fetched once, and again only if the cell's copy changed."""
    cache.mkdir(parents=True, exist_ok=True)
    have = {f.name: f for f in client.files(job_id).files}
    if callable(names):
        names = [n for n in have if names(n)]
    out = {}
    for name in names:
        if name not in have:
            continue
        dest, stamp = cache / name, cache / f"{name}.sha256"
        if not (dest.is_file() and stamp.is_file() and stamp.read_text() == have[name].sha256):
            client.fetch(job_id, name, dest)
            stamp.write_text(have[name].sha256)
        out[name] = dest
    return out


def paint_pictures(client: CellClient, job_id: str, cache: Path) -> list[tuple[str, Path]]:
    """Each view's picture with what it took as paint (paint_view<k>.png, in view order), and the check's
    picture of a refused piece (paint_check.png) when the job has no view of its own: (caption, file)."""
    files = fetch(client, job_id, cache, lambda n: PAINT_PICTURE.match(n) is not None)
    views = sorted((int(m.group(1)), f) for n, f in files.items() if (m := PAINT_PICTURE.match(n)) and m.group(1))
    out = [(f"View {k + 1}", f) for k, f in views]
    if not out and "paint_check.png" in files:
        out.append(("The first view", files["paint_check.png"]))
    return out


def _cloud(path: Path | None) -> tuple[np.ndarray, np.ndarray]:
    if path is None:
        return np.zeros((0, 3)), np.zeros((0, 3))
    pc = trimesh.load(path, file_type="ply")
    xyz = np.asarray(pc.vertices, dtype=np.float64)
    rgb = np.asarray(pc.colors[:, :3], dtype=np.float64) / 255 if getattr(pc, "colors", None) is not None \
        and len(pc.colors) == len(xyz) else np.full((len(xyz), 3), 0.6)
    return xyz, rgb


def load(files: dict[str, Path], max_points: int) -> JobGeometry:
    """The picture; the surface is cropped to a sphere round the drawing and the cut (1.5 times the
    radius that frames them), so the table and the floor do not fill the view."""
    g = JobGeometry(missing=[n for n in FILES if n not in files])
    g.drawing = thin(_cloud(files.get("drawing.ply"))[0], max(100, max_points // 4))[0]
    if "cut_path.json" in files:
        cut = json.loads(files["cut_path.json"].read_text())
        tips, axes = [], []
        for b in cut.get("branches", []):
            pts = np.asarray(b.get("points") or [], dtype=np.float64).reshape(-1, 3)
            (g.cuts if b.get("feasible") else g.blocked).append(pts)
            if b.get("feasible") and b.get("normals"):
                tips.append(pts)
                axes.append(np.asarray(b["normals"], dtype=np.float64).reshape(-1, 3))
        g.gaps = [np.asarray(x["points"], dtype=np.float64).reshape(-1, 3) for x in cut.get("gaps", [])
                  if x.get("points") and float(x.get("length_m", 0)) > 0]
        if tips:
            tip, axis = np.concatenate(tips), np.concatenate(axes)
            pick = np.unique(np.linspace(0, len(tip) - 1, min(TORCH_AXES, len(tip))).round().astype(int))
            g.torches = [(tip[i], tip[i] + TORCH_LEN_M * axis[i]) for i in pick]
    xyz, rgb = _cloud(files.get("surface.ply"))
    if len(g.drawing) or g.cuts or g.gaps:
        centre, radius = g.frame()
        near = np.linalg.norm(xyz - centre, axis=1) <= 1.5 * radius
        xyz, rgb = xyz[near], rgb[near]
    g.surface, g.surface_rgb = thin(xyz, max_points, rgb)
    return g
