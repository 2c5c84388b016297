"""The arm and the camera a scan job drives (behind ``drivers.interfaces.Arm`` / ``RGBDCamera``), opened
as the cell's mode says (cellctl.scan.modes: sim, fcisim, real), and whether they are ready; the
wrappers fcisim drives through: the twin's camera posed from the franky arm's *measured* joints (the
picture, the robot in it, which the scan's self-filter removes, and the scene are where the arm really
is), and the twin's contact check of every motion the arm made."""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path
from typing import ContextManager

import numpy as np

from cellctl.config import CellConfig
from cellctl.scan.modes import MODES
from drivers.interfaces import (Arm, ArmWrapper, ContactLog, DeviceError, JointTrajectory, MotionCounter, MotionLog,
                                RGBDCamera, RGBDFrame)
from sim.config import TwinConfig
from sim.scenes.model import Scene

MIRROR_STEP_RAD = 0.01  # replaying a measured motion in the twin: joint step between contact checks


@dataclass
class Devices:
    """What one job drives. ``twin`` is None in mode real; ``scene`` is the scene as placed in the twin
    (a fault may move it) or, in mode real, as loaded."""

    mode: str
    arm: Arm
    camera: RGBDCamera
    scene: Scene
    twin: object | None
    description: str


def open_devices(cfg: CellConfig, scene: Scene, twin_cfg: TwinConfig, *, run_dir: Path | None = None,
                 arm_host: str | None = None) -> ContextManager[Devices]:
    """The cell's arm and camera for one job, closed on the way out (also on errors), as its mode opens
    them (cellctl.scan.modes). ``arm_host``: fcisim, a franky-sim already running there (the service's
    own) instead of the config's choice. ``run_dir``: real, where a camera with ``keep_view_bags``
    records ``views.bag``. DeviceError with the adapter's explanation when a device cannot be opened."""
    return MODES[cfg.mode].open(cfg, scene, twin_cfg, run_dir=run_dir, arm_host=arm_host)


class MirroredCamera(RGBDCamera):
    """The twin's D435 rendering from wherever the real (or franky-sim) arm measures it is: the twin's
    robot is set to the arm's joints before each capture (implements ``RGBDCamera``). Of the twin
    camera's own extras it passes on ``last_truth`` and ``render_truth``."""

    def __init__(self, twin_camera, twin_arm, arm: Arm) -> None:
        self._camera, self._twin_arm, self._arm = twin_camera, twin_arm, arm
        self.intrinsics = twin_camera.intrinsics
        self._lock = threading.Lock()

    def sync(self) -> np.ndarray:
        """Pose the twin's robot at the arm's measured joints; returns them."""
        q = self._arm.joint_positions()
        self._twin_arm.mirror(q)
        return q

    def capture(self) -> RGBDFrame:
        with self._lock:
            self.sync()
            return self._camera.capture()

    @property
    def last_truth(self) -> np.ndarray | None:
        """The noise-free depth of the last capture (the twin camera's)."""
        return self._camera.last_truth

    def render_truth(self, T_base_cam: np.ndarray | None = None) -> np.ndarray:
        """Noise-free depth at ``T_base_cam`` (default: the twin robot's camera pose, the arm's as of the
        last capture or motion)."""
        return self._camera.render_truth(T_base_cam)


class TwinCheckedArm(ArmWrapper, ContactLog):
    """The franky arm, plus the twin's own contact check of what it did: after each ``execute()`` the
    measured joints are replayed on the twin's robot against the scene (``last_motion_contacts``, as
    the twin reports for its own motions), and the twin's robot is left where the arm is. The franky
    arm's optional abilities are passed on (``ArmWrapper``: ``Recoverable``, ``EventLog``, ``MotionLog``,
    ``MotionCounter``). The wrapped arm must count and log its motions (TypeError otherwise)."""

    def __init__(self, arm: Arm, twin_arm) -> None:
        if not (isinstance(arm, MotionCounter) and isinstance(arm, MotionLog)):
            raise TypeError(f"TwinCheckedArm replays the motions the arm measured: {type(arm).__name__} is not "
                            f"both a MotionCounter and a MotionLog")
        super().__init__(arm)
        self._measured: MotionLog = arm
        self._count: MotionCounter = arm
        self._twin_arm = twin_arm
        self.last_motion_contacts: list[dict] = []

    def execute(self, trajectory: JointTrajectory) -> float:
        self.last_motion_contacts = []
        sent = self._count.motions_sent
        try:
            return self._arm.execute(trajectory)
        finally:
            if self._count.motions_sent != sent:  # something moved (refusals move nothing)
                self._replay()

    def _replay(self) -> None:
        try:
            Q = np.asarray(self._measured.last_motion_actual, dtype=np.float64).reshape(-1, 7)
            Q = np.vstack([Q, self._arm.joint_positions()])
            keep = [0]
            for k in range(1, len(Q)):  # samples MIRROR_STEP_RAD apart, and the last
                if np.max(np.abs(Q[k] - Q[keep[-1]])) >= MIRROR_STEP_RAD:
                    keep.append(k)
            if keep[-1] != len(Q) - 1:
                keep.append(len(Q) - 1)
            self.last_motion_contacts = list(self._twin_arm.mirror(Q[keep]))
        except (DeviceError, ValueError):  # the arm's own error is what the caller must see
            pass


# --- readiness ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Readiness:
    """Whether a job could start now, and if not, why (for the status and the submit refusal)."""

    arm_ready: bool
    camera_ready: bool
    arm: str
    camera: str

    @property
    def ready(self) -> bool:
        return self.arm_ready and self.camera_ready

    @property
    def reason(self) -> str | None:
        if self.ready:
            return None
        parts = ([f"arm: {self.arm}"] if not self.arm_ready else []) + \
                ([f"camera: {self.camera}"] if not self.camera_ready else [])
        return "; ".join(parts)


def module_available(name: str) -> bool:
    """Whether ``name`` can be imported, without importing it. A job thread that is importing it
    right now has put it in sys.modules without a spec yet, and find_spec then raises ValueError:
    a status query at that moment answered internal_error (seen in the load test on a busy machine)."""
    if name in sys.modules:
        return True
    try:
        return find_spec(name) is not None
    except ValueError:  # the import began between the two lines above
        return name in sys.modules


def check_readiness(cfg: CellConfig, arm_host: str | None = None, *, full: bool = True) -> Readiness:
    """Never raises. sim: pybullet is there. fcisim: the franky-sim robot answers (``drivers.panda.probe``:
    ``full`` connects once through libfranka, else only its handshake) and the twin can render. real: the
    Franka answers and the configured D435 is connected with its modes (``drivers.realsense.check_devices``).
    Takes up to ``arm.connect_timeout_s`` twice (TCP connect, then the handshake) for an unreachable robot."""
    return MODES[cfg.mode].readiness(cfg, arm_host, full=full)


def camera_readiness(camera_cfg) -> tuple[bool, str]:
    """(ready, message) of the configured D435; never raises (a broken Open3D/libusb install is a reason)."""
    try:
        from drivers.realsense import check_devices, list_devices

        devices = list_devices()
        problems = check_devices(camera_cfg, devices)
    except Exception as e:  # noqa: BLE001 - e.g. libusb missing: Open3D does not load
        return False, f"cannot enumerate RealSense devices: {type(e).__name__}: {e}"
    if problems:
        return False, "; ".join(problems)
    chosen = next((d for d in devices if d.serial == camera_cfg.serial), devices[0])
    return True, f"{chosen.name} {chosen.serial}"
