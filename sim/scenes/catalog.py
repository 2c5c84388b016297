"""The built-in test objects: the paper's six feature categories plus its branched drawing.

Each builder makes the object in its own frame with the drawing defined analytically on the
surface, and a pose T_base_obj that puts every drawing point within the Panda's reach with room
for a camera 0.3-0.4 m off the paint. `assemble_scene` (shared with user scene files) paints,
moves everything into the base frame and adds ground truth and initial views.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

from sim.scenes.model import Scene
from sim.scenes.paint import free_ends, paint_surface, sample_painted
from sim.scenes.views import initial_views


@dataclass
class Blueprint:
    """An object before painting: everything in the object frame except the pose."""

    mesh: trimesh.Trimesh
    polylines: list[np.ndarray]
    width: float
    T_base_obj: np.ndarray
    category: int | None
    max_offset: float | None = None  # drop drawing points this far off the surface (gaps)


def assemble_scene(name: str, bp: Blueprint, *, object_rgb=None, paint_rgb=None,
                   initial_camera_pose: np.ndarray | None = None) -> Scene:
    """Paint, move into the base frame, sample the ground truth, find extremities and views."""
    obj, paint, lines = paint_surface(bp.mesh, bp.polylines, bp.width, max_offset=bp.max_offset)
    T = np.asarray(bp.T_base_obj, dtype=np.float64)
    obj.apply_transform(T)
    paint.apply_transform(T)
    lines = [p @ T[:3, :3].T + T[:3, 3] for p in lines]
    colors = {k: tuple(float(c) for c in v) for k, v in
              (("object_rgb", object_rgb), ("paint_rgb", paint_rgb)) if v is not None}
    scene = Scene(name=name, category=bp.category, object_mesh=obj, paint_mesh=paint,
                  drawing_polylines=lines, drawing_width=float(bp.width),
                  gt_points=sample_painted(paint), extremities=free_ends(lines),
                  initial_camera_pose=initial_camera_pose, **colors)
    scene.initial_view_candidates = initial_views(scene)
    return scene


# --- geometry helpers -------------------------------------------------------------------------

def _translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def _revolve_y(profile: list[tuple[float, float]], sections: int = 128) -> trimesh.Trimesh:
    """Solid of revolution about the object y axis from a (radius, y) profile closed on the axis."""
    mesh = trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # z -> y
    return mesh


def _on_pipe(radius, y, theta) -> np.ndarray:
    """Points on a pipe about the y axis; theta is measured from +z toward +x (the far side)."""
    radius, y, theta = np.broadcast_arrays(radius, y, theta)
    return np.column_stack([radius * np.sin(theta), y, radius * np.cos(theta)])


def _union(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return trimesh.boolean.union(meshes, engine="manifold")


# --- the objects ------------------------------------------------------------------------------

def smooth_cylinder() -> Blueprint:
    """Cat. 1: a 0.7 m pipe lying across the robot, a long helix-like line over its top."""
    r = 0.12
    mesh = _revolve_y([(0, -0.35), (r, -0.35), (r, 0.35), (0, 0.35)])
    t = np.linspace(0.0, 1.0, 800)
    theta = np.radians(-40 + 90 * t + 12 * np.sin(2 * np.pi * t))
    line = _on_pipe(r, -0.32 + 0.64 * t, theta)
    return Blueprint(mesh, [line], 0.02, _translation(0.43, 0.0, r), 1)


def sharp_cylinder() -> Blueprint:
    """Cat. 2: a pipe through a collar; the line climbs over the collar and goes on behind it,
    where the collar hides it from any view on the near side."""
    r, rc, hc, half = 0.09, 0.15, 0.025, 0.32
    mesh = _revolve_y([(0, -half), (r, -half), (r, -hc), (rc, -hc), (rc, hc), (r, hc), (r, half), (0, half)])
    end = 0.29

    def theta(y):
        return np.radians(10 + 20 * (y + end) / (2 * end))

    s = np.linspace(0.0, 1.0, 300)
    y_in, y_out = -end + (end - hc) * s, hc + (end - hc) * s
    ramp = r + (rc - r) * s
    line = np.vstack([
        _on_pipe(r, y_in, theta(y_in)),                   # along the pipe
        _on_pipe(ramp, -hc, theta(-hc)),                  # up the collar's near face
        _on_pipe(rc, -hc + 2 * hc * s, theta(-hc + 2 * hc * s)),  # over its rim
        _on_pipe(ramp[::-1], hc, theta(hc)),              # down the far face
        _on_pipe(r, y_out, theta(y_out)),                 # on behind it
    ])
    return Blueprint(mesh, [line], 0.02, _translation(0.45, 0.0, rc), 2)


def round_tank() -> Blueprint:
    """Cat. 3: a tank with a hemispherical end; the line runs along the top and wraps over the
    dome onto its far face, which the dome's own curvature hides from the top views."""
    r, y_flat, y_dome = 0.15, -0.3, 0.1
    arc = np.linspace(0.0, np.pi / 2, 33)
    profile = [(0, y_flat), (r, y_flat)] + [(r * np.cos(a), y_dome + r * np.sin(a)) for a in arc]
    profile[-1] = (0.0, y_dome + r)
    mesh = _revolve_y(profile)
    s = np.linspace(0.0, 1.0, 400)
    y = -0.25 + (y_dome + 0.25) * s
    body = _on_pipe(r, y, np.radians(-45) * (1 - s) ** 2)
    g = np.radians(115) * s  # from the top of the rim over the apex and down the far face
    phi = np.radians(25) * s**2
    dome = np.column_stack([r * np.cos(g) * np.sin(phi), y_dome + r * np.sin(g), r * np.cos(g) * np.cos(phi)])
    return Blueprint(mesh, [np.vstack([body, dome[1:]])], 0.025, _translation(0.42, 0.0, r), 3)


def t_piece() -> Blueprint:
    """Cat. 4: a T junction (boolean union); the line runs along the main pipe, turns sharply at
    the saddle and climbs the branch, twisting round it toward the robot."""
    r, rb, yb, top = 0.08, 0.06, 0.08, 0.49
    main = trimesh.creation.cylinder(radius=r, height=0.56, sections=96)
    main.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    main.apply_translation([0.0, -0.1, 0.0])  # y from -0.38 to 0.18
    branch = trimesh.creation.cylinder(radius=rb, height=top, sections=96)
    branch.apply_translation([0.0, yb, top / 2])
    mesh = _union([main, branch])
    beta0 = np.radians(-30)  # where on the branch the line meets it; 0 faces -y, <0 faces the robot
    x0 = rb * np.sin(beta0)
    y_j, z_j = yb - rb * np.cos(beta0), np.sqrt(r**2 - x0**2)
    s = np.linspace(0.0, 1.0, 400)
    along = np.column_stack([np.full_like(s, x0), -0.34 + (y_j + 0.34) * s, np.full_like(s, z_j)])
    beta = beta0 + np.radians(-45) * s
    up = np.column_stack([rb * np.sin(beta), yb - rb * np.cos(beta), z_j + (0.45 - z_j) * s])
    return Blueprint(mesh, [np.vstack([along, up[1:]])], 0.02, _translation(0.47, 0.0, r), 4)


def i_beam() -> Blueprint:
    """Cat. 5: an I-beam on its flange edges; the line crosses flange, web and flange, over two
    sharp rims and into the trench between the flanges."""
    length, depth, height, tf, tw = 0.5, 0.26, 0.2, 0.012, 0.01
    flange = [trimesh.creation.box([length, tf, height], trimesh.transformations.translation_matrix(
        [0.0, sgn * depth / 2, height / 2])) for sgn in (-1, 1)]
    web = trimesh.creation.box([length, depth, tw], trimesh.transformations.translation_matrix(
        [0.0, 0.0, height / 2]))
    mesh = _union(flange + [web])
    yo, yi, zw, zl = depth / 2 + tf / 2, depth / 2 - tf / 2, height / 2 + tw / 2, 0.115
    corners = np.array([(-yo, zl), (-yo, height), (-yi, height), (-yi, zw),
                        (yi, zw), (yi, height), (yo, height), (yo, zl)])
    seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.linspace(0.0, arc[-1], 1500)
    s = np.union1d(s, arc)  # keep the corners exact
    yz = np.column_stack([np.interp(s, arc, corners[:, 0]), np.interp(s, arc, corners[:, 1])])
    x = -0.07 + 0.14 * s / arc[-1]  # sprayed at a slant across the beam
    line = np.column_stack([x, yz])
    return Blueprint(mesh, [line], 0.02, _translation(0.5, 0.0, 0.0), 5)


def basket() -> Blueprint:
    """Cat. 6: a half-cylinder cage of 16 rods; the line crosses 13 of them, paint only where
    the spray meets a rod."""
    rc, rr, length = 0.2, 0.008, 0.4
    angles = np.radians(np.arange(-90, 91, 12))
    rods = []
    for a in angles:
        rod = trimesh.creation.cylinder(radius=rr, height=length, sections=16)
        rod.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))  # z -> x
        rod.apply_translation([0.0, rc * np.sin(a), rc * np.cos(a)])
        rods.append(rod)
    keep_top = trimesh.creation.box([1.0, 1.0, 1.0], trimesh.transformations.translation_matrix([0, 0, 0.5]))
    hoops = []
    for x in (-0.18, 0.18):
        ring = trimesh.creation.torus(rc, rr, major_sections=96, minor_sections=12)
        ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))  # axis z -> x
        ring.apply_translation([x, 0.0, 0.0])
        hoops.append(trimesh.boolean.intersection([ring, keep_top], engine="manifold"))
    mesh = _union(rods + hoops)
    psi = np.radians(np.linspace(-72, 72, 1500))
    line = np.column_stack([0.06 * psi / psi[-1], (rc + rr) * np.sin(psi), (rc + rr) * np.cos(psi)])
    return Blueprint(mesh, [line], 0.025, _translation(0.5, 0.0, rr), 6, max_offset=0.003)


def branched_cylinder() -> Blueprint:
    """The paper's Fig. 9: a pipe with two crossing lines, a drawing with four extremities."""
    r = 0.12
    mesh = _revolve_y([(0, -0.3), (r, -0.3), (r, 0.3), (0, 0.3)])
    t = np.linspace(0.0, 1.0, 600)
    y = -0.24 + 0.48 * t
    a = _on_pipe(r, y, np.radians(-40 + 85 * t))
    b = _on_pipe(r, y, np.radians(45 - 85 * t + 12 * np.sin(np.pi * t)))
    return Blueprint(mesh, [a, b], 0.02, _translation(0.45, 0.0, r), None)


BUILDERS: dict[str, Callable[[], Blueprint]] = {
    "smooth_cylinder": smooth_cylinder,
    "sharp_cylinder": sharp_cylinder,
    "round_tank": round_tank,
    "t_piece": t_piece,
    "i_beam": i_beam,
    "basket": basket,
    "branched_cylinder": branched_cylinder,
}
SCENE_NAMES: tuple[str, ...] = tuple(BUILDERS)


@functools.lru_cache(maxsize=None)
def _cached(name: str) -> Scene:
    return assemble_scene(name, BUILDERS[name]())


def copy_scene(scene: Scene) -> Scene:
    """A deep copy, so callers may move or edit meshes without touching the cache."""
    opt = None if scene.initial_camera_pose is None else scene.initial_camera_pose.copy()
    return dataclasses.replace(
        scene, object_mesh=scene.object_mesh.copy(), paint_mesh=scene.paint_mesh.copy(),
        drawing_polylines=[p.copy() for p in scene.drawing_polylines], gt_points=scene.gt_points.copy(),
        extremities=scene.extremities.copy(), initial_camera_pose=opt,
        initial_view_candidates=scene.initial_view_candidates.copy())


def build_catalog_scene(name: str) -> Scene:
    """A fresh copy of a built-in scene; each is built once per process (KeyError if unknown)."""
    return copy_scene(_cached(name))
