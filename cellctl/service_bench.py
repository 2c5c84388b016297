"""Latency of the job API on loopback, for `cellctl bench` and the tests: a real `cellctl serve`
subprocess, a real Zenoh client, nothing mocked.

    from cellctl.service_bench import measure
    measure(n=100)  # -> {"status_rtt_ms": {...}, "submit_to_first_event_ms": {...}, ...}
"""

from __future__ import annotations

import json
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

from configs import CONFIG_DIR

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_config(path: Path, port: int, data_dir: Path, *, cell_id: str = "sim-1", cell: dict | None = None,
                 **service) -> Path:
    """The sim cell config with a loopback listen endpoint, a data dir and any service overrides;
    ``cell`` is merged into the rest of the config (e.g. ``{"twin": {"execution": "teleport"}}``)."""
    doc = _merge(yaml.safe_load((CONFIG_DIR / "cell.sim.yaml").read_text()), cell or {})
    doc["cell_id"] = cell_id
    doc["planners_config"] = str(CONFIG_DIR / doc.get("planners_config", "planners.yaml"))
    doc["service"] = {**doc.get("service", {}), "data_dir": str(data_dir), "zenoh_mode": "peer",
                      "listen": [f"tcp/127.0.0.1:{port}"], "connect": [], **service}
    path.write_text(yaml.safe_dump(doc))
    return path


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


class ServiceProcess:
    """`python -m cellctl.cli serve` as a subprocess on a loopback port; stop() by signal, timed."""

    def __init__(self, workdir: Path, *, port: int | None = None, cell_id: str = "sim-1", cell: dict | None = None,
                 **service):
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.cell_id = cell_id
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.data_dir = self.workdir / "data"
        self.config = write_config(self.workdir / "cell.yaml", self.port, self.data_dir, cell_id=cell_id, cell=cell,
                                   **service)
        self.proc: subprocess.Popen | None = None
        self.log = self.workdir / "service.log"
        self.startup_s: float | None = None

    # The default waits are liveness bounds (they fail on a hang, not on a loaded machine): start-up takes
    # a few seconds of imports, a reply milliseconds (~0.3 s while a scan holds the GIL), an exit under a
    # second (up to service.shutdown_grace_s, 30 s, while a job finishes its step).
    def start(self, timeout_s: float = 120.0) -> ServiceProcess:
        from cellctl.client import CellClient, CellUnreachable, NoReply

        t0 = time.monotonic()
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "serve", "--config", str(self.config)],
                                         cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        try:
            while time.monotonic() - t0 < timeout_s:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"the service exited with {self.proc.returncode}:\n"
                                       f"{self.log.read_text()[-3000:]}")
                try:
                    with CellClient(self.cell_id, [self.endpoint], timeout_s=1.0) as c:
                        c.status()
                        if c.alive():
                            self.startup_s = time.monotonic() - t0
                            return self
                except (CellUnreachable, NoReply):
                    time.sleep(0.1)
            raise TimeoutError(f"the service did not answer within {timeout_s} s:\n{self.log.read_text()[-3000:]}")
        except BaseException:  # e.g. a reply this client's API refuses: the caller never gets the process to stop
            self.kill()
            raise

    def client(self, timeout_s: float = 30.0):
        from cellctl.client import CellClient

        return CellClient(self.cell_id, [self.endpoint], timeout_s=timeout_s)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 120.0) -> tuple[int, float]:
        """Send ``sig``; (exit status, seconds to exit). Killed if it does not exit in time."""
        t0 = time.monotonic()
        self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            raise TimeoutError(f"the service did not exit within {timeout_s} s of {signal.Signals(sig).name}")
        return rc, time.monotonic() - t0

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def __enter__(self) -> ServiceProcess:
        return self.start()

    def __exit__(self, *_exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            try:
                self.stop()
            except TimeoutError:
                pass


def _stats(xs: list[float]) -> dict:
    xs = sorted(xs)
    q = lambda p: xs[min(len(xs) - 1, int(p * len(xs)))]  # noqa: E731
    return {"n": len(xs), "median": round(statistics.median(xs), 3), "p90": round(q(0.9), 3),
            "min": round(xs[0], 3), "max": round(xs[-1], 3)}


def measure(n: int = 100, *, submits: int | None = None, workdir: str | Path | None = None) -> dict:
    """Start a service on loopback and measure, in milliseconds:
    - status_rtt_ms: ``n`` status queries while idle, and ``n`` while a scan runs (the worker thread
      and the Zenoh callbacks share the GIL);
    - submit_to_first_event_ms: from sending a submit to receiving its "queued" event (``submits``
      of them, default min(n, 20), made while a scan runs and cancelled while still queued, so only one
      scan ever runs, itself cancelled after its first view); submit_to_first_event_idle_ms: the one
      submit made while the cell was idle;
    - job_start_ms: from the first submit to its first step event (twin built, first view captured).
    """
    from cellctl.api import ScanDrawingRequest

    submits = min(n, 20) if submits is None else submits
    tmp = tempfile.TemporaryDirectory(prefix="scrapcell-svcbench-") if workdir is None else None
    wd = Path(workdir) if workdir else Path(tmp.name)
    svc = ServiceProcess(wd, queue_max=max(submits + 1, 2))
    out: dict = {"n": n, "endpoint": "", "pid": None}
    try:
        svc.start()
        out.update(endpoint=svc.endpoint, pid=svc.proc.pid, service_startup_s=round(svc.startup_s, 3))
        with svc.client() as c:
            c.status()  # warm the path
            out["status_rtt_idle_ms"] = _stats([_timed(c.status) for _ in range(n)])
            first_step = threading.Event()
            t_sub = time.perf_counter()
            t_step: list[float] = []

            t_first: list[float] = []

            def on(ev):
                if not t_first:
                    t_first.append(time.perf_counter())
                if ev.step is not None and not first_step.is_set():
                    t_step.append(time.perf_counter())
                    first_step.set()

            long = ScanDrawingRequest(scene="smooth_cylinder", max_steps=6, noise=False)
            job = c.submit(long, on_event=on).job_id
            if not first_step.wait(120):
                raise TimeoutError("the scan did not reach its first step within 120 s")
            out["submit_to_first_event_idle_ms"] = round(1e3 * (t_first[0] - t_sub), 3)
            out["job_start_ms"] = round(1e3 * (t_step[0] - t_sub), 1)
            out["status_rtt_busy_ms"] = _stats([_timed(c.status) for _ in range(n)])
            lat = []
            for _ in range(submits):
                got = threading.Event()
                t0 = time.perf_counter()
                t_ev: list[float] = []
                reply = c.submit(long, on_event=lambda ev, t=t_ev, g=got: (t.append(time.perf_counter()), g.set()))
                if got.wait(10):
                    lat.append(1e3 * (t_ev[0] - t0))
                c.cancel(reply.job_id)
            out["submit_to_first_event_ms"] = _stats(lat) if lat else None
            c.cancel(job)
            c.wait(job, 60)
        rc, exit_s = svc.stop()
        out.update(exit_status=rc, sigterm_to_exit_s=round(exit_s, 3))
    finally:
        svc.kill()
        if tmp is not None:
            tmp.cleanup()
    return out


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - t0)


if __name__ == "__main__":
    print(json.dumps(measure(int(sys.argv[1]) if len(sys.argv) > 1 else 100), indent=2))
