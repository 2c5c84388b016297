"""A whole scan job recorded into its folder and run again from it, through the real drivers' code path.

Recording (``JobSpec.record``) wraps the job's devices: every frame the job captures goes into
``capture.bag`` (a RealSense .bag, written by ``drivers.realsense.bag_writer``) and every position the arm
reached into ``capture_arm.jsonl`` (its joints and camera pose, with each motion's planned end), with the
arm's model in the first line; each position and each capture there carries its wall-clock time, and each
capture the camera's own timestamp (the bag's clock only orders the frames). The job is handed each frame as the bag will give it back (depth in the
bag's units, as a real D435 delivers it), so a replay sees exactly what the recorded job saw.

Replaying (``cellctl replay <job folder>``) opens ``capture.bag`` with ``drivers.realsense.RealSenseBag``
(the camera a real cell plays bags with) and a ``ReplayArm`` that serves the recorded positions, and runs
the same scan job: each motion the planner sends takes the arm to the next recorded position. Where the
planner now plans a different motion than the recorded one, the arm still goes where the recording went,
and the replay counts it (``ReplayArm.diverged``)."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellctl.scan.devices import Devices
from drivers.interfaces import (Arm, ArmModel, ArmWrapper, DeviceError, JointTrajectory, RGBDCamera, RGBDFrame,
                                TrajectoryError)
from drivers.realsense.bag_format import DEPTH_UNIT_M
from drivers.realsense.bag_writer import BagWriter, depth_to_units
from drivers.realsense.frames import depth_to_metres

BAG = "capture.bag"
ARM_LOG = "capture_arm.jsonl"
SCHEMA = 1
PLAN_TOL_RAD = 1e-6  # a replayed motion whose planned end is further than this from the recorded one diverged


def _model_dict(m: ArmModel) -> dict:
    return {"urdf_path": m.urdf_path, "base_link": m.base_link, "flange_link": m.flange_link,
            "joint_names": list(m.joint_names),
            **{k: np.asarray(getattr(m, k)).tolist() for k in ("lower", "upper", "max_velocity", "max_acceleration",
                                                               "max_jerk", "T_flange_cam")}}


def _model(d: dict) -> ArmModel:
    arrays = {k: np.asarray(d[k], dtype=np.float64) for k in ("lower", "upper", "max_velocity", "max_acceleration",
                                                              "max_jerk", "T_flange_cam")}
    return ArmModel(urdf_path=d["urdf_path"], base_link=d["base_link"], flange_link=d["flange_link"],
                    joint_names=tuple(d["joint_names"]), **arrays)


class RecordingCamera(RGBDCamera):
    """Passes the job's camera on, writing each frame to the bag and handing back the frame as the bag will
    play it (depth rounded to the bag's depth unit)."""

    def __init__(self, camera: RGBDCamera, writer: BagWriter, log) -> None:
        self._camera, self._writer, self._log = camera, writer, log
        self.intrinsics = camera.intrinsics
        # what RealSenseBag computes from the bag's depth unit (float32 in the bag's metadata)
        self._scale = float(1.0 / np.float32(writer.depth_unit_m))

    def capture(self) -> RGBDFrame:
        frame = self._camera.capture()
        depth = depth_to_metres(depth_to_units(frame.depth, self._writer.depth_unit_m).astype(np.uint16), self._scale)
        played = RGBDFrame(frame.color, depth, frame.intrinsics, frame.timestamp)
        self._writer.add(played)
        self._log.write(json.dumps({"capture": self._writer.frames, "timestamp": frame.timestamp,
                                    "wall": time.time()}) + "\n")
        self._log.flush()
        return played


class RecordingArm(ArmWrapper):
    """Passes the job's arm on (and its abilities), logging where it starts and every position a motion
    leaves it at: joints, camera pose, and the motion's planned end."""

    def __init__(self, arm: Arm, log) -> None:
        super().__init__(arm)
        self._log = log
        self._write({"schema_version": SCHEMA, "model": _model_dict(arm.model)})
        self._position(None, None)

    def _write(self, entry: dict) -> None:
        self._log.write(json.dumps(entry) + "\n")
        self._log.flush()

    def _position(self, planned_end, error: str | None) -> None:
        self._write({"q": self._arm.joint_positions().tolist(), "T_base_cam": self._arm.camera_pose().tolist(),
                     "planned_end": None if planned_end is None else np.asarray(planned_end).tolist(),
                     "error": error, "wall": time.time()})

    def execute(self, trajectory: JointTrajectory) -> float:
        end = np.asarray(trajectory.positions)[-1]
        try:
            duration = self._arm.execute(trajectory)
        except (TrajectoryError, DeviceError) as e:
            self._position(end, f"{type(e).__name__}: {e}")
            raise
        self._position(end, None)
        return duration


@dataclass
class _Position:
    q: np.ndarray
    T_base_cam: np.ndarray
    planned_end: np.ndarray | None
    error: str | None


class ReplayArm(Arm):
    """The recorded arm: starts where the recording started; each ``execute`` goes to the next recorded
    position (or fails as the recorded motion failed). A motion whose planned end differs from the recorded
    one counts in ``diverged``; a motion past the recording's end is a DeviceError."""

    def __init__(self, path: Path) -> None:
        lines = [json.loads(s) for s in Path(path).read_text().splitlines() if s.strip()]
        if not lines or lines[0].get("schema_version") != SCHEMA:
            raise DeviceError(f"{path}: not a job's arm recording (schema_version {SCHEMA} expected)")
        self.model = _model(lines[0]["model"])
        self._positions = [_Position(np.asarray(p["q"], dtype=np.float64), np.asarray(p["T_base_cam"], dtype=np.float64),
                                     None if p["planned_end"] is None else np.asarray(p["planned_end"]), p["error"])
                           for p in lines[1:] if "q" in p]  # the captures' lines only time the frames
        if not self._positions:
            raise DeviceError(f"{path}: the recording has no arm position")
        self._at = 0
        self.diverged = 0  # motions planned otherwise than recorded

    @property
    def motions_left(self) -> int:
        return len(self._positions) - 1 - self._at

    def joint_positions(self) -> np.ndarray:
        return self._positions[self._at].q.copy()

    def camera_pose(self) -> np.ndarray:
        return self._positions[self._at].T_base_cam.copy()

    def stop(self) -> None:
        pass

    def execute(self, trajectory: JointTrajectory) -> float:
        if self.motions_left <= 0:
            raise DeviceError(f"the recording ends after {len(self._positions) - 1} motions; the replayed job asks "
                              f"for one more")
        self._at += 1
        p = self._positions[self._at]
        end = np.asarray(trajectory.positions)[-1]
        if p.planned_end is None or np.max(np.abs(end - p.planned_end)) > PLAN_TOL_RAD:
            self.diverged += 1
        if p.error is not None:
            raise TrajectoryError(f"as recorded: {p.error}")
        return float(trajectory.times[-1])


@contextlib.contextmanager
def recording(dev: Devices, run_dir: Path) -> Iterator[Devices]:
    """``dev`` with its arm and camera recorded into ``run_dir``."""
    run_dir = Path(run_dir)
    with open(run_dir / ARM_LOG, "w") as log, BagWriter(run_dir / BAG, dev.camera.intrinsics,
                                                        depth_unit_m=DEPTH_UNIT_M) as writer:
        yield Devices(dev.mode, RecordingArm(dev.arm, log), RecordingCamera(dev.camera, writer, log), dev.scene, dev.twin,
                      dev.description + "; recorded")


@contextlib.contextmanager
def replay_devices(folder: Path, scene) -> Iterator[Devices]:
    """The devices of a recorded job: its bag through the RealSense bag player, its arm positions."""
    from drivers.realsense import RealSenseBag

    folder = Path(folder)
    for name in (BAG, ARM_LOG):
        if not (folder / name).is_file():
            raise DeviceError(f"{folder} has no {name}: was the job recorded (cellctl scan --record)?")
    arm = ReplayArm(folder / ARM_LOG)
    with RealSenseBag(folder / BAG) as camera:
        yield Devices("replay", arm, camera, scene, None, f"replay of {folder}")


def drawing_distance_mm(a: Path, b: Path) -> tuple[float, float] | None:
    """Median and 99th percentile (mm) of the distance from each point of drawing cloud ``b`` to ``a``'s
    nearest (None when either is missing or empty)."""
    import trimesh
    from scipy.spatial import cKDTree

    if not (a.is_file() and b.is_file()):
        return None
    pa, pb = (np.asarray(trimesh.load(p, file_type="ply").vertices) for p in (a, b))
    if not len(pa) or not len(pb):
        return None
    d, _ = cKDTree(pa).query(pb)
    return float(np.median(d) * 1000), float(np.percentile(d, 99) * 1000)


def compare(recorded: Path, replayed: Path) -> dict:
    """The recorded job beside its replay: views, coverage, the drawing's points and their distance."""
    a = json.loads((Path(recorded) / "result.json").read_text())
    b = json.loads((Path(replayed) / "result.json").read_text())
    out = {k: (a.get(k), b.get(k)) for k in ("steps", "coverage_percent", "terminated_by", "error")}
    out["drawing_points"] = tuple(r["records"][-1]["drawing_points"] if r.get("records") else None for r in (a, b))
    out["drawing_distance_mm"] = drawing_distance_mm(Path(recorded) / "drawing.ply", Path(replayed) / "drawing.ply")
    return out
