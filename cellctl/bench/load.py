"""The load test of the job API on loopback (docs/RELIABILITY.md, "Load"): a real `cellctl serve`
subprocess, ``clients`` Zenoh sessions submitting ``jobs`` jobs into a queue bounded by
``service.queue_max`` (each retries after a short back-off on ``queue_full``), a poller querying status
and jobs at ``hz`` throughout, a subscriber to every job event and a sampler of the service's RSS.
Afterwards the store is read back to check that no job was lost, duplicated, ended twice or started out
of order. Nothing is mocked; the jobs are real twin jobs (``service.job_profile``, cellctl.scan.initial_view).

    from cellctl.bench.load import LoadSpec, run_load
    doc = run_load(LoadSpec(jobs=200, clients=10, hz=50))   # doc["checks"][name]["ok"], doc["figures"]

Clients are threads of one process: their submit latencies include this process's GIL; the service,
the thing measured, runs alone in its own process."""

from __future__ import annotations

import json
import os
import random
import shutil
import sqlite3
import statistics
import tempfile
import threading
import time
from collections import Counter, defaultdict
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from cellctl.bench.stats import summary
from cellctl.service.api import TERMINAL_STATES

# the cheapest twin the D435 model supports: 640x480 (4:3 crop, square pixels) and no dynamics
FAST_TWIN = {"twin": {"camera": {"width": 640, "height": 480, "hfov_deg": 55.0}, "execution": "teleport"}}
JOB = {"scene": "smooth_cylinder", "max_steps": 1, "noise": False}


@dataclass
class LoadSpec:
    jobs: int = 200
    clients: int = 10
    hz: float = 50.0  # poller ticks per second; each tick is a status query and a jobs query
    queue_max: int = 8  # below the number of clients: their first round alone fills it, so the bound is hit
    profile: str = "initial_view"  # service.job_profile: initial_view (0.3 s jobs) or scan (the full job)
    backoff_s: float = 0.5  # after queue_full a client waits backoff_s * (1 + U(0, 1)): 13 tries/s for 3 jobs/s
    job: dict = field(default_factory=lambda: dict(JOB))
    fast_twin: bool = True
    job_timeout_s: float = 120.0
    timeout_s: float = 1800.0  # the whole run, a safety net
    reply_timeout_s: float = 5.0
    peak_rss_max_mb: float = 1536.0  # checks: the service's VmHWM (its job worker's added) ...
    rss_growth_max_mb: float = 64.0  # ... and its RSS trend from job rss_from to the last job
    rss_from: int = 50
    threads_growth_max: int = 4  # the lanes of Zenoh's runtime may still be starting; a thread per job is a leak


# --- small helpers --------------------------------------------------------------------------------
def process_tree(pid: int) -> list[int]:
    """``pid`` and its live descendants: the service, its job worker (cellctl.service.worker) and
    multiprocessing's resource tracker."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:  # ended meanwhile
            pass
    return out


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS, VmHWM (kB) and Threads of a live process and its descendants together, from
    /proc/<pid>/status: the service's jobs run in its worker process, and their memory is the cell's."""
    out = {"VmRSS": 0, "VmHWM": 0, "Threads": 0}
    for i, p in enumerate(process_tree(pid)):
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    key, _, val = line.partition(":")
                    if key in out:
                        out[key] += int(val.split()[0])
        except OSError:
            if i == 0:  # the service itself is gone
                raise
    return out


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a live process and its descendants (/proc/<pid>/stat)."""
    total = 0.0
    for i, p in enumerate(process_tree(pid)):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            if i == 0:
                raise
            continue
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


# --- the actors -----------------------------------------------------------------------------------
class Submitter(threading.Thread):
    """One client session submitting ``n`` jobs in turn; on queue_full it backs off and retries."""

    def __init__(self, idx: int, n: int, make_client, spec: LoadSpec, go: threading.Barrier,
                 stop: threading.Event, known: list[str]):
        super().__init__(name=f"load-client-{idx}", daemon=True)
        self.idx, self.n, self.make_client, self.spec = idx, n, make_client, spec
        self.go, self.stop, self.known = go, stop, known
        self.accepted: list[dict] = []  # job_id, queue_position, at (monotonic), in submit order
        self.submit_ms: list[float] = []  # every submit that got a reply, accepted or refused
        self.queue_full = 0
        self.uncoded = 0  # error replies the client could not parse as an ErrorReply
        self.other_codes: Counter = Counter()
        self.no_reply = 0
        self.errors: list[str] = []  # the first few refusals other than queue_full, for the report
        self.exc: str | None = None

    def run(self) -> None:
        from cellctl.service.client import CellError, NoReply

        req = {**self.spec.job, "requested_by": f"load-{self.idx}"}
        rng = random.Random(self.idx)
        try:
            with self.make_client() as c:
                self.go.wait()
                for _ in range(self.n):
                    while not self.stop.is_set():
                        t0 = time.perf_counter()
                        try:
                            r = c.submit(req)
                        except CellError as e:
                            self.submit_ms.append(1e3 * (time.perf_counter() - t0))
                            if e.code == "queue_full" and e.message:
                                self.queue_full += 1
                            elif e.code == "bad_reply":
                                self.uncoded += 1
                            else:
                                self.other_codes[e.code] += 1
                            if e.code != "queue_full" and len(self.errors) < 3:
                                self.errors.append(str(e)[:300])
                            self.stop.wait(self.spec.backoff_s * (1 + rng.random()))
                            continue
                        except NoReply as e:  # unknown whether it was queued: a retry may make a phantom job
                            self.no_reply += 1
                            if len(self.errors) < 3:
                                self.errors.append(str(e)[:300])
                            continue
                        self.submit_ms.append(1e3 * (time.perf_counter() - t0))
                        self.accepted.append({"job_id": r.job_id, "queue_position": r.queue_position,
                                              "at": time.monotonic()})
                        self.known.append(r.job_id)
                        break
        except Exception as e:  # noqa: BLE001 - reported as a failed check, not a hung run
            self.exc = f"{type(e).__name__}: {e}"


class Poller(threading.Thread):
    """Open loop, like many tablets: at ``hz`` ticks per second, whether or not earlier queries have
    been answered, a status query and a jobs query (the list, then a random known job's record,
    alternately), sent from a pool of ``lanes`` threads sharing one session. A reply that is slow
    does not lower the rate offered; it shows up as latency (and as tick lateness if every lane is busy)."""

    def __init__(self, make_client, hz: float, known: list[str], stop: threading.Event, lanes: int = 8):
        super().__init__(name="load-poller", daemon=True)
        self.make_client, self.period, self.known, self.stop, self.lanes = make_client, 1.0 / hz, known, stop, lanes
        self.ms: dict[str, list[float]] = {"status": [], "jobs_list": [], "job_record": []}
        self.late_ms: list[float] = []  # from a tick's scheduled time to its first query being sent
        self.failed: Counter = Counter()  # "kind: code"
        self.unanswered: Counter = Counter()
        self.errors: list[str] = []  # the first few, for the report
        self.ticks = 0
        self.max_queue_length = 0
        self.t_run = 0.0
        self.exc: str | None = None
        self._rng = random.Random(0)
        self._lock = threading.Lock()

    def _one(self, kind: str, fn) -> None:
        from cellctl.service.client import CellError, NoReply

        t0 = time.perf_counter()
        try:
            r = fn()
        except CellError as e:
            with self._lock:
                self.failed[f"{kind}: {e.code}"] += 1
                self.errors += [str(e)[:300]] if len(self.errors) < 5 else []
            return
        except NoReply as e:
            with self._lock:
                self.unanswered[kind] += 1
                self.errors += [str(e)[:300]] if len(self.errors) < 5 else []
            return
        with self._lock:
            self.ms[kind].append(1e3 * (time.perf_counter() - t0))
            if kind == "status":
                self.max_queue_length = max(self.max_queue_length, r.queue_length)

    def _tick(self, c, n: int, due: float) -> None:
        with self._lock:
            self.late_ms.append(1e3 * max(0.0, time.monotonic() - due))
            job_id = self._rng.choice(self.known) if n % 2 and self.known else None
        self._one("status", c.status)
        if job_id is None:
            self._one("jobs_list", lambda: c.jobs(limit=20))
        else:
            self._one("job_record", lambda: c.job(job_id))

    def run(self) -> None:
        from concurrent.futures import ThreadPoolExecutor

        try:
            with self.make_client() as c, ThreadPoolExecutor(self.lanes, thread_name_prefix="load-poll") as pool:
                t_start = due = time.monotonic()
                while not self.stop.is_set():
                    pool.submit(self._tick, c, self.ticks, due)
                    self.ticks += 1
                    due += self.period
                    self.stop.wait(max(0.0, due - time.monotonic()))
                self.t_run = time.monotonic() - t_start
        except Exception as e:  # noqa: BLE001
            self.exc = f"{type(e).__name__}: {e}"


class EventLog:
    """Every job event (from the subscriber's Zenoh thread); wakes the waiter when jobs end."""

    def __init__(self):
        self.by_job: dict[str, list[tuple[int, str]]] = defaultdict(list)
        self.ended: set[str] = set()
        self.terminal_events = 0
        self._cv = threading.Condition()

    def __call__(self, ev) -> None:
        with self._cv:
            self.by_job[ev.job_id].append((ev.seq, ev.phase))
            if ev.phase in TERMINAL_STATES:
                self.terminal_events += 1
                self.ended.add(ev.job_id)
                self._cv.notify_all()

    def wait_ended(self, ids: set[str], timeout_s: float) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: ids <= self.ended, timeout_s)


class RssSampler(threading.Thread):
    """The service's RSS every ``period`` s, with how many jobs had ended by then."""

    def __init__(self, pid: int, events: EventLog, stop: threading.Event, period: float = 0.1):
        super().__init__(name="load-rss", daemon=True)
        self.pid, self.events, self.stop, self.period = pid, events, stop, period
        self.samples: list[tuple[float, int, int, int]] = []  # (t s, jobs ended, VmRSS kB, threads)

    def run(self) -> None:
        t0 = time.monotonic()
        while True:
            stopping = self.stop.wait(self.period)  # one more sample once stopped: the state after the last job
            try:
                st = proc_status(self.pid)
            except OSError:
                return
            self.samples.append((round(time.monotonic() - t0, 2), len(self.events.ended), st["VmRSS"], st["Threads"]))
            if stopping:
                return

    def rss_mb_after(self, n_jobs: int) -> float | None:
        """RSS at the first sample taken once ``n_jobs`` jobs had ended."""
        s = next((s for s in self.samples if s[1] >= n_jobs), None)
        return round(s[2] / 1024, 1) if s else None

    def rss_trend_mb(self, from_job: int) -> float | None:
        """RSS growth from job ``from_job`` to the last one along the least-squares line through every
        sample in between: a job's own transient allocations (tens of MB in a full scan) make any two
        single samples differ by that much; a leak is a slope."""
        pts = [(n, kb / 1024) for _, n, kb, _ in self.samples if n >= from_job]
        if len(pts) < 2 or pts[-1][0] == pts[0][0]:
            return None
        slope, _ = statistics.linear_regression([p[0] for p in pts], [p[1] for p in pts])
        return slope * (pts[-1][0] - pts[0][0])

    def threads_after(self, n_jobs: int) -> int | None:
        s = next((s for s in self.samples if s[1] >= n_jobs), None)
        return s[3] if s else None


# --- the run --------------------------------------------------------------------------------------
def run_load(spec: LoadSpec = LoadSpec(), workdir: str | Path | None = None, *, log_to: Path | None = None) -> dict:
    """Run the load test: a dict with "spec", "figures", "checks" (name -> ok, detail), "ok", and
    "raw" (the orders, transitions and events the checks were made on, so they can be re-checked).
    ``workdir`` keeps the service's config, store and job folders (default: a temp dir, removed);
    ``log_to``: copy the service's log there."""
    from cellctl.service.loopback import ServiceProcess

    if spec.jobs < 1 or spec.clients < 1 or spec.hz <= 0:
        raise ValueError("--jobs and --clients must be >= 1 and --hz > 0")
    if spec.rss_from >= spec.jobs:  # a short run: measure the growth over its last three quarters
        spec = replace(spec, rss_from=max(1, spec.jobs // 4))
    tmp = tempfile.TemporaryDirectory(prefix="scrapcell-load-") if workdir is None else None
    wd = Path(workdir) if workdir else Path(tmp.name)
    svc = ServiceProcess(wd, queue_max=spec.queue_max, job_profile=spec.profile, job_timeout_s=spec.job_timeout_s,
                         cell=FAST_TWIN if spec.fast_twin else None)
    load_before = os.getloadavg()
    t_begin = time.monotonic()
    try:
        svc.start()
        pid = svc.proc.pid
        make_client = lambda: svc.client(timeout_s=spec.reply_timeout_s)  # noqa: E731
        stop_submit, stop_watch = threading.Event(), threading.Event()
        known: list[str] = []
        events = EventLog()
        go = threading.Barrier(spec.clients + 1)
        share = [spec.jobs // spec.clients + (i < spec.jobs % spec.clients) for i in range(spec.clients)]
        submitters = [Submitter(i, n, make_client, spec, go, stop_submit, known) for i, n in enumerate(share)]
        with make_client() as watch:
            sub = watch.events(None, events)
            sampler = RssSampler(pid, events, stop_watch)
            poller = Poller(make_client, spec.hz, known, stop_watch)
            cpu0 = proc_cpu_s(pid)
            sampler.start()
            poller.start()
            for s in submitters:
                s.start()
            go.wait(60)
            t0 = time.monotonic()
            deadline = t0 + spec.timeout_s
            for s in submitters:
                s.join(max(0.0, deadline - time.monotonic()))
            stop_submit.set()
            t_submitted = time.monotonic()
            accepted = [a["job_id"] for s in submitters for a in s.accepted]
            drained = events.wait_ended(set(accepted), max(0.0, deadline - time.monotonic()))
            t_drained = time.monotonic()
            stop_watch.set()
            poller.join(300)  # a liveness bound: its lanes finish the ticks already sent, each query within its timeout
            sampler.join(5)
            vm = proc_status(pid)
            cpu_s = proc_cpu_s(pid) - cpu0
            api_states, results = _read_records(watch, accepted)
            jobs_total = watch.status().jobs_total
            sub.close()
        rc, exit_s = svc.stop()
        store = _read_store(svc.data_dir / "jobs.sqlite")
    finally:
        svc.kill()
        if log_to is not None and svc.log.is_file():
            shutil.copyfile(svc.log, log_to)
        if tmp is not None:
            tmp.cleanup()
    wall = time.monotonic() - t_begin
    with events._cv:
        by_job = {j: list(v) for j, v in events.by_job.items()}
    raw = {"accepted": {f"load-{s.idx}": [a["job_id"] for a in s.accepted] for s in submitters},
           "drained": drained, "jobs_total": jobs_total, "api_states": api_states, "results": results,
           "events": by_job, **store,
           "actor_errors": [f"{s.name}: {s.exc}" for s in (*submitters, poller) if s.exc]
           + [f"{s.name}: still running" for s in submitters if s.is_alive()],
           "submit_refusals": {"queue_full": sum(s.queue_full for s in submitters),
                               "uncoded": sum(s.uncoded for s in submitters),
                               "other": dict(sum((s.other_codes for s in submitters), Counter())),
                               "no_reply": sum(s.no_reply for s in submitters)},
           "poller_failed": dict(poller.failed), "poller_unanswered": dict(poller.unanswered),
           "error_samples": [e for s in (*submitters, poller) for e in s.errors][:10],
           "queue_position_max": max((a["queue_position"] for s in submitters for a in s.accepted), default=0)}
    figures = _figures(spec, raw, submitters, poller, sampler, t0=t0, t_submitted=t_submitted, t_drained=t_drained,
                       wall=wall, vm=vm, cpu_s=cpu_s, startup_s=svc.startup_s, exit=(rc, exit_s),
                       load=(load_before, os.getloadavg()))
    checks = evaluate(asdict(spec), figures, raw)
    return {"schema_version": 1, "spec": asdict(spec), "figures": figures, "checks": checks,
            "ok": all(c["ok"] for c in checks.values()),
            "rss_samples": [{"t_s": t, "jobs_ended": n, "rss_mb": round(kb / 1024, 1), "threads": th}
                            for t, n, kb, th in sampler.samples[:: max(1, len(sampler.samples) // 400)]],
            "raw": raw}


def _read_records(c, ids: list[str]) -> tuple[dict[str, str | None], dict[str, list]]:
    """Every accepted job's state through the API after the run (None: not found or no reply), and
    what its result says it did: [views, coverage %, result.json among its artifacts]."""
    from cellctl.service.client import CellError, NoReply

    states: dict[str, str | None] = {}
    results: dict[str, list] = {}
    for job_id in ids:
        try:
            rec = c.job(job_id)
        except (CellError, NoReply):
            states[job_id] = None
            continue
        states[job_id] = rec.state
        if rec.result is not None:
            results[job_id] = [rec.result.steps, rec.result.coverage_percent,
                               rec.artifacts is not None and "result.json" in rec.artifacts.files]
    return states, results


def _read_store(path: Path) -> dict:
    """Creation order, start order and each job's transitions, read read-only from the stopped
    service's SQLite store. rowid is insertion order, so it orders the transitions even where two
    share a millisecond timestamp."""
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        created = [{"job_id": j, "requested_by": json.loads(r).get("requested_by")}
                   for j, r in db.execute("SELECT job_id, request FROM jobs ORDER BY id")]
        trans: dict[str, list[list[str]]] = defaultdict(list)
        started: list[list[str]] = []
        for job_id, state, at in db.execute("SELECT job_id, state, at FROM transitions ORDER BY rowid"):
            trans[job_id].append([state, at])
            if state == "running":
                started.append([job_id, at])
    finally:
        db.close()
    return {"created": created, "started": started, "transitions": dict(trans)}


def _seconds_between(a: str, b: str) -> float:
    from datetime import datetime

    f = lambda s: datetime.fromisoformat(s.replace("Z", "+00:00"))  # noqa: E731
    return (f(b) - f(a)).total_seconds()


def _figures(spec: LoadSpec, raw: dict, subs: list[Submitter], poller: Poller, sampler: RssSampler, *, t0,
             t_submitted, t_drained, wall, vm, cpu_s, startup_s, exit, load) -> dict:
    trans = raw["transitions"].values()
    waits = [_seconds_between(t[0][1], t[1][1]) for t in trans if len(t) > 1 and t[1][0] == "running"]
    runs = [_seconds_between(t[1][1], t[-1][1]) for t in trans if len(t) > 2 and t[1][0] == "running"]
    queries = {k: {**(summary(v) or {"n": 0}), "failed": sum(n for key, n in poller.failed.items()
                                                           if key.startswith(k + ":")),
                   "unanswered": poller.unanswered[k]} for k, v in poller.ms.items()}
    n_acc = sum(len(v) for v in raw["accepted"].values())
    n_ended = max((s[1] for s in sampler.samples), default=0)
    rss_at = {str(n): sampler.rss_mb_after(n) for n in sorted({10, 20, spec.rss_from, 100, n_ended}) if n <= n_ended}
    grow = sampler.rss_trend_mb(spec.rss_from)
    return {
        "jobs_accepted": n_acc,
        "clients": spec.clients,
        "poller_hz_target": spec.hz,
        "poller_ticks": poller.ticks,
        "poller_hz_achieved": round(poller.ticks / poller.t_run, 2) if poller.t_run else None,
        "poller_tick_late_ms": summary(poller.late_ms),
        "queue_max": spec.queue_max,
        "queue_length_max_seen": poller.max_queue_length,
        "queue_full_replies": raw["submit_refusals"]["queue_full"],
        "queue_full_per_client": [s.queue_full for s in subs],
        "submit_ms": summary([x for s in subs for x in s.submit_ms]),
        "queries_ms": queries,
        "queries_total": sum(q["n"] + q["failed"] + q["unanswered"] for q in queries.values()),
        "job_wait_s": summary(waits),
        "job_run_s": summary(runs),
        "wall_s": round(wall, 1),
        "service_startup_s": round(startup_s or 0, 2),
        "submit_phase_s": round(t_submitted - t0, 1),
        "run_s": round(t_drained - t0, 1),
        "throughput_jobs_per_s": round(n_acc / (t_drained - t0), 2) if t_drained > t0 else None,
        "service_cpu_s": round(cpu_s, 1),
        "peak_rss_mb": round(vm["VmHWM"] / 1024, 1),
        "rss_end_mb": round(vm["VmRSS"] / 1024, 1),
        "rss_mb_after_jobs": rss_at,
        "rss_growth_mb": round(grow, 1) if grow is not None else None,
        "threads_max": max((s[3] for s in sampler.samples), default=None),
        "threads_after_jobs": {k: sampler.threads_after(int(k)) for k in rss_at},
        "threads_end": vm["Threads"],
        "exit_status": exit[0],
        "sigterm_to_exit_s": round(exit[1], 2),
        "loadavg_before": [round(x, 2) for x in load[0]],
        "loadavg_after": [round(x, 2) for x in load[1]],
        "cpus": os.cpu_count(),
    }


# --- the checks: plain data in, so a test can feed them a perturbed run ---------------------------
def _check(ok: bool, detail: str) -> dict:
    return {"ok": bool(ok), "detail": detail}


def evaluate(spec: dict, fig: dict, raw: dict) -> dict[str, dict]:
    """Every check of the run (name -> ok, detail) from the spec, the figures and the raw record."""
    accepted = [j for ids in raw["accepted"].values() for j in ids]
    acc_set = set(accepted)
    created = [c["job_id"] for c in raw["created"]]
    trans = raw["transitions"]
    c: dict[str, dict] = {}
    c["actors_ran"] = _check(not raw["actor_errors"], "; ".join(raw["actor_errors"]) or "all finished")
    c["all_submitted"] = _check(len(accepted) == spec["jobs"], f"{len(accepted)} of {spec['jobs']} accepted")
    dup = len(accepted) - len(acc_set)
    c["no_duplicate_ids"] = _check(dup == 0 and len(created) == len(set(created)),
                                   f"{dup} ids accepted twice, {len(created) - len(set(created))} stored twice")
    lost, phantom = acc_set - set(created), set(created) - acc_set
    c["none_lost"] = _check(not lost and not phantom and len(created) == len(accepted) == raw["jobs_total"],
                            f"store {len(created)} jobs, accepted {len(accepted)}, status jobs_total "
                            f"{raw['jobs_total']}; lost {len(lost)}, stored but never accepted {len(phantom)}")
    paths = Counter(" > ".join(s for s, _ in trans.get(j, [])) for j in accepted)
    n_terminal = Counter(sum(s in TERMINAL_STATES for s, _ in trans.get(j, [])) for j in accepted)
    ends_last = all(trans.get(j) and trans[j][-1][0] in TERMINAL_STATES for j in accepted)
    c["terminal_exactly_once"] = _check(set(n_terminal) == {1} and ends_last and raw["drained"],
                                        f"transitions {dict(paths)}; terminal transitions per job "
                                        f"{dict(n_terminal)}; every job's events ended in time: {raw['drained']}")
    finals = Counter(trans[j][-1][0] if trans.get(j) else None for j in accepted)
    api = Counter(raw["api_states"].get(j) for j in accepted)
    c["all_done"] = _check(finals == Counter({"done": len(accepted)}) == api,
                           f"final states in the store {dict(finals)}, through the API {dict(api)}")
    res = raw["results"]
    scanned = [j for j in accepted if j in res and res[j][0] >= 1 and res[j][1] > 0 and res[j][2]]
    cov = sorted(res[j][1] for j in scanned)
    c["jobs_scanned"] = _check(len(scanned) == len(accepted),
                               f"{len(scanned)} of {len(accepted)} jobs have a result with a view, coverage > 0 and "
                               f"result.json" + (f"; coverage {cov[0]}..{cov[-1]} %" if cov else ""))
    ev = raw["events"]
    gaps = [j for j in accepted if sorted(s for s, _ in ev.get(j, [])) != list(range(len(ev.get(j, []))))]
    ends = Counter(sum(p in TERMINAL_STATES for _, p in ev.get(j, [])) for j in accepted)
    c["events_complete"] = _check(not gaps and set(ends) == {1},
                                  f"{sum(len(ev.get(j, [])) for j in accepted)} events; jobs with a gap or a "
                                  f"repeat in seq {len(gaps)}; terminal events per job {dict(ends)}")
    started = [j for j, _ in raw["started"]]
    started_at = [at for _, at in raw["started"]]
    stored_by: dict[str, list[str]] = defaultdict(list)
    for row in raw["created"]:
        stored_by[row["requested_by"]].append(row["job_id"])
    client_order = all(stored_by[k] == ids for k, ids in raw["accepted"].items())
    first = next((i for i, (a, b) in enumerate(zip(created, started)) if a != b), None)
    c["fifo"] = _check(started == created and started_at == sorted(started_at) and client_order,
                       f"{len(started)} starts; start order = acceptance (store) order: {started == created}"
                       + (f" (first difference at #{first})" if first is not None else "")
                       + f"; start times non-decreasing: {started_at == sorted(started_at)}; each client's jobs "
                         f"stored in its submit order: {client_order}")
    r = raw["submit_refusals"]
    c["queue_full_coded"] = _check(r["queue_full"] > 0 and r["uncoded"] == 0 and not r["other"] and r["no_reply"] == 0,
                                   f"{r['queue_full']} coded queue_full replies, {r['uncoded']} uncoded, other "
                                   f"codes {r['other']}, submits unanswered {r['no_reply']}")
    c["queue_bounded"] = _check(fig["queue_length_max_seen"] <= spec["queue_max"]
                                and raw["queue_position_max"] <= spec["queue_max"],
                                f"longest queue seen by the poller {fig['queue_length_max_seen']}, highest "
                                f"queue_position in a submit reply {raw['queue_position_max']} "
                                f"(queue_max {spec['queue_max']})")
    q = fig["queries_ms"]
    bad = sum(v["failed"] + v["unanswered"] for v in q.values())
    c["queries_answered"] = _check(bad == 0 and all(v["n"] > 0 for v in q.values()),
                                   f"{fig['queries_total']} poller queries, failed {raw['poller_failed']}, "
                                   f"unanswered {raw['poller_unanswered']}")
    c["peak_rss"] = _check(fig["peak_rss_mb"] < spec["peak_rss_max_mb"],
                           f"service VmHWM {fig['peak_rss_mb']} MB (bound {spec['peak_rss_max_mb']:g} MB)")
    g = fig["rss_growth_mb"]
    c["rss_bounded"] = _check(g is not None and g < spec["rss_growth_max_mb"],
                              f"RSS trend from job {spec['rss_from']} to the last job: "
                              f"{'+' if g and g > 0 else ''}{g} MB (bound {spec['rss_growth_max_mb']:g} MB)")
    th = fig["threads_after_jobs"]
    th_from, th_end = th.get(str(spec["rss_from"])), max((int(k) for k in th), default=None)
    th_grow = th[str(th_end)] - th_from if th_from is not None and th_end is not None else None
    c["threads_bounded"] = _check(th_grow is not None and th_grow <= spec["threads_growth_max"],
                                  f"service threads after job {spec['rss_from']}: {th_from}, after the last: "
                                  f"{th.get(str(th_end))} (bound +{spec['threads_growth_max']})")
    c["clean_exit"] = _check(fig["exit_status"] == 0, f"exit status {fig['exit_status']} "
                                                      f"{fig['sigterm_to_exit_s']} s after SIGTERM")
    return c


# --- the report -----------------------------------------------------------------------------------
def markdown(doc: dict, command: str | None = None) -> str:
    f, s = doc["figures"], doc["spec"]
    lat = lambda st: (f"{st['median']:.1f} | {st['p90']:.1f} | {st['p99']:.1f} | {st['max']:.1f}"  # noqa: E731
                      if st and st.get("median") is not None else "– | – | – | –")
    md = ["# Load test on loopback", ""]
    if command:
        md += [f"`{command}`", ""]
    md += [f"- {f['jobs_accepted']} jobs from {f['clients']} clients, job profile `{s['profile']}` "
           f"({json.dumps(s['job'])}{', 640x480, teleport' if s['fast_twin'] else ''}), queue_max {f['queue_max']}, "
           f"poller {f['poller_hz_target']:g} Hz open loop (achieved {f['poller_hz_achieved']} Hz; a tick waited for a "
           f"free lane at most {_g(f['poller_tick_late_ms'], 'max')} ms)",
           f"- wall {f['wall_s']} s (service start-up {f['service_startup_s']} s, submits done after "
           f"{f['submit_phase_s']} s, last job ended after {f['run_s']} s: {f['throughput_jobs_per_s']} jobs/s); "
           f"service CPU {f['service_cpu_s']} s; {f['cpus']} CPUs, load average "
           f"{f['loadavg_before'][0]} before, {f['loadavg_after'][0]} after",
           f"- queue_full replies {f['queue_full_replies']} (per client {f['queue_full_per_client']}); longest queue "
           f"seen {f['queue_length_max_seen']}",
           f"- job wait (queued to running) median {_g(f['job_wait_s'], 'median')} s, max "
           f"{_g(f['job_wait_s'], 'max')} s; job run median {_g(f['job_run_s'], 'median')} s, max "
           f"{_g(f['job_run_s'], 'max')} s",
           f"- service memory: peak RSS (VmHWM) {f['peak_rss_mb']} MB; RSS after jobs "
           + ", ".join(f"{k}: {v} MB" for k, v in f["rss_mb_after_jobs"].items())
           + f"; trend from job {s['rss_from']} to the last {f['rss_growth_mb']} MB; service threads after jobs "
           + ", ".join(f"{k}: {v}" for k, v in f["threads_after_jobs"].items()),
           "", "| query (ms) | n | failed | unanswered | median | p90 | p99 | max |",
           "|---|--:|--:|--:|--:|--:|--:|--:|"]
    sm = f["submit_ms"]
    md.append(f"| submit (accepted or queue_full) | {sm['n'] if sm else 0} | – | – | {lat(sm)} |")
    for k, v in f["queries_ms"].items():
        md.append(f"| {k} | {v['n']} | {v['failed']} | {v['unanswered']} | {lat(v)} |")
    md += ["", "| check | ok | detail |", "|---|---|---|"]
    md += [f"| {k} | {'yes' if v['ok'] else '**NO**'} | {v['detail']} |" for k, v in doc["checks"].items()]
    samples = doc.get("raw", {}).get("error_samples")
    if samples:
        md += ["", "First failures (other than queue_full):", ""] + [f"- `{e}`" for e in samples]
    return "\n".join(md) + "\n"


def _g(st: dict | None, k: str):
    return st[k] if st else "–"


def cli_load(args, out: Path) -> int:
    """`cellctl bench --load` (parser in cellctl/cli.py): OUT/load.json and load.md. Exit 0: every
    check passed; 1: some check failed (the table says which)."""
    import sys
    from datetime import datetime

    from cellctl.bench.machine import code_info, machine_info
    from cellctl.scan.artifacts import write_json

    spec = LoadSpec(jobs=args.jobs, clients=args.clients, hz=50.0 if args.hz is None else args.hz,
                    queue_max=args.queue_max,
                    profile=args.job_profile)
    if not 1 <= spec.queue_max <= 1000:
        raise ValueError("--queue-max must be in 1..1000 (service.queue_max)")
    out.mkdir(parents=True, exist_ok=True)
    command = "cellctl " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["bench"] else None
    print(f"load test: {spec.jobs} jobs, {spec.clients} clients, {spec.hz:g} Hz -> {out}", file=sys.stderr)
    doc = run_load(spec, log_to=out / "load-service.log")
    doc = {"created": datetime.now().astimezone().isoformat(timespec="seconds"), "command": command,
           "machine": machine_info(), "code": code_info(), **doc}
    write_json(out / "load.json", doc)
    md = markdown(doc, command)
    (out / "load.md").write_text(md)
    print(md)
    return 0 if doc["ok"] else 1


if __name__ == "__main__":
    import sys

    d = run_load(LoadSpec(jobs=int(sys.argv[1]) if len(sys.argv) > 1 else 200))
    print(markdown(d))
