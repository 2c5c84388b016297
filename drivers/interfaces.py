"""The contracts every arm and camera honours, so the twin and real devices are interchangeable.

Frames and units: SI everywhere; poses are 4x4 float64 ``T_<to>_<from>``; camera optical frame is
z forward, x right, y down. Depth is float32 metres with NaN where the sensor gave no return.

Beyond ``Arm``, an arm may offer optional abilities (``Recoverable``, ``ContactLog``, ``MotionLog``,
``EventLog``, ``MotionCounter``): small protocols the scan checks once where it is wired
(``ArmAbilities.of``). ``ArmWrapper`` is the base of an arm that wraps another one and passes exactly
the wrapped arm's abilities on.
"""

from __future__ import annotations

import types
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Protocol, runtime_checkable

import numpy as np

from configs.lens import NO_DISTORTION, distorted


class DeviceError(RuntimeError):
    """A device is missing, disconnected or returned something unusable."""


class TrajectoryError(RuntimeError):
    """A trajectory was refused or its execution failed."""


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics of the (colour-aligned) depth image: the pinhole and the lens's distortion, as the
    device (or its .bag) reports it (librealsense's model name and five coefficients, configs/lens.py).
    Every pixel becomes a ray through ``configs.lens.deproject``; the twin's renderer is a pinhole."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str = "None"
    coeffs: tuple[float, ...] = NO_DISTORTION

    @property
    def distorted(self) -> bool:
        return distorted(self.model, self.coeffs)

    @property
    def lens(self) -> tuple[str, tuple[float, ...]] | None:
        """(model, coefficients) when the lens distorts, for ``planners.clouds``; None for a pinhole."""
        return (self.model, self.coeffs) if self.distorted else None

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass
class RGBDFrame:
    """One aligned color + depth capture."""

    color: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 metres, NaN = no return
    intrinsics: Intrinsics
    timestamp: float  # seconds, monotonic clock of the producer

    def __post_init__(self) -> None:
        h, w = self.intrinsics.height, self.intrinsics.width
        if self.color.shape != (h, w, 3) or self.color.dtype != np.uint8:
            raise DeviceError(f"color image must be ({h}, {w}, 3) uint8, got {self.color.shape} {self.color.dtype}")
        if self.depth.shape != (h, w) or self.depth.dtype != np.float32:
            raise DeviceError(f"depth image must be ({h}, {w}) float32, got {self.depth.shape} {self.depth.dtype}")


@dataclass
class JointTrajectory:
    """Time-parameterized joint path, sampled densely enough to follow by position control."""

    times: np.ndarray  # (T,) seconds from start, strictly increasing, times[0] == 0
    positions: np.ndarray  # (T, 7) radians
    velocities: np.ndarray | None = None  # (T, 7) rad/s

    @property
    def duration(self) -> float:
        return float(self.times[-1]) if len(self.times) else 0.0


@dataclass(frozen=True)
class ArmModel:
    """What planners need to know about an arm: its kinematics file and its limits."""

    urdf_path: str
    base_link: str
    flange_link: str  # the link the camera (and later the torch) is mounted on
    joint_names: tuple[str, ...]
    lower: np.ndarray = field(repr=False)
    upper: np.ndarray = field(repr=False)
    max_velocity: np.ndarray = field(repr=False)
    max_acceleration: np.ndarray = field(repr=False)
    max_jerk: np.ndarray = field(repr=False)
    T_flange_cam: np.ndarray = field(repr=False)  # hand-eye extrinsic


@runtime_checkable
class Arm(Protocol):
    model: ArmModel

    def joint_positions(self) -> np.ndarray:
        """Current joint angles (7,), radians. Non-blocking."""

    def execute(self, trajectory: JointTrajectory) -> float:
        """Follow a trajectory; blocks until done. Returns the max joint tracking error (rad).
        Raises TrajectoryError if refused or aborted."""

    def stop(self) -> None:
        """Stop any motion as soon as possible."""

    def camera_pose(self) -> np.ndarray:
        """T_base_cam from the arm's own forward kinematics and the hand-eye extrinsic."""


@runtime_checkable
class RGBDCamera(Protocol):
    intrinsics: Intrinsics

    def capture(self) -> RGBDFrame:
        """Block until the next frame; raises DeviceError on timeout or a broken device."""


# --- optional abilities ---------------------------------------------------------------------------
# What some arms offer beyond ``Arm`` and the scan uses when it is there. Each is checked once where
# the devices are wired (``ArmAbilities.of``, ``isinstance``), never probed with getattr in the loop.
# An implementation declares the ones it has among its bases; a wrapper (``ArmWrapper``) offers exactly
# the ones of the arm it wraps.


@runtime_checkable
class Recoverable(Protocol):
    """Refuses motions after a fault until recovered (a Franka after a reflex or a lost connection): the
    scan recovers it after an error, so the cell can take the next job."""

    needs_recovery: str | None  # why the arm refuses motions until recover(); None: ready

    def recover(self) -> dict:
        """Clear the fault (reconnecting first if the connection died); returns the event it logged."""


@runtime_checkable
class ContactLog(Protocol):
    """Reports the robot-scene contacts of its last motion (the twin's own check): the scan records them
    for every move and every phase of the cut's dry run."""

    last_motion_contacts: list[dict]


@runtime_checkable
class MotionLog(Protocol):
    """Keeps the joints commanded and measured during its last motion: the cut's dry run measures how
    well the torch tip followed the cut from them, and the fcisim twin replays the measured ones."""

    last_motion_desired: np.ndarray  # (T, 7) radians
    last_motion_actual: np.ndarray  # (T, 7) radians, NaN where no sample was taken


@runtime_checkable
class EventLog(Protocol):
    """Logs its own refusals, reflexes, connection losses and recoveries, oldest first: the job copies the
    entries made while it ran into its result."""

    events: list[dict]


@runtime_checkable
class MotionCounter(Protocol):
    """Counts the motions it handed to the robot (a refused trajectory moves nothing and does not count):
    the fcisim twin replays a motion only when one happened."""

    motions_sent: int


@dataclass(frozen=True)
class ArmAbilities:
    """The optional abilities of one arm, found once where it is wired (``of``): each is the arm itself,
    typed as that ability, or None when it lacks it."""

    recovery: Recoverable | None = None
    contacts: ContactLog | None = None
    motion_log: MotionLog | None = None
    events: EventLog | None = None

    @classmethod
    def of(cls, arm: object) -> "ArmAbilities":
        return cls(recovery=arm if isinstance(arm, Recoverable) else None,
                   contacts=arm if isinstance(arm, ContactLog) else None,
                   motion_log=arm if isinstance(arm, MotionLog) else None,
                   events=arm if isinstance(arm, EventLog) else None)


# The mixins that pass each ability on to the arm a wrapper holds in ``self._arm`` (read-only: what the
# wrapper reads is always the wrapped arm's current value).
class _ForwardsRecovery(Recoverable):
    needs_recovery = property(lambda self: self._arm.needs_recovery)

    def recover(self) -> dict:
        return self._arm.recover()


class _ForwardsContactLog(ContactLog):
    last_motion_contacts = property(lambda self: self._arm.last_motion_contacts)


class _ForwardsMotionLog(MotionLog):
    last_motion_desired = property(lambda self: self._arm.last_motion_desired)
    last_motion_actual = property(lambda self: self._arm.last_motion_actual)


class _ForwardsEventLog(EventLog):
    events = property(lambda self: self._arm.events)


class _ForwardsMotionCounter(MotionCounter):
    motions_sent = property(lambda self: self._arm.motions_sent)


#: each optional ability, and the mixin that passes it on to a wrapper's ``self._arm``
ABILITY_FORWARDERS: dict[type, type] = {Recoverable: _ForwardsRecovery, ContactLog: _ForwardsContactLog,
                                        MotionLog: _ForwardsMotionLog, EventLog: _ForwardsEventLog,
                                        MotionCounter: _ForwardsMotionCounter}


class ArmWrapper(Arm):
    """Base of an arm wrapping another one (``self._arm``): passes the ``Arm`` protocol on (a subclass
    overrides what it changes) and, when constructed, becomes the subclass that also passes on each
    optional ability the wrapped arm has (the mixins of ``ABILITY_FORWARDERS``), and no other, so
    ``isinstance(wrapper, Recoverable)`` is true exactly when the wrapped arm is. An ability the wrapper
    class declares among its own bases is its own and is not forwarded."""

    _arm: Arm

    def __new__(cls, arm: Arm, *args, **kwargs):
        base = cls.__dict__.get("_forwarding_base", cls)  # cls may be a class picked for another arm
        passed = tuple(p for p in ABILITY_FORWARDERS if p not in base.__mro__ and isinstance(arm, p))
        self = super().__new__(_forwarding_class(base, passed))
        if not isinstance(self, cls):  # not a cls, so Python will not call __init__ itself
            self.__init__(arm, *args, **kwargs)
        return self

    def __init__(self, arm: Arm) -> None:
        self._arm = arm
        self.model: ArmModel = arm.model

    def joint_positions(self) -> np.ndarray:
        return self._arm.joint_positions()

    def execute(self, trajectory: JointTrajectory) -> float:
        return self._arm.execute(trajectory)

    def stop(self) -> None:
        self._arm.stop()

    def camera_pose(self) -> np.ndarray:
        return self._arm.camera_pose()


@lru_cache(maxsize=None)
def _forwarding_class(base: type, abilities: tuple[type, ...]) -> type:
    """``base`` plus the forwarding mixin of each ability, e.g. ``FaultyArm[ContactLog, MotionLog]``."""
    if not abilities:
        return base
    name = f"{base.__name__}[{', '.join(p.__name__ for p in abilities)}]"

    def body(ns: dict) -> None:
        ns.update(__module__=base.__module__, __qualname__=name, __doc__=base.__doc__, _forwarding_base=base)

    return types.new_class(name, (base, *(ABILITY_FORWARDERS[p] for p in abilities)), exec_body=body)
