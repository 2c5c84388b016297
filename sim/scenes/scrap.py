"""The scrap generator: procedural pieces of the kinds a scrapyard cuts, each with a sprayed line.

A piece is named by a reference ``scrap:<gen_seed>:<index>``; the same reference gives the same mesh
and the same true line on every machine (numpy's seeded generator, no global state). Families:
flat and folded plates, pipes and elbows, pipes standing on plates (an inside corner), channels,
angles, box sections, I-beams, lying tanks with dished heads, a dished head on its own, gratings
and baskets. Each family is a solid (built from trimesh's primitives, extrusions and manifold
booleans) and a *chart*: a map from a flat (u, v) patch, both in metres of surface, onto the face a
worker sprays. Lines are drawn in the chart (straight, curved, zigzag with tips down to 15 degrees,
dashed, crossing, several strokes, over an edge, round a pipe) and mapped onto the surface, where
``assemble_scene`` projects and paints them as it does for every scene. The piece is turned about z
and placed where the Panda reaches its whole line.

``generate(gen_seed, index)`` -> (name, Blueprint, meta); ``load_scene("scrap:0:7")`` builds it;
``write_scene_file`` keeps one as a scene file (a regression test, docs/SCENES.md)."""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from sim.scenes.catalog import Blueprint, assemble_scene, copy_scene
from sim.scenes.model import Scene

REF = re.compile(r"^scrap:(\d+):(\d+)$")
SHOULDER = np.array([0.0, 0.0, 0.333])  # the Panda's shoulder, base frame
REACH_M = 0.64  # every line point within this of the shoulder (the built-in scenes: 0.65)
BASE_CLEAR_M = 0.2  # no part of the piece within this of the robot's base axis
MIN_TIP_DEG = 15.0  # the sharpest zigzag tip drawn
MIN_LINE_M = 0.08  # the shortest line drawn (all its strokes)
DASH_MIN_M = 0.03  # the shortest dash: longer than the widest spray (a scene file refuses a stroke under its width)
APART_M = 0.038  # separate strokes' centrelines at least this far apart: 10 mm of metal beside the widest spray
END_MARGIN_M = 0.022  # a drawn line keeps this far inside its face's patch: half the widest spray and 8 mm


def scrap_ref(gen_seed: int, index: int) -> str:
    return f"scrap:{int(gen_seed)}:{int(index)}"


def scrap_refs(n: int, gen_seed: int = 0) -> list[str]:
    """The first ``n`` pieces of generator seed ``gen_seed``."""
    return [scrap_ref(gen_seed, i) for i in range(int(n))]


def parse_ref(ref: str) -> tuple[int, int] | None:
    """(gen_seed, index) of a ``scrap:S:I`` reference, None for anything else."""
    m = REF.match(str(ref).strip())
    return None if m is None else (int(m.group(1)), int(m.group(2)))


# --- charts: a flat (u, v) patch onto the sprayed face ------------------------------------------

@dataclass
class Chart:
    """``point(uv)`` maps (N, 2) chart coordinates (metres along the surface) to (N, 3) points on
    the sprayed face, object frame. ``u`` and ``v`` are the ranges a line may use; ``edges_v``
    the v of the profile's corners (a line crossing one goes over an edge); ``round_v`` the v range
    once round a pipe (None where there is no pipe)."""

    point: Callable[[np.ndarray], np.ndarray]
    u: tuple[float, float]
    v: tuple[float, float]
    edges_v: tuple[float, ...] = ()
    round_v: tuple[float, float] | None = None


def _arc(q: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])


def _prism_chart(profile_yz: np.ndarray, length: float, margin: float = 0.03) -> Chart:
    """The outer path of an extruded section: u along the extrusion (x), v along the path."""
    q = np.asarray(profile_yz, dtype=np.float64)
    s = _arc(q)

    def point(uv):
        return np.column_stack([uv[:, 0], np.interp(uv[:, 1], s, q[:, 0]), np.interp(uv[:, 1], s, q[:, 1])])

    return Chart(point, (-length / 2 + margin, length / 2 - margin), (0.0, float(s[-1])), tuple(s[1:-1]))


def _revolution_chart(profile_rh: np.ndarray, axis: str, r_ref: float, *, s_margin: float = 0.02,
                      v_half: float | None = None) -> Chart:
    """A surface of revolution: u along the meridian (its arc length), v round it at radius ``r_ref``
    (theta = v / r_ref, 0 on top for a lying axis, toward +x for a standing one)."""
    q = np.asarray(profile_rh, dtype=np.float64)
    s = _arc(q)

    def point(uv):
        r, h = np.interp(uv[:, 0], s, q[:, 0]), np.interp(uv[:, 0], s, q[:, 1])
        th = uv[:, 1] / r_ref
        if axis == "z":
            return np.column_stack([r * np.cos(th), r * np.sin(th), h])
        return np.column_stack([r * np.sin(th), h, r * np.cos(th)])

    half = np.pi * r_ref * 0.55 if v_half is None else v_half
    corners = tuple(s[1:-1])
    return Chart(point, (s_margin, float(s[-1]) - s_margin), (-half, half), corners, (-np.pi * r_ref, np.pi * r_ref))


# --- solids -------------------------------------------------------------------------------------

def _union(meshes):
    return trimesh.boolean.union(meshes, engine="manifold")


def _box(extents, center) -> trimesh.Trimesh:
    return trimesh.creation.box(extents, trimesh.transformations.translation_matrix(center))


def _strip(mid: np.ndarray, thickness: float, closed: bool = False):
    """A polyline thickened to a strip: (left, right) offset polylines (mitred corners)."""
    p = np.asarray(mid, dtype=np.float64)
    if closed:
        d_in = p - np.roll(p, 1, axis=0)
        d_out = np.roll(p, -1, axis=0) - p
    else:
        d = np.diff(p, axis=0)
        d_in = np.vstack([d[:1], d])
        d_out = np.vstack([d, d[-1:]])
    t_in = d_in / np.linalg.norm(d_in, axis=1, keepdims=True)
    t_out = d_out / np.linalg.norm(d_out, axis=1, keepdims=True)
    n_in, n_out = np.column_stack([-t_in[:, 1], t_in[:, 0]]), np.column_stack([-t_out[:, 1], t_out[:, 0]])
    miter = n_in + n_out
    miter /= np.linalg.norm(miter, axis=1, keepdims=True)
    scale = 1.0 / np.clip(np.einsum("ij,ij->i", miter, n_out), 0.3, None)
    off = miter * (thickness / 2 * scale)[:, None]
    return p + off, p - off


def _extrude_strip(left: np.ndarray, right: np.ndarray, length: float, closed: bool = False) -> trimesh.Trimesh:
    """The solid swept by the strip between two offset polylines of the section (y, z), along x."""
    n = len(left)
    verts = np.vstack([left, right])
    idx = np.arange(n - 1) if not closed else np.arange(n)
    a, b = idx, (idx + 1) % n
    tri = np.vstack([np.column_stack([a, b, n + b]), np.column_stack([a, n + b, n + a])])
    e1, e2 = verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    tri[area < 0] = tri[area < 0][:, ::-1]  # counter-clockwise in the section plane
    mesh = trimesh.creation.extrude_triangulation(verts, tri, length)
    # (y, z, h) -> (h - L/2, y, z): a cyclic permutation of the axes keeps the winding
    mesh.vertices = np.column_stack([mesh.vertices[:, 2] - length / 2, mesh.vertices[:, 0], mesh.vertices[:, 1]])
    mesh.merge_vertices()
    mesh.fix_normals()
    return mesh


def _revolve(profile_rh: np.ndarray, axis: str, sections: int = 128) -> trimesh.Trimesh:
    """Solid of revolution from a (radius, height) profile closed on the axis; axis 'z' or 'y'."""
    mesh = trimesh.creation.revolve(np.asarray(profile_rh, dtype=np.float64), sections=sections)
    if axis == "y":
        mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # z -> y
    return mesh


def _tube(centre: np.ndarray, radius: float, sections: int = 48) -> trimesh.Trimesh:
    """A closed pipe of ``radius`` along a centreline lying in the xy plane (straight ends and bends):
    one ring of vertices per centreline point, square to the mean of its two segments, and flat caps.
    One sweep, no booleans: a union of a torus with cylinders left near-duplicate seam vertices."""
    c = np.asarray(centre, dtype=np.float64)
    d = np.diff(c, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = np.vstack([d[:1], d[:-1] + d[1:], d[-1:]])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    z = np.array([0.0, 0.0, 1.0])
    n = np.cross(t, z)
    a = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    ring = (c[:, None, :] + radius * (np.cos(a)[None, :, None] * n[:, None, :] + np.sin(a)[None, :, None] * z))
    k, m = len(c), sections
    verts = np.vstack([ring.reshape(-1, 3), c[:1], c[-1:]])
    i, j = np.meshgrid(np.arange(k - 1), np.arange(m), indexing="ij")
    v00, v01 = i * m + j, i * m + (j + 1) % m
    v10, v11 = v00 + m, v01 + m
    side = np.vstack([np.column_stack([v00.ravel(), v10.ravel(), v11.ravel()]),
                      np.column_stack([v00.ravel(), v11.ravel(), v01.ravel()])])
    jj = np.arange(m)
    cap0 = np.column_stack([np.full(m, k * m), (jj + 1) % m, jj])
    cap1 = np.column_stack([np.full(m, k * m + 1), (k - 1) * m + jj, (k - 1) * m + (jj + 1) % m])
    mesh = trimesh.Trimesh(verts, np.vstack([side, cap0, cap1]), process=True)
    mesh.fix_normals()
    return mesh


def _dished_head(radius: float, rng) -> np.ndarray:
    """A torispherical head's (radius, height) meridian from the rim (0) to the crown: crown radius
    ~ the diameter, knuckle 10-20 % of it (ASME flanged and dished heads)."""
    D = 2 * radius
    Rc = D * rng.uniform(0.8, 1.0)
    rk = D * rng.uniform(0.1, 0.2)
    # the knuckle's centre at (radius - rk, 0); the crown's at (0, -(Rc - ...)) tangent to it
    ck = np.array([radius - rk, 0.0])
    zc = -np.sqrt((Rc - rk) ** 2 - ck[0] ** 2)  # crown centre below the rim plane
    cc = np.array([0.0, zc])
    dirn = (ck - cc) / np.linalg.norm(ck - cc)
    a_end = np.arctan2(dirn[1], dirn[0])  # where the knuckle meets the crown
    ka = np.linspace(0.0, a_end, 16)
    knuckle = ck + rk * np.column_stack([np.cos(ka), np.sin(ka)])
    ca = np.linspace(a_end, np.pi / 2, 24)[1:]
    crown = cc + Rc * np.column_stack([np.cos(ca), np.sin(ca)])
    return np.vstack([knuckle, crown])


# --- the families: each returns (mesh, chart, params, max_offset) in its object frame ---------

def plate(rng):
    L, W, t = rng.uniform(0.3, 0.45), rng.uniform(0.22, 0.34), rng.uniform(0.006, 0.015)
    mid = np.array([[-W / 2, t / 2], [W / 2, t / 2]])
    left, right = _strip(mid, t)
    mesh = _extrude_strip(left, right, L)
    top = np.array([[-W / 2, t], [W / 2, t]])
    return mesh, _prism_chart(top, L), {"length_m": L, "width_m": W, "thickness_m": t}, None


def folded_plate(rng):
    """1-3 folds of 30-150 degrees (the bend's turn), legs 0.08-0.2 m, upward or downward."""
    folds = int(rng.integers(1, 4))
    L, t = rng.uniform(0.3, 0.42), rng.uniform(0.005, 0.012)
    turns = rng.uniform(30, 150, folds) * rng.choice([-1, 1], folds)
    legs = rng.uniform(0.08, 0.18, folds + 1)
    # walk the section; keep the heading within +-90 deg of +y so it stays a one-sided plate seen from above
    headings, heading = [0.0], 0.0
    for i in range(folds):
        nxt = heading + np.radians(turns[i])
        if abs(nxt) > np.radians(95):
            turns[i] = -turns[i]
            nxt = heading + np.radians(turns[i])
        heading = nxt
        headings.append(heading)
    h = np.array(headings)
    if np.abs(h).max() > np.radians(95):  # a first turn over 95 deg: the range centred on +y, or a leg's
        h -= 0.5 * (h.max() + h.min())     # upper face looks at the floor (paint sprayed from underneath)
    pts = [np.zeros(2)]
    for leg, hd in zip(legs, h):
        pts.append(pts[-1] + leg * np.array([np.cos(hd), np.sin(hd)]))
    mid = np.array(pts)
    mid[:, 1] -= mid[:, 1].min() - t
    mid[:, 0] -= mid[:, 0].mean()
    left, right = _strip(mid, t)
    drop = min(left[:, 1].min(), right[:, 1].min())  # rest the lowest corner on the floor
    left[:, 1] -= drop
    right[:, 1] -= drop
    mesh = _extrude_strip(left, right, L)
    top = left  # the left of a path heading +y is +z: the upper face
    return mesh, _prism_chart(top, L), {"length_m": L, "thickness_m": t, "fold_turns_deg": [round(float(x), 1) for x in turns]}, None


def channel(rng):
    W, H, t, L = rng.uniform(0.12, 0.24), rng.uniform(0.05, 0.1), rng.uniform(0.006, 0.012), rng.uniform(0.3, 0.45)
    up = rng.random() < 0.6  # on its back (a trough) or mouth down
    if up:
        mid = np.array([[-W / 2, H], [-W / 2, t / 2], [W / 2, t / 2], [W / 2, H]])
    else:
        mid = np.array([[-W / 2, 0.0], [-W / 2, H - t / 2], [W / 2, H - t / 2], [W / 2, 0.0]])
    left, right = _strip(mid, t)
    mesh = _extrude_strip(left, right, L)
    # the left of the walk is the face the spray meets: inside the trough, over the back mouth down
    return mesh, _prism_chart(left, L), {"width_m": W, "height_m": H, "thickness_m": t, "mouth": "up" if up else "down"}, None


def angle(rng):
    a, b, t, L = rng.uniform(0.06, 0.14), rng.uniform(0.06, 0.14), rng.uniform(0.006, 0.012), rng.uniform(0.3, 0.45)
    if rng.random() < 0.5:  # on its heel: an inverted V, sprayed over the ridge
        h = a / np.sqrt(2)
        mid = np.array([[-h, 0.0], [0.0, h], [b / np.sqrt(2), h - b / np.sqrt(2)]])
        mid[:, 1] += t
        pose = "ridge"
    else:  # one leg flat, one up: sprayed across the inside corner
        mid = np.array([[-a, t / 2], [0.0, t / 2], [0.0, b]])
        pose = "corner"
    left, right = _strip(mid, t)
    lift = -min(left[:, 1].min(), right[:, 1].min())  # a longer far leg would reach below the floor
    left[:, 1] += lift
    right[:, 1] += lift
    mesh = _extrude_strip(left, right, L)
    return mesh, _prism_chart(left, L), {"legs_m": [a, b], "thickness_m": t, "pose": pose}, None


def box_section(rng):
    W, H, t, L = rng.uniform(0.1, 0.2), rng.uniform(0.08, 0.18), rng.uniform(0.005, 0.01), rng.uniform(0.3, 0.45)
    mid = np.array([[-W / 2, t / 2], [W / 2, t / 2], [W / 2, H - t / 2], [-W / 2, H - t / 2]])
    left, right = _strip(mid, t, closed=True)
    mesh = _extrude_strip(left, right, L, closed=True)
    # up one side, over, down the other: on the outer faces (the walls' midlines lie t/2 inside them, as
    # near the inner faces as the outer, and a line drawn there was painted inside the box, unseen)
    w = W / 2 + t / 2
    o = np.array([[-w, 0.0], [-w, H], [w, H], [w, 0.0]])
    return mesh, _prism_chart(o, L), {"width_m": W, "height_m": H, "thickness_m": t}, None


def i_beam(rng):
    W, H, tf, tw, L = (rng.uniform(0.1, 0.18), rng.uniform(0.12, 0.22), rng.uniform(0.008, 0.014),
                       rng.uniform(0.006, 0.01), rng.uniform(0.3, 0.45))
    flanges = [_box([L, W, tf], [0, 0, tf / 2]), _box([L, W, tf], [0, 0, H - tf / 2])]
    web = _box([L, tw, H - 2 * tf + 0.002], [0, 0, H / 2])
    mesh = _union(flanges + [web])
    # over the top flange, round its edge, under it into the corner and down the web
    o = np.array([[-W / 2, H - tf], [-W / 2, H], [W / 2, H], [W / 2, H - tf], [tw / 2, H - tf], [tw / 2, tf]])
    return mesh, _prism_chart(o, L), {"width_m": W, "height_m": H, "flange_m": tf, "web_m": tw}, None


def pipe(rng):
    r, L = rng.uniform(0.06, 0.14), rng.uniform(0.35, 0.6)
    prof = [(0, -L / 2), (r, -L / 2), (r, L / 2), (0, L / 2)]
    mesh = _revolve(prof, "y")
    chart = _revolution_chart(np.array([[r, -L / 2], [r, L / 2]]), "y", r, s_margin=0.03)
    mesh.apply_translation([0, 0, r])
    base = chart.point
    chart.point = lambda uv: base(uv) + [0.0, 0.0, r]
    return mesh, chart, {"radius_m": r, "length_m": L}, None


def elbow(rng):
    """A bent pipe lying on the floor: a torus section of 45-120 degrees with short straight ends."""
    r = rng.uniform(0.05, 0.1)
    R = rng.uniform(1.5, 3.0) * r
    bend = np.radians(rng.uniform(45, 120))
    stub = rng.uniform(0.03, 0.08)
    phi = np.linspace(0.0, bend, 1 + int(np.ceil(bend / np.radians(1.5))))
    arc = np.column_stack([R * np.cos(phi), R * np.sin(phi), np.zeros_like(phi)])
    tangent_end = np.array([-np.sin(bend), np.cos(bend), 0.0])
    centre = np.vstack([[R, -stub, 0.0], arc, arc[-1] + stub * tangent_end])
    mesh = _tube(centre, r)
    mesh.apply_translation([0, 0, r])

    def point(uv):
        phi, th = uv[:, 0] / R, uv[:, 1] / r  # th 0 on top
        rr = R + r * np.sin(th)
        return np.column_stack([rr * np.cos(phi), rr * np.sin(phi), r + r * np.cos(th)])

    chart = Chart(point, (0.02, R * bend - 0.02), (-np.pi * r * 0.55, np.pi * r * 0.55), (), (-np.pi * r, np.pi * r))
    return mesh, chart, {"radius_m": r, "bend_radius_m": R, "bend_deg": round(float(np.degrees(bend)), 1)}, None


def pipe_on_plate(rng):
    """A pipe standing on a plate or a round flange: the line runs down it into the inside corner."""
    r, h = rng.uniform(0.04, 0.09), rng.uniform(0.12, 0.25)
    a, t = rng.uniform(r + 0.1, r + 0.16), rng.uniform(0.008, 0.02)
    round_flange = rng.random() < 0.4
    if round_flange:
        base = trimesh.creation.cylinder(radius=a, height=t, sections=128)
        base.apply_translation([0, 0, t / 2])
    else:
        base = _box([2 * a, 2 * a, t], [0, 0, t / 2])
    p = trimesh.creation.cylinder(radius=r, height=h + 0.002, sections=96)
    p.apply_translation([0, 0, t + h / 2 - 0.001])
    mesh = _union([base, p])
    prof = np.array([[0.0, t + h], [r, t + h], [r, t], [a * 0.92, t]])  # over the top rim, down, out
    chart = _revolution_chart(prof, "z", r, s_margin=0.01, v_half=np.pi * r)
    return mesh, chart, {"radius_m": r, "height_m": h, "base_half_m": a, "base": "flange" if round_flange else "plate"}, None


def tank(rng):
    """A tank lying on the floor: a shell with one or two dished heads."""
    R, Lc = rng.uniform(0.1, 0.16), rng.uniform(0.15, 0.35)
    head = _dished_head(R, rng)
    two = rng.random() < 0.5
    prof = [(0.0, -Lc / 2)] if not two else [(0.0, -Lc / 2 - head[-1, 1])]
    if two:
        prof += [(x, -Lc / 2 - z) for x, z in head[::-1]]
    else:
        prof += [(R, -Lc / 2)]
    prof += [(x, Lc / 2 + z) for x, z in head]
    prof[-1] = (0.0, prof[-1][1])
    prof = np.array(prof)
    mesh = _revolve(prof, "y")
    mesh.apply_translation([0, 0, R])
    chart = _revolution_chart(prof[1:], "y", R, s_margin=0.02)  # along the shell and over the far head
    base = chart.point
    chart.point = lambda uv: base(uv) + [0.0, 0.0, R]
    return mesh, chart, {"radius_m": R, "shell_m": Lc, "heads": 2 if two else 1}, None


def tank_head(rng):
    """A dished head on its rim, crown up, on a short skirt."""
    R = rng.uniform(0.14, 0.22)
    skirt = rng.uniform(0.03, 0.08)
    head = _dished_head(R, rng)
    prof = np.vstack([[[0.0, 0.0], [R, 0.0]], head + [0.0, skirt]])
    prof[-1, 0] = 0.0
    mesh = _revolve(prof, "z")
    meridian = np.vstack([prof[1:][::-1]])  # from the crown out over the knuckle and down the skirt
    chart = _revolution_chart(meridian, "z", R, s_margin=0.02, v_half=np.pi * R)
    return mesh, chart, {"radius_m": R, "skirt_m": skirt}, None


def grid(rng):
    """A grating: flat bars on edge with cross rods; paint only where the spray meets a bar."""
    pitch, bar_h, bar_t = rng.uniform(0.03, 0.05), rng.uniform(0.025, 0.04), rng.uniform(0.004, 0.008)
    L, W = rng.uniform(0.28, 0.4), rng.uniform(0.22, 0.32)
    ys = np.arange(-W / 2, W / 2 + 1e-9, pitch)
    bars = [_box([L, bar_t, bar_h], [0, y, bar_h / 2]) for y in ys]
    rods = []
    for x in np.arange(-L / 2 + 0.02, L / 2, rng.uniform(0.08, 0.12)):
        c = trimesh.creation.cylinder(radius=0.004, height=W + 0.01, sections=12)
        c.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        c.apply_translation([x, 0, bar_h - 0.005])
        rods.append(c)
    mesh = _union(bars + rods)

    def point(uv):
        return np.column_stack([uv[:, 0], uv[:, 1], np.full(len(uv), bar_h + 0.001)])

    chart = Chart(point, (-L / 2 + 0.03, L / 2 - 0.03), (-W / 2 + 0.02, W / 2 - 0.02))
    return mesh, chart, {"pitch_m": pitch, "bar_m": [bar_t, bar_h], "length_m": L, "width_m": W}, 0.003


def basket(rng):
    """A half-cylinder cage of rods with two hoops (as the built-in basket, sized at random)."""
    rc, rr, L = rng.uniform(0.14, 0.22), rng.uniform(0.006, 0.01), rng.uniform(0.3, 0.42)
    step = rng.uniform(10, 16)
    angles = np.radians(np.arange(-90, 90 + 1e-9, step))
    rods = []
    for a in angles:
        rod = trimesh.creation.cylinder(radius=rr, height=L, sections=16)
        rod.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        rod.apply_translation([0.0, rc * np.sin(a), rc * np.cos(a)])
        rods.append(rod)
    keep_top = _box([1.0, 1.0, 1.0], [0, 0, 0.5])
    hoops = []
    for x in (-L / 2 + 0.02, L / 2 - 0.02):
        ring = trimesh.creation.torus(rc, rr, major_sections=96, minor_sections=12)
        ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        ring.apply_translation([x, 0.0, 0.0])
        hoops.append(trimesh.boolean.intersection([ring, keep_top], engine="manifold"))
    mesh = _union(rods + hoops)
    mesh.apply_translation([0, 0, rr])
    R = rc + rr

    def point(uv):
        th = uv[:, 1] / R
        return np.column_stack([uv[:, 0], R * np.sin(th), R * np.cos(th) + rr])

    chart = Chart(point, (-L / 2 + 0.04, L / 2 - 0.04), (-R * np.radians(75), R * np.radians(75)))
    return mesh, chart, {"radius_m": rc, "rod_m": rr, "rod_step_deg": round(float(step), 1), "length_m": L}, 0.003


FAMILIES: dict[str, Callable] = {
    "plate": plate, "folded_plate": folded_plate, "pipe": pipe, "elbow": elbow, "pipe_on_plate": pipe_on_plate,
    "channel": channel, "angle": angle, "box_section": box_section, "i_beam": i_beam, "tank": tank,
    "tank_head": tank_head, "grid": grid, "basket": basket,
}
FAMILY_NAMES = tuple(FAMILIES)

# the line kinds each family is drawn with (a chart without a pipe has no "round")
LINE_KINDS = ("straight", "curved", "zigzag", "over_edge", "round", "dashed", "crossing", "strokes")
_FAMILY_LINES = {
    "plate": ("straight", "curved", "zigzag", "dashed", "crossing", "strokes"),
    "folded_plate": ("over_edge", "over_edge", "zigzag", "curved", "dashed", "strokes"),
    "channel": ("over_edge", "over_edge", "straight", "zigzag", "dashed"),
    "angle": ("over_edge", "over_edge", "zigzag", "curved", "straight"),
    "box_section": ("over_edge", "over_edge", "zigzag", "straight", "crossing"),
    "i_beam": ("over_edge", "over_edge", "straight", "zigzag"),
    "pipe": ("curved", "round", "straight", "zigzag", "dashed", "crossing"),
    "elbow": ("curved", "straight", "round", "zigzag", "dashed"),
    "pipe_on_plate": ("over_edge", "over_edge", "round", "curved"),
    "tank": ("over_edge", "curved", "round", "zigzag", "crossing"),
    "tank_head": ("over_edge", "curved", "straight", "zigzag"),
    "grid": ("straight", "curved", "zigzag"),
    "basket": ("straight", "curved"),
}


# --- lines in the chart -------------------------------------------------------------------------

def _dense(p: np.ndarray, step: float = 0.002) -> np.ndarray:
    s = _arc(p)
    n = max(int(np.ceil(s[-1] / step)), 1) + 1
    t = np.linspace(0.0, s[-1], n)
    t = np.union1d(t, s)  # keep the corners exact
    return np.column_stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])])


def _fit(strokes: list[np.ndarray], chart: Chart, rng, margin: float = 0.0) -> list[np.ndarray]:
    """Scale the strokes down (never up) to fit the chart's patch, turned a quarter where that keeps more
    of them, and place them at random in it."""
    extent = np.array([chart.u[1] - chart.u[0], chart.v[1] - chart.v[0]])
    allp = np.vstack(strokes)
    size0 = np.maximum(allp.max(0) - allp.min(0), 1e-6)
    if min(extent / size0) < min(extent / size0[::-1]):  # it keeps more of its length turned a quarter
        strokes = [p @ np.array([[0.0, 1.0], [-1.0, 0.0]]) for p in strokes]
        allp = np.vstack(strokes)
    lo, hi = allp.min(0), allp.max(0)
    extent = np.array([chart.u[1] - chart.u[0], chart.v[1] - chart.v[0]])
    margin = np.minimum(margin, 0.25 * extent)  # a small patch keeps half of itself for the line
    box = extent - 2 * margin
    size = np.maximum(hi - lo, 1e-6)
    k = float(min(1.0, *(box / size)))
    strokes = [(p - lo) * k for p in strokes]
    size = size * k
    slack = np.maximum(box - size, 0.0)
    off = np.array([chart.u[0], chart.v[0]]) + margin + rng.uniform(0, 1, 2) * slack
    return [p + off for p in strokes]


def _curve(rng, length: float) -> np.ndarray:
    """A smooth stroke: a random walk of heading, low-passed (a sprayed arc, an S)."""
    n = 60
    k = rng.normal(0, 1, 4)
    t = np.linspace(0, 1, n)
    heading = rng.uniform(-np.pi, np.pi) + 1.2 * (k[0] * t + k[1] * np.sin(np.pi * t) + 0.5 * k[2] * np.sin(2 * np.pi * t))
    d = np.column_stack([np.cos(heading), np.sin(heading)]) * (length / n)
    return np.vstack([[0, 0], np.cumsum(d, axis=0)])


def _zigzag(rng, tip_deg: np.ndarray, leg: float) -> np.ndarray:
    """Legs alternating to either side of the u axis, each tip the given interior angle."""
    heading = np.radians(90 - tip_deg[0] / 2)  # the first leg's heading off u
    pts, sgn = [np.zeros(2)], 1.0
    for i in range(len(tip_deg) + 1):
        if i > 0:
            sgn = -sgn
            heading = np.radians(90 - tip_deg[i - 1] / 2)
        pts.append(pts[-1] + leg * np.array([np.cos(heading), sgn * np.sin(heading)]))
    return np.array(pts)


def draw_line(kind: str, chart: Chart, rng) -> tuple[list[np.ndarray], dict]:
    """The strokes of one line kind in chart coordinates, and what was drawn."""
    du, dv = chart.u[1] - chart.u[0], chart.v[1] - chart.v[0]
    info: dict = {}
    if kind == "straight":
        L = rng.uniform(0.2, 0.45)
        a = rng.uniform(-0.6, 0.6) + (0 if du >= dv else np.pi / 2)
        strokes = [np.array([[0, 0], [L * np.cos(a), L * np.sin(a)]])]
    elif kind == "curved":
        strokes = [_curve(rng, rng.uniform(0.25, 0.5))]
    elif kind == "zigzag":
        tips = int(rng.integers(2, 5))
        tip_deg = rng.uniform(MIN_TIP_DEG, 120.0, tips)
        leg = rng.uniform(0.08, 0.14)
        z = _zigzag(rng, tip_deg, leg)
        if du < dv:
            z = z[:, ::-1]
        strokes = [z]
        info["tips_deg"] = [round(float(x), 1) for x in tip_deg]
    elif kind == "over_edge":
        # across the profile: from one v to another, crossing at least one corner
        e = np.array(chart.edges_v) if chart.edges_v else np.array([(chart.v[0] + chart.v[1]) / 2])
        c = float(rng.choice(e))
        v0 = max(chart.v[0] + END_MARGIN_M, c - rng.uniform(0.06, 0.2))
        v1 = min(chart.v[1] - END_MARGIN_M, c + rng.uniform(0.06, 0.2))
        u0 = rng.uniform(chart.u[0] + 0.05 * du, chart.u[1] - 0.05 * du)
        slant = rng.uniform(-0.5, 0.5) * (v1 - v0)
        strokes = [np.array([[u0, v0], [u0 + slant, v1]])]
        strokes[0][:, 0] = np.clip(strokes[0][:, 0], chart.u[0], chart.u[1])
        return [_dense(p) for p in strokes], {"edge_v": round(c, 3)}
    elif kind == "round":
        lo, hi = chart.round_v
        span = rng.uniform(0.5, 0.85) * (hi - lo)
        u0 = rng.uniform(chart.u[0] + 0.1 * du, chart.u[1] - 0.1 * du)
        v0 = rng.uniform(-0.15, 0.15) * (hi - lo) - span / 2
        strokes = [np.array([[u0, v0], [u0 + rng.uniform(-0.03, 0.03), v0 + span]])]
        info["round_deg"] = round(float(np.degrees(span / ((hi - lo) / (2 * np.pi)))), 1)
        return [_dense(p) for p in strokes], info
    elif kind == "dashed":
        base = _dense(_curve(rng, rng.uniform(0.3, 0.5)) if rng.random() < 0.5 else
                      np.array([[0, 0], [rng.uniform(0.3, 0.45), rng.uniform(-0.1, 0.1)]]))
        # the gap between the dashes' centrelines: wider than the spray (at most 28 mm), so the paint has gaps;
        # dashed after the line is fitted to its patch, which would shrink the gaps with the line
        dash, gap = rng.uniform(0.04, 0.08), rng.uniform(0.045, 0.07)
        base = _dense(_fit([base], chart, rng, margin=END_MARGIN_M)[0])
        s = _arc(base)
        phase = np.mod(s, dash + gap) < dash
        cuts = np.flatnonzero(np.diff(phase.astype(int)) != 0) + 1
        strokes = [p for p, on in zip(np.split(base, cuts), np.split(phase, cuts))  # a dash cut short at the end:
                   if on[0] and len(p) > 2 and _arc(p)[-1] >= DASH_MIN_M]  # kept only if longer than any spray
        info.update(dash_m=round(float(dash), 3), gap_m=round(float(gap), 3))
        return strokes, info
    elif kind == "crossing":
        L1, L2 = rng.uniform(0.2, 0.35), rng.uniform(0.15, 0.3)
        a = rng.uniform(0, np.pi)
        b = a + rng.uniform(np.radians(35), np.radians(145))
        c = np.array([0.0, 0.0])
        strokes = [c + np.outer([-0.5, 0.5], [np.cos(a), np.sin(a)]) * L1,
                   c + np.outer([-0.5, 0.5], [np.cos(b), np.sin(b)]) * L2]
    elif kind == "strokes":
        n = int(rng.integers(2, 4))
        strokes = []
        for i in range(n):
            L = rng.uniform(0.08, 0.18)
            a = rng.uniform(-0.4, 0.4)
            o = np.array([0.0, i * rng.uniform(0.06, 0.09)])
            strokes.append(o + np.array([[0, 0], [L * np.cos(a), L * np.sin(a)]]))
    else:
        raise ValueError(f"unknown line kind {kind!r}: use one of {', '.join(LINE_KINDS)}")
    # ends kept a half spray width and more inside the patch: a line that stops within half a width of an
    # edge sprays paint to the edge, and nobody (the cell included) can tell whether it meant to run off
    return [_dense(p) for p in _fit(strokes, chart, rng, margin=END_MARGIN_M)], info


# --- placing the piece --------------------------------------------------------------------------

def _rz(yaw: float) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])


def _place(mesh: trimesh.Trimesh, lines: list[np.ndarray], rng, tries: int = 60) -> np.ndarray:
    """T_base_obj: a turn about z and a spot on the floor where the arm reaches the whole line and the
    piece keeps clear of the robot's base; the best of ``tries`` draws if none is perfect."""
    pts = np.vstack(lines)
    hull = mesh.convex_hull.vertices if len(mesh.vertices) > 400 else mesh.vertices
    best, best_bad = None, np.inf
    for _ in range(tries):
        yaw = rng.uniform(-np.pi, np.pi)
        R = _rz(yaw)
        c = (pts @ R[:3, :3].T).mean(0)
        target = np.array([rng.uniform(0.45, 0.56), rng.uniform(-0.12, 0.12)])
        T = R.copy()
        T[:2, 3] = target - c[:2]
        p = pts @ T[:3, :3].T + T[:3, 3]
        h = hull @ T[:3, :3].T + T[:3, 3]
        reach = np.linalg.norm(p - SHOULDER, axis=1).max() - REACH_M
        base = BASE_CLEAR_M - np.hypot(h[:, 0], h[:, 1]).min()
        near = 0.32 - np.hypot(p[:, 0], p[:, 1]).min()  # not under the shoulder, where the torch cannot point down
        bad = max(reach, 0) + max(base, 0) + max(near, 0)
        if bad < best_bad:
            best, best_bad = T, bad
        if bad == 0:
            break
    return best


# --- the generator ------------------------------------------------------------------------------

def _ends_clear(strokes: list[np.ndarray], chart: Chart) -> bool:
    """No stroke ends within ``END_MARGIN_M`` of a corner of the profile: its paint would wrap over the
    edge, and where the worker meant the line to stop could not be told."""
    if not chart.edges_v:
        return True
    ends_v = np.array([p[[0, -1], 1] for p in strokes]).ravel()
    return bool(np.abs(ends_v[:, None] - np.asarray(chart.edges_v)[None, :]).min() >= END_MARGIN_M)


def _apart(lines: list[np.ndarray], kind: str) -> bool:
    """Separate strokes (dashes, strokes side by side) keep ``APART_M`` between their centrelines: the
    widest spray leaves bare metal between their paints. Scaled into a small patch they can come
    closer (a dashed line on a short elbow: 1.5 mm of metal between its dashes' paint), and then paint
    that merges is one line to anyone reading it, the cell included."""
    if kind == "crossing" or len(lines) < 2:
        return True
    trees = [cKDTree(p) for p in lines]
    return all(trees[i].query(lines[j], distance_upper_bound=APART_M)[0].min() >= APART_M
               for i in range(len(lines)) for j in range(i + 1, len(lines)))  # a handful of strokes


def _sprayable(lines: list[np.ndarray], mesh: trimesh.Trimesh) -> bool:
    """Half the line at least on faces a worker standing by the piece sprays: not facing the floor
    (normal more than 60 deg below the horizon). A fold turned past the vertical puts the chart's face
    underneath, on the table (scrap:0:45 redrawn: every dash on the underside, no view sees any)."""
    from sim.scenes.paint import closest_points

    pts = np.vstack(lines)[:: max(1, sum(len(p) for p in lines) // 200)]
    _, _, tri = closest_points(mesh, pts)
    return bool(np.mean(mesh.face_normals[tri][:, 2] >= -0.5) >= 0.5)


def _family_of(gen_seed: int, index: int) -> str:
    """Families in turn, in an order shuffled by the generator seed: every family in each run of 13."""
    order = np.random.default_rng([int(gen_seed), 7919]).permutation(len(FAMILY_NAMES))
    return FAMILY_NAMES[int(order[index % len(FAMILY_NAMES)])]


def generate(gen_seed: int, index: int) -> tuple[str, Blueprint, dict]:
    """Piece ``index`` of generator seed ``gen_seed``: (scene name, blueprint, what was drawn)."""
    family = _family_of(gen_seed, index)
    rng = np.random.default_rng([int(gen_seed), int(index), 1])
    mesh, chart, params, max_offset = FAMILIES[family](rng)
    kinds = [k for k in _FAMILY_LINES[family] if k != "round" or chart.round_v is not None]
    kind = str(rng.choice(kinds))
    best = None  # a line squeezed into a small patch (a short elbow), or ending at an edge, is drawn again
    for _ in range(20):
        strokes, info = draw_line(kind, chart, rng)
        lines = [chart.point(p) for p in strokes]
        long = sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in lines) >= MIN_LINE_M
        rank = 8 * _sprayable(lines, mesh) + 4 * _apart(lines, kind) + 2 * long + _ends_clear(strokes, chart)
        if best is None or rank > best[0]:
            best = (rank, strokes, info, lines)
        if rank == 15:
            break
    _, strokes, info, lines = best
    # a line off the chart's face (past the end of a pipe, off a plate) is pulled onto the mesh by the
    # painter; points nudged 1 mm outward from the face would be no better, so they are left as drawn
    width = float(rng.uniform(0.016, 0.028))
    T = _place(mesh, lines, rng)
    length = float(sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in lines))
    meta = {"family": family, "lines": [kind], "width_m": round(width, 4), "length_m": round(length, 3),
            "strokes": len(lines), **info,
            "params": {k: (round(float(v), 4) if isinstance(v, (float, np.floating)) else v) for k, v in params.items()}}
    name = f"scrap-{gen_seed}-{index}-{family}"
    return name, Blueprint(mesh, lines, width, T, None, max_offset=max_offset), meta


@functools.lru_cache(maxsize=32)
def _cached(gen_seed: int, index: int) -> Scene:
    name, bp, _ = generate(gen_seed, index)
    return assemble_scene(name, bp)


def load_scrap(ref: str) -> Scene:
    """A fresh copy of the generated piece ``scrap:S:I`` (built once per process)."""
    key = parse_ref(ref)
    if key is None:
        raise ValueError(f"not a generated piece: {ref!r} (scrap:<gen_seed>:<index>)")
    return copy_scene(_cached(*key))


def write_scene_file(ref: str, out_dir: str | Path) -> Path:
    """Keep a generated piece as a scene file (docs/SCENES.md): <name>.yaml beside its mesh <name>.obj, in
    the object frame with its pose, so ``load_scene`` on it rebuilds the same piece."""
    from scipy.spatial.transform import Rotation
    import yaml

    from sim.appearance import parse_look, split_look

    ref, look = split_look(str(ref))
    key = parse_ref(ref)
    if key is None:
        raise ValueError(f"not a generated piece: {ref!r} (scrap:<gen_seed>:<index>[@<look>])")
    name, bp, meta = generate(*key)
    appearance = parse_look(look, key) if look is not None else None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mesh_path = out / f"{name}.obj"
    bp.mesh.export(mesh_path)
    T = np.asarray(bp.T_base_obj)
    doc = {
        "name": name,
        "mesh": mesh_path.name,
        "pose": {"xyz": [round(float(x), 6) for x in T[:3, 3]],
                 "rpy_deg": [round(float(x), 6) for x in Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)]},
        "drawing": {"width": round(float(bp.width), 5),
                    "polylines": [[[round(float(c), 6) for c in p] for p in line[:: max(1, len(line) // 400)].tolist()
                                   + [line[-1].tolist()]] for line in bp.polylines],
                    **({"max_offset": float(bp.max_offset)} if bp.max_offset is not None else {})},
    }
    if appearance is not None:
        doc["appearance"] = {"finish": appearance.finish, "paint": appearance.paint, "light": appearance.light,
                             "seed": appearance.seed}
    path = out / f"{name}.yaml"
    header = f"# generated piece {ref}: {meta['family']}, line {', '.join(meta['lines'])} (sim/scenes/scrap.py)\n"
    path.write_text(header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))
    return path
