"""The "Fit" of Alg. 1 by topological skeletonization (§V-A): an unordered drawing cloud becomes an
ordered curve, so a planner knows which way the drawing goes and where its two ends are."""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from skimage.morphology import skeletonize

#: one of each opposite pair of the 26 neighbour offsets: every skeleton edge is found once
_HALF_26 = np.array([o for o in itertools.product((-1, 0, 1), repeat=3) if o > (0, 0, 0)], dtype=np.int64)


def voxelize(xyz: np.ndarray, voxel: float, pad: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy of the points' bounding box only (not the workspace), padded so closing and thinning
    never touch the border. Returns (volume, integer index of its corner voxel)."""
    ijk = np.floor(np.asarray(xyz, dtype=np.float64) / voxel).astype(np.int64)
    lo = ijk.min(axis=0) - pad
    ijk -= lo
    vol = np.zeros(tuple(ijk.max(axis=0) + pad + 1), dtype=bool)
    vol[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return vol, lo


def skeleton_graph(skel: np.ndarray) -> tuple[np.ndarray, "coo_matrix"]:
    """Skeleton voxels (N,3) and their 26-neighbourhood graph, edges weighted by length in voxels."""
    nodes = np.argwhere(skel)
    index = np.full(skel.shape, -1, dtype=np.int64)
    index[nodes[:, 0], nodes[:, 1], nodes[:, 2]] = np.arange(len(nodes))
    hi = np.asarray(skel.shape) - 1
    rows, cols, w = [], [], []
    for off in _HALF_26:  # 13 offsets, each vectorized over all voxels
        nb = nodes + off
        inside = np.all((nb >= 0) & (nb <= hi), axis=1)
        j = np.full(len(nodes), -1, dtype=np.int64)
        j[inside] = index[nb[inside, 0], nb[inside, 1], nb[inside, 2]]
        ok = j >= 0
        rows.append(np.flatnonzero(ok))
        cols.append(j[ok])
        w.append(np.full(ok.sum(), np.linalg.norm(off)))
    r, c, ww = np.concatenate(rows), np.concatenate(cols), np.concatenate(w)
    return nodes, coo_matrix((ww, (r, c)), shape=(len(nodes), len(nodes)))


def _farthest(graph, source: int, with_path: bool = False):
    d, pred = dijkstra(graph, directed=False, indices=source, return_predecessors=True)
    d[~np.isfinite(d)] = -1.0
    far = int(np.argmax(d))
    if not with_path:
        return far, None
    path = [far]
    while pred[path[-1]] >= 0:  # a walk over the few path nodes
        path.append(int(pred[path[-1]]))
    return far, np.asarray(path[::-1])


def order_curve(xyz: np.ndarray, voxel: float, closing_iterations: int = 1) -> np.ndarray:
    """Voxelize, close gaps of up to 2 x `closing_iterations` voxels (a patch the sensor dropped), thin
    to a 1-voxel skeleton and return its longest geodesic path (double sweep: the node farthest from
    any node is an end; the node farthest from that is the other) as voxel centres (K,3) in metres,
    from one end to the other. Of skeleton pieces still apart, the one with most voxels wins.
    A branched drawing yields one curve between two of its ends: E-NVP's limit, by design."""
    if len(xyz) == 0:
        return np.zeros((0, 3))
    pad = closing_iterations + 2
    vol, lo = voxelize(xyz, voxel, pad)
    if closing_iterations > 0:
        vol = ndimage.binary_closing(vol, structure=np.ones((3, 3, 3), bool), iterations=closing_iterations)
    skel = skeletonize(vol) > 0
    if not skel.any():  # thinning keeps at least one voxel per component; only an empty input ends here
        return np.zeros((0, 3))
    nodes, graph = skeleton_graph(skel)
    graph = graph.tocsr()
    _, labels = connected_components(graph, directed=False)
    start = int(np.flatnonzero(labels == np.argmax(np.bincount(labels)))[0])
    a, _ = _farthest(graph, start)
    _, path = _farthest(graph, a, with_path=True)
    return (nodes[path] + lo + 0.5) * voxel
