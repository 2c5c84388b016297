"""Play a recorded RealSense ``.bag`` back as an ``RGBDCamera``, so a recorded session can be processed
offline exactly as the live camera's frames: Open3D's ``t.io.RSBagReader`` reads it (librealsense
inside, depth aligned to colour), intrinsics and depth scale come from the bag's own metadata.

Before playing, the bag's index is read with ``rosbags`` (pure Python, no frame data): a bag cut
short or never closed has no usable index and is refused with the reason, and the number of colour
frames that have depth is known. That count matters because when the depth stream stops early,
librealsense keeps pairing new colour frames with the last depth frame: those stale pairs are not
served. Every wait is bounded: the end of the bag, a stream that stops early and a playback that
stalls all raise ``DeviceError``."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.interfaces import DeviceError, Intrinsics, RGBDFrame
from drivers.realsense.frames import (call_with_timeout, check_color_format, clean_error, depth_scale_from_metadata,
                                      intrinsics_from_metadata, to_rgbd_frame)

_IMAGE_TOPIC = re.compile(r"^/device_(\d+)/sensor_(\d+)/(Depth|Color)_(\d+)/image/data$")


@dataclass(frozen=True)
class BagIndex:
    """When the bag's two image streams have frames (ns on the bag clock, sorted), from its index."""

    color_ns: np.ndarray
    depth_ns: np.ndarray

    def paired_frames(self, fps: float) -> int:
        """Colour frames no later than the last depth frame (half a period of slack): the ones that
        get their own depth."""
        return int(np.searchsorted(self.color_ns, self.depth_ns[-1] + 0.5e9 / fps, side="right"))

    def stop_early(self, fps: float) -> str | None:
        """Which stream stops early, in words, or None when both run to the end (within two periods)."""
        nc, nd = len(self.color_ns), len(self.depth_ns)
        tc, td = self.color_ns[-1] * 1e-9, self.depth_ns[-1] * 1e-9
        if tc - td > 2.0 / fps:
            return (f"the depth stream stops after {_frames(nd)} at {td:.2f} s while the colour stream runs on "
                    f"to {_frames(nc)} at {tc:.2f} s")
        if td - tc > 2.0 / fps:
            return (f"the colour stream stops after {_frames(nc)} at {tc:.2f} s while the depth stream runs on "
                    f"to {_frames(nd)} at {td:.2f} s")
        return None


def read_bag_index(path: str | os.PathLike) -> BagIndex:
    """Read the rosbag index (no image data). DeviceError names what is wrong: not a bag, cut short
    (no index), or without a colour or a depth stream."""
    try:
        from rosbags.rosbag1 import Reader, ReaderError
    except ImportError as e:
        raise DeviceError("playing a .bag back needs the 'rosbags' package (pip install rosbags)") from e
    path = Path(path)
    try:
        with Reader(path) as reader:
            times: dict[str, list[int]] = {}
            for conn in reader.connections:
                m = _IMAGE_TOPIC.match(conn.topic)
                if m and m.group(3) not in times:  # Open3D plays the first colour and depth streams
                    times[m.group(3)] = sorted(entry.time for entry in reader.indexes[conn.id])
    except FileNotFoundError:
        raise DeviceError(f"{path}: no such .bag file") from None
    except (ReaderError, OSError, KeyError, ValueError) as e:
        raise DeviceError(f"{path}: not a readable RealSense bag ({e}); a bag cut short, or whose recorder was "
                          f"killed before closing it, has no usable index: record it again") from None
    missing = [word for name, word in (("Color", "colour"), ("Depth", "depth")) if not times.get(name)]
    if missing:
        raise DeviceError(f"{path}: the bag has no {' and no '.join(missing)} frames; playback needs colour and "
                          f"depth (record with both streams enabled)")
    return BagIndex(color_ns=np.asarray(times["Color"], dtype=np.int64),
                    depth_ns=np.asarray(times["Depth"], dtype=np.int64))


def _frames(n: int) -> str:
    return f"{n} frame" if n == 1 else f"{n} frames"


class RealSenseBag:
    """A recorded ``.bag`` served through ``RGBDCamera``: ``capture()`` returns its frames in order,
    then raises DeviceError. Use as a context manager or call ``close()``.

    ``frame_timeout_s`` bounds the wait for one frame on top of Open3D's own end-of-file wait (10
    frame periods). ``metadata`` is Open3D's: device name, serial number, fps, stream length."""

    def __init__(self, path: str | os.PathLike, *, frame_timeout_s: float = 2.0, buffer_size: int = 32) -> None:
        import open3d.t.io as o3dio

        self.path = Path(path)
        if not self.path.is_file():
            raise DeviceError(f"{self.path}: no such .bag file")
        self.index = read_bag_index(self.path)
        reader = o3dio.RSBagReader(buffer_size)
        try:
            opened = call_with_timeout(lambda: reader.open(str(self.path)), 10.0, "bag open")
        except RuntimeError as e:  # Open3D raises for unsupported formats and unequal stream rates
            raise DeviceError(f"{self.path}: Open3D cannot play this bag back: {clean_error(e)}") from None
        if not opened:
            raise DeviceError(f"{self.path}: librealsense cannot play this bag back (Open3D: unable to open file); "
                              f"it needs librealsense's rosbag layout with a colour and a depth stream")
        self._reader = reader
        try:
            self.metadata = reader.metadata
            self.intrinsics: Intrinsics = intrinsics_from_metadata(self.metadata)
            self.depth_scale: float = depth_scale_from_metadata(self.metadata)
            self._color_format = check_color_format(self.metadata)
        except BaseException:
            self.close()
            raise
        self.fps = float(self.metadata.fps)
        self._stream_error = self.index.stop_early(self.fps)
        self.frames_expected = self.index.paired_frames(self.fps)
        self.frames_served = 0
        self.frame_timeout_s = float(frame_timeout_s) + 10.0 / self.fps
        self._broken: str | None = None

    def capture(self) -> RGBDFrame:
        """The next frame of the bag. Blocks at most ``frame_timeout_s`` + 10 frame periods. DeviceError
        at the end of the bag, where a stream stops early, or when the playback stalls."""
        if self._broken:
            raise DeviceError(self._broken)
        if self._reader is None:
            raise DeviceError(f"{self.path}: the bag player is closed")
        if self.frames_served >= self.frames_expected:
            if self._stream_error:
                raise DeviceError(f"{self.path}: frames stop early: {self._stream_error}; {_frames(self.frames_served)} "
                                  f"served (the rest would pair colour with stale depth)")
            raise DeviceError(f"{self.path}: end of bag: all {_frames(self.frames_served)} served")
        reader = self._reader
        try:
            image = call_with_timeout(reader.next_frame, self.frame_timeout_s, "bag playback")
        except DeviceError as e:
            # the playback thread hangs: keep the reader alive (its thread still uses it), never reuse it
            self._broken = f"{self.path}: playback stalled after {_frames(self.frames_served)} ({e})"
            self._reader = None
            self._stuck_reader = reader
            raise DeviceError(self._broken) from None
        if image.is_empty():
            self._broken = (f"{self.path}: playback ended after {self.frames_served} of {self.frames_expected} "
                            f"frames: frames were dropped (a gap of over 10 frame periods in the recording, or a "
                            f"reader too slow for the bag clock) or the bag is damaged")
            raise DeviceError(self._broken)
        frame = to_rgbd_frame(image, self.intrinsics, self.depth_scale, self._color_format)
        self.frames_served += 1
        return frame

    def close(self) -> None:
        """Stop the playback. Bounded and never raises: librealsense may take a few seconds to stop a
        playback that waits on a gap in the recording; after 10 s the reader is left to its thread."""
        reader, self._reader = self._reader, None
        if reader is not None:
            try:
                call_with_timeout(reader.close, 10.0, "bag close")
            except DeviceError:
                self._stuck_reader = reader

    def __enter__(self) -> "RealSenseBag":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"RealSenseBag({str(self.path)!r}, {self.intrinsics.width}x{self.intrinsics.height} @ {self.fps:g} fps, "
                f"{self.frames_served}/{self.frames_expected} frames served)")
