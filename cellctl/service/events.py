"""A job's events: numbered per job, stored as the job's progress, then published on
``cell/<id>/jobs/<job_id>/events``; in that order, so a client that hears an event can read the record
that says the same. Publication never raises: a lost event must not fail the job."""

from __future__ import annotations

import logging
import threading
from typing import Callable

import zenoh

from cellctl.service.api import TERMINAL_STATES, JobEvent, Keys, Progress, dumps
from cellctl.service.store import JobStore, now_iso

log = logging.getLogger("cellctl.service.events")


class JobEvents:
    def __init__(self, store: JobStore, keys: Keys, session: Callable[[], object | None]):
        self.store, self.keys, self._session = store, keys, session
        self._lock = threading.Lock()
        self._seq: dict[str, int] = {}

    def emit(self, job_id: str, phase: str, state: str, *, step: int | None = None, max_steps: int | None = None,
             coverage_percent: float | None = None, drawing_points: int | None = None,
             message: str | None = None) -> None:
        """Number, store and publish one event; what it does not say is carried from the last one (a
        new "queued" carries no step). A job this process has not numbered yet (one a previous process
        left unfinished) goes on from its last stored event."""
        with self._lock:
            last = None
            if job_id not in self._seq or max_steps is None or step is None or coverage_percent is None:
                rec = self.store.get(job_id)
                last = rec.progress if rec else None
            seq = self._seq[job_id] + 1 if job_id in self._seq else (last.seq + 1 if last is not None else 0)
            self._seq[job_id] = seq
            at = now_iso()
            if max_steps is None or step is None or coverage_percent is None:
                if last is not None:
                    max_steps = max_steps if max_steps is not None else last.max_steps
                    if phase != "queued":
                        step = step if step is not None else last.step
                        coverage_percent = coverage_percent if coverage_percent is not None else last.coverage_percent
                        drawing_points = drawing_points if drawing_points is not None else last.drawing_points
            ev = JobEvent(job_id=job_id, seq=seq, phase=phase, state=state, step=step, max_steps=max_steps,
                          coverage_percent=coverage_percent, drawing_points=drawing_points, time=at,
                          message=message[:2000] if message else None)
            self.store.set_progress(job_id, Progress(phase=phase, seq=seq, step=step, max_steps=max_steps,
                                                     coverage_percent=coverage_percent,
                                                     drawing_points=drawing_points, at=at))
            if phase in TERMINAL_STATES:
                self._seq.pop(job_id, None)
            session = self._session()
            if session is None:
                return
            try:
                session.put(self.keys.events(job_id), dumps(ev), encoding=zenoh.Encoding.APPLICATION_JSON)
            except Exception as e:  # noqa: BLE001 - session closing
                log.warning("event %s/%d not published: %s", job_id, seq, e)
