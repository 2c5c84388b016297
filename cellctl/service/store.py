"""The job store: every job's request, state transitions, progress, result summary and error in SQLite
(stdlib sqlite3, WAL), so a restarted service still lists past jobs and serves their results, and a job
that was queued or running when the service died is marked `interrupted`, never silently lost.

One connection guarded by a lock: the Zenoh callback threads and the worker thread all write a few rows
per job, far from any contention that would call for a pool."""

from __future__ import annotations

import json
import sqlite3
import threading
from datetime import datetime, timezone
from pathlib import Path

from cellctl.service.api import (TERMINAL_STATES, Artifacts, JobBrief, JobRecord, Progress, ResultSummary,
                                 ScanDrawingRequest, Transition)

STORE_SCHEMA = 1

# state -> the states it may go to; anything else is a bug the store refuses
ALLOWED: dict[str, frozenset[str]] = {
    "queued": frozenset({"running", "cancelled", "interrupted"}),
    "running": frozenset({"cancelling", "done", "failed", "cancelled", "interrupted"}),
    "cancelling": frozenset({"done", "failed", "cancelled", "interrupted"}),
    **{s: frozenset() for s in TERMINAL_STATES},
}

_DDL = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,          -- creation order: the list is newest first
    job_id TEXT NOT NULL UNIQUE,
    cell_id TEXT NOT NULL,
    request TEXT NOT NULL,                         -- ScanDrawingRequest JSON
    state TEXT NOT NULL,
    created_at TEXT NOT NULL,
    updated_at TEXT NOT NULL,
    progress TEXT,                                 -- Progress JSON
    result TEXT,                                   -- ResultSummary JSON
    error TEXT,
    artifacts TEXT                                 -- Artifacts JSON
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state);
-- a client's idempotency key names one job at most (a store written before keys existed gains the index)
CREATE UNIQUE INDEX IF NOT EXISTS jobs_request_id ON jobs(json_extract(request, '$.request_id'))
    WHERE json_extract(request, '$.request_id') IS NOT NULL;
CREATE TABLE IF NOT EXISTS transitions (
    job_id TEXT NOT NULL REFERENCES jobs(job_id),
    n INTEGER NOT NULL,
    state TEXT NOT NULL,
    at TEXT NOT NULL,
    note TEXT,
    PRIMARY KEY (job_id, n)
);
"""


class StoreError(RuntimeError):
    """A store misuse (unknown job, forbidden transition) or an unreadable database."""


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class JobStore:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        try:
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=10.0)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")  # a job's end must survive a power cut, writes are few
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.executescript(_DDL)
            row = self._db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
            if row is None:
                self._db.execute("INSERT INTO meta VALUES ('schema', ?)", (str(STORE_SCHEMA),))
            elif int(row[0]) != STORE_SCHEMA:
                raise StoreError(f"{self.path}: store schema {row[0]}, this version reads {STORE_SCHEMA}")
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path}: cannot open the job store: {e}") from None

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # --- writes -----------------------------------------------------------------------------------
    def create(self, job_id: str, cell_id: str, request: ScanDrawingRequest, artifacts_dir: str,
               at: str | None = None) -> None:
        at = at or now_iso()
        arts = Artifacts(dir=artifacts_dir).model_dump_json()
        with self._lock, self._db:
            self._db.execute("BEGIN IMMEDIATE")
            self._db.execute("INSERT INTO jobs (job_id, cell_id, request, state, created_at, updated_at, artifacts) "
                             "VALUES (?, ?, ?, 'queued', ?, ?, ?)",
                             (job_id, cell_id, request.model_dump_json(), at, at, arts))
            self._db.execute("INSERT INTO transitions VALUES (?, 0, 'queued', ?, NULL)", (job_id, at))

    def by_request_id(self, request_id: str) -> tuple[str, ScanDrawingRequest, str] | None:
        """(job id, request, state) of the job submitted with this idempotency key, if any."""
        with self._lock:
            row = self._db.execute("SELECT job_id, request, state FROM jobs WHERE json_extract(request, "
                                   "'$.request_id') = ?", (request_id,)).fetchone()
        if row is None:
            return None
        return row[0], ScanDrawingRequest.model_validate_json(row[1]), row[2]

    def transition(self, job_id: str, state: str, note: str | None = None, *, result: ResultSummary | None = None,
                   error: str | None = None, artifacts: Artifacts | None = None) -> str:
        """Move the job to ``state`` (checked against ALLOWED) and, in the same transaction, keep its
        result/error/artifacts. Returns the previous state."""
        at = now_iso()
        with self._lock, self._db:
            self._db.execute("BEGIN IMMEDIATE")
            row = self._db.execute("SELECT state FROM jobs WHERE job_id=?", (job_id,)).fetchone()
            if row is None:
                raise StoreError(f"no job {job_id}")
            prev = row[0]
            if state not in ALLOWED[prev]:
                raise StoreError(f"job {job_id}: {prev} -> {state} is not a valid transition")
            n = self._db.execute("SELECT COALESCE(MAX(n), -1) + 1 FROM transitions WHERE job_id=?", (job_id,)).fetchone()[0]
            self._db.execute("INSERT INTO transitions VALUES (?, ?, ?, ?, ?)", (job_id, n, state, at, note))
            sets, args = ["state=?", "updated_at=?"], [state, at]
            if result is not None:
                sets.append("result=?")
                args.append(result.model_dump_json())
            if error is not None:
                sets.append("error=?")
                args.append(error)
            if artifacts is not None:
                sets.append("artifacts=?")
                args.append(artifacts.model_dump_json())
            self._db.execute(f"UPDATE jobs SET {', '.join(sets)} WHERE job_id=?", (*args, job_id))
        return prev

    def set_progress(self, job_id: str, progress: Progress) -> None:
        with self._lock, self._db:
            self._db.execute("UPDATE jobs SET progress=?, updated_at=? WHERE job_id=?",
                             (progress.model_dump_json(), progress.at, job_id))

    def recover(self, note: str, *, requeue: bool = True) -> tuple[list[str], list[str]]:
        """At start, the jobs a service that died left unfinished: (interrupted, still queued), oldest
        first. A job that was running or cancelling is interrupted, what it wrote kept and listed; a
        queued one never started and stays queued (``requeue``), else it is interrupted too."""
        with self._lock:
            rows = self._db.execute("SELECT job_id, state, artifacts FROM jobs WHERE state IN ('queued', "
                                    "'running', 'cancelling') ORDER BY id").fetchall()
        interrupted, queued = [], []
        for job_id, state, arts in rows:
            if state == "queued" and requeue:
                queued.append(job_id)
                continue
            self.transition(job_id, "interrupted", note, error=f"interrupted: {note}", artifacts=_on_disk(arts))
            interrupted.append(job_id)
        return interrupted, queued

    # --- reads ------------------------------------------------------------------------------------
    def get(self, job_id: str) -> JobRecord | None:
        with self._lock:
            row = self._db.execute("SELECT job_id, cell_id, request, state, created_at, updated_at, progress, result, "
                                   "error, artifacts FROM jobs WHERE job_id=?", (job_id,)).fetchone()
            if row is None:
                return None
            trans = self._db.execute("SELECT state, at, note FROM transitions WHERE job_id=? ORDER BY n",
                                     (job_id,)).fetchall()
        jid, cell, req, state, created, updated, prog, res, err, arts = row
        return JobRecord(
            job_id=jid, cell_id=cell, request=ScanDrawingRequest.model_validate_json(req), state=state,
            created_at=created, updated_at=updated,
            transitions=[Transition(state=s, at=a, note=n) for s, a, n in trans][-50:],
            progress=Progress.model_validate_json(prog) if prog else None,
            result=ResultSummary.model_validate_json(res) if res else None,
            error=err[:2000] if err else None,
            artifacts=_existing(arts))

    def state(self, job_id: str) -> str | None:
        with self._lock:
            row = self._db.execute("SELECT state FROM jobs WHERE job_id=?", (job_id,)).fetchone()
        return row[0] if row else None

    def list(self, limit: int = 20, state: str | None = None) -> tuple[list[JobBrief], int]:
        """Newest first, at most ``limit``; and how many match in all."""
        where, args = ("WHERE state=?", (state,)) if state else ("", ())
        with self._lock:
            total = self._db.execute(f"SELECT COUNT(*) FROM jobs {where}", args).fetchone()[0]
            rows = self._db.execute(f"SELECT job_id, state, created_at, updated_at, request, result, error FROM jobs "
                                    f"{where} ORDER BY id DESC LIMIT ?", (*args, limit)).fetchall()
        out = []
        for jid, st, created, updated, req, res, err in rows:
            r = json.loads(req)
            cov = json.loads(res).get("coverage_percent") if res else None
            out.append(JobBrief(job_id=jid, state=st, created_at=created, updated_at=updated, scene=r["scene"],
                                planner=r["planner"], coverage_percent=cov, error=_first_line(err)))
        return out, total

    def ended_folders(self) -> list[tuple[str, str, Path]]:
        """(job id, when it ended, its folder) of every ended job with a folder, oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT job_id, updated_at, artifacts FROM jobs WHERE state IN ('done', 'failed', "
                                    "'cancelled', 'interrupted') AND artifacts IS NOT NULL ORDER BY id").fetchall()
        return [(jid, at, Path(Artifacts.model_validate_json(arts).dir)) for jid, at, arts in rows]

    def count(self) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM jobs").fetchone()[0]


def _first_line(text: str | None, n: int = 200) -> str | None:
    if not text:
        return None
    line = text.strip().splitlines()[0] if text.strip() else text
    return line if len(line) <= n else line[: n - 1] + "…"


def _existing(artifacts_json: str | None) -> Artifacts | None:
    """The record's artifacts as stored, if its folder exists (a job that never ran has none; a folder
    removed later, e.g. by retention, is not pointed at)."""
    if not artifacts_json:
        return None
    arts = Artifacts.model_validate_json(artifacts_json)
    return arts if Path(arts.dir).is_dir() else None


def _on_disk(artifacts_json: str | None) -> Artifacts | None:
    """The record's artifacts with the files its folder holds now (None when it has no folder)."""
    if not artifacts_json:
        return None
    try:
        arts = Artifacts.model_validate_json(artifacts_json)
        d = Path(arts.dir)
        files = sorted(p.name for p in d.iterdir() if p.is_file()) if d.is_dir() else []
    except (OSError, ValueError):  # an unreadable folder must not keep the service from starting
        return None
    return Artifacts(dir=arts.dir, files=files[:100])
