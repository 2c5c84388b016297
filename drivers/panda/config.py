"""Validated configuration of the real Franka arm (Panda or FR3) driven through franky.

The ``arm:`` block of ``configs/cell.real.yaml`` (see docs/HARDWARE.md). Pydantic v2: unknown fields
are refused and every number must be finite, because a typo in a safety limit must stop the cell
instead of silently falling back to a default.
"""

from __future__ import annotations

import ipaddress
import re
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator, model_validator

from configs.loading import load_yaml_model
from configs.panda import BASE_LINK, FLANGE_LINK, JOINT_NAMES, PANDA_URDF  # noqa: F401 - the arm's description
from configs.poses import HandEyeBase, Vec3

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)

Vec6 = Annotated[list[float], Field(min_length=6, max_length=6)]
Vec7 = Annotated[list[float], Field(min_length=7, max_length=7)]

FCI_PORT = 1337  # libfranka's command port (fixed by the protocol)

_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"^(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*$")


class JointLimits(BaseModel):
    """Published limits of one arm model, joint order 1..7: position (rad), velocity (rad/s),
    acceleration (rad/s^2), jerk (rad/s^3)."""

    model_config = _STRICT

    q_min: Vec7
    q_max: Vec7
    max_velocity: Vec7
    max_acceleration: Vec7
    max_jerk: Vec7

    @model_validator(mode="after")
    def _consistent(self) -> "JointLimits":
        if any(lo >= hi for lo, hi in zip(self.q_min, self.q_max)):
            raise ValueError(f"q_min {self.q_min} must be below q_max {self.q_max} for every joint")
        for name in ("max_velocity", "max_acceleration", "max_jerk"):
            if any(v <= 0.0 for v in getattr(self, name)):
                raise ValueError(f"{name} must be strictly positive, got {getattr(self, name)}")
        return self


def _panda() -> JointLimits:
    # Franka Emika Panda datasheet (FCI docs, "Robot and interface specifications").
    return JointLimits(
        q_min=[-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973],
        q_max=[2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973],
        max_velocity=[2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61],
        max_acceleration=[15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0],
        max_jerk=[7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0],
    )


def _fr3() -> JointLimits:
    # Franka Research 3 datasheet (same values as franky-sim's MJCF joint ranges).
    return JointLimits(
        q_min=[-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159],
        q_max=[2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159],
        max_velocity=[2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26],
        max_acceleration=[10.0] * 7,
        max_jerk=[5000.0] * 7,
    )


class ModelLimits(BaseModel):
    """Limits of both arm models, so switching ``model`` can never leave the other's limits active."""

    model_config = _STRICT

    panda: JointLimits = Field(default_factory=_panda)
    fr3: JointLimits = Field(default_factory=_fr3)


class CollisionConfig(BaseModel):
    """libfranka collision behaviour (``set_collision_behavior``): above a lower threshold the robot
    reports contact, above an upper threshold it stops with a reflex. Joint torques in Nm (7),
    Cartesian forces/torques in N / Nm (x, y, z, rx, ry, rz). Defaults are libfranka's examples."""

    model_config = _STRICT

    lower_torque_nm: Vec7 = Field(default_factory=lambda: [20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0])
    upper_torque_nm: Vec7 = Field(default_factory=lambda: [20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0])
    lower_force_n: Vec6 = Field(default_factory=lambda: [20.0, 20.0, 20.0, 25.0, 25.0, 25.0])
    upper_force_n: Vec6 = Field(default_factory=lambda: [20.0, 20.0, 20.0, 25.0, 25.0, 25.0])

    @model_validator(mode="after")
    def _ordered(self) -> "CollisionConfig":
        for lo_name, hi_name in (("lower_torque_nm", "upper_torque_nm"), ("lower_force_n", "upper_force_n")):
            lo, hi = getattr(self, lo_name), getattr(self, hi_name)
            if any(v <= 0.0 for v in lo + hi):
                raise ValueError(f"{lo_name} and {hi_name} must be strictly positive")
            if any(a > b for a, b in zip(lo, hi)):
                raise ValueError(f"{lo_name} {lo} must not exceed {hi_name} {hi}")
        return self


class Box(BaseModel):
    """Axis-aligned box in the robot base frame, metres."""

    model_config = _STRICT

    min_m: Vec3
    max_m: Vec3

    @model_validator(mode="after")
    def _ordered(self) -> "Box":
        if any(lo >= hi for lo, hi in zip(self.min_m, self.max_m)):
            raise ValueError(f"box min_m {self.min_m} must be below max_m {self.max_m} on every axis")
        return self


class WorkspaceConfig(BaseModel):
    """Where the flange (``panda_hand`` origin) and the camera optical centre may go. ``check_step_rad``:
    the path between samples is checked at joint-space steps no larger than this."""

    model_config = _STRICT

    flange: Box = Field(default_factory=lambda: Box(min_m=[-0.35, -0.85, 0.10], max_m=[0.95, 0.85, 1.30]))
    camera: Box | None = Field(default_factory=lambda: Box(min_m=[-0.40, -0.90, 0.10], max_m=[1.00, 0.90, 1.35]))
    check_step_rad: float = Field(0.02, gt=0.0, le=0.2)


class HandEye(HandEyeBase):
    """T_flange_cam of the real camera (no default: it comes from calibration)."""


class FrankaConfig(BaseModel):
    """The real arm. ``host``: the FCI address (the controller's shop-floor port, not the arm base).
    ``model`` picks which of ``limits.panda`` / ``limits.fr3`` is enforced. ``realtime``: require a
    PREEMPT_RT kernel (libfranka's ``RealtimeConfig.Enforce``); false only for simulators.
    ``connect_timeout_s`` bounds the TCP probe and the libfranka handshake each, ``command_timeout_s``
    any other call to the robot.

    Safety (checked before anything is sent, drivers/panda/safety.py): samples must stay
    ``joint_limit_margin_rad`` inside the position limits, within the velocity, acceleration and
    jerk limits (times ``1 + limit_tolerance`` for finite-difference round-off), the flange and
    camera inside ``workspace``, and the first sample within ``start_tolerance_rad`` of the arm.
    ``relative_dynamics_factor`` scales franky's (Ruckig's) limits: a trajectory faster than the
    scaled limits is slowed down along its waypoints, never sped up."""

    model_config = _STRICT

    host: str
    model: Literal["panda", "fr3"] = "panda"
    limits: ModelLimits = Field(default_factory=ModelLimits)
    realtime: bool = True
    connect_timeout_s: float = Field(3.0, gt=0.0, le=60.0)
    command_timeout_s: float = Field(10.0, gt=0.0, le=120.0)
    relative_dynamics_factor: float = Field(0.2, gt=0.0, le=1.0)
    collision: CollisionConfig = Field(default_factory=CollisionConfig)
    workspace: WorkspaceConfig = Field(default_factory=WorkspaceConfig)
    joint_limit_margin_rad: float = Field(0.05, ge=0.0, le=0.5)
    limit_tolerance: float = Field(0.01, ge=0.0, le=0.5)
    start_tolerance_rad: float = Field(0.05, gt=0.0, le=0.5)
    waypoint_period_s: float = Field(0.05, ge=0.001, le=1.0)
    monitor_period_s: float = Field(0.005, ge=0.001, le=0.1)
    settle_tolerance_rad: float = Field(0.002, gt=0.0, le=0.1)
    settle_timeout_s: float = Field(1.0, ge=0.0, le=10.0)
    hand_eye: HandEye
    urdf_path: str = PANDA_URDF

    @field_validator("host")
    @classmethod
    def _host(cls, v: str) -> str:
        v = v.strip()
        try:
            ipaddress.ip_address(v)
        except ValueError:
            if not _HOSTNAME.match(v):
                raise ValueError(f"host {v!r} is neither an IP address nor a hostname") from None
        return v

    @field_validator("urdf_path")
    @classmethod
    def _urdf(cls, v: str) -> str:
        if not Path(v).is_file():
            raise ValueError(f"urdf_path {v!r} does not exist")
        return v

    @model_validator(mode="after")
    def _margin_fits(self) -> "FrankaConfig":
        lim = self.active_limits
        span = np.asarray(lim.q_max) - np.asarray(lim.q_min)
        if np.any(span <= 2.0 * self.joint_limit_margin_rad):
            raise ValueError(f"joint_limit_margin_rad {self.joint_limit_margin_rad} leaves no range on some joint "
                             f"of the {self.model}")
        return self

    @property
    def active_limits(self) -> JointLimits:
        return getattr(self.limits, self.model)

    def T_flange_cam(self) -> np.ndarray:
        return self.hand_eye.T_flange_cam()

    @classmethod
    def from_yaml(cls, path: str | Path, key: str = "arm") -> "FrankaConfig":
        """The ``key:`` block of a cell YAML (other blocks, e.g. ``camera:``, are not ours to judge)."""
        wrapper = create_model("ArmBlock", __config__=ConfigDict(extra="ignore"), **{key: (cls, ...)})
        return getattr(load_yaml_model(path, wrapper, what=f"{key} block"), key)
