"""`cellctl tablet`: the web app's process. Its session secret and NiceGUI's per-browser storage live in
the config's state_dir; the accounts file is read again whenever it changes (AccountBook)."""

from __future__ import annotations

import logging
import os
import secrets
from pathlib import Path

from cellctl.tablet.accounts import AccountBook
from cellctl.tablet.config import TabletConfig

log = logging.getLogger("cellctl.tablet")


def session_secret(state_dir: Path) -> str:
    """A random secret kept in state_dir (0600): logins survive a restart, and no two tablets share one."""
    path = Path(state_dir) / "session.secret"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32))
    return path.read_text().strip()


def serve(cfg: TabletConfig) -> None:
    accounts = AccountBook(cfg.accounts_file)  # before anything starts: no accounts, no app
    https = {}
    if cfg.https_cert:
        from cellctl import tls

        try:
            for warning in tls.check_server_pair(cfg.https_cert, cfg.https_key, who="tablet app"):
                log.warning(warning)
        except tls.CertificateError as e:
            raise ValueError(str(e)) from None
        # the session cookie only over HTTPS, so a page login never leaves the tablet in clear
        https = {"ssl_certfile": str(cfg.https_cert), "ssl_keyfile": str(cfg.https_key),
                 "session_middleware_kwargs": {"https_only": True}}
    secret = session_secret(cfg.state_dir)
    os.environ["NICEGUI_STORAGE_PATH"] = str(Path(cfg.state_dir).resolve() / "storage")  # read at import
    from nicegui import app, ui

    from cellctl.tablet.pages import register
    from cellctl.tablet.yard import Yard

    yard = Yard(cfg)
    app.on_startup(yard.start)
    app.on_shutdown(yard.stop)
    register(cfg, yard, accounts)
    log.info("tablet app on %s://%s:%d, cells via %s (%s)", "https" if https else "http", cfg.host, cfg.port,
             ", ".join(cfg.connect), cfg.zenoh_mode)
    ui.run(host=cfg.host, port=cfg.port, title=cfg.title, storage_secret=secret, reload=False, show=False,
           show_welcome_message=False, favicon="🔥", reconnect_timeout=10.0, **https)
