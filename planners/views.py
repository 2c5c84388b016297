"""Camera-pose geometry shared by the planners: look-at rotations and ray bundles, vectorized."""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


def look_at_rotations(eyes: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """R_base_cam (M,3,3) with the optical axis (z) from each eye to its target and the image's
    up (-y) as close to world up as the axis allows. Roll stays free for IK anyway."""
    eyes = np.atleast_2d(eyes).astype(np.float64)
    targets = np.broadcast_to(np.atleast_2d(targets), eyes.shape).astype(np.float64)
    z = targets - eyes
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    up = np.broadcast_to(WORLD_UP, z.shape).copy()
    degenerate = np.abs(z @ WORLD_UP) > 0.999
    up[degenerate] = [1.0, 0.0, 0.0]
    up_perp = up - (np.sum(up * z, axis=1, keepdims=True)) * z
    up_perp /= np.linalg.norm(up_perp, axis=1, keepdims=True)
    y = -up_perp
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=2)


def roll_along(rotations: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The same optical axes, each rolled so the image's wide axis (x: 87 of the D435's 87 x 58 deg)
    lies along ``directions`` (C,3) as seen by that camera, image up kept toward world up. A
    direction (nearly) along the optical axis leaves that rotation as it was."""
    R = np.array(rotations, dtype=np.float64)
    z = R[:, :, 2]
    d = np.broadcast_to(np.asarray(directions, dtype=np.float64), z.shape)
    dp = d - np.sum(d * z, axis=1, keepdims=True) * z
    n = np.linalg.norm(dp, axis=1)
    ok = n > 0.2 * np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    x = dp[ok] / n[ok, None]
    y = np.cross(z[ok], x)
    flip = (y @ WORLD_UP) > 0  # image up (-y) toward world up
    x[flip], y[flip] = -x[flip], -y[flip]
    R[ok, :, 0], R[ok, :, 1] = x, y
    return R


def quarter_turn(rotations: np.ndarray) -> np.ndarray:
    """The same optical axes, each image turned 90 deg about it: the wide axis where the narrow one
    was (a framed view is scored at both)."""
    R0 = np.asarray(rotations, dtype=np.float64)
    R = R0.copy()
    R[..., 0], R[..., 1] = R0[..., 1], -R0[..., 0]
    return R


def poses_from(eyes: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(eyes), 1, 1))
    T[:, :3, :3] = rotations
    T[:, :3, 3] = eyes
    return T


def ray_bundle(K: np.ndarray, image_size: tuple[int, int], n_w: int, n_h: int) -> np.ndarray:
    """Unit ray directions (n_w*n_h, 3) in the optical frame through an even grid of pixels."""
    w, h = image_size
    us = (np.arange(n_w) + 0.5) * (w / n_w)
    vs = (np.arange(n_h) + 0.5) * (h / n_h)
    uu, vv = np.meshgrid(us, vs)
    d = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], axis=-1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def sphere_lattice(radius: float, inner: float, spacing: float) -> np.ndarray:
    """Offsets of a cubic lattice inside a spherical shell: the candidate search primitive S(f)."""
    n = int(np.ceil(radius / spacing))
    ax = np.arange(-n, n + 1) * spacing
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)
    r = np.linalg.norm(g, axis=1)
    return g[(r <= radius) & (r >= inner)]


def surface_normal(points: np.ndarray, center: np.ndarray, radius: float, toward: np.ndarray,
                   max_curvature: float = 0.05) -> np.ndarray | None:
    """PCA normal of the surface points near `center`, flipped to face `toward` (a viewpoint that saw
    them). None when too few points or where the patch is not a plane (an edge or corner, whose
    "normal" would forbid exactly the views that see round it): surface variation
    λ_min / Σλ above `max_curvature`."""
    d2 = np.sum((points - center) ** 2, axis=1)
    near = points[d2 < radius * radius]
    if len(near) < 10:
        return None
    c = near - near.mean(axis=0)
    _, sv, vt = np.linalg.svd(c.astype(np.float64), full_matrices=False)
    ev = sv ** 2
    if ev[2] / max(ev.sum(), 1e-18) > max_curvature:
        return None
    n = vt[2]
    if np.dot(n, toward - center) < 0:
        n = -n
    return n / np.linalg.norm(n)


def in_image(eyes: np.ndarray, rotations: np.ndarray, points: np.ndarray, K: np.ndarray,
             image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(C, M) depth of each point along each camera's axis (eyes (C,3), R_base_cam (C,3,3)), and
    whether it lands in that camera's image in front of it."""
    cam = np.einsum("cji,cmj->cmi", rotations, points[None, :, :] - eyes[:, None, :])  # R^T (p - e)
    z = cam[..., 2]
    zs = np.maximum(z, 1e-9)
    u = K[0, 0] * cam[..., 0] / zs + K[0, 2]
    v = K[1, 1] * cam[..., 1] / zs + K[1, 2]
    w, h = image_size
    return z, (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
