"""Spray paint on a mesh.

The drawing becomes its own set of faces so the renderer colours it exactly (no texture seams) and
the metrics get a ground truth cloud from the very faces the camera sees. Only the faces near the
drawing are refined (render cost), by splitting edges at their midpoints, which keeps the mesh
watertight (no T-junction cracks for the depth camera to see through), and flipping edges
toward Delaunay, which turns the long needles of a revolved pipe into well-shaped triangles.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

#: faces whose normal turns more than this far from the drawn side stay unpainted (the underside
#: of a thin plate lies within width/2 of the line, but no spray reaches it)
_MIN_NORMAL_DOT = -0.3


def resample_polyline(points: np.ndarray, step: float) -> np.ndarray:
    """(K,3) -> (M,3) points every `step` metres of arc length, both ends kept."""
    p = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0.0:
        return p[:1].copy()
    n = max(int(np.ceil(s[-1] / step)), 1) + 1
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, p[:, k]) for k in range(3)])


def polyline_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def closest_on_triangles(tri: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(N,3) closest point on each triangle (N,3,3) to each point (N,3) (Ericson, RTCD 5.1.5).

    Our own because trimesh's compares products of four lengths against a fixed 1e-13, which
    misplaces points by 0.1 mm on the millimetre faces near the paint.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac = b - a, c - a

    def dot(u, v):
        return np.einsum("ij,ij->i", u, v)

    ap, bp, cp = pts - a, pts - b, pts - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    safe = np.where(denom > 0, denom, 1.0)
    out = a + (vb / safe)[:, None] * ab + (vc / safe)[:, None] * ac  # inside the face
    done = np.zeros(len(pts), dtype=bool)

    def put(mask, value):
        mask = mask & ~done
        out[mask] = value[mask]
        done[mask] = True

    def frac(num, den):
        return (num / np.where(den != 0, den, 1.0))[:, None]

    put((d1 <= 0) & (d2 <= 0), a)
    put((d3 >= 0) & (d4 <= d3), b)
    put((d6 >= 0) & (d5 <= d6), c)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + frac(d1, d1 - d3) * ab)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + frac(d2, d2 - d6) * ac)
    put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + frac(d4 - d3, (d4 - d3) + (d5 - d6)) * (c - b))
    put(denom <= 0, a)  # degenerate leftovers
    return out


def closest_points(mesh: trimesh.Trimesh, points: np.ndarray):
    """Exact closest surface points -> (closest (N,3), distance (N,), triangle index (N,)).

    trimesh's own query needs rtree, which we do not ship. Triangles are grouped by size (radius
    about the centroid, within a factor of 2); per group a k-d tree on centroids gives the k
    nearest, k doubled until the k-th centroid is provably too far to hold a closer point. Fast
    for points on or near the surface; far points touch many faces.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri = mesh.triangles
    cen = tri.mean(axis=1)
    rad = np.linalg.norm(tri - cen[:, None, :], axis=2).max(axis=1)
    n = len(pts)
    best_d = np.full(n, np.inf)
    best_p = np.zeros((n, 3))
    best_t = np.zeros(n, dtype=np.int64)

    def consider(pi, ti):
        cp = closest_on_triangles(tri[ti], pts[pi])
        d = np.linalg.norm(cp - pts[pi], axis=1)
        order = np.lexsort((d, pi))  # per point, nearest first
        pi, ti, d, cp = pi[order], ti[order], d[order], cp[order]
        first = np.ones(len(pi), dtype=bool)
        first[1:] = pi[1:] != pi[:-1]
        pi, ti, d, cp = pi[first], ti[first], d[first], cp[first]
        better = d < best_d[pi]
        pi = pi[better]
        best_d[pi], best_p[pi], best_t[pi] = d[better], cp[better], ti[better]

    level = np.floor(np.log2(np.maximum(rad, 1e-6))).astype(np.int64)
    groups = [np.flatnonzero(level == g) for g in np.unique(level)]
    trees = [cKDTree(cen[g]) for g in groups]
    for g, tree in zip(groups, trees):  # a first bound from a few nearby faces of every size
        k = min(4, len(g))
        idx = tree.query(pts, k=k)[1].reshape(n, -1)
        consider(np.repeat(np.arange(n), k), g[idx.ravel()])
    for g, tree in zip(groups, trees):
        reach = rad[g].max()
        todo = np.arange(n)
        k = min(8, len(g))
        while len(todo) and k <= len(g):
            dist, idx = tree.query(pts[todo], k=k)
            dist, idx = dist.reshape(len(todo), -1), idx.reshape(len(todo), -1)
            consider(np.repeat(todo, k), g[idx.ravel()])
            todo = todo[(dist[:, -1] <= best_d[todo] + reach) & (k < len(g))]
            k = min(2 * k, len(g))
    return best_p, best_d, best_t


def raycasting_scene(mesh):
    """(Open3D RaycastingScene of a trimesh, the centre it is taken about): its BVH answers many
    distance and ray queries at once. Float32 inside, so the mesh is moved to about its centre first
    (0.1 µm at 1 m); queries subtract the centre too."""
    import open3d as o3d

    c = np.asarray(mesh.vertices, dtype=np.float64).mean(axis=0)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor((np.asarray(mesh.vertices) - c).astype(np.float32)),
                     o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    return rs, c


def distance_to_mesh(mesh, points: np.ndarray) -> np.ndarray:
    """(N,) distances of points to a trimesh's surface, as ``closest_points`` gives them: Open3D's BVH,
    for many points off a mesh of every face size (a scan's flame tips), where the k-d tree over face
    centres touches many faces."""
    import open3d as o3d

    rs, c = raycasting_scene(mesh)
    q = o3d.core.Tensor((np.asarray(points, dtype=np.float64).reshape(-1, 3) - c).astype(np.float32))
    return rs.compute_distance(q).numpy().astype(np.float64)


def _split_edges(vertices: np.ndarray, faces: np.ndarray, split_edge) -> tuple[np.ndarray, np.ndarray]:
    """Split the edges for which `split_edge(unique_edges, lengths)` is True at their midpoints.

    Splitting by edge (not by face) keeps the mesh conforming with no closure pass: both faces of
    an edge see the same decision. A face with 1, 2 or 3 split edges becomes 2, 3 or 4 triangles.
    """
    nv = len(vertices)
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    key = e[:, 0].astype(np.int64) * nv + e[:, 1]
    ukey, inv = np.unique(key, return_inverse=True)
    fe = inv.reshape(-1, 3)  # edge k of a face joins its vertices k and k+1
    ea, eb = ukey // nv, ukey % nv
    marked = split_edge(fe, np.linalg.norm(vertices[ea] - vertices[eb], axis=1))
    mids = np.flatnonzero(marked)
    mid_id = np.full(len(ukey), -1, dtype=np.int64)
    mid_id[mids] = nv + np.arange(len(mids))
    vertices = np.vstack([vertices, 0.5 * (vertices[ea[mids]] + vertices[eb[mids]])])

    fm = marked[fe]
    count = fm.sum(axis=1)
    # roll each face so its pattern is canonical, winding kept: one split edge -> it is ab;
    # two -> the unsplit one is bc; three -> any
    first = np.where(count == 1, np.argmax(fm, axis=1), np.where(count == 2, (np.argmin(fm, axis=1) + 2) % 3, 0))
    rows = np.arange(len(faces))
    roll = (first[:, None] + np.arange(3)) % 3
    a, b, c = (faces[rows, roll[:, i]] for i in range(3))
    m, p, q = (mid_id[fe[rows, roll[:, i]]] for i in range(3))  # midpoints of ab, bc, ca
    out = [faces[count == 0]]
    s = count == 1
    out += [np.column_stack([a[s], m[s], c[s]]), np.column_stack([m[s], b[s], c[s]])]
    s = count == 2
    # the quad m-b-c-q is cut along its shorter diagonal
    mc = np.linalg.norm(vertices[m[s]] - vertices[c[s]], axis=1)
    bq = np.linalg.norm(vertices[b[s]] - vertices[q[s]], axis=1)
    t, u = s.copy(), s.copy()
    t[s], u[s] = mc <= bq, mc > bq
    out += [np.column_stack([a[s], m[s], q[s]]),
            np.column_stack([m[t], b[t], c[t]]), np.column_stack([m[t], c[t], q[t]]),
            np.column_stack([m[u], b[u], q[u]]), np.column_stack([b[u], c[u], q[u]])]
    s = count == 3
    out += [np.column_stack([a[s], m[s], q[s]]), np.column_stack([m[s], b[s], p[s]]),
            np.column_stack([q[s], p[s], c[s]]), np.column_stack([m[s], p[s], q[s]])]
    return vertices, np.vstack(out)


def _flip_pass(vertices: np.ndarray, faces: np.ndarray, active: np.ndarray, max_bend: float = 5e-5):
    """Flip non-Delaunay edges between nearly coplanar `active` faces -> (faces, n_flipped).

    A flip may move the surface by at most `max_bend` (the height of the fourth vertex over the
    first face's plane), far below the depth noise, so curved surfaces get flips too.

    Midpoint splits alone keep a needle (the diagonal of a long pipe facet) a needle at every
    scale; flips turn the split pieces into well-shaped triangles. Each face takes part in at most
    one flip per pass, so the pass is a plain array update.
    """
    nv = len(vertices)
    fidx = np.repeat(np.flatnonzero(active), 3)
    loc = np.tile(np.arange(3), len(fidx) // 3)
    a, b = faces[fidx, loc], faces[fidx, (loc + 1) % 3]
    key = np.minimum(a, b).astype(np.int64) * nv + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    pair = np.flatnonzero(ks[1:] == ks[:-1])
    pair = pair[((pair + 2 >= len(ks)) | (ks[np.minimum(pair + 2, len(ks) - 1)] != ks[pair]))
                & ((pair == 0) | (ks[pair - 1] != ks[pair]))]  # manifold edges only
    h1, h2 = order[pair], order[pair + 1]
    f1, f2, k1, k2 = fidx[h1], fidx[h2], loc[h1], loc[h2]
    a, b = faces[f1, k1], faces[f1, (k1 + 1) % 3]
    c, d = faces[f1, (k1 + 2) % 3], faces[f2, (k2 + 2) % 3]
    ok = (faces[f2, k2] == b) & (c != d)  # consistent winding
    pa, pb, pc, pd = vertices[a], vertices[b], vertices[c], vertices[d]
    n1 = np.cross(pb - pa, pc - pa)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True) + 1e-300
    ok &= np.abs(np.einsum("ij,ij->i", pd - pa, n1)) <= max_bend

    def angle(p, q, r):  # at p
        u, w = q - p, r - p
        cosv = np.einsum("ij,ij->i", u, w) / (np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1) + 1e-300)
        return np.arccos(np.clip(cosv, -1.0, 1.0))

    excess = angle(pc, pa, pb) + angle(pd, pb, pa) - np.pi
    ok &= excess > 1e-6
    # the new faces (a,d,c), (d,b,c) must keep the orientation: the quad is convex
    ok &= np.einsum("ij,ij->i", np.cross(pd - pa, pc - pa), n1) > 0
    ok &= np.einsum("ij,ij->i", np.cross(pb - pd, pc - pd), n1) > 0
    cand = np.flatnonzero(ok)
    if not len(cand):
        return faces, 0
    # an edge already present between c and d would become doubled
    cd = np.minimum(c[cand], d[cand]).astype(np.int64) * nv + np.maximum(c[cand], d[cand])
    pos = np.searchsorted(ks, cd).clip(max=len(ks) - 1)
    cand = cand[ks[pos] != cd]
    # independent set: an edge flips when it is the worst edge of both its faces
    best = np.full(len(faces), -1.0)
    np.maximum.at(best, f1[cand], excess[cand])
    np.maximum.at(best, f2[cand], excess[cand])
    cand = cand[(best[f1[cand]] == excess[cand]) & (best[f2[cand]] == excess[cand])]
    _, first = np.unique(f1[cand], return_index=True)  # ties: one flip per face
    cand = cand[first]
    _, first = np.unique(f2[cand], return_index=True)
    cand = cand[first]
    cand = cand[~np.isin(f1[cand], f2[cand])]  # (small arrays)
    faces = faces.copy()
    faces[f1[cand]] = np.column_stack([a[cand], d[cand], c[cand]])
    faces[f2[cand]] = np.column_stack([d[cand], b[cand], c[cand]])
    return faces, len(cand)


def _refine_near(mesh: trimesh.Trimesh, samples: np.ndarray, radius: float, max_edge: float):
    """Split longest edges (then flip) until every face with a point within `radius` of the
    samples has edges <= max_edge. Longest-edge splits keep shapes bounded; flips then fix needles.

    No point of a face whose longest edge is L lies nearer than (its nearest vertex's distance - L),
    so the test is conservative for large faces and tightens as they shrink.
    """
    tree = cKDTree(samples)
    v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    for _ in range(64):
        longest = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2).max(axis=1)
        d = tree.query(v, distance_upper_bound=radius + longest.max())[0]
        near = (longest > max_edge) & (d[f].min(axis=1) <= radius + longest)
        if not near.any():
            break

        def split_edge(fe, length, near=near):  # the longest edge of each near face
            marked = np.zeros(len(length), dtype=bool)
            fe = fe[near]
            marked[fe[np.arange(len(fe)), np.argmax(length[fe], axis=1)]] = True
            return marked

        v, f = _split_edges(v, f, split_edge)
        d = tree.query(v, distance_upper_bound=2 * radius)[0]
        active = (d[f] < np.inf).any(axis=1)
        for _ in range(8):
            f, n = _flip_pass(v, f, active)
            if not n:
                break
    return trimesh.Trimesh(v, f, process=False)


def paint_surface(mesh: trimesh.Trimesh, polylines: list[np.ndarray], width: float,
                  max_edge: float = 0.004, *, margin: float = 0.01, step: float = 0.001,
                  max_offset: float | None = None):
    """Paint a line of `width` along `polylines` -> (object_mesh, paint_mesh, projected_polylines).

    Polylines are resampled every `step` and projected onto the surface. With `max_offset`, points
    farther than that from the surface are dropped: they hang over a gap (a basket's bars), where
    the spray hits nothing. The returned polylines are the projected samples (gaps become jumps).
    Faces within width/2 + `margin` get edges <= `max_edge`; a face is paint when its centroid
    lies within width/2 of the projected line and it faces the drawn side.
    """
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)  # merged: bisection needs shared edges
    dense = [resample_polyline(p, step) for p in polylines]
    counts = np.cumsum([len(p) for p in dense])[:-1]
    proj, dist, tri = closest_points(mesh, np.vstack(dense))
    normals = mesh.face_normals[tri]
    keep = np.ones(len(proj), dtype=bool) if max_offset is None else dist <= max_offset
    lines = [p[k] for p, k in zip(np.split(proj, counts), np.split(keep, counts))]
    if any(len(p) < 2 for p in lines):
        raise ValueError("a polyline has fewer than 2 points on the surface")
    samples, normals = proj[keep], normals[keep]

    fine = _refine_near(mesh, samples, width / 2 + margin, max_edge)
    d, nearest = cKDTree(samples).query(fine.triangles_center)
    facing = np.einsum("ij,ij->i", fine.face_normals, normals[nearest]) > _MIN_NORMAL_DOT
    paint = (d <= width / 2) & facing
    if not paint.any():
        raise ValueError("the drawing paints no face")
    if paint.all():
        raise ValueError("the drawing covers the whole object")
    object_mesh = trimesh.Trimesh(fine.vertices, fine.faces[~paint], process=False)
    paint_mesh = trimesh.Trimesh(fine.vertices, fine.faces[paint], process=False)
    object_mesh.remove_unreferenced_vertices()
    paint_mesh.remove_unreferenced_vertices()
    return object_mesh, paint_mesh, lines


def sample_painted(paint_mesh: trimesh.Trimesh, spacing: float = 0.002, seed: int = 0) -> np.ndarray:
    """(N,3) float32 roughly uniform samples of the painted area, about one per `spacing`-sized
    cell: over-sample by area, then keep one point per voxel. Deterministic for a given seed."""
    areas = paint_mesh.area_faces
    total = float(areas.sum())
    n = int(np.ceil(4.0 * total / spacing**2)) + 1
    rng = np.random.default_rng(seed)
    face = rng.choice(len(areas), size=n, p=areas / total)
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    tri = paint_mesh.triangles[face]
    pts = ((1 - r1)[:, None] * tri[:, 0] + (r1 * (1 - r2))[:, None] * tri[:, 1]
           + (r1 * r2)[:, None] * tri[:, 2])
    cells = np.floor(pts / spacing).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return pts[np.sort(first)].astype(np.float32)


def free_ends(polylines: list[np.ndarray], tol: float = 0.01) -> np.ndarray:
    """(E,3) polyline endpoints that no other polyline passes within `tol` of (a line that starts
    on another one is a branch, not an extremity; a closed loop has no ends)."""
    ends = []
    for i, p in enumerate(polylines):
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        for end, far in ((p[0], s > 2 * tol), (p[-1], s < s[-1] - 2 * tol)):
            others = [q for j, q in enumerate(polylines) if j != i] + [p[far]]
            others = np.vstack([q for q in others if len(q)] or [np.full((1, 3), np.inf)])
            if np.linalg.norm(others - end, axis=1).min() > tol:
                ends.append(end)
    return np.array(ends, dtype=np.float64).reshape(-1, 3)
