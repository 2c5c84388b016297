"""Play a recorded RealSense ``.bag`` back as an ``RGBDCamera``, paced by the reader, never by a clock.

Why not Open3D's ``t.io.RSBagReader``: it runs librealsense's playback in real time (Open3D leaves
``set_real_time(false)`` commented out, librealsense issue 7547) behind a one-frameset pipeline
queue, and its reader thread declares end of file after 10 frame periods without a frame. On a
busy PC frames were dropped, a bag ended early, and colour was paired with the wrong depth, so a
recorded scan did not replay the same way twice. Neither setting is reachable from Python.

Here the bag is read with ``rosbags`` (pure Python) in the bag's own order: colour and depth are
paired from the bag's index (each colour frame with the depth frame nearest in bag time, within
half a frame period), and depth is aligned to colour as librealsense does (``align.py``). The same
bag yields the same frames, in the same order, at any load. A colour frame with no depth within half
a period is refused with a clear error, never served with stale or foreign depth."""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.interfaces import DeviceError, Intrinsics, RGBDCamera, RGBDFrame
from drivers.realsense.align import align_depth
from drivers.realsense.bag_format import DISTORTION_MODELS, IMAGE_TOPIC, StreamModel, quat_to_matrix, typestore
from drivers.realsense.frames import COLOR_FORMATS, depth_to_metres

_DEPTH_ENCODINGS = ("mono16", "16uc1")
_SENSOR_OF = re.compile(r"^(/device_\d+/sensor_\d+)/")


@dataclass(frozen=True)
class BagIndex:
    """When the bag's two image streams have frames (ns on the bag clock, sorted), from its index."""

    color_ns: np.ndarray
    depth_ns: np.ndarray

    def pairs(self, fps: float) -> np.ndarray:
        """For each colour frame, the index of the depth frame nearest in bag time if it lies within
        half a frame period, else -1 (librealsense's syncer would pair it with whatever depth it had)."""
        d = self.depth_ns
        j = np.clip(np.searchsorted(d, self.color_ns), 1, max(len(d) - 1, 1))
        prev = np.clip(j - 1, 0, len(d) - 1)
        nxt = np.clip(j, 0, len(d) - 1)
        best = np.where(np.abs(d[prev] - self.color_ns) <= np.abs(d[nxt] - self.color_ns), prev, nxt)
        ok = np.abs(d[best] - self.color_ns) <= 0.5e9 / fps
        return np.where(ok, best, -1)

    def stop_early(self, fps: float) -> str | None:
        """Which stream stops early, in words, or None when both run to the end: colour frames after
        the last one with its own depth mean the depth stream stopped; depth frames more than half a
        period after the last colour frame mean the colour stream stopped."""
        pairs = self.pairs(fps)
        nc, nd = len(self.color_ns), len(self.depth_ns)
        tc, td = self.color_ns[-1] * 1e-9, self.depth_ns[-1] * 1e-9
        paired = np.nonzero(pairs >= 0)[0]
        last = int(paired[-1]) + 1 if len(paired) else 0
        if last < nc:
            return (f"the depth stream stops after {_frames(nd)} at {td:.2f} s while the colour stream runs on "
                    f"to {_frames(nc)} at {tc:.2f} s")
        if td - tc > 0.5 / fps:
            return (f"the colour stream stops after {_frames(nc)} at {tc:.2f} s while the depth stream runs on "
                    f"to {_frames(nd)} at {td:.2f} s")
        return None


@dataclass(frozen=True)
class BagMetadata:
    """What the bag says about its recording (the fields Open3D's metadata had)."""

    device_name: str
    serial_number: str
    fps: float
    color_format: str  # RGB8 or BGR8
    depth_scale: float  # depth units per metre (1000 for 1 mm units)
    stream_length_usec: int
    color: StreamModel
    depth: StreamModel


def _open_reader(path: Path):
    try:
        from rosbags.rosbag1 import Reader, ReaderError
    except ImportError as e:
        raise DeviceError("playing a .bag back needs the 'rosbags' package (pip install rosbags)") from e
    reader = Reader(path)
    try:
        reader.open()
    except FileNotFoundError:
        raise DeviceError(f"{path}: no such .bag file") from None
    except (ReaderError, OSError, KeyError, ValueError) as e:
        raise DeviceError(f"{path}: not a readable RealSense bag ({e}); a bag cut short, or whose recorder was "
                          f"killed before closing it, has no usable index: record it again") from None
    return reader


def _image_connections(reader, path: Path) -> dict[str, object]:
    """The first colour and the first depth image stream (what a D435 recording has)."""
    conns: dict[str, object] = {}
    for conn in reader.connections:
        m = IMAGE_TOPIC.match(conn.topic)
        if m and m.group(3) not in conns:
            conns[m.group(3)] = conn
    missing = [word for name, word in (("Color", "colour"), ("Depth", "depth"))
               if name not in conns or not reader.indexes[conns[name].id]]
    if missing:
        raise DeviceError(f"{path}: the bag has no {' and no '.join(missing)} frames; playback needs colour and "
                          f"depth (record with both streams enabled)")
    return conns


def read_bag_index(path: str | os.PathLike) -> BagIndex:
    """Read the rosbag index (no image data). DeviceError names what is wrong: not a bag, cut short
    (no index), or without a colour or a depth stream."""
    path = Path(path)
    reader = _open_reader(path)
    try:
        return _index(reader, _image_connections(reader, path))
    finally:
        reader.close()


def _index(reader, conns) -> BagIndex:
    times = {k: np.sort(np.fromiter((e.time for e in reader.indexes[c.id]), dtype=np.int64)) for k, c in conns.items()}
    return BagIndex(color_ns=times["Color"], depth_ns=times["Depth"])


def _frames(n: int) -> str:
    return f"{n} frame" if n == 1 else f"{n} frames"


class RealSenseBag(RGBDCamera):
    """A recorded ``.bag`` served through ``RGBDCamera``: ``capture()`` returns its colour frames in
    bag order, each with its own depth aligned to colour, then raises DeviceError. Use as a context
    manager or call ``close()``. ``metadata``: device name, serial number, fps, stream models."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise DeviceError(f"{self.path}: no such .bag file")
        self._reader = _open_reader(self.path)
        try:
            conns = _image_connections(self._reader, self.path)
            self.index = _index(self._reader, conns)
            self._store = typestore()
            self.metadata = self._read_metadata(conns)
        except BaseException:
            self.close()
            raise
        md = self.metadata
        self.intrinsics = md.color.intrinsics
        self.depth_scale = md.depth_scale
        self.fps = md.fps
        self._color_conn, self._depth_conn = conns["Color"], conns["Depth"]
        self._pairs = self.index.pairs(self.fps)
        paired = np.nonzero(self._pairs >= 0)[0]
        # colour frames after the last one with depth: the depth stream stopped, not a dropped frame
        self._tail = int(paired[-1]) + 1 if len(paired) else 0
        self._stream_error = self.index.stop_early(self.fps)
        self.frames_expected = int(len(paired))
        self.frames_served = 0
        self.frames_refused = 0
        self._next = 0  # next colour frame to play
        self._messages = None
        self._pending: dict[tuple[str, int], bytes] = {}
        self._seen = {"Color": 0, "Depth": 0}
        #: bag time (ns) of the last frame served, the stamp to compare with the recording's other logs
        self.last_bag_time_ns: int | None = None

    # ------------------------------------------------------------------ metadata
    def _read_metadata(self, conns) -> BagMetadata:
        path, store = self.path, self._store
        depth_prefix = conns["Depth"].topic.rsplit("/image/data", 1)[0]
        color_prefix = conns["Color"].topic.rsplit("/image/data", 1)[0]
        depth_sensor = _SENSOR_OF.match(depth_prefix).group(1)
        device = depth_prefix.split("/sensor_")[0]
        wanted = {f"{device}/info": "device", f"{depth_prefix}/info": "depth_info",
                  f"{color_prefix}/info": "color_info", f"{depth_prefix}/info/camera_info": "depth_cam",
                  f"{color_prefix}/info/camera_info": "color_cam",
                  f"{depth_sensor}/option/Depth_Units/value": "depth_units"}
        tf = {c.topic: ("depth_tf" if c.topic.startswith(f"{depth_prefix}/tf/") else "color_tf")
              for c in self._reader.connections
              if re.match(rf"^({re.escape(depth_prefix)}|{re.escape(color_prefix)})/tf/\d+$", c.topic)}
        wanted.update(tf)
        static = [c for c in self._reader.connections if c.topic in wanted]
        found: dict[str, object] = {}
        info: dict[str, str] = {}
        try:
            for conn, _, raw in self._reader.messages(connections=static):
                key = wanted[conn.topic]
                msg = store.deserialize_ros1(raw, conn.msgtype)
                if key == "device":
                    info.setdefault(msg.key, msg.value)
                else:
                    found.setdefault(key, msg)
        except Exception as e:  # noqa: BLE001 - rosbags raises several types for damaged data
            raise DeviceError(f"{path}: the bag's stream descriptions cannot be read: {e}") from None
        for key, what in (("color_cam", "colour camera_info"), ("depth_cam", "depth camera_info"),
                          ("color_info", "colour stream info"), ("depth_info", "depth stream info"),
                          ("depth_units", "Depth_Units option")):
            if key not in found:
                raise DeviceError(f"{path}: the bag has no {what}; it is not a librealsense recording")
        fps_c, fps_d = float(found["color_info"].fps), float(found["depth_info"].fps)
        if fps_c <= 0 or fps_c != fps_d:
            raise DeviceError(f"{path}: colour at {fps_c:g} fps and depth at {fps_d:g} fps: playback needs both "
                              f"streams at the same, positive rate")
        color_format = str(found["color_info"].encoding).upper()
        if color_format not in COLOR_FORMATS:
            raise DeviceError(f"colour format {color_format} is not supported: record or stream with color_format "
                              f"RGB8 or BGR8")
        unit = float(found["depth_units"].data)
        if not np.isfinite(unit) or unit <= 0:
            raise DeviceError(f"{path}: the bag's depth unit {unit} is unusable")
        color = _stream_model(found["color_cam"], found.get("color_tf"), path, "colour")
        depth = _stream_model(found["depth_cam"], found.get("depth_tf"), path, "depth")
        t = np.concatenate([self.index.color_ns, self.index.depth_ns])
        return BagMetadata(device_name=info.get("Name", ""), serial_number=info.get("Serial Number", ""),
                           fps=fps_c, color_format=color_format, depth_scale=float(1.0 / np.float32(unit)),
                           stream_length_usec=int((t.max() - t.min()) // 1000), color=color, depth=depth)

    # ------------------------------------------------------------------ frames
    def capture(self) -> RGBDFrame:
        """The next frame of the bag. DeviceError at the end of the bag, where a stream stops early,
        and for a colour frame the bag has no depth for (the next call plays the frame after it)."""
        if self._reader is None:
            raise DeviceError(f"{self.path}: the bag player is closed")
        k = self._next
        if k >= self._tail:
            if self._stream_error:
                raise DeviceError(f"{self.path}: frames stop early: {self._stream_error}; {_frames(self.frames_served)} "
                                  f"served (the rest would pair colour with stale depth)")
            raise DeviceError(f"{self.path}: end of bag: all {_frames(self.frames_served)} served")
        self._next += 1
        j = int(self._pairs[k])
        tc = int(self.index.color_ns[k])
        if j < 0:
            self.frames_refused += 1
            d = self.index.depth_ns
            near = d[np.argmin(np.abs(d - tc))]
            raise DeviceError(f"{self.path}: colour frame {k + 1} at {tc * 1e-9:.3f} s has no depth frame within half "
                              f"a frame period (nearest at {near * 1e-9:.3f} s): refused, never served with other "
                              f"depth; the next capture plays the frame after it")
        color_raw = self._take("Color", k)
        depth_raw = self._take("Depth", j)
        later_depth = self._pairs[self._next:]
        self._pending = {key: v for key, v in self._pending.items()
                         if (key[0] == "Color" and key[1] >= self._next) or (key[0] == "Depth" and key[1] in later_depth)}
        try:
            color = self._decode_color(color_raw)
            raw = self._decode_depth(depth_raw)
            raw = align_depth(raw, 1.0 / self.depth_scale, self.metadata.depth, self.metadata.color)
        except (ValueError, KeyError, AssertionError) as e:
            raise DeviceError(f"{self.path}: colour frame {k + 1} cannot be decoded: {e}") from None
        self.frames_served += 1
        self.last_bag_time_ns = tc
        return RGBDFrame(color=color, depth=depth_to_metres(raw, self.depth_scale), intrinsics=self.intrinsics,
                         timestamp=time.monotonic())

    def _take(self, stream: str, i: int) -> bytes:
        """The raw message of frame ``i`` of a stream, reading on in bag order; messages no later
        frame needs are not kept."""
        key = (stream, i)
        if self._messages is None:
            self._messages = self._reader.messages(connections=[self._color_conn, self._depth_conn])
        needed_depth = self._pairs[self._next - 1:]  # this frame's depth and every later frame's
        while key not in self._pending:
            try:
                conn, _, raw = next(self._messages)
            except StopIteration:
                raise DeviceError(f"{self.path}: the bag ends before {stream.lower()} frame {i + 1} its index "
                                  f"lists: the file is damaged") from None
            except Exception as e:  # noqa: BLE001
                raise DeviceError(f"{self.path}: the bag is damaged: {e}") from None
            name = "Color" if conn.id == self._color_conn.id else "Depth"
            n = self._seen[name]
            self._seen[name] += 1
            if (name == "Color" and n >= self._next - 1) or (name == "Depth" and n in needed_depth):
                self._pending[(name, n)] = raw
        return self._pending.pop(key)

    def _decode_color(self, raw: bytes) -> np.ndarray:
        msg = self._store.deserialize_ros1(raw, "sensor_msgs/msg/Image")
        img = _image_array(msg, np.uint8, 3, self.metadata.color)
        if str(msg.encoding).upper() != self.metadata.color_format:
            raise ValueError(f"encoding {msg.encoding} differs from the stream's {self.metadata.color_format}")
        return np.ascontiguousarray(img[..., ::-1] if self.metadata.color_format == "BGR8" else img)

    def _decode_depth(self, raw: bytes) -> np.ndarray:
        msg = self._store.deserialize_ros1(raw, "sensor_msgs/msg/Image")
        if str(msg.encoding).lower() not in _DEPTH_ENCODINGS:
            raise ValueError(f"depth encoding {msg.encoding} is not Z16 (mono16)")
        return _image_array(msg, np.dtype(">u2" if msg.is_bigendian else "<u2"), 1, self.metadata.depth).astype(np.uint16)

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Close the file. Never raises."""
        reader, self._reader = self._reader, None
        self._messages = None
        self._pending = {}
        if reader is not None:
            try:
                reader.close()
            except Exception:  # noqa: BLE001
                pass

    def __enter__(self) -> "RealSenseBag":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"RealSenseBag({str(self.path)!r}, {self.intrinsics.width}x{self.intrinsics.height} @ {self.fps:g} fps, "
                f"{self.frames_served}/{self.frames_expected} frames served)")


def _image_array(msg, dtype, channels: int, s: StreamModel) -> np.ndarray:
    dtype = np.dtype(dtype)
    K = s.intrinsics
    if (msg.width, msg.height) != (K.width, K.height):
        raise ValueError(f"image is {msg.width}x{msg.height}, its stream says {K.width}x{K.height}")
    row = msg.width * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.step < row or data.size < msg.step * msg.height:
        raise ValueError(f"image data holds {data.size} bytes, {msg.height} rows of {msg.step} expected")
    rows = data[:msg.step * msg.height].reshape(msg.height, msg.step)[:, :row]
    img = np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width, channels)
    return img[..., 0] if channels == 1 else img


def _stream_model(cam, tf, path: Path, what: str) -> StreamModel:
    K = np.asarray(cam.K, dtype=np.float64)
    w, h = int(cam.width), int(cam.height)
    if w <= 0 or h <= 0 or K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0:
        raise DeviceError(f"{path}: the {what} stream has unusable intrinsics: {w}x{h}, K={K.tolist()}")
    model = str(cam.distortion_model) or "None"
    coeffs = tuple(float(c) for c in np.asarray(cam.D, dtype=np.float64).ravel()[:5])
    coeffs = coeffs + (0.0,) * (5 - len(coeffs))
    if not np.all(np.isfinite(coeffs)):
        raise DeviceError(f"{path}: the {what} stream's distortion coefficients are not finite: {coeffs}")
    if model not in DISTORTION_MODELS and any(coeffs):
        raise DeviceError(f"{path}: the {what} stream's distortion model {model!r} is not supported "
                          f"(supported: {', '.join(DISTORTION_MODELS)})")
    R = t = None
    if tf is not None:
        try:
            R = quat_to_matrix(tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w)
        except ValueError as e:
            raise DeviceError(f"{path}: the {what} stream's extrinsic: {e}") from None
        t = np.array([tf.translation.x, tf.translation.y, tf.translation.z], dtype=np.float64)
        if not np.all(np.isfinite(t)):
            raise DeviceError(f"{path}: the {what} stream's extrinsic translation is not finite: {t.tolist()}")
    return StreamModel(Intrinsics(width=w, height=h, fx=float(K[0]), fy=float(K[4]), cx=float(K[2]),
                                  cy=float(K[5]), model=model, coeffs=coeffs), R=R, t=t)
