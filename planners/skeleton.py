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


def _cells(xyz: np.ndarray, voxel: float, lo: np.ndarray, shape: tuple) -> np.ndarray:
    """Boolean volume of ``shape`` (corner cell ``lo``) marking the cells that hold a point."""
    ijk = np.floor(np.asarray(xyz, dtype=np.float64) / voxel).astype(np.int64) - lo
    ijk = ijk[np.all((ijk >= 0) & (ijk < np.asarray(shape)), axis=1)]
    vol = np.zeros(shape, dtype=bool)
    vol[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return vol


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


_ATTEMPTS = ((0.0, None), (0.5, None), (0.0, 2), (0.0, 0), (0.0, 1))
_GOOD_SPAN = 0.8
_S26 = np.ones((3, 3, 3), dtype=bool)


def _span_score(vol: np.ndarray, skel: np.ndarray) -> float:
    """How much of the occupied volume the skeleton spans (sum over pieces of the skeleton's
    bounding-box diagonal over the piece's), 0 when thinning broke the topology: a piece with no
    skeleton left, or a skeleton in more pieces than the volume."""
    lv, nv = ndimage.label(vol, _S26)
    _, ns = ndimage.label(skel, _S26)
    lab = lv[skel]
    if ns != nv or len(np.unique(lab)) != nv:
        return 0.0

    def diag(ijk, labels):
        lo = np.stack([ndimage.minimum(ijk[:, k], labels, np.arange(1, nv + 1)) for k in range(3)], axis=1)
        hi = np.stack([ndimage.maximum(ijk[:, k], labels, np.arange(1, nv + 1)) for k in range(3)], axis=1)
        return np.linalg.norm(hi - lo, axis=1) + 1.0

    occupied = np.argwhere(vol)
    return float(diag(np.argwhere(skel), lab).sum() / diag(occupied, lv[vol]).sum())


def thin(xyz: np.ndarray, voxel: float, closing: int, support: np.ndarray | None = None):
    """Thinned skeleton (voxel indices, 26-graph, centres in metres). skimage's 3-D thinning
    (Lee) sometimes erases flat pieces of even thickness outright, or most of their length
    (scikit-image#3757, still open): a flat plate lying square to the grid, the commonest scrap,
    loses its line about one time in three. The grid is shifted or one axis grown by a voxel
    until the skeleton keeps the volume's topology and spans most of it; else the best one.

    ``support``: points of the surface the drawing lies on; closing then fills only cells that
    hold some of it. Paint on both faces of a thin plate (a line wrapped over a rim) is otherwise
    joined through the metal, and the line's skeleton takes that short cut instead of the rim."""
    best = None
    for shift, grow in _ATTEMPTS:
        vol, lo = voxelize(xyz + shift * voxel, voxel, closing + 2)
        if grow is not None:  # the padding keeps the roll from wrapping anything round
            vol = vol | np.roll(vol, 1, axis=grow)
        if closing > 0:
            closed = ndimage.binary_closing(vol, structure=_S26, iterations=closing)
            if support is not None and len(support):
                on = _cells(support + shift * voxel, voxel, lo, vol.shape)
                if grow is not None:
                    on = on | np.roll(on, 1, axis=grow)
                closed = vol | (closed & on)
            vol = closed
        skel = skeletonize(vol) > 0
        score = _span_score(vol, skel)
        if best is None or score > best[0]:
            offset = -shift - (0.5 * np.eye(3)[grow] if grow is not None else np.zeros(3))  # undo the shift/growth
            best = (score, skel, lo, offset)
        if score >= _GOOD_SPAN:
            break
    _, skel, lo, offset = best
    ijk, G = skeleton_graph(skel)
    return ijk, G, (ijk + lo + 0.5 + offset) * voxel


def order_curve(xyz: np.ndarray, voxel: float, closing_iterations: int = 1) -> np.ndarray:
    """Voxelize, close gaps of up to 2 x `closing_iterations` voxels (a patch the sensor dropped), thin
    to a 1-voxel skeleton and return its longest geodesic path (double sweep: the node farthest from
    any node is an end; the node farthest from that is the other) as voxel centres (K,3) in metres,
    from one end to the other. Of skeleton pieces still apart, the one with most voxels wins.
    A branched drawing yields one curve between two of its ends: E-NVP's limit, by design."""
    if len(xyz) == 0:
        return np.zeros((0, 3))
    _, graph, centres = thin(xyz, voxel, closing_iterations)
    if len(centres) == 0:
        return np.zeros((0, 3))
    graph = graph.tocsr()
    _, labels = connected_components(graph, directed=False)
    start = int(np.flatnonzero(labels == np.argmax(np.bincount(labels)))[0])
    a, _ = _farthest(graph, start)
    _, path = _farthest(graph, a, with_path=True)
    return centres[path]
