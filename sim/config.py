"""Validated configuration of the pybullet twin: the simulated D435, the hand-eye extrinsic and the
twin itself. Pydantic v2 models; unknown fields are refused and every number must be finite."""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from configs.loading import load_yaml_model
from configs.poses import HandEyeBase, Vec3, pose_from_xyz_rpy_deg
from sim.faults import FaultsConfig

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)

#: Image sizes the D435 colour stream offers that the twin supports (width, height).
SUPPORTED_SIZES: tuple[tuple[int, int], ...] = ((848, 480), (640, 480))


class D435Config(BaseModel):
    """The simulated Intel RealSense D435, depth aligned to colour.

    ``hfov_deg``/``vfov_deg`` are the colour FOV at the chosen resolution (69.4 x 42.5 at 848x480;
    at 640x480 the colour image is a 4:3 crop, use about 55 x 42.5). ``depth_hfov_deg`` is the FOV of
    the depth imager: its focal length in pixels at ``width`` sets the stereo noise
    (:func:`sim.d435.depth_rms`)."""

    model_config = _STRICT

    width: int = 848
    height: int = 480
    hfov_deg: float = Field(69.4, gt=10.0, lt=150.0)
    vfov_deg: float = Field(42.5, gt=10.0, lt=150.0)
    depth_hfov_deg: float = Field(87.0, gt=10.0, lt=150.0)
    baseline_m: float = Field(0.050, gt=0.005, le=0.5)
    subpixel: float = Field(0.08, gt=0.0, le=1.0)
    min_range_m: float = Field(0.2, ge=0.01, le=5.0)
    max_range_m: float = Field(2.0, gt=0.05, le=20.0)
    max_incidence_deg: float = Field(80.0, gt=0.0, le=90.0)
    noise: bool = True
    seed: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _consistent(self) -> "D435Config":
        if (self.width, self.height) not in SUPPORTED_SIZES:
            raise ValueError(f"image size {self.width}x{self.height} not supported; use one of {SUPPORTED_SIZES}")
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        fx = 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2.0)
        fy = 0.5 * self.height / math.tan(math.radians(self.vfov_deg) / 2.0)
        if abs(fx / fy - 1.0) > 0.05:
            raise ValueError(
                f"hfov_deg {self.hfov_deg} / vfov_deg {self.vfov_deg} at {self.width}x{self.height} give "
                f"non-square pixels (fx={fx:.1f}, fy={fy:.1f}); the D435 colour camera has square pixels "
                f"(at 640x480 use hfov_deg about 55)")
        return self




class HandEyeConfig(HandEyeBase):
    """The twin's T_flange_cam. The default puts the optical z axis along the panda_hand z axis, 7 cm
    off along hand x and 5 cm forward."""

    xyz: Vec3 = Field(default_factory=lambda: [0.07, 0.0, 0.05])
    rpy_deg: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])

    @classmethod
    def from_file(cls, path, error: type[Exception] = ValueError) -> "HandEyeConfig":
        """The ``hand_eye:`` block of a file written by `cellctl calibrate hand-eye`; its other keys
        (residual, method, date) are the calibration's record, not config, and are not checked."""
        return load_yaml_model(path, _HandEyeFile, error, "hand-eye file").hand_eye


class _HandEyeFile(BaseModel):
    model_config = ConfigDict(extra="ignore")

    hand_eye: HandEyeConfig


Joint7 = Annotated[list[Annotated[float, Field(ge=-4.0, le=4.0)]], Field(min_length=7, max_length=7)]


class TwinToolConfig(BaseModel):
    """A tool on the hand whose contacts the twin reports (the cutting torch): a cylinder of
    ``radius_m`` from its tip back ``length_m`` along -z of the tip frame ``xyz``/``rpy_deg`` in the
    flange frame. Contact only, never drawn: the camera sees what the real one sees of the piece."""

    model_config = _STRICT

    xyz: Vec3
    rpy_deg: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    radius_m: float = Field(gt=0, le=0.2)
    length_m: float = Field(gt=0, le=1.0)
    nozzle_radius_m: float | None = Field(None, gt=0, le=0.2, description="at the tip; None: radius_m")
    nozzle_length_m: float = Field(0.0, ge=0, le=1.0, description="the taper from radius_m to the tip")

    @model_validator(mode="after")
    def _nozzle(self) -> "TwinToolConfig":
        if self.nozzle_length_m >= self.length_m:
            raise ValueError(f"tool nozzle_length_m ({self.nozzle_length_m}) must be shorter than length_m "
                             f"({self.length_m})")
        return self

    def T_flange_tip(self) -> np.ndarray:
        """4x4 pose of the tip frame in the flange frame."""
        return pose_from_xyz_rpy_deg(self.xyz, self.rpy_deg)

    def hull(self, sides: int = 24) -> np.ndarray:
        """(3 * sides, 3) vertices in the tip frame whose convex hull is the tool: the back ring, the
        ring where the nozzle starts and the tip ring (a polygon round each circle)."""
        a = 2 * np.pi * (np.arange(sides) + 0.5) / sides
        ring = np.stack([np.cos(a), np.sin(a), np.zeros(sides)], axis=1) / np.cos(np.pi / sides)
        tip = self.radius_m if self.nozzle_radius_m is None else self.nozzle_radius_m
        return np.vstack([ring * [self.radius_m, self.radius_m, 0] + [0, 0, -self.length_m],
                          ring * [self.radius_m, self.radius_m, 0] + [0, 0, -self.nozzle_length_m],
                          ring * [tip, tip, 0]])


class TwinConfig(BaseModel):
    """The pybullet twin. ``execution``: "step" follows trajectories by position control with
    dynamics at ``sim_hz``; "teleport" sets the joint states at each sample (fast tests).
    ``faults``: failures to inject (sim/faults.py), none by default."""

    model_config = _STRICT

    camera: D435Config = Field(default_factory=D435Config)
    hand_eye: HandEyeConfig = Field(default_factory=HandEyeConfig)
    # camera at (0.35, 0, 0.84) looking down and forward; the hand stays above z = 0.75, clear of every
    # built-in scene (the tallest, t_piece, ends at 0.57)
    home_q: Joint7 = Field(default_factory=lambda: [0.0, -0.7, 0.0, -1.7, 0.0, 1.5, 0.785])
    sim_hz: int = Field(240, ge=60, le=2000)
    execution: Literal["step", "teleport"] = "step"
    tool: TwinToolConfig | None = None
    faults: FaultsConfig = Field(default_factory=FaultsConfig)
