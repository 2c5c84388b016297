"""Air moves the straight and lifted routes cannot make: a lazy probabilistic roadmap (Bohlin &
Kavraki 2000). Configurations are sampled in the joint limits (half uniform, half about the two
ends), kept when free (one batched check), joined to their nearest neighbours (scipy's k-d tree);
scipy's Dijkstra finds the shortest route, only that route's motions are checked (the timed motion
the arm will make, as ``motion`` gives it), motions found to collide are cut from the graph and
the search runs again. The route found is then shortened by skipping waypoints where the direct
motion is clear."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

IsFree = Callable[[np.ndarray], np.ndarray]
#: (a, b) -> (T, dof) samples of the motion a -> b, or None when there is no such motion
Motion = Callable[[np.ndarray, np.ndarray], "np.ndarray | None"]


def roadmap_route(q_from: np.ndarray, q_to: np.ndarray, is_free: IsFree, motion: Motion, lower: np.ndarray,
                  upper: np.ndarray, *, samples: int = 400, neighbours: int = 10, searches: int = 40,
                  seed: int = 0) -> list[np.ndarray] | None:
    """Waypoints [q_from, ..., q_to] whose consecutive motions are all clear, or None.

    ``motion(a, b)`` samples the motion between two waypoints densely enough for ``is_free`` to
    judge it (the caller's own timing and resolution); ``is_free`` takes (N, dof) -> (N,) bool."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    a, b = np.asarray(q_from, float), np.asarray(q_to, float)
    spread = 0.25 * (hi - lo)
    cand = np.vstack([rng.uniform(lo, hi, (samples // 2, len(lo))),
                      np.clip(a + rng.normal(0.0, 1.0, (samples // 4, len(lo))) * spread, lo, hi),
                      np.clip(b + rng.normal(0.0, 1.0, (samples - samples // 2 - samples // 4, len(lo))) * spread, lo, hi)])
    nodes = np.vstack([a, b, cand[np.asarray(is_free(cand), dtype=bool)]])
    n = len(nodes)
    k = min(neighbours + 1, n)
    _, idx = cKDTree(nodes).query(nodes, k=k)
    pairs = np.sort(np.column_stack([np.repeat(np.arange(n), k - 1), idx[:, 1:].ravel()]), axis=1)
    pairs = np.unique(pairs[pairs[:, 0] != pairs[:, 1]], axis=0)  # undirected, once each
    weight = np.linalg.norm(nodes[pairs[:, 0]] - nodes[pairs[:, 1]], axis=1)
    alive = np.ones(len(pairs), dtype=bool)
    known_clear: set[tuple[int, int]] = set()
    for _ in range(searches):
        route = _shortest(n, pairs[alive], weight[alive])
        if route is None:
            return None
        steps = [(min(u, v), max(u, v)) for u, v in zip(route[:-1], route[1:])]
        todo = [s for s in steps if s not in known_clear]
        bad = _colliding(todo, nodes, is_free, motion)
        known_clear.update(s for s in todo if s not in bad)
        if not bad:
            return _shortcut([nodes[r] for r in route], is_free, motion)
        hit = np.array(sorted(bad))
        alive &= ~((pairs[:, None, 0] == hit[None, :, 0]) & (pairs[:, None, 1] == hit[None, :, 1])).any(axis=1)
    return None


def _shortest(n: int, pairs: np.ndarray, weight: np.ndarray) -> list[int] | None:
    """Node indices of the shortest route from node 0 to node 1, or None."""
    if len(pairs) == 0:
        return None
    G = coo_matrix((weight + 1e-12, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    d, pred = dijkstra(G, directed=False, indices=0, return_predecessors=True)
    if not np.isfinite(d[1]):
        return None
    route = [1]
    while route[-1] != 0:
        route.append(int(pred[route[-1]]))
    return route[::-1]


def _colliding(steps: list[tuple[int, int]], nodes: np.ndarray, is_free: IsFree, motion: Motion) -> set:
    """The steps (node pairs) whose motion collides, all checked in one call."""
    if not steps:
        return set()
    Q = [motion(nodes[u], nodes[v]) for u, v in steps]
    bad = {s for s, q in zip(steps, Q) if q is None}
    Q = [(s, q) for s, q in zip(steps, Q) if q is not None]
    if Q:
        ok = np.asarray(is_free(np.vstack([q for _, q in Q])), dtype=bool)
        owner = np.repeat(np.arange(len(Q)), [len(q) for _, q in Q])
        bad |= {Q[k][0] for k in np.unique(owner[~ok])}
    return bad


def _shortcut(route: list[np.ndarray], is_free: IsFree, motion: Motion) -> list[np.ndarray]:
    """Greedy: from each kept waypoint, the farthest later one whose direct motion is clear."""
    out = [route[0]]
    i = 0
    while i < len(route) - 1:
        j = len(route) - 1
        while j > i + 1 and not _clear(motion(route[i], route[j]), is_free):
            j -= 1
        out.append(route[j])
        i = j
    return out


def _clear(Q: np.ndarray | None, is_free: IsFree) -> bool:
    return Q is not None and bool(np.asarray(is_free(Q), dtype=bool).all())
