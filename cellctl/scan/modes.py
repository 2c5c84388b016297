"""The cell's device modes, each defined once, as one class: what it drives, the config blocks it needs,
how its arm and camera open, how readiness is checked, one line for the status. The config, the API's
status, the devices, the service and the commissioning tools read ``MODES``; adding a mode is adding
one subclass of ``DeviceMode`` here.

Light to import (the API module reads the names): a mode imports its drivers when it opens them."""

from __future__ import annotations

import ipaddress
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING, ClassVar, Iterator, Literal

if TYPE_CHECKING:
    from pathlib import Path

    from cellctl.config import CellConfig
    from cellctl.scan.devices import Devices, Readiness
    from sim.config import TwinConfig
    from sim.scenes.model import Scene


class DeviceMode:
    """One way to run the cell. ``twin``: the pybullet twin renders the scene (it has ground truth);
    ``twin_arm``: the twin's arm is the arm (load-test jobs and the twin's hand-eye calibration run only
    there); ``probed``: readiness depends on devices outside the process, checked at start and while idle."""

    name: ClassVar[str]
    summary: ClassVar[str]
    twin: ClassVar[bool]
    twin_arm: ClassVar[bool] = False
    probed: ClassVar[bool] = True

    def check(self, cfg: CellConfig) -> None:
        """ValueError naming the config field to fix when ``cfg`` lacks what this mode drives."""

    def describe(self, cfg: CellConfig, arm_host: str | None = None) -> str:
        """One line for the status (at most 200 characters): what drives the arm and the camera."""
        raise NotImplementedError

    def open(self, cfg: CellConfig, scene: Scene, twin_cfg: TwinConfig, *, run_dir: Path | None = None,
             arm_host: str | None = None):
        """A context manager yielding the job's ``Devices``, closed on the way out (also on errors)."""
        raise NotImplementedError

    def readiness(self, cfg: CellConfig, arm_host: str | None = None, *, full: bool = True) -> Readiness:
        """Whether a job could start now; never raises. ``full`` False: the cheap probe the service runs
        while idle (no session with the arm's controller)."""
        raise NotImplementedError

    def twin_config(self, cfg: CellConfig, twin_cfg: TwinConfig) -> TwinConfig:
        """The twin's config for this mode's jobs: as configured, unless the mode says otherwise."""
        return twin_cfg

    def starts_simulator(self, cfg: CellConfig) -> bool:
        """Whether the cell runs the arm's simulator itself (for as long as the service lives)."""
        return False


def _twin_readiness() -> tuple[bool, str]:
    from cellctl.scan.devices import module_available

    ok = module_available("pybullet")
    return ok, "pybullet twin" if ok else "pybullet is not installed (pip install -e .)"


def _arm_readiness(cfg: CellConfig, arm_host: str | None, full: bool) -> tuple[bool, str]:
    from drivers.panda import probe

    arm_cfg = cfg.arm.model_copy(update={"host": arm_host}) if arm_host else cfg.arm
    try:
        st = probe(arm_cfg, full=full)
        return st.ready, st.message
    except Exception as e:  # noqa: BLE001 - probe() reports DeviceErrors; anything else is still "not ready"
        return False, f"probing the arm failed: {type(e).__name__}: {e}"


def _needs_arm(cfg: CellConfig, example: str) -> None:
    if cfg.arm is None:
        raise ValueError(f"arm: mode {cfg.mode} needs an `arm:` block (drivers.panda FrankaConfig: host, model, "
                         f"hand_eye, ...; see configs/{example})")


class SimMode(DeviceMode):
    name = "sim"
    summary = "the pybullet twin"
    twin, twin_arm, probed = True, True, False

    def describe(self, cfg, arm_host=None) -> str:
        return "pybullet twin (arm and D435), built per job"

    @contextmanager
    def open(self, cfg, scene, twin_cfg, *, run_dir=None, arm_host=None) -> Iterator[Devices]:
        from cellctl.scan.devices import Devices
        from sim.twin import Twin

        with Twin(scene, twin_cfg) as twin:
            twin.arm.reset(twin_cfg.home_q)
            yield Devices(self.name, twin.arm, twin.camera, twin.scene, twin, self.describe(cfg))

    def readiness(self, cfg, arm_host=None, *, full=True) -> Readiness:
        from cellctl.scan.devices import Readiness

        ok, msg = _twin_readiness()
        return Readiness(ok, ok, msg, msg)


class FciSimMode(DeviceMode):
    """The franky adapter (``drivers.panda.FrankaArm``) on franky-sim (a MuJoCo FR3 behind libfranka's
    protocol; embedded = a child process the cell starts, or one already running at ``arm.host``), and the
    twin's renderer, whose robot is set to the franky arm's *measured* joints before every capture
    (``devices.MirroredCamera``); after every motion the twin replays them against the scene
    (``devices.TwinCheckedArm``). The scene (objects, ground truth, initial views) is the twin's."""

    name = "fcisim"
    summary = "the Franka adapter on franky-sim, the twin's camera"
    twin = True

    def check(self, cfg) -> None:
        _needs_arm(cfg, "cell.fcisim.yaml")
        arm = cfg.arm
        if arm.model != "fr3":
            raise ValueError(f"arm.model: franky-sim simulates an FR3 (robot server version 10); mode fcisim "
                             f"needs arm.model: fr3, got {arm.model!r}")
        if arm.realtime:
            raise ValueError("arm.realtime: must be false in mode fcisim (franky-sim is no real-time "
                             "controller, and libfranka would take a core at real-time priority)")
        if cfg.fcisim.simulator == "embedded" and not _is_loopback(arm.host):
            raise ValueError(f"arm.host: with fcisim.simulator embedded the simulator binds a loopback address "
                             f"(the first free one from arm.host on); got {arm.host!r}, use e.g. 127.0.0.1")

    def describe(self, cfg, arm_host=None) -> str:
        where = "embedded" if cfg.fcisim.simulator == "embedded" else "external"
        return (f"franky {cfg.arm.model} on franky-sim ({where}, {arm_host or cfg.arm.host}); camera: twin "
                f"renderer posed from the arm")[:200]

    def twin_config(self, cfg, twin_cfg: TwinConfig) -> TwinConfig:
        """The twin renders with the arm's hand-eye: the camera_pose() the scan plans with (the arm's FK +
        arm.hand_eye) and the pose the twin renders from must be one."""
        from sim.config import HandEyeConfig

        return twin_cfg.model_copy(update={"hand_eye": HandEyeConfig(**cfg.arm.hand_eye.model_dump())})

    @contextmanager
    def open(self, cfg, scene, twin_cfg, *, run_dir=None, arm_host=None) -> Iterator[Devices]:
        from cellctl.scan.devices import Devices, MirroredCamera, TwinCheckedArm
        from drivers.panda import FrankaArm
        from sim.twin import Twin

        with ExitStack() as stack:
            host = arm_host
            if host is None and self.starts_simulator(cfg):
                from cellctl.scan.fcisim import FrankySim

                host = stack.enter_context(FrankySim(cfg.arm.host, twin_cfg.home_q, cfg.fcisim.start_timeout_s)).host
            arm_cfg = cfg.arm.model_copy(update={"host": host or cfg.arm.host})
            twin = stack.enter_context(Twin(scene, self.twin_config(cfg, twin_cfg)))
            franky = stack.enter_context(FrankaArm(arm_cfg))
            camera = MirroredCamera(twin.camera, twin.arm, franky)
            camera.sync()
            yield Devices(self.name, TwinCheckedArm(franky, twin.arm), camera, twin.scene, twin,
                          self.describe(cfg, arm_cfg.host))

    def readiness(self, cfg, arm_host=None, *, full=True) -> Readiness:
        from cellctl.scan.devices import Readiness

        arm_ok, arm_msg = _arm_readiness(cfg, arm_host, full)
        twin_ok, twin_msg = _twin_readiness()
        return Readiness(arm_ok, twin_ok, arm_msg, "twin renderer posed from the arm" if twin_ok else twin_msg)

    def starts_simulator(self, cfg) -> bool:
        return cfg.fcisim.simulator == "embedded"


class RealMode(DeviceMode):
    """``drivers.panda.FrankaArm`` and the live D435 (``drivers.realsense``); the scene file gives the
    initial view candidates and the expected drawing."""

    name = "real"
    summary = "the Franka and the D435"
    twin = False

    def check(self, cfg) -> None:
        _needs_arm(cfg, "cell.real.yaml")
        if cfg.camera is None:
            raise ValueError("camera: mode real needs a `camera:` block (drivers.realsense RealSenseConfig: serial, "
                             "modes, ...; see configs/cell.real.yaml)")
        if cfg.camera.bag is not None:
            raise ValueError(f"camera.bag: a real cell streams the live D435 while the arm moves; {cfg.camera.bag} "
                             f"can only be replayed offline (drivers.realsense.RealSenseBag)")

    def describe(self, cfg, arm_host=None) -> str:
        cam = cfg.camera
        return (f"franky {cfg.arm.model} at {arm_host or cfg.arm.host}; RealSense D435 {cam.serial or '(first found)'} "
                f"{cam.color_width}x{cam.color_height}@{cam.fps}")[:200]

    @contextmanager
    def open(self, cfg, scene, twin_cfg, *, run_dir=None, arm_host=None) -> Iterator[Devices]:
        from pathlib import Path

        from cellctl.scan.devices import Devices
        from drivers.panda import FrankaArm
        from drivers.realsense import open_camera

        with ExitStack() as stack:
            franky = stack.enter_context(FrankaArm(cfg.arm))
            rec = {}
            if cfg.camera.keep_view_bags and run_dir is not None:
                rec = {"record_to": Path(run_dir) / "views.bag", "record": "views"}
            camera = stack.enter_context(open_camera(cfg.camera, **rec))
            yield Devices(self.name, franky, camera, scene, None, self.describe(cfg))

    def readiness(self, cfg, arm_host=None, *, full=True) -> Readiness:
        from cellctl.scan.devices import Readiness, camera_readiness

        arm_ok, arm_msg = _arm_readiness(cfg, arm_host, full)
        cam_ok, cam_msg = camera_readiness(cfg.camera)
        return Readiness(arm_ok, cam_ok, arm_msg, cam_msg)


MODES: dict[str, DeviceMode] = {cls.name: cls() for cls in DeviceMode.__subclasses__()}  # in the order above
ModeName = Literal[tuple(MODES)]  # the config's and the status's field type


def modes_help() -> str:
    """'sim: ...; fcisim: ...; real: ...' for the config's and the API's docs."""
    return "; ".join(f"{m.name}: {m.summary}" for m in MODES.values())


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback and ipaddress.ip_address(host).version == 4
    except ValueError:
        return False
