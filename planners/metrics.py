"""The paper's benchmarking metrics (§VI-C): coverage (eq. 13) and displacement (eq. 12)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planners.clouds import voxel_keys


@dataclass
class Coverage:
    hit: int
    total: int

    @property
    def fraction(self) -> float:
        return self.hit / self.total if self.total else 0.0

    @property
    def percent(self) -> float:
        return 100.0 * self.fraction


def coverage(reconstruction: np.ndarray, ground_truth: np.ndarray, voxel: float) -> Coverage:
    """card(vox(C) ∩ vox(G)) / card(vox(G)) on one common grid anchored at the base-frame origin."""
    if len(ground_truth) == 0:
        raise ValueError("ground truth cloud is empty: coverage is undefined")
    g = np.unique(voxel_keys(np.asarray(ground_truth, dtype=np.float64), voxel))
    if len(reconstruction) == 0:
        return Coverage(0, len(g))
    c = np.unique(voxel_keys(np.asarray(reconstruction, dtype=np.float64), voxel))
    return Coverage(int(np.isin(g, c, assume_unique=True).sum()), len(g))


def displacement(positions: np.ndarray) -> float:
    """Eq. 12: summed straight-line distance between consecutive viewpoints, initial one included."""
    p = np.asarray(positions, dtype=np.float64)
    if len(p) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def dense_polylines(polylines: list[np.ndarray], step: float) -> np.ndarray:
    """Points every ``step`` along each polyline (ends kept), stacked (M,3)."""
    out = []
    for p in polylines:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        if len(p) == 1:
            out.append(p)
            continue
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        t = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / step)), 1) + 1)
        out.append(np.column_stack([np.interp(t, s, p[:, k]) for k in range(3)]))
    return np.vstack(out) if out else np.zeros((0, 3))


FRAGMENT_M = 0.02  # a cut shorter than this is a fragment, a pierce for a stub, unless its paint is as short


def _line_pieces(true_polylines: list[np.ndarray], step_m: float, painted: np.ndarray | None,
                 on_metal_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(the true line's samples on metal (M,3), the length of the unbroken piece of paint each lies in
    (M,)): a line over a grid's bars is a piece per bar; a dashed line a piece per dash. A piece's samples
    reach ``on_metal_m`` beyond its paint at each end: not counted in its length."""
    from scipy.spatial import cKDTree

    tree = cKDTree(np.asarray(painted, dtype=np.float64)) if painted is not None and len(painted) else None
    pts, lengths = [], []
    for poly in true_polylines:  # a handful of strokes
        line = dense_polylines([poly], step_m)
        on = np.ones(len(line), bool) if tree is None else tree.query(line)[0] <= on_metal_m
        run = np.cumsum(np.concatenate([[1], np.diff(on.astype(np.int8)) != 0]))  # one label per run
        size = np.bincount(run)[run] * step_m - (0.0 if tree is None else 2.0 * on_metal_m)  # the margin off
        pts.append(line[on])
        lengths.append(size[on])
    return (np.vstack(pts), np.concatenate(lengths)) if pts else (np.zeros((0, 3)), np.zeros(0))


def cut_accuracy(true_polylines: list[np.ndarray], cuts: list[np.ndarray], tolerance_m: float = 0.005,
                 step_m: float = 0.001, painted: np.ndarray | None = None, on_metal_m: float = 0.003,
                 fragment_m: float = FRAGMENT_M) -> dict:
    """The planned cuts against the painted line's true centerline (the twin knows it).

    cut_coverage: share of the true centerline within ``tolerance_m`` of a cut; path_to_line: how
    far the cuts stray from the line (mean, max; what the torch would get wrong); line_to_path: how
    far the line is from the nearest cut (max includes uncut gaps); cuts against strokes. Both
    curves are sampled every ``step_m``, so distances are exact to half of it. ``painted``: samples
    of the painted surface; then only the line where it lies on metal (within ``on_metal_m`` of the
    paint) counts: where a line crosses the air between the bars of a basket there is nothing to cut.
    fragments: cuts shorter than ``fragment_m`` along a piece of the line (on metal, unbroken) that is
    longer: a pierce for a stub; a cut over a bar the paint crosses in 16 mm is whole, not a fragment."""
    from scipy.spatial import cKDTree

    line, piece = _line_pieces(true_polylines, step_m, painted, on_metal_m)
    if len(line) == 0:
        raise ValueError("the true drawing has no polyline (on metal): cut accuracy is undefined")
    out = {"strokes": len(true_polylines), "cuts": len(cuts), "line_on_metal_m": round(step_m * len(line), 4),
           "cut_coverage": 0.0, "path_to_line_mean_mm": None,
           "path_to_line_max_mm": None, "line_to_path_mean_mm": None, "line_to_path_max_mm": None,
           "fragments": 0}
    path = dense_polylines(cuts, step_m)
    if len(path) == 0:
        return out
    tree = cKDTree(line)
    for c in cuts:  # a handful of cuts: one shorter than fragment_m is a fragment unless its paint is as short
        c = np.asarray(c, dtype=np.float64).reshape(-1, 3)
        if len(c) and np.linalg.norm(np.diff(c, axis=0), axis=1).sum() < fragment_m:
            near = tree.query_ball_point(dense_polylines([c], step_m), tolerance_m)
            on = np.unique(np.concatenate([np.asarray(n, dtype=np.int64) for n in near]))
            out["fragments"] += int(not len(on) or piece[on].max() > fragment_m)
    d_line, _ = cKDTree(path).query(line)
    d_path, _ = tree.query(path)
    out.update(cut_coverage=round(float(np.mean(d_line <= tolerance_m)), 4),
               path_to_line_mean_mm=round(1e3 * float(d_path.mean()), 3),
               path_to_line_max_mm=round(1e3 * float(d_path.max()), 3),
               line_to_path_mean_mm=round(1e3 * float(d_line.mean()), 3),
               line_to_path_max_mm=round(1e3 * float(d_line.max()), 3))
    return out
