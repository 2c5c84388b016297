"""User scenes: a YAML file naming a mesh, its pose and the drawing on it (format: docs/SCENES.md).

Every problem, from bad YAML to a drawing off the surface, raises `SceneError` with the file and
the field path, so a user can fix the file without reading a traceback.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import numpy as np
import trimesh
from pydantic import AllowInfNan, BaseModel, ConfigDict, Field, Strict, model_validator
from scipy.spatial.transform import Rotation

from configs.loading import load_yaml_model
from sim.appearance import Appearance
from sim.scenes.catalog import Blueprint, assemble_scene
from sim.scenes.model import Scene
from sim.scenes.paint import closest_points, resample_polyline
from sim.scenes.views import look_at

MESH_SUFFIXES = (".obj", ".stl", ".ply")
MAX_OFF_SURFACE = 0.05  # m: a drawing point farther than this from the mesh is a mistake
MAX_EXTENT = 5.0  # m: anything larger is probably in millimetres


class SceneError(ValueError):
    """An invalid scene: the message names the file and the field."""


Num = Annotated[float, Strict(), AllowInfNan(False)]  # a finite int or float; no "1.0" strings, no booleans
Vec3 = tuple[Num, Num, Num]
Unit = Annotated[Num, Field(ge=0.0, le=1.0)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class PoseSpec(_Strict):
    xyz: Vec3 = (0.0, 0.0, 0.0)  # m, base frame
    rpy_deg: Vec3 = (0.0, 0.0, 0.0)  # fixed-axis roll about x, pitch about y, yaw about z


class DrawingSpec(_Strict):
    width: Annotated[Num, Field(ge=0.005, le=0.05)]
    polylines: Annotated[list[Annotated[list[Vec3], Field(min_length=2)]], Field(min_length=1)]
    # paint only where the line lies within this of the surface (a line drawn across a basket's gaps)
    max_offset: Annotated[Num, Field(gt=0.0, le=MAX_OFF_SURFACE)] | None = None


class CameraSpec(_Strict):
    eye: Vec3  # base frame
    target: Vec3

    @model_validator(mode="after")
    def _apart(self):
        if math.dist(self.eye, self.target) < 0.05:
            raise ValueError("eye and target must be at least 0.05 m apart")
        return self


class ColorsSpec(_Strict):
    object: tuple[Unit, Unit, Unit] | None = None
    paint: tuple[Unit, Unit, Unit] | None = None


class AppearanceSpec(_Strict):
    """The twin's finish, paint and light by name (sim.appearance: FINISHES, PAINTS, LIGHTS)."""

    finish: str = "grey_steel"
    paint: str = "red"
    light: str = "normal"
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0

    @model_validator(mode="after")
    def _known(self) -> "AppearanceSpec":
        Appearance(self.finish, self.paint, self.light, self.seed)  # ValueError names the unknown one
        return self


class SceneSpec(_Strict):
    name: Annotated[str, Field(min_length=1)]
    mesh: Annotated[str, Field(min_length=1)]  # relative to the YAML file
    pose: PoseSpec = PoseSpec()
    drawing: DrawingSpec
    initial_camera: CameraSpec | None = None
    colors: ColorsSpec | None = None
    appearance: AppearanceSpec | None = None  # textured metal, paint and light; replaces `colors` in the render

    @model_validator(mode="after")
    def _one_look(self) -> "SceneSpec":
        if self.colors is not None and self.appearance is not None:
            raise ValueError("give `colors` (flat colours) or `appearance` (finish, paint, light), not both")
        return self


def pose_matrix(pose: PoseSpec) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", pose.rpy_deg, degrees=True).as_matrix()
    T[:3, 3] = pose.xyz
    return T


def read_scene_spec(path: str | Path) -> SceneSpec:
    """Parse and validate the YAML alone (no mesh loading)."""
    return load_yaml_model(path, SceneSpec, SceneError, "scene")


def _load_mesh(path: str | Path, spec: SceneSpec) -> trimesh.Trimesh:
    mesh_path = (Path(path).parent / spec.mesh).resolve()
    if mesh_path.suffix.lower() not in MESH_SUFFIXES:
        raise SceneError(f"{path}: mesh: unsupported format {mesh_path.suffix!r}; "
                         f"use one of {', '.join(MESH_SUFFIXES)}")
    if not mesh_path.is_file():
        raise SceneError(f"{path}: mesh: file not found: {mesh_path}")
    try:
        mesh = trimesh.load(mesh_path, force="mesh", process=True)
    except Exception as exc:  # noqa: BLE001 - any loader failure is the file's fault
        raise SceneError(f"{path}: mesh: cannot load {mesh_path}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SceneError(f"{path}: mesh: {mesh_path} has no triangles")
    if not np.isfinite(mesh.vertices).all():
        raise SceneError(f"{path}: mesh: {mesh_path} has non-finite vertex coordinates")
    mesh.fix_normals()  # consistent outward winding: paint only goes on the side facing the line
    extent = float(np.max(mesh.extents))
    if extent > MAX_EXTENT:
        raise SceneError(f"{path}: mesh: {mesh_path} is {extent:g} units across; meshes must be in metres")
    return mesh


def load_scene_file(path: str | Path) -> Scene:
    """Build a `Scene` from a YAML scene file; SceneError names the file and the field."""
    spec = read_scene_spec(path)
    mesh = _load_mesh(path, spec)
    polylines = [np.asarray(p, dtype=np.float64) for p in spec.drawing.polylines]
    for i, line in enumerate(polylines):
        d = closest_points(mesh, line)[1]
        if d.max() > MAX_OFF_SURFACE:
            j = int(np.argmax(d))
            raise SceneError(f"{path}: drawing.polylines[{i}][{j}]: point {line[j].tolist()} is {d[j]:.3f} m "
                             f"from the mesh surface (at most {MAX_OFF_SURFACE} m; object frame, metres)")
        dense = [resample_polyline(line[j:j + 2], 0.005) for j in range(len(line) - 1)]
        seg = np.repeat(np.arange(len(dense)), [len(q) for q in dense])
        far = closest_points(mesh, np.vstack(dense))[1] > MAX_OFF_SURFACE
        if far.any():
            j = int(seg[np.argmax(far)])
            raise SceneError(f"{path}: drawing.polylines[{i}][{j}:{j + 2}]: the segment leaves the surface by more "
                             f"than {MAX_OFF_SURFACE} m between its points; add points along the surface")
        if np.linalg.norm(np.diff(line, axis=0), axis=1).sum() < spec.drawing.width:
            raise SceneError(f"{path}: drawing.polylines[{i}]: shorter than the line width")
    camera = None
    if spec.initial_camera is not None:
        camera = look_at(spec.initial_camera.eye, spec.initial_camera.target)
    colors = spec.colors or ColorsSpec()
    bp = Blueprint(mesh, polylines, spec.drawing.width, pose_matrix(spec.pose), None,
                   max_offset=spec.drawing.max_offset)
    try:
        scene = assemble_scene(spec.name, bp, object_rgb=colors.object, paint_rgb=colors.paint,
                               initial_camera_pose=camera)
    except ValueError as exc:
        raise SceneError(f"{path}: drawing: {exc}") from None
    if spec.appearance is not None:
        a = spec.appearance
        scene.appearance = Appearance(a.finish, a.paint, a.light, a.seed)
    return scene
