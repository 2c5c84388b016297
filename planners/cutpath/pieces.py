"""Paint the skeleton cannot make a branch of: a broken line (paint only where the spray met a bar of
a basket, a dashed stroke). Each such piece is a short cut along the line it belongs to, never
nothing.

A piece's own shape does not say which way the line runs (paint on a 16 mm rod is a patch wider
along the rod than across it); its neighbours do. The pieces' centroids are joined by a minimum
spanning tree (no edge longer than ``bridge_max_m``) and a piece's cut runs along the principal axis
of itself and its tree neighbours, through its centroid, across the paint. At each end the cut stops
where the metal stops (the edge of a bar) or, where the metal goes on, half a line width before
the paint does (a sprayed stroke ends in a round cap)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from planners.cutpath.geometry import Surface


@dataclass
class Piece:
    points: np.ndarray  # (K,3) the paint of this piece
    centre: np.ndarray  # (3,)
    direction: np.ndarray  # (3,) unit, along the line
    line: np.ndarray  # (M,3) the cut's straight segment before it is put on the surface


def paint_parts(xyz: np.ndarray, link_m: float) -> list[np.ndarray]:
    """Indices of the connected pieces of a cloud whose points are linked within ``link_m``."""
    pairs = cKDTree(xyz).query_pairs(link_m, output_type="ndarray")
    n = len(xyz)
    A = csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    k, lab = connected_components(A, directed=False)
    order = np.argsort(lab, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(lab[order])) + 1) if n else []


def short_pieces(drawing: np.ndarray, branches: list[np.ndarray], surface: Surface, *, voxel_m: float,
                 spacing_m: float, bridge_max_m: float, min_piece_m: float) -> tuple[list[Piece], int]:
    """Pieces of the drawing cloud that no branch passes through, as short straight cuts.

    Returns (pieces, ignored): ``ignored`` counts the specks too small to be paint of a line
    (shorter than ``min_piece_m`` along it, or with no neighbour and no length of their own)."""
    if len(drawing) == 0:
        return [], 0
    tree = cKDTree(drawing)
    crowd = tree.query_ball_point(drawing, voxel_m, return_length=True)
    xyz = drawing[crowd >= max(3.0, 0.25 * float(np.median(crowd)))]
    if len(xyz) == 0:
        return [], 0
    comps = paint_parts(xyz, 1.5 * voxel_m)
    if branches:
        on_branch = cKDTree(np.vstack(branches))
        comps = [c for c in comps if not np.any(on_branch.query(xyz[c], distance_upper_bound=3.0 * voxel_m)[0] < np.inf)]
    comps = [c for c in comps if len(c) >= 10]
    if not comps:
        return [], 0
    centres = np.array([xyz[c].mean(axis=0) for c in comps])
    m = len(comps)
    if m > 1:
        D = np.linalg.norm(centres[:, None] - centres[None], axis=2)
        D[D > bridge_max_m] = 0.0  # no edge
        T = minimum_spanning_tree(csr_matrix(D))
        T = (T + T.T).tocsr()
        neighbours = [T.indices[T.indptr[i]:T.indptr[i + 1]] for i in range(m)]
    else:
        neighbours = [np.zeros(0, dtype=np.int64)]
    pieces, ignored = [], 0
    for i, c in enumerate(comps):  # a handful of pieces
        P = xyz[c]
        group = np.vstack([centres[i:i + 1], centres[neighbours[i]]])
        if len(group) >= 2:
            d = np.linalg.svd(group - group.mean(axis=0), full_matrices=False)[2][0]
        else:  # alone: only its own elongation says which way (a dash)
            ev, vec = np.linalg.eigh(np.cov((P - P.mean(axis=0)).T))
            if ev[-1] < 4.0 * ev[-2]:  # round: no direction, a speck
                ignored += 1
                continue
            d = vec[:, -1]
        d /= np.linalg.norm(d)
        s = (P - centres[i]) @ d
        lateral = np.linalg.norm((P - centres[i]) - s[:, None] * d[None], axis=1)
        hw = max(float(np.percentile(lateral, 90)), voxel_m)
        lo, hi = float(s.min()), float(s.max())
        for sign in (-1.0, 1.0):  # shrink an end by half a width where the metal goes on past it
            end = centres[i] + (hi if sign > 0 else lo) * d
            beyond = end + sign * 0.75 * hw * d
            if surface.tree.query(beyond, distance_upper_bound=0.5 * hw)[0] < np.inf:
                if sign > 0:
                    hi -= hw
                else:
                    lo += hw
        if hi - lo < min_piece_m:
            ignored += 1
            continue
        k = max(int(round((hi - lo) / spacing_m)), 1) + 1
        line = centres[i] + np.linspace(lo, hi, k)[:, None] * d
        pieces.append(Piece(P, centres[i], d, line))
    return pieces, ignored
