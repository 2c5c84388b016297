"""The SQLite job store: records survive a reopen, transitions are checked, unfinished jobs become
`interrupted`, and threads can share it."""

from __future__ import annotations

import sqlite3
import threading

import pytest

from cellctl.service.api import Artifacts, Progress, ResultSummary, ScanDrawingRequest
from cellctl.service.store import JobStore, StoreError

REQ = ScanDrawingRequest(scene="smooth_cylinder", max_steps=2, noise=False)


def _jid(i: int) -> str:
    return f"20250101T0000{i:02d}Z-00000{i % 10}"


def _result(cov: float = 90.0) -> ResultSummary:
    return ResultSummary(scene="smooth_cylinder", planner="gnbv", steps=2, terminated_by="max_steps",
                         coverage_percent=cov, coverage_hit=9, coverage_total=10, planning_s=1.0, step_s=1.0,
                         capture_s=0.1, motion_planning_s=0.1, motion_s=1.0, displacement_m=0.1)


@pytest.fixture
def store(tmp_path):
    s = JobStore(tmp_path / "jobs.sqlite")
    yield s
    s.close()


def test_a_job_lives_through_its_states_and_a_reopen(tmp_path):
    path = tmp_path / "jobs.sqlite"
    s = JobStore(path)
    s.create(_jid(1), "sim-1", REQ, str(tmp_path / "jobs" / _jid(1)))
    s.transition(_jid(1), "running")
    s.set_progress(_jid(1), Progress(phase="scanning", seq=2, step=1, max_steps=2, coverage_percent=50.0,
                                     at="2025-01-01T00:00:02.000Z"))
    (tmp_path / "d").mkdir()
    s.transition(_jid(1), "done", result=_result(), artifacts=Artifacts(dir=str(tmp_path / "d"), files=["result.json"]))
    s.close()
    s = JobStore(path)
    rec = s.get(_jid(1))
    assert rec.state == "done" and rec.request == REQ and rec.cell_id == "sim-1"
    assert [t.state for t in rec.transitions] == ["queued", "running", "done"]
    assert rec.result.coverage_percent == 90.0 and rec.artifacts.files == ["result.json"]
    assert rec.progress.seq == 2 and rec.progress.step == 1
    assert s.get("20250101T000000Z-ffffff") is None
    mode = sqlite3.connect(path).execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"
    s.close()


def test_transitions_are_checked(store):
    store.create(_jid(1), "sim-1", REQ, "d")
    with pytest.raises(StoreError, match="queued -> done"):
        store.transition(_jid(1), "done")
    store.transition(_jid(1), "cancelled", "cancel requested")
    with pytest.raises(StoreError, match="cancelled -> running"):
        store.transition(_jid(1), "running")
    with pytest.raises(StoreError, match="no job"):
        store.transition(_jid(9), "running")
    rec = store.get(_jid(1))
    assert [(t.state, t.note) for t in rec.transitions] == [("queued", None), ("cancelled", "cancel requested")]


def test_list_is_newest_first_bounded_and_filtered(store):
    for i in range(5):
        store.create(_jid(i), "sim-1", REQ, "d")
    store.transition(_jid(3), "running")
    store.transition(_jid(3), "failed", error="ScanError: no initial view\ntraceback...")
    jobs, total = store.list(limit=3)
    assert total == 5 and [j.job_id for j in jobs] == [_jid(4), _jid(3), _jid(2)]
    assert jobs[1].error == "ScanError: no initial view"  # first line only
    jobs, total = store.list(limit=10, state="failed")
    assert total == 1 and jobs[0].job_id == _jid(3)
    assert store.count() == 5


def test_a_dead_services_running_jobs_are_interrupted_its_queued_ones_queue_again(store):
    for i, path in enumerate([[], ["running"], ["running", "cancelling"], ["running", "done"]]):
        store.create(_jid(i), "sim-1", REQ, "d")
        for st in path:
            store.transition(_jid(i), st)
    interrupted, queued = store.recover("the service stopped before the job ended")
    assert interrupted == [_jid(1), _jid(2)] and queued == [_jid(0)]  # never started: it queues again
    assert [store.state(_jid(i)) for i in range(4)] == ["queued", "interrupted", "interrupted", "done"]
    rec = store.get(_jid(1))
    assert rec.transitions[-1].note == "the service stopped before the job ended" and "interrupted" in rec.error
    assert rec.artifacts is None  # its folder "d" does not exist: no record points at a missing folder
    assert store.recover("again") == ([], [_jid(0)])
    assert store.recover("without requeue", requeue=False) == ([_jid(0)], [])
    assert store.recover("once more") == ([], [])


def test_threads_share_the_store(store):
    errors = []

    def work(k: int) -> None:
        try:
            for i in range(10):
                jid = f"20250101T{k:02d}00{i:02d}Z-0000{k:02d}"
                store.create(jid, "sim-1", REQ, "d")
                store.transition(jid, "running")
                store.set_progress(jid, Progress(phase="scanning", seq=1, at="2025-01-01T00:00:00.000Z"))
                store.transition(jid, "done", result=_result())
                store.list(limit=5)
        except Exception as e:  # noqa: BLE001
            errors.append(e)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and store.count() == 40
    assert store.list(limit=100, state="done")[1] == 40


def test_a_broken_file_is_a_clear_error(tmp_path):
    p = tmp_path / "jobs.sqlite"
    p.write_bytes(b"this is not a database" * 100)
    with pytest.raises(StoreError, match="cannot open the job store"):
        JobStore(p)


def test_retention_deletes_the_oldest_ended_folders_first_and_never_a_running_or_the_last_one(store, tmp_path):
    """cellctl.service.retention: by size, the oldest ended jobs' folders go until the rest fits; by age,
    those ended long enough ago; a running job's folder and the last ended one's always stay, and a
    record whose folder is gone names none."""
    from datetime import datetime, timedelta, timezone

    from cellctl.service.retention import folder_bytes, prune

    root = tmp_path / "jobs"
    states = ["done", "failed", "running", "done", "cancelled"]  # oldest first
    for i, st in enumerate(states):
        d = root / _jid(i)
        d.mkdir(parents=True)
        (d / "scan.rrd").write_bytes(b"x" * 1_000_000)
        store.create(_jid(i), "sim-1", REQ, str(d))
        store.transition(_jid(i), "running")
        if st != "running":
            store.transition(_jid(i), st, artifacts=Artifacts(dir=str(d), files=["scan.rrd"]))
    assert folder_bytes(root) == 5_000_000
    assert prune(store, root, max_age_days=None, max_gb=None) == []
    assert prune(store, root, max_age_days=None, max_gb=0.0035) == [_jid(0), _jid(1)]  # 5 MB -> 3 MB
    assert sorted(p.name for p in root.iterdir()) == [_jid(2), _jid(3), _jid(4)]
    assert store.get(_jid(0)).artifacts is None and store.get(_jid(0)).state == "done"  # the record stays
    assert prune(store, root, max_age_days=None, max_gb=0.0001) == [_jid(3)]  # not the running one, nor the last
    later = datetime.now(timezone.utc) + timedelta(days=40)
    assert prune(store, root, max_age_days=30, max_gb=None, now=later) == []  # only the last ended is left
    assert sorted(p.name for p in root.iterdir()) == [_jid(2), _jid(4)]


def test_retention_by_age_deletes_what_ended_longer_ago(store, tmp_path):
    from datetime import datetime, timedelta, timezone

    from cellctl.service.retention import prune

    root = tmp_path / "jobs"
    for i in range(3):
        d = root / _jid(i)
        d.mkdir(parents=True)
        store.create(_jid(i), "sim-1", REQ, str(d))
        store.transition(_jid(i), "cancelled", artifacts=Artifacts(dir=str(d), files=[]))
    now = datetime.now(timezone.utc)
    assert prune(store, root, max_age_days=1, max_gb=None, now=now + timedelta(hours=12)) == []
    assert prune(store, root, max_age_days=1, max_gb=None, now=now + timedelta(days=2)) == [_jid(0), _jid(1)]
    assert [p.name for p in root.iterdir()] == [_jid(2)]  # the last ended job's folder stays
