"""A client for the scrapcell job API written from docs/API.md alone.

It imports nothing of cellctl (only the standard library and eclipse-zenoh): it is the proof that
the documented contract is enough to write a client. Not a test module; use it like this:

    with RawCell("tcp/127.0.0.1:7447", "sim-1") as cell:
        sub = cell.subscribe_events(print)          # before submitting, as the doc says
        reply = cell.submit({"scene": "smooth_cylinder", "requested_by": "tablet-2"})
        record = cell.wait(reply["job_id"], timeout_s=600)
        cell.fetch(reply["job_id"], "cut_path.json", "/tmp")
        sub.undeclare()
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import threading
import time
import uuid

import zenoh

SCHEMA_VERSION = 1
TERMINAL_STATES = frozenset({"done", "failed", "cancelled", "interrupted"})
_JOB_ID = re.compile(r"^[0-9]{8}T[0-9]{6}Z-[0-9a-f]{6}$")            # JobRecord.job_id
_CELL_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")                       # CellStatus.cell_id
_FILE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}$")        # FileInfo.name
_REQUEST_ID = re.compile(r"^[A-Za-z0-9_.:-]{8,64}$")                  # ScanDrawingRequest.request_id
_SUBMIT_GAP_S = 0.2   # "Rate limit": a submit within 0.2 s of the previous one is dropped silently


class CellError(Exception):
    """An error reply (Zenoh reply_err with an ErrorReply payload) from the cell itself."""

    def __init__(self, code: str, message: str, details: list | None = None):
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.details = list(details or [])   # [{"loc": ..., "msg": ...}, ...]


class NoAnswer(TimeoutError):
    """No usable reply within the timeout: the cell is down, the key is not served (wrong cell id),
    access control or the router's rate limit dropped the query, or Zenoh ended it with its own
    `Timeout` error reply (or with no reply at all)."""


class RawCell:
    def __init__(self, endpoint: str, cell_id: str, timeout_s: float = 5.0):
        if not _CELL_ID.match(cell_id):
            raise ValueError(f"cell_id {cell_id!r} does not match {_CELL_ID.pattern}")
        self.cell_id = cell_id
        self.timeout_s = timeout_s
        self._prefix = f"cell/{cell_id}"
        self._subscribers: list = []
        self._last_submit = 0.0
        self._lock = threading.Lock()
        config = zenoh.Config()
        config.insert_json5("mode", json.dumps("client"))
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))
        config.insert_json5("scouting/multicast/enabled", "false")
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as e:   # nothing listens on the endpoint
            raise NoAnswer(f"cannot connect to {endpoint}: {e}") from e

    # -- session ------------------------------------------------------------------------------

    def close(self) -> None:
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception:
                pass   # already undeclared by the caller
        self._subscribers.clear()
        self._session.close()

    def __enter__(self) -> "RawCell":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- one query ----------------------------------------------------------------------------

    def _query(self, key: str, payload: dict | None = None, timeout_s: float | None = None) -> dict:
        """One Zenoh get; the first JSON reply wins. Ok -> dict, ErrorReply -> CellError,
        Zenoh's own `Timeout` (not JSON), a non-JSON reply or no reply at all -> NoAnswer."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        kwargs = {"timeout": timeout}
        if payload is not None:
            body = dict(payload)
            body.setdefault("schema_version", SCHEMA_VERSION)
            kwargs["payload"] = json.dumps(body, allow_nan=False).encode("utf-8")
            kwargs["encoding"] = zenoh.Encoding.APPLICATION_JSON
        t0 = time.monotonic()
        for reply in self._session.get(key, **kwargs):
            if reply.ok is not None:
                data = _json(reply.ok.payload)
                if isinstance(data, dict):
                    return data
            else:
                data = _json(reply.err.payload)
                if isinstance(data, dict) and isinstance(data.get("code"), str):
                    raise CellError(data["code"], str(data.get("message", "")), data.get("details"))
            # anything else (b"Timeout", garbage): not an answer from the cell; try the next reply
        raise NoAnswer(f"no reply on {key} (waited {time.monotonic() - t0:.1f} s of up to {timeout} s): "
                       "the cell is down, or access control denied this request")

    def _job_key(self, job_id: str, *rest: str) -> str:
        if not _JOB_ID.match(job_id):   # exact keys only: no '*', no '/'
            raise ValueError(f"job_id {job_id!r} does not match {_JOB_ID.pattern}")
        return "/".join((self._prefix, "jobs", job_id) + rest)

    # -- API ----------------------------------------------------------------------------------

    def status(self) -> dict:
        return self._query(f"{self._prefix}/status")

    def submit(self, request: dict, *, retries: int = 3, timeout_s: float | None = None) -> dict:
        """Submit a ScanDrawingRequest; returns the SubmitReply (check `duplicate`).

        Adds a request_id if there is none and, when no answer comes, sends the same request
        (request_id and all) again, at most `retries` attempts in all, with a growing pause.
        A CellError (queue_full, cell_not_ready, invalid_request, ...) is raised at once."""
        body = dict(request)
        body.setdefault("schema_version", SCHEMA_VERSION)
        body.setdefault("kind", "scan_drawing")
        if not body.get("request_id"):
            who = re.sub(r"[^A-Za-z0-9_.-]", "_", str(body.get("requested_by") or "raw"))[:27]
            body["request_id"] = f"{who}:{uuid.uuid4()}"   # <= 27 + 1 + 36 = 64 characters
        elif not _REQUEST_ID.match(str(body["request_id"])):
            raise ValueError(f"request_id {body['request_id']!r} does not match {_REQUEST_ID.pattern}")
        last: NoAnswer | None = None
        for attempt in range(max(1, retries)):
            if attempt:
                time.sleep(0.5 * 2 ** (attempt - 1))   # 0.5 s, 1 s, 2 s, ...
            with self._lock:   # keep this session's submits 0.2 s apart (the router drops closer ones)
                wait = self._last_submit + _SUBMIT_GAP_S - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                self._last_submit = time.monotonic()
            try:
                return self._query(f"{self._prefix}/jobs/submit", body, timeout_s)
            except NoAnswer as e:
                last = e
        raise NoAnswer(f"{last}; tried {max(1, retries)} times with request_id "
                       f"{body['request_id']}: keep the request and send it again later")

    def subscribe_events(self, callback) -> object:
        """Call callback(event: dict) for every JobEvent of this cell (all jobs: filter on
        event["job_id"]). Subscribe before submitting to see a job's first event. Returns the
        Zenoh subscriber (call .undeclare() to stop); close() undeclares it too."""
        def on_sample(sample) -> None:
            event = _json(sample.payload)
            if isinstance(event, dict):
                callback(event)
        sub = self._session.declare_subscriber(f"{self._prefix}/jobs/*/events", on_sample)
        self._subscribers.append(sub)
        return sub

    def job(self, job_id: str) -> dict:
        return self._query(self._job_key(job_id))

    def wait(self, job_id: str, timeout_s: float, poll_s: float = 1.0) -> dict:
        """Poll the JobRecord until the job is in a terminal state; returns that record.
        A read that gets no answer is simply asked again (the doc: "for reads just ask again").
        Raises TimeoutError when the job has not ended within timeout_s."""
        deadline = time.monotonic() + timeout_s
        state = "unknown (no answer)"
        while True:
            try:
                record = self.job(job_id)
                state = record.get("state")
                if state in TERMINAL_STATES:
                    return record
            except NoAnswer:
                pass
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"job {job_id} has not ended after {timeout_s} s (last state: {state})")
            time.sleep(min(poll_s, left))

    def files(self, job_id: str) -> dict:
        return self._query(self._job_key(job_id, "files"))

    def fetch(self, job_id: str, name: str, dest: str, chunk: int = 65536) -> dict:
        """Fetch one file of an ended job chunk by chunk into dest (a file path, or a directory
        to put `name` in); verifies the size and the SHA-256. Returns {"size": ..., "sha256": ...}.
        Raises CellError (not_ended, not_found, ...), NoAnswer, or ValueError on a mismatch."""
        if not _FILE_NAME.match(name):
            raise ValueError(f"file name {name!r} does not match {_FILE_NAME.pattern}")
        if not 1 <= chunk <= 524288:
            raise ValueError("chunk must be 1..524288 bytes (FileChunkRequest.length)")
        key = self._job_key(job_id, "files", name)
        path = os.path.join(dest, name) if os.path.isdir(dest) else dest
        part = path + ".part"
        try:
            for _restart in range(3):   # "if it [sha256] changes, start over"
                result = self._fetch_once(key, name, part, chunk)
                if result is not None:
                    os.replace(part, path)
                    return result
            raise ValueError(f"{name}: the file kept changing on the cell while it was fetched")
        finally:
            if os.path.exists(part):
                os.remove(part)

    def _fetch_once(self, key: str, name: str, part: str, chunk: int) -> dict | None:
        """One pass from offset 0; None when the file changed on the cell during it."""
        digest, offset, expected, size = hashlib.sha256(), 0, None, None
        with open(part, "wb") as out:
            while True:
                reply = self._read_chunk(key, offset, chunk)
                if reply.get("name") != name or reply.get("offset") != offset:
                    raise ValueError(f"{name}: asked for offset {offset}, got {reply.get('name')!r} "
                                     f"at {reply.get('offset')}")
                if expected is None:
                    expected, size = reply["sha256"], reply["size"]
                elif reply["sha256"] != expected or reply["size"] != size:
                    return None
                data = base64.b64decode(reply["data"], validate=True)
                if len(data) != reply["length"]:
                    raise ValueError(f"{name}: chunk at {offset} says {reply['length']} bytes, "
                                     f"carries {len(data)}")
                out.write(data)
                digest.update(data)
                offset += len(data)
                if reply["eof"]:
                    break
                if not data:
                    raise ValueError(f"{name}: empty chunk at {offset} of {size} without eof")
        got = digest.hexdigest()
        if offset != size or got != expected:
            raise ValueError(f"{name}: got {offset} bytes with SHA-256 {got}, "
                             f"the cell says {size} bytes with SHA-256 {expected}")
        return {"size": size, "sha256": got}

    def _read_chunk(self, key: str, offset: int, length: int, attempts: int = 3) -> dict:
        for attempt in range(attempts):
            try:
                return self._query(key, {"offset": offset, "length": length})
            except NoAnswer:
                if attempt == attempts - 1:
                    raise
                time.sleep(0.5 * 2 ** attempt)
        raise AssertionError("unreachable")


def _json(payload) -> object:
    """The payload as JSON, or None when it is not UTF-8 JSON (e.g. Zenoh's b"Timeout")."""
    if payload is None:
        return None
    try:
        return json.loads(payload.to_bytes().decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
