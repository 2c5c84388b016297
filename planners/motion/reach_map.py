"""Where the camera can be and which way it can look: a capability map of the arm (Zacharias et al.,
2007), sampled once per arm. Joint configurations drawn uniformly inside the limits are put through
forward kinematics; each marks its camera cell and the direction bin of its optical axis. A view
planner drops the candidates the map calls unreachable before it scores them, so its ranking is
not led by views the runner's IK will refuse one by one (the far side of a piece, looking back at
the robot). The map is a prefilter only: the runner still solves IK and checks collisions.

It errs on the side of reach: every marked bin is widened to its neighbour cells and to the
directions within `cone_deg`, so a view is dropped only where no sample came near it."""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from planners.motion.kinematics import Kinematics
from planners.views import fibonacci_sphere


class ReachMap:
    """Boolean map (cell x direction bin) of camera poses the arm reaches, roll about the optical axis
    free (as the view planners leave it)."""

    def __init__(self, kin: Kinematics, cell_m: float = 0.05, samples: int = 500_000, directions: int = 256,
                 cone_deg: float = 20.0, margin_rad: float = 0.05, seed: int = 0):
        if not (0.01 <= cell_m <= 0.5 and samples >= 1000 and directions >= 32 and 0 < cone_deg < 90):
            raise ValueError(f"ReachMap: cell_m {cell_m}, samples {samples}, directions {directions}, "
                             f"cone_deg {cone_deg} out of range")
        self.cell = float(cell_m)
        self._dirs = cKDTree(fibonacci_sphere(directions))
        rng = np.random.default_rng(seed)
        lo, hi = kin.lower + margin_rad, kin.upper - margin_rad  # the runner's IK keeps this margin too
        T = kin.fk_batch(lo + (hi - lo) * rng.random((samples, kin.dof)))
        pos, axis = T[:, :3, 3], T[:, :3, 2]
        self.lo = pos.min(axis=0) - 2 * self.cell
        ijk = np.floor((pos - self.lo) / self.cell).astype(np.int64)
        self.shape = tuple(int(s) for s in ijk.max(axis=0) + 3)
        _, b = self._dirs.query(axis)
        cells, row = np.unique(np.ravel_multi_index(ijk.T, self.shape), return_inverse=True)
        raw = np.zeros((len(cells), directions), dtype=np.float32)  # only the cells some sample hit
        raw[row.reshape(-1), b] = 1.0
        # widen in direction: one product with the bins' adjacency (all bins within cone_deg)
        pairs = self._dirs.query_pairs(2.0 * np.sin(np.radians(cone_deg) / 2.0), output_type="ndarray")
        adj = np.eye(directions, dtype=np.float32)
        adj[pairs[:, 0], pairs[:, 1]] = adj[pairs[:, 1], pairs[:, 0]] = 1.0
        wide = np.zeros((int(np.prod(self.shape)), directions), dtype=bool)
        wide[cells] = raw @ adj > 0
        wide = wide.reshape(self.shape + (directions,))
        # ... and in space: a sample's neighbour cells
        self.map = ndimage.binary_dilation(wide, structure=np.ones((3, 3, 3, 1), dtype=bool))

    def reachable(self, positions: np.ndarray, axes: np.ndarray) -> np.ndarray:
        """(M,) bool: may the camera be at `positions` (M, 3) looking along `axes` (M, 3)?"""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        ijk = np.floor((positions - self.lo) / self.cell).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(self.shape)), axis=1)
        out = np.zeros(len(positions), dtype=bool)
        if inside.any():
            _, b = self._dirs.query(np.asarray(axes, dtype=np.float64).reshape(-1, 3)[inside])
            c = ijk[inside]
            out[inside] = self.map[c[:, 0], c[:, 1], c[:, 2], b]
        return out


@functools.lru_cache(maxsize=4)
def _cached(urdf: str, joints: tuple, flange: str, T: bytes, lower: bytes, upper: bytes) -> ReachMap:
    kin = Kinematics(urdf, joints, flange, np.frombuffer(T).reshape(4, 4),
                     lower=np.frombuffer(lower), upper=np.frombuffer(upper))
    return ReachMap(kin)


def reach_map_for(kin: Kinematics) -> ReachMap:
    """The map of this arm and camera mount, built once per process (about 2 s)."""
    return _cached(kin.urdf_path, kin.joint_names, kin.flange_link, np.ascontiguousarray(kin.T_flange_cam).tobytes(),
                   np.ascontiguousarray(kin.lower).tobytes(), np.ascontiguousarray(kin.upper).tobytes())
