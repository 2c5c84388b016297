"""A small client of the job API for the operator tablet (and `cellctl submit/jobs/status`).

Needs only zenoh and pydantic. Every call either returns a reply model, raises CellError (the cell
answered with an error code), or raises NoReply: with Zenoh access control a denied query is not
answered at all, so "no reply" means "the cell is down, or you may not ask this"."""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import re
import socket
import threading
import time
import uuid
from pathlib import Path
from typing import Callable, TypeVar

import zenoh
from pydantic import BaseModel, ValidationError

from cellctl import tls
from cellctl.service.api import (CHUNK_DEFAULT, TERMINAL_STATES, CancelReply, CancelRequest, CellStatus, ErrorReply,
                                 FileChunk, FileChunkRequest, FileInfo, FileList, JobEvent, JobList, JobRecord, Keys,
                                 ListJobsRequest, ScanDrawingRequest, SubmitReply, dumps)
from cellctl.service.api import CommissionPaintReply, CommissionPaintRequest, PaintReply

log = logging.getLogger("cellctl.service.client")
M = TypeVar("M", bound=BaseModel)
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def zenoh_error(e: Exception) -> str:
    """Zenoh's message without the Rust source locations it appends."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(e)).strip()


class CellError(RuntimeError):
    """The cell answered with an error reply (docs/API.md lists the codes)."""

    def __init__(self, code: str, message: str, details: list | None = None):
        super().__init__(f"{code}: {message}")
        self.code, self.message, self.details = code, message, details or []


class NoReply(TimeoutError):
    """No reply at all: the cell is down, unreachable, or access control denied the request."""


class CellUnreachable(ConnectionError):
    """The Zenoh session could not be opened: nothing answers at the endpoints, or (``SessionRefused``)
    something does and refused this session."""


class SessionRefused(CellUnreachable):
    """A router (or cell) answers at an endpoint but refused the Zenoh session: wrong user or password."""


class CertificateProblem(CellUnreachable):
    """TLS does not fit: this client's CA file is missing, unreadable or out of date, or the router's
    certificate is expired, not signed by that CA, or made for another name."""


class Subscription:
    def __init__(self, sub):
        self._sub = sub
        self.ended = False  # the job's terminal event was delivered

    def close(self) -> None:
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except Exception:  # noqa: BLE001 - session already closed
                pass
            self._sub = None


def _accepts_tcp(endpoint: str, timeout_s: float = 2.0) -> bool:
    """Whether a TCP (or TLS) endpoint accepts a connection: tells a router that refused the session
    from one that is not there."""
    parsed = tls.split_endpoint(endpoint)
    if not parsed or parsed[0] not in ("tcp", "tls"):
        return False
    try:
        with socket.create_connection(parsed[1:], timeout=timeout_s):
            return True
    except OSError:
        return False


def open_config(conf: zenoh.Config, connect: list[str], creds: str) -> zenoh.Session:
    """Open a session that connects to ``connect``; on failure, say why (``creds``: where this client's
    user and password are, for the message). Raises CertificateProblem (certificates), SessionRefused
    (something answers and refused the session: credentials), CellUnreachable (nothing answers)."""
    ca = tls.configured_ca(conf)
    secure = [ep for ep in connect if tls.is_tls(ep)]
    if secure:
        if not ca:
            raise CertificateProblem(f"{', '.join(secure)} is TLS: give the yard's CA certificate (--ca FILE, "
                                     f"tls_ca in a config, or transport.link.tls.root_ca_certificate in the Zenoh "
                                     f"config)")
        try:
            for warning in tls.check_ca(ca):
                log.warning(warning)
        except tls.CertificateError as e:
            raise CertificateProblem(str(e)) from None
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        why = zenoh_error(e)
    found = [tls.probe(ep, ca) if tls.is_tls(ep) else
             tls.Probe(ep, "plain" if _accepts_tcp(ep) else "down") for ep in connect]
    bad = [p.message for p in found if p.kind == "certificate"]
    if bad:
        raise CertificateProblem("; ".join(bad) + f" ({why})")
    plain_to_tls = [p.endpoint for p in found if p.kind == "plain" and tls.speaks_tls(p.endpoint)]
    if plain_to_tls:
        raise CertificateProblem(f"{', '.join(plain_to_tls)} speaks TLS: connect with tls/ instead of tcp/ and the "
                                 f"yard's CA certificate ({why})")
    other = [p.message for p in found if p.kind == "not-tls"]
    if other:
        raise CellUnreachable("; ".join(other) + f" ({why})")
    listening = [p.endpoint for p in found if p.kind in ("ok", "plain")]
    if listening:
        raise SessionRefused(f"{', '.join(listening)} answers but refused this session: check {creds} ({why})")
    raise CellUnreachable(f"cannot reach the cell network at {', '.join(connect) or '(scouting)'}: "
                          f"nothing answers there ({why})")


def open_session(connect: list[str] | tuple[str, ...] = (DEFAULT_ENDPOINT,), *, mode: str = "client",
                 zenoh_config_file: str | None = None, tls_ca: str | Path | None = None) -> zenoh.Session:
    """A Zenoh session to the cell network (a cell's endpoint or the yard router); ``tls_ca``: the
    yard's CA certificate, for tls/ endpoints. Raises what open_config raises."""
    connect = list(connect)
    try:
        conf = zenoh.Config.from_file(zenoh_config_file) if zenoh_config_file else zenoh.Config()
    except zenoh.ZError as e:
        raise ValueError(f"Zenoh config {zenoh_config_file}: {zenoh_error(e)}") from None
    conf.insert_json5("mode", json.dumps(mode))
    if tls_ca:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tls_ca)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("scouting/multicast/enabled", "false")
    creds = f"the user and password in {zenoh_config_file}" if zenoh_config_file else \
        "whether it needs a user and password (--zenoh-config, see deploy/zenoh/operator.json5)"
    return open_config(conf, connect, creds)


class CellClient:
    def __init__(self, cell_id: str, connect: list[str] | tuple[str, ...] = (DEFAULT_ENDPOINT,), *,
                 timeout_s: float = 5.0, mode: str = "client", zenoh_config_file: str | None = None,
                 session: zenoh.Session | None = None, tls_ca: str | Path | None = None):
        """``session``: use this open Zenoh session (one app serving many cells, e.g. the tablet) instead
        of opening one; it stays open when this client closes."""
        self.keys = Keys(cell_id)
        self.cell_id, self.timeout_s, self.connect = cell_id, timeout_s, list(connect)
        self._subs: list[Subscription] = []
        self._owns_session = session is None
        if session is not None:
            self.session = session
            return
        self.session = open_session(self.connect, mode=mode, zenoh_config_file=zenoh_config_file, tls_ca=tls_ca)

    def __enter__(self) -> CellClient:
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    def close(self) -> None:
        """Close the session explicitly: an unclosed session can hang the interpreter's exit."""
        if self.session is not None:
            for sub in self._subs:
                sub.close()
            self._subs.clear()
            if self._owns_session:
                self.session.close()
            self.session = None

    # --- queries ----------------------------------------------------------------------------------
    def _query(self, key: str, model: type[M], payload: bytes | None = None, timeout_s: float | None = None) -> M:
        t = self.timeout_s if timeout_s is None else timeout_s
        for reply in self.session.get(key, payload=payload, timeout=t):
            if reply.ok is not None:
                try:
                    return model.model_validate_json(reply.ok.payload.to_bytes())
                except ValidationError as e:
                    raise CellError("bad_reply", f"{key}: the cell's reply does not match this client's API "
                                                 f"({model.__name__}): {e.errors()[0]['msg']}") from None
            raw = reply.err.payload.to_bytes()
            if raw == b"Timeout":  # Zenoh's own error reply once a timeout is up (this session's, or a peer's
                break              # or router's on the way); the cell's errors are ErrorReply JSON
            try:
                err = ErrorReply.model_validate_json(raw)
            except ValidationError:
                raise CellError("bad_reply", f"{key}: {raw[:300]!r}") from None
            raise CellError(err.code, err.message, [d.model_dump() for d in err.details])
        raise NoReply(f"no reply from cell {self.cell_id!r} to {key} (waited up to {t:g} s): the cell is down, "
                      f"or access control denied this request")

    def status(self, timeout_s: float | None = None) -> CellStatus:
        return self._query(self.keys.status, CellStatus, timeout_s=timeout_s)

    def paint(self) -> PaintReply:
        """The paint the cell's jobs look for."""
        return self._query(self.keys.paint, PaintReply)

    def commission_paint(self, request: CommissionPaintRequest | dict, timeout_s: float = 60.0) -> CommissionPaintReply:
        """Learn the yard's paint from a sample in front of the camera (a few seconds; the cell must be idle)."""
        req = request if isinstance(request, CommissionPaintRequest) else CommissionPaintRequest.model_validate(request)
        return self._query(self.keys.paint_commission, CommissionPaintReply, payload=req.model_dump_json().encode(),
                           timeout_s=timeout_s)

    def submit(self, request: ScanDrawingRequest | dict | bytes,
               on_event: Callable[[JobEvent], None] | None = None, *, attempts: int = 3) -> SubmitReply:
        """Queue a job. With ``on_event`` the job's events are delivered from the very first one
        ("queued"): the subscription is made before the submit, so none is missed.

        A request without a ``request_id`` gets one (a random UUID), so a submit whose reply is lost
        is sent again, up to ``attempts`` times, without queueing the job twice: the cell answers a
        known request_id with the job it made (``duplicate``). 3 attempts in all, 0.5 s then 1 s apart, as
        docs/API.md advises a tablet. Raw bytes are sent once, as they are."""
        if isinstance(request, bytes):
            payload, attempts = request, 1
        else:
            if isinstance(request, dict):
                request = request if "request_id" in request else {**request, "request_id": uuid.uuid4().hex}
                payload = json.dumps(request).encode()
            else:
                if request.request_id is None:
                    request = request.model_copy(update={"request_id": uuid.uuid4().hex})
                payload = dumps(request)
        if on_event is None:
            return self._submit(payload, attempts)
        self._reap()
        buffered: dict[str, list[JobEvent]] = {}
        target: list[str] = []
        lock = threading.Lock()  # held while delivering: buffered and live events never overtake each other

        def deliver(ev: JobEvent) -> None:
            with lock:
                if not target:
                    buffered.setdefault(ev.job_id, []).append(ev)
                elif ev.job_id == target[0] and not sub.ended:
                    sub.ended = ev.phase in TERMINAL_STATES
                    _call(on_event, ev)

        sub = self._subscribe(self.keys.all_events, deliver)
        try:
            reply = self._submit(payload, attempts)
        except BaseException:
            sub.close()
            raise
        self._subs.append(sub)
        with lock:
            target.append(reply.job_id)
            for ev in sorted(buffered.pop(reply.job_id, []), key=lambda e: e.seq):
                sub.ended = sub.ended or ev.phase in TERMINAL_STATES
                _call(on_event, ev)
            buffered.clear()
        return reply

    def _submit(self, payload: bytes, attempts: int) -> SubmitReply:
        attempt = 1
        while True:
            try:
                return self._query(self.keys.submit, SubmitReply, payload)
            except NoReply:
                if attempt >= attempts:
                    raise
                log.warning("no reply to submit (attempt %d of %d); sending it again with the same request_id",
                            attempt, attempts)
                time.sleep(0.5 * attempt)  # 0.5 s, 1 s: past the yard router's 0.2 s between submits
                attempt += 1

    def _reap(self) -> None:
        """Drop the subscriptions of submitted jobs that have ended (not from inside their callback)."""
        for sub in [s for s in self._subs if s.ended]:
            sub.close()
            self._subs.remove(sub)

    def job(self, job_id: str) -> JobRecord:
        return self._query(self.keys.job(job_id), JobRecord)

    def jobs(self, limit: int = 20, state: str | None = None) -> JobList:
        return self._query(self.keys.jobs, JobList, dumps(ListJobsRequest(limit=limit, state=state)))

    def cancel(self, job_id: str, reason: str | None = None) -> CancelReply:
        return self._query(self.keys.cancel(job_id), CancelReply, dumps(CancelRequest(reason=reason)))

    def files(self, job_id: str) -> FileList:
        """The files of an ended job's folder, with their sizes and SHA-256."""
        return self._query(self.keys.files(job_id), FileList)

    def fetch(self, job_id: str, name: str, dest: Path, chunk: int = CHUNK_DEFAULT) -> FileInfo:
        """One file of an ended job, chunk by chunk, into ``dest`` (written beside it and renamed once its
        SHA-256 matches: a file that arrived damaged or changed on the way is never left there)."""
        tmp = dest.with_name(dest.name + ".part")
        h, offset, first = hashlib.sha256(), 0, None
        with open(tmp, "wb") as out:
            while True:
                c = self._query(self.keys.file(job_id, name), FileChunk,
                                dumps(FileChunkRequest(offset=offset, length=chunk)))
                first = first or c
                if (c.size, c.sha256) != (first.size, first.sha256) or c.offset != offset:
                    tmp.unlink(missing_ok=True)
                    raise CellError("bad_reply", f"{name}: the file changed while it was fetched")
                data = base64.b64decode(c.data, validate=True)
                h.update(data)
                out.write(data)
                offset += len(data)
                if c.eof or not data:
                    break
        if h.hexdigest() != first.sha256 or offset != first.size:
            tmp.unlink(missing_ok=True)
            raise CellError("bad_reply", f"{name}: {offset} bytes with SHA-256 {h.hexdigest()[:12]}..., the cell "
                                         f"says {first.size} bytes, {first.sha256[:12]}...")
        tmp.replace(dest)
        return FileInfo(name=name, size=first.size, sha256=first.sha256)

    def alive(self, timeout_s: float = 2.0) -> bool:
        """Is the cell's liveliness token there (the service is up and ready)?"""
        return any(r.ok is not None for r in self.session.liveliness().get(self.keys.alive, timeout=timeout_s))

    # --- events -----------------------------------------------------------------------------------
    def events(self, job_id: str | None, callback: Callable[[JobEvent], None]) -> Subscription:
        """Events of one job (or of every job: ``job_id=None``), delivered on a Zenoh thread."""
        return self._subscribe(self.keys.events(job_id) if job_id else self.keys.all_events,
                               lambda ev: _call(callback, ev))

    def _subscribe(self, key: str, deliver: Callable[[JobEvent], None]) -> Subscription:
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                ev = JobEvent.model_validate_json(sample.payload.to_bytes())
            except ValidationError as e:
                log.warning("ignored an event on %s that does not match the API: %s", sample.key_expr, e)
                return
            deliver(ev)

        return Subscription(self.session.declare_subscriber(key, on_sample))

    def wait(self, job_id: str, timeout_s: float, on_event: Callable[[JobEvent], None] | None = None,
             poll_s: float = 2.0) -> JobRecord:
        """Until the job ends: woken by its terminal event, and re-reading the record every ``poll_s``
        in case an event was lost. TimeoutError if it is still going after ``timeout_s``."""
        ended = threading.Event()

        def on(ev: JobEvent) -> None:
            if on_event:
                _call(on_event, ev)
            if ev.phase in TERMINAL_STATES:
                ended.set()

        sub = self._subscribe(self.keys.events(job_id), on)
        try:
            deadline = time.monotonic() + timeout_s
            while True:
                rec = self.job(job_id)
                if rec.state in TERMINAL_STATES:
                    return rec
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"job {job_id} is still {rec.state} after {timeout_s:g} s")
                ended.wait(min(poll_s, left))
        finally:
            sub.close()


def _call(cb: Callable[[JobEvent], None], ev: JobEvent) -> None:
    try:
        cb(ev)
    except Exception:  # noqa: BLE001 - a client callback bug must not kill Zenoh's thread
        log.exception("event callback failed")
