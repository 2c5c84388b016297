"""The nozzle against the scanned surface. The arm's and the torch head's collision model works on
the occupancy grid (1 cm cells), too coarse for the last centimetres of the torch, which work
``standoff_m`` off the metal; the nozzle is checked against the surface cloud itself, as a chain of
balls along its taper whose union contains it (a k-d tree query per ball, all poses at once)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from planners.config import TorchConfig

#: axial length of the nozzle each ball covers
BALL_STEP_M = 0.005


def nozzle_balls(torch: TorchConfig) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (K,), radii (K,)): ball centres on the torch axis, offsets back from the tip, and
    radii such that the balls contain the taper from ``nozzle_radius_m`` at the tip to
    ``radius_m`` at ``nozzle_length_m`` (each ball: its slice's half length and widest radius)."""
    L = torch.nozzle_length_m
    if L <= 0:
        return np.zeros(0), np.zeros(0)
    K = max(1, int(np.ceil(L / BALL_STEP_M - 1e-9)))
    s = L / K
    u = (np.arange(K) + 0.5) * s
    widest = torch.nozzle_radius_m + (torch.radius_m - torch.nozzle_radius_m) * (u + s / 2) / L
    return u, np.hypot(s / 2, widest)


class NozzleCheck:
    """Is the nozzle clear of the scanned surface by ``margin_m`` with its tip at ``tips`` and its
    axis (tip pointing along it, into the metal) along ``axes``?"""

    def __init__(self, surface_xyz: np.ndarray | cKDTree, torch: TorchConfig, margin_m: float) -> None:
        if isinstance(surface_xyz, cKDTree):  # the surface's own index (geometry.Surface.tree)
            self.tree = surface_xyz
        else:
            self.tree = cKDTree(np.asarray(surface_xyz, dtype=np.float64).reshape(-1, 3), balanced_tree=False,
                                compact_nodes=False)  # built per cut: half the time
        self.offsets, self.radii = nozzle_balls(torch)
        self.margin = float(margin_m)

    def __call__(self, tips: np.ndarray, axes: np.ndarray) -> np.ndarray:
        """(...) bool for tips and unit axes of shape (..., 3)."""
        tips, axes = np.asarray(tips, dtype=np.float64), np.asarray(axes, dtype=np.float64)
        if len(self.offsets) == 0 or self.tree.n == 0:
            return np.ones(tips.shape[:-1], dtype=bool)
        centres = tips[..., None, :] - self.offsets[:, None] * axes[..., None, :]  # (..., K, 3)
        reach = self.radii + self.margin
        d, _ = self.tree.query(centres.reshape(-1, 3), distance_upper_bound=float(reach.max()))
        return (d.reshape(centres.shape[:-1]) > reach).all(axis=-1)
