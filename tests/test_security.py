"""Security (docs/RELIABILITY.md, "Security"): the yard router's own limits and per-cell access control,
the scene path allow-list, and no credential in the repo. Real parts only: `cellctl router` with the
shipped deploy/zenoh/router.json5 on loopback, real `cellctl serve` cells, credentials made at test time
by deploy/make-users.sh (the `router` fixture of tests/test_deploy.py).

Tests of: cellctl.service.router, cellctl.service.logs (one line per log record, whatever a key holds)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from test_deploy import ROOT, _creds, free_port, router  # noqa: F401 - router: the module-scoped fixture

from cellctl.service.api import MAX_MESSAGE_BYTES, CellStatus, ErrorReply
from cellctl.service.client import CellClient, CellError
from cellctl.service.loopback import ServiceProcess, write_config
from configs import CONFIG_DIR

SCENES = CONFIG_DIR / "scenes"
BAD_SUBMIT = json.dumps({"scene": "no_such_scene"}).encode()  # refused at once, nothing queued
NO_JOB = "20250101T000000Z-abcdef"
# Liveness bounds: they fail on a hang, never because the machine is loaded. A reply the test needs
# comes in milliseconds (~0.3 s while the cell's scan holds the GIL); a query that must get no reply
# waits out its whole timeout, so that one is shorter, yet far longer than any allowed reply takes.
REPLY_S = 30.0
NO_REPLY_S = 5.0
JOB_S = 300.0  # a scan reaches its first view, or ends after a cancel (idle: seconds)
UP_S = 120.0  # processes come up (a few seconds of imports) or exit (under a second)
YARD_CA: list[Path] = []  # the yard CA of the module's router (set by the `yard` fixture)


def session(endpoint: str, user: str, password: str) -> zenoh.Session:
    """A client of the router (TLS, trusting the yard CA); shared memory off, so big payloads take the
    network path as a tablet's do."""
    c = zenoh.Config()
    c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(YARD_CA[0])))
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/shared_memory/enabled", "false")
    c.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    c.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(c)


def answers(handler) -> list:
    """The replies of whoever answered. Zenoh ends a query nobody answered in time with its own error reply
    b"Timeout" (the router may send it): that is no answer."""
    return [r for r in handler if not (r.err is not None and r.err.payload.to_bytes() == b"Timeout")]


@pytest.fixture(scope="module")
def yard(router, tmp_path_factory):  # noqa: F811 - the imported fixture
    """The router with one real cell (sim-1) behind it, as deployed; sim-2 is left for impostors."""
    endpoint, pw, rproc, ca = router
    YARD_CA[:] = [ca]
    d = tmp_path_factory.mktemp("yard")
    cfg = write_config(d / "sim-1.yaml", free_port(), d / "data", cell_id="sim-1", zenoh_mode="client", listen=[],
                       connect=[endpoint], zenoh_config_file=_creds(d, "cell-sim-1", pw["cell-sim-1"], ca))
    with open(d / "cell.log", "w") as log:
        cell = subprocess.Popen([sys.executable, "-m", "cellctl.cli", "serve", "--config", str(cfg)], cwd=ROOT,
                                stdout=log, stderr=subprocess.STDOUT)
    try:
        with CellClient("sim-1", [endpoint], timeout_s=REPLY_S,
                        zenoh_config_file=_creds(d, "operator", pw["operator"], ca)) as c:
            deadline = time.monotonic() + UP_S
            while not c.alive(0.5):
                assert cell.poll() is None and time.monotonic() < deadline, (d / "cell.log").read_text()[-2000:]
        yield endpoint, pw, rproc, cell
    finally:
        cell.send_signal(signal.SIGTERM)
        try:
            assert cell.wait(timeout=UP_S) == 0
        except subprocess.TimeoutExpired:
            cell.kill()
            pytest.fail(f"the cell did not exit within {UP_S:g} s of SIGTERM")


def _alive(yard) -> None:
    _, _, rproc, cell = yard
    assert rproc.poll() is None and cell.poll() is None


def _until(condition, what: str, timeout_s: float = UP_S, period_s: float = 0.05) -> None:
    """Poll ``condition`` until it holds: instead of a sleep that hopes something has happened by then."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(period_s)


def _through_the_router(sender: zenoh.Session, receiver: zenoh.Session, user: str) -> None:
    """Until something ``sender`` (a cell's credentials) publishes after this call has come through the
    router to ``receiver``: one session's messages reach the router in order, so the router has handled
    whatever ``sender`` sent before (e.g. a declaration the access control denies, which nothing else shows)."""
    key = f"cell/{user.removeprefix('cell-')}/jobs/{NO_JOB}/events"
    marks: list[bytes] = []
    sub = receiver.declare_subscriber(key, lambda sample: marks.append(sample.payload.to_bytes()))
    try:
        _until(lambda: sender.put(key, b"mark") or bool(marks), f"nothing {user} published came through",
               period_s=0.2)
    finally:
        sub.undeclare()


def _serves(s: zenoh.Session, key: str, payload: bytes | None = None) -> list[bytes]:
    """What a query through the router gets back, right now (a declaration still on its way: nothing)."""
    return [r.ok.payload.to_bytes() for r in answers(s.get(key, payload=payload, timeout=REPLY_S)) if r.ok is not None]


# --- the router's own limits -----------------------------------------------------------------------
def test_the_shipped_router_config_caps_messages_sessions_and_commands():
    """Read the way `cellctl router` reads it: the caps are in the shipped file, not only in a test."""
    from cellctl.service.router import router_config

    cfg = router_config(ROOT / "deploy/zenoh/router.json5")
    get = lambda key: json.loads(cfg.get_json(key))  # noqa: E731
    assert get("transport/link/rx/max_message_size") == MAX_MESSAGE_BYTES  # Zenoh's default: 1 GiB
    assert get("transport/unicast/max_sessions") == 64 and get("transport/unicast/max_links") == 1
    assert {r["key_expr"]: r["freq"] for d in get("downsampling") for r in d["rules"]} == \
        {"cell/*/jobs/submit": 5.0, "cell/*/jobs/*/cancel": 5.0, "cell/*/paint/commission": 1.0}
    assert all(d["flows"] == ["ingress"] and d["messages"] == ["query"] for d in get("downsampling"))
    acl = get("access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert get("transport/auth/usrpwd/dictionary_file") and get("transport/auth/usrpwd/password") is None


def test_an_oversized_query_is_dropped_by_the_router_and_everyone_carries_on(yard):
    """2 MiB from an authorized operator: the router drops it (a probe queryable with Zenoh's 1 GiB default
    never sees it, while 512 KiB passes), the real cell gets nothing, and both answer the next query."""
    endpoint, pw, _, _ = yard
    seen: list[int] = []
    probe = session(endpoint, "cell-sim-2", pw["cell-sim-2"])  # stands in for cell sim-2: no cap of its own
    op = session(endpoint, "operator", pw["operator"])
    try:
        def answer(q: zenoh.Query) -> None:
            n = len(q.payload.to_bytes()) if q.payload is not None else 0
            seen.append(n)
            q.reply(q.key_expr, str(n).encode())

        probe_q = probe.declare_queryable("cell/sim-2/status", answer)
        _until(lambda: _serves(op, "cell/sim-2/status") == [b"0"], "the probe's declaration never reached the router")
        seen.clear()
        half = MAX_MESSAGE_BYTES // 2
        r = answers(op.get("cell/sim-2/status", payload=b"x" * half, timeout=REPLY_S))
        assert [x.ok.payload.to_bytes() for x in r] == [str(half).encode()] and seen == [half]
        big = b"{" * (2 * MAX_MESSAGE_BYTES)
        t0 = time.monotonic()
        assert answers(op.get("cell/sim-2/status", payload=big, timeout=NO_REPLY_S)) == []
        # not even an error came back early: the query waited out its timeout (a lower bound no load can
        # break), and the probe never saw it
        assert time.monotonic() - t0 >= NO_REPLY_S - 0.5 and seen == [half]
        assert answers(op.get("cell/sim-1/jobs/submit", payload=big, timeout=NO_REPLY_S)) == []
        assert answers(op.get("cell/sim-1/status", payload=big, timeout=NO_REPLY_S)) == []
        # the same session, the router and the cell carry on
        r = answers(op.get("cell/sim-1/status", timeout=REPLY_S))
        assert len(r) == 1 and CellStatus.model_validate_json(r[0].ok.payload.to_bytes()).cell_id == "sim-1"
        r = answers(op.get("cell/sim-2/status", payload=b"{}", timeout=REPLY_S))
        assert [x.ok.payload.to_bytes() for x in r] == [b"2"] and seen == [half, 2]
        probe_q.undeclare()
    finally:
        op.close()
        probe.close()
    _alive(yard)


def _burst(s: zenoh.Session, key: str, payload: bytes | None, n: int, timeout_s: float,
           meanwhile=lambda: None) -> list[tuple[float, list]]:
    """``n`` queries sent back to back, then ``meanwhile()``: for each query, (time sent, [(time received,
    code or b"ok")] of its answers), once every one of them has ended (answered, or timed out: dropped)."""
    results: list[tuple[float, list]] = []
    ended = [threading.Event() for _ in range(n)]

    def on_reply(got: list, r) -> None:
        if r.ok is not None:
            got.append((time.monotonic(), b"ok"))
        elif r.err.payload.to_bytes() != b"Timeout":  # Zenoh's own end of an unanswered query: no answer
            got.append((time.monotonic(), ErrorReply.model_validate_json(r.err.payload.to_bytes()).code))

    for i in range(n):
        got: list = []
        results.append((time.monotonic(), got))
        s.get(key, zenoh.handlers.Callback(lambda r, got=got: on_reply(got, r), ended[i].set), payload=payload,
              timeout=timeout_s)
    meanwhile()
    for e in ended:
        assert e.wait(timeout_s + UP_S), "a query never ended"
    return results


def test_commands_are_rate_limited_per_session_reads_are_not(yard):
    """Zenoh downsampling in the router: a session's commands (submit, cancel) pass at most one per 0.2 s,
    the others are dropped (no reply); another session is not held up by it, and a command 0.2 s after the
    last one that passed is answered. Judged by what the clock cannot blur on a loaded machine:
    - of a burst sent back to back, not all pass (the router would have had to take 0.2 s per command
      to read them) and the first does;
    - two commands that both passed were read by the router 0.2 s apart or more, and it reads one before
      answering it, so the later one's answer came at least 0.2 s after the earlier one was sent;
    - the command after the pause is sent 0.3 s after the last answer came back: more than 0.2 s after the
      router read that command, however long the answer took."""
    endpoint, pw, _, _ = yard
    op, other = (session(endpoint, "operator", pw["operator"]) for _ in range(2))
    n = 10
    try:
        for key, code in [("cell/sim-1/jobs/submit", "invalid_request"),
                          (f"cell/sim-1/jobs/{NO_JOB}/cancel", "not_found")]:
            payload = BAD_SUBMIT if "submit" in key else None
            elsewhere = []  # another session's command, sent right after the burst: not held up by it

            def meanwhile(key=key, payload=payload):
                elsewhere.extend(answers(other.get(key, payload=payload, timeout=REPLY_S)))

            burst = _burst(op, key, payload, n, 10.0, meanwhile)
            passed = [(sent, got) for sent, got in burst if got]
            assert all([c for _, c in got] == [code] for _, got in passed), burst
            assert burst[0][1] and 1 <= len(passed) < n, [len(got) for _, got in burst]
            for (sent, _), (_, got) in zip(passed, passed[1:]):
                assert got[0][0] - sent >= 0.2, burst
            assert [ErrorReply.model_validate_json(r.err.payload.to_bytes()).code for r in elsewhere] == [code]
            time.sleep(max(0.0, max(got[0][0] for _, got in passed) + 0.3 - time.monotonic()))
            after = answers(op.get(key, payload=payload, timeout=REPLY_S))
            assert [ErrorReply.model_validate_json(r.err.payload.to_bytes()).code for r in after] == [code]
        reads = [op.get("cell/sim-1/status", timeout=REPLY_S) for _ in range(5)]  # a burst of reads: all answered
        assert all(len(answers(h)) == 1 for h in reads)
    finally:
        op.close()
        other.close()
    _alive(yard)


# --- access control: operators command, cells only serve, tablets publish nothing -------------------
def test_an_operator_submits_and_cancels_through_the_router(yard, tmp_path):
    """An operator's commands pass the ACL and the rate limit: a real job runs, its events reach the
    operator through the router, the cancel stops it and its files can be fetched. The router's own admin
    space stays closed."""
    endpoint, pw, _, _ = yard
    events, started = [], threading.Event()

    def on(ev) -> None:
        events.append(ev.phase)
        if ev.step == 0:
            started.set()

    creds = _creds(tmp_path, "operator", pw["operator"], YARD_CA[0])
    with CellClient("sim-1", [endpoint], timeout_s=REPLY_S, zenoh_config_file=creds) as c:
        job = c.submit({"scene": "smooth_cylinder", "max_steps": 12, "noise": False}, on_event=on).job_id
        assert started.wait(JOB_S), events
        assert c.cancel(job, reason="security test").state == "cancelling"
        rec = c.wait(job, JOB_S)
        assert rec.state == "cancelled" and rec.transitions[-2].note == "cancel requested: security test"
        assert events[0] == "queued" and "scanning" in events
        names = [f.name for f in c.files(job).files]  # what the cancelled job wrote, fetched through the router
        assert "scan.rrd" in names and c.fetch(job, "result.json", tmp_path / "result.json").size > 0
        admin = answers(c.session.get("@/**", timeout=NO_REPLY_S))  # only the operator's own session answers
        assert admin and all(str(r.ok.key_expr).startswith(f"@/{c.session.zid()}/") for r in admin)
    _alive(yard)


def test_a_cell_can_only_serve_its_own_keys(yard):
    """A cell's credentials (cell-sim-2) cannot query, command or answer for another cell: an impostor
    queryable on cell/sim-1 is never offered to the operator, whose query reaches only the real sim-1."""
    endpoint, pw, _, _ = yard
    imp, own = (session(endpoint, "cell-sim-2", pw["cell-sim-2"]) for _ in "12")
    op = session(endpoint, "operator", pw["operator"])
    asked: list[str] = []
    try:
        mine = own.declare_queryable("cell/sim-2/status", lambda q: q.reply(q.key_expr, b"sim-2"))
        _until(lambda: _serves(op, "cell/sim-2/status") == [b"sim-2"], "cell-sim-2's own queryable never reached "
                                                                       "the operator")
        assert answers(imp.get("cell/sim-2/status", timeout=NO_REPLY_S)) == []  # not even its own: a cell only serves
        assert answers(imp.get("cell/sim-1/jobs/submit", payload=BAD_SUBMIT, timeout=NO_REPLY_S)) == []
        assert answers(imp.get(f"cell/sim-1/jobs/{NO_JOB}/cancel", timeout=NO_REPLY_S)) == []
        assert answers(imp.get("cell/sim-1/status", timeout=NO_REPLY_S)) == []
        mine.undeclare()

        def impostor(q: zenoh.Query) -> None:
            asked.append(str(q.key_expr))
            q.reply(q.key_expr, b"impostor")

        fake = imp.declare_queryable("cell/sim-1/**", impostor)
        _through_the_router(imp, op, "cell-sim-2")  # the router has handled (and denied) that declaration
        for key, payload in [("cell/sim-1/status", None), ("cell/sim-1/jobs/submit", BAD_SUBMIT)]:
            replies = answers(op.get(key, payload=payload, target=zenoh.QueryTarget.ALL,
                                     consolidation=zenoh.ConsolidationMode.NONE, timeout=REPLY_S))
            assert len(replies) == 1, [(r.ok or r.err).payload.to_bytes()[:80] for r in replies]
            r = replies[0]
            assert b"impostor" not in (r.ok or r.err).payload.to_bytes()
        assert asked == []
        fake.undeclare()
    finally:
        for s_ in (op, imp, own):
            s_.close()
    _alive(yard)


def test_only_a_cell_publishes_its_own_events(yard):
    """Job events are what tablets show: a viewer, an operator or another cell cannot publish fake ones."""
    endpoint, pw, _, _ = yard
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()
    op = session(endpoint, "operator", pw["operator"])
    others = {u: session(endpoint, u, pw[u]) for u in ("viewer", "operator", "cell-sim-2")}
    try:
        def on(sample: zenoh.Sample) -> None:
            with lock:
                got.append((str(sample.key_expr), sample.payload.to_bytes()))

        def arrived(payload: bytes) -> bool:
            with lock:
                return any(p == payload for _, p in got)

        own = f"cell/sim-2/jobs/{NO_JOB}/events"
        sub = op.declare_subscriber("cell/*/jobs/*/events", on)
        # the control, a cell's own event, is delivered: sent until one arrives (the subscription is in place)
        _until(lambda: others["cell-sim-2"].put(own, b"own event") or arrived(b"own event"),
               "a cell's own event never arrived", period_s=0.2)
        for user, s in others.items():
            s.put(f"cell/sim-1/jobs/{NO_JOB}/events", f"fake from {user}".encode())
        # Instead of waiting a while for fakes that must not come: each session's messages reach the router in
        # order, so once a query each faking session sent after its fake is answered, the router has handled
        # the fake (forwarded it to the operator, or dropped it); the router forwards to the operator in order,
        # so a fake it had forwarded arrives before a control published after that.
        for user in ("viewer", "operator"):
            assert len(answers(others[user].get("cell/sim-1/status", timeout=REPLY_S))) == 1, user
        others["cell-sim-2"].put(own, b"last")  # after its own fake, on the same session
        _until(lambda: arrived(b"last"), "the last control never arrived")
        with lock:
            assert {k for k, _ in got} == {own} and {p for _, p in got} == {b"own event", b"last"}, got
        sub.undeclare()
    finally:
        for s in (op, *others.values()):
            s.close()
    _alive(yard)


# --- scene paths -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene_cell(tmp_path_factory):
    """A cell whose scene directories are the shipped configs/scenes and, relative to its config file,
    scenes/ (with symlinks planted in it); outside/ holds a valid scene the cell must not read."""
    work = tmp_path_factory.mktemp("scene-cell")
    (work / "outside").mkdir()
    for f in ("example_plate.yaml", "example_plate.obj"):
        shutil.copy(SCENES / f, work / "outside" / f)
    (work / "scenes").mkdir()
    (work / "scenes" / "escape.yaml").symlink_to(work / "outside" / "example_plate.yaml")
    (work / "scenes" / "toml.yaml").symlink_to(ROOT / "pyproject.toml")
    (work / "scenes" / "mesh.yaml").symlink_to(SCENES / "example_plate.obj")  # inside, but not a scene file
    svc = ServiceProcess(work, scene_dirs=[str(SCENES), "scenes"]).start()
    yield svc, work
    rc, _ = svc.stop(signal.SIGTERM)
    assert rc == 0


OUTSIDE = [
    "configs/scenes/../cell.sim.yaml",  # traversal to an existing yaml (a cell config)
    "configs/scenes/../../pyproject.yaml",  # traversal to nothing
    str(CONFIG_DIR / "cell.sim.yaml"),  # absolute, exists
    "/etc/scrapcell/cell-1.yaml",  # absolute, does not exist here
    "{work}/outside/example_plate.yaml",  # a valid scene, outside
    "{work}/scenes/../outside/example_plate.yaml",
    "{work}/scenes/escape.yaml",  # a symlink inside to that scene outside
    "{work}/scenes/toml.yaml",  # a symlink inside to a non-yaml file outside
    "{work}/scenes/mesh.yaml",  # a symlink inside to a non-yaml file inside
]


def test_scene_paths_outside_the_allowed_directories_are_refused_alike(scene_cell):
    """Each gets invalid_request naming `scene` and the allowed directories, and one message shape whether
    the file exists or not (the reply tells nothing about the cell's other files); no job is created."""
    svc, work = scene_cell
    allowed = f"{SCENES}, {(work / 'scenes').resolve()}"
    shapes = set()
    with svc.client() as c:
        for scene in [s.format(work=work) for s in OUTSIDE]:
            with pytest.raises(CellError) as e:
                c.submit({"scene": scene, "max_steps": 1, "noise": False})
            err = e.value
            assert err.code == "invalid_request" and [d["loc"] for d in err.details] == ["scene"], (scene, err)
            assert allowed in err.message and "service.scene_dirs" in err.message, err.message
            shapes.add(err.message.replace(repr(scene), "<scene>"))
        assert len(shapes) == 1, shapes
        for scene, words in [("configs/scenes/example_plate.obj", "pattern"),  # not .yaml: the model refuses it
                             ("configs/scenes/no_such.yaml", "no scene file")]:  # inside: may say it is missing
            with pytest.raises(CellError) as e:
                c.submit({"scene": scene, "max_steps": 1})
            assert e.value.code == "invalid_request" and words in e.value.message, e.value.message
        st = c.status()
        assert st.jobs_total == 0 and st.queue_length == 0 and st.running_job is None
        assert c.jobs().jobs == []


def test_a_scene_inside_the_allowed_directory_runs(scene_cell):
    """The shipped example scene, named relative to the service's working directory, runs to the end."""
    svc, _ = scene_cell
    with svc.client() as c:
        job = c.submit({"scene": "configs/scenes/example_plate.yaml", "max_steps": 1, "noise": False}).job_id
        rec = c.wait(job, JOB_S)
    assert rec.state == "done", rec.error
    assert rec.request.scene == "configs/scenes/example_plate.yaml" and rec.result.scene == "example_plate"


def test_scene_dirs_default_and_relative_entries_resolve_against_the_config_file(tmp_path):
    """The default is scenes/ beside the config (configs/scenes for the shipped one); a symlink inside that
    points inside is followed, and the job gets the resolved path."""
    from cellctl.config import ServiceConfig, load_cell_config
    from cellctl.service.server import CellService

    cfg, path = load_cell_config(CONFIG_DIR / "cell.sim.yaml")
    assert cfg.service.scene_dirs == ["scenes"]
    svc = CellService(cfg, path, tmp_path / "data")
    try:
        assert svc.scene_dirs == [SCENES]
        assert svc._check_scene(str(SCENES / "example_plate.yaml")) == str(SCENES / "example_plate.yaml")
        assert svc._check_scene("t_piece") == "t_piece"
    finally:
        svc.store.close()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "alias.yaml").symlink_to(SCENES / "example_plate.yaml")
    cfg2 = cfg.model_copy(update={"planners_config": str(CONFIG_DIR / "planners.yaml"),
                                  "service": cfg.service.model_copy(update={"scene_dirs": ["mine", str(SCENES)]})})
    svc = CellService(cfg2, tmp_path / "cell.yaml", tmp_path / "data2")
    try:
        assert svc.scene_dirs == [(tmp_path / "mine").resolve(), SCENES]
        assert svc._check_scene(str(tmp_path / "mine" / "alias.yaml")) == str(SCENES / "example_plate.yaml")
    finally:
        svc.store.close()
    cfg3 = cfg.model_copy(update={"service": cfg.service.model_copy(update={"scene_dirs": []})})
    svc = CellService(cfg3, path, tmp_path / "data3")
    try:
        with pytest.raises(Exception, match=r"scene_dirs: none"):
            svc._check_scene(str(SCENES / "example_plate.yaml"))
    finally:
        svc.store.close()
    for bad in (["d"] * 17, [""], ["a\nb"], ["x" * 501]):
        with pytest.raises(ValueError, match="scene_dirs"):
            ServiceConfig(scene_dirs=bad)


# --- no secret in the repo -------------------------------------------------------------------------
PRIVATE_KEY = re.compile(r"-{5}BEGIN (?:[A-Z0-9]+ )*PRIVATE KEY-{5}")
ASSIGNED = re.compile(r"""(?i)["']?\b(pass(?:word|wd)?|secret|token|api[_-]?key|private[_-]?key(?:_pem)?)\b["']?"""
                      r"""\s*[:=]\s*(?P<v>"[^"\n]*"|'[^'\n]*'|<[^>\n]*>|[^\s,;}\]#]+)""")
DICTIONARY_LINE = re.compile(r"^\s*[A-Za-z0-9_.@-]{1,64}:[^\s:\"'`]{8,}\s*$")
SECRET_FILE = re.compile(r"(^|/)(zenoh-users\.txt|[^/]*\.password|[^/]*\.pem|[^/]*\.key|id_(rsa|dsa|ecdsa|ed25519)|"
                         r"\.env)$")
PLACEHOLDER = re.compile(r"(?i)^(|null|none|~|true|false|<[^>]*>|\$\{?[A-Za-z_][A-Za-z0-9_]*\}?|x+|\*+|\.\.\.|"
                         r"change[-_ ]?me|redacted|placeholder)$")


def find_secrets(root: Path, files: list[str]) -> list[str]:
    """Credential material in these files: private key blocks, literal passwords/tokens in config, docs or
    code (placeholders such as null, "<...>" or ${VAR} are fine), `user:password` dictionary lines, and
    files whose names say they hold credentials."""
    found = []
    for name in files:
        fenced = False
        if SECRET_FILE.search(name):
            found.append(f"{name}: a credential file is tracked")
        try:
            text = (root / name).read_text(encoding="utf-8")
        except (UnicodeDecodeError, IsADirectoryError, FileNotFoundError):
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if PRIVATE_KEY.search(line):
                found.append(f"{name}:{n}: a private key")
            if name.endswith(".md") and line.lstrip().startswith("```"):
                fenced = not fenced
            for m in ASSIGNED.finditer(line):
                v = m.group("v")
                quoted = v[:1] in "\"'"
                if not quoted and (name.endswith(".py") or (name.endswith(".md") and not fenced)):
                    continue  # a variable (password=pw) or prose ("token: present while ..."), not a value
                if not PLACEHOLDER.match(v.strip("\"'")):
                    found.append(f"{name}:{n}: {m.group(1)} with a literal value")
            if not name.endswith((".py", ".md")) and DICTIONARY_LINE.match(line):
                found.append(f"{name}:{n}: a user:password line")
    return found


def test_no_credentials_are_tracked_in_the_repo():
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True,
                           timeout=30).stdout.decode().split("\0")
    files = [f for f in files if f]
    assert len(files) > 50 and "deploy/zenoh/router.json5" in files
    assert find_secrets(ROOT, files) == []


def test_the_secret_scan_finds_planted_credentials(tmp_path):
    """The scan is only worth something if it fires: plant one of each kind (built at run time, so this
    file holds none) and a few placeholders that must pass."""
    pem = "-" * 5 + "BEGIN OPENSSH PRIVATE KEY" + "-" * 5
    planted = {
        "router.json5": '{ transport: { auth: { usrpwd: { user: "operator", pass' + 'word: "s3cr3t-Pw" } } } }',
        "cell.yaml": "service:\n  pass" + "word: hunter2hunter2\n",
        "client.py": 'CONF = {"pass' + 'word": "letmein-123"}\n',
        "users.txt": "operator:" + "Zq8" * 6 + "\n",
        "deploy.md": f"```\n{pem}\nAAAA\n```\n",
        "setup.md": "Then:\n```yaml\nusrpwd:\n  pass" + "word: Op3rator-2024\n```\n",
        "zenoh-users.txt": "",
        "operator.password": "",
    }
    fine = {
        "ok.json5": '{ usrpwd: { user: null, pass' + 'word: null, dictionary_file: "/etc/x" } }',
        "ok.yaml": "pass" + "word: <from make-users.sh>\ntoken: ${ZENOH_TOKEN}\n",
        "ok.py": "c.insert_json5('transport/auth/usrpwd/pass" + "word', json.dumps(pw))\nrun(pass" + "word=pw)\n",
        "ok.md": "A liveliness token: present while the cell is up.\n```yaml\npass" + "word: <from make-users>\n```\n",
    }
    for name, text in {**planted, **fine}.items():
        (tmp_path / name).write_text(text)
    found = find_secrets(tmp_path, [*planted, *fine])
    assert {f.split(":")[0] for f in found} == set(planted), found


def test_make_users_makes_fresh_private_credentials(tmp_path):
    """deploy/make-users.sh (which tests/test_deploy.py runs) makes new random passwords each time, readable
    by the owner only; the script itself holds none."""
    runs = []
    for i in range(2):
        d = tmp_path / f"run{i}"
        subprocess.run(["sh", str(ROOT / "deploy/make-users.sh"), str(d), "operator", "viewer"], check=True,
                       capture_output=True, timeout=30)
        lines = (d / "zenoh-users.txt").read_text().splitlines()
        assert [ln.split(":")[0] for ln in lines] == ["operator", "viewer"]
        pws = [ln.split(":", 1)[1] for ln in lines]
        assert pws == [(d / f"{u}.password").read_text().strip() for u in ("operator", "viewer")]
        assert all(re.fullmatch(r"[A-Za-z0-9]{24}", p) for p in pws), [len(p) for p in pws]  # as RELIABILITY.md says
        for f in (d / "zenoh-users.txt", d / "operator.password", d / "viewer.password"):
            assert stat.S_IMODE(os.stat(f).st_mode) == 0o600, f
        assert stat.S_IMODE(os.stat(d).st_mode) == 0o700
        runs.append(pws)
    assert not set(runs[0]) & set(runs[1])
    script = (ROOT / "deploy/make-users.sh").read_text()
    assert "/dev/urandom" in script and find_secrets(ROOT, ["deploy/make-users.sh"]) == []


def test_a_line_forged_in_a_key_is_escaped_in_the_log(scene_cell):
    """A key, like every string a client sends, reaches the cell's log on one line: a newline or a NUL
    in it is written as its escape, so it cannot forge a line of the log (nor of journald's)."""
    svc, _ = scene_cell
    forged = "2026-12-01 16:40:00,000 INFO job 20261201T164000Z-abcdef done"
    with svc.client() as c:
        replies = list(c.session.get(f"cell/sim-1/jobs/x\n{forged}\x00", timeout=REPLY_S))
    assert len(replies) == 1 and replies[0].err is not None  # not_found, as for any unknown job
    assert json.loads(replies[0].err.payload.to_bytes())["code"] == "not_found"
    deadline = time.monotonic() + 10.0
    while "x\\n" + forged not in svc.log.read_text() and time.monotonic() < deadline:
        time.sleep(0.1)
    log = svc.log.read_text()
    assert "x\\n" + forged + "\\x00" in log, log[-2000:]
    assert not any(line.startswith(forged) for line in log.splitlines())
