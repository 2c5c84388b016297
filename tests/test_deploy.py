"""deploy/: the router config with TLS, authentication and access control, run as `cellctl router` on
loopback. Credentials and certificates are made at test time by deploy/make-users.sh and
deploy/make-certs.sh (none live in the repo)."""

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
# Liveness bounds: they only fail on a hang, never because the machine is loaded. A reply the test
# needs may take this long (a cell replies in milliseconds, or ~0.2 s while its worker holds the GIL)
REPLY_S = 30.0
DENIED_S = 10.0  # how long a query the ACL denies waits for the reply it must not get
EXIT_S = 120.0  # a process exits this long after SIGTERM (idle: well under a second)
UP_S = 120.0  # a cell shows up behind the router (idle: a few seconds of imports)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_certs(d: Path, *names: str) -> Path:
    """The yard CA and a router certificate for ``names`` in ``d``, by the shipped script."""
    for args in (["ca"], ["router", *(names or ("localhost", "127.0.0.1"))]):
        subprocess.run(["sh", str(ROOT / "deploy/make-certs.sh"), str(d), *args], check=True, capture_output=True,
                       timeout=60)
    return d


def client(endpoint: str, ca: Path | None, user: str | None = None, password: str | None = None) -> "zenoh.Session":
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    if ca is not None:
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca)))
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    if user is not None:
        c.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        c.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(c)


def answered(session, key: str) -> bool:
    return any(r.ok is not None for r in session.get(key, timeout=REPLY_S))


@pytest.fixture(scope="module")
def router(tmp_path_factory):
    d = tmp_path_factory.mktemp("deploy")
    users = ("operator", "viewer", f"cell-{CELL}", "cell-sim-2")
    subprocess.run(["sh", str(ROOT / "deploy/make-users.sh"), str(d), *users], check=True, capture_output=True,
                   timeout=30)
    pw = {u: (d / f"{u}.password").read_text().strip() for u in users}
    assert len(set(pw.values())) == len(users) and all(len(p) >= 16 for p in pw.values())
    make_certs(d / "tls")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.service.router",
                             "--config", str(ROOT / "deploy/zenoh/router.json5"),
                             "--listen", endpoint, "--users", str(d / "zenoh-users.txt"),
                             "--tls-cert", str(d / "tls/router.crt"), "--tls-key", str(d / "tls/router.key")],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
        assert "listening" in line, line
        yield endpoint, pw, proc, d / "tls/ca.crt"
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=EXIT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                pytest.fail(f"the router did not exit within {EXIT_S:g} s of SIGTERM")


def _creds(tmp: Path, user: str, password: str, ca: Path) -> str:
    """The shipped example client config of the user's role (deploy/zenoh/), filled in as its comments
    say (its password, and the yard CA's path): so the examples are the configs every test through the
    router uses."""
    role = "cell" if user.startswith("cell-") else user
    text = (ROOT / "deploy/zenoh" / f"{role}.json5").read_text()
    if role == "cell":
        text = text.replace("cell-<cell_id>", user)
    placeholder = "<PASSWORD>"
    assert placeholder in text, f"deploy/zenoh/{role}.json5 has no {placeholder}"
    assert "/etc/scrapcell/tls/ca.crt" in text, f"deploy/zenoh/{role}.json5 names no CA"
    f = tmp / f"{user}.json5"
    f.write_text(text.replace(placeholder, password).replace("/etc/scrapcell/tls/ca.crt", str(ca)))
    return str(f)


def test_two_cells_behind_the_router_one_operator_and_a_viewer(router, tmp_path):
    """The yard: `cellctl router` with deploy/'s auth and ACL, two real cell services (ids sim-1 and
    sim-2) as its clients, one operator client driving both, and a viewer who may read but whose
    submit and cancel get no reply."""
    from cellctl.service.api import ScanDrawingRequest
    from cellctl.service.client import CellClient, NoReply
    from cellctl.service.loopback import write_config

    endpoint, pw, _, ca = router
    cells = {}
    try:
        for cid in (CELL, "sim-2"):
            user = f"cell-{cid}"
            cfg = write_config(tmp_path / f"{cid}.yaml", free_port(), tmp_path / f"data-{cid}", cell_id=cid,
                               zenoh_mode="client", listen=[], connect=[endpoint],
                               zenoh_config_file=_creds(tmp_path, user, pw[user], ca))
            cells[cid] = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "serve", "--config", str(cfg)],
                                          cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        op_creds = _creds(tmp_path, "operator", pw["operator"], ca)
        with CellClient(CELL, [endpoint], timeout_s=REPLY_S, zenoh_config_file=op_creds) as c1, \
                CellClient("sim-2", [endpoint], timeout_s=REPLY_S, zenoh_config_file=op_creds) as c2:
            for c in (c1, c2):
                deadline = time.monotonic() + UP_S
                while not c.alive(0.5):
                    assert time.monotonic() < deadline, f"cell {c.cell_id} never appeared behind the router"
                    assert cells[c.cell_id].poll() is None, cells[c.cell_id].stderr.read()[-3000:]
            req = ScanDrawingRequest(scene="smooth_cylinder", max_steps=1, noise=False)
            jobs = {c.cell_id: c.submit(req).job_id for c in (c1, c2)}
            for c in (c1, c2):
                rec = c.wait(jobs[c.cell_id], 300)  # a liveness bound: one view and its cut take seconds
                assert rec.state == "done", (c.cell_id, rec.state, rec.error)
                assert c.status().cell_id == c.cell_id
        with CellClient("sim-2", [endpoint], timeout_s=REPLY_S, zenoh_config_file=op_creds) as c2:
            listed = c2.jobs()
            assert listed.cell_id == "sim-2" and [j.job_id for j in listed.jobs] == [jobs["sim-2"]]  # its own only
        viewer_creds = _creds(tmp_path, "viewer", pw["viewer"], ca)
        # the commands the ACL denies get no reply at all: each waits out its whole timeout, so theirs is
        # shorter than REPLY_S, yet still far longer than an allowed reply takes on a loaded machine
        with CellClient(CELL, [endpoint], timeout_s=REPLY_S, zenoh_config_file=viewer_creds) as v, \
                CellClient(CELL, [endpoint], timeout_s=DENIED_S, zenoh_config_file=viewer_creds) as denied:
            assert v.status().cell_id == CELL
            assert v.job(jobs[CELL]).state == "done"  # records are readable
            with pytest.raises(NoReply, match="access control"):
                denied.submit(req)
            with pytest.raises(NoReply):
                denied.cancel(jobs[CELL])
    finally:
        for cid, proc in cells.items():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    assert proc.wait(timeout=EXIT_S) == 0, cid
                except subprocess.TimeoutExpired:
                    proc.kill()
                    pytest.fail(f"cell {cid} did not exit within {EXIT_S:g} s of SIGTERM")


@pytest.mark.parametrize("user,password", [("operator", "not-the-password"), (None, None), ("intruder", "x")])
def test_sessions_without_valid_credentials_are_refused(router, user, password):
    endpoint, _, _, ca = router
    with pytest.raises(Exception, match="Unable to connect"):
        client(endpoint, ca, user, password).close()


def test_a_wrong_password_and_a_router_that_is_down_are_told_apart(router, tmp_path):
    """Both fail to open a session; the client says which: the router answered and refused (check the
    password in this file), or nothing answers there."""
    from cellctl.service.client import CellClient, CellUnreachable, SessionRefused

    endpoint, pw, _, ca = router
    wrong = _creds(tmp_path, "operator", pw["operator"] + "x", ca)
    with pytest.raises(SessionRefused, match=f"answers but refused this session: check the user and password in {wrong}"):
        CellClient("sim-1", [endpoint], zenoh_config_file=wrong)
    down = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(CellUnreachable, match="nothing answers there") as e:
        CellClient("sim-1", [down], zenoh_config_file=_creds(tmp_path, "viewer", pw["viewer"], ca))
    assert not isinstance(e.value, SessionRefused)
    out = subprocess.run([sys.executable, "-m", "cellctl.cli", "status", "--cell", "sim-1", "--connect", endpoint,
                          "--zenoh-config", wrong], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 3 and "refused this session" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_router_config_errors_are_clear(tmp_path):
    from cellctl.service.router import router_config

    with pytest.raises(ValueError, match="does not exist"):
        router_config(tmp_path / "nope.json5")
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(ValueError, match="not a valid Zenoh config"):
        router_config(bad)
    with pytest.raises(ValueError, match="make-users.sh"):
        router_config(ROOT / "deploy/zenoh/router.json5", users_file=str(tmp_path / "none.txt"))
    # the shipped config names /etc/scrapcell/zenoh-users.txt: not made yet is one clear line, no traceback
    if not Path("/etc/scrapcell/zenoh-users.txt").exists():
        out = subprocess.run([sys.executable, "-m", "cellctl.service.router", "--config",
                              str(ROOT / "deploy/zenoh/router.json5"), "--listen", f"tls/127.0.0.1:{free_port()}"],
                             cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        assert "/etc/scrapcell/zenoh-users.txt (transport.auth.usrpwd.dictionary_file" in out.stderr, out.stderr


def test_router_exits_on_sigterm(tmp_path):
    subprocess.run(["sh", str(ROOT / "deploy/make-users.sh"), str(tmp_path), "operator"], check=True,
                   capture_output=True, timeout=30)
    make_certs(tmp_path / "tls")
    proc = subprocess.Popen([sys.executable, "-m", "cellctl.service.router", "--listen", f"tls/127.0.0.1:{free_port()}",
                             "--users", str(tmp_path / "zenoh-users.txt"), "--tls-cert", str(tmp_path / "tls/router.crt"),
                             "--tls-key", str(tmp_path / "tls/router.key")], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    assert "listening" in proc.stderr.readline()
    proc.send_signal(signal.SIGTERM)
    try:  # exits, and cleanly (a process killed by the signal has status -15)
        assert proc.wait(timeout=EXIT_S) == 0
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"the router did not exit within {EXIT_S:g} s of SIGTERM")
    assert "zenoh router closed" in proc.stderr.read()  # closed its session on the way out
    assert not any(f.endswith(".password") and os.path.getsize(tmp_path / f) == 0 for f in os.listdir(tmp_path))
