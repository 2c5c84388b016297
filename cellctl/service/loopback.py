"""A real `cellctl serve` subprocess on loopback, for the tests and the load bench: a free port, the sim
cell config pointed at it, and the process started, queried and stopped by signal. Nothing is mocked.

    from cellctl.service.loopback import ServiceProcess
    with ServiceProcess(tmp_path) as svc, svc.client() as c:
        c.status()
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import yaml

from configs import CONFIG_DIR

ROOT = Path(__file__).resolve().parents[2]


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
        from cellctl.service.client import CellClient, CellUnreachable, NoReply

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
        from cellctl.service.client import CellClient

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
