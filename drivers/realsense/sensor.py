"""The live Intel RealSense D435 as an ``RGBDCamera``, through Open3D's built-in RealSense support
(``open3d.t.io.RealSenseSensor``; the customer forbids pyrealsense2).

Streams colour and depth at one rate, depth aligned to colour by librealsense; intrinsics and depth
scale are the device's own (``get_metadata()``). Every call that could block on the device is
bounded: opening in a worker thread, frames by polling (``capture_frame(wait=False)``) until
``frame_timeout_s``. Optionally records a ``.bag`` through the same sensor, either everything it
streams or only the frames ``capture()`` returns (the views of a scan)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from drivers.interfaces import DeviceError, Intrinsics, RGBDCamera, RGBDFrame
from drivers.realsense.config import RealSenseConfig
from drivers.realsense.frames import (call_with_timeout, check_color_format, clean_error, depth_scale_from_metadata,
                                      intrinsics_from_metadata, to_rgbd_frame)

OPEN_TIMEOUT_S = 10.0
POLL_S = 0.002

NO_DEVICE_HELP = (
    "no RealSense device found. Check: the D435 is plugged into a USB3 port (blue or marked SS) with a "
    "USB3 cable, straight or through a powered hub; the udev rules are installed "
    "(99-realsense-libusb.rules in /etc/udev/rules.d, then `sudo udevadm control --reload-rules && "
    "sudo udevadm trigger` and replug) so libusb may open it without root; no other program "
    "(realsense-viewer, another cellctl) holds the camera; `lsusb` lists 8086:0b07. See docs/HARDWARE.md.")


@dataclass(frozen=True)
class DeviceInfo:
    """One connected RealSense and the modes it offers (Open3D's ``enumerate_devices``)."""

    name: str
    serial: str
    valid_configs: dict[str, list[str]] = field(default_factory=dict)


def list_devices() -> list[DeviceInfo]:
    """Connected RealSense cameras, [] when there is none. Quick (about 0.1 s), never raises for a
    missing camera; ``cellctl doctor`` prints it."""
    import open3d.t.io as o3dio

    return [DeviceInfo(name=str(d.name), serial=str(d.serial),
                       valid_configs={k: sorted(v) for k, v in dict(d.valid_configs).items()})
            for d in o3dio.RealSenseSensor.enumerate_devices()]


def check_devices(config: RealSenseConfig, devices: list[DeviceInfo] | None = None) -> list[str]:
    """Problems that would stop ``RealSenseCamera(config)`` from opening, in words ([] = fine): no
    camera, not the configured serial, a mode the camera does not list. For ``cellctl doctor``."""
    devices = list_devices() if devices is None else devices
    if not devices:
        return [NO_DEVICE_HELP]
    if config.serial:
        chosen = [d for d in devices if d.serial == config.serial]
        if not chosen:
            return [f"no RealSense with serial {config.serial}; connected: "
                    f"{', '.join(f'{d.name} {d.serial}' for d in devices)}"]
    else:
        chosen = devices[:1]
    dev, want, problems = chosen[0], config.open3d_config(), []
    for key, value in (("color_resolution", want["color_resolution"]), ("depth_resolution", want["depth_resolution"]),
                       ("color_format", want["color_format"]), ("depth_format", want["depth_format"]),
                       ("color_fps", want["fps"]), ("depth_fps", want["fps"])):
        offered = dev.valid_configs.get(key)
        if offered and value not in offered:
            problems.append(f"{dev.name} {dev.serial} does not offer {key} {value}; it offers {', '.join(offered)}")
    return problems


class RealSenseCamera(RGBDCamera):
    """A live D435 (implements ``drivers.interfaces.RGBDCamera``); a context manager.

    ``record_to``: write a ``.bag`` through the same sensor (``config.record_bag`` when None).
    ``record``: "all" records everything streamed from start to close; "views" records only around
    each ``capture()``, so a scan job keeps the bag of its views and not the travel in between.
    Raises DeviceError at once when no camera is connected (the message says what to check)."""

    def __init__(self, config: RealSenseConfig, *, record_to: str | os.PathLike | None = None,
                 record: Literal["all", "views"] = "all", open_timeout_s: float = OPEN_TIMEOUT_S) -> None:
        import open3d.t.io as o3dio

        if record not in ("all", "views"):
            raise ValueError(f"record must be 'all' or 'views', got {record!r}")
        if config.bag is not None:
            raise DeviceError(f"camera config names a bag ({config.bag}): play it with RealSenseBag, not the live camera")
        self.config = config
        problems = check_devices(config)
        if problems:
            raise DeviceError("; ".join(problems))
        record_to = record_to if record_to is not None else config.record_bag
        self.record_path = Path(record_to) if record_to is not None else None
        self.record_mode = record
        if self.record_path is not None:
            self.record_path.parent.mkdir(parents=True, exist_ok=True)
        sensor = o3dio.RealSenseSensor()
        rs_config = o3dio.RealSenseSensorConfig(config.open3d_config())
        try:
            ok = call_with_timeout(lambda: sensor.init_sensor(rs_config, 0, str(self.record_path or "")),
                                   open_timeout_s, "init_sensor")
        except RuntimeError as e:  # Open3D raises for "camera not connected" and invalid configs
            raise DeviceError(f"RealSense {config.serial or '(first device)'} did not open: {clean_error(e)}") from None
        if not ok:
            raise DeviceError(f"RealSense {config.serial or '(first device)'} did not open with {config.open3d_config()}")
        start_record = self.record_path is not None and record == "all"
        try:
            if not call_with_timeout(lambda: sensor.start_capture(start_record), open_timeout_s, "start_capture"):
                raise DeviceError("RealSense start_capture failed")
        except RuntimeError as e:
            raise DeviceError(f"RealSense did not start streaming: {clean_error(e)}") from None
        self._sensor = sensor
        try:
            md = sensor.get_metadata()
            self.metadata = md
            self.intrinsics: Intrinsics = intrinsics_from_metadata(md)
            self.depth_scale: float = depth_scale_from_metadata(md)
            self._color_format = check_color_format(md)
        except BaseException:
            self.close()
            raise
        self.serial = str(md.serial_number)
        self.device_timestamp_us = 0

    def capture(self) -> RGBDFrame:
        """The next aligned frameset. Blocks at most ``config.frame_timeout_s``; DeviceError on timeout
        (cable, USB2 bandwidth, camera reset) or when the camera is closed."""
        sensor = self._sensor
        if sensor is None:
            raise DeviceError("the RealSense camera is closed")
        views = self.record_path is not None and self.record_mode == "views"
        try:
            if views:
                for _ in range(4):  # drop what was queued while paused: the frame returned must be in the bag
                    if sensor.capture_frame(False, True).is_empty():
                        break
                sensor.resume_record()
            try:
                deadline = time.monotonic() + self.config.frame_timeout_s
                while True:
                    image = sensor.capture_frame(False, True)
                    if not image.is_empty():
                        break
                    if time.monotonic() > deadline:
                        raise DeviceError(
                            f"no frame from the RealSense {self.serial} within {self.config.frame_timeout_s} s: check "
                            f"the USB3 cable and port (on a USB2 link {self.config.color_width}x"
                            f"{self.config.color_height} @ {self.config.fps} fps may not stream)")
                    time.sleep(POLL_S)
            finally:
                if views:
                    sensor.pause_record()
        except RuntimeError as e:  # Open3D: CaptureFrame() failed (unplugged, reset)
            raise DeviceError(f"the RealSense {self.serial} failed: {clean_error(e)}") from None
        self.device_timestamp_us = int(sensor.get_timestamp())
        return to_rgbd_frame(image, self.intrinsics, self.depth_scale, self._color_format)

    def close(self) -> None:
        """Stop streaming; a recording is closed and becomes playable."""
        sensor, self._sensor = self._sensor, None
        if sensor is not None:
            sensor.stop_capture()

    def __enter__(self) -> "RealSenseCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()



def open_camera(config: RealSenseConfig, **live_kwargs):
    """The camera a config asks for: its recorded ``bag`` played back (offline re-processing), else the
    live D435 (``live_kwargs`` go to RealSenseCamera). Both are ``RGBDCamera``s."""
    if config.bag is not None:
        from drivers.realsense.bag import RealSenseBag

        return RealSenseBag(config.bag)
    return RealSenseCamera(config, **live_kwargs)
