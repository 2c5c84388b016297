"""The contract's proof: tests/raw_client.py was written from docs/API.md alone (no cellctl import, only
the standard library and zenoh) and drives a real `cellctl serve` on loopback: it submits, loses a reply
and retries safely, follows the job's events, waits for the end and fetches the cut and the recording.

Tests of: the contract in docs/API.md (cellctl.service.apidoc)."""

from __future__ import annotations

import ast
import hashlib
import json
import signal
import sys
import threading
from pathlib import Path

import pytest

from cellctl.service.loopback import ServiceProcess

sys.path.insert(0, str(Path(__file__).parent))
from raw_client import CellError, NoAnswer, RawCell  # noqa: E402 - the client under test, beside this file

START_S = 120.0  # a started service answers within this (idle: a few seconds of imports)
JOB_S = 300.0  # a short scan ends within this (idle: seconds)
REPLY_S = 30.0


def test_the_raw_client_imports_only_the_standard_library_and_zenoh():
    tree = ast.parse((Path(__file__).parent / "raw_client.py").read_text())
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            roots.add((node.module or "").split(".")[0])
    assert roots <= set(sys.stdlib_module_names) | {"zenoh", "__future__"}, roots


def test_a_client_written_from_the_docs_alone_submits_follows_fetches_and_retries(tmp_path):
    svc = ServiceProcess(tmp_path / "cell").start(START_S)
    try:
        with RawCell(svc.endpoint, "sim-1", timeout_s=REPLY_S) as cell:
            assert cell.status()["ready"] is True
            events, ended = [], threading.Event()

            def on_event(ev: dict) -> None:
                events.append(ev)
                if ev["phase"] in ("done", "failed", "cancelled", "interrupted"):
                    ended.set()

            sub = cell.subscribe_events(on_event)
            req = {"scene": "smooth_cylinder", "max_steps": 2, "noise": False, "request_id": "raw-client:0001"}
            try:  # a reply lost to a client that gave up after 1 ms: the cell may have queued the job
                cell.submit(req, retries=1, timeout_s=0.001)
            except NoAnswer:
                pass
            job_id = cell.submit(req)["job_id"]  # the documented retry: the same request, request_id and all
            with pytest.raises(CellError) as e:
                cell.submit({**req, "max_steps": 3})  # the same key for another job
            assert e.value.code == "invalid_request"
            record = cell.wait(job_id, JOB_S)
            assert record["state"] == "done" and record["request"]["request_id"] == req["request_id"]
            assert ended.wait(REPLY_S), events
            mine = [ev for ev in events if ev["job_id"] == job_id]
            assert [ev["seq"] for ev in mine] == list(range(len(mine))) and mine[-1]["phase"] == "done"
            sub.undeclare()
            folder = Path(record["artifacts"]["dir"])
            names = [f["name"] for f in cell.files(job_id)["files"]]
            assert "cut_path.json" in names and "scan.rrd" in names
            for name in ("cut_path.json", "scan.rrd"):
                got = cell.fetch(job_id, name, str(tmp_path / name), chunk=64 * 1024)
                assert (tmp_path / name).read_bytes() == (folder / name).read_bytes()
                assert got["sha256"] == hashlib.sha256((folder / name).read_bytes()).hexdigest()
            assert json.loads((tmp_path / "cut_path.json").read_text())["branches"]
            with pytest.raises(CellError) as e:
                cell.job("20250101T000000Z-abcdef")
            assert e.value.code == "not_found"
        with RawCell(svc.endpoint, "no-such-cell", timeout_s=1.0) as nobody:
            with pytest.raises(NoAnswer):
                nobody.status()
        rc, _ = svc.stop(signal.SIGTERM)
        assert rc == 0
    finally:
        svc.kill()
