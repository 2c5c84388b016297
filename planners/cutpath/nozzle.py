"""The torch's working end against the scanned surface. The arm's and the rest of the torch's
collision model works on the occupancy grid (1 cm cells, a margin round each), too coarse for the
last centimetres of the torch, which work ``standoff_m`` off the metal: in an inside corner the cells
close the room the nozzle and head fit into. The first ``fine_length_m`` of the torch (nozzle taper,
then head) is checked against the surface cloud itself, as a chain of balls whose union contains it
(a k-d tree query per ball, all poses at once), and against the unseen cells in front of the
surface, where a piece the scan missed could stand. The balls bulge past the tip's flat face (by
5 mm at the first ball): where they meet the surface, the points they hold are measured against
the torch's own solid of revolution, so the depth noise of the metal under the tip does not close
the standoff."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from planners.config import TorchConfig

#: axial length of the nozzle each ball covers
BALL_STEP_M = 0.005


def nozzle_balls(torch: TorchConfig) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (K,), radii (K,)): ball centres on the torch axis, offsets back from the tip, and
    radii such that the balls contain the torch's first ``fine_length_m``: the taper from
    ``nozzle_radius_m`` at the tip to ``radius_m`` at ``nozzle_length_m``, then the head (each
    ball: its slice's half length and widest radius)."""
    L, F = torch.nozzle_length_m, torch.fine_length_m
    if F <= 0:
        return np.zeros(0), np.zeros(0)
    K = max(1, int(np.ceil(F / BALL_STEP_M - 1e-9)))
    s = F / K
    u = (np.arange(K) + 0.5) * s
    taper = (u + s / 2) / L if L > 0 else np.ones(K)
    widest = torch.nozzle_radius_m + (torch.radius_m - torch.nozzle_radius_m) * np.minimum(taper, 1.0)
    return u, np.hypot(s / 2, widest)


def _profile(torch: TorchConfig) -> np.ndarray:
    """(5,2) the outline of the torch's first ``fine_length_m`` as (back from the tip, off the axis):
    the axis at the tip, the nozzle's rim, the taper's top (``nozzle_length_m``), the head's top, the axis."""
    L, F = torch.nozzle_length_m, torch.fine_length_m
    rn, R = torch.nozzle_radius_m, torch.radius_m

    def radius(x: float) -> float:
        return rn + (R - rn) * min(max(x / L, 0.0), 1.0) if L > 0 else R

    Lc = min(L, F)
    return np.array([[0.0, 0.0], [0.0, radius(0.0)], [Lc, radius(Lc)], [F, radius(F)], [F, 0.0]])


def frustum_distance(u: np.ndarray, rho: np.ndarray, torch: TorchConfig) -> np.ndarray:
    """Distance (0 inside) from points at ``u`` back from the tip along the axis and ``rho`` off it
    to the torch's first ``fine_length_m``: the solid of revolution of the taper from
    ``nozzle_radius_m`` at the tip to ``radius_m`` at ``nozzle_length_m``, then the head. Its
    profile is convex, so outside it the distance is the nearest of its four edges."""
    V = _profile(torch)
    F = torch.fine_length_m
    inside = (u >= 0.0) & (u <= F) & (rho <= np.interp(u, V[1:4, 0], V[1:4, 1]))
    Q = np.stack([u, rho], axis=-1)
    d = np.full(u.shape, np.inf)
    for a, b in zip(V[:-1], V[1:]):  # the profile's four edges
        ab = b - a
        t = np.clip(((Q - a) @ ab) / max(float(ab @ ab), 1e-18), 0.0, 1.0)
        d = np.minimum(d, np.linalg.norm(Q - (a + t[..., None] * ab), axis=-1))
    return np.where(inside, 0.0, d)


class NozzleCheck:
    """Is the torch's working end clear of the scanned surface by ``margin_m`` with its tip at
    ``tips`` and its axis (tip pointing along it, into the metal) along ``axes``? ``unseen``: centres
    of cells of side ``cell_m`` nobody has seen into, each an obstacle as large as its bounding ball
    for the head (the nozzle works within a cell of the metal, where the cells next to a surface seen
    at a slant are often unseen); pass only those in front of the surface: the ones behind it are
    the metal's inside, which the surface already bounds. ``floor_z``: the plane the piece stands on
    (the base frame's z = 0 in the cell), which the working end's solid may not come within the margin of:
    the scan keeps little of the table, and the arm's own floor test leaves the working end out."""

    def __init__(self, surface_xyz: np.ndarray | cKDTree, torch: TorchConfig, margin_m: float,
                 unseen: np.ndarray | None = None, cell_m: float = 0.0, floor_z: float | None = None) -> None:
        if isinstance(surface_xyz, cKDTree):  # the surface's own index (geometry.Surface.tree)
            self.tree = surface_xyz
        else:
            self.tree = cKDTree(np.asarray(surface_xyz, dtype=np.float64).reshape(-1, 3), balanced_tree=False,
                                compact_nodes=False)  # built per cut: half the time
        unseen = np.zeros((0, 3)) if unseen is None else np.asarray(unseen, dtype=np.float64).reshape(-1, 3)
        self.unseen = cKDTree(unseen) if len(unseen) else None
        self.cell_reach = float(cell_m) * np.sqrt(3.0) / 2.0
        self.offsets, self.radii = nozzle_balls(torch)
        self.head = self.offsets >= torch.nozzle_length_m  # the nozzle works closer to the metal than a cell
        self.margin = float(margin_m)
        self.floor_z = None if floor_z is None else float(floor_z)
        self._torch = torch

    def __call__(self, tips: np.ndarray, axes: np.ndarray) -> np.ndarray:
        """(...) bool for tips and unit axes of shape (..., 3)."""
        tips, axes = np.asarray(tips, dtype=np.float64), np.asarray(axes, dtype=np.float64)
        if len(self.offsets) == 0 or self.tree.n == 0:
            return np.ones(tips.shape[:-1], dtype=bool)
        centres = tips[..., None, :] - self.offsets[:, None] * axes[..., None, :]  # (..., K, 3)
        flat = centres.reshape(-1, 3)
        reach = self.radii + self.margin
        d, _ = self.tree.query(flat, distance_upper_bound=float(reach.max()))
        clear = (d.reshape(centres.shape[:-1]) > reach).all(axis=-1)
        if not clear.all():  # the balls are a broad phase: the torch's own shape decides
            clear[~clear] = self._solid_clear(tips[~clear], axes[~clear], centres[~clear])
        if self.floor_z is not None:  # the table the piece lies on: rarely in the scan, always there; the
            # torch's lowest point (the flat nozzle's rim, or its side when it lies low) above it by the margin
            clear &= self._lowest(tips, axes) >= self.floor_z + self.margin
        head = self.head
        if self.unseen is not None and head.any():
            reach = self.radii[head] + self.margin + self.cell_reach
            d, _ = self.unseen.query(centres[..., head, :].reshape(-1, 3), distance_upper_bound=float(reach.max()))
            clear &= (d.reshape(centres.shape[:-2] + (int(head.sum()),)) > reach).all(axis=-1)
        return clear

    def _lowest(self, tips: np.ndarray, axes: np.ndarray) -> np.ndarray:
        """(...) the lowest z of the working end's solid: its profile (``_profile``) swept round the
        axis, lowest at one of the profile's outer vertices, by its radius times the axis' tilt."""
        u, r = _profile(self._torch)[1:4].T  # the outer vertices, back from the tip along -axis
        az = axes[..., 2:3]
        sideways = np.sqrt(np.clip(1.0 - az**2, 0.0, 1.0))  # the circle's lowest point: r times the axis' tilt
        return (tips[..., 2:3] - u * az - r * sideways).min(axis=-1)

    def _solid_clear(self, tips: np.ndarray, axes: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """(M,) bool for tips and axes (M,3) and their ball centres (M,K,3): no surface point within
        ``margin_m`` of the torch's solid (``frustum_distance``), among the points the balls (dilated
        by the margin) hold."""
        K = len(self.offsets)
        centres = centres.reshape(-1, 3)
        reach = np.tile(self.radii + self.margin, len(tips))
        counts = self.tree.query_ball_point(centres, reach, return_length=True)
        near = self.tree.query_ball_point(centres, reach, return_sorted=False)
        idx = np.concatenate(near).astype(np.int64) if counts.sum() else np.zeros(0, np.int64)
        pose = np.repeat(np.repeat(np.arange(len(tips)), K), counts)
        rel = self.tree.data[idx] - tips[pose]
        along = np.einsum("ij,ij->i", rel, axes[pose])  # into the metal; the torch lies back along -axis
        rho = np.linalg.norm(rel - along[:, None] * axes[pose], axis=1)
        hit = frustum_distance(-along, rho, self._torch) <= self.margin
        clear = np.ones(len(tips), dtype=bool)
        clear[pose[hit]] = False
        return clear
