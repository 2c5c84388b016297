"""Page logins: user, role and a salted scrypt hash (hashlib), kept in a YAML file the app only reads.

An operator starts and cancels jobs; a viewer sees everything and commands nothing. The role is checked
on the server for every command, not only by hiding buttons."""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import secrets
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field

from cellctl.tablet.config import USER_PATTERN
from configs.loading import load_yaml_model

log = logging.getLogger("cellctl.tablet.accounts")
Role = Literal["operator", "viewer"]
# scrypt's cost: 16 MiB and ~50 ms a check, so a stolen file costs an attacker as much per guess
N, R, P = 2**14, 8, 1
MIN_PASSWORD = 8


class Account(BaseModel):
    model_config = ConfigDict(extra="forbid")

    user: str = Field(pattern=USER_PATTERN)
    role: Role
    scrypt: str = Field(pattern=r"^[0-9]+\$[0-9]+\$[0-9]+\$[0-9a-f]{32}\$[0-9a-f]{64}$",
                        description="n$r$p$salt$hash, made by `cellctl tablet --add-user`")


class Accounts(BaseModel):
    model_config = ConfigDict(extra="forbid")

    accounts: list[Account] = Field(default_factory=list)

    def check(self, user: str, password: str) -> Account | None:
        """The account if the password is right; the hash is computed even for an unknown user, so the
        answer's timing does not tell which users exist."""
        acct = next((a for a in self.accounts if a.user == user), None)
        stored = acct.scrypt if acct else f"{N}${R}${P}${'0' * 32}${'0' * 64}"
        ok = hmac.compare_digest(_hash(password, stored), stored)
        return acct if acct and ok else None


def _hash(password: str, like: str) -> str:
    n, r, p, salt, _ = like.split("$")
    digest = hashlib.scrypt(password.encode(), salt=bytes.fromhex(salt), n=int(n), r=int(r), p=int(p),
                            maxmem=64 * 1024 * 1024, dklen=32)
    return f"{n}${r}${p}${salt}${digest.hex()}"


def hash_password(password: str) -> str:
    if len(password) < MIN_PASSWORD:
        raise ValueError(f"a password needs at least {MIN_PASSWORD} characters")
    return _hash(password, f"{N}${R}${P}${secrets.token_hex(16)}$")


def load_accounts(path: Path) -> Accounts:
    if not Path(path).is_file():
        raise ValueError(f"{path}: no accounts file; add a login with "
                         f"`cellctl tablet --config <tablet.yaml> --add-user NAME --role operator`")
    accts = load_yaml_model(path, Accounts, what="accounts")
    if not accts.accounts:
        raise ValueError(f"{path}: no accounts; add one with `cellctl tablet --add-user NAME --role operator`")
    names = [a.user for a in accts.accounts]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: a user is listed twice")
    return accts


def _write(path: Path, accts: Accounts) -> None:
    """0600, atomically: the running app never reads half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        yaml.safe_dump(accts.model_dump(), f, sort_keys=False)
    os.replace(tmp, path)


def add_user(path: Path, user: str, role: Role, password: str) -> Account:
    """Add or replace ``user`` in the accounts file."""
    path = Path(path)
    accts = load_yaml_model(path, Accounts, what="accounts") if path.is_file() else Accounts()
    acct = Account(user=user, role=role, scrypt=hash_password(password))
    accts.accounts = [a for a in accts.accounts if a.user != user] + [acct]
    _write(path, accts)
    return acct


def remove_user(path: Path, user: str) -> None:
    """Take ``user``'s login away (a lost tablet, someone who left): a running app ends its pages' sessions
    at their next refresh or command (AccountBook)."""
    path = Path(path)
    accts = load_accounts(path)
    if not any(a.user == user for a in accts.accounts):
        raise ValueError(f"{path} has no login {user!r} (it has: {', '.join(a.user for a in accts.accounts)})")
    accts.accounts = [a for a in accts.accounts if a.user != user]
    _write(path, accts)


class AccountBook:
    """The accounts file as the running app sees it, read again whenever it changes: a login removed or
    given another role takes effect at once, without a restart. A file that is gone or unreadable lets
    nobody in (and says so in the log) rather than keeping logins that were meant to end."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._accounts = load_accounts(self.path)  # no accounts at start: the app does not start
        self._stamp = self._stat()

    def _stat(self) -> tuple[int, int] | None:
        try:
            st = self.path.stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    def current(self) -> Accounts:
        stamp = self._stat()
        if stamp != self._stamp:
            try:
                self._accounts = load_accounts(self.path)
            except ValueError as e:
                log.warning("accounts: %s; nobody can log in until it is mended", e)
                self._accounts = Accounts()
            self._stamp = stamp
        return self._accounts

    def check(self, user: str, password: str) -> Account | None:
        return self.current().check(user, password)

    def lookup(self, user: str) -> Account | None:
        return next((a for a in self.current().accounts if a.user == user), None)
