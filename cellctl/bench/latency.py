"""Latency of the job API on loopback, for `cellctl bench` and the tests: a real `cellctl serve`
subprocess (cellctl.service.loopback), a real Zenoh client, nothing mocked.

    from cellctl.bench.latency import measure
    measure(n=100)  # -> {"status_rtt_ms": {...}, "submit_to_first_event_ms": {...}, ...}
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

from cellctl.service.loopback import ServiceProcess


def _stats(xs: list[float]) -> dict:
    xs = sorted(xs)
    q = lambda p: xs[min(len(xs) - 1, int(p * len(xs)))]  # noqa: E731
    return {"n": len(xs), "median": round(statistics.median(xs), 3), "p90": round(q(0.9), 3),
            "min": round(xs[0], 3), "max": round(xs[-1], 3)}


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
            out["status_rtt_idle_ms"] = _stats([_timed(c.status) for _ in range(n)])
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
            out["status_rtt_busy_ms"] = _stats([_timed(c.status) for _ in range(n)])
            lat = []
            for _ in range(submits):
                got = threading.Event()
                t0 = time.perf_counter()
                t_ev: list[float] = []
                reply = c.submit(long, on_event=lambda ev, t=t_ev, g=got: (t.append(time.perf_counter()), g.set()))
                if got.wait(10):
                    lat.append(1e3 * (t_ev[0] - t0))
                c.cancel(reply.job_id)
            out["submit_to_first_event_ms"] = _stats(lat) if lat else None
            c.cancel(job)
            c.wait(job, 60)
        rc, exit_s = svc.stop()
        out.update(exit_status=rc, sigterm_to_exit_s=round(exit_s, 3))
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
