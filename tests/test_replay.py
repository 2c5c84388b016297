"""A whole scan job recorded into its folder and run again from it (`cellctl scan --record`, `cellctl replay`):
the frames through the RealSense bag player, the arm from its recorded positions, the same scan code.

Tests of: cellctl.scan.replay."""

from __future__ import annotations

import contextlib
import io
import json

import pytest

from cellctl.cli import main
from cellctl.config import load_cell_config
from cellctl.scan.replay import ARM_LOG, BAG, compare
from cellctl.scan.run import run_job
from cellctl.scan.spec import JobSpec
from configs import CONFIG_DIR


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A twin job on t_piece (noise on), recorded."""
    cfg, path = load_cell_config(CONFIG_DIR / "cell.sim.yaml")
    out = tmp_path_factory.mktemp("recorded")
    result, run_dir = run_job(JobSpec(cfg, path, "t_piece", "gnbv", out=str(out), cut=False, record=True))
    assert result.error is None and result.steps >= 2
    return result, run_dir


def _replay(folder, out) -> tuple[int, str, str]:
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(["replay", str(folder), "--out", str(out), "--quiet"])
    return rc, stdout.getvalue(), stderr.getvalue()


def test_a_recorded_twin_job_replays_to_the_same_views_coverage_and_drawing(recorded, tmp_path):
    result, run_dir = recorded
    assert (run_dir / BAG).stat().st_size > 0
    lines = (run_dir / ARM_LOG).read_text().splitlines()
    assert json.loads(lines[0])["model"]["joint_names"][0] == "panda_joint1"
    entries = [json.loads(x) for x in lines[1:]]
    captures = [e for e in entries if "capture" in e]
    assert [e["capture"] for e in captures] == list(range(1, result.steps + 1))  # every view, numbered as in the bag
    assert all(e["wall"] > 0 for e in entries) and all("timestamp" in e for e in captures)
    assert len(entries) - len(captures) >= result.steps  # the start, a position per motion
    rc, out, err = _replay(run_dir, tmp_path)
    assert rc == 0, err
    replayed = next(p for p in tmp_path.iterdir() if p.is_dir())
    c = compare(run_dir, replayed)
    assert c["steps"][0] == c["steps"][1] == result.steps
    assert c["coverage_percent"][0] == c["coverage_percent"][1] == result.coverage_percent
    assert c["drawing_points"][0] == c["drawing_points"][1]
    median_mm, p99_mm = c["drawing_distance_mm"]
    assert median_mm <= 0.5 and p99_mm <= 0.5, c  # the stated tolerance; in practice the same points
    assert "replayed points lie" in out


def test_a_recording_cut_short_fails_the_replay_with_the_reason(recorded, tmp_path):
    _, run_dir = recorded
    short = tmp_path / "short"
    short.mkdir()
    for name in ("result.json", BAG):
        (short / name).write_bytes((run_dir / name).read_bytes())
    lines = (run_dir / ARM_LOG).read_text().splitlines()
    positions = [x for x in lines[1:] if '"q"' in x]
    (short / ARM_LOG).write_text("\n".join([lines[0], *positions[:2]]) + "\n")  # the model, the start, one motion
    rc, _, _ = _replay(short, tmp_path / "out")
    assert rc == 1
    replayed = next((tmp_path / "out").iterdir())
    error = json.loads((replayed / "result.json").read_text())["error"]
    assert "the recording ends after 1 motions" in error, error


def test_replaying_a_job_that_was_not_recorded_says_so(recorded, tmp_path):
    _, run_dir = recorded
    (tmp_path / "result.json").write_bytes((run_dir / "result.json").read_bytes())
    rc, _, err = _replay(tmp_path, tmp_path / "out")
    assert rc == 3 and "has no capture.bag" in err and "--record" in err
    rc, _, err = _replay(tmp_path / "nowhere", tmp_path / "out")
    assert rc == 2 and "no readable result.json" in err
