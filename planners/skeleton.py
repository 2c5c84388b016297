"""The "Fit" of Alg. 1 by topological skeletonization (§V-A): an unordered drawing cloud becomes an
ordered curve, so a planner knows which way the drawing goes and where its two ends are."""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree
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


def _bridges(nodes: np.ndarray, labels: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shortest link (rows, cols, lengths) between every two skeleton pieces closer than `reach`
    voxels: a gap the closing could not fill (a missed patch of paint) should not cut the curve."""
    pairs = cKDTree(nodes).query_pairs(reach, output_type="ndarray")
    pairs = pairs[labels[pairs[:, 0]] != labels[pairs[:, 1]]]
    if len(pairs) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    length = np.linalg.norm(nodes[pairs[:, 0]] - nodes[pairs[:, 1]], axis=1)
    la, lb = labels[pairs[:, 0]], labels[pairs[:, 1]]
    key = np.minimum(la, lb) * (labels.max() + 1) + np.maximum(la, lb)
    order = np.lexsort((length, key))
    _, first = np.unique(key[order], return_index=True)
    keep = order[first]
    return pairs[keep, 0], pairs[keep, 1], length[keep]


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


def order_curve(xyz: np.ndarray, voxel: float, closing_iterations: int = 1, bridge_m: float = 0.04) -> np.ndarray:
    """Voxelize, close small gaps, thin to a 1-voxel skeleton and return its longest geodesic path
    (double sweep: the node farthest from any node is an end; the node farthest from that is the
    other) as voxel centres (K,3) in metres, from one end to the other. Pieces of the skeleton within
    `bridge_m` of each other are linked; of what stays apart, the piece with most voxels wins.
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
    n_pieces, labels = connected_components(graph, directed=False)
    if n_pieces > 1:
        r, c, w = _bridges(nodes, labels, bridge_m / voxel)
        graph = coo_matrix((np.concatenate([graph.data, w]), (np.concatenate([graph.row, r]),
                                                              np.concatenate([graph.col, c]))), shape=graph.shape)
        n_pieces, labels = connected_components(graph, directed=False)
    graph = graph.tocsr()
    start = int(np.flatnonzero(labels == np.argmax(np.bincount(labels)))[0])
    a, _ = _farthest(graph, start)
    _, path = _farthest(graph, a, with_path=True)
    return (nodes[path] + lo + 0.5) * voxel
