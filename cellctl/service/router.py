"""The yard's Zenoh router as a Python process: no zenohd package installs here, and a session opened
in router mode is a real router (cells and tablets connect to it as clients; it routes queries,
replies and events, and enforces authentication and access control from its config). It listens on
TLS only: over plain TCP every password, job and cutting path would cross the yard network readable."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

import zenoh

from cellctl import tls


def router_config(path: str | Path, listen: list[str] | None = None, users_file: str | None = None,
                  tls_cert: str | None = None, tls_key: str | None = None) -> "zenoh.Config":
    """The router's config from a JSON5 file, with the listen endpoints, credential file or TLS
    certificate and key replaced (a test or a second router on one host)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"router config {p} does not exist")
    try:
        cfg = zenoh.Config.from_file(str(p))
    except Exception as e:  # zenoh raises its own error type for a bad file
        raise ValueError(f"router config {p} is not a valid Zenoh config: {e}") from None
    cfg.insert_json5("mode", '"router"')
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(listen))
    if users_file:
        if not Path(users_file).is_file():
            raise ValueError(f"credential file {users_file} does not exist (make it with deploy/make-users.sh)")
        cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users_file)))
    if tls_cert:
        cfg.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(tls_cert)))
    if tls_key:
        cfg.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(tls_key)))
    plain = [ep for ep in tls.config_value(cfg, "listen/endpoints") or [] if not tls.is_tls(ep)]
    if plain:
        raise ValueError(f"the yard router listens on TLS only, not on {', '.join(plain)}: use tls/HOST:PORT "
                         f"(over tcp/ passwords and jobs cross the network in the clear)")
    return cfg


def check_certificates(cfg: "zenoh.Config", path: str | Path) -> list[str]:
    """ValueError unless the router's certificate and key are there, in date, a pair, and private
    (Zenoh would fail on the first client's handshake, or serve an expired certificate); warnings."""
    cert = tls.config_value(cfg, "transport/link/tls/listen_certificate")
    key = tls.config_value(cfg, "transport/link/tls/listen_private_key")
    if not (cert and key):
        raise ValueError(f"{path} sets no transport.link.tls.listen_certificate / listen_private_key: make them "
                         f"with deploy/make-certs.sh, or pass --tls-cert and --tls-key")
    try:
        return tls.check_server_pair(cert, key)
    except tls.CertificateError as e:
        raise ValueError(str(e)) from None


def check_credentials(cfg: "zenoh.Config", path: str | Path) -> None:
    """ValueError when the router would start without the credential file its config names (Zenoh
    would fail with a traceback-sized error)."""
    configured = tls.config_value(cfg, "transport/auth/usrpwd/dictionary_file")  # None: a router without passwords
    if configured and not Path(configured).is_file():
        raise ValueError(f"credential file {configured} (transport.auth.usrpwd.dictionary_file in {path}) does not "
                         f"exist: make it with deploy/make-users.sh DIR USER..., or pass --users FILE")


def run_router(cfg: "zenoh.Config", stop: threading.Event | None = None) -> None:
    """Serve until SIGINT/SIGTERM (or `stop`), then close the session: an unclosed session can keep
    the process alive for minutes."""
    stop = stop or threading.Event()
    session = zenoh.open(cfg)
    try:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: stop.set())
        print(f"zenoh router {session.zid()} listening on {', '.join(tls.config_value(cfg, 'listen/endpoints') or [])}",
              file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        session.close()
        print("zenoh router closed", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="cellctl router", description=__doc__)
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[2] / "deploy/zenoh/router.json5"),
                    help="router JSON5 config (default: deploy/zenoh/router.json5)")
    ap.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                    help="listen endpoint, e.g. tcp/127.0.0.1:7447 (repeatable; default: the config's)")
    ap.add_argument("--users", default=None, help="user:password file (default: the config's dictionary_file)")
    ap.add_argument("--tls-cert", default=None, help="the router's certificate (default: the config's "
                    "transport.link.tls.listen_certificate; deploy/make-certs.sh makes it)")
    ap.add_argument("--tls-key", default=None, help="the router's private key (default: the config's listen_private_key)")
    args = ap.parse_args(argv)
    try:
        cfg = router_config(args.config, args.listen, args.users, args.tls_cert, args.tls_key)
        check_credentials(cfg, args.config)
        for warning in check_certificates(cfg, args.config):
            print(f"cellctl router: warning: {warning}", file=sys.stderr)
    except ValueError as e:
        print(f"cellctl router: {e}", file=sys.stderr)
        return 2
    try:
        run_router(cfg)
    except zenoh.ZError as e:  # e.g. the listen address is taken
        print(f"cellctl router: cannot start: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
