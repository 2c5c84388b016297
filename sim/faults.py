"""Faults injected into the twin, so that the scan's handling of each one can be proven (the table
in docs/RELIABILITY.md). ``FaultsConfig`` is the ``faults:`` section of the twin config; by default
nothing is injected and the twin behaves exactly as without this module.

The camera wrapper damages selected captures (counted from 0 over every ``capture()`` call of one twin,
retries included); the arm wrapper aborts selected motions (counted from 0 over every ``execute()``
call) through the twin arm's own stop path, so the arm really halts part way. ``ik_failure`` moves
the workpiece out of the arm's reach (``place_out_of_reach``): every view then fails the planners' own
reach and IK checks, no planner code knows about faults.

Never imports planners/ or cellctl/.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from drivers.interfaces import (ArmWrapper, DeviceError, Intrinsics, JointTrajectory, RGBDCamera, RGBDFrame,
                                TrajectoryError)

if TYPE_CHECKING:
    from sim.twin import TwinArm, TwinCamera

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)

#: how far ``ik_failure`` moves the workpiece along +x: the Panda reaches about 0.86 m (+ the camera)
OUT_OF_REACH_M = 3.0

Indices = Annotated[list[Annotated[int, Field(ge=0, le=1_000_000)]], Field(max_length=1000)]


class CameraFaults(BaseModel):
    """Damage to selected captures. Indices count every capture() of the twin from 0 (a retry is a
    capture too)."""

    model_config = _STRICT

    drop_frames: Indices = Field(default_factory=list, description="captures that raise DeviceError (no frame "
                                 "arrived), like the RealSense SDK's frame timeout")
    drop_probability: float = Field(0.0, ge=0.0, lt=1.0, description="each capture is also dropped with this "
                                    "probability (seeded by `seed`)")
    disconnect_at: int | None = Field(None, ge=0, le=1_000_000, description="from this capture on every capture "
                                      "raises DeviceError: the camera is gone")
    nan_depth_frames: Indices = Field(default_factory=list, description="captures whose depth is NaN everywhere")
    zero_depth_frames: Indices = Field(default_factory=list, description="captures whose depth is 0 everywhere "
                                       "(the SDK's 'no data')")
    stale_timestamp_frames: Indices = Field(default_factory=list, description="captures that re-deliver the "
                                            "previous frame, timestamp included (>= 1: capture 0 has no previous)")
    noise_sigma_m: float = Field(0.0, ge=0.0, le=10.0, description="Gaussian noise (m, 1 sigma) added to every "
                                 "valid depth pixel of every capture, on top of the D435 model")
    seed: int = Field(0, ge=0, le=2**32 - 1)

    @field_validator("drop_frames", "nan_depth_frames", "zero_depth_frames", "stale_timestamp_frames")
    @classmethod
    def _sorted_unique(cls, v: list[int], info) -> list[int]:
        if info.field_name == "stale_timestamp_frames" and 0 in v:
            raise ValueError("capture 0 has no previous frame to re-deliver; stale frames start at index 1")
        return sorted(set(v))

    @property
    def active(self) -> bool:
        return bool(self.drop_frames or self.drop_probability or self.disconnect_at is not None
                    or self.nan_depth_frames or self.zero_depth_frames or self.stale_timestamp_frames
                    or self.noise_sigma_m)


class ArmFaults(BaseModel):
    """Failures of the arm. Motion indices count every execute() of the twin from 0 (0 is the move to
    the initial view)."""

    model_config = _STRICT

    ik_failure: bool = Field(False, description="every view is unreachable: the workpiece is placed "
                             f"{OUT_OF_REACH_M:g} m further along +x, beyond the arm's reach")
    reflex_on_motion: Indices = Field(default_factory=list, description="motions aborted part way by a reflex "
                                      "(libfranka's joint/cartesian reflex): the arm stops, execute() raises")
    reflex_after_s: float | None = Field(None, gt=0.0, le=600.0, description="time into the motion of the reflex "
                                         "(default: half its duration)")
    stop_on_motion: Indices = Field(default_factory=list, description="motions during which a stop is requested "
                                    "from outside the job (arm.stop(), as a pendant or a safety input would)")
    stop_after_s: float | None = Field(None, gt=0.0, le=600.0, description="time into the motion of the stop "
                                       "(default: half its duration)")

    @field_validator("reflex_on_motion", "stop_on_motion")
    @classmethod
    def _sorted_unique(cls, v: list[int]) -> list[int]:
        return sorted(set(v))

    @property
    def active(self) -> bool:
        """Whether the arm needs the FaultyArm wrapper (ik_failure acts on the scene instead)."""
        return bool(self.reflex_on_motion or self.stop_on_motion)


class FaultsConfig(BaseModel):
    """The twin's ``faults:`` section; empty means no fault."""

    model_config = _STRICT

    camera: CameraFaults = Field(default_factory=CameraFaults)
    arm: ArmFaults = Field(default_factory=ArmFaults)

    @property
    def active(self) -> bool:
        return self.camera.active or self.arm.active or self.arm.ik_failure


class FaultyCamera(RGBDCamera):
    """The twin's camera (``drivers.interfaces.RGBDCamera``) whose selected captures are dropped, emptied,
    stale or drowned in noise. The twin-only helpers below are passed on to the wrapped camera as they
    are (no fault applies to them)."""

    def __init__(self, camera: "TwinCamera", faults: CameraFaults) -> None:
        self._camera = camera
        self._faults = faults
        self.intrinsics: Intrinsics = camera.intrinsics
        self._rng = np.random.default_rng(faults.seed)
        self._last: RGBDFrame | None = None
        self.captures = 0  # capture() calls so far
        self.injected: list[tuple[int, str]] = []  # (capture index, fault) as they happened

    # --- twin only, passed on: hand-eye, benches and tests render through a twin that may have faults
    @property
    def K(self) -> np.ndarray:
        return self._camera.K

    @property
    def last_truth(self) -> np.ndarray | None:
        return self._camera.last_truth

    def capture_at(self, T_base_cam: np.ndarray) -> RGBDFrame:
        return self._camera.capture_at(T_base_cam)

    def render(self, T_base_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._camera.render(T_base_cam)

    def render_truth(self, T_base_cam: np.ndarray | None = None) -> np.ndarray:
        return self._camera.render_truth(T_base_cam)

    def sensor_depth(self, raw: np.ndarray) -> np.ndarray:
        return self._camera.sensor_depth(raw)

    def capture(self) -> RGBDFrame:
        f, i = self._faults, self.captures
        self.captures += 1
        drop = self._rng.random() < f.drop_probability  # drawn every time: the sequence depends only on the seed
        if f.disconnect_at is not None and i >= f.disconnect_at:
            self.injected.append((i, "disconnected"))
            raise DeviceError(f"camera disconnected: no device answers (capture {i}, injected fault)")
        if drop or i in f.drop_frames:
            self.injected.append((i, "dropped"))
            raise DeviceError(f"frame didn't arrive within 5000 ms (capture {i}, injected fault)")
        if i in f.stale_timestamp_frames and self._last is not None:
            self.injected.append((i, "stale"))
            return self._last  # the driver re-served its last buffer: same image, same timestamp
        frame = self._camera.capture()
        depth = frame.depth
        if i in f.nan_depth_frames:
            self.injected.append((i, "nan_depth"))
            depth = np.full_like(depth, np.nan)
        elif i in f.zero_depth_frames:
            self.injected.append((i, "zero_depth"))
            depth = np.zeros_like(depth)
        if f.noise_sigma_m > 0:
            noise = self._rng.normal(0.0, f.noise_sigma_m, depth.shape).astype(np.float32)
            depth = np.where(np.isfinite(depth) & (depth > 0), depth + noise, depth).astype(np.float32)
        if depth is not frame.depth:
            frame = dataclasses.replace(frame, depth=depth)
        self._last = frame
        return frame


class FaultyArm(ArmWrapper):
    """The twin's arm (``drivers.interfaces.Arm``) whose selected motions end part way, by a reflex or by
    a stop request. The abort goes through the wrapped twin arm's own ``stop()`` (called from its
    per-sample hook ``on_sample``), so the arm really halts and holds where it is. The wrapped arm's
    optional abilities are passed on (``ArmWrapper``: the twin's ``ContactLog`` and ``MotionLog``), and so
    are the twin-only members below."""

    _arm: "TwinArm"

    def __init__(self, arm: "TwinArm", faults: ArmFaults) -> None:
        super().__init__(arm)
        self._faults = faults
        self.motions = 0  # execute() calls so far
        self.injected: list[tuple[int, str, float]] = []  # (motion index, fault, time into the motion)

    # --- twin only, passed on: the twin, the scan's devices and tests reach them through a faulty arm
    def reset(self, q) -> None:
        self._arm.reset(q)

    def mirror(self, samples) -> list[dict]:
        return self._arm.mirror(samples)

    @property
    def flange_index(self) -> int:
        return self._arm.flange_index

    def joint_velocities(self):
        return self._arm.joint_velocities()

    def execute(self, trajectory: JointTrajectory) -> float:
        f, i = self._faults, self.motions
        self.motions += 1
        kind = "reflex" if i in f.reflex_on_motion else "stop" if i in f.stop_on_motion else None
        if kind is None:
            return self._arm.execute(trajectory)
        duration = trajectory.duration
        after = f.reflex_after_s if kind == "reflex" else f.stop_after_s
        t_fault = min(after, duration) if after is not None else 0.5 * duration
        fired: list[float] = []

        def on_sample(t: float) -> None:
            if not fired and t >= t_fault:
                fired.append(t)
                self._arm.stop()

        self._arm.on_sample = on_sample
        try:
            return self._arm.execute(trajectory)
        except TrajectoryError as e:
            if not fired:
                raise
            self.injected.append((i, kind, fired[0]))
            if kind == "reflex":
                raise TrajectoryError(f"reflex: motion {i} aborted at t = {fired[0]:.2f} s of {duration:.2f} s "
                                      f"(joint_reflex, injected fault); the arm stopped and holds") from e
            raise TrajectoryError(f"stop requested during motion {i} at t = {fired[0]:.2f} s of {duration:.2f} s; "
                                  f"{e}") from e
        finally:
            self._arm.on_sample = None


def place_out_of_reach(scene, offset_m: float = OUT_OF_REACH_M):
    """The scene moved ``offset_m`` along +x (meshes, drawing, ground truth, view poses): the arm
    reaches none of it. A new Scene; the given one is left as it was."""
    d = np.array([offset_m, 0.0, 0.0])
    views = np.array(scene.initial_view_candidates, dtype=np.float64, copy=True)
    views[:, :3, 3] += d
    pose = None
    if scene.initial_camera_pose is not None:
        pose = np.array(scene.initial_camera_pose, dtype=np.float64, copy=True)
        pose[:3, 3] += d
    return dataclasses.replace(
        scene,
        object_mesh=scene.object_mesh.copy().apply_translation(d),
        paint_mesh=scene.paint_mesh.copy().apply_translation(d),
        drawing_polylines=[np.asarray(p) + d for p in scene.drawing_polylines],
        gt_points=(np.asarray(scene.gt_points) + d).astype(np.asarray(scene.gt_points).dtype),
        extremities=np.asarray(scene.extremities) + d,
        initial_camera_pose=pose,
        initial_view_candidates=views,
    )
