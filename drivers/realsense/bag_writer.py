"""Write ``RGBDFrame``s as a RealSense ``.bag`` (librealsense's rosbag layout, file version 4) that
Open3D's ``RSBagReader`` plays back, with the pure-Python ``rosbags`` ROS1 writer: no pyrealsense2,
no camera. Tests build their fixtures from twin frames with it, and ``cellctl`` can export a twin
session in the format a real recording has.

What playback needs and the pitfalls (found by trying, see docs/HARDWARE.md): uncompressed chunks,
frame numbers from 1, the depth unit as an option message. By default depth is written on the colour
grid (same intrinsics, identity extrinsic), so alignment maps every depth pixel onto itself; a
separate depth stream (its own intrinsics and a depth-to-colour extrinsic, as a real D435 records)
is written with ``depth_intrinsics`` and ``T_color_depth``. Frames are 1/fps apart on the bag clock."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from drivers.interfaces import Intrinsics, RGBDFrame
from drivers.realsense.bag_format import (COLOR_STREAM as _COLOR, DEPTH_STREAM as _DEPTH, DEPTH_UNIT_M, FILE_VERSION,
                                          matrix_to_quat, typestore as _typestore)


def depth_to_units(depth_m: np.ndarray, unit_m: float = DEPTH_UNIT_M) -> np.ndarray:
    """Metres (NaN = no return) to the camera's uint16 depth units, 0 = no return; depths the 16 bits
    cannot hold are no return too, as on the device."""
    d = np.asarray(depth_m, dtype=np.float64) / unit_m
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(d) & (d > 0.5) & (d < 65535.5)
    return np.where(ok, np.rint(np.where(ok, d, 0.0)), 0.0).astype(np.uint16)


class BagWriter:
    """Context manager: ``with BagWriter(path, intrinsics) as w: w.add(frame)``. The file must not
    exist. ``serial`` and ``device_name`` are what the bag's metadata reports on playback.
    ``depth_intrinsics``/``T_color_depth`` (4x4, depth frame -> colour frame) describe a depth imager
    apart from the colour camera; ``add(frame, depth_m=...)`` then takes its depth image."""

    def __init__(self, path: str | os.PathLike, intrinsics: Intrinsics, *, fps: int = 30,
                 depth_unit_m: float = DEPTH_UNIT_M, frame_spacing_s: float | None = None,
                 serial: str = "000000000000", device_name: str = "Intel RealSense D435",
                 color_format: str = "RGB8", depth_intrinsics: Intrinsics | None = None,
                 T_color_depth: np.ndarray | None = None) -> None:
        frame_spacing_s = 1.0 / fps if frame_spacing_s is None else frame_spacing_s
        if not frame_spacing_s > 0.0:
            raise ValueError(f"frame_spacing_s {frame_spacing_s} must be positive")
        if color_format not in ("RGB8", "BGR8"):
            raise ValueError(f"color_format must be RGB8 or BGR8, got {color_format!r}")
        self.path = Path(path)
        self.intrinsics = intrinsics
        self.depth_intrinsics = depth_intrinsics or intrinsics
        self.T_color_depth = np.eye(4) if T_color_depth is None else np.asarray(T_color_depth, dtype=np.float64)
        if self.T_color_depth.shape != (4, 4):
            raise ValueError(f"T_color_depth must be 4x4, got {self.T_color_depth.shape}")
        self.color_format = color_format
        self.fps = int(fps)
        self.depth_unit_m = float(depth_unit_m)
        self.spacing_ns = int(round(frame_spacing_s * 1e9))
        self.serial = serial
        self.device_name = device_name
        self.frames = 0
        self._store = None
        self._writer = None
        self._conn: dict[str, object] = {}

    # ------------------------------------------------------------------ context
    def __enter__(self) -> "BagWriter":
        self.open()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def open(self) -> None:
        from rosbags.rosbag1 import Writer, WriterError

        self._store = _typestore()
        try:
            self._writer = Writer(self.path)  # uncompressed: BZ2 bags crash the reader, LZ4 ones do not open
            self._writer.open()
        except (WriterError, OSError) as e:
            raise ValueError(f"cannot write {self.path}: {e}") from None
        self._write_static()

    def close(self) -> None:
        """Write the index; a bag without it (process killed) does not open."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def abort(self) -> None:
        """Drop a bag that failed half-way: without its index it would not open anyway."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None
            self.path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ frames
    def add(self, frame: RGBDFrame, streams: tuple[str, ...] = ("depth", "color"), *,
            depth_m: np.ndarray | None = None, offset_s: float = 0.0) -> None:
        """Append one colour + depth pair, numbered from 1, ``frame_spacing_s`` after the previous.
        ``streams`` leaves one out, to make a recording whose stream stops early (tests, fault drills).
        ``depth_m`` is the depth imager's own image (default: the frame's depth, on the colour grid);
        ``offset_s`` shifts this depth frame on the bag clock (unsynchronised streams)."""
        K, Kd = self.intrinsics, self.depth_intrinsics
        if self._writer is None:
            raise ValueError(f"{self.path} is not open for writing (use BagWriter as a context manager)")
        if frame.intrinsics != K:
            raise ValueError(f"frame intrinsics {frame.intrinsics} differ from the bag's {K}")
        if not streams or set(streams) - {"depth", "color"}:
            raise ValueError(f"streams must be 'depth' and/or 'color', got {streams!r}")
        self.frames += 1
        t = 1_000_000_000 + self.frames * self.spacing_ns  # static info sits at 1 ns, frames after
        if "depth" in streams:
            d = frame.depth if depth_m is None else np.asarray(depth_m)
            if d.shape != (Kd.height, Kd.width):
                raise ValueError(f"depth image is {d.shape}, the depth stream is {Kd.height}x{Kd.width}")
            depth = np.ascontiguousarray(depth_to_units(d, self.depth_unit_m).astype("<u2"))
            td = t + int(round(offset_s * 1e9))
            self._image(f"{_DEPTH}/image/data", td, "mono16", depth.view(np.uint8).reshape(-1), 2 * Kd.width, Kd)
        if "color" in streams:
            color = frame.color[..., ::-1] if self.color_format == "BGR8" else frame.color
            self._image(f"{_COLOR}/image/data", t, self.color_format.lower(), np.ascontiguousarray(color).reshape(-1),
                        3 * K.width, K)

    def add_all(self, frames: Iterable[RGBDFrame]) -> None:
        for f in frames:
            self.add(f)

    # ------------------------------------------------------------------ internals
    def _put(self, topic: str, msgtype: str, t_ns: int, msg) -> None:
        conn = self._conn.get(topic)
        if conn is None:
            conn = self._conn[topic] = self._writer.add_connection(topic, msgtype, typestore=self._store)
        self._writer.write(conn, t_ns, self._store.serialize_ros1(msg, msgtype))

    def _header(self, seq: int, t_ns: int, frame_id: str = "0"):
        T = self._store.types
        return T["std_msgs/msg/Header"](seq=seq, stamp=T["builtin_interfaces/msg/Time"](
            sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000), frame_id=frame_id)

    def _image(self, topic: str, t_ns: int, encoding: str, data: np.ndarray, step: int, K: Intrinsics) -> None:
        msg = self._store.types["sensor_msgs/msg/Image"](
            header=self._header(self.frames, t_ns), height=K.height, width=K.width, encoding=encoding,
            is_bigendian=0, step=step, data=data)
        self._put(topic, "sensor_msgs/msg/Image", t_ns, msg)

    def _write_static(self) -> None:
        T, t = self._store.types, 1
        kv = T["diagnostic_msgs/msg/KeyValue"]
        self._put("/file_version", "std_msgs/msg/UInt32", t, T["std_msgs/msg/UInt32"](data=FILE_VERSION))
        for key, value in (("Name", self.device_name), ("Serial Number", self.serial),
                           ("Firmware Version", "0.0.0.0"), ("Product Line", "D400"), ("Product Id", "0B07")):
            self._put("/device_0/info", "diagnostic_msgs/msg/KeyValue", t, kv(key=key, value=value))
        self._put("/device_0/sensor_0/info", "diagnostic_msgs/msg/KeyValue", t, kv(key="Name", value="Stereo Module"))
        self._put("/device_0/sensor_1/info", "diagnostic_msgs/msg/KeyValue", t, kv(key="Name", value="RGB Camera"))
        self._put("/device_0/sensor_0/option/Depth_Units/value", "std_msgs/msg/Float32", t,
                  T["std_msgs/msg/Float32"](data=self.depth_unit_m))
        self._put("/device_0/sensor_0/option/Depth_Units/description", "std_msgs/msg/String", t,
                  T["std_msgs/msg/String"](data="Number of meters represented by a single depth unit"))
        # the depth stream is the reference; the colour stream's tf is the depth -> colour extrinsic
        x, y, z, w = matrix_to_quat(self.T_color_depth[:3, :3])
        tc = self.T_color_depth[:3, 3]
        for stream, encoding, K, (qx, qy, qz, qw), (tx, ty, tz) in (
                (_DEPTH, "mono16", self.depth_intrinsics, (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0)),
                (_COLOR, self.color_format.lower(), self.intrinsics, (x, y, z, w), tuple(float(v) for v in tc))):
            kmat = np.array([K.fx, 0.0, K.cx, 0.0, K.fy, K.cy, 0.0, 0.0, 1.0])
            pmat = np.array([K.fx, 0.0, K.cx, 0.0, 0.0, K.fy, K.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
            self._put(f"{stream}/info", "realsense_msgs/msg/StreamInfo", t,
                      T["realsense_msgs/msg/StreamInfo"](fps=self.fps, encoding=encoding, is_recommended=True))
            info = T["sensor_msgs/msg/CameraInfo"](
                header=self._header(0, t), height=K.height, width=K.width, distortion_model=K.model,
                D=np.asarray(K.coeffs, dtype=np.float64), K=kmat, R=np.eye(3).reshape(-1), P=pmat, binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            self._put(f"{stream}/info/camera_info", "sensor_msgs/msg/CameraInfo", t, info)
            self._put(f"{stream}/tf/0", "geometry_msgs/msg/Transform", t, T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
                rotation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))


def write_bag(path: str | os.PathLike, frames: Iterable[RGBDFrame], **kwargs) -> Path:
    """Write ``frames`` (all with the same intrinsics) to a new ``.bag``; returns its path."""
    frames = list(frames)
    if not frames:
        raise ValueError("no frames to write")
    with BagWriter(path, frames[0].intrinsics, **kwargs) as w:
        w.add_all(frames)
    return w.path
