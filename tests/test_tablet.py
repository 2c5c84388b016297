"""The tablet app's parts without a browser: its config, its logins, the 3-D picture of a job, the words.

Tests of: cellctl.tablet.config, cellctl.tablet.accounts, cellctl.tablet.geometry, cellctl.tablet.words,
cellctl.tablet.yard (the browser test runs it whole: tests/test_tablet_browser.py)."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from cellctl.service.api import JobRecord, ScanDrawingRequest, Transition
from cellctl.service.loopback import ROOT
from cellctl.tablet import geometry, words
from cellctl.tablet.accounts import AccountBook, Accounts, add_user, load_accounts
from cellctl.tablet.config import load_config


def test_the_shipped_config_loads_and_a_bad_one_names_its_field(tmp_path):
    cfg = load_config(ROOT / "configs" / "tablet.yaml")
    assert cfg.zenoh_mode == "client" and cfg.connect == ["tcp/127.0.0.1:7447"]
    bad = tmp_path / "t.yaml"
    for text, field in [("port: 0\n", "port"), ("connect: [127.0.0.1:7447]\n", "connect"),
                        ("zenoh_mode: router\n", "zenoh_mode"), ("colour: red\n", "colour"),
                        ("zenoh_config: /nowhere.json5\n", "zenoh_config")]:
        bad.write_text(text)
        with pytest.raises(ValueError, match=rf"t\.yaml: {field}"):
            load_config(bad)


def test_logins_are_salted_scrypt_the_file_is_private_and_a_wrong_password_or_user_fails(tmp_path):
    path = tmp_path / "accounts.yaml"
    add_user(path, "ana", "operator", "cut-steel-42")
    add_user(path, "vic", "viewer", "just-watch-7")
    add_user(path, "ana", "operator", "a-new-password")  # replaces, does not add
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    text = path.read_text()
    assert "cut-steel-42" not in text and "a-new-password" not in text
    accts = load_accounts(path)
    assert [a.user for a in accts.accounts] == ["vic", "ana"]
    assert accts.accounts[0].scrypt.split("$")[3] != accts.accounts[1].scrypt.split("$")[3]  # own salts
    assert accts.check("ana", "a-new-password").role == "operator"
    assert accts.check("vic", "just-watch-7").role == "viewer"
    assert accts.check("ana", "cut-steel-42") is None
    assert accts.check("nobody", "a-new-password") is None
    with pytest.raises(ValueError, match="at least 8"):
        add_user(path, "bo", "viewer", "short")
    with pytest.raises(ValueError, match="no accounts file"):
        load_accounts(tmp_path / "none.yaml")
    (tmp_path / "empty.yaml").write_text("accounts: []\n")
    with pytest.raises(ValueError, match="no accounts"):
        load_accounts(tmp_path / "empty.yaml")
    assert isinstance(accts, Accounts)


def test_the_cli_adds_a_login_from_stdin_and_refuses_to_serve_without_accounts(tmp_path):
    cfg = tmp_path / "tablet.yaml"
    cfg.write_text(f"accounts_file: {tmp_path / 'acc.yaml'}\nstate_dir: {tmp_path / 'state'}\n")
    run = [sys.executable, "-m", "cellctl.cli", "tablet", "--config", str(cfg)]
    r = subprocess.run(run, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "no accounts file" in r.stderr and "--add-user" in r.stderr
    r = subprocess.run(run + ["--add-user", "ana", "--role", "viewer"], input="cut-steel-42\n", cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert load_accounts(tmp_path / "acc.yaml").check("ana", "cut-steel-42").role == "viewer"


def test_a_login_removed_or_changed_ends_in_the_running_app_at_once(tmp_path):
    """A lost tablet: `cellctl tablet --remove-user` takes its login away, and the running app's AccountBook
    sees that at the next page or command (the pages log such a session out), without a restart."""
    path = tmp_path / "acc.yaml"
    add_user(path, "ana", "operator", "cut-steel-42")
    add_user(path, "tab7", "operator", "lost-tablet-7")
    book = AccountBook(path)
    assert book.lookup("tab7").role == "operator" and book.check("tab7", "lost-tablet-7")
    cfg = tmp_path / "tablet.yaml"
    cfg.write_text(f"accounts_file: {path}\nstate_dir: {tmp_path / 'state'}\n")
    run = [sys.executable, "-m", "cellctl.cli", "tablet", "--config", str(cfg)]
    r = subprocess.run(run + ["--remove-user", "tab7"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "removed" in r.stdout, r.stderr
    assert book.lookup("tab7") is None and book.check("tab7", "lost-tablet-7") is None
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    r = subprocess.run(run + ["--remove-user", "tab7"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "has no login 'tab7'" in r.stderr and "Traceback" not in r.stderr, r.stderr
    add_user(path, "ana", "viewer", "cut-steel-42")  # demoted: the role the pages see changes too
    assert book.lookup("ana").role == "viewer"
    path.unlink()  # gone: nobody, rather than the logins it last held
    assert book.lookup("ana") is None


def test_thinning_keeps_an_even_spread_under_the_limit():
    rng = np.random.default_rng(0)
    # a plate seen from near: 90 % of the points in one corner
    near = rng.uniform([0, 0, 0], [0.05, 0.05, 0], (45000, 3))
    far = rng.uniform([0, 0, 0], [0.5, 0.5, 0], (5000, 3))
    xyz = np.concatenate([near, far])
    rgb = np.arange(len(xyz))[:, None].repeat(3, 1).astype(float)
    out, out_rgb = geometry.thin(xyz, 2000, rgb)
    assert 500 < len(out) <= 2000
    assert np.array_equal(xyz[out_rgb[:, 0].astype(int)], out)  # colours travel with their points
    in_corner = np.mean((out[:, 0] < 0.05) & (out[:, 1] < 0.05))
    assert in_corner < 0.1  # the corner is 1 % of the plate; a random subset would keep 90 % there
    small = xyz[:10]
    assert geometry.thin(small, 2000)[0] is small


def _ply(path, xyz, rgb):
    trimesh.PointCloud(xyz, colors=np.c_[rgb, np.full(len(rgb), 255)].astype(np.uint8)).export(path)


def test_a_jobs_picture_frames_the_drawing_crops_the_floor_and_draws_the_torch_axes(tmp_path):
    t = np.linspace(0, 1, 200)
    line = np.c_[0.5 + 0.2 * t, 0.1 * np.sin(3 * t), np.full_like(t, 0.3)]
    plate = np.c_[np.random.default_rng(1).uniform([0.3, -0.2], [0.9, 0.3], (30000, 2)), np.full(30000, 0.3)]
    floor = np.c_[np.random.default_rng(2).uniform([-2, -2], [2, 2], (30000, 2)), np.zeros(30000)]
    _ply(tmp_path / "surface.ply", np.concatenate([plate, floor]), np.full((60000, 3), 120))
    _ply(tmp_path / "drawing.ply", line, np.tile([200, 10, 10], (200, 1)))
    normals = np.tile([0.0, 0.0, 1.0], (200, 1))
    cut = {"branches": [{"points": line[:150].tolist(), "normals": normals[:150].tolist(), "feasible": True},
                        {"points": line[150:].tolist(), "normals": normals[150:].tolist(), "feasible": False}],
           "gaps": [{"points": line[150:].tolist(), "length_m": 0.05}, {"points": None, "length_m": 0.0}]}
    (tmp_path / "cut_path.json").write_text(json.dumps(cut))
    files = {n: tmp_path / n for n in geometry.FILES}
    g = geometry.load(files, max_points=5000)
    centre, radius = g.frame()
    assert np.allclose(centre, [0.6, line[:, 1].max() / 2, 0.3], atol=0.01) and 0.1 <= radius < 0.2
    assert 0 < len(g.surface) <= 5000 and not np.any(g.surface[:, 2] < 0.29)  # no floor, only the plate
    assert len(g.cuts) == 1 and len(g.blocked) == 1 and len(g.gaps) == 1
    assert len(g.torches) == geometry.TORCH_AXES
    tips, tails = np.array([a for a, _ in g.torches]), np.array([b for _, b in g.torches])
    assert np.allclose(tails - tips, [0, 0, geometry.TORCH_LEN_M])  # the torch stands on the surface normal
    assert geometry.load({}, 5000).missing == list(geometry.FILES)


def test_the_words_a_worker_reads():
    req = ScanDrawingRequest(scene="t_piece")
    rec = JobRecord(job_id="20261203T100000Z-abcdef", cell_id="sim-1", request=req, state="done",
                    created_at="2026-12-03T10:00:00.000Z", updated_at="2026-12-03T10:01:05.500Z",
                    transitions=[Transition(state="queued", at="2026-12-03T10:00:00.000Z"),
                                 Transition(state="running", at="2026-12-03T10:00:02.000Z"),
                                 Transition(state="done", at="2026-12-03T10:01:05.500Z")])
    assert words.elapsed(rec) == "1 min 03 s"
    assert words.elapsed(rec.model_copy(update={"transitions": rec.transitions[:1], "state": "queued"})) == \
        "not started"
    assert words.gap_reason("collision") == "the torch would hit the piece"
    assert words.gap_reason("something new") == "something new"
    assert words.when("not a time") == "not a time" and words.when(None) == "-"
