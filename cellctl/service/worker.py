"""The jobs' own process. The service runs every job in one worker process that owns the devices
while a job runs and sends its progress and result back through a pipe; a worker that dies is
replaced by a new one for the next job.

Why a process: pybullet, Open3D and numba hold the interpreter's lock for long stretches, so in
the service's own interpreter status queries waited behind them; and a crash in their native code
would take the API down with the job. Why one worker for the cell's life and not one per job: a
worker's imports and the twin's first build take seconds, longer than a load test's whole job; the
FCI rule holds either way, because a job opens the arm and camera itself and closes them before it
reports its result (cellctl.scan.run), and the service's idle readiness probe waits for that report.
A worker that crashes or is killed has closed its libfranka session with the process."""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from cellctl.scan.result import ResultFile
from cellctl.scan.spec import JobSpec
from cellctl.service import logs
from cellctl.service.api import ResultSummary

log = logging.getLogger("cellctl.service.worker")
#: a cancelled job that has not ended this long after the cancel has its worker killed (a scan
#: checks its cancel between moves and stops the arm mid-move; the cut's planning takes seconds)
KILL_AFTER_S = 30.0


@dataclass
class Outcome:
    """How a job ended in the worker: its summary (None if there is none), its error."""

    summary: ResultSummary | None
    error: str | None
    crashed: bool  # the worker died before it sent the result


class Worker:
    """The worker process and its pipes; a new one when the last one died."""

    def __init__(self) -> None:
        self._ctx = mp.get_context("spawn")  # never fork a process that runs Zenoh's threads
        self.proc = None
        self._jobs = self._msgs = None
        self._stop = self._ctx.Event()  # the running job's cancel, as the worker sees it
        self._stopped_as = self._ctx.Array("c", 32)  # and what it means: cancelled, timeout, interrupted

    def start(self) -> None:
        """Start the worker if none is running (it imports the scan's libraries before the first
        job). Call it from the thread that runs the jobs: a worker dies with the thread that
        started it (``_die_with``)."""
        if self.proc is not None and self.proc.is_alive():
            return
        jobs_end, self._jobs = self._ctx.Pipe(duplex=False)  # (receiving end, sending end)
        self._msgs, msgs_end = self._ctx.Pipe(duplex=False)
        self.proc = self._ctx.Process(target=_worker_main, args=(jobs_end, msgs_end, self._stop, self._stopped_as,
                                                                      os.getpid()),
                                      name="cell-job-worker")
        self.proc.start()
        jobs_end.close()  # the worker holds these ends: EOF on ours when it is gone
        msgs_end.close()
        log.info("job worker started (pid %d)", self.proc.pid)

    def run(self, spec: JobSpec, cancel: threading.Event, *, on_step: Callable[[dict], None],
            on_phase: Callable[[str], None], stopped_as: Callable[[], str] = lambda: "cancelled") -> Outcome:
        """Run one job in the worker and wait for its result. ``cancel`` (operator, timeout,
        shutdown) is passed on, with ``stopped_as()``, the result's terminated_by; a worker still busy ``KILL_AFTER_S`` later is killed. A worker that
        dies without a result (a crash in native code, killed) gives a crashed Outcome, the summary
        of whatever result.json the job wrote, and an error that says how it died."""
        self.start()
        self._stop.clear()
        self._stopped_as.value = b""
        summary, error, cancelled_at, got_result = None, None, None, False
        try:
            self._jobs.send(spec)
            while not got_result:
                if cancel.is_set() and cancelled_at is None:
                    self._stopped_as.value = stopped_as().encode()[:31]
                    self._stop.set()
                    cancelled_at = time.monotonic()
                if cancelled_at is not None and time.monotonic() - cancelled_at > KILL_AFTER_S and self.proc.is_alive():
                    log.error("job %s: the worker did not stop %.0f s after the cancel; killing it",
                              spec.run_dir.name, KILL_AFTER_S)
                    self.proc.kill()
                if not self._msgs.poll(0.1):
                    if not self.proc.is_alive() and not self._msgs.poll(0):
                        break
                    continue
                kind, *body = self._msgs.recv()
                if kind == "step":
                    on_step(body[0])
                elif kind == "phase":
                    on_phase(body[0])
                elif kind == "result":
                    got_result = True
                    summary = ResultSummary.model_validate_json(body[0]) if body[0] else None
                    error = body[1]
        except (EOFError, OSError):  # the worker's end closed: it is gone
            pass
        if got_result:
            return Outcome(summary, error, False)
        self.proc.join(5.0)
        code = self.proc.exitcode
        how = (f"was killed by {signal.Signals(-code).name}" if code is not None and code < 0
               else f"exited with status {code}")
        error = f"the job's worker process {how} before the job ended (pid {self.proc.pid}); what it wrote is kept"
        self.close()
        return Outcome(summary_from_file(spec.run_dir / "result.json"), error, True)

    def close(self, timeout_s: float = 5.0) -> None:
        """End the worker: asked to, then killed (a job still running holds the arm). Idempotent."""
        proc, self.proc = self.proc, None
        if proc is not None:
            try:
                self._jobs.send(None)
            except (OSError, ValueError):
                pass
            proc.join(timeout_s)
            if proc.is_alive():
                log.error("killing the job worker (pid %d)", proc.pid)
                proc.kill()
                proc.join(5.0)
        for conn in (self._jobs, self._msgs):
            if conn is not None:
                conn.close()
        self._jobs = self._msgs = None


def _die_with(parent_pid: int) -> None:
    """The worker ends when the service does, however the service ends (SIGKILL included): an
    orphan would go on moving the arm, hold its FCI session against the restarted service and
    write into a job the restarted service has already marked interrupted (Linux: the parent's
    death signal, sent when the thread that started the worker ends: the service's job thread,
    which lives as long as the service)."""
    PR_SET_PDEATHSIG = 1
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL))
    except (OSError, AttributeError):  # not Linux: the broken pipe ends the worker at its next step
        pass
    if os.getppid() != parent_pid:  # the service died before the signal was armed
        os._exit(1)


def _worker_main(jobs, msgs, stop, stopped_as, parent_pid: int) -> None:
    """The worker process: run each job it is sent, report each step and phase, then the result;
    None ends it."""
    _die_with(parent_pid)
    logs.setup()
    # A Ctrl-C in the terminal reaches the whole process group, and systemd stops every process of
    # the unit: the service decides how its job ends, so here both only ask the job to stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    import cellctl.scan.initial_view  # noqa: F401 - the heavy imports, before the first job
    from cellctl.scan.run import run_job
    from cellctl.scan.spec import Hooks

    while True:
        try:
            spec = jobs.recv()
        except (EOFError, OSError):
            return
        if spec is None:
            return

        def on_step(r) -> None:
            msgs.send(("step", {"step": r.step, "coverage_percent": r.coverage_percent,
                                "drawing_points": r.drawing_points}))

        try:
            hooks = Hooks(cancel=stop, stopped_as=lambda: stopped_as.value.decode() or "interrupted", on_step=on_step,
                          on_phase=lambda p: msgs.send(("phase", p)))  # unexplained: a SIGTERM to the worker
            result, _ = run_job(spec, hooks)
            msgs.send(("result", result.summary().model_dump_json(), result.error))
        except Exception as e:  # noqa: BLE001 - a failed job: say why, keep what was written
            summary = summary_from_file(spec.run_dir / "result.json")
            msgs.send(("result", summary.model_dump_json() if summary else None, f"{type(e).__name__}: {e}"))


def summary_from_file(path: Path) -> ResultSummary | None:
    """The summary of a result.json a job wrote, or None when there is none (or it is unreadable)."""
    try:
        return ResultFile.model_validate_json(path.read_text()).summary()
    except Exception:  # noqa: BLE001 - no (readable) partial result: the record says why the job failed
        return None
