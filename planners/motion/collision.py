"""Collision checking of the arm, its camera (and later its torch) against the floor, itself and
the scene as scanned so far, with python-fcl.

Robot: every URDF ``<collision>`` element becomes one ``fcl.Convex``, the convex hull of its
geometry. pybullet_data's Panda collision meshes already are convex hulls, and pybullet collides
them as hulls too, so nothing is lost and GJK treats each part as a solid (a voxel deep inside a
link still counts, which a triangle-soup BVH would miss). Tool shapes (camera box, torch cylinder)
are extra convex parts rigid on the flange link. Poses come from the same Pinocchio model as
``Kinematics``; locked joints (the fingers) stay at their neutral value.

Scene: the occupied (and unknown-near-occupied) voxels become one ``fcl.OcTree``, encoded here in
numpy as octomap's binary stream (full 2x2x2 blocks merge into bigger solid boxes): about 20 ms
for 60k voxels. The clearance margin is applied by testing
the scene against copies of the robot parts inflated by ``margin_m`` (hull of the part's vertices
plus a polytope circumscribing the margin ball: at most 7 % more than the margin), so the voxels
stay exact and the margin does not depend on the voxel size.

Floor: the half-space ``z < floor_margin_m``, tested exactly in numpy on the hull vertices. Parts
fixed to the base (``panda_link0``) are left out of the floor and scene tests: they cannot move,
so whatever touches them is the floor or the robot itself seen by the camera, and counting it would
forbid every motion.

Self-collision: every pair of parts except those rigidly connected (same moving joint: link7, hand,
fingers, tools), adjacent across one joint (URDF links only) or in contact in every one of a fixed
set of sampled configurations (computed once per model).

Not thread-safe (one Pinocchio data buffer, fcl objects moved in place): give each thread its own
``RobotCollisionModel`` and checker.
"""

from __future__ import annotations

import functools
import itertools
import math
import numbers
import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field

from typing import Annotated

import fcl
import numba as nb
import numpy as np
import trimesh
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage
from scipy.spatial import cKDTree

from .kinematics import Kinematics, _as_pose

_OCTREE_DEPTH = 16  # octomap's fixed key width: keys are 16-bit, centred on 2**15
_KEY_OFFSET = 1 << (_OCTREE_DEPTH - 1)
_SELF_SAMPLES = 200  # random configurations that decide which pairs are "always in contact"
_SELF_SEED = 0
_RAW = 0.1  # path_samples: raw resampling step as a fraction of the bounds (the thinning overhead)
_MAX_SAMPLES = 2_000_000  # resampled path rows, a guard against absurd step bounds


_Size = Annotated[float, Field(gt=0, le=0.5)]
_Size3 = Annotated[float, Field(gt=0, le=10.0)]


class StaticBox(BaseModel):
    """A fixed obstacle of the cell (a stand, a table, a fence), axis-aligned in the base frame."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = Field(pattern=r"^[A-Za-z0-9_-]{1,64}$")
    center_m: tuple[float, float, float]
    size_m: tuple[_Size3, _Size3, _Size3]


#: the floor (the table the piece stands on) is the plane z = 0 of the robot base frame
FLOOR_Z_M = 0.0


class CollisionConfig(BaseModel):
    """Collision checking parameters. Units are in the names.

    margin_m: clearance kept between the robot (camera and torch included) and the scene voxels.
    unknown_as_occupied: count unknown cells near occupied ones as obstacles (the inside and the
        unseen back of an object are unknown; the arm must not go there).
    unknown_near_m: how far (centre to centre) from an occupied cell an unknown cell still counts.
    object_box_m: > 0: every unknown cell in the box of the object seen so far, grown by this much
        sideways and upwards, counts too (parts not seen yet); 0: off.
    floor_margin_m: clearance above the floor plane z = 0 of the robot base frame.
    camera_box_m: D435 housing (x, y, z) in the camera optical frame: the long side along the
        camera x axis, centred on the optical frame origin.
    self_collision: also check pairs of robot parts against each other.
    static_boxes: fixed obstacles of the cell (stand, table, fence), kept clear by margin_m.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    margin_m: float = Field(0.02, ge=0, le=0.2)
    unknown_as_occupied: bool = True
    unknown_near_m: float = Field(0.05, ge=0, le=0.5)
    object_box_m: float = Field(0.0, ge=0, le=1.0)
    floor_margin_m: float = Field(0.02, ge=0, le=0.5)
    camera_box_m: tuple[_Size, _Size, _Size] = (0.09, 0.025, 0.025)
    self_collision: bool = True
    static_boxes: list[StaticBox] = Field(default_factory=list, max_length=64)


@dataclass(frozen=True, eq=False)
class TorchShape:
    """A cutting torch as a cylinder rigid on the flange link: radius ``radius_m``, axis = the z
    axis of ``T_flange_torch``, spanning z in [0, length_m] of that frame (origin at the mount)."""

    radius_m: float
    length_m: float
    T_flange_torch: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        for name in ("radius_m", "length_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not (math.isfinite(v) and 0 < v <= 2.0):
                raise ValueError(f"{name} must be a finite length in (0, 2] m, got {v!r}")
        object.__setattr__(self, "T_flange_torch", _as_pose(self.T_flange_torch, "T_flange_torch").copy())


@dataclass(frozen=True, eq=False)
class Collision:
    """What collided, for error messages and for planners that want to react to it."""

    kind: str  # "floor" | "static" | "scene" | "self"
    part: str  # robot part: URDF link name, "camera" or "torch"
    other: str  # "floor", "scene" or the other part
    q: np.ndarray = field(repr=False)  # the colliding configuration
    index: int | None = None  # row of the checked configurations (densified rows for check_path)
    segment: int | None = None  # check_path: the collision lies between Q[segment] and Q[segment + 1]

    def __str__(self) -> str:
        where = "" if self.index is None else f" at sample {self.index}"
        if self.segment is not None:
            where += f" (path segment {self.segment})"
        q = "[" + " ".join(f"{x:.3f}" for x in self.q) + "]"
        return f"{self.part} hits {self.other}{where}, q={q}"


# ---------------------------------------------------------------------------------------- geometry


def _rpy(rpy: Sequence[float]) -> np.ndarray:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _floats(text: str | None, n: int, default: float, what: str) -> list[float]:
    if text is None:
        return [default] * n
    vals = [float(v) for v in text.split()]
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"URDF {what} must be {n} finite numbers, got {text!r}")
    return vals


def _resolve_mesh(filename: str, urdf_dir: str) -> str:
    """package:// paths are taken relative to the URDF's directory (with or without a package name)."""
    if filename.startswith("file://"):
        filename = filename[len("file://"):]
    if filename.startswith("package://"):
        rest = filename[len("package://"):]
        candidates = [os.path.join(urdf_dir, rest)]
        if "/" in rest:  # package://<pkg>/path: try the path under the URDF dir and its parents
            tail = rest.split("/", 1)[1]
            d = urdf_dir
            for _ in range(3):
                candidates.append(os.path.join(d, tail))
                d = os.path.dirname(d)
    else:
        candidates = [filename if os.path.isabs(filename) else os.path.join(urdf_dir, filename)]
    for c in candidates:
        if os.path.isfile(c):
            return c
    raise ValueError(f"collision mesh {filename!r} not found (tried {candidates})")


def _cylinder_points(radius: float, z0: float, z1: float, n: int = 16) -> np.ndarray:
    """Rings of a polygon circumscribing the circle, so the prism contains the cylinder."""
    a = np.arange(n) * (2 * np.pi / n)
    r = radius / math.cos(math.pi / n)
    ring = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    return np.concatenate([np.c_[ring, np.full(n, z0)], np.c_[ring, np.full(n, z1)]])


def _box_points(size: Sequence[float]) -> np.ndarray:
    corners = np.array(list(itertools.product((-0.5, 0.5), repeat=3)))
    return corners * np.asarray(size, dtype=np.float64)


def _urdf_collision_points(urdf_path: str) -> list[tuple[str, np.ndarray]]:
    """(link, points in the link frame) per <collision> element; hulls are taken later. Read once
    per file version (a cut plan builds its own checker; the meshes are the same every time)."""
    try:
        st = os.stat(urdf_path)
    except OSError as e:
        raise ValueError(f"urdf_path {urdf_path!r} cannot be read as URDF: {e}") from None
    return _urdf_points_of(os.path.abspath(urdf_path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=8)
def _urdf_points_of(urdf_path: str, mtime_ns: int, size: int) -> list[tuple[str, np.ndarray]]:
    try:
        root = ET.parse(urdf_path).getroot()
    except (OSError, ET.ParseError) as e:
        raise ValueError(f"urdf_path {urdf_path!r} cannot be read as URDF: {e}") from None
    urdf_dir = os.path.dirname(os.path.abspath(urdf_path))
    out = []
    for link in root.findall("link"):
        name = link.get("name")
        for col in link.findall("collision"):
            origin = col.find("origin")
            T = np.eye(4)
            if origin is not None:
                T[:3, :3] = _rpy(_floats(origin.get("rpy"), 3, 0.0, "origin rpy"))
                T[:3, 3] = _floats(origin.get("xyz"), 3, 0.0, "origin xyz")
            geom = col.find("geometry")
            shape = None if geom is None else next(iter(geom), None)
            if shape is None:
                raise ValueError(f"URDF link {name!r} has a <collision> without geometry")
            if shape.tag == "mesh":
                path = _resolve_mesh(shape.get("filename", ""), urdf_dir)
                pts = np.asarray(trimesh.load(path, force="mesh").vertices, dtype=np.float64)
                pts = pts * _floats(shape.get("scale"), 3, 1.0, "mesh scale")
            elif shape.tag == "box":
                pts = _box_points(_floats(shape.get("size"), 3, 0.0, "box size"))
            elif shape.tag == "cylinder":
                r, length = float(shape.get("radius")), float(shape.get("length"))
                pts = _cylinder_points(r, -length / 2, length / 2)
            elif shape.tag == "sphere":
                ico = trimesh.creation.icosphere(subdivisions=1)
                pts = ico.vertices * float(shape.get("radius")) / _inscribed_radius(ico)
            else:
                raise ValueError(f"URDF link {name!r}: unsupported collision geometry <{shape.tag}>")
            if len(pts) < 4:
                raise ValueError(f"URDF link {name!r}: collision geometry has fewer than 4 vertices")
            out.append((name, _frozen(pts @ T[:3, :3].T + T[:3, 3])))
    return out


def _prismatic_travel(urdf_path: str, arm_joints: Sequence[str]) -> dict[str, np.ndarray]:
    """Child link -> its travel (axis x [lower, upper]) for prismatic joints outside the arm (the
    gripper fingers): the model locks them at zero, the gripper may stand anywhere in its range."""
    root = ET.parse(urdf_path).getroot()
    out = {}
    for j in root.findall("joint"):
        if j.get("type") != "prismatic" or j.get("name") in arm_joints:
            continue
        child, lim, ax = j.find("child"), j.find("limit"), j.find("axis")
        if child is None or lim is None:
            continue
        axis = np.asarray(_floats(None if ax is None else ax.get("xyz"), 3, 0.0, "joint axis")) if ax is not None \
            else np.array([1.0, 0.0, 0.0])
        lo, hi = float(lim.get("lower", 0.0)), float(lim.get("upper", 0.0))
        out[child.get("link")] = np.outer([lo, hi], axis)  # joint frame == child link frame
    return out


def _inscribed_radius(poly: trimesh.Trimesh) -> float:
    v = poly.vertices[poly.faces[:, 0]]
    return float(np.min(np.abs(np.einsum("ij,ij->i", poly.face_normals, v))))


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False  # shared by every checker built from the same geometry
    return a


def _memo(fn):
    """``fn(*args)`` computed once per distinct arguments (arrays by their contents): the same
    robot's hulls, inflations and ball covers are asked for by every checker, and each cut plan
    builds its own. Results are read-only."""
    cache: dict = {}

    @functools.wraps(fn)
    def call(*args):
        key = tuple((a.tobytes(), a.shape, a.dtype.str) if isinstance(a, np.ndarray) else a for a in args)
        out = cache.get(key)
        if out is None:
            out = tuple(_frozen(o) for o in fn(*args))
            if len(cache) >= 512:
                cache.pop(next(iter(cache)))
            cache[key] = out
        return out
    return call


@_memo
def _hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h = trimesh.convex.convex_hull(points)
    return np.asarray(h.vertices, dtype=np.float64), np.asarray(h.faces, dtype=np.int64)


_BALL = trimesh.creation.icosphere(subdivisions=1)
_BALL_POINTS = _BALL.vertices / _inscribed_radius(_BALL)  # contains the unit ball, <= 7 % larger


@_memo
def _inflate(vertices: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Hull of the Minkowski sum with a polytope that contains the margin ball (conservative)."""
    if margin == 0:
        return _hull(vertices)
    return _hull((vertices[:, None, :] + margin * _BALL_POINTS[None]).reshape(-1, 3))


@_memo
def _ball_cover(vertices: np.ndarray, faces: np.ndarray, slab_m: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """(centres (B, 3), radii (B,)) of balls whose union contains the convex hull: the hull cut into
    slabs ``slab_m`` thick along its longest principal axis, each slab's piece in one ball. A piece
    of a convex polytope is the hull of the polytope's vertices inside the slab and the points where
    its edges cross the slab's planes, so the ball round those points holds it. Finer than one ball
    per part for the distance-map shortcut of ``CollisionChecker.free``."""
    c = vertices.mean(axis=0)
    axis = np.linalg.svd(vertices - c, full_matrices=False)[2][0]
    t = (vertices - c) @ axis
    k = max(1, int(np.ceil((t.max() - t.min()) / slab_m)))
    cuts = np.linspace(t.min(), t.max(), k + 1)
    e = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    a, b = vertices[e[:, 0]], vertices[e[:, 1]]
    ta, tb = t[e[:, 0]], t[e[:, 1]]
    centres, radii = [], []
    for lo, hi in zip(cuts[:-1], cuts[1:]):  # a few slabs per part
        pts = [vertices[(t >= lo - 1e-12) & (t <= hi + 1e-12)]]
        for plane in (lo, hi):
            cross = (np.minimum(ta, tb) < plane) & (np.maximum(ta, tb) > plane)
            f = (plane - ta[cross]) / (tb[cross] - ta[cross])
            pts.append(a[cross] + f[:, None] * (b[cross] - a[cross]))
        pts = np.vstack(pts)
        m = (pts.max(axis=0) + pts.min(axis=0)) / 2
        centres.append(m)
        radii.append(np.linalg.norm(pts - m, axis=1).max())
    return np.array(centres), np.array(radii)


@nb.njit(cache=True, parallel=True)
def _on_parts(pts, centres, reach, R, t, plane_n, plane_d, plane_start, pad):
    """Per point: inside some part's hull grown by `pad` (the part's bounding ball first, then every
    face plane in the part's frame)? One compiled pass over a D435 frame's 400 k points."""
    n = pts.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for i in nb.prange(n):
        x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
        for k in range(centres.shape[0]):
            dx, dy, dz = x - centres[k, 0], y - centres[k, 1], z - centres[k, 2]
            if dx * dx + dy * dy + dz * dz > reach[k] * reach[k]:
                continue
            ex, ey, ez = x - t[k, 0], y - t[k, 1], z - t[k, 2]
            lx = ex * R[k, 0, 0] + ey * R[k, 1, 0] + ez * R[k, 2, 0]  # (p - t) @ R: into the part's frame
            ly = ex * R[k, 0, 1] + ey * R[k, 1, 1] + ez * R[k, 2, 1]
            lz = ex * R[k, 0, 2] + ey * R[k, 1, 2] + ez * R[k, 2, 2]
            inside = True
            for f in range(plane_start[k], plane_start[k + 1]):
                if lx * plane_n[f, 0] + ly * plane_n[f, 1] + lz * plane_n[f, 2] > plane_d[f] + pad:
                    inside = False
                    break
            if inside:
                out[i] = True
                break
    return out


def warmup() -> None:
    """Compile (or load from numba's cache) the robot self-filter before the first timed step."""
    one = np.zeros((1, 3))
    _on_parts(one, one, np.ones(1), np.eye(3)[None], one, one, np.ones(1), np.array([0, 1], np.int64), 0.0)


def _face_planes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals (m, 3) and offsets (m,) of a convex hull's faces: inside is n.x <= d."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    d = np.einsum("ij,ij->i", n, a)
    flip = d < np.einsum("ij,j->i", n, vertices.mean(axis=0))  # orient away from the centroid
    n[flip], d[flip] = -n[flip], -d[flip]
    return n, d


def _convex(vertices: np.ndarray, faces: np.ndarray) -> fcl.CollisionObject:
    flat = np.c_[np.full(len(faces), 3), faces].ravel().tolist()
    return fcl.CollisionObject(fcl.Convex(vertices, len(faces), flat), fcl.Transform())


def _place(obj: fcl.CollisionObject, T: np.ndarray) -> None:
    obj.setTransform(fcl.Transform(T[:3, :3], T[:3, 3]))


# ---------------------------------------------------------------------------------------- robot


@dataclass(frozen=True, eq=False)
class _Part:
    name: str
    link: str
    vertices: np.ndarray  # (n, 3) convex hull vertices, link frame
    faces: np.ndarray  # (m, 3)
    tool: bool = False  # a shape added on the flange, not a URDF collision element


class RobotCollisionModel:
    """The arm's collision parts (URDF hulls + camera box + optional torch) and their poses.

    Args:
        urdf_path, joint_names, flange_link, T_flange_cam: as for ``Kinematics``.
        camera_box_m: D435 housing size in the camera frame (x long side), or None for no camera.
        torch: optional cylinder on the flange.
        home_q: a configuration free of self-collision (default: middle of the joint limits);
            pairs touching there and in each of 200 random samples are not self-checked.
        sweep_gripper: the finger hulls cover their whole travel (closed to fully open), since
            the kinematic model holds them closed while the real gripper may stand open.

    Raises:
        ValueError: unreadable URDF or mesh, bad link/joint names, bad shapes or poses.
    """

    def __init__(
        self,
        urdf_path: str,
        joint_names: Sequence[str],
        flange_link: str,
        T_flange_cam: np.ndarray,
        *,
        camera_box_m: Sequence[float] | None = (0.09, 0.025, 0.025),
        torch: TorchShape | None = None,
        home_q: np.ndarray | None = None,
        sweep_gripper: bool = True,
    ) -> None:
        if not os.path.isfile(str(urdf_path)):
            raise ValueError(f"urdf_path {urdf_path!r} is not a file")
        self.kin = Kinematics(urdf_path, joint_names, flange_link, T_flange_cam)
        kin = self.kin
        parts: list[_Part] = []
        seen: dict[str, int] = {}
        travel = _prismatic_travel(kin.urdf_path, joint_names) if sweep_gripper else {}
        for link, pts in _urdf_collision_points(kin.urdf_path):
            kin.link_frame_id(link)
            if link in travel:  # the hull swept over the joint's whole travel: any gripper opening
                pts = np.concatenate([pts + d for d in travel[link]])
            k = seen.get(link, 0)
            seen[link] = k + 1
            parts.append(_Part(link if k == 0 else f"{link}#{k}", link, *_hull(pts)))
        if not parts:
            raise ValueError(f"urdf_path {urdf_path!r} has no <collision> geometry")
        if camera_box_m is not None:
            size = np.asarray(camera_box_m, dtype=np.float64)
            if size.shape != (3,) or not np.all(np.isfinite(size)) or not np.all(size > 0):
                raise ValueError(f"camera_box_m must be 3 positive finite sizes, got {camera_box_m!r}")
            T = kin.T_flange_cam
            parts.append(_Part("camera", flange_link, *_hull(_box_points(size) @ T[:3, :3].T + T[:3, 3]), tool=True))
        if torch is not None:
            if not isinstance(torch, TorchShape):
                raise ValueError(f"torch must be a TorchShape, got {type(torch).__name__}")
            T = torch.T_flange_torch
            pts = _cylinder_points(torch.radius_m, 0.0, torch.length_m)
            parts.append(_Part("torch", flange_link, *_hull(pts @ T[:3, :3].T + T[:3, 3]), tool=True))
        self.parts: tuple[_Part, ...] = tuple(parts)
        self.part_names: tuple[str, ...] = tuple(p.name for p in parts)
        self.links: tuple[str, ...] = tuple(dict.fromkeys(p.link for p in parts))
        self._part_link = np.array([self.links.index(p.link) for p in parts], dtype=np.intp)
        model = kin.model
        joint_of = np.array([model.frames[kin.link_frame_id(p.link)].parentJoint for p in parts])
        #: parts fixed to the base: never tested against the floor or the scene
        self.fixed = joint_of == 0
        self._raw = [_convex(p.vertices, p.faces) for p in parts]
        # bounding spheres (link frame) for a cheap numpy pre-test of the pairs
        lo = np.stack([p.vertices.min(0) for p in parts])
        hi = np.stack([p.vertices.max(0) for p in parts])
        self._centre = (lo + hi) / 2
        self._radius = np.array([np.linalg.norm(p.vertices - c, axis=1).max() for p, c in zip(parts, self._centre)])
        # for on_robot: every part's hull face planes packed for the compiled filter, part k's normals
        # and offsets at rows _plane_start[k]:_plane_start[k + 1]
        planes = [_face_planes(p.vertices, p.faces) for p in parts]
        self._plane_n = np.ascontiguousarray(np.concatenate([n for n, _ in planes]), dtype=np.float64)
        self._plane_d = np.ascontiguousarray(np.concatenate([d for _, d in planes]), dtype=np.float64)
        self._plane_start = np.concatenate([[0], np.cumsum([len(d) for _, d in planes])]).astype(np.int64)

        if home_q is None:
            home_q = (kin.lower + kin.upper) / 2
        home_q = kin._vec(home_q, "home_q")
        pairs = []
        for i, j in itertools.combinations(range(len(parts)), 2):
            a, b = int(joint_of[i]), int(joint_of[j])
            rigid = a == b
            adjacent = not (parts[i].tool or parts[j].tool) and (model.parents[a] == b or model.parents[b] == a)
            if not (rigid or adjacent):
                pairs.append((i, j))
        pairs_arr = np.array(pairs, dtype=np.intp).reshape(-1, 2)
        rng = np.random.default_rng(_SELF_SEED)
        samples = np.vstack([home_q, rng.uniform(kin.lower, kin.upper, (_SELF_SAMPLES, kin.dof))])
        always = np.ones(len(pairs_arr), dtype=bool)
        for q in samples:
            if not always.any():
                break
            hit = self._pairs_colliding(q, pairs_arr[always])
            always[np.flatnonzero(always)[~hit]] = False
        #: (K, 2) part indices checked for self-collision
        self.self_pairs = pairs_arr[~always]
        #: part-name pairs left out because they touch in every sampled configuration
        self.always_touching = tuple((self.part_names[i], self.part_names[j]) for i, j in pairs_arr[always])

    @classmethod
    def from_arm_model(cls, arm_model, cfg: CollisionConfig | None = None, *,
                       torch: TorchShape | None = None, home_q: np.ndarray | None = None) -> "RobotCollisionModel":
        """From anything with ``urdf_path, joint_names, flange_link, T_flange_cam`` (an ArmModel)."""
        cfg = cfg or CollisionConfig()
        return cls(arm_model.urdf_path, arm_model.joint_names, arm_model.flange_link, arm_model.T_flange_cam,
                   camera_box_m=cfg.camera_box_m, torch=torch, home_q=home_q)

    def link_poses(self, q: np.ndarray) -> np.ndarray:
        """T_base_<link> (L, 4, 4) of ``self.links`` at q (parts are given in their link frames)."""
        return self.kin.link_poses(q, self.links)

    def part_poses(self, q: np.ndarray) -> np.ndarray:
        """(P, 4, 4) pose of each part's frame (= its link's frame) at q."""
        return self.link_poses(q)[self._part_link]

    def part_poses_batch(self, Q: np.ndarray) -> np.ndarray:
        """(N, P, 4, 4): ``part_poses`` for every row of Q (N, dof)."""
        return self.kin.link_poses_batch(Q, self.links)[:, self._part_link]

    def on_robot(self, points: np.ndarray, q: np.ndarray, pad_m: float = 0.02) -> np.ndarray:
        """Which points (N, 3), base frame, lie on the robot at q (inside a part's hull grown by
        ``pad_m``): the camera sees its own arm now and then, and those returns must not become
        obstacles the arm then collides with (a robot self-filter)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        out = np.zeros(len(pts), dtype=bool)
        if len(pts) == 0:
            return out
        P = self.part_poses(q)
        c = np.einsum("pij,pj->pi", P[:, :3, :3], self._centre) + P[:, :3, 3]
        return _on_parts(np.ascontiguousarray(pts), c, self._radius + pad_m, np.ascontiguousarray(P[:, :3, :3]),
                         np.ascontiguousarray(P[:, :3, 3]), self._plane_n, self._plane_d, self._plane_start, float(pad_m))

    def _pairs_colliding(self, q: np.ndarray, pairs: np.ndarray, poses: np.ndarray | None = None) -> np.ndarray:
        """Boolean per pair; numpy bounding-sphere test first, fcl only for the overlapping ones."""
        P = self.part_poses(q) if poses is None else poses
        c = np.einsum("pij,pj->pi", P[:, :3, :3], self._centre) + P[:, :3, 3]
        i, j = pairs[:, 0], pairs[:, 1]
        near = np.linalg.norm(c[i] - c[j], axis=1) <= self._radius[i] + self._radius[j]
        out = np.zeros(len(pairs), dtype=bool)
        placed = set()
        for k in np.flatnonzero(near):
            a, b = int(i[k]), int(j[k])
            for m in (a, b):
                if m not in placed:
                    _place(self._raw[m], P[m])
                    placed.add(m)
            out[k] = fcl.collide(self._raw[a], self._raw[b]) > 0
        return out


# ---------------------------------------------------------------------------------------- octree


def _octree_data(keys: np.ndarray) -> tuple[list[int], int]:
    """octomap ``readBinaryData`` stream of occupied leaves at the given 16-bit keys (N, 3), and the
    number of distinct leaves.

    Each inner node is 2 bytes, 2 bits per child (child index = x + 2y + 4z of the key bit at that
    level; value 2 = occupied leaf, 3 = inner node, 0 = absent), in depth-first pre-order. Nodes whose 8
    children are all occupied leaves become one bigger occupied leaf. Vectorized per level: the
    codes stay sorted, so parents are found with a diff instead of a sort.
    """
    k = keys.astype(np.uint64)
    code = np.zeros(len(k), dtype=np.uint64)
    one = np.uint64(1)
    for b in range(_OCTREE_DEPTH):  # Morton code: 3 bits per level, root level most significant
        ub = np.uint64(b)
        digit = ((k[:, 0] >> ub) & one) | (((k[:, 1] >> ub) & one) << one) | (((k[:, 2] >> ub) & one) << np.uint64(2))
        code |= digit << np.uint64(3 * b)
    leaves = np.unique(code)
    n_leaves = len(leaves)
    inner = np.empty(0, dtype=np.uint64)
    codes, status = [], []
    for d in range(_OCTREE_DEPTH, 0, -1):  # children at depth d -> their parents at depth d - 1
        child = np.concatenate([leaves, inner])
        kind = np.concatenate([np.full(len(leaves), 2, np.uint8), np.full(len(inner), 3, np.uint8)])
        if len(leaves) and len(inner):
            order = np.argsort(child, kind="stable")  # two sorted runs: a merge
            child, kind = child[order], kind[order]
        p = child >> np.uint64(3)
        first = np.empty(len(p), dtype=bool)
        first[:1] = True
        np.not_equal(p[1:], p[:-1], out=first[1:])
        parent = p[first]
        st = np.zeros((len(parent), 8), np.uint8)
        st[np.cumsum(first) - 1, (child & np.uint64(7)).astype(np.intp)] = kind
        full = np.all(st == 2, axis=1)
        if d == 1:
            full[:] = False  # the root is always written as an inner node
        leaves, inner = parent[full], parent[~full]
        # pre-order key: the node's code padded to full depth, then its depth (a prefix comes first)
        codes.append((inner << np.uint64(3 * (_OCTREE_DEPTH - d + 1) + 4)) | np.uint64(d - 1))
        status.append(st[~full])
    codes_a, st_a = np.concatenate(codes), np.concatenate(status)
    st_a = st_a[np.argsort(codes_a)].astype(np.uint16)
    shift = np.array([0, 2, 4, 6], dtype=np.uint16)
    lo = (st_a[:, :4] << shift).sum(1).astype(np.uint8)
    hi = (st_a[:, 4:] << shift).sum(1).astype(np.uint8)
    # python-fcl copies the stream through a vector<char>: it wants signed values
    return np.stack([lo, hi], 1).reshape(-1).view(np.int8).tolist(), n_leaves


# ---------------------------------------------------------------------------------------- paths


def _xyz(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def _positive(x, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not math.isfinite(x) or x <= 0:
        raise ValueError(f"{name} must be a finite positive number, got {x!r}")
    return float(x)


def _subdivide(X: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Split step k (X[k] -> X[k+1]) into counts[k] equal steps, linearly."""
    if counts.sum() > _MAX_SAMPLES:
        raise ValueError(f"the path would need {int(counts.sum())} samples (> {_MAX_SAMPLES}): "
                         "max_joint_step_rad / max_tcp_step_m are too small for it")
    idx = np.repeat(np.arange(len(X) - 1), counts)
    start = np.repeat(np.cumsum(counts) - counts, counts)
    frac = ((np.arange(len(idx)) - start) / np.repeat(counts, counts))[:, None]
    return np.vstack([X[idx] + frac * (X[idx + 1] - X[idx]), X[-1:]])


def _densify(X: np.ndarray, step: float) -> np.ndarray:
    d = np.abs(np.diff(X[:, :-1], axis=0)).max(axis=1)
    return _subdivide(X, np.maximum(np.ceil(d / step - 1e-9).astype(np.intp), 1))


def _with_param(Q: np.ndarray) -> np.ndarray:
    """Q with an extra last column t = row index: interpolated along, it tells each sample's segment
    (floor t) and whether it is a row of Q (t integer: the interpolation adds exactly 0 there)."""
    return np.c_[Q, np.arange(len(Q), dtype=np.float64)]


def _segment(t: np.ndarray, T: int) -> np.ndarray:
    return np.minimum(np.floor(t).astype(np.intp), max(T - 2, 0))


def densify_joint_path(Q: np.ndarray, max_joint_step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear joint-space resampling so no joint moves more than ``max_joint_step_rad`` between
    consecutive rows; every row of Q is kept. Returns (Qd, segment): row r of Qd lies on
    Q[segment[r]] -> Q[segment[r] + 1] (Q[-1] belongs to the last segment)."""
    Q = np.asarray(Q, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[0] == 0 or Q.shape[1] == 0:
        raise ValueError(f"Q must have shape (T, dof) with T >= 1, got {Q.shape}")
    if not np.all(np.isfinite(Q)):
        raise ValueError("Q contains NaN or inf")
    step = _positive(max_joint_step_rad, "max_joint_step_rad")
    if len(Q) == 1:
        return Q.copy(), np.zeros(1, dtype=np.intp)
    X = _densify(_with_param(Q), step)
    return X[:, :-1], _segment(X[:, -1], len(Q))


# ---------------------------------------------------------------------------------------- scene


def _object_box_unknown(grid, ijk: np.ndarray, margin_m: float, floor_m: float = 0.03) -> np.ndarray:
    """Unknown cells (K, 3) in the box around the object seen so far (its occupied cells above the
    floor, grown by ``margin_m`` sideways and upwards, down to the floor): a part no view has seen
    yet (the far end of a T-piece) is somewhere in there."""
    obj = ijk[grid.centers(ijk)[:, 2] > floor_m]
    if len(obj) == 0 or margin_m <= 0:
        return np.empty((0, 3), dtype=np.int64)
    m = int(math.ceil(margin_m / grid.voxel))
    lo = np.maximum(obj.min(axis=0) - m, 0)
    lo[2] = 0
    hi = np.minimum(obj.max(axis=0) + m + 1, grid.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    return np.argwhere(grid.unknown[box]) + lo


def grid_scene_voxels(grid, unknown_near_m: float, object_box_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(occupied centres (N, 3), unknown centres (M, 3) that count as solid) of an ``OccupancyGrid``:
    the unknown within ``unknown_near_m`` of an occupied cell (the inside and back of an object are as
    solid as its surface) and, with ``object_box_m`` > 0, every unknown cell of the object's box
    grown by that margin.

    Works on the occupied cells' bounding box grown by the distance only."""
    near = float(unknown_near_m)
    if not math.isfinite(near) or near < 0:
        raise ValueError(f"unknown_near_m must be a finite distance >= 0, got {unknown_near_m!r}")
    occ = grid.occupied
    ijk = np.argwhere(occ)
    if len(ijk) == 0:
        return np.empty((0, 3)), np.empty((0, 3))
    occupied = grid.centers(ijk)
    in_box = _object_box_unknown(grid, ijk, float(object_box_m))
    r = int(math.floor(near / grid.voxel + 1e-9))
    if r == 0:
        return occupied, grid.centers(in_box)
    lo = np.maximum(ijk.min(axis=0) - r, 0)
    hi = np.minimum(ijk.max(axis=0) + r + 1, grid.shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    # unknown cells within the cube of half-side r (separable max filter, cheap), then the exact
    # Euclidean test on those few with a k-d tree of the occupied cells
    cube = ndimage.maximum_filter(occ[box], size=2 * r + 1, mode="constant", cval=False)
    cand = np.argwhere(cube & grid.unknown[box]) + lo
    if len(cand) == 0:
        return occupied, grid.centers(in_box)
    reach = near / grid.voxel + 1e-9  # in cells, centre to centre
    dist, _ = cKDTree(ijk).query(cand, distance_upper_bound=reach)
    solid = cand[dist <= reach]
    if len(in_box):
        solid = np.unique(np.concatenate([solid, in_box]), axis=0)
    return occupied, grid.centers(solid)


# ---------------------------------------------------------------------------------------- checker


class CollisionChecker:
    """Robot vs floor, itself and the scanned scene, with a clearance margin to the scene.

    Args:
        robot: the collision model (``RobotCollisionModel``); shared read-only geometry.
        cfg: margins and what counts as an obstacle.
    """

    def __init__(self, robot: RobotCollisionModel, cfg: CollisionConfig | None = None) -> None:
        if not isinstance(robot, RobotCollisionModel):
            raise ValueError(f"robot must be a RobotCollisionModel, got {type(robot).__name__}")
        cfg = CollisionConfig() if cfg is None else cfg
        if not isinstance(cfg, CollisionConfig):
            raise ValueError(f"cfg must be a CollisionConfig, got {type(cfg).__name__}")
        self.robot = robot
        self.cfg = cfg
        parts = robot.parts
        moving = np.flatnonzero(~robot.fixed)
        self._moving = moving
        # floor: all hull vertices of the moving parts, stacked, with their part index
        self._floor_v = np.concatenate([parts[i].vertices for i in moving])
        self._floor_part = np.repeat(moving, [len(parts[i].vertices) for i in moving])
        self._floor_start = np.cumsum([0] + [len(parts[i].vertices) for i in moving[:-1]])
        # scene: parts inflated by the margin, with their local boxes for a numpy pre-test
        inflated = [_inflate(parts[i].vertices, cfg.margin_m) for i in moving]
        self._inflated = [_convex(v, f) for v, f in inflated]
        lo = np.stack([v.min(0) for v, _ in inflated])
        hi = np.stack([v.max(0) for v, _ in inflated])
        self._box_c, self._box_h = (lo + hi) / 2, (hi - lo) / 2
        # balls covering each inflated part, for the scene's distance map: (B,3) in their part's frame
        cover = [_ball_cover(v, f) for v, f in inflated]
        self._ball_part = np.repeat(np.arange(len(cover)), [len(c) for c, _ in cover])
        self._ball_c = np.vstack([c for c, _ in cover])
        self._ball_r = np.concatenate([r for _, r in cover])
        self._ball_start = np.cumsum([0] + [len(c) for c, _ in cover[:-1]])
        self._scene_dist = None
        # balls covering each part as it is (self-collision uses the bare hulls), and for every self
        # pair the pairs of its two parts' balls, grouped by self pair
        raw = [_ball_cover(p.vertices, p.faces) for p in parts]
        offset = np.cumsum([0] + [len(c) for c, _ in raw[:-1]])
        ba, bb, first = [], [], []
        for a, b in robot.self_pairs:
            first.append(len(ba))
            ia = offset[a] + np.arange(len(raw[a][0]))
            ib = offset[b] + np.arange(len(raw[b][0]))
            ba += np.repeat(ia, len(ib)).tolist()
            bb += np.tile(ib, len(ia)).tolist()
        self._self_balls = (np.repeat(np.arange(len(raw)), [len(c) for c, _ in raw]), np.vstack([c for c, _ in raw]),
                            np.concatenate([r for _, r in raw]), np.array(ba, dtype=np.intp),
                            np.array(bb, dtype=np.intp), np.array(first, dtype=np.intp))
        self._scene: fcl.CollisionObject | None = None
        self._scene_lo = self._scene_hi = None
        self.scene_voxels = 0
        self._static = [(b.name, fcl.CollisionObject(fcl.Box(*b.size_m), fcl.Transform(np.asarray(b.center_m, float))),
                         np.asarray(b.center_m) - np.asarray(b.size_m) / 2, np.asarray(b.center_m) + np.asarray(b.size_m) / 2)
                        for b in cfg.static_boxes]

    @classmethod
    def for_arm(cls, arm_model, cfg: CollisionConfig | None = None, *,
                torch: TorchShape | None = None) -> "CollisionChecker":
        """Checker for an ``ArmModel``-like object (``urdf_path, joint_names, flange_link, T_flange_cam``)."""
        cfg = CollisionConfig() if cfg is None else cfg
        return cls(RobotCollisionModel.from_arm_model(arm_model, cfg, torch=torch), cfg)

    # ------------------------------------------------------------------ scene

    def set_scene(self, occupied_xyz: np.ndarray, voxel_m: float, unknown_xyz: np.ndarray | None = None) -> None:
        """Replace the scene with cubes of side ``voxel_m`` at the given centres (all on one lattice).
        Unknown cells are obstacles only when ``cfg.unknown_as_occupied``."""
        voxel = _positive(voxel_m, "voxel_m")
        occ = _xyz(occupied_xyz, "occupied_xyz")
        pts = [occ]
        if unknown_xyz is not None:
            unk = _xyz(unknown_xyz, "unknown_xyz")
            if self.cfg.unknown_as_occupied:
                pts.append(unk)
        xyz = np.concatenate(pts) if len(pts) > 1 else occ
        if len(xyz) == 0:
            self.clear_scene()
            return
        origin = xyz.min(axis=0) - voxel / 2  # a lattice corner: every centre is origin + (ijk + 1/2) voxel
        f = (xyz - origin) / voxel - 0.5
        ijk = np.rint(f)
        if np.abs(f - ijk).max() > 0.1:
            raise ValueError(f"voxel centres are not on one lattice of pitch voxel_m={voxel} "
                             f"(off by up to {np.abs(f - ijk).max():.2f} voxel)")
        ijk = ijk.astype(np.int64)
        if ijk.max() >= _KEY_OFFSET:
            raise ValueError(f"scene spans {ijk.max() + 1} voxels on an axis; at most {_KEY_OFFSET} fit one octree")
        data, n = _octree_data(ijk + _KEY_OFFSET)
        tree = fcl.OcTree(voxel, data)
        self._scene = fcl.CollisionObject(tree, fcl.Transform(origin))
        self._scene_ijk, self._scene_voxel, self._scene_dist = ijk - ijk.min(axis=0), voxel, None
        self._scene_lo = origin + ijk.min(axis=0) * voxel
        self._scene_hi = origin + (ijk.max(axis=0) + 1) * voxel
        self.scene_voxels = n

    def set_scene_from_grid(self, grid) -> np.ndarray:
        """Scene from an ``OccupancyGrid``: its occupied cells and the unknown ones near them.
        Returns the centres (M,3) of the unknown cells it counts as solid."""
        near = self.cfg.unknown_near_m if self.cfg.unknown_as_occupied else 0.0
        occ, unk = grid_scene_voxels(grid, near, self.cfg.object_box_m if self.cfg.unknown_as_occupied else 0.0)
        self.set_scene(occ, grid.voxel, unk)
        return unk if self.cfg.unknown_as_occupied else np.zeros((0, 3))

    def clear_scene(self) -> None:
        self._scene = None
        self._scene_lo = self._scene_hi = None
        self.scene_voxels = 0

    # ------------------------------------------------------------------ queries

    def check(self, q: np.ndarray) -> Collision | None:
        """The first collision found at q (floor, then scene, then self), or None when free."""
        q = self.robot.kin._vec(q)
        return self._check(q)

    def in_collision(self, q: np.ndarray) -> bool:
        return self.check(q) is not None

    def free(self, Q: np.ndarray) -> np.ndarray:
        """(N,) bool: row k of Q (N, dof) is clear of floor, static boxes, scene and self, exactly as
        ``not in_collision(Q[k])``. The broad phase runs for all rows at once in numpy (forward
        kinematics, the floor, part boxes against the scene's box, the scene's distance map against
        each part's bounding sphere, bounding spheres of self pairs); fcl sees only what is left."""
        Q = self._rows(Q)
        robot = self.robot
        P = robot.part_poses_batch(Q)  # (N, P, 4, 4)
        # floor: each moving part's bounding sphere first; hull vertices only for rows where one dips
        Zm = P[:, self._moving, 2]  # (N, M, 4): the z row of each moving part's pose
        low = np.einsum("nmj,mj->nm", Zm[..., :3], robot._centre[self._moving]) + Zm[..., 3] \
            - robot._radius[self._moving] < self.cfg.floor_margin_m
        ok = np.ones(len(Q), dtype=bool)
        rows = np.flatnonzero(low.any(axis=1))
        if len(rows):
            Z = P[rows][:, self._floor_part, 2]  # (n, V, 4): the z row of each vertex's part pose
            z = np.einsum("vj,nvj->nv", self._floor_v, Z[..., :3]) + Z[..., 3]
            ok[rows] = np.minimum.reduceat(z, self._floor_start, axis=1).min(axis=1) >= self.cfg.floor_margin_m
        if self._scene is not None or self._static:
            Pm = P[:, self._moving]
            R = Pm[..., :3, :3]
            c = np.einsum("npij,pj->npi", R, self._box_c) + Pm[..., :3, 3]
            h = np.einsum("npij,pj->npi", np.abs(R), self._box_h)
            for _, box, lo, hi in self._static:
                cand = ok[:, None] & np.all((c + h >= lo) & (c - h <= hi), axis=2)
                ok &= ~self._narrow(cand, Pm, box)
            if self._scene is not None:
                cand = ok[:, None] & np.all((c + h >= self._scene_lo) & (c - h <= self._scene_hi), axis=2)
                if cand.any():  # does some ball of the part reach the scene?
                    Pb = Pm[:, self._ball_part]
                    centre = np.einsum("nbij,bj->nbi", Pb[..., :3, :3], self._ball_c) + Pb[..., :3, 3]
                    near = self._scene_distance(centre) <= self._ball_r  # (N, B), balls grouped by part
                    cand &= np.logical_or.reduceat(near, self._ball_start, axis=1)
                ok &= ~self._narrow(cand, Pm, self._scene)
        if self.cfg.self_collision and len(robot.self_pairs) and ok.any():
            rows = np.flatnonzero(ok)
            i, j = robot.self_pairs[:, 0], robot.self_pairs[:, 1]
            bp, bc, br, ba, bb, first = self._self_balls
            # the two parts' bounding spheres first; their balls only for the pairs whose spheres meet
            Pr = P[rows]
            pc = np.einsum("npij,pj->npi", Pr[..., :3, :3], robot._centre) + Pr[..., :3, 3]
            near = np.linalg.norm(pc[:, i] - pc[:, j], axis=2) <= robot._radius[i] + robot._radius[j]  # (n, pairs)
            some = np.flatnonzero(near.any(axis=0))
            if len(some):
                last = np.append(first[1:], len(ba))
                cols = np.concatenate([np.arange(first[k], last[k]) for k in some])  # a few dozen pairs
                Pb = Pr[:, bp]  # (n, balls, 4, 4): each ball's part pose
                c = np.einsum("nbij,bj->nbi", Pb[..., :3, :3], bc) + Pb[..., :3, 3]
                a_, b_ = ba[cols], bb[cols]
                meet = np.linalg.norm(c[:, a_] - c[:, b_], axis=2) <= br[a_] + br[b_]  # (n, their ball pairs)
                starts = np.cumsum([0] + [int(last[k] - first[k]) for k in some[:-1]])
                near[:, some] &= np.logical_or.reduceat(meet, starts, axis=1)  # some balls of the two meet
            for r, k in zip(*np.nonzero(near)):  # narrow phase: the few pairs whose balls meet
                if not ok[rows[r]]:
                    continue
                a, b = int(i[k]), int(j[k])
                _place(robot._raw[a], P[rows[r], a])
                _place(robot._raw[b], P[rows[r], b])
                if fcl.collide(robot._raw[a], robot._raw[b]) > 0:
                    ok[rows[r]] = False
        return ok

    def _narrow(self, cand: np.ndarray, Pm: np.ndarray, other: fcl.CollisionObject) -> np.ndarray:
        """(N,) bool: some candidate (row, moving part) of ``cand`` (N, M) touches ``other`` (fcl)."""
        hit = np.zeros(len(cand), dtype=bool)
        for n, k in zip(*np.nonzero(cand)):  # narrow phase only: no batched call in fcl
            if hit[n]:
                continue
            obj = self._inflated[k]
            _place(obj, Pm[n, k])
            hit[n] = fcl.collide(obj, other) > 0
        return hit

    def _scene_distance(self, points: np.ndarray) -> np.ndarray:
        """Lower bound on the distance from each point (..., 3) to the scene's voxels (their cubes),
        from a distance map of the scene's lattice built on first use (the octree has none)."""
        if self._scene_dist is None:
            from scipy.ndimage import distance_transform_edt
            occ = np.ones(tuple(self._scene_ijk.max(axis=0) + 1), dtype=bool)
            occ[tuple(self._scene_ijk.T)] = False
            self._scene_dist = distance_transform_edt(occ) * self._scene_voxel  # centre to nearest centre
        v = self._scene_voxel
        f = (points - self._scene_lo) / v - 0.5
        shape = np.array(self._scene_dist.shape)
        idx = np.clip(np.rint(f), 0, shape - 1).astype(np.intp)
        outside = np.linalg.norm((f - idx) * v, axis=-1)  # how far beyond the map's edge (0 within)
        inside_d = self._scene_dist[idx[..., 0], idx[..., 1], idx[..., 2]]
        # from the point to the centre of its cell is ``outside`` (exact); an occupied cube reaches half
        # a cell's diagonal beyond its centre. Beyond the map, the box of all cubes is at least
        # ``outside`` minus that away.
        return np.maximum(inside_d - outside, outside) - 0.5 * np.sqrt(3.0) * v

    def check_all(self, Q: np.ndarray) -> Collision | None:
        """Report of the first colliding row of Q (T, dof), with ``index`` set; None if all are free."""
        Q = self._rows(Q)
        for k, q in enumerate(Q):
            hit = self._check(q)
            if hit is not None:
                return Collision(hit.kind, hit.part, hit.other, hit.q, index=k)
        return None

    def first_collision(self, Q: np.ndarray) -> int | None:
        """Index of the first colliding row of Q (T, dof), or None."""
        hit = self.check_all(Q)
        return None if hit is None else hit.index

    def path_samples(self, Q: np.ndarray, max_joint_step_rad: float = math.radians(1.0),
                     max_tcp_step_m: float | None = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """The configurations ``check_path`` tests on the piecewise-linear joint path Q (T, dof):
        between consecutive ones no joint moves more than ``max_joint_step_rad`` and the camera
        origin travels at most ``max_tcp_step_m`` along the path (None: no TCP bound).

        Coarse paths are densified; dense ones (a trajectory sampled every few ms) are thinned, so
        the number of checks follows the motion, not the sampling rate. The first and last rows of
        Q are always checked; the others are within one bound of a checked sample.
        Returns (samples (S, dof), segment (S,)): sample r lies on Q[segment[r]] -> Q[segment[r]+1].
        """
        Q = self._rows(Q)
        step = _positive(max_joint_step_rad, "max_joint_step_rad")
        tcp = None if max_tcp_step_m is None else _positive(max_tcp_step_m, "max_tcp_step_m")
        if len(Q) == 1:
            return Q.copy(), np.zeros(1, dtype=np.intp)
        # 1. raw steps of at most _RAW of the bounds (linear in joint space)
        X = _densify(_with_param(Q), _RAW * step)
        d = None
        if tcp is not None:
            kin = self.robot.kin
            for _ in range(8):  # the camera is locally linear in q: one or two rounds suffice
                d = np.linalg.norm(np.diff(kin.fk_positions(X[:, :-1], "cam"), axis=0), axis=1)
                if d.max() <= _RAW * tcp:
                    break
                X = _subdivide(X, np.maximum(np.ceil(d / (0.9 * _RAW * tcp)).astype(np.intp), 1))
            else:
                d = np.linalg.norm(np.diff(kin.fk_positions(X[:, :-1], "cam"), axis=0), axis=1)
        Qd, t = X[:, :-1], X[:, -1]
        m = np.abs(np.diff(Qd, axis=0)).max(axis=1) / step  # each raw step, in units of the bounds
        if d is not None:
            m = np.maximum(m, d / tcp)
        # 2. thin: keep a sample where the normalized travel since the start crosses a multiple of
        # (1 - _RAW); between two kept samples every joint and the camera then travel less than
        # (1 - _RAW) bound plus one raw step <= _RAW bound.
        bucket = np.floor(np.cumsum(m) / (1 - _RAW))
        keep = np.ones(len(Qd), dtype=bool)
        keep[1:] = bucket != np.r_[0.0, bucket[:-1]]
        keep[-1] = True
        return Qd[keep], _segment(t[keep], len(Q))

    def check_path(self, Q: np.ndarray, max_joint_step_rad: float = math.radians(1.0),
                   max_tcp_step_m: float | None = 0.01) -> Collision | None:
        """Check the joint path Q (T, dof) at ``path_samples`` in order; the first hit's ``index`` is
        its row in those samples and ``segment`` the row of Q its path segment starts from."""
        Qd, seg = self.path_samples(Q, max_joint_step_rad, max_tcp_step_m)
        for k, q in enumerate(Qd):
            hit = self._check(q)
            if hit is not None:
                return Collision(hit.kind, hit.part, hit.other, hit.q, index=k, segment=int(seg[k]))
        return None

    # ------------------------------------------------------------------ internals

    def _rows(self, Q: np.ndarray) -> np.ndarray:
        Q = np.asarray(Q, dtype=np.float64)
        dof = self.robot.kin.dof
        if Q.ndim != 2 or Q.shape[1] != dof or Q.shape[0] == 0:
            raise ValueError(f"Q must have shape (T, {dof}) with T >= 1, got {Q.shape}")
        if not np.all(np.isfinite(Q)):
            raise ValueError("Q contains NaN or inf")
        return Q

    def _check(self, q: np.ndarray) -> Collision | None:
        robot = self.robot
        P = robot.part_poses(q)
        names = robot.part_names
        # floor: lowest hull vertex of each moving part (exact for convex parts)
        Z = P[:, 2][self._floor_part]  # the z row of each vertex's part pose
        z = np.einsum("vj,vj->v", self._floor_v, Z[:, :3]) + Z[:, 3]
        zmin = np.minimum.reduceat(z, self._floor_start)
        lowest = int(np.argmin(zmin))
        if zmin[lowest] < self.cfg.floor_margin_m:  # name the part that goes deepest
            return Collision("floor", names[self._moving[lowest]], "floor", q.copy())
        # scene and static boxes: world box of each inflated part against theirs, fcl for the overlapping
        if self._scene is not None or self._static:
            Pm = P[self._moving]
            R = Pm[:, :3, :3]
            c = np.einsum("pij,pj->pi", R, self._box_c) + Pm[:, :3, 3]
            h = np.einsum("pij,pj->pi", np.abs(R), self._box_h)
        for name, box, lo, hi in self._static:  # a handful of boxes
            for k in np.flatnonzero(np.all((c + h >= lo) & (c - h <= hi), axis=1)):
                _place(self._inflated[k], Pm[k])
                if fcl.collide(self._inflated[k], box) > 0:
                    return Collision("static", names[self._moving[k]], name, q.copy())
        if self._scene is not None:
            over = np.all((c + h >= self._scene_lo) & (c - h <= self._scene_hi), axis=1)
            for k in np.flatnonzero(over):
                obj = self._inflated[k]
                _place(obj, Pm[k])
                if fcl.collide(obj, self._scene) > 0:
                    return Collision("scene", names[self._moving[k]], "scene", q.copy())
        if self.cfg.self_collision and len(robot.self_pairs):
            hit = robot._pairs_colliding(q, robot.self_pairs, P)
            if hit.any():
                i, j = robot.self_pairs[np.flatnonzero(hit)[0]]
                return Collision("self", names[i], names[j], q.copy())
        return None


__all__ = [
    "Collision",
    "CollisionChecker",
    "CollisionConfig",
    "RobotCollisionModel",
    "StaticBox",
    "TorchShape",
    "densify_joint_path",
    "grid_scene_voxels",
]
