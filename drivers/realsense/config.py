"""Validated configuration of the real Intel RealSense D435, opened through Open3D's RealSense support
(``open3d.t.io.RealSenseSensor`` live, ``bag.RealSenseBag`` for a recorded ``.bag``; no pyrealsense2).

Everything the device would refuse at start (an unknown resolution, frame rate or format) is refused
here first, naming the field, so a wrong YAML fails at load time and not in front of the robot."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True, validate_default=True)

#: D435 colour stream sizes (RGB camera, librealsense 2.5x) as (width, height).
COLOR_SIZES: tuple[tuple[int, int], ...] = (
    (1920, 1080), (1280, 720), (960, 540), (848, 480), (640, 480), (640, 360), (424, 240), (320, 240), (320, 180))
#: D435 depth stream sizes (stereo module) as (width, height).
DEPTH_SIZES: tuple[tuple[int, int], ...] = (
    (1280, 720), (848, 480), (640, 480), (640, 360), (480, 270), (424, 240), (256, 144))
#: Frame rates both streams offer; Open3D streams colour and depth at one common rate.
FPS: tuple[int, ...] = (6, 15, 30, 60)
#: Depth presets of the D400 family, as in the RealSense Viewer.
VISUAL_PRESETS: tuple[str, ...] = (
    "default", "custom", "hand", "high_accuracy", "high_density", "medium_density", "remove_ir_pattern")


def _mode(width: int | None, height: int, sizes: tuple[tuple[int, int], ...], stream: str) -> int:
    if width is not None and (width, height) not in sizes:
        raise ValueError(f"{stream}_width x {stream}_height {width}x{height} is not a D435 {stream} mode; use one of "
                         f"{', '.join(f'{w}x{h}' for w, h in sizes)}")
    return height


class RealSenseConfig(BaseModel):
    """One D435 on the hand.

    ``serial`` picks the camera when several are plugged in ("" = the first one found). Colour and
    depth sizes are separate because the D435's depth imager has its own modes; the depth is always
    aligned to colour (``align_depth_to_color``), so frames come out at the colour size with the
    colour intrinsics. ``frame_timeout_s`` bounds every wait for a frame. ``bag`` plays a recording
    back instead of opening a device; ``record_bag`` records what the live camera streams.
    ``keep_view_bags`` asks the scan runner to keep a bag of the views of every real scan job."""

    model_config = _STRICT

    serial: str = Field("", max_length=32, pattern=r"^[0-9A-Za-z_-]*$")
    color_width: int = 848
    color_height: int = 480
    depth_width: int = 848
    depth_height: int = 480
    fps: int = 30
    color_format: Literal["RGB8", "BGR8"] = "RGB8"
    depth_format: Literal["Z16"] = "Z16"
    visual_preset: Literal[VISUAL_PRESETS] = "default"  # type: ignore[valid-type]
    align_depth_to_color: bool = True
    frame_timeout_s: float = Field(2.0, gt=0.0, le=30.0)
    bag: Path | None = None
    record_bag: Path | None = None
    keep_view_bags: bool = False

    @field_validator("color_height")
    @classmethod
    def _color_mode(cls, v: int, info: ValidationInfo) -> int:
        return _mode(info.data.get("color_width"), v, COLOR_SIZES, "color")

    @field_validator("depth_height")
    @classmethod
    def _depth_mode(cls, v: int, info: ValidationInfo) -> int:
        return _mode(info.data.get("depth_width"), v, DEPTH_SIZES, "depth")

    @field_validator("fps")
    @classmethod
    def _fps(cls, v: int, info: ValidationInfo) -> int:
        if v not in FPS:
            raise ValueError(f"{v} is not a rate both D435 streams offer; use one of {', '.join(map(str, FPS))}")
        widest = max(info.data.get("color_width", 0), info.data.get("depth_width", 0))
        if v > 30 and widest > 848:
            raise ValueError(f"{v}: the D435 streams {widest}-pixel-wide images at 30 fps at most; lower fps or "
                             f"the resolution")
        return v

    @field_validator("frame_timeout_s")
    @classmethod
    def _timeout(cls, v: float, info: ValidationInfo) -> float:
        fps = info.data.get("fps")
        if fps and v < 2.0 / fps:
            raise ValueError(f"{v} s is shorter than two frame periods at {fps} fps ({2.0 / fps:.3f} s)")
        return v

    @field_validator("align_depth_to_color")
    @classmethod
    def _aligned(cls, v: bool) -> bool:
        if not v:
            raise ValueError("must be true: an RGBDFrame carries depth aligned to colour, with the colour "
                             "intrinsics (unaligned depth has other intrinsics and another viewpoint)")
        return v

    @field_validator("bag", "record_bag")
    @classmethod
    def _bag_path(cls, v: Path | None, info: ValidationInfo) -> Path | None:
        if v is not None and v.suffix.lower() != ".bag":
            raise ValueError(f"{str(v)!r} is not a .bag file path")
        if v is not None and info.field_name == "record_bag" and info.data.get("bag") is not None:
            raise ValueError("cannot record while playing a bag back: set bag or record_bag, not both")
        return v

    def open3d_config(self) -> dict[str, str]:
        """The string map ``open3d.t.io.RealSenseSensorConfig`` takes (its keys and enum spellings)."""
        return {
            "serial": self.serial,
            "color_format": f"RS2_FORMAT_{self.color_format}",
            "color_resolution": f"{self.color_width},{self.color_height}",
            "depth_format": f"RS2_FORMAT_{self.depth_format}",
            "depth_resolution": f"{self.depth_width},{self.depth_height}",
            "fps": str(self.fps),
            "visual_preset": f"RS2_RS400_VISUAL_PRESET_{self.visual_preset.upper()}",
        }



def load_realsense_config(path: str | Path) -> RealSenseConfig:
    """Read a camera YAML: either the fields at the top level (configs/camera.d435.yaml) or a cell
    config with a ``camera:`` block. CameraConfigError names the file and the field; relative
    ``bag``/``record_bag`` paths are taken relative to the file."""
    import yaml
    from pydantic import ValidationError

    from configs.loading import field_path, load_yaml_model, safe_load

    path = Path(path)
    try:
        data = safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        data = None  # load_yaml_model reports it with the file name
    if isinstance(data, dict) and isinstance(data.get("camera"), dict) and "color_width" not in data:
        try:
            cfg = RealSenseConfig.model_validate(data["camera"])
        except ValidationError as e:
            raise CameraConfigError("\n".join(f"{path}: {field_path(('camera', *err['loc']))}: {err['msg']}"
                                               for err in e.errors())) from None
    else:
        cfg = load_yaml_model(path, RealSenseConfig, CameraConfigError, "camera config")
    # relative bag paths resolve against the config file, as every path in the project's configs
    return cfg.model_copy(update={k: path.parent / v for k in ("bag", "record_bag")
                                  if (v := getattr(cfg, k)) is not None and not v.is_absolute()})


class CameraConfigError(ValueError):
    """A camera YAML that does not validate; the message names the file and the field."""
