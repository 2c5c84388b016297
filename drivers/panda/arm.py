"""The real Franka arm (Panda or FR3) behind ``drivers.interfaces.Arm``, through franky
(libfranka + Ruckig).

``FrankaArm(config)`` connects with a bounded timeout (a plain TCP probe of the FCI port first, so an
unreachable host or an inactive FCI fails in ``connect_timeout_s`` with a message saying which,
instead of libfranka's 60 s), then applies the configured joint limits, relative dynamics factor and
collision thresholds. ``execute()`` refuses a trajectory with the checks of safety.py before anything
is sent, then sends it as franky joint waypoints (position + velocity, minimum time = our timing), so
Ruckig follows our samples within our limits; it polls the robot state to measure tracking and waits
for the arm to settle. ``stop()`` replaces the motion by a Ruckig stop motion. A reflex or a lost
connection leaves the arm refusing motions until ``recover()`` (franky's ``recover_from_errors``,
reconnecting first if the connection died); every refusal, abort and recovery is appended to
``events`` (and handed to ``on_event``) for the job to record.

Never imports planners/, cellctl/ or sim/ (kinematics: drivers/panda/safety.py, Pinocchio).
"""

from __future__ import annotations

import gc
import logging
import os
import queue
import re
import socket
import struct
import threading
import time
import weakref
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Callable

import franky
import numpy as np

from drivers.interfaces import (Arm, ArmModel, DeviceError, EventLog, JointTrajectory, MotionCounter, MotionLog,
                                Recoverable, TrajectoryError)
from drivers.panda.config import BASE_LINK, FCI_PORT, FLANGE_LINK, JOINT_NAMES, FrankaConfig
from configs.chain import Chain
from drivers.panda.safety import CheckedTrajectory, SafetyChecker, derivatives

log = logging.getLogger(__name__)

DESK_PORT = 443  # Franka Desk (HTTPS): answers when the controller is up, with or without FCI
KINEMATICS_TOLERANCE_M = 0.002  # our URDF's flange vs the robot's own O_T_EE * F_T_EE^-1
KINEMATICS_TOLERANCE_RAD = 0.01
SETTLED_SPEED = 2e-3  # rad/s on every joint: the controller holds its final (steady-state) error


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class ArmStatus:
    """What the service shows for the arm: ready or not, and why."""

    ready: bool
    message: str


def _connect(host: str, port: int, timeout: float) -> socket.socket | str:
    """A TCP connection, or why there is none ("timeout", "refused", text)."""
    try:
        return socket.create_connection((host, port), timeout=timeout)
    except (socket.timeout, TimeoutError):
        return "timeout"
    except ConnectionRefusedError:
        return "refused"
    except socket.gaierror as e:
        return f"cannot resolve: {e.strerror or e}"
    except OSError as e:
        return e.strerror or str(e)


def _probe_port(host: str, port: int, timeout: float) -> str | None:
    """None if something accepts TCP on host:port; otherwise why not ("timeout", "refused", text)."""
    s = _connect(host, port, timeout)
    if isinstance(s, str):
        return s
    s.close()
    return None


def _server_version(host: str, timeout: float) -> int | str:
    """The robot server's protocol version, or why there is none ("timeout", "refused",
    "no-handshake", text). One libfranka Connect request (12-byte header command/id/size, then
    version and UDP port, little endian: the same from server version 2 to 10) with version 0, which
    a Franka controller answers with "incompatible" and its own version without opening a session;
    franky-sim answers every request."""
    s = _connect(host, FCI_PORT, timeout)
    if isinstance(s, str):
        return s
    with s, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("", 0))  # a real port in case the server starts streaming state
        data = b""
        try:
            s.settimeout(timeout)
            s.sendall(struct.pack("<IIIHH", 0, 1, 16, 0, udp.getsockname()[1]))
            while len(data) < 16:
                chunk = s.recv(16 - len(data))
                if not chunk:
                    return "closed the connection without answering the libfranka handshake"
                data += chunk
        except (socket.timeout, TimeoutError):
            return "no-handshake"
        except OSError as e:
            return f"the libfranka handshake failed: {e.strerror or e}"
    command, command_id, _size, _status, version = struct.unpack("<IIIHH", data)
    if command != 0 or command_id != 1 or not 1 <= version < 1000:
        return f"answered something else than libfranka's protocol ({data.hex()})"
    return version


def preflight(host: str, timeout: float) -> int:
    """Fail fast, with a message an operator can act on, unless a Franka controller answers the
    libfranka handshake on the FCI port (connect and answer each bounded by ``timeout``). Returns
    its robot server version. libfranka itself is never started against a host that does not
    answer: its own handshake waits 60 s (and spins at real-time priority meanwhile)."""
    v = _server_version(host, timeout)
    if isinstance(v, int):
        return v
    if v == "timeout":
        raise DeviceError(
            f"Franka at {host} is unreachable: no answer on the FCI port {FCI_PORT} within {timeout:.1f} s "
            f"(robot powered? network cable? this PC on the robot's subnet? arm.host right?)")
    if v == "refused":
        desk = _probe_port(host, DESK_PORT, min(timeout, 1.0)) is None
        hint = ("Desk answers on port 443: open Desk, unlock the joints and activate FCI" if desk else
                "nothing answers on port 443 either: is arm.host the controller's address?")
        raise DeviceError(f"Franka at {host}: connection to the FCI port {FCI_PORT} refused: "
                          f"FCI is not active ({hint})")
    if v == "no-handshake":
        raise DeviceError(f"Franka at {host} is unreachable as a robot: TCP port {FCI_PORT} accepts connections "
                          f"but the libfranka handshake got no answer within {timeout:.1f} s (wrong address "
                          f"behind a firewall or proxy? another FCI client connected?)")
    raise DeviceError(f"Franka at {host} is unreachable: {v}")


def model_of_server_version(version: int) -> str:
    """Robot server versions <= 5 are the Panda's (system <= 4.2, libfranka <= 0.9); the FR3 started at 6."""
    return "panda" if version <= 5 else "fr3"


def checked_server_version(cfg: FrankaConfig) -> int:
    """``preflight``, and the robot it finds is the model the config names (DeviceError if not)."""
    version = preflight(cfg.host, cfg.connect_timeout_s)
    if model_of_server_version(version) != cfg.model:
        which = "an FR3" if model_of_server_version(version) == "fr3" else "a Panda"
        raise DeviceError(f"Franka at {cfg.host} speaks robot server version {version}, so it is {which}, "
                          f"but arm.model is {cfg.model!r}: its limits would be wrong")
    return version


def _explain_connect_error(host: str, e: BaseException) -> str:
    name, msg = type(e).__name__, str(e)
    if name == "IncompatibleVersionException":
        m = re.search(r"server version: (\d+)", msg)
        server = f"robot server version {m.group(1)}" if m else "the robot"
        return (f"Franka at {host}: {msg}. This franky wheel speaks another libfranka protocol than {server}: "
                f"a Panda (system 4.x, server 5) needs franky built for libfranka 0.9.x, an FR3 one for "
                f"libfranka >= 0.10 matching its system version (docs/HARDWARE.md)")
    if name == "RealtimeException":
        return (f"Franka at {host}: {msg}: libfranka needs real-time scheduling (PREEMPT_RT kernel, the user in "
                f"the realtime group, docs/HARDWARE.md); arm.realtime: false only for a simulator")
    if "refused" in msg.lower():
        return f"Franka at {host}: {msg} (FCI is not active: activate it in Desk)"
    return f"Franka at {host}: connecting failed: {name}: {msg}"


class _Owner:
    """The one thread that talks to libfranka. Why a thread of its own: libfranka's Robot constructor
    raises the constructing thread to SCHED_FIFO when it may (always on the real cell PC, where
    ``realtime`` is enforced), and franky's 1 kHz control thread inherits the scheduling of the thread
    that calls move(). Constructed elsewhere, the control loop runs at normal priority and misses
    cycles under load (measured on franky-sim: 2-27 ms gaps, motions up to 50 % late); constructed in
    the caller's thread, that thread (e.g. a service's main thread) would become real-time. One owner
    also serializes the calls, which libfranka requires (concurrent reads are refused)."""

    def __init__(self, name: str) -> None:
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            fn, fut = item
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn())
                except BaseException as e:  # noqa: BLE001 - handed to the caller
                    fut.set_exception(e)

    def call(self, fn: Callable, timeout: float):
        """fn() on the owner thread; its exception re-raised here; _Timeout if it takes longer."""
        fut: Future = Future()
        self._q.put((fn, fut))
        try:
            return fut.result(timeout)
        except FutureTimeout:
            if not fut.done():
                fut.cancel()
                raise _Timeout() from None
            return fut.result()

    def close(self) -> None:
        self._q.put(None)

    def demote(self) -> None:
        """Back to normal scheduling: a libfranka call stuck past our timeout must not hold a core
        at real-time priority until libfranka gives up."""
        tid = self._thread.native_id
        try:
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, tid, 19)
        except (OSError, AttributeError, TypeError):
            pass


class _Timeout(Exception):
    """A call to the robot got no answer in time (the owner thread is stuck in libfranka)."""


class FrankaArm(Arm, Recoverable, EventLog, MotionLog, MotionCounter):
    """The real arm (implements ``drivers.interfaces.Arm``). Use as a context manager or ``close()``.
    Thread-safe: joint_positions()/camera_pose()/stop() may be called while execute() runs. Optional
    abilities: ``recover()`` after a reflex or a lost connection (``Recoverable``), its own ``events``
    (``EventLog``), the joints commanded and measured during the last motion (``MotionLog``) and the
    motions handed to the robot (``MotionCounter``)."""

    def __init__(self, config: FrankaConfig, *, connect: bool = True) -> None:
        self.config = config
        self.safety = SafetyChecker(config)
        self._link8 = Chain.from_urdf(config.urdf_path, JOINT_NAMES, "panda_link8")
        lim = config.active_limits
        self.model = ArmModel(
            urdf_path=config.urdf_path,
            base_link=BASE_LINK,
            flange_link=FLANGE_LINK,
            joint_names=JOINT_NAMES,
            # what a planner may use: the published limits less the margin execute() enforces
            lower=_readonly(self.safety.lower),
            upper=_readonly(self.safety.upper),
            max_velocity=_readonly(lim.max_velocity),
            max_acceleration=_readonly(lim.max_acceleration),
            max_jerk=_readonly(lim.max_jerk),
            T_flange_cam=_readonly(config.T_flange_cam()),
        )
        self._owner: _Owner | None = None
        #: the controller's libfranka protocol version (<= 5: Panda, >= 6: FR3), once connected
        self.server_version: int | None = None
        self._robot: franky.Robot | None = None  # touched on the owner thread only
        self._broken = False  # the connection died: recover() reconnects
        self._motion = threading.Lock()  # one execute()/recover() at a time
        self._stop = threading.Event()
        self._dynamics_factor = config.relative_dynamics_factor
        self._robot_limits = tuple(np.asarray(x, dtype=np.float64) for x in
                                   (lim.max_velocity, lim.max_acceleration, lim.max_jerk))  # as set in franky
        #: why the arm refuses motions until recover() (None: ready)
        self.needs_recovery: str | None = None
        #: refusals, aborts, reflexes, connection losses and recoveries, oldest first (the job records them)
        self.events: list[dict] = []
        #: called with each new event (errors in the callback are logged, never raised)
        self.on_event: Callable[[dict], None] | None = None
        #: motions handed to the robot (refused trajectories never count)
        self.motions_sent = 0
        #: the last execute(): summary, robot times (s) and the joints commanded (q_d) and measured (q)
        self.last_motion: dict = {}
        self.last_motion_times = np.zeros(0)
        self.last_motion_desired = np.zeros((0, 7))
        self.last_motion_actual = np.zeros((0, 7))
        if connect:
            self.connect()

    # ------------------------------------------------------------------ connection
    @property
    def connected(self) -> bool:
        return self._robot is not None and not self._broken

    def connect(self) -> None:
        """Connect and apply the configured limits; the TCP probe and the libfranka handshake are each
        bounded by ``connect_timeout_s``. DeviceError says what is wrong: unreachable host, FCI
        inactive, version mismatch, model mismatch (a Panda configured as FR3 or the reverse), or the
        robot's kinematics disagreeing with the URDF the safety checks use."""
        if self._robot is not None:
            return
        cfg = self.config
        self.server_version = checked_server_version(cfg)
        rt = franky.RealtimeConfig.Enforce if cfg.realtime else franky.RealtimeConfig.Ignore
        owner = _Owner(f"franky-{cfg.host}")

        try:
            robot = owner.call(lambda: franky.Robot(cfg.host, realtime_config=rt), cfg.connect_timeout_s)
        except _Timeout:
            owner.demote()
            owner.close()  # the thread ends when libfranka gives up (60 s)
            raise DeviceError(f"Franka at {cfg.host}: the FCI port answers but the libfranka handshake did not "
                              f"complete within {cfg.connect_timeout_s:.1f} s (another client connected?)") from None
        except Exception as e:  # noqa: BLE001 - franky's exception classes are unrelated
            owner.close()
            raise DeviceError(_explain_connect_error(cfg.host, e)) from e
        self._owner, self._robot, self._broken = owner, robot, False
        weakref.finalize(self, owner.close)  # an arm dropped without close() does not leak its thread
        del robot  # the owner thread drops the last reference (libfranka disconnects in the destructor)
        try:
            why = self._call(lambda r: _model_mismatch(cfg, r), "reading the robot model")
            if why:
                raise DeviceError(f"Franka at {cfg.host}: {why}")
            self.configure()
            self._check_kinematics()
        except BaseException:
            self._disconnect()
            raise
        self._record("connected", f"{cfg.model} at {cfg.host}")

    def configure(self) -> None:
        """Apply relative dynamics factor, joint limits and collision thresholds (also after a reconnect)."""
        cfg, lim = self.config, self.config.active_limits
        factor = self._dynamics_factor

        def apply(r: "franky.Robot") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            r.relative_dynamics_factor = factor
            # franky refuses values above Franka's maxima: ours may be the FR3's, larger on some joints
            v = np.minimum(lim.max_velocity, r.joint_velocity_limit.max)
            a = np.minimum(lim.max_acceleration, r.joint_acceleration_limit.max)
            j = np.minimum(lim.max_jerk, r.joint_jerk_limit.max)
            r.joint_velocity_limit.set(v)
            r.joint_acceleration_limit.set(a)
            r.joint_jerk_limit.set(j)
            c = cfg.collision
            r.set_collision_behavior(c.lower_torque_nm, c.upper_torque_nm, c.lower_force_n, c.upper_force_n)
            return v, a, j

        self._robot_limits = self._call(apply, "applying limits and collision thresholds")

    @property
    def relative_dynamics_factor(self) -> float:
        return self._dynamics_factor

    @relative_dynamics_factor.setter
    def relative_dynamics_factor(self, value: float) -> None:
        """Speed scaling of franky's velocity, acceleration and jerk limits, in (0, 1]; between motions."""
        value = float(value)
        if not (0.0 < value <= 1.0):
            raise ValueError(f"relative_dynamics_factor must be in (0, 1], got {value}")
        if not self._motion.acquire(blocking=False):
            raise TrajectoryError("cannot change the speed while a trajectory is executing")
        try:
            self._dynamics_factor = value
            if self._robot is not None:
                self._call(lambda r: setattr(r, "relative_dynamics_factor", value), "setting the speed")
        finally:
            self._motion.release()

    @property
    def robot(self) -> "franky.Robot":
        """The underlying franky.Robot, for diagnostics only: calls on it bypass the owner thread and
        every check here."""
        if self._robot is None:
            raise DeviceError(f"Franka at {self.config.host} is not connected")
        return self._robot

    def close(self) -> None:
        """Stop any motion and disconnect (libfranka closes the connection when the Robot is destroyed)."""
        self._stop.set()
        with self._motion:
            self._disconnect()

    def __enter__(self) -> "FrankaArm":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ Arm protocol
    def joint_positions(self) -> np.ndarray:
        """Current joint angles (7,), radians (the last state libfranka received)."""
        return self._call(lambda r: np.array(r.current_joint_positions, dtype=np.float64), "reading the joints")

    def camera_pose(self) -> np.ndarray:
        """T_base_cam: forward kinematics of the URDF at the measured joints, then the hand-eye extrinsic."""
        return self.safety.camera_poses(self.joint_positions()[None])[0]

    def flange_pose(self) -> np.ndarray:
        """T_base_flange (panda_hand) at the measured joints."""
        return self.safety.flange_poses(self.joint_positions()[None])[0]

    def execute(self, trajectory: JointTrajectory) -> float:
        """Follow ``trajectory``; blocks until the arm has settled on its last sample. Returns the
        max joint tracking error (rad): the robot's commanded vs measured joints while moving, and
        the remaining error after settling. Refused (TrajectoryError, nothing sent) by safety.py's
        checks, a first sample more than ``start_tolerance_rad`` from the arm, or a pending
        recover(); aborted (TrajectoryError) by stop(), a reflex or a lost connection."""
        try:
            checked = self.safety.check(trajectory)
        except TrajectoryError as e:
            self._record("refused", str(e))
            raise
        if not self._motion.acquire(blocking=False):
            raise TrajectoryError("another trajectory is executing")
        try:
            if self.needs_recovery:
                raise self._refuse(f"the arm needs recover() first ({self.needs_recovery})")
            q_now = self.joint_positions()
            gap = np.abs(checked.positions[0] - q_now)
            if np.max(gap) > self.config.start_tolerance_rad:
                j = int(np.argmax(gap))
                raise self._refuse(f"start: sample 0, joint {j + 1} is {gap[j]:.3f} rad from the arm "
                                   f"(tolerance {self.config.start_tolerance_rad} rad)")
            scale = self._time_scale(checked)
            motion = self._waypoints(checked, scale)
            self._stop.clear()
            return self._run(motion, checked, scale)
        finally:
            self._motion.release()

    def stop(self) -> None:
        """Stop a running execute() as soon as possible: within one monitor period it is replaced by
        a Ruckig stop motion (decelerates within the limits) and raises TrajectoryError. Idle: no-op."""
        self._stop.set()

    # ------------------------------------------------------------------ recovery
    def recover(self) -> dict:
        """Clear a reflex (franky ``recover_from_errors``), reconnecting first if the connection died,
        and re-apply the limits. Returns the event recorded. DeviceError if the robot cannot be
        reached or refuses (e.g. the emergency stop is still pressed)."""
        if not self._motion.acquire(timeout=self.config.command_timeout_s):
            raise DeviceError("recover() while a trajectory is executing: stop() it first")
        try:
            cause = self.needs_recovery or "nothing pending"
            reconnected = False
            if self._robot is None or self._broken:
                self._reconnect()
                reconnected = True
            try:
                errors, ok = self._call(lambda r: (str(r.state.last_motion_errors), bool(r.recover_from_errors())),
                                        "automatic error recovery")
            except DeviceError:
                if not self._broken:
                    raise
                self._reconnect()  # the connection died under us after all
                reconnected = True
                errors, ok = self._call(lambda r: (str(r.state.last_motion_errors), bool(r.recover_from_errors())),
                                        "automatic error recovery")
            if not ok:
                self._record("recovery_failed", f"after {cause}", errors=errors)
                raise DeviceError(f"Franka at {self.config.host}: automatic error recovery failed "
                                  f"({errors or 'no error reported'}): check the emergency stop and Desk")
            self.configure()
            self.needs_recovery = None
            return self._record("recovered", f"after {cause}", reconnected=reconnected, errors=errors)
        finally:
            self._motion.release()

    # ------------------------------------------------------------------ internals
    def _call(self, fn: Callable, what: str, timeout: float | None = None):
        """fn(robot) on the owner thread. Not connected, no answer in time, or a network failure:
        DeviceError (and the connection counts as broken). Other franky errors are re-raised."""
        owner, cfg = self._owner, self.config
        if owner is None or self._robot is None:
            raise DeviceError(f"Franka at {cfg.host} is not connected")
        try:
            return owner.call(lambda: fn(self._robot), cfg.command_timeout_s if timeout is None else timeout)
        except _Timeout:
            self._broken = True
            waited = cfg.command_timeout_s if timeout is None else timeout
            raise DeviceError(f"Franka at {cfg.host}: {what}: no answer within {waited:.1f} s") from None
        except Exception as e:  # noqa: BLE001
            if _is_network_error(e):
                self._broken = True
                raise DeviceError(f"Franka at {cfg.host}: {what}: connection lost ({type(e).__name__}: {e})") from e
            raise

    def _disconnect(self) -> None:
        owner, self._owner = self._owner, None
        if owner is None:
            self._robot = None
            return

        def drop() -> None:
            self._robot = None
            gc.collect()  # libfranka disconnects in the destructor

        try:
            owner.call(drop, self.config.command_timeout_s)
        except Exception:  # noqa: BLE001 - disconnecting is best effort
            self._robot = None
        owner.close()

    def _reconnect(self) -> None:
        self._disconnect()
        self.connect()
        self._record("reconnected", f"{self.config.model} at {self.config.host}")

    def _record(self, kind: str, message: str, **extra) -> dict:
        event = {"time": _now(), "kind": kind, "message": message, **extra}
        self.events.append(event)
        (log.info if kind in ("connected", "reconnected", "recovered") else log.warning)("franka %s: %s", kind, message)
        if self.on_event is not None:
            try:
                self.on_event(event)
            except Exception:  # noqa: BLE001 - a recorder bug must not break the arm
                log.exception("on_event callback failed")
        return event

    def _refuse(self, message: str) -> TrajectoryError:
        self._record("refused", message)
        return TrajectoryError(message)

    def _check_kinematics(self) -> None:
        """Our URDF must agree with the robot's own kinematics, or the workspace check means nothing."""
        def read(r: "franky.Robot"):  # the commanded pair: no measurement noise between q and the pose
            s = r.state
            return s.O_T_EE_d.matrix, s.F_T_EE.matrix, np.array(s.q_d)

        O_T_EE, F_T_EE, q = self._call(read, "reading the robot state")
        robot_flange = O_T_EE @ np.linalg.inv(F_T_EE)
        ours = self._link8.poses(q[None])[0]
        dp = float(np.linalg.norm(robot_flange[:3, 3] - ours[:3, 3]))
        dR = float(np.arccos(np.clip((np.trace(robot_flange[:3, :3].T @ ours[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
        if dp > KINEMATICS_TOLERANCE_M or dR > KINEMATICS_TOLERANCE_RAD:
            raise DeviceError(f"Franka at {self.config.host}: the robot's flange pose differs from "
                              f"{self.config.urdf_path} by {dp * 1000:.1f} mm / {np.degrees(dR):.2f} deg at "
                              f"q={np.round(q, 3).tolist()}: wrong URDF")

    def _time_scale(self, tr: CheckedTrajectory) -> float:
        """Speed scaling: >= 1, the uniform slow-down that keeps the trajectory within franky's
        limits times ``relative_dynamics_factor`` (velocity ~ 1/s, acceleration ~ 1/s^2, jerk ~ 1/s^3),
        plus 2 %. The path stays ours; only time stretches (Ruckig refuses waypoint velocities above
        its scaled limits, and would otherwise lag behind our timing unevenly)."""
        if len(tr.times) < 2:
            return 1.0
        v, a, j = (np.max(np.abs(d), axis=0) for d in derivatives(tr.times, tr.positions))
        lv, la, lj = (self._dynamics_factor * x for x in self._robot_limits)
        s = max(float(np.max(v / lv)), float(np.max(a / la)) ** 0.5, float(np.max(j / lj)) ** (1.0 / 3.0))
        return 1.0 if s <= 1.0 else 1.02 * s

    def _waypoints(self, tr: CheckedTrajectory, scale: float = 1.0) -> "franky.JointWaypointMotion":
        """Our samples every ``waypoint_period_s`` (and the last) as franky waypoints: position,
        velocity from the positions (central differences: a given velocity that disagreed with the
        positions would make Ruckig swing where the checks did not look), minimum time = our time
        (times ``scale``) since the previous waypoint, in franky's whole milliseconds (rounded
        cumulatively)."""
        times, q = tr.times * scale, tr.positions
        v = np.gradient(q, times, axis=0) if len(times) > 1 else np.zeros_like(q)
        v[-1] = 0.0  # execute() ends at rest
        slot = np.floor(tr.times / self.config.waypoint_period_s + 1e-9)  # keep the first sample of each slot
        keep = np.concatenate([[len(times) == 1], slot[1:] != slot[:-1]])  # the start is where the arm is
        keep[-1] = True
        idx = np.flatnonzero(keep)
        ms = np.round(times[idx] * 1000.0).astype(np.int64)
        dms = np.maximum(np.diff(np.concatenate([[0], ms])), 1)
        return franky.JointWaypointMotion([
            franky.JointWaypoint(franky.JointState(q[i], v[i]), minimum_time=franky.Duration(int(d)))
            for i, d in zip(idx, dms)])

    def _run(self, motion: "franky.JointWaypointMotion", tr: CheckedTrajectory, scale: float) -> float:
        cfg = self.config
        period = cfg.monitor_period_s
        times_l, qd_l, q_l = [], [], []
        stopping = False

        def start(r: "franky.Robot") -> float:
            t0 = r.state.time.to_sec()
            r.move(motion, asynchronous=True)
            return t0

        def poll(r: "franky.Robot"):
            done = r.join_motion(timeout=period)
            s = r.state
            return done, s.time.to_sec(), np.array(s.q_d), np.array(s.q)

        try:
            t0 = self._call(start, "starting the motion")
            self.motions_sent += 1
            while True:
                if self._stop.is_set() and not stopping:
                    self._call(lambda r: r.move(franky.JointStopMotion(), asynchronous=True), "stopping")
                    stopping = True
                done, t, qd, q = self._call(poll, "following the motion", timeout=period + cfg.command_timeout_s)
                times_l.append(t - t0)
                qd_l.append(qd)
                q_l.append(q)
                if done:
                    break
        except Exception as e:  # noqa: BLE001 - franky's exception classes are unrelated
            self._keep(times_l, qd_l, q_l, tr, stopping, scale)
            raise self._aborted(e, stopping) from e
        track = self._keep(times_l, qd_l, q_l, tr, stopping, scale)
        if stopping:
            self._record("stopped", f"at t={self.last_motion['duration_s']:.3f} s of {tr.times[-1]:.3f} s")
            raise TrajectoryError(f"execution stopped at t={self.last_motion['duration_s']:.3f} s "
                                  f"of {tr.times[-1]:.3f} s")
        # settle on the last sample (the controller's lag): until close, at rest, or the timeout
        target, deadline = tr.positions[-1], time.monotonic() + cfg.settle_timeout_s

        def joints(r: "franky.Robot"):
            s = r.state
            return np.array(s.q), np.array(s.dq)

        while True:
            q, dq = self._call(joints, "reading the joints")
            final = float(np.max(np.abs(q - target)))
            if (final < cfg.settle_tolerance_rad or np.max(np.abs(dq)) < SETTLED_SPEED
                    or time.monotonic() >= deadline or self._stop.is_set()):
                break
            time.sleep(period)
        self.last_motion["final_error_rad"] = final
        return max(track, final)

    def _keep(self, times_l, qd_l, q_l, tr: CheckedTrajectory, stopped: bool, scale: float) -> float:
        t = np.asarray(times_l, dtype=np.float64)
        qd = np.asarray(qd_l, dtype=np.float64).reshape(-1, 7)
        q = np.asarray(q_l, dtype=np.float64).reshape(-1, 7)
        self.last_motion_times, self.last_motion_desired, self.last_motion_actual = t, qd, q
        track = float(np.max(np.abs(qd - q))) if len(q) else 0.0
        # against our own timing, stretched by the speed scaling
        ours = np.column_stack([np.interp(t, tr.times * scale, tr.positions[:, j]) for j in range(7)]) if len(t) else q
        self.last_motion = {"planned_s": float(tr.times[-1]), "time_scale": scale,
                            "duration_s": float(t[-1]) if len(t) else 0.0,
                            "max_tracking_rad": track,
                            "max_deviation_from_plan_rad": float(np.max(np.abs(q - ours))) if len(q) else 0.0,
                            "polls": int(len(t)), "stopped": stopped}
        return track

    def _aborted(self, e: BaseException, stopping: bool) -> TrajectoryError:
        name, msg = type(e).__name__, str(e)
        if isinstance(e, DeviceError) or _is_network_error(e):
            self._broken = True
            self.needs_recovery = f"connection lost: {msg}"
            self._record("connection_lost", msg)
            return TrajectoryError(f"connection lost during the motion: {msg}; recover() reconnects")
        if stopping and name == "ControlException":
            self._record("stopped", msg)
            return TrajectoryError(f"execution stopped: {msg}")
        kind = "reflex" if "reflex" in msg.lower() else "control_error"
        errors = ""
        try:
            errors = self._call(lambda r: str(r.state.last_motion_errors), "reading the errors")
        except Exception:  # noqa: BLE001 - best effort, the abort is what matters
            pass
        self.needs_recovery = f"{kind}: {msg}"
        self._record(kind, msg, errors=errors)
        detail = f"; errors {errors}" if errors else ""
        return TrajectoryError(f"motion aborted by the robot ({kind}: {name}: {msg}{detail}); recover() clears it")


def _is_network_error(e: BaseException) -> bool:
    # franky.NetworkException; a Poco "Net Exception" (RuntimeError) once the socket is gone
    return type(e).__name__ == "NetworkException" or (type(e) is RuntimeError and "net" in str(e).lower())


def _model_mismatch(config: FrankaConfig, robot: "franky.Robot") -> str | None:
    try:
        urdf = robot.model_urdf  # libfranka >= 0.15 (FR3); the Panda builds (0.9.x) do not have it
    except Exception:  # noqa: BLE001
        return None
    m = re.search(r'<robot\s+name="([^"]+)"', urdf or "")
    if not m:
        return None
    name = m.group(1).lower()
    is_fr3 = "fr3" in name
    is_panda = "panda" in name or name.startswith("fer")
    if is_fr3 and config.model != "fr3" or is_panda and config.model != "panda":
        return f"the robot reports model {m.group(1)!r} but arm.model is {config.model!r}: its limits would be wrong"
    return None


def probe(config: FrankaConfig, *, full: bool = True) -> ArmStatus:
    """What the service reports for the arm, never an exception. ``full``: connect once through libfranka
    and disconnect (a session: the controller's one FCI client for that while). Not ``full``: only the
    handshake ``preflight`` sends, which a controller answers without opening a session, so a cell can
    ask every few seconds while idle without disturbing the arm (or someone else's FCI client); the
    full check then happens when a job opens the arm."""
    if not full:
        try:
            v = checked_server_version(config)
            return ArmStatus(True, f"{config.model} at {config.host} answers with FCI active (robot server version "
                                   f"{v}); the full check is at job start")
        except DeviceError as e:
            return ArmStatus(False, str(e))
    try:
        with FrankaArm(config) as arm:
            q = arm.joint_positions()
        return ArmStatus(True, f"{config.model} at {config.host} ready, joints {np.round(q, 3).tolist()}")
    except DeviceError as e:
        return ArmStatus(False, str(e))
