"""The cell service end to end over real Zenoh on loopback: `cellctl serve` as a subprocess (free port,
multicast scouting off, temp data dir), the CellClient, and short scans in the twin (smooth_cylinder,
2 views, no noise). Nothing is mocked.

Tests of: cellctl.service.server, cellctl.service.events, cellctl.service.files, cellctl.service.client,
cellctl.service.worker, cellctl.bench.latency (the status round trip under a scan).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from cellctl.service.api import FileChunk, JobEvent
from cellctl.service.client import CellClient, CellError, NoReply
from cellctl.service.loopback import ROOT, ServiceProcess, free_port
from cellctl.service.store import JobStore

SHORT = {"scene": "smooth_cylinder", "max_steps": 2, "noise": False}
LONG = {"scene": "smooth_cylinder", "max_steps": 12, "noise": False}  # cancelled or killed long before its end
# Liveness bounds: they fail on a hang, never because the machine is loaded (speed is `cellctl bench --service`);
# each stays under pytest-timeout's 600 s per test (pyproject.toml), so a hang fails with its own message
EXIT_S = 120.0  # a stopped service is gone within this (idle: under a second; a running job ends at its step)
START_S = 120.0  # a started service answers within this (idle: a few seconds of imports)
JOB_S = 300.0  # a short scan ends within this (idle: seconds)
REPLY_S = 30.0  # a reply the test needs


class Events:
    """Collects a job's events as the client delivers them (on Zenoh's thread)."""

    def __init__(self):
        self.items, self.times = [], []
        self._cv = threading.Condition()

    def __call__(self, ev) -> None:
        with self._cv:
            self.items.append(ev)
            self.times.append(time.perf_counter())
            self._cv.notify_all()

    def wait_for(self, pred, timeout_s: float = 60.0):
        with self._cv:
            assert self._cv.wait_for(lambda: any(pred(e) for e in self.items), timeout_s), \
                [(e.seq, e.phase, e.step) for e in self.items]
            return next(e for e in self.items if pred(e))


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """One service for the tests that need no restart; queue_max 1 makes 'queue full' cheap."""
    svc = ServiceProcess(tmp_path_factory.mktemp("cell"), queue_max=1).start(START_S)
    yield svc
    rc, _took = svc.stop(signal.SIGTERM, EXIT_S)
    assert rc == 0


def test_submit_events_result_survive_a_restart(tmp_path):
    svc = ServiceProcess(tmp_path, cell_id="cell-a").start(START_S)
    try:
        with svc.client(REPLY_S) as c:
            events = Events()
            t0 = time.perf_counter()
            job_id = c.submit(SHORT, on_event=events).job_id
            rec = c.wait(job_id, JOB_S)
            events.wait_for(lambda e: e.phase == "done")
            first_event_ms = 1e3 * (events.times[0] - t0)
            status = c.status()
        assert rec.state == "done", rec.error
        seqs = [e.seq for e in events.items]
        assert seqs == list(range(len(seqs))), seqs
        phases = [e.phase for e in events.items]
        assert [p for i, p in enumerate(phases) if i == 0 or p != phases[i - 1]] == \
            ["queued", "scanning", "planning-cut", "done"], phases
        assert [e.step for e in events.items if e.phase == "scanning" and e.step is not None] == [0, 1]
        assert all(e.job_id == job_id for e in events.items) and events.items[-1].coverage_percent > 0
        r = rec.result
        assert r.steps == 2 and r.terminated_by == "max_steps" and r.coverage_percent > 30
        assert r.cut is not None and r.cut.poses > 0 and r.cut.length_m > 0
        assert [t.state for t in rec.transitions] == ["queued", "running", "done"]
        for name in ("result.json", "drawing.ply", "surface.ply", "cut_path.json", "cut_trajectory.npz", "scan.rrd"):
            assert name in rec.artifacts.files and (Path(rec.artifacts.dir) / name).stat().st_size > 0, name
        assert Path(rec.artifacts.dir) == svc.data_dir / "jobs" / job_id
        assert json.loads((Path(rec.artifacts.dir) / "result.json").read_text())["steps"] == 2
        assert status.cell_id == "cell-a" and status.queue_length == 0 and status.running_job is None
        assert status.jobs_total == 1 and status.arm_ready and status.accepting_jobs
        print(f"submit -> first event {first_event_ms:.1f} ms, startup {svc.startup_s:.2f} s")

        rc, _took = svc.stop(signal.SIGTERM, EXIT_S)
        assert rc == 0
        svc.start(START_S)
        with svc.client(REPLY_S) as c:
            again = c.job(job_id)
            listed = c.jobs()
        assert again.state == "done" and again.result == rec.result and again.transitions == rec.transitions
        assert [j.job_id for j in listed.jobs] == [job_id] and listed.jobs[0].coverage_percent == r.coverage_percent
        rc, _took = svc.stop(signal.SIGINT, EXIT_S)
        assert rc == 0
    finally:
        svc.kill()


def test_a_job_running_when_the_service_dies_is_interrupted_and_the_queued_ones_run_after_it(tmp_path):
    """SIGKILL with one job running and two queued: at the restart the running one is interrupted (what
    it wrote kept and listed), the queued ones keep their place and run to the end, each with its events;
    no record points at a folder that does not exist."""
    svc = ServiceProcess(tmp_path).start(START_S)
    try:
        with svc.client(REPLY_S) as c:
            events = Events()
            killed = c.submit(LONG, on_event=events).job_id
            waiting = [c.submit(SHORT).job_id for _ in range(2)]
            events.wait_for(lambda e: e.step == 0, JOB_S)
            assert all(c.job(j).artifacts is None for j in waiting)  # no folder yet: none named
        svc.proc.send_signal(signal.SIGKILL)
        svc.proc.wait(EXIT_S)
        svc.start(START_S)
        with svc.client(REPLY_S) as c:
            after = Events()
            sub = c.session.declare_subscriber(  # noqa: F841 - kept while the jobs run
                c.keys.all_events, lambda sample: after(JobEvent.model_validate_json(sample.payload.to_bytes())))
            rec = c.job(killed)
            assert rec.state == "interrupted" and "interrupted" in rec.error
            assert [t.state for t in rec.transitions] == ["queued", "running", "interrupted"]
            assert rec.progress.phase == "interrupted" and rec.progress.seq > events.items[-1].seq
            assert "scan.rrd" in rec.artifacts.files and Path(rec.artifacts.dir).is_dir()
            for job_id in waiting:
                done = c.wait(job_id, JOB_S)
                assert done.state == "done" and [t.state for t in done.transitions] == ["queued", "running", "done"]
                assert "result.json" in done.artifacts.files and Path(done.artifacts.dir).is_dir()
                after.wait_for(lambda e, j=job_id: e.job_id == j and e.phase == "done", JOB_S)
                seqs = [e.seq for e in after.items if e.job_id == job_id]
                assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and seqs[-1] == done.progress.seq, seqs
            # SIGTERM while a job runs: the scan stops, its partial result is kept, the process exits
            events = Events()
            stopped = c.submit(LONG, on_event=events).job_id
            events.wait_for(lambda e: e.step == 0, JOB_S)
        rc, _took = svc.stop(signal.SIGTERM, EXIT_S)
        assert rc == 0
        store = JobStore(svc.data_dir / "jobs.sqlite")
        rec = store.get(stopped)
        store.close()
        assert rec.state == "interrupted" and rec.result is not None and rec.result.terminated_by == "interrupted"
        assert "result.json" in rec.artifacts.files and "drawing.ply" in rec.artifacts.files
    finally:
        svc.kill()


@pytest.mark.parametrize("payload, code", [
    (b"{not json", "bad_json"),
    (b"", "bad_json"),
    (b'\xff\xfe{"scene": "smooth_cylinder"}', "bad_json"),
    (b'{"scene": "smooth_cylinder", "planner": "astar"}', "invalid_request"),
    (b'{"planner": "gnbv"}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "max_steps": "2"}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "speed": 2}', "invalid_request"),
    (b'{"scene": "no_such_scene"}', "invalid_request"),
    (b'{"scene": "nowhere/scene.yaml"}', "invalid_request"),
    (b'{"scene": "smooth_cylinder", "schema_version": 9}', "unsupported_schema_version"),
    (json.dumps({"scene": "smooth_cylinder", "requested_by": "x" * 100_000}).encode(), "payload_too_large"),
])
def test_invalid_submits_get_an_error_reply(cell, payload, code):
    with cell.client() as c:
        with pytest.raises(CellError) as e:
            c.submit(payload)
        assert e.value.code == code and e.value.message
        assert c.status().cell_id == "sim-1"  # still serving


def test_bad_keys_and_ids_get_an_error_reply(cell):
    with cell.client() as c:
        k = c.keys
        for key, code in [(k.job("20250101T000000Z-abcdef"), "not_found"), (k.job("nonsense"), "not_found"),
                          (k.cancel("20250101T000000Z-abcdef"), "not_found"), (k.jobs + "/*", "invalid_request"),
                          (k.events("20250101T000000Z-abcdef"), "invalid_request"),
                          (k.jobs + "/a/b/c", "invalid_request")]:
            with pytest.raises(CellError) as e:
                c._query(key, dict)
            assert e.value.code == code, key
        with pytest.raises(CellError) as e:
            c._query(k.jobs, dict, b'{"limit": "all"}')
        assert e.value.code == "invalid_request"
        assert c.status().accepting_jobs
        # wildcards: `cell/*/status` is answered on the cell's own key; `cell/sim-1/**` reaches every queryable:
        # status and paint answer, the jobs tree and the paint's commissioning serve exact keys only
        replies = list(c.session.get("cell/*/status", timeout=REPLY_S))
        assert [(str(r.ok.key_expr), json.loads(r.ok.payload.to_bytes())["cell_id"]) for r in replies] == [
            ("cell/sim-1/status", "sim-1")]
        both = list(c.session.get("cell/sim-1/**", timeout=REPLY_S))
        assert sorted("ok" if r.ok is not None else json.loads(r.err.payload.to_bytes())["code"] for r in both) == [
            "invalid_request", "invalid_request", "ok", "ok"]


def test_queue_full_then_cancel_queued_and_running(cell):
    with cell.client(REPLY_S) as c:
        events = Events()
        running = c.submit(LONG, on_event=events).job_id
        events.wait_for(lambda e: e.step == 0, JOB_S)
        queued = c.submit(LONG)
        assert queued.queue_position == 1
        with pytest.raises(CellError) as e:
            c.submit(SHORT)
        assert e.value.code == "queue_full"
        st = c.status()
        assert st.queue_length == 1 and st.running_job == running

        assert c.cancel(queued.job_id).state == "cancelled"
        assert c.job(queued.job_id).state == "cancelled"
        assert c.cancel(running, reason="test").state == "cancelling"
        rec = c.wait(running, JOB_S)
        assert rec.state == "cancelled" and rec.result.terminated_by == "cancelled" and rec.result.steps >= 1
        assert rec.result.cut is None
        assert [t.state for t in rec.transitions] == ["queued", "running", "cancelling", "cancelled"]
        assert rec.transitions[2].note == "cancel requested: test"
        for name in ("result.json", "drawing.ply", "surface.ply", "scan.rrd"):
            assert name in rec.artifacts.files, name
        events.wait_for(lambda e: e.phase == "cancelled")
        assert "planning-cut" not in [e.phase for e in events.items]
        # the cancel took effect at once: the step in progress when it came (its event says "cancelling") was
        # the last; counted in steps, not seconds, which depend on the machine's load
        steps = [(e.step, e.state) for e in events.items if e.phase == "scanning" and e.step is not None]
        assert [s for s, _ in steps] == list(range(rec.result.steps)), steps
        assert sum(state == "cancelling" for _, state in steps) <= 1 and rec.result.steps < LONG["max_steps"], steps

        for job_id, code in [(running, "not_cancellable"), (queued.job_id, "not_cancellable")]:
            with pytest.raises(CellError) as e:
                c.cancel(job_id)
            assert e.value.code == code
        listed = c.jobs(limit=2)
        assert [j.job_id for j in listed.jobs][:2] == [queued.job_id, running]
        assert c.jobs(state="cancelled").total >= 2
        assert c.status().queue_length == 0


def test_a_submit_sent_again_with_its_request_id_is_one_job(cell):
    """A tablet whose submit timed out cannot know whether the job was queued: it sends the same request,
    request_id and all, again and gets the one job back (the documented retry, docs/API.md)."""
    req = {**SHORT, "request_id": f"tablet-2:{uuid.uuid4()}"}
    with cell.client(REPLY_S) as c:
        before = c.status().jobs_total
        # the client gives up after 1 ms (its reply, if any came that fast, is not read): the cell queues it
        list(c.session.get(c.keys.submit, payload=json.dumps(req).encode(), timeout=0.001))
        deadline = time.monotonic() + REPLY_S
        while c.status().jobs_total == before and time.monotonic() < deadline:  # the cell queued it anyway
            time.sleep(0.05)
        newest = c.jobs(limit=1).jobs[0].job_id
        again = c.submit(req)
        assert again.duplicate and again.job_id == newest and c.status().jobs_total == before + 1
        assert c.job(newest).request.request_id == req["request_id"]
        with pytest.raises(CellError) as e:  # the same key for another job is a client bug, said so
            c.submit({**req, "max_steps": 3})
        assert e.value.code == "invalid_request" and [d["loc"] for d in e.value.details] == ["request_id"]
        with pytest.raises(CellError) as e:  # its folder is still being written
            c.files(newest)
        assert e.value.code == "not_ended"
        rec = c.wait(newest, JOB_S)
        late = c.submit(req)  # long after: still that job, now ended
        assert (late.job_id, late.state, late.queue_position, late.duplicate) == (newest, rec.state, None, True)
        auto = c.submit(SHORT)  # the client's own key, so its retries are safe too
        assert not auto.duplicate and c.job(auto.job_id).request.request_id
        assert c.status().jobs_total == before + 2
        c.wait(auto.job_id, JOB_S)


def test_an_ended_jobs_cut_and_recording_are_fetched_in_chunks_and_verified(cell, tmp_path):
    """The cut is the product: the tablet gets it over the API, not as a folder on the cell's disk. Files
    come in chunks (here 64 KiB, so the recording takes several), each reply under the message cap, and
    the joined bytes match the whole file's SHA-256 and the file the job wrote."""
    import base64
    import hashlib

    with cell.client(REPLY_S) as c:
        rec = c.wait(c.submit(SHORT).job_id, JOB_S)
        assert rec.state == "done"
        listing = c.files(rec.job_id)
        by_name = {f.name: f for f in listing.files}
        assert {"cut_path.json", "cut_trajectory.npz", "drawing.ply", "scan.rrd", "result.json"} <= set(by_name)
        assert [f.name for f in listing.files] == sorted(rec.artifacts.files)
        folder = Path(rec.artifacts.dir)
        for name in ("cut_path.json", "scan.rrd"):
            got = c.fetch(rec.job_id, name, tmp_path / name, chunk=64 * 1024)
            disk = (folder / name).read_bytes()
            assert (tmp_path / name).read_bytes() == disk and got == by_name[name]
            assert got.sha256 == hashlib.sha256(disk).hexdigest()
        assert by_name["scan.rrd"].size > 3 * 64 * 1024  # several chunks
        cut = json.loads((tmp_path / "cut_path.json").read_text())
        assert cut["branches"] and all("poses" in b for b in cut["branches"])
        k = c.keys
        last = c._query(k.file(rec.job_id, "scan.rrd"), FileChunk,
                        json.dumps({"offset": by_name["scan.rrd"].size - 10, "length": 100}).encode())
        assert (last.length, last.eof) == (10, True)
        assert base64.b64decode(last.data) == (folder / "scan.rrd").read_bytes()[-10:]
        for name, code in [("no_such.bin", "not_found"), ("..", "invalid_request"), (".hidden", "invalid_request")]:
            with pytest.raises(CellError) as e:
                c._query(k.file(rec.job_id, name), FileChunk)
            assert e.value.code == code, name
        with pytest.raises(CellError) as e:
            c._query(k.file(rec.job_id, "scan.rrd"), FileChunk, b'{"length": 600000}')  # over CHUNK_MAX
        assert e.value.code == "invalid_request"
    out = subprocess.run([sys.executable, "-m", "cellctl.cli", "jobs", "fetch", rec.job_id, "--out",
                          str(tmp_path / "cli"), "--name", "cut_path.json", "--cell", "sim-1", "--connect", cell.endpoint],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "cli" / rec.job_id / "cut_path.json").read_bytes() == (folder / "cut_path.json").read_bytes()


def test_cli_status_and_clear_no_reply(cell):
    def cli(*args):
        return subprocess.run([sys.executable, "-m", "cellctl.cli", *args], cwd=ROOT, capture_output=True,
                              text=True, timeout=300)  # a liveness bound

    ok = cli("status", "--cell", "sim-1", "--connect", cell.endpoint, "--reply-timeout", str(REPLY_S))
    assert ok.returncode == 0 and "queue_length" in ok.stdout, ok.stderr
    nobody = cli("status", "--cell", "other-cell", "--connect", cell.endpoint, "--reply-timeout", "1")
    assert nobody.returncode == 3
    assert "no reply" in nobody.stderr and "access control denied" in nobody.stderr
    down = cli("jobs", "list", "--cell", "sim-1", "--connect", f"tcp/127.0.0.1:{free_port()}")
    assert down.returncode == 3 and "cannot reach" in down.stderr, down.stderr


def test_client_reports_no_reply_clearly(cell):
    with CellClient("not-this-cell", [cell.endpoint], timeout_s=0.5) as c:
        with pytest.raises(NoReply, match="the cell is down, or access control denied"):
            c.status()
        assert not c.alive(0.5)


def test_a_job_over_its_timeout_fails_in_process(tmp_path):
    """The service class in this process (same code as `serve`): the job timeout cancels the scan."""
    from cellctl.config import load_cell_config
    from cellctl.service.loopback import write_config
    from cellctl.service.server import CellService

    port = free_port()
    cfg, cfg_path = load_cell_config(write_config(tmp_path / "cell.yaml", port, tmp_path / "data", job_timeout_s=1.0))
    svc = CellService(cfg, cfg_path)
    svc.start()
    try:
        with CellClient("sim-1", [f"tcp/127.0.0.1:{port}"], timeout_s=REPLY_S) as c:
            job_id = c.submit(LONG).job_id  # 12 views: far longer than the 1 s job timeout on any machine
            rec = c.wait(job_id, JOB_S)
        assert rec.state == "failed" and rec.error.startswith("timeout:"), rec.error
        assert rec.result is not None and rec.result.terminated_by == "timeout"
        assert "result.json" in rec.artifacts.files
    finally:
        svc.stop(10)
        svc.close()


def test_service_bench_measures_latency(tmp_path):
    """`cellctl bench --service N`: a real service on loopback, figures in service.json/.md. The figures
    are measured, not judged here: how fast is the bench's business, and depends on the machine's load."""
    proc = subprocess.run([sys.executable, "-m", "cellctl.cli", "bench", "--service", "5", "--clients", "3", "--hz",
                           "10", "--scenes", "smooth_cylinder", "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=570)  # a liveness bound (idle: ~30 s)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = json.loads((tmp_path / "service.json").read_text())["service"]
    assert m["status_rtt_idle_ms"]["n"] == 5 and 0 < m["status_rtt_idle_ms"]["median"]
    assert m["submit_to_first_event_ms"]["n"] == 5 and m["submit_to_first_event_idle_ms"] > 0
    assert m["exit_status"] == 0 and m["sigterm_to_exit_s"] > 0
    assert "| status round trip, cell idle |" in (tmp_path / "service.md").read_text()
    load = json.loads((tmp_path / "service.json").read_text())["status_under_scan"]
    assert load["job_state"] == "done" and load["clients"] == 3 and load["scene"] == "smooth_cylinder"
    assert load["status_rtt_idle_ms"]["n"] >= 3 and load["status_rtt_scan_ms"]["n"] >= 3  # every client, each phase
    assert load["failed_or_unanswered"] == {"idle": 0, "scan": 0}
    assert "| status round trip, 3 clients at 10 Hz, during a scan |" in (tmp_path / "service.md").read_text()


def test_one_service_per_data_dir(cell):
    """A second service on the same data dir would mark the first one's running job interrupted."""
    second = subprocess.run([sys.executable, "-m", "cellctl.cli", "serve", "--config", str(cell.config), "--listen",
                             f"tcp/127.0.0.1:{free_port()}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert second.returncode == 1 and "in use by another service" in second.stderr, second.stderr
    with cell.client() as c:
        assert c.status().accepting_jobs
