"""Pictures of a scan: viewpoints and covered/missed ground-truth voxels (the paper's Table III)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from planners.clouds import voxel_keys


def _frame(ax, mid: np.ndarray, r: float, elev: float, azim: float, legend: bool) -> None:
    """A cube of half side r about mid, seen from (elev, azim), axes named; the legend on one view."""
    ax.set_xlim(mid[0] - r, mid[0] + r)
    ax.set_ylim(mid[1] - r, mid[1] + r)
    ax.set_zlim(mid[2] - r, mid[2] + r)
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if legend:
        ax.legend(loc="upper left", fontsize=7)


def _save(fig, path: str | Path, title: str) -> None:
    import matplotlib.pyplot as plt

    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def coverage_figure(path: str | Path, gt: np.ndarray, recon: np.ndarray, viewpoints: np.ndarray, voxel: float,
                    surface: np.ndarray | None = None, title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys_gt = voxel_keys(gt.astype(np.float64), voxel)
    uniq, first = np.unique(keys_gt, return_index=True)
    centers = (np.floor(gt[first] / voxel) + 0.5) * voxel
    hit = np.isin(uniq, voxel_keys(recon.astype(np.float64), voxel)) if len(recon) else np.zeros(len(uniq), bool)
    vp = np.asarray(viewpoints).reshape(-1, 3)
    fig = plt.figure(figsize=(12, 4.2))
    for i, (elev, azim) in enumerate([(90, -90), (20, -60), (20, 120)]):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        if surface is not None and len(surface):
            s = surface[:: max(1, len(surface) // 4000)]
            ax.scatter(s[:, 0], s[:, 1], s[:, 2], s=0.3, c="0.75", alpha=0.4)
        ax.scatter(*centers[hit].T, s=4, c="tab:green", label=f"covered {hit.sum()}")
        ax.scatter(*centers[~hit].T, s=6, c="tab:red", label=f"missed {(~hit).sum()}")
        if len(vp):
            ax.plot(vp[:, 0], vp[:, 1], vp[:, 2], "-o", c="magenta", ms=3, lw=1)
            ax.text(*vp[0], "0", fontsize=7)
        allp = np.vstack([centers, vp]) if len(vp) else centers
        mid = (allp.max(0) + allp.min(0)) / 2
        r = (allp.max(0) - allp.min(0)).max() / 2 + 0.02
        _frame(ax, mid, r, elev, azim, legend=i == 0)
    _save(fig, path, title)


def cut_figure(path: str | Path, surface: np.ndarray, cuts: list[np.ndarray], gaps: list,
               truth: list[np.ndarray] | None = None, title: str = "") -> None:
    """The cut as planned: the scanned surface (grey), each runnable cut (green, numbered in cutting
    order, its start marked), each uncut stretch (red, with its reason and length) and, in the
    twin, the true painted line (thin black). Three views, as the coverage figure. ``gaps``:
    cellctl.scan.result.GapRecord."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [c for c in cuts if len(c)] + [np.asarray(g.points) for g in gaps if len(g.points)]
    allp = np.vstack(shown) if shown else (surface if len(surface) else np.zeros((1, 3)))
    mid = (allp.max(0) + allp.min(0)) / 2
    r = (allp.max(0) - allp.min(0)).max() / 2 + 0.03
    near = surface[np.all(np.abs(surface - mid) <= r, axis=1)] if len(surface) else surface
    fig = plt.figure(figsize=(12, 4.6))
    for i, (elev, azim) in enumerate([(90, -90), (25, -60), (25, 120)]):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        if len(near):
            s = near[:: max(1, len(near) // 5000)]
            ax.scatter(s[:, 0], s[:, 1], s[:, 2], s=0.3, c="0.7", alpha=0.35)
        for line in truth or []:
            ax.plot(*np.asarray(line).T, c="k", lw=0.6, label="true line" if line is truth[0] else None)
        for k, c in enumerate(cuts):
            ax.plot(*c.T, c="tab:green", lw=2.2, label="cut" if k == 0 else None)
            ax.scatter(*c[0], c="tab:green", s=14)
            ax.text(*c[0], str(k), fontsize=7)
        for k, g in enumerate([g for g in gaps if g.length_m > 0]):  # a reconfiguration leaves nothing uncut
            pts = np.asarray(g.points or [g.start, g.end])
            ax.plot(*pts.T, c="tab:red", lw=3.0, label="not cut" if k == 0 else None)
            if i == 0:
                ax.text(*pts[len(pts) // 2], f"{g.reason} {1000 * g.length_m:.0f} mm", fontsize=7, c="tab:red")
        _frame(ax, mid, r, elev, azim, legend=i == 0)
    _save(fig, path, title)
