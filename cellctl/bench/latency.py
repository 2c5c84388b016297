"""Latency of the job API on loopback, for `cellctl bench` and the tests: a real `cellctl serve`
subprocess (cellctl.service.loopback), a real Zenoh client, nothing mocked.

    from cellctl.bench.latency import measure
    measure(n=100)  # -> {"status_rtt_ms": {...}, "submit_to_first_event_ms": {...}, ...}
"""

from __future__ import annotations

import json
import sys
import tempfile
import threading
import time
from pathlib import Path

from cellctl.bench.stats import summary
from cellctl.service.loopback import ServiceProcess


def measure(n: int = 100, *, submits: int | None = None, workdir: str | Path | None = None) -> dict:
    """Start a service on loopback and measure, in milliseconds:
    - status_rtt_ms: ``n`` status queries while idle, and ``n`` while a scan runs (the worker thread
      and the Zenoh callbacks share the GIL);
    - submit_to_first_event_ms: from sending a submit to receiving its "queued" event (``submits``
      of them, default min(n, 20), made while a scan runs and cancelled while still queued, so only one
      scan ever runs, itself cancelled after its first view); submit_to_first_event_idle_ms: the one
      submit made while the cell was idle;
    - job_start_ms: from the first submit to its first step event (twin built, first view captured).
    """
    from cellctl.service.api import ScanDrawingRequest

    submits = min(n, 20) if submits is None else submits
    tmp = tempfile.TemporaryDirectory(prefix="scrapcell-svcbench-") if workdir is None else None
    wd = Path(workdir) if workdir else Path(tmp.name)
    svc = ServiceProcess(wd, queue_max=max(submits + 1, 2))
    out: dict = {"n": n, "endpoint": "", "pid": None}
    try:
        svc.start()
        out.update(endpoint=svc.endpoint, pid=svc.proc.pid, service_startup_s=round(svc.startup_s, 3))
        with svc.client() as c:
            c.status()  # warm the path
            out["status_rtt_idle_ms"] = summary([_timed(c.status) for _ in range(n)])
            first_step = threading.Event()
            t_sub = time.perf_counter()
            t_step: list[float] = []

            t_first: list[float] = []

            def on(ev):
                if not t_first:
                    t_first.append(time.perf_counter())
                if ev.step is not None and not first_step.is_set():
                    t_step.append(time.perf_counter())
                    first_step.set()

            long = ScanDrawingRequest(scene="smooth_cylinder", max_steps=6, noise=False)
            job = c.submit(long, on_event=on).job_id
            if not first_step.wait(120):
                raise TimeoutError("the scan did not reach its first step within 120 s")
            out["submit_to_first_event_idle_ms"] = round(1e3 * (t_first[0] - t_sub), 3)
            out["job_start_ms"] = round(1e3 * (t_step[0] - t_sub), 1)
            out["status_rtt_busy_ms"] = summary([_timed(c.status) for _ in range(n)])
            lat = []
            for _ in range(submits):
                got = threading.Event()
                t0 = time.perf_counter()
                t_ev: list[float] = []
                reply = c.submit(long, on_event=lambda ev, t=t_ev, g=got: (t.append(time.perf_counter()), g.set()))
                if got.wait(10):
                    lat.append(1e3 * (t_ev[0] - t0))
                c.cancel(reply.job_id)
            out["submit_to_first_event_ms"] = summary(lat)
            c.cancel(job)
            c.wait(job, 60)
        rc, exit_s = svc.stop()
        out.update(exit_status=rc, sigterm_to_exit_s=round(exit_s, 3))
    finally:
        svc.kill()
        if tmp is not None:
            tmp.cleanup()
    return out


def status_under_scan(clients: int = 10, hz: float = 20.0, *, scene: str = "basket", planner: str = "gnbv",
                      idle_s: float = 5.0, workdir: str | Path | None = None) -> dict:
    """Status round trips (ms) of ``clients`` Zenoh sessions, each querying at ``hz``, first for
    ``idle_s`` with the cell idle, then for the whole of one scan job (``scene``, ``planner``, the
    cell config's twin and steps) from its first step to its terminal event. A client sends on a
    fixed schedule; a late reply delays only that client's next query (no backlog). Queries
    that fail or go unanswered are counted, not timed."""
    from cellctl.service.api import ScanDrawingRequest
    from cellctl.service.client import CellError, NoReply

    tmp = tempfile.TemporaryDirectory(prefix="scrapcell-statusload-") if workdir is None else None
    wd = Path(workdir) if workdir else Path(tmp.name)
    svc = ServiceProcess(wd)
    phase = {"now": "idle"}
    ms: dict[str, list[float]] = {"idle": [], "scan": []}
    lost: dict[str, int] = {"idle": 0, "scan": 0}
    lock, stop = threading.Lock(), threading.Event()

    def poll(c) -> None:
        due = time.monotonic()
        while not stop.is_set():
            now = phase["now"]
            try:
                t = _timed(c.status)
            except (CellError, NoReply):
                with lock:
                    lost[now] += 1
            else:
                if phase["now"] == now:  # the phase did not change under this query
                    with lock:
                        ms[now].append(t)
            due = max(due + 1.0 / hz, time.monotonic())
            stop.wait(due - time.monotonic())

    out: dict = {"clients": clients, "hz": hz, "scene": scene, "planner": planner}
    try:
        svc.start()
        sessions = [svc.client() for _ in range(clients)]
        pollers = [threading.Thread(target=poll, args=(c,), daemon=True) for c in sessions]
        try:
            for c in sessions:
                c.__enter__()
                c.status()  # warm the path
            for t in pollers:
                t.start()
            time.sleep(idle_s)
            phase["now"] = "between"
            ms["between"], lost["between"] = [], 0
            stepped, ended = threading.Event(), threading.Event()

            def on(ev):
                if ev.step is not None:
                    phase["now"] = "scan"
                    stepped.set()
                if ev.state in ("done", "failed", "cancelled", "interrupted"):
                    phase["now"] = "between"
                    ended.set()

            with svc.client() as c:
                t0 = time.monotonic()
                job = c.submit(ScanDrawingRequest(scene=scene, planner=planner, noise=False), on_event=on).job_id
                if not ended.wait(600):
                    raise TimeoutError("the scan did not end within 600 s")
                rec = c.job(job)
            out.update(job_state=rec.state, job_s=round(time.monotonic() - t0, 1),
                       views=rec.result.steps if rec.result else None)
        finally:
            stop.set()
            for t in pollers:
                t.join(30)
            for c in sessions:
                c.__exit__(None, None, None)
        out["status_rtt_idle_ms"] = summary(ms["idle"])
        out["status_rtt_scan_ms"] = summary(ms["scan"])
        out["failed_or_unanswered"] = {k: v for k, v in lost.items() if k != "between"}
        svc.stop()
    finally:
        svc.kill()
        if tmp is not None:
            tmp.cleanup()
    return out


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - t0)


if __name__ == "__main__":
    print(json.dumps(measure(int(sys.argv[1]) if len(sys.argv) > 1 else 100), indent=2))
