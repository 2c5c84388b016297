"""The yard network over TLS (deploy/README.md): certificates made by deploy/make-certs.sh at test time,
a router that listens on TLS only, clients that verify it against the yard CA, and errors that tell a
certificate problem from a router that is down and from a wrong password. Jobs and the access control
over TLS: tests/test_deploy.py and tests/test_security.py (their router is this one).

Tests of: cellctl.tls, cellctl.service.router, cellctl.commissioning.doctor (the yard network)."""

from __future__ import annotations

import ipaddress
import json
import os
import signal
import socket
import ssl
import stat
import subprocess
import sys
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from test_deploy import ROOT, free_port, make_certs

from cellctl import tls
from cellctl.service.client import (CellClient, CellUnreachable, CertificateProblem, SessionRefused, open_session)
from cellctl.service.loopback import write_config

REPLY_S = 30.0  # liveness bounds only: they fail on a hang, never because the machine is loaded
UP_S = 120.0
MAKE_CERTS = ROOT / "deploy/make-certs.sh"


def _sh(*args: str, env: dict | None = None, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["sh", str(MAKE_CERTS), *args], capture_output=True, text=True, timeout=60, check=check,
                          env={**os.environ, **(env or {})})


def issue(ca_dir: Path, out: Path, names: list[str], *, days: tuple[float, float] = (-1, 365)) -> tuple[Path, Path]:
    """A server certificate signed by the yard CA in ``ca_dir``, valid from ``days[0]`` to ``days[1]``
    days from now (make-certs.sh only makes certificates valid from now: an expired one is made here)."""
    ca_key = serialization.load_pem_private_key((ca_dir / "ca.key").read_bytes(), None)
    ca = x509.load_pem_x509_certificate((ca_dir / "ca.crt").read_bytes())
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.now(timezone.utc)
    sans = [x509.IPAddress(ipaddress.ip_address(n)) if n[0].isdigit() else x509.DNSName(n) for n in names]
    cert = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, names[0])]))
            .issuer_name(ca.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now + timedelta(days=days[0])).not_valid_after(now + timedelta(days=days[1]))
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .sign(ca_key, hashes.SHA256()))
    out.mkdir(parents=True, exist_ok=True)
    (out / "router.crt").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (out / "router.key").write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                       serialization.NoEncryption()))
    os.chmod(out / "router.key", 0o600)
    return out / "router.crt", out / "router.key"


def raw_router(cert: Path, key: Path, port: int) -> zenoh.Session:
    """A Zenoh router serving ``cert`` as it is (no checks of ours: the client side is under test)."""
    c = zenoh.Config()
    c.insert_json5("mode", '"router"')
    c.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(cert)))
    c.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(key)))
    return zenoh.open(c)


@pytest.fixture(scope="module")
def yard_ca(tmp_path_factory) -> Path:
    return make_certs(tmp_path_factory.mktemp("yard-ca"))


# --- deploy/make-certs.sh --------------------------------------------------------------------------
def test_make_certs_writes_private_keys_named_certificates_and_their_expiry(tmp_path):
    d = tmp_path / "ca"
    out = _sh(str(d), "ca", env={"CA_DAYS": "1000"}).stdout
    assert "expires" in out and "keep it offline" in out
    out = _sh(str(d), "router", "yard-router", "yard-router.local", "10.20.0.2", env={"DAYS": "90"}).stdout
    for key in ("ca.key", "router.key"):
        assert stat.S_IMODE((d / key).stat().st_mode) == 0o600, key
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    ca, router = (x509.load_pem_x509_certificate((d / f).read_bytes()) for f in ("ca.crt", "router.crt"))
    assert tls.names(router) == ["yard-router", "yard-router.local", "10.20.0.2"]
    now = datetime.now(timezone.utc)
    assert abs((ca.not_valid_after_utc - now).days - 1000) <= 1 and abs((router.not_valid_after_utc - now).days - 90) <= 1
    assert tls.check_ca(d / "ca.crt") == [] and tls.check_server_pair(d / "router.crt", d / "router.key") == []
    shown = _sh(str(d), "show").stdout
    assert "router.crt" in shown and "DNS:yard-router.local" in shown and "expires" in shown
    # rotation: a new router certificate from the same CA, the old pair kept beside it
    first = (d / "router.crt").read_bytes()
    _sh(str(d), "router", "yard-router")
    assert (d / "router.crt.old").read_bytes() == first and (d / "router.crt").read_bytes() != first
    assert tls.check_server_pair(d / "router.crt", d / "router.key") == []


def test_make_certs_refuses_to_replace_a_ca_or_to_write_into_git(tmp_path):
    d = make_certs(tmp_path / "ca")
    before = (d / "ca.key").read_bytes()
    r = _sh(str(d), "ca", check=False)
    assert r.returncode == 1 and "new directory" in r.stderr and (d / "ca.key").read_bytes() == before
    r = _sh(str(ROOT / "deploy/should-not-exist"), "ca", check=False)
    assert r.returncode == 1 and "git work tree" in r.stderr and not (ROOT / "deploy/should-not-exist").exists()
    r = _sh(str(tmp_path / "empty"), "router", "x", check=False)
    assert r.returncode == 1 and "no CA" in r.stderr


# --- the router: TLS only, with a certificate that fits ---------------------------------------------
def test_the_router_listens_on_tls_only_and_checks_its_certificate(tmp_path, yard_ca):
    from cellctl.service.router import check_certificates, router_config

    shipped = ROOT / "deploy/zenoh/router.json5"
    cfg = router_config(shipped)
    assert all(ep.startswith("tls/") for ep in json.loads(cfg.get_json("listen/endpoints")))
    with pytest.raises(ValueError, match="listens on TLS only, not on tcp/0.0.0.0:7447"):
        router_config(shipped, listen=["tcp/0.0.0.0:7447"])
    good = dict(tls_cert=str(yard_ca / "router.crt"), tls_key=str(yard_ca / "router.key"))
    assert check_certificates(router_config(shipped, **good), shipped) == []
    expired = issue(yard_ca, tmp_path / "expired", ["localhost"], days=(-30, -1))
    with pytest.raises(ValueError, match="router certificate .* expired on"):
        check_certificates(router_config(shipped, tls_cert=str(expired[0]), tls_key=str(expired[1])), shipped)
    with pytest.raises(ValueError, match="does not belong to the certificate"):
        check_certificates(router_config(shipped, tls_cert=good["tls_cert"], tls_key=str(expired[1])), shipped)
    os.chmod(expired[1], 0o644)
    fresh = issue(yard_ca, tmp_path / "open", ["localhost"])
    os.chmod(fresh[1], 0o644)
    with pytest.raises(ValueError, match="readable by every user .* chmod 600"):
        check_certificates(router_config(shipped, tls_cert=str(fresh[0]), tls_key=str(fresh[1])), shipped)
    with pytest.raises(ValueError, match="does not exist .*make-certs.sh"):
        check_certificates(router_config(shipped, tls_cert=str(tmp_path / "none.crt"), **{"tls_key": good["tls_key"]}),
                           shipped)
    # the command line: one clear line and exit 2, no traceback
    subprocess.run(["sh", str(ROOT / "deploy/make-users.sh"), str(tmp_path), "operator"], check=True,
                   capture_output=True, timeout=30)
    for extra, said in ((["--tls-cert", str(expired[0]), "--tls-key", str(expired[1])], "expired on"),
                        (["--listen", f"tcp/127.0.0.1:{free_port()}"], "TLS only")):
        out = subprocess.run([sys.executable, "-m", "cellctl.cli", "router", "--users", str(tmp_path / "zenoh-users.txt"),
                              "--listen", f"tls/127.0.0.1:{free_port()}", "--tls-cert", good["tls_cert"],
                              "--tls-key", good["tls_key"], *extra], cwd=ROOT, capture_output=True, text=True,
                             timeout=UP_S)
        assert out.returncode == 2 and said in out.stderr and "Traceback" not in out.stderr, out.stderr


# --- clients: refused without the CA, and told why -------------------------------------------------
@pytest.fixture(scope="module")
def tls_router(yard_ca):
    port = free_port()
    r = raw_router(yard_ca / "router.crt", yard_ca / "router.key", port)
    yield port
    r.close()


def test_a_client_without_the_yard_ca_is_refused(tls_router, yard_ca, tmp_path):
    ep = f"tls/127.0.0.1:{tls_router}"
    open_session([ep], tls_ca=yard_ca / "ca.crt").close()  # with it: in
    bare = zenoh.Config()  # Zenoh itself, with no CA: refused
    bare.insert_json5("mode", '"client"')
    bare.insert_json5("connect/endpoints", json.dumps([ep]))
    bare.insert_json5("scouting/multicast/enabled", "false")
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(bare).close()
    with pytest.raises(CertificateProblem, match="is TLS: give the yard's CA certificate"):
        open_session([ep])
    other = make_certs(tmp_path / "other-yard")  # a CA, but not this yard's
    with pytest.raises(CertificateProblem, match="not signed by the CA in"):
        open_session([ep], tls_ca=other / "ca.crt")


def test_a_plain_tcp_client_gets_nothing(tls_router, yard_ca):
    with pytest.raises(CertificateProblem, match="speaks TLS: connect with tls/ instead of tcp/"):
        open_session([f"tcp/127.0.0.1:{tls_router}"], tls_ca=yard_ca / "ca.crt")
    # Zenoh's own opening message over plain TCP: what comes back is at most a TLS alert, never Zenoh
    with socket.create_connection(("127.0.0.1", tls_router), timeout=REPLY_S) as s:
        s.sendall(bytes.fromhex("1400" "0108" "00") + b"\x00" * 16)
        s.settimeout(5.0)
        got = b""
        try:
            while chunk := s.recv(4096):
                got += chunk
        except (TimeoutError, ConnectionResetError):
            pass
    assert got == b"" or got[0] == 0x15, got[:16]  # 0x15: a TLS alert record


def test_certificate_problems_router_down_and_wrong_password_are_told_apart(tmp_path, yard_ca):
    ca = yard_ca / "ca.crt"
    expired = issue(yard_ca, tmp_path / "expired", ["localhost", "127.0.0.1"], days=(-30, -1))
    only_ip = issue(yard_ca, tmp_path / "ip", ["127.0.0.1"])
    p1, p2 = free_port(), free_port()
    r1, r2 = raw_router(*expired, p1), raw_router(*only_ip, p2)
    try:
        with pytest.raises(CertificateProblem, match="certificate has expired"):
            open_session([f"tls/127.0.0.1:{p1}"], tls_ca=ca)
        with pytest.raises(CertificateProblem, match="not valid for this name 'localhost'"):
            open_session([f"tls/localhost:{p2}"], tls_ca=ca)
        open_session([f"tls/127.0.0.1:{p2}"], tls_ca=ca).close()  # the name it was made for
        assert tls.probe(f"tls/127.0.0.1:{p2}", ca).warning == ""
    finally:
        r1.close()
        r2.close()
    soon = issue(yard_ca, tmp_path / "soon", ["127.0.0.1"], days=(-300, 10))  # still good, not for long
    r3 = raw_router(*soon, p3 := free_port())
    try:
        found = tls.probe(f"tls/127.0.0.1:{p3}", ca)
        assert found.kind == "ok" and "expires in 9 days" in found.warning, found
    finally:
        r3.close()
    with pytest.raises(CellUnreachable, match="nothing answers there") as down:
        open_session([f"tls/127.0.0.1:{free_port()}"], tls_ca=ca)
    assert not isinstance(down.value, (CertificateProblem, SessionRefused))
    # this client's own CA file: missing, not a certificate, not a CA, out of date
    with pytest.raises(CertificateProblem, match="does not exist"):
        open_session([f"tls/127.0.0.1:{p1}"], tls_ca=tmp_path / "nope.crt")
    (tmp_path / "junk.crt").write_text("not a certificate")
    with pytest.raises(CertificateProblem, match="holds no PEM certificate"):
        open_session([f"tls/127.0.0.1:{p1}"], tls_ca=tmp_path / "junk.crt")
    with pytest.raises(CertificateProblem, match="is not a CA certificate"):
        open_session([f"tls/127.0.0.1:{p1}"], tls_ca=only_ip[0])
    with pytest.raises(tls.CertificateError, match="CA certificate .* expired on"):
        tls.check_ca(ca, now=datetime.now(timezone.utc) + timedelta(days=4000))
    assert "expires in" in tls.check_ca(ca, now=datetime.now(timezone.utc) + timedelta(days=3640))[0]


def test_a_ca_file_with_the_old_and_the_new_ca_trusts_both_during_rotation(tmp_path, yard_ca):
    new = make_certs(tmp_path / "new-ca")
    bundle = tmp_path / "ca.crt"
    bundle.write_bytes((yard_ca / "ca.crt").read_bytes() + (new / "ca.crt").read_bytes())
    assert tls.check_ca(bundle) == []
    port = free_port()
    r = raw_router(new / "router.crt", new / "router.key", port)  # the router already moved to the new CA
    try:
        open_session([f"tls/127.0.0.1:{port}"], tls_ca=bundle).close()
        with pytest.raises(CertificateProblem, match="not signed by the CA"):
            open_session([f"tls/127.0.0.1:{port}"], tls_ca=yard_ca / "ca.crt")
    finally:
        r.close()


# --- a cell over TLS, configured by its own fields; and `cellctl doctor` ----------------------------
def test_a_cell_with_tls_ca_file_serves_an_operator_over_tls_and_doctor_checks_it(tmp_path, yard_ca):
    """`cellctl router` (shipped config, TLS only) with a real `cellctl serve` cell that trusts the CA through
    service.tls_ca_file (relative to its config; its credentials file names a wrong CA path, which the field
    overrides), an operator on the CLI with --ca runs a job, and the doctor checks the cell's certificates."""
    from cellctl.commissioning.doctor import check_network
    from cellctl.config import load_cell_config

    subprocess.run(["sh", str(ROOT / "deploy/make-users.sh"), str(tmp_path), "operator", "cell-sim-1"], check=True,
                   capture_output=True, timeout=30)
    pw = {u: (tmp_path / f"{u}.password").read_text().strip() for u in ("operator", "cell-sim-1")}
    port = free_port()
    router = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "router", "--users", str(tmp_path / "zenoh-users.txt"),
                               "--listen", f"tls/127.0.0.1:{port}", "--listen", f"tls/127.0.0.2:{port}",
                               "--tls-cert", str(yard_ca / "router.crt"),
                               "--tls-key", str(yard_ca / "router.key")], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    cell = None
    try:
        assert "listening on tls/127.0.0.1" in router.stderr.readline()
        ep = f"tls/localhost:{port}"
        (tmp_path / "cell").mkdir()
        creds = tmp_path / "cell" / "cell-sim-1.json5"
        creds.write_text((ROOT / "deploy/zenoh/cell.json5").read_text().replace("cell-<cell_id>", "cell-sim-1")
                         .replace("<PASSWORD>", pw["cell-sim-1"]).replace("/etc/scrapcell/tls/ca.crt", "/nonexistent.crt"))
        (tmp_path / "cell" / "ca.crt").write_bytes((yard_ca / "ca.crt").read_bytes())
        cfg_path = write_config(tmp_path / "cell" / "sim-1.yaml", free_port(), tmp_path / "data", cell_id="sim-1",
                                zenoh_mode="client", listen=[], connect=[ep], zenoh_config_file=creds.name,
                                tls_ca_file="ca.crt", job_profile="initial_view")
        cfg, _ = load_cell_config(cfg_path)
        ok = check_network(cfg, cfg_path)
        assert ok.ok and "trusted and valid for localhost" in ok.detail, ok
        cell = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "serve", "--config", str(cfg_path)], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        op = tmp_path / "operator.json5"
        op.write_text((ROOT / "deploy/zenoh/operator.json5").read_text().replace("<PASSWORD>", pw["operator"])
                      .replace("/etc/scrapcell/tls/ca.crt", "/nonexistent.crt"))
        with CellClient("sim-1", [ep], timeout_s=REPLY_S, zenoh_config_file=str(op), tls_ca=yard_ca / "ca.crt") as c:
            deadline = time.monotonic() + UP_S
            while not c.alive(0.5):
                assert cell.poll() is None and time.monotonic() < deadline, cell.stderr.read()[-2000:]
        cli = [sys.executable, "-m", "cellctl.cli"]
        common = ["--cell", "sim-1", "--connect", ep, "--zenoh-config", str(op), "--ca", str(yard_ca / "ca.crt"),
                  "--reply-timeout", str(REPLY_S)]
        sub = subprocess.run(cli + ["submit", "scan-drawing", *common, "--scene", "t_piece", "--wait"], cwd=ROOT, capture_output=True,
                             text=True, timeout=UP_S * 3)
        assert sub.returncode == 0 and "done" in sub.stdout, sub.stdout + sub.stderr
        # the same CLI without --ca (its credentials file names a CA that is not there): one clear line, exit 3
        bare = subprocess.run(cli + ["status", *common[:6]], cwd=ROOT, capture_output=True, text=True, timeout=UP_S)
        assert bare.returncode == 3 and "CA certificate /nonexistent.crt does not exist" in bare.stderr and \
            "Traceback" not in bare.stderr, bare.stderr
        # doctor: the router reached at an address its certificate does not list (127.0.0.2), then down
        wrong = check_network(cfg.model_copy(update={"service": cfg.service.model_copy(
            update={"connect": [f"tls/127.0.0.2:{port}"]})}), cfg_path)
        assert not wrong.ok and "not valid for this address" in wrong.detail, wrong
    finally:
        for proc in (cell, router):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=UP_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
    down = check_network(cfg, cfg_path)
    assert not down.ok and "nothing accepts a connection" in down.detail and "start the router" in down.fix
    plain = check_network(cfg.model_copy(update={"service": cfg.service.model_copy(
        update={"connect": [f"tcp/127.0.0.1:{port}"]})}), cfg_path)
    assert not plain.ok and "TLS only" in plain.detail


def test_the_tablet_app_joins_over_tls_with_its_ca_and_says_why_not_without(tls_router, yard_ca):
    """cellctl.tablet.yard: the app's session takes the tablet config's tls_ca; without it, the page banner
    (Yard.problem) names the missing CA instead of 'router down'."""
    from cellctl.tablet.config import TabletConfig
    from cellctl.tablet.yard import Yard

    ep = f"tls/localhost:{tls_router}"
    for ca, expect in ((yard_ca / "ca.crt", None), (None, "give the yard's CA certificate")):
        yard = Yard(TabletConfig(connect=[ep], tls_ca=ca, refresh_s=0.1)).start()
        try:
            deadline = time.monotonic() + UP_S
            while yard.problem == "connecting to the cell network" or (expect is None and yard.problem):
                assert time.monotonic() < deadline, yard.problem
                time.sleep(0.05)
            assert yard.problem is None if expect is None else expect in yard.problem, yard.problem
        finally:
            yard.stop()


def test_the_tablet_pages_are_served_over_https_with_a_certificate_from_the_yard_ca(tmp_path, yard_ca):
    """`make-certs.sh DIR tablet NAME`: the app serves its pages over HTTPS only, with a session cookie marked
    Secure (a page login never crosses the yard in clear); a key every user can read stops it at start."""
    import urllib.request

    from cellctl.tablet.loopback import TabletProcess

    _sh(str(yard_ca), "tablet", "localhost", "127.0.0.1")
    https = dict(https_cert=yard_ca / "tablet.crt", https_key=yard_ca / "tablet.key")
    users = {"ana": ("operator", "cut-steel-42")}
    with TabletProcess(tmp_path / "tab", f"tcp/127.0.0.1:{free_port()}", users, https_ca=yard_ca / "ca.crt",
                       **https) as tab:
        assert tab.url.startswith("https://")
        ctx = ssl.create_default_context(cafile=str(yard_ca / "ca.crt"))
        with urllib.request.urlopen(f"{tab.url}/login", timeout=REPLY_S, context=ctx) as r:
            cookies = r.headers.get_all("set-cookie") or []
            assert r.status == 200 and "Log in" in r.read().decode()
        assert cookies and all("secure" in c.lower() for c in cookies), cookies
        with pytest.raises(OSError):  # plain HTTP on the same port gets no page (the connection is closed)
            urllib.request.urlopen(f"http://127.0.0.1:{tab.port}/login", timeout=REPLY_S).read()
    os.chmod(yard_ca / "tablet.key", 0o644)
    try:
        bad = TabletProcess(tmp_path / "bad", f"tcp/127.0.0.1:{free_port()}", users, https_ca=yard_ca / "ca.crt",
                            **https)
        with pytest.raises(RuntimeError, match="readable by every user"):
            bad.start()
    finally:
        os.chmod(yard_ca / "tablet.key", 0o600)
