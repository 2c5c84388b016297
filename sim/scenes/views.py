"""Initial views: camera poses that each see part of the drawing (the paper's task #1, assumed done).

The runner takes the first candidate the arm can reach, so candidates are ordered best first:
a point a quarter of the way along the first polyline (so the planner still has to explore both
ways), seen along the surface normal tilted up, since a Panda on the floor reaches down-looking
poses most easily.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sim.scenes.model import Scene
from sim.scenes.paint import closest_points, raycasting_scene

FRACTIONS = (0.25, 0.2, 0.3, 0.15, 0.35, 0.5, 0.75)
#: weight of +z added to the unit normal: 1 views a wall from 45 deg above, 2 from 63 deg, 0.5 from 27
UP_BLENDS = (1.0, 2.0, 0.5)


def look_at(eye, target, up_hint=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_base_cam of an optical frame at `eye` with z toward `target`, x perpendicular to z and as
    horizontal as `up_hint` allows, y down (image up is up_hint)."""
    eye, target = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    z = target - eye
    n = np.linalg.norm(z)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError("eye and target coincide")
    z /= n
    x = np.cross(z, np.asarray(up_hint, dtype=np.float64))
    if np.linalg.norm(x) < 1e-6:  # looking along the hint: any horizontal x will do
        x = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def sight_blocked(mesh, eyes: np.ndarray, targets: np.ndarray, short_m: float = 0.0) -> np.ndarray:
    """(M,) bool: does the sight line eye->target, stopped ``short_m`` before the target (its own
    face), cross the trimesh ``mesh``? One ray per line through Open3D's BVH (``raycasting_scene``)."""
    import open3d as o3d

    eyes = np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    if len(eyes) == 0:
        return np.zeros(0, dtype=bool)
    rs, c = raycasting_scene(mesh)
    d = targets - eyes
    dist = np.linalg.norm(d, axis=1)
    unit = d / np.maximum(dist, 1e-12)[:, None]
    t = rs.cast_rays(o3d.core.Tensor(np.hstack([eyes - c, unit]).astype(np.float32)))["t_hit"].numpy()
    return (dist > 1e-9) & np.isfinite(t) & (t < dist - short_m)


def _clearance(mesh, points: np.ndarray, spacing: float = 0.005) -> np.ndarray:
    """Distance to the surface within about `spacing`, from a point sampling of it: exact queries
    from far away touch too many faces of a finely painted mesh."""
    n = int(np.ceil(mesh.area / spacing**2))
    samples = mesh.sample(n, seed=0) if n else mesh.vertices
    return cKDTree(np.vstack([samples, mesh.vertices])).query(points)[0]


#: fewer views than this along the normals (a line inside a V, under an overhang): look all round too
FEW_VIEWS = 4
ROUND_DIRECTIONS = 160  # directions over the sphere tried then (the upper ones kept)
ROUND_MOST = 24  # views so found, at most


def _sphere(n: int) -> np.ndarray:
    """(n,3) unit vectors spread evenly over the sphere (the Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1.0 - 2.0 * i / n), np.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)])


def _views_round(mesh, targets: np.ndarray, normals: np.ndarray, standoff: float, min_eye_z: float,
                 min_clearance: float, end_gap: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(eye, target) pairs from all round each target, when the blended normals give few views: a line
    inside a fold's V or under an overhang is seen from few directions, none of them near its normal plus
    up (scrap:0:19, a fold opening towards the arm's base: one view, none reachable). Eyes in front of
    the paint's face, above ``min_eye_z``, clear of the piece, with an open sight line (Open3D's ray
    casting); ordered by the angle from the normal tilted up, the nearest ``ROUND_MOST``."""
    d = _sphere(ROUND_DIRECTIONS)
    d = d[d[:, 2] > 0.05]
    k = np.arange(len(targets))
    ti, di, si = (a.ravel() for a in np.meshgrid(k, np.arange(len(d)), np.array([1.0, 1.3]), indexing="ij"))
    eyes = targets[ti] + standoff * si[:, None] * d[di]
    ok = (np.einsum("ij,ij->i", d[di], normals[ti]) > 0.1) & (eyes[:, 2] >= min_eye_z)
    ok[ok] &= _clearance(mesh, eyes[ok]) >= min_clearance
    ok &= ~sight_blocked(mesh, eyes, targets[ti], end_gap)
    up = normals[ti] + np.array([0.0, 0.0, 1.0])
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    order = np.argsort(-np.einsum("ij,ij->i", d[di], up)[ok], kind="stable")[:ROUND_MOST]
    return list(zip(eyes[ok][order], targets[ti][ok][order]))


def initial_views(scene: Scene, standoff: float = 0.35, fractions=FRACTIONS, up_blends=UP_BLENDS,
                  min_eye_z: float = 0.15, min_clearance: float = 0.1, end_gap: float = 0.005) -> np.ndarray:
    """(M,4,4) T_base_cam candidates, best first; the scene's fixed initial camera leads.

    Eyes below `min_eye_z`, nearer than `min_clearance` to the object (no room for the hand), or
    whose sight line is blocked short of `end_gap` before the target are dropped.
    """
    mesh = scene.full_mesh
    line = scene.drawing_polylines[0]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    idx = np.searchsorted(arc, np.asarray(fractions) * arc[-1]).clip(0, len(line) - 1)
    # the normal averaged over +-15 mm of line, so a point on a sharp rim gets a sensible one
    window = (np.abs(arc[None, :] - arc[idx, None]) <= 0.015)
    _, _, tri = closest_points(mesh, line[window.any(axis=0)])
    face_n = np.zeros((len(line), 3))
    face_n[window.any(axis=0)] = mesh.face_normals[tri]
    normals = window.astype(np.float64) @ face_n
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12

    targets = np.repeat(line[idx], len(up_blends), axis=0)
    dirs = np.repeat(normals, len(up_blends), axis=0) + np.tile(up_blends, len(idx))[:, None] * [0.0, 0.0, 1.0]
    norm = np.linalg.norm(dirs, axis=1, keepdims=True)
    ok = norm[:, 0] > 1e-6
    eyes = targets + standoff * dirs / np.where(norm > 1e-6, norm, 1.0)
    ok &= eyes[:, 2] >= min_eye_z
    ok[ok] &= _clearance(mesh, eyes[ok]) >= min_clearance
    ok[ok] &= ~sight_blocked(mesh, eyes[ok], targets[ok], end_gap)
    poses = [look_at(e, t) for e, t in zip(eyes[ok], targets[ok])]
    if len(poses) < FEW_VIEWS:
        poses += [look_at(e, t) for e, t in _views_round(mesh, line[idx], normals, standoff, min_eye_z, min_clearance,
                                                        end_gap)]
    if scene.initial_camera_pose is not None:
        poses.insert(0, np.asarray(scene.initial_camera_pose, dtype=np.float64))
    return np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
