"""Run folders: result.json plus the clouds as PLY, written so a crash mid-way keeps what exists."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from planners.clouds import Cloud


def new_run_dir(root: str | Path, scene: str, planner: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    safe_scene = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in Path(scene).stem)
    base = Path(root) / f"{stamp}-{safe_scene}-{planner}"
    path, n = base, 1
    while path.exists():
        n += 1
        path = base.with_name(f"{base.name}-{n}")
    path.mkdir(parents=True)
    return path


def write_json(path: Path, data: dict) -> None:
    """Atomic: write a sibling temp file, then rename over."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=_default))
    os.replace(tmp, path)


def _default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def write_ply(path: Path, cloud: Cloud) -> None:
    """Binary PLY, float32 positions (metres; 0.1 um steps at the cell's range) and uint8 colours: 15
    bytes a point, not the 27 of doubles."""
    import open3d as o3d  # heavy import, only where clouds are written

    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(np.ascontiguousarray(cloud.xyz, dtype=np.float32))
    pc.point.colors = o3d.core.Tensor(np.ascontiguousarray(cloud.rgb, dtype=np.uint8))
    if not o3d.t.io.write_point_cloud(str(path), pc, write_ascii=False):
        raise OSError(f"could not write {path}")


def save_png(path: Path, rgb: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(path, rgb)


def paint_overlay(rgb: np.ndarray, paint: np.ndarray) -> np.ndarray:
    """The camera image with what the cell took as paint in cyan over the rest in dim grey: what an
    operator checks when a piece is refused (or a cut looks wrong)."""
    grey = rgb.astype(np.float32).mean(axis=2, keepdims=True) * 0.45
    out = np.repeat(grey, 3, axis=2)
    out[paint] = 0.3 * rgb[paint] + 0.7 * np.array([0.0, 255.0, 255.0])
    return out.clip(0, 255).astype(np.uint8)
