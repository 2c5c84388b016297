"""`cellctl bench`: the report on a hand-made bench.json (fast), the bench loop with a fake scanner
(fast), and one real `--quick` bench in the twin (slow, ~1-2 min).

Tests of: cellctl.bench.scans, cellctl.bench.report, cellctl.bench.machine, cellctl.bench.scoring, cellctl.bench.stats.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellctl.bench import report, scans
from cellctl.bench.report import PAPER_TABLE_II
from cellctl.scan.result import ScanResult
from planners.registry import PLANNERS

ROOT = Path(__file__).resolve().parents[1]


# --- a hand-made bench.json -------------------------------------------------------------------------

def _run(scene, cat, planner, seed, *, views=4, planning=2.0, disp=0.5, hit=90, total=100, error=None, run_dir=None):
    vp = max(views - 1, 0)
    return {"scene": scene, "category": cat, "planner": planner, "seed": seed, "views": views, "viewpoints": vp,
            "planning_s": planning, "step_s": planning / vp if vp else None, "capture_s": 0.5, "motion_s": 3.0,
            "motion_planning_s": 0.2, "displacement_m": disp,
            "coverage": {"hit": hit, "total": total, "percent": round(100 * hit / total, 2) if total else 0.0},
            "terminated_by": "error" if error else "quality", "peak_memory_mb": 50.0, "process_max_rss_mb": 700.0,
            "wall_s": 9.0, "error": error, "run_dir": run_dir}


def _doc(runs, scenes=("smooth_cylinder", "round_tank"), planners=("gnbv", "cnbv", "global", "enpv")):
    return {"schema_version": 1, "created": "2026-01-01T00:00:00+00:00", "complete": True,
            "bench": {"scenes": list(scenes), "planners": list(planners), "seeds": [0, 1, 2], "quick": False,
                      "memory": True, "noise": True},
            "config": {}, "machine": {"cpus": 2, "python": "3.11", "platform": "test"}, "code": {},
            "process": {"max_rss_mb": 800.0, "wall_s": 100.0}, "runs": runs}


@pytest.fixture
def doc():
    runs = []
    # smooth_cylinder: G-NBV 3 seeds with planning 2, 4, 9 s and views 4, 5, 6 (viewpoints 3, 4, 5)
    for seed, (views, planning, hit) in enumerate([(4, 2.0, 90), (5, 4.0, 95), (6, 9.0, 99)]):
        runs.append(_run("smooth_cylinder", 1, "gnbv", seed, views=views, planning=planning, hit=hit,
                         disp=0.1 * (seed + 1)))
    # C-NBV: 40 s over 3 viewpoints on every seed
    runs += [_run("smooth_cylinder", 1, "cnbv", s, views=4, planning=40.0) for s in range(3)]
    # global: 2 seeds ok (views 7, planning 12 s), one crashed: excluded from the medians
    runs += [_run("smooth_cylinder", 1, "global", s, views=7, planning=12.0) for s in range(2)]
    runs.append(_run("smooth_cylinder", 1, "global", 2, views=2, planning=0.1, hit=3,
                     error="RuntimeError: boom\nTraceback ..."))
    # E-NVP does not import: an error row per seed
    runs += [_run("smooth_cylinder", 1, "enpv", s, views=0, planning=0.0, hit=0, total=0,
                  error="planner 'enpv' does not import: ModuleNotFoundError: No module named 'planners.enpv'")
             for s in range(3)]
    runs += [_run("round_tank", 3, "gnbv", s, views=4, planning=3.0, hit=82, total=82) for s in range(3)]
    return _doc(runs)


def test_medians_over_error_free_seeds(doc):
    aggs = report.aggregate(doc)
    g = aggs[("smooth_cylinder", "gnbv")]
    assert (g.n, g.n_ok) == (3, 3)
    assert g.viewpoints == 4 and g.views == 5
    assert g.planning_s == 4.0
    assert g.step_s == pytest.approx(1.0)  # median of 2/3, 4/4, 9/5
    assert g.displacement_cm == pytest.approx(20.0)
    assert (g.hit, g.total, g.percent) == (95, 100, 95.0)
    assert (g.percent_min, g.percent_max) == (90.0, 99.0)
    gl = aggs[("smooth_cylinder", "global")]
    assert (gl.n, gl.n_ok) == (3, 2) and gl.viewpoints == 6 and gl.hit == 90 and len(gl.errors) == 1
    e = aggs[("smooth_cylinder", "enpv")]
    assert e.n_ok == 0 and e.viewpoints is None and e.percent is None
    assert ("round_tank", "cnbv") not in aggs


def test_ratio_table(doc):
    rows = {r["scene"]: r for r in report.ratio_rows(doc)}
    sc = rows["smooth_cylinder"]
    assert sc["cnbv_gnbv_step"] == pytest.approx((40.0 / 3) / 1.0)
    assert sc["paper_cnbv_gnbv_step"] == pytest.approx(202.0 / 9.6)
    assert sc["global_gnbv_viewpoints"] == pytest.approx(6 / 4)
    assert sc["global_gnbv_planning"] == pytest.approx(12.0 / 4.0)
    rt = rows["round_tank"]  # no C-NBV, no global there
    assert rt["cnbv_gnbv_step"] is None and rt["global_gnbv_viewpoints"] is None
    assert rt["paper_cnbv_gnbv_step"] == pytest.approx(51.1 / 13.9)


def test_markdown_has_paper_numbers_error_rows_and_ratios(doc):
    md = report.render_markdown(doc)
    lines = md.splitlines()
    g = next(ln for ln in lines if ln.startswith("| smooth_cylinder (cat. 1) | G-NBV |"))
    cells = [c.strip() for c in g.strip("|").split("|")]
    # ours beside the paper: viewpoints, total, s/step, displacement, voxels, %
    assert cells[2:] == ["3/3", "4", "4", "4.0", "38.6", "1.00", "9.6", "20.0", "67.8", "95/100", "197/199",
                         "95.0", "99.0"]
    e = next(ln for ln in lines if ln.startswith("| smooth_cylinder (cat. 1) | E-NVP"))
    assert "error: planner 'enpv' does not import" in e and "| 0/3 |" in e and "| 61.9 |" in e
    gl = next(ln for ln in lines if ln.startswith("| smooth_cylinder (cat. 1) | global |"))
    assert "| 2/3 |" in gl and gl.count("–") == 6  # no paper column for ours
    assert "## Errors" in md and "RuntimeError: boom" in md and "Traceback" not in md
    ratio = next(ln for ln in lines if ln.startswith("| smooth_cylinder (cat. 1) | 13.3 |"))
    assert "| 21.0 | 1.50 | 3.00 |" in ratio
    assert "| round_tank (cat. 3) | G-NBV | 3/3 |" in md and "| 82/82 |" in md


def test_paper_table_is_complete():
    assert sorted(PAPER_TABLE_II) == [1, 2, 3, 4, 5, 6]
    for cat, rows in PAPER_TABLE_II.items():
        assert sorted(rows) == ["cnbv", "enpv", "gnbv"]
        for vp, total, step, disp, hit, tot, pct in rows.values():
            assert hit <= tot and abs(100 * hit / tot - pct) < 0.1, (cat, hit, tot, pct)
            assert abs(total / vp - step) < 0.06, (cat, total, vp, step)  # eq. 11 holds in the paper


def _png(path: Path, rgb) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    plt.imsave(path, np.full((20, 40, 3), rgb, dtype=np.uint8))


def test_report_from_json_alone_picks_median_seed(doc, tmp_path):
    for i, r in enumerate(doc["runs"]):
        if r["planner"] == "gnbv" or r["planner"] == "global":
            r["run_dir"] = f"runs/seed{r['seed']}/run{i}"
            _png(tmp_path / r["run_dir"] / "coverage.png", (10 * i, 0, 0))
    (tmp_path / "bench.json").write_text(json.dumps(doc))
    assert report.median_coverage_run(doc, "smooth_cylinder", "gnbv", tmp_path)["seed"] == 1
    assert report.median_coverage_run(doc, "smooth_cylinder", "global", tmp_path)["error"] is None
    assert report.median_coverage_run(doc, "smooth_cylinder", "enpv", tmp_path) is None
    from cellctl.cli import main

    assert main(["bench", "--report", str(tmp_path / "bench.json")]) == 0
    for name in ("bench.md", "coverage.png", "step_time.png", "table3_smooth_cylinder.png", "table3_round_tank.png"):
        assert (tmp_path / name).stat().st_size > 0, name


def test_load_bench_rejects_other_files(tmp_path):
    p = tmp_path / "x.json"
    p.write_text(json.dumps({"schema_version": 2, "runs": []}))
    with pytest.raises(ValueError, match="schema_version 1"):
        report.load_bench(p)


# --- the bench loop with a fake scanner ---------------------------------------------------------------

def test_parse_list():
    allowed = ("a", "b", "c")
    assert scans.parse_list(None, allowed, "x", ("b",)) == ["b"]
    assert scans.parse_list("all", allowed, "x", ("b",)) == ["a", "b", "c"]
    assert scans.parse_list("c, a,c", allowed, "x", ()) == ["c", "a"]
    with pytest.raises(ValueError, match="unknown 'd'"):
        scans.parse_list("a,d", allowed, "x", ())


def test_run_record_uses_the_papers_viewpoint_count():
    r = ScanResult(scene="s", planner="gnbv", steps=5, planning_s=8.0, displacement_m=0.5, coverage_hit=3, coverage_total=4,
                   coverage_percent=75.0, terminated_by="quality")
    rec = scans.run_record("s", 1, "gnbv", 0, r, "runs/x", 3.0, 12.0)
    assert rec["views"] == 5 and rec["viewpoints"] == 4 and rec["step_s"] == 2.0
    assert rec["coverage"] == {"hit": 3, "total": 4, "percent": 75.0}
    only_initial = scans.run_record("s", 1, "gnbv", 0, ScanResult(scene="s", planner="gnbv", steps=1, planning_s=1.0),
                                    None, 1.0, None)
    assert only_initial["viewpoints"] == 0 and only_initial["step_s"] is None


def test_bench_goes_on_after_failures(monkeypatch, tmp_path):
    """A planner that does not import, one that raises, one whose scan reports an error: all rows kept."""
    import cellctl.scan.run
    import sim.scenes
    from cellctl.config import load_cell_config

    class _Scene:
        category = 1

    def fake_job(spec, hooks=None):
        assert hooks is None and spec.noise is True and spec.profile == "scan"
        scene, planner, seed = spec.scene, spec.planner, spec.seed
        run_dir = Path(spec.out) / f"{scene}-{planner}-{seed}"
        run_dir.mkdir(parents=True)
        if planner == "global":
            raise RuntimeError("planner crashed")
        held = np.ones(20 * 2**20, dtype=np.uint8) if (planner, seed) == ("gnbv", 0) else None  # 20 MiB at peak
        del held
        r = ScanResult(scene=scene, planner=planner, steps=3, planning_s=1.5, coverage_hit=5, coverage_total=10,
                       coverage_percent=50.0, terminated_by="quality")
        if seed == 1:
            r.error, r.terminated_by = "Unreachable: nowhere to go", "error"
        return r, run_dir

    monkeypatch.setattr(cellctl.scan.run, "run_job", fake_job)
    monkeypatch.setattr(sim.scenes, "load_scene", lambda name: _Scene())
    monkeypatch.setitem(PLANNERS, "cnbv", "planners.no_such_module:Nope")
    cfg, cfg_path = load_cell_config(None)
    err = io.StringIO()
    doc = scans.run_bench(cfg, cfg_path, ["smooth_cylinder"], ["gnbv", "cnbv", "global"], 2, tmp_path, stream=err)
    runs = {(r["planner"], r["seed"]): r for r in doc["runs"]}
    assert len(runs) == 6 and doc["complete"]
    assert runs[("gnbv", 0)]["error"] is None and runs[("gnbv", 0)]["viewpoints"] == 2
    assert runs[("gnbv", 0)]["run_dir"] == "runs/seed0/smooth_cylinder-gnbv-0"
    assert 20.0 <= runs[("gnbv", 0)]["peak_memory_mb"] < 30.0  # tracemalloc saw the run's peak, not the process's
    assert runs[("gnbv", 1)]["peak_memory_mb"] < 5.0
    assert runs[("gnbv", 1)]["error"].startswith("Unreachable")
    assert "does not import" in runs[("cnbv", 0)]["error"] and runs[("cnbv", 0)]["run_dir"] is None
    assert runs[("global", 1)]["error"].startswith("RuntimeError: planner crashed")
    assert runs[("global", 1)]["run_dir"] == "runs/seed1/smooth_cylinder-global-1"  # found though it raised
    saved = json.loads((tmp_path / "bench.json").read_text())
    assert saved["runs"] == json.loads(json.dumps(doc["runs"])) and saved["process"]["max_rss_mb"] > 0
    progress = err.getvalue()
    assert "6/6" in progress and "ERROR" in progress and "ETA" in progress


# --- one real quick bench in the twin -----------------------------------------------------------------

# ~80 s on an idle 2-core machine, ~4 x that beside two busy processes: the per-test 600 s of
# pyproject.toml would make this test's verdict depend on the load; its own liveness bound is the
# subprocess timeout. --no-memory: tracemalloc makes a scan 2.7 x slower; the memory measurement is
# checked by test_bench_goes_on_after_failures.
@pytest.mark.timeout(1800)
def test_quick_bench_end_to_end(tmp_path):
    out = tmp_path / "bench"
    proc = subprocess.run([sys.executable, "-m", "cellctl.cli", "bench", "--quick", "--no-memory", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=1700)
    assert proc.returncode == 0, proc.stderr[-3000:]
    doc = json.loads((out / "bench.json").read_text())
    assert doc["schema_version"] == 1 and doc["complete"] is True
    assert {"created", "config", "machine", "code", "process", "runs"} <= set(doc)
    assert {"cell", "planners"} <= set(doc["config"]) and doc["config"]["planners"]["max_steps"] >= 1
    assert {"cpus", "python", "platform"} <= set(doc["machine"])
    keys = {"scene", "category", "planner", "seed", "views", "viewpoints", "planning_s", "step_s", "capture_s",
            "motion_s", "motion_planning_s", "displacement_m", "coverage", "terminated_by", "peak_memory_mb",
            "wall_s", "error", "run_dir", "coverage_by_view", "planning_s_by_view", "motion_contacts",
            "cut_feasible_poses"}
    got = set()
    for r in doc["runs"]:
        assert keys <= set(r), keys - set(r)
        assert r["error"] is None, (r["scene"], r["planner"], r["error"])
        c = r["coverage"]
        assert 0 <= c["percent"] <= 100 and 0 <= c["hit"] <= c["total"] and c["total"] > 0
        assert r["views"] >= 1 and r["viewpoints"] == r["views"] - 1
        assert r["planning_s"] >= 0 and r["displacement_m"] >= 0 and r["peak_memory_mb"] is None
        assert r["category"] in (1, 3)
        assert len(r["coverage_by_view"]) == len(r["planning_s_by_view"]) == r["views"]
        assert r["motion_contacts"] == 0
        assert r["coverage_by_view"][-1] == c["percent"] and sorted(r["planning_s_by_view"]) == r["planning_s_by_view"]
        assert (out / r["run_dir"] / "result.json").is_file() and (out / r["run_dir"] / "coverage.png").is_file()
        got.add((r["scene"], r["planner"], r["seed"]))
    assert got == {(s, p, 0) for s in ("smooth_cylinder", "round_tank") for p in ("gnbv", "enpv")}
    assert len(doc["runs"]) == 4
    md = (out / "bench.md").read_text()
    for paper in ("38.6", "9.6", "67.8", "197/199", "61.9", "144.6", "41.6", "13.9", "68.1", "82/82", "149.5"):
        assert f"| {paper} |" in md, paper
    for row in ("| smooth_cylinder (cat. 1) | G-NBV | 1/1 |", "| smooth_cylinder (cat. 1) | E-NVP | 1/1 |",
                "| round_tank (cat. 3) | G-NBV | 1/1 |", "| round_tank (cat. 3) | E-NVP | 1/1 |"):
        assert row in md, row
    for name in ("coverage.png", "step_time.png", "table3_smooth_cylinder.png", "table3_round_tank.png"):
        assert (out / name).stat().st_size > 1000, name


def test_equal_coverage_compares_views_and_time_to_the_same_level():
    def run(planner, seed, cov, cum):
        r = _run("smooth_cylinder", 1, planner, seed, views=len(cov), hit=round(cov[-1]), total=100)
        r["coverage_by_view"], r["planning_s_by_view"] = cov, cum
        return r
    # G-NBV ends at 99 %, global at 90 %: the level is 90 %; G-NBV passes it at viewpoint 2 (1.5 s of
    # planning before that view), global at viewpoint 6 (12 s); one global seed never gets there
    runs = [run("gnbv", s, [40, 80, 95, 99], [0.5, 1.5, 2.0, 2.5]) for s in range(3)]
    runs += [run("global", s, [30, 50, 60, 70, 80, 85, 90, 90], [2, 4, 6, 8, 10, 12, 14, 15]) for s in range(2)]
    runs.append(run("global", 2, [30, 89], [2, 4]))
    doc = _doc(runs, scenes=("smooth_cylinder",), planners=("gnbv", "global"))
    (row,) = report.equal_coverage_rows(doc)
    assert row["level"] == 90
    assert row["gnbv"] == {"reached": 3, "runs": 3, "viewpoints": 2, "planning_s": 1.5}
    assert row["global"]["reached"] == 2 and row["global"]["viewpoints"] == 6 and row["global"]["planning_s"] == 12
    assert row["viewpoints_ratio"] == 3 and row["planning_ratio"] == 8
    md = report.render_markdown(doc)
    assert "| smooth_cylinder (cat. 1) | 90.0 | 2 (3/3) | 6 (2/3) | 3.00 | 1.50 | 12.00 | 8.00 |" in md
    assert report.to_reach({"coverage_by_view": [50, 60]}, 90) == (None, None)
    assert report.to_reach({"coverage_by_view": [95], "planning_s_by_view": [1.0]}, 90) == (0, 0.0)


def test_progress_eta_per_planner():
    err = io.StringIO()
    bar = scans.Progress(["gnbv", "cnbv", None, "gnbv", "cnbv"], err)
    bar.start("a")
    assert "ETA ?" in err.getvalue()
    bar.finish("a", {"wall_s": 10.0, "error": None, "views": 3, "coverage": {"percent": 90.0}, "planning_s": 1.0})
    bar.finish("b", {"wall_s": 300.0, "error": None, "views": 3, "coverage": {"percent": 90.0}, "planning_s": 1.0})
    bar.finish("c", {"wall_s": 0.0, "error": "planner 'x' does not import", "views": 0,
                     "coverage": {"percent": 0.0}, "planning_s": 0.0})
    last = err.getvalue().splitlines()[-1]
    assert "3/5" in last and "ERROR planner 'x'" in last and "ETA 5:10" in last  # 10 s + 300 s left


def test_scoring_bench_compares_exact_and_coarse_to_fine_on_the_same_states(tmp_path):
    """`cellctl bench --scoring` on one scene: both scorings plan from the same two states; the report
    says how much faster and whether the best view changed (the figure itself is not asserted). The
    I-beam has a second view to plan under either gain; with gain_all_frontier the smooth cylinder's
    first view leaves nothing to plan in the noise-free twin."""
    r = subprocess.run([sys.executable, "-m", "cellctl.cli", "bench", "--scoring", "--scenes", "i_beam",
                        "--seeds", "1", "--out", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "scoring.json").read_text())
    assert doc["states"] == len(doc["rows"]) == 2 and [row["step"] for row in doc["rows"]] == [0, 1]
    for row in doc["rows"]:
        assert row["exact_s"] > 0 and row["coarse_to_fine_s"] > 0
        assert row["best_gain_exact"] > 0 and row["best_gain_coarse_to_fine"] > 0
        assert row["same_best_view"] == (row["best_view_offset_m"] == 0.0)
    assert "| i_beam | 1 |" in (tmp_path / "scoring.md").read_text()


def test_a_bench_tail_figure_is_a_value_that_was_measured():
    """cellctl.bench.stats.summary: nearest-rank tail percentiles (p90 of 1..10 is 9, not 9.1), the usual
    median, no sample no figure."""
    from cellctl.bench.stats import summary

    s = summary(list(range(10, 0, -1)))
    assert (s["n"], s["min"], s["median"], s["p90"], s["p99"], s["max"]) == (10, 1, 5.5, 9, 10, 10)
    assert summary([]) is None
