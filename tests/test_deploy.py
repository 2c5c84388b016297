"""deploy/: the router config with authentication and access control, run as `cellctl router` on
loopback. Credentials are made at test time by deploy/make-users.sh (none live in the repo)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

ROOT = Path(__file__).resolve().parents[1]
CELL = "sim-1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def client(endpoint: str, user: str | None = None, password: str | None = None) -> "zenoh.Session":
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    if user is not None:
        c.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        c.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(c)


def answered(session, key: str) -> bool:
    return any(r.ok is not None for r in session.get(key, timeout=1.5))


@pytest.fixture(scope="module")
def router(tmp_path_factory):
    d = tmp_path_factory.mktemp("deploy")
    subprocess.run(["sh", str(ROOT / "deploy/make-users.sh"), str(d), "operator", "viewer", f"cell-{CELL}"],
                   check=True, capture_output=True, timeout=30)
    pw = {u: (d / f"{u}.password").read_text().strip() for u in ("operator", "viewer", f"cell-{CELL}")}
    assert len(set(pw.values())) == 3 and all(len(p) >= 16 for p in pw.values())
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.router", "--config", str(ROOT / "deploy/zenoh/router.json5"),
                             "--listen", endpoint, "--users", str(d / "zenoh-users.txt")],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
        assert "listening" in line, line
        yield endpoint, pw, proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                pytest.fail("the router did not exit within 10 s of SIGTERM")


def test_access_control_lets_operators_command_and_viewers_only_read(router):
    endpoint, pw, _ = router
    cell = client(endpoint, f"cell-{CELL}", pw[f"cell-{CELL}"])
    op = viewer = None
    try:
        keys = [f"cell/{CELL}/status", f"cell/{CELL}/jobs/submit", f"cell/{CELL}/jobs/j1/cancel", f"cell/{CELL}/jobs/j1"]
        queryables = [cell.declare_queryable(k, lambda q: q.reply(q.key_expr, b"{}")) for k in keys]
        op = client(endpoint, "operator", pw["operator"])
        viewer = client(endpoint, "viewer", pw["viewer"])
        time.sleep(0.5)  # declarations reach the router
        status, submit, cancel, record = keys
        assert all(answered(op, k) for k in keys)
        assert answered(viewer, status) and answered(viewer, record)
        assert not answered(viewer, submit) and not answered(viewer, cancel)  # denied = no reply
        for qb in queryables:
            qb.undeclare()
    finally:
        for s in (op, viewer, cell):
            if s is not None:
                s.close()


@pytest.mark.parametrize("user,password", [("operator", "not-the-password"), (None, None), ("intruder", "x")])
def test_sessions_without_valid_credentials_are_refused(router, user, password):
    endpoint, _, _ = router
    with pytest.raises(Exception, match="Unable to connect"):
        client(endpoint, user, password).close()


def test_router_config_errors_are_clear(tmp_path):
    from cellctl.router import router_config

    with pytest.raises(ValueError, match="does not exist"):
        router_config(tmp_path / "nope.json5")
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(ValueError, match="not a valid Zenoh config"):
        router_config(bad)
    with pytest.raises(ValueError, match="make-users.sh"):
        router_config(ROOT / "deploy/zenoh/router.json5", users_file=str(tmp_path / "none.txt"))


def test_router_exits_on_sigterm(tmp_path):
    subprocess.run(["sh", str(ROOT / "deploy/make-users.sh"), str(tmp_path), "operator"], check=True,
                   capture_output=True, timeout=30)
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.router", "--listen", f"tcp/127.0.0.1:{free_port()}",
                             "--users", str(tmp_path / "zenoh-users.txt")], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    assert "listening" in proc.stderr.readline()
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=10) == 0 and time.monotonic() - t0 < 5
    assert not any(f.endswith(".password") and os.path.getsize(tmp_path / f) == 0 for f in os.listdir(tmp_path))
