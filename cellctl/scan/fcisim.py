"""franky-sim as the fcisim cell's robot: a MuJoCo FR3 behind a libfranka server on a loopback address,
run in a child process the cell owns.

Why a child process and not a thread of the cell: franky-sim steps its simulator and answers libfranka in
a Python loop at 1 kHz. In the service process that loop would share the GIL with the scan (planning,
rendering), run irregularly and lose simulated time; in its own process it keeps its pace and a crash of
either side leaves the other standing. libfranka's port is fixed (1337), so the server takes the first free
loopback *address* from the one asked for (127.0.0.1, 127.0.0.2, ...).

    python -m cellctl.scan.fcisim [--host 127.0.0.1] [--q q1 ... q7]   # an external franky-sim for fcisim cells

prints ``FRANKY_SIM_READY <address>`` once it serves and runs until SIGINT/SIGTERM; the cell's own child
(``--owned``) also ends when its stdin closes, so it never outlives the cell that started it.
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator, Sequence

from drivers.interfaces import DeviceError

READY = "FRANKY_SIM_READY"
ROOT = Path(__file__).resolve().parents[2]


def loopback_from(first: str) -> Iterator[str]:
    """127.x.y.z addresses from ``first`` on (never the network or broadcast address)."""
    start = int(ipaddress.IPv4Address(first))
    end = int(ipaddress.IPv4Address("127.255.255.254"))
    for n in range(max(start, int(ipaddress.IPv4Address("127.0.0.1"))), end + 1):
        yield str(ipaddress.IPv4Address(n))


class FrankySim:
    """One franky-sim child process. ``start()`` returns the address it serves; ``close()`` ends it.
    A context manager. DeviceError when it does not come up within ``timeout_s`` (its output is quoted)."""

    def __init__(self, first_host: str = "127.0.0.1", initial_q: Sequence[float] | None = None,
                 timeout_s: float = 60.0) -> None:
        if not ipaddress.ip_address(first_host).is_loopback:
            raise ValueError(f"franky-sim serves loopback only; {first_host!r} is not a 127.x.y.z address")
        self.first_host = first_host
        self.initial_q = None if initial_q is None else [float(v) for v in initial_q]
        if self.initial_q is not None and len(self.initial_q) != 7:
            raise ValueError(f"initial_q needs 7 joint angles, got {len(self.initial_q)}")
        self.timeout_s = timeout_s
        self.host: str | None = None
        self.proc: subprocess.Popen | None = None

    def start(self) -> str:
        if self.proc is not None:
            return self.host  # type: ignore[return-value]
        cmd = [sys.executable, "-m", "cellctl.scan.fcisim", "--owned", "--host", self.first_host]
        if self.initial_q is not None:
            cmd += ["--q", *map(repr, self.initial_q)]
        self.proc = subprocess.Popen(cmd, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, bufsize=1)
        seen: list[str] = []
        deadline = time.monotonic() + self.timeout_s
        try:
            while time.monotonic() < deadline:
                ready, _, _ = select.select([self.proc.stdout], [], [], 0.2)
                if ready:
                    line = self.proc.stdout.readline()
                    if line.startswith(READY):
                        self.host = line.split()[1]
                        break
                    if line:
                        seen.append(line.rstrip())
                        continue
                if self.proc.poll() is not None:
                    raise DeviceError(f"franky-sim exited with status {self.proc.returncode} before serving: "
                                      + " | ".join(seen[-5:]))
            else:
                raise DeviceError(f"franky-sim did not serve within {self.timeout_s:.0f} s: " + " | ".join(seen[-5:]))
        except BaseException:
            self.close()
            raise
        # from now on its output goes nowhere we read: drain it so a chatty simulator never blocks on a full pipe
        threading.Thread(target=self._drain, args=(self.proc,), name="franky-sim-out", daemon=True).start()
        return self.host

    @staticmethod
    def _drain(proc: subprocess.Popen) -> None:
        log = logging.getLogger("cellctl.scan.fcisim")
        for line in proc.stdout:
            log.warning("franky-sim: %s", line.rstrip())

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def close(self) -> None:
        """Close its stdin (it exits), then SIGTERM, then SIGKILL: at most a few seconds. Idempotent."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()
        except OSError:
            pass
        for sig, wait in ((None, 3.0), (signal.SIGTERM, 3.0), (signal.SIGKILL, 5.0)):
            if sig is not None:
                proc.send_signal(sig)
            try:
                proc.wait(wait)
                break
            except subprocess.TimeoutExpired:
                continue

    def __enter__(self) -> "FrankySim":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- the child --------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cellctl.scan.fcisim",
                                 description="franky-sim (MuJoCo FR3, libfranka protocol) on a loopback address")
    ap.add_argument("--host", default="127.0.0.1", help="first loopback address to try (default 127.0.0.1)")
    ap.add_argument("--q", type=float, nargs=7, default=None, metavar="RAD", help="initial joints")
    ap.add_argument("--owned", action="store_true", help="exit when stdin closes (the cell that started us ended)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stdout, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("numba").setLevel(logging.WARNING)
    if not ipaddress.ip_address(args.host).is_loopback:
        print(f"--host {args.host}: franky-sim serves loopback addresses only", flush=True)
        return 2

    from franky_sim import SimulationServer
    from franky_sim.constants import DEFAULT_INITIAL_JOINT_POS
    from franky_sim.mujoco_simulator import MujocoSimulator

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    sim = MujocoSimulator(enable_visualization=False)
    sim.init()
    robot = sim.add_robot(initial_q=tuple(args.q) if args.q else DEFAULT_INITIAL_JOINT_POS)
    server = SimulationServer(sim, hostname_candidates=loopback_from(args.host))
    try:
        server.init()
        server.run_async()
        print(f"{READY} {robot.hostname}", flush=True)
        while not stop.is_set():  # until signalled, or (owned) the parent closes our stdin or dies
            if args.owned:
                if select.select([sys.stdin], [], [], 0.5)[0] and not os.read(sys.stdin.fileno(), 4096):
                    break
            else:
                stop.wait(0.5)
            if server.async_thread is not None and not server.async_thread.is_alive():
                print("franky-sim's control loop died", flush=True)
                return 1
    finally:
        server.cleanup()
        sim.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
