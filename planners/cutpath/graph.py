"""The drawing's topology: a 3-D skeleton of the drawing cloud as a graph of junctions, free ends
and the branches between them, each branch an ordered polyline. A cut needs every branch, not
just the longest path `planners.skeleton.order_curve` gives a scanning planner."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, depth_first_order, dijkstra, minimum_spanning_tree
from scipy.spatial import cKDTree

from planners.cutpath import _checks
from planners.cutpath.geometry import arc_length, painted_over
from planners.skeleton import thin

JUNCTION, END, LOOP = "junction", "end", "loop"


@dataclass
class DrawingGraph:
    """Key nodes (junctions, free ends, one start node per closed loop) and the branches between
    them. Branch i runs from node ends[i][0] to ends[i][1]; its first and last points are those
    nodes' positions (a closed loop starts and ends on its own node)."""

    nodes: np.ndarray  # (M,3) metres
    kinds: list[str]  # JUNCTION | END | LOOP per node
    branches: list[np.ndarray]  # (K_i,3) ordered polylines, metres
    ends: list[tuple[int, int]]
    voxel_m: float
    lengths_m: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.lengths_m = np.array([polyline_length(b) for b in self.branches], dtype=np.float64)

    def _of_kind(self, kind: str) -> np.ndarray:
        idx = [i for i, k in enumerate(self.kinds) if k == kind]
        return self.nodes[idx].reshape(-1, 3)

    @property
    def junctions(self) -> np.ndarray:
        return self._of_kind(JUNCTION)

    @property
    def endpoints(self) -> np.ndarray:
        return self._of_kind(END)

    def closed(self, i: int) -> bool:
        a, b = self.ends[i]
        return a == b and self.kinds[a] == LOOP


def polyline_length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def _without_shortcuts(G) -> csr_matrix:
    """Symmetric 26-adjacency minus the diagonal edges that a two-step path of shorter steps also
    joins: the staircase triangles a 26-connected skeleton is full of would otherwise make every
    corner a degree-3 "junction". Connectivity is unchanged (the two-step path stays)."""
    S = (G + G.T).tocoo()
    n = S.shape[0]
    cls = np.rint(S.data ** 2).astype(np.int64)  # 1 face, 2 edge, 3 corner neighbour
    keep = np.ones(len(cls), dtype=bool)
    for c in (2, 3):
        m = cls == c
        if not m.any():
            continue
        lo = cls < c
        L = csr_matrix((np.ones(lo.sum()), (S.row[lo], S.col[lo])), shape=(n, n))
        two_step = (L @ L).tocsr()
        hit = np.asarray(two_step[S.row[m], S.col[m]]).ravel() > 0
        keep[np.flatnonzero(m)[hit]] = False
    return csr_matrix((S.data[keep], (S.row[keep], S.col[keep])), shape=(n, n))


class _Builder:
    """Mutable key nodes and branches while spurs are pruned and junctions dissolved."""

    def __init__(self) -> None:
        self.pos: dict[int, np.ndarray] = {}
        self.kind: dict[int, str] = {}
        self.branches: dict[int, list] = {}  # id -> [points, a, b]
        self._next_key = 0
        self._next_branch = 0

    def key(self, pos: np.ndarray, kind: str) -> int:
        k = self._next_key
        self._next_key += 1
        self.pos[k], self.kind[k] = np.asarray(pos, dtype=np.float64), kind
        return k

    def branch(self, pts: np.ndarray, a: int, b: int) -> None:
        self.branches[self._next_branch] = [pts, a, b]
        self._next_branch += 1

    def degree(self) -> dict[int, int]:
        d = dict.fromkeys(self.pos, 0)
        for _, a, b in self.branches.values():
            d[a] += 1
            d[b] += 1
        return d

    def drop_branch(self, i: int) -> None:
        del self.branches[i]

    def settle(self) -> None:
        """Junctions left with two branches become ordinary points, with one an end, with none
        nothing; repeated because each merge can change another junction's degree."""
        changed = True
        while changed:
            changed = False
            deg = self.degree()
            for k, d in deg.items():
                if self.kind[k] != JUNCTION or d >= 3:
                    continue
                changed = True
                if d == 0:
                    del self.pos[k], self.kind[k]
                elif d == 1:
                    self.kind[k] = END
                else:
                    self._merge_at(k)
                break  # degrees changed: recount

    def _merge_at(self, k: int) -> None:
        at = [i for i, (_, a, b) in self.branches.items() if k in (a, b)]
        if len(at) == 1:  # a loop through k and nothing else: a closed curve
            self.kind[k] = LOOP
            return
        i, j = at
        p, a, b = self.branches.pop(i)
        q, c, d = self.branches.pop(j)
        if a == k:
            p, a, b = p[::-1], b, a
        if d == k:
            q, c, d = q[::-1], d, c
        self.branch(np.vstack([p, q[1:]]), a, d)
        del self.pos[k], self.kind[k]
        if a == d and self.kind[a] == END:  # impossible for a true end; keep the graph sane
            self.kind[a] = LOOP


def _trace(A: csr_matrix, pos: np.ndarray) -> _Builder:
    """Key nodes and ordered branches of the thinned skeleton graph."""
    out = _Builder()
    n = A.shape[0]
    deg = np.diff(A.indptr)
    J = deg >= 3
    R = (deg == 1) | (deg == 2)

    jidx = np.flatnonzero(J)
    cluster = np.full(n, -1, dtype=np.int64)
    if len(jidx):
        n_j, jlab = connected_components(A[jidx][:, jidx], directed=False)
        cluster[jidx] = jlab
        count = np.bincount(jlab, minlength=n_j)
        centroid = np.stack([np.bincount(jlab, pos[jidx, k], n_j) for k in range(3)], axis=1) / count[:, None]
        jkey = [out.key(c, JUNCTION) for c in centroid]

    ridx = np.flatnonzero(R)
    if len(ridx) == 0:
        return out
    AR = A[ridx][:, ridx].tocsr()
    n_s, slab = connected_components(AR, directed=False)
    deg_r = np.diff(AR.indptr)

    coo = A.tocoo()
    m = R[coo.row] & J[coo.col]
    border: dict[int, list[int]] = {}
    for u, c in zip(coo.row[m].tolist(), cluster[coo.col[m]].tolist()):  # ~2 pairs per branch
        border.setdefault(u, []).append(jkey[c])

    by_seg = np.argsort(slab, kind="stable")
    cuts = np.flatnonzero(np.diff(slab[by_seg])) + 1
    for members in np.split(by_seg, cuts):  # one per branch
        tips = members[deg_r[members] <= 1]
        start = int(tips[0]) if len(tips) else int(members[0])
        order = depth_first_order(AR, start, directed=False, return_predecessors=False)
        g = ridx[order]
        pts = pos[g]
        if len(tips) == 0:  # a closed curve with no junction on it
            k = out.key(pts[0], LOOP)
            out.branch(np.vstack([pts, pts[:1]]), k, k)
            continue
        f, l = int(g[0]), int(g[-1])
        if len(g) == 1 and deg[f] == 2:  # one voxel between two junction voxels
            a, b = border[f][0], border[f][1]
        elif len(g) == 1:  # an end right next to a junction
            a, b = out.key(pts[0], END), border[f][0]
        else:
            a = out.key(pts[0], END) if deg[f] == 1 else border[f][0]
            b = out.key(pts[-1], END) if deg[l] == 1 else border[l][0]
        if out.kind[a] == JUNCTION:
            pts = np.vstack([out.pos[a], pts])
        if out.kind[b] == JUNCTION:
            pts = np.vstack([pts, out.pos[b]])
        out.branch(pts, a, b)
    return out


def _prune(g: _Builder, min_branch_m: float, islands: bool = True) -> None:
    """Remove spurs (a junction-to-end branch, or a junction's loop onto itself) shorter than
    min_branch_m, the shortest first, so that of a short line with a hair the line survives; then
    (with ``islands``) drop isolated pieces that short: noise, not a line to cut, unless a bridge
    still joins them into the line (a stretch over a plate's rim between two holes)."""
    g.settle()
    while True:
        best, best_len = None, min_branch_m
        for i, (p, a, b) in g.branches.items():
            ka, kb = g.kind[a], g.kind[b]
            spur = {ka, kb} == {JUNCTION, END} or (a == b and ka == JUNCTION)
            if spur:
                L = polyline_length(p)
                if L < best_len:
                    best, best_len = i, L
        if best is None:
            break
        _, a, b = g.branches[best]
        g.drop_branch(best)
        for k in {a, b}:
            if g.kind[k] == END:
                del g.pos[k], g.kind[k]
        g.settle()
    for i, (p, a, b) in list(g.branches.items()) if islands else []:
        if g.kind[a] != JUNCTION and g.kind[b] != JUNCTION and (polyline_length(p) < min_branch_m or len(p) < 2):
            g.drop_branch(i)
    used = {k for _, a, b in g.branches.values() for k in (a, b)}
    for k in [k for k in g.pos if k not in used]:
        del g.pos[k], g.kind[k]


def _pop_painted_over(g: _Builder, xyz: np.ndarray, voxel: float) -> None:
    """Drop the cycles no worker drew: a loop narrower than the band of paint round it would have
    its hole painted over (``geometry.painted_over``). Thinning makes them where paint wraps a thin
    bar or a plate's rim (the paint round the bar is a tube with the metal as its hole): a closed
    branch or a junction's loop onto itself goes (its paint is then a piece, ``pieces.py``); of two
    branches between the same two junctions (a bubble round a rim) the longer goes."""
    for i, (p, a, b) in list(g.branches.items()):  # a handful of branches
        if a == b and painted_over(p, xyz, voxel):
            g.drop_branch(i)
    twins: dict[frozenset, list[int]] = {}
    for i, (p, a, b) in g.branches.items():
        if a != b:
            twins.setdefault(frozenset((a, b)), []).append(i)
    for ids in twins.values():
        if len(ids) < 2:
            continue
        ids = sorted(ids, key=lambda i: polyline_length(g.branches[i][0]))
        p, a, _ = g.branches[ids[0]]
        for i in ids[1:]:
            q, c, _ = g.branches[i]
            loop = np.vstack([p, (q if c != a else q[::-1])[1:]])  # a -> b, then back to a
            if painted_over(loop, xyz, voxel):
                g.drop_branch(i)
    g.settle()
    for k in [k for k, d in g.degree().items() if d == 0]:
        del g.pos[k], g.kind[k]


def _half_width(c: np.ndarray, t: np.ndarray, xyz: np.ndarray, tree: cKDTree, voxel: float) -> float:
    """Half the line's width at centre-line point `c` (direction `t`): the spread of the paint in
    a thin slab across the line there."""
    v = xyz[tree.query_ball_point(c, max(8.0 * voxel, 0.04))] - c
    slab = v[np.abs(v @ t) < max(voxel, 0.003)]
    if len(slab) < 4:
        return voxel
    slab = slab - slab.mean(axis=0)
    sv = np.linalg.svd(slab, full_matrices=False)[1]
    return max(float(np.sqrt(3.0) * sv[0] / np.sqrt(len(slab))), 0.5 * voxel)  # uniform across: std = w/√12


def _cap_centre(e: np.ndarray, xyz: np.ndarray, tree: cKDTree, hw: float) -> np.ndarray:
    """Mean shift to the centre of a line's round end cap: a disc of paint of the line's half
    width round it is symmetric about it, so that centre is where the centroid stays put."""
    for _ in range(10):
        near = tree.query_ball_point(e, hw)
        if len(near) < 3:
            break
        c = xyz[near].mean(axis=0)
        done = np.linalg.norm(c - e) < 1e-4
        e = c
        if done:
            break
    return e


def _paint_ahead(e: np.ndarray, t: np.ndarray, xyz: np.ndarray, tree: cKDTree, hw: float,
                 voxel: float) -> np.ndarray | None:
    """Where the paint ahead of a skeleton end `e` (tangent `t`) really ends: the paint point
    geodesically farthest from `e` (through the paint, across gaps of up to 1.5 voxels), less half
    a width `hw`, since a sprayed line ends in a round cap centred on its end. Returns the path on
    from `e` to that end (K,3), or None when the paint stops at `e`."""
    reach = max(10.0 * hw, 8.0 * voxel)
    P = xyz[tree.query_ball_point(e, reach)]
    v = P - e
    along = v @ t
    lateral = np.linalg.norm(v - along[:, None] * t, axis=1)
    keep = (along > -hw) & (lateral < 2.0 * hw + voxel)
    P, along = P[keep], along[keep]
    if len(P) < 3:
        return None
    sub = cKDTree(P)
    pairs = sub.query_pairs(1.5 * voxel, output_type="ndarray")
    if len(pairs) == 0:
        return None
    w = np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1) + 1e-12
    graph = csr_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(len(P), len(P)))
    sources = np.atleast_1d(sub.query(e, k=min(5, len(P)))[1])
    dist, pred, src = dijkstra(graph, directed=False, indices=sources, min_only=True, return_predecessors=True)
    reached = np.isfinite(dist)
    dist[reached] += np.linalg.norm(P[src[reached]] - e, axis=1)
    # the cap is ahead, not beside or behind the end, and is paint, not a stray speck next to it
    crowd = sub.query_ball_point(P, 1.5 * voxel, return_length=True)
    dist[~reached | (along <= 0) | (crowd < 0.25 * np.median(crowd))] = -1.0
    far = int(np.argmax(dist))
    path = [far]
    while pred[path[-1]] >= 0:  # a walk over the few path points
        path.append(int(pred[path[-1]]))
    q = np.vstack([e, P[path[::-1]]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    # the path zigzags from point to point, so go back from the cap's tip in a straight line
    tip = q[-1]
    before = np.array([np.interp(s[-1] - 2.0 * hw, s, q[:, k]) for k in range(3)])
    u = tip - before if np.linalg.norm(tip - before) > 1e-9 else t
    end = tip - hw * u / np.linalg.norm(u)
    stop = s[-1] - hw
    ts = np.arange(voxel, stop - 0.5 * voxel, voxel)
    out = np.vstack([np.column_stack([np.interp(ts, s, q[:, k]) for k in range(3)]), end])
    out[-1] = _cap_centre(out[-1], xyz, tree, hw)
    if (out[-1] - e) @ t <= 0.25 * voxel:
        return None
    return out


def _extend_ends(g: _Builder, xyz: np.ndarray, tree: cKDTree, voxel: float, rounds: int = 5) -> None:
    """Thinning eats into a line's ends (by several widths on noisy or flat clouds): each free end
    is carried on through the paint, a reach at a time, to where the line really ends."""
    back = 6.0 * voxel  # the end's direction and width are taken this far back along the branch
    for i, (p, a, b) in g.branches.items():  # a handful of branches
        for at_start in (True, False):
            k = a if at_start else b
            if g.kind[k] != END or len(p) < 2:
                continue
            q = p[::-1] if at_start else p  # q[-1] is this end
            for _ in range(rounds):
                to_end = np.concatenate([np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1)[::-1])[::-1], [0.0]])
                j = min(int(np.flatnonzero(to_end <= back)[0]), len(q) - 2)
                t = q[-1] - q[j]
                if np.linalg.norm(t) < 1e-12:
                    break
                t = t / np.linalg.norm(t)
                hw = _half_width(q[j], t, xyz, tree, voxel)
                more = _paint_ahead(q[-1], t, xyz, tree, hw, voxel)
                if more is None:
                    break
                q = np.vstack([q, more])
            g.pos[k] = q[-1].copy()
            p = q[::-1] if at_start else q
        g.branches[i][0] = p


#: voxel grid variants tried in turn: (grid offset in voxels, axis grown by one voxel or None)
def drawing_graph(xyz: np.ndarray, voxel_m: float = 0.005, min_branch_m: float = 0.03,
                  closing_iterations: int = 1, extend_ends: bool = True,
                  surface: np.ndarray | None = None) -> DrawingGraph:
    """Skeleton graph of a drawing cloud (N,3): junctions (clusters of adjacent degree-≥3
    skeleton voxels, at their centroid), free ends (degree 1) and one ordered polyline per branch
    between them, spurs shorter than `min_branch_m` pruned, free ends carried on to where the paint
    ends. Voxelization, gap closing and thinning are those of `order_curve`, made robust to the
    thinning's habit of erasing flat pieces (see `_skeleton`). ``surface``: the scanned surface,
    where gap closing may add cells (``skeleton.thin``)."""
    xyz = _checks.points(xyz, "xyz")
    voxel = _checks.positive(voxel_m, "voxel_m")
    min_branch = _checks.non_negative(min_branch_m, "min_branch_m")
    if not isinstance(closing_iterations, (int, np.integer)) or closing_iterations < 0:
        raise ValueError(f"closing_iterations must be a non-negative integer, got {closing_iterations!r}")
    extent = xyz.max(axis=0) - xyz.min(axis=0)
    cells = np.prod(extent / voxel + 2 * closing_iterations + 6)
    if cells > 2e8:
        raise ValueError(f"voxel_m={voxel} is too small for a drawing spanning {extent.round(3).tolist()} m "
                         f"({cells:.2g} voxels)")
    tree = cKDTree(xyz)
    crowd = tree.query_ball_point(xyz, voxel, return_length=True)
    dense = crowd >= max(3.0, 0.25 * float(np.median(crowd)))  # a stray speck would grow a false end
    if dense.sum() >= 0.5 * len(xyz):  # else the cloud is just sparse: keep it all
        xyz = xyz[dense]
        tree = cKDTree(xyz)
    ijk, G, pos = thin(xyz, voxel, int(closing_iterations), surface)
    A = _without_shortcuts(G)
    b = _trace(A, pos)
    _prune(b, min_branch)
    _pop_painted_over(b, xyz, voxel)
    if extend_ends:
        _extend_ends(b, xyz, tree, voxel)
    keys = list(b.pos)
    new_id = {k: i for i, k in enumerate(keys)}
    nodes = np.array([b.pos[k] for k in keys], dtype=np.float64).reshape(-1, 3)
    branches = [p for p, _, _ in b.branches.values()]
    ends = [(new_id[a], new_id[c]) for _, a, c in b.branches.values()]
    return DrawingGraph(nodes, [b.kind[k] for k in keys], branches, ends, voxel)


def curve_graph(points: np.ndarray, cell_m: float = 0.003, link_m: float = 0.008,
                min_branch_m: float = 0.03, paint: cKDTree | None = None, bridge_m: float = 0.0) -> DrawingGraph:
    """The graph of a thin cloud of points on a curve (the paint's outline moved onto its line,
    ``outline.py``), not of a band: each point moved to the mean of its neighbours within ``cell_m``
    (the rows the band's two sides put on the line merge), one kept per ``cell_m`` cell, joined by their minimum spanning tree within ``link_m`` (a curve's
    neighbours are its nearest points, so the tree follows it into a sharp tip where a voxel skeleton
    of the band would cut the tip off), then traced, and its spurs pruned, as the skeleton's are.
    Where strokes cross or meet the outline leaves a hole (the paint there is far from every side):
    two free ends up to ``bridge_m`` apart that continue each other over ``paint`` (its k-d tree)
    are joined across it (``_bridge``)."""
    xyz = _checks.points(points, "points")
    cell = _checks.positive(cell_m, "cell_m")
    near = cKDTree(xyz).sparse_distance_matrix(cKDTree(xyz), cell, output_type="coo_matrix")
    W = csr_matrix((np.ones(len(near.row)), (near.row, near.col)), shape=(len(xyz), len(xyz)))
    W = W + csr_matrix((np.ones(len(xyz)), (np.arange(len(xyz)), np.arange(len(xyz)))), shape=W.shape)
    xyz = (W @ xyz) / np.asarray(W.sum(axis=1))  # each point to the mean of its neighbours: the sides' rows merge
    _, first = np.unique(np.floor(xyz / cell).astype(np.int64), axis=0, return_index=True)
    P = xyz[np.sort(first)]
    twins = cKDTree(P).query_pairs(0.5 * cell, output_type="ndarray")  # one row split by a cell border
    P = np.delete(P, np.unique(twins.max(axis=1)), axis=0) if len(twins) else P
    pairs = cKDTree(P).query_pairs(link_m, output_type="ndarray")
    w = np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1) + 1e-12
    T = minimum_spanning_tree(coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(len(P), len(P))).tocsr())
    b = _trace(((T + T.T) > 0).astype(np.float64).tocsr(), P)
    bridging = paint is not None and bridge_m > 0
    _prune(b, min(min_branch_m, bridge_m) if bridging else min_branch_m, islands=not bridging)
    if bridging:
        _bridge(b, paint, bridge_m, cell_m)
        _prune(b, min_branch_m)
    keys = list(b.pos)
    new_id = {k: i for i, k in enumerate(keys)}
    nodes = np.array([b.pos[k] for k in keys], dtype=np.float64).reshape(-1, 3)
    return DrawingGraph(nodes, [b.kind[k] for k in keys], [p for p, _, _ in b.branches.values()],
                        [(new_id[a], new_id[c]) for _, a, c in b.branches.values()], cell_m)


#: two free ends continue each other when each one's direction points at the other within this angle
BRIDGE_DEG = 35.0
#: ends this share of the bridge's reach apart (a spray width) are joined over paint whatever their directions,
#: once every pair that continues each other is: a line wrapped over a plate's rim turns back in space there
NEAR_BRIDGE = 1.0 / 3.0


def _end_direction(p: np.ndarray, at_start: bool, back_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(the end point, its outward unit direction over the last ``back_m`` of the branch)."""
    q = p[::-1] if at_start else p
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    j = int(np.searchsorted(s, s[-1] - back_m))
    t = q[-1] - q[min(j, len(q) - 2)]
    return q[-1], t / max(float(np.linalg.norm(t)), 1e-12)


def _bridge(g: _Builder, paint: cKDTree, bridge_m: float, step_m: float) -> None:
    """Join free ends that continue each other across a hole in the line points, nearest pairs
    first: within ``bridge_m``, each end's direction pointing at the other within BRIDGE_DEG, and
    the straight join over paint all the way (every ``step_m``); then ends left within
    ``NEAR_BRIDGE * bridge_m`` of each other over paint (one band: a wrap over a rim)."""
    ends = []  # (branch id, at_start, point, outward direction)
    for i, (p, a, c) in g.branches.items():
        if len(p) < 2 or a == c:
            continue
        for at_start, k in ((True, a), (False, c)):
            if g.kind[k] == END:
                ends.append((i, at_start, *_end_direction(p, at_start, 0.02)))
    cos = np.cos(np.radians(BRIDGE_DEG))
    pairs = []
    for x in range(len(ends)):  # a few dozen ends
        for y in range(x + 1, len(ends)):
            (i, _, e, t), (j, _, f, u) = ends[x], ends[y]
            d = f - e
            dist = float(np.linalg.norm(d))
            ahead = d @ t >= cos * dist and -(d @ u) >= cos * dist
            if not 0 < dist <= (bridge_m if ahead else NEAR_BRIDGE * bridge_m):
                continue
            if i == j and polyline_length(g.branches[i][0]) < 3.0 * bridge_m:  # a closed line: only a long one
                continue
            line = e + np.linspace(0.0, 1.0, max(int(dist / step_m), 1) + 1)[:, None] * d
            if np.isfinite(paint.query(line, distance_upper_bound=1.5 * step_m)[0]).all():
                pairs.append((not ahead, dist, x, y))  # the ends that continue each other first
    used: set[int] = set()
    joined: dict[int, int] = {}  # a branch merged into another lives on under that one's id

    def alive(i: int) -> int:
        while i in joined:
            i = joined[i]
        return i

    for _, _, x, y in sorted(pairs):
        if x in used or y in used:
            continue
        (i, si, e, _), (j, sj, f, _) = ends[x], ends[y]
        i, j = alive(i), alive(j)
        if i == j:  # the two ends of one branch: a closed line
            p, a, c = g.branches.pop(i)
            if g.kind.get(a) != END or g.kind.get(c) != END:
                g.branches[i] = [p, a, c]
                continue
            for k in (a, c):
                del g.pos[k], g.kind[k]
            k = g.key(p[0], LOOP)
            g.branch(np.vstack([p, p[:1]]), k, k)
            used.update((x, y))
            continue
        p, a, c = g.branches[i]
        q, a2, c2 = g.branches[j]
        # orient so p ends at e and q starts at f
        if np.allclose(p[0], e):
            p, a, c = p[::-1], c, a
        if np.allclose(q[-1], f):
            q, a2, c2 = q[::-1], c2, a2
        for k in (c, a2):
            if g.kind.get(k) == END:
                del g.pos[k], g.kind[k]
        g.drop_branch(i)
        g.drop_branch(j)
        g.branch(np.vstack([p, q]), a, c2)
        new = g._next_branch - 1
        joined[i], joined[j] = new, new
        used.update((x, y))


def through_junctions(g: DrawingGraph, max_turn_deg: float = 45.0, near_m: float = 0.015, far_m: float = 0.04,
                      bridge_max_m: float = 0.15, cover_m: float = 0.01) -> list[tuple[np.ndarray, int, int]]:
    """The drawing's strokes: at a junction, the two branches that continue each other (their
    directions away from it within ``max_turn_deg`` of opposite) are joined into one polyline, so a
    crossing is cut straight through instead of stopping at it; the straightest pair first, and
    again at the next junction along. A branch's direction is taken between ``near_m`` and
    ``far_m`` from the junction: the skeleton bends toward the other branches right at it, so a
    stroke crosses a junction on the chord between its two branches' points ``near_m`` away.

    Two lines crossing at a shallow angle thin to two junctions and a bridge between them (an X
    becomes two Ys): a bridge shorter than ``bridge_max_m`` whose every point lies within
    ``cover_m`` of the chords of the strokes that would cross there instead is dropped and its two
    junctions become one (an H keeps its crossbar: no chord covers it).
    Returns (polyline, start node, end node) per stroke."""
    strokes = [[np.asarray(p, dtype=np.float64), a, b] for p, (a, b) in zip(g.branches, g.ends)]
    cos_max = -np.cos(np.radians(max_turn_deg))
    kinds = list(g.kinds)
    root = list(range(len(kinds)))

    def at(node: int) -> list[tuple[int, bool]]:
        """(stroke, whether it starts there) of every live stroke end at a (merged) junction."""
        return [(i, end == "start") for i, (p, a, b) in enumerate(strokes) if p is not None and a != b
                for end, n in (("start", a), ("end", b)) if _root(root, n) == node]

    for k, (p, a, b) in enumerate(strokes):  # bridges first
        if p is None or a == b or kinds[a] != JUNCTION or kinds[b] != JUNCTION or arc_length(p)[-1] > bridge_max_m:
            continue
        ra, rb = _root(root, a), _root(root, b)
        if ra == rb:
            continue
        others = [x for x in at(ra) + at(rb) if x[0] != k]
        pairs = _pairs([(i, s0, _away(strokes[i][0], s0, near_m, far_m)) for i, s0 in others], cos_max)
        chords = [(_point_back(strokes[i][0], si, near_m), _point_back(strokes[j][0], sj, near_m))
                  for (i, si), (j, sj) in pairs]
        if chords and _covered(p, chords, cover_m):
            root[rb] = ra
            strokes[k][0] = None
    for st in strokes:
        if st[0] is not None:
            st[1], st[2] = _root(root, st[1]), _root(root, st[2])

    for node in [i for i, kind in enumerate(kinds) if kind == JUNCTION and _root(root, i) == i]:  # a few junctions
        while True:
            ends = at(node)
            pair = _pairs([(i, s0, _away(strokes[i][0], s0, near_m, far_m)) for i, s0 in ends], cos_max)[:1]
            if not pair:
                break
            (i, i_starts), (j, j_starts) = pair[0]
            p, a, b = strokes[i]
            q, c, d = strokes[j]
            if i_starts:  # make p end at the junction
                p, a, b = p[::-1], b, a
            if not j_starts:  # make q start at it
                q, c, d = q[::-1], d, c
            p = p[: max(2, len(p) - int(np.searchsorted(arc_length(p[::-1]), near_m)))]
            q = q[min(int(np.searchsorted(arc_length(q), near_m)), max(len(q) - 2, 0)):]
            strokes[i] = [np.vstack([p, q]), a, d]
            strokes[j][0] = None
    return [(p, a, b) for p, a, b in strokes if p is not None]


def _away(p: np.ndarray, at_start: bool, near_m: float, far_m: float) -> np.ndarray | None:
    """Unit direction of a branch away from its junction end, between near_m and far_m along it."""
    q = p if at_start else p[::-1]
    s = arc_length(q)
    i = min(int(np.searchsorted(s, near_m)), len(q) - 1)
    j = min(int(np.searchsorted(s, far_m)), len(q) - 1)
    d = q[j] - q[i] if j > i else q[-1] - q[0]
    n = np.linalg.norm(d)
    return d / n if n > 1e-9 else None


def _point_back(p: np.ndarray, at_start: bool, dist: float) -> np.ndarray:
    """The branch's point ``dist`` along it from its junction end (its far end if shorter)."""
    q = p if at_start else p[::-1]
    return q[min(int(np.searchsorted(arc_length(q), dist)), len(q) - 1)]


def _pairs(dirs: list, cos_max: float) -> list[tuple[tuple[int, bool], tuple[int, bool]]]:
    """Greedy, straightest first: pairs of branch ends (stroke, starts there) whose directions away
    from the junction are within the turn of opposite (cosine below cos_max); each end used once."""
    dirs = [x for x in dirs if x[2] is not None]
    cand = sorted((float(dirs[u][2] @ dirs[v][2]), u, v) for u in range(len(dirs)) for v in range(u + 1, len(dirs))
                  if dirs[u][0] != dirs[v][0])  # a handful of branches meet at a junction
    used, out = set(), []
    for c, u, v in cand:
        if c < cos_max and u not in used and v not in used:
            used |= {u, v}
            out.append(((dirs[u][0], dirs[u][1]), (dirs[v][0], dirs[v][1])))
    return out


def _covered(p: np.ndarray, chords: list[tuple[np.ndarray, np.ndarray]], tol: float) -> bool:
    """Every point of p lies within tol of one of the segments."""
    a = np.array([c[0] for c in chords])
    b = np.array([c[1] for c in chords])
    ab = b - a
    t = np.clip(np.einsum("pkj,kj->pk", p[:, None, :] - a[None], ab) / np.maximum(np.einsum("kj,kj->k", ab, ab), 1e-18),
                0.0, 1.0)
    d = np.linalg.norm(p[:, None, :] - (a[None] + t[..., None] * ab[None]), axis=2)
    return bool((d.min(axis=1) <= tol).all())


def _root(root: list[int], i: int) -> int:
    """Union-find: the node a junction was merged into."""
    while root[i] != i:
        i = root[i]
    return i
