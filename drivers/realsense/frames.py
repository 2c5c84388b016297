"""Open3D RealSense output -> our ``RGBDFrame``, and the depth conversion the live camera and the bag player share."""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from drivers.interfaces import DeviceError, Intrinsics, RGBDFrame

T = TypeVar("T")

#: Colour formats an RGBDFrame can be made of without a colour conversion library.
COLOR_FORMATS = ("RGB8", "BGR8")


def intrinsics_from_metadata(md) -> Intrinsics:
    """The colour intrinsics the device (or the bag) reports: with depth aligned to colour they are the
    depth image's too. Never hard-coded: every D435 has its own factory calibration."""
    K = np.asarray(md.intrinsics.intrinsic_matrix, dtype=np.float64)
    w, h = int(md.intrinsics.width), int(md.intrinsics.height)
    if w <= 0 or h <= 0 or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DeviceError(f"the RealSense reported unusable intrinsics: {w}x{h}, K={K.tolist()}")
    return Intrinsics(width=w, height=h, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]))


def depth_scale_from_metadata(md) -> float:
    """Depth units per metre (Open3D's convention: 1000 for the D435's default 1 mm unit)."""
    scale = float(md.depth_scale)
    if not np.isfinite(scale) or scale <= 0:
        raise DeviceError(f"the RealSense reported an unusable depth scale {scale}")
    return scale


def check_color_format(md) -> str:
    fmt = str(md.color_format)
    if fmt not in COLOR_FORMATS:
        raise DeviceError(f"colour format {fmt} is not supported: record or stream with color_format RGB8 or BGR8")
    return fmt


def to_rgbd_frame(image, intrinsics: Intrinsics, depth_scale: float, color_format: str) -> RGBDFrame:
    """Open3D ``t.geometry.RGBDImage`` (uint16 depth aligned to colour) -> RGBDFrame: depth in float32
    metres (raw / depth_scale), 0 = no return -> NaN; BGR swapped to RGB."""
    color = np.asarray(image.color.as_tensor().numpy())
    raw = np.asarray(image.depth.as_tensor().numpy())
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.dtype != np.uint16:
        raise DeviceError(f"depth must be uint16 (Z16), got {raw.dtype}")
    if color_format == "BGR8":
        color = color[..., ::-1]
    return RGBDFrame(color=np.ascontiguousarray(color, dtype=np.uint8), depth=depth_to_metres(raw, depth_scale),
                     intrinsics=intrinsics, timestamp=time.monotonic())


def depth_to_metres(raw: np.ndarray, depth_scale: float) -> np.ndarray:
    """uint16 depth units -> float32 metres (raw / depth_scale, Open3D's convention), 0 (no return) -> NaN."""
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[raw == 0] = np.nan
    return depth


def call_with_timeout(fn: Callable[[], T], timeout_s: float, what: str) -> T:
    """Run a blocking Open3D call in a daemon thread and give up after ``timeout_s``: the calls release
    the GIL, so the wait is bounded even when the device or the playback thread never answers. On
    timeout the call keeps running in its thread (it cannot be interrupted); the caller must treat
    the device as broken."""
    box: dict[str, object] = {}
    done = threading.Event()

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - re-raised in the caller's thread
            box["error"] = e
        finally:
            done.set()

    threading.Thread(target=run, name=f"realsense-{what}", daemon=True).start()
    if not done.wait(timeout_s):
        raise DeviceError(f"RealSense {what} did not return within {timeout_s:.1f} s")
    if "error" in box:
        raise box["error"]  # type: ignore[misc]
    return box["value"]  # type: ignore[return-value]


def clean_error(e: Exception) -> str:
    """Open3D's error text without its ANSI colours and C++ source location."""
    text = str(e).replace("\x1b[1;31m", "").replace("\x1b[0;m", "").replace("[Open3D Error] ", "").strip()
    return " ".join(re.split(r"\.cpp:\d+: ", text)[-1].split())
