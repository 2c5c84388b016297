"""A real `cellctl tablet` subprocess on a free loopback port, with its own accounts and state folder:
for the browser test and `make screenshots`. Nothing is mocked.

    with ServiceProcess(tmp / "cell") as svc, TabletProcess(tmp / "tablet", svc.endpoint,
                                                            {"ana": ("operator", "a-password")}) as tab:
        page.goto(tab.url)
"""

from __future__ import annotations

import os
import signal
import ssl
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import yaml

from cellctl.service.loopback import ROOT, free_port
from cellctl.tablet.accounts import add_user


class TabletProcess:
    def __init__(self, workdir: Path, endpoint: str, users: dict[str, tuple[str, str]], *,
                 https_ca: Path | None = None, **cfg):
        """``cfg``: tablet config fields; with ``https_cert``/``https_key`` the pages are HTTPS, checked
        against ``https_ca``."""
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.url = f"{'https' if cfg.get('https_cert') else 'http'}://127.0.0.1:{self.port}"
        self._ssl = ssl.create_default_context(cafile=str(https_ca)) if https_ca else None
        self.config = self.workdir / "tablet.yaml"
        accounts = self.workdir / "accounts.yaml"
        for user, (role, password) in users.items():
            add_user(accounts, user, role, password)
        doc = {"host": "127.0.0.1", "port": self.port, "connect": [endpoint], "accounts_file": str(accounts),
               "state_dir": str(self.workdir / "state"), **{k: str(v) if isinstance(v, Path) else v
                                                             for k, v in cfg.items()}}
        self.config.write_text(yaml.safe_dump(doc))
        self.log = self.workdir / "tablet.log"
        self.proc: subprocess.Popen | None = None

    def start(self, timeout_s: float = 120.0) -> TabletProcess:
        # NiceGUI takes a PYTEST_CURRENT_TEST in its environment for its own test harness: this is the real app
        env = {k: v for k, v in os.environ.items() if k != "PYTEST_CURRENT_TEST"}
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "tablet", "--config", str(self.config)],
                                         cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=env)
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:  # a liveness bound: start-up takes seconds
            if self.proc.poll() is not None:
                raise RuntimeError(f"the tablet app exited with {self.proc.returncode}:\n{self.log.read_text()[-3000:]}")
            try:
                with urllib.request.urlopen(f"{self.url}/login", timeout=2, context=self._ssl) as r:
                    if r.status == 200:
                        return self
            except OSError:
                time.sleep(0.2)
        self.stop()
        raise TimeoutError(f"the tablet app did not answer within {timeout_s} s:\n{self.log.read_text()[-3000:]}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)

    def __enter__(self) -> TabletProcess:
        return self.start()

    def __exit__(self, *_exc) -> None:
        self.stop()
