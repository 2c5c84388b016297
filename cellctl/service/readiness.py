"""Whether the cell could start a job now, kept current: fcisim and real probe their arm and camera at
start, every READINESS_PERIOD_S while idle and at once when poked (a refused submit, a finished job), so
a robot switched on or a camera unplugged shows in the status. The probe does not disturb the arm: it
sends only libfranka's version handshake, which the controller answers without opening a session
(``drivers.panda.probe(full=False)``); the full connection is made by the job that opens the arm. The
devices have one holder at a time, so a probe never runs while a job holds them (``held``)."""

from __future__ import annotations

import logging
import threading

from cellctl.config import CellConfig
from cellctl.scan.devices import Readiness, check_readiness
from cellctl.scan.modes import DeviceMode

log = logging.getLogger("cellctl.service.readiness")
READINESS_PERIOD_S = 10.0  # fcisim/real: the arm and camera are probed this often while no job runs


class DeviceWatch:
    """The cell's readiness, and (fcisim, embedded) the franky-sim the cell runs as its robot."""

    def __init__(self, cfg: CellConfig, mode: DeviceMode):
        self.cfg, self.mode = cfg, mode
        self.arm_host: str | None = None  # fcisim embedded: where the service's own franky-sim serves
        self._franky_sim = None
        self._sim_error: str | None = None
        self._readiness: Readiness | None = None
        self.held = threading.Lock()  # held by a job, or by a probe
        self._poke = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the cell's own simulator if its mode has one (it lives as long as the service, like a
        robot, so the arm keeps its pose between jobs and can be probed), check once, then keep watching."""
        if self.mode.starts_simulator(self.cfg):
            from cellctl.scan.fcisim import FrankySim
            from drivers.interfaces import DeviceError

            sim = FrankySim(self.cfg.arm.host, self.cfg.twin.home_q, self.cfg.fcisim.start_timeout_s)
            try:
                self.arm_host = sim.start()
                self._franky_sim = sim
                log.info("franky-sim serves the fcisim arm at %s", self.arm_host)
            except (DeviceError, OSError) as e:  # the cell serves anyway and says why it is not ready
                self._sim_error = f"the embedded franky-sim did not start: {e}"
                log.error("%s", self._sim_error)
        self.refresh()

    def watch(self) -> None:
        """The watcher thread, for modes whose devices are probed."""
        if self.mode.probed and self._thread is None:
            self._thread = threading.Thread(target=self._watch, name="cell-devices", daemon=True)
            self._thread.start()

    def poke(self) -> None:
        """Check again now (when idle)."""
        self._poke.set()

    def describe(self) -> str:
        return self.mode.describe(self.cfg, self.arm_host)

    def readiness(self) -> Readiness:
        rd = self._readiness
        if rd is None:  # a mode that is not probed (static), or before the first check
            if not self.mode.probed:
                return self.mode.readiness(self.cfg)
            return Readiness(False, False, "not checked yet", "not checked yet")
        return rd

    def refresh(self, *, blocking: bool = True) -> None:
        if not self.mode.probed:
            return
        if not self.held.acquire(blocking=blocking):
            return  # a job holds the devices: its own outcome tells
        try:
            sim = self._franky_sim
            if sim is not None and not sim.alive():  # our own robot is gone: say so, not "FCI inactive"
                status = getattr(sim.proc, "returncode", None)
                self._sim_error = f"the embedded franky-sim exited (status {status}); restart the service"
            if self._sim_error:
                rd = Readiness(False, True, self._sim_error, "twin renderer posed from the arm")
            else:
                rd = check_readiness(self.cfg, self.arm_host, full=False)
        finally:
            self.held.release()
        if rd != self._readiness:
            (log.info if rd.ready else log.warning)("cell %s: %s", "ready" if rd.ready else "not ready",
                                                    f"arm: {rd.arm}; camera: {rd.camera}")
        self._readiness = rd

    def stop(self) -> None:
        """The watcher ends (at its next wake-up)."""
        self._stopping.set()
        self._poke.set()

    def close(self) -> None:
        """Stop watching and stop the cell's simulator. A probe in flight ends within its timeouts; a
        process leaving while libfranka or librealsense threads run is aborted by the C++ runtime."""
        self.stop()
        if self._thread is not None:
            self._thread.join(2.0 * self.cfg.arm.connect_timeout_s + 15.0 if self.cfg.arm else 15.0)
            self._thread = None
        if self._franky_sim is not None:
            self._franky_sim.close()
            self._franky_sim = None

    def _watch(self) -> None:
        while not self._stopping.is_set():
            self._poke.wait(READINESS_PERIOD_S)
            self._poke.clear()
            if self._stopping.is_set():
                return
            try:
                self.refresh(blocking=False)
            except Exception:  # noqa: BLE001 - the watcher must outlive one bad probe
                log.exception("checking the devices failed")
