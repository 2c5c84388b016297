"""The bench report, regenerable from bench.json alone: bench.md (our medians beside the paper's
Table II, a ratio table, every run), coverage.png, step_time.png and table3_<scene>.png.

Aggregation: per (scene, planner), the median over the seeds whose run has no error; errored runs
are counted in the "runs ok" column and listed, never averaged in.
"""

from __future__ import annotations

import json
import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path

# Source: the paper in /work/shared/reference/feature-driven-nvp-paper.txt, TABLE II "Simulation
# Results: Evaluating Benchmarking Metrics for each NVP Algorithm on all Object Categories".
# category -> planner -> (viewpoints, total duration s, avg. step duration s/step, total displacement cm,
# coverage hit voxels, coverage total voxels, coverage %). Numbers exactly as printed.
# Paper note: E-NVP backtracks to the initial point after finding the first endpoint and counts
# that revisited viewpoint as a step.
PAPER_TABLE_II: dict[int, dict[str, tuple]] = {
    1: {"enpv": (9, 61.9, 6.9, 144.6, 197, 199, 99.0),
        "cnbv": (4, 808.0, 202.0, 48.5, 197, 199, 99.0),
        "gnbv": (4, 38.6, 9.6, 67.8, 197, 199, 99.0)},
    2: {"enpv": (8, 43.4, 5.4, 88.3, 372, 569, 65.4),
        "cnbv": (4, 417.5, 104.4, 87.7, 569, 569, 100),
        "gnbv": (3, 43.4, 14.5, 66.0, 568, 569, 99.8)},
    3: {"enpv": (6, 30.1, 5.0, 149.5, 82, 82, 100),
        "cnbv": (3, 153.3, 51.1, 81.8, 82, 82, 100),
        "gnbv": (3, 41.6, 13.9, 68.1, 82, 82, 100)},
    4: {"enpv": (4, 18.0, 4.5, 81.7, 179, 182, 98.4),
        "cnbv": (4, 463.5, 115.9, 88.7, 179, 182, 98.4),
        "gnbv": (3, 47.0, 15.7, 53.7, 177, 182, 97.25)},
    5: {"enpv": (6, 29.0, 4.8, 90.0, 234, 532, 44.0),
        "cnbv": (5, 549.0, 109.8, 108.4, 525, 532, 98.7),
        "gnbv": (3, 56.4, 18.8, 10.5, 501, 532, 94.2)},
    6: {"enpv": (8, 46.0, 5.7, 94.1, 153, 155, 98.7),
        "cnbv": (2, 187.7, 93.8, 11.82, 130, 155, 83.9),
        "gnbv": (2, 50.6, 25.3, 23.9, 145, 155, 93.5)},
}
PAPER_CATEGORY_NAMES = {1: "Smooth Cylinder", 2: "Sharp Cylinder", 3: "Round Tank", 4: "T-Piece", 5: "I-Beam",
                        6: "Basket"}
PLANNER_LABELS = {"enpv": "E-NVP", "cnbv": "C-NBV", "gnbv": "G-NBV", "global": "global"}
PLANNER_COLORS = {"enpv": "tab:orange", "cnbv": "tab:blue", "gnbv": "tab:green", "global": "tab:purple"}
NA = "–"


@dataclass
class Agg:
    """Medians over the error-free seeds of one (scene, planner)."""

    scene: str
    category: int | None
    planner: str
    n: int = 0
    n_ok: int = 0
    viewpoints: float | None = None
    views: float | None = None
    planning_s: float | None = None
    step_s: float | None = None
    displacement_cm: float | None = None
    hit: float | None = None
    total: float | None = None
    percent: float | None = None
    percent_min: float | None = None
    percent_max: float | None = None
    step_s_min: float | None = None
    step_s_max: float | None = None
    peak_memory_mb: float | None = None
    errors: list[str] = field(default_factory=list)


def load_bench(path: str | Path) -> dict:
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{p}: cannot read bench.json: {e}") from None
    if not isinstance(doc, dict) or doc.get("schema_version") != 1 or not isinstance(doc.get("runs"), list):
        raise ValueError(f"{p}: not a schema_version 1 bench.json")
    return doc


def _median(values: list) -> float | None:
    vals = [v for v in values if v is not None]
    return float(statistics.median(vals)) if vals else None


def _order(doc: dict, key: str) -> list[str]:
    """Scenes or planners in bench order, then any only present in the runs."""
    listed = list(doc.get("bench", {}).get(key, []))
    field_ = key[:-1]
    return listed + [x for x in dict.fromkeys(r[field_] for r in doc["runs"]) if x not in listed]


def aggregate(doc: dict) -> dict[tuple[str, str], Agg]:
    out: dict[tuple[str, str], Agg] = {}
    for scene in _order(doc, "scenes"):
        for planner in _order(doc, "planners"):
            runs = [r for r in doc["runs"] if r["scene"] == scene and r["planner"] == planner]
            if not runs:
                continue
            ok = [r for r in runs if not r.get("error")]
            a = Agg(scene, runs[0].get("category"), planner, n=len(runs), n_ok=len(ok),
                    errors=[r["error"] for r in runs if r.get("error")])
            if ok:
                pct = [r["coverage"]["percent"] for r in ok]
                steps = [r["step_s"] for r in ok if r["step_s"] is not None]
                a.viewpoints = _median([r["viewpoints"] for r in ok])
                a.views = _median([r["views"] for r in ok])
                a.planning_s = _median([r["planning_s"] for r in ok])
                a.step_s = _median(steps)
                a.step_s_min, a.step_s_max = (min(steps), max(steps)) if steps else (None, None)
                a.displacement_cm = _median([100.0 * r["displacement_m"] for r in ok])
                a.hit = _median([r["coverage"]["hit"] for r in ok])
                a.total = _median([r["coverage"]["total"] for r in ok])
                a.percent = _median(pct)
                a.percent_min, a.percent_max = min(pct), max(pct)
                a.peak_memory_mb = _median([r.get("peak_memory_mb") for r in ok])
            out[(scene, planner)] = a
    return out


def _ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None or den <= 0:
        return None
    return num / den


def ratio_rows(doc: dict, aggs: dict[tuple[str, str], Agg] | None = None) -> list[dict]:
    """Per scene, ratios of medians measured in this bench: C-NBV/G-NBV planning time per step (with
    the paper's), global/G-NBV viewpoints and total planning time."""
    aggs = aggregate(doc) if aggs is None else aggs
    rows = []
    for scene in _order(doc, "scenes"):
        g, c, gl = (aggs.get((scene, p)) for p in ("gnbv", "cnbv", "global"))
        cat = next((a.category for a in (g, c, gl) if a is not None), None)
        paper = PAPER_TABLE_II.get(cat)
        rows.append({
            "scene": scene, "category": cat,
            "cnbv_gnbv_step": _ratio(c and c.step_s, g and g.step_s),
            "paper_cnbv_gnbv_step": paper["cnbv"][2] / paper["gnbv"][2] if paper else None,
            "global_gnbv_viewpoints": _ratio(gl and gl.viewpoints, g and g.viewpoints),
            "global_gnbv_planning": _ratio(gl and gl.planning_s, g and g.planning_s),
        })
    return rows


def to_reach(run: dict, level: float) -> tuple[int | None, float | None]:
    """(viewpoints, planning s) a run needed before its drawing coverage first reached `level` %, or
    (None, None) if it never did. The initial view is viewpoint 0 and needs no planning."""
    cov = run.get("coverage_by_view") or []
    t = run.get("planning_s_by_view") or []
    for i, c in enumerate(cov):
        if c is not None and c >= level - 1e-9:
            return i, (t[i - 1] if i > 0 and i - 1 < len(t) else 0.0)
    return None, None


def equal_coverage_rows(doc: dict, aggs: dict[tuple[str, str], Agg] | None = None,
                        baseline: str = "global") -> list[dict]:
    """Per scene, what G-NBV and the baseline needed to reach the same drawing coverage: the lower of
    their two median final coverages. Medians over the runs that reached it."""
    aggs = aggregate(doc) if aggs is None else aggs
    rows = []
    for scene in _order(doc, "scenes"):
        g, b = aggs.get((scene, "gnbv")), aggs.get((scene, baseline))
        if g is None or b is None or g.percent is None or b.percent is None:
            continue
        level = min(g.percent, b.percent)
        row = {"scene": scene, "category": g.category, "level": level}
        for name in ("gnbv", baseline):
            runs = [r for r in doc["runs"] if r["scene"] == scene and r["planner"] == name and not r.get("error")]
            reached = [to_reach(r, level) for r in runs]
            ok = [x for x in reached if x[0] is not None]
            row[name] = {"reached": len(ok), "runs": len(runs), "viewpoints": _median([x[0] for x in ok]),
                         "planning_s": _median([x[1] for x in ok])}
        gv, bv = row["gnbv"], row[baseline]
        row["viewpoints_ratio"] = _ratio(bv["viewpoints"], gv["viewpoints"])
        row["planning_ratio"] = _ratio(bv["planning_s"], gv["planning_s"])
        rows.append(row)
    return rows


# --- markdown ---------------------------------------------------------------------------------------

def _num(v: float | None, digits: int = 1) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return NA
    return f"{v:.{digits}f}"


def _count(v: float | None) -> str:
    """A count, or the median of an even number of counts (x.5)."""
    if v is None:
        return NA
    return str(int(v)) if float(v).is_integer() else f"{v:.1f}"


def _paper(v) -> str:
    """A paper number exactly as the paper prints it."""
    return NA if v is None else repr(v)


def _first_line(err: str, n: int = 120) -> str:
    line = err.strip().splitlines()[0] if err.strip() else "error"
    line = line.replace("|", "\\|")
    return line if len(line) <= n else line[: n - 1] + "…"


def _scene_label(scene: str, cat: int | None) -> str:
    return f"{scene} (cat. {cat})" if cat else scene


def render_markdown(doc: dict) -> str:
    aggs = aggregate(doc)
    b = doc.get("bench", {})
    m = doc.get("machine", {})
    code = doc.get("code", {})
    proc = doc.get("process", {})
    seeds = b.get("seeds", [])
    L = ["# Benchmark: our planners beside the paper's Table II", ""]
    L.append(f"- created {doc.get('created', '?')}; {'complete' if doc.get('complete') else 'INCOMPLETE (interrupted)'}; "
             f"{len(doc['runs'])} runs, {sum(1 for r in doc['runs'] if r.get('error'))} with an error")
    L.append(f"- scenes: {', '.join(b.get('scenes', []))}; planners: {', '.join(b.get('planners', []))}; "
             f"seeds (sensor noise): {', '.join(map(str, seeds))}{' (--quick)' if b.get('quick') else ''}")
    L.append(f"- machine: {m.get('cpus', '?')} CPUs, Python {m.get('python', '?')}, {m.get('platform', '?')}")
    if code.get("git_commit"):
        L.append(f"- code: {code['git_commit'][:12]}{' + uncommitted changes' if code.get('dirty') else ''}")
    if proc:
        L.append(f"- bench wall time {_num(proc.get('wall_s'), 0)} s; process max RSS {_num(proc.get('max_rss_mb'), 0)} MiB")
    if b.get("generated"):
        from cellctl.bench.generated import section

        L += [""] + section(doc)
    L += ["", "## Table II, ours beside the paper", "",
          "Ours: median over the seeds without error (\"runs ok\"); paper: Table II (simulation). "
          "Viewpoints exclude the initial view (§VI-C.1); total = planning time Δt (eq. 10); "
          "s/step = Δt / viewpoints (eq. 11); displacement between captured views incl. the initial one (eq. 12); "
          "coverage of the ground-truth drawing voxels (eq. 13). Our scenes are analogs of the paper's categories, "
          "not its scanned objects, and the computers differ: compare trends and ratios, not absolute values.", ""]
    head = ["category (scene)", "planner", "runs ok", "viewpoints", "paper", "total (s)", "paper", "s/step", "paper",
            "displacement (cm)", "paper", "coverage (voxels)", "paper", "coverage (%)", "paper"]
    L.append("| " + " | ".join(head) + " |")
    L.append("|" + "|".join(["---"] * 2 + ["--:"] * (len(head) - 2)) + "|")
    for (scene, planner), a in aggs.items():
        p = PAPER_TABLE_II.get(a.category, {}).get(planner)
        pp = [_paper(x) for x in p] if p else [NA] * 7
        label = PLANNER_LABELS.get(planner, planner)
        if a.n_ok == 0:
            ours = [NA] * 6
            label += f" — error: {_first_line(a.errors[0], 80)}"
        else:
            ours = [_count(a.viewpoints), _num(a.planning_s, 1), _num(a.step_s, 2), _num(a.displacement_cm, 1),
                    f"{_count(a.hit)}/{_count(a.total)}", _num(a.percent, 1)]
        cov_p = f"{pp[4]}/{pp[5]}" if p else NA
        row = [_scene_label(scene, a.category), label, f"{a.n_ok}/{a.n}",
               ours[0], pp[0], ours[1], pp[1], ours[2], pp[2], ours[3], pp[3], ours[4], cov_p, ours[5], pp[6]]
        L.append("| " + " | ".join(row) + " |")
    L += ["", "Paper note: its E-NVP backtracks to the initial point after finding the first endpoint and counts "
          "that revisited viewpoint as a step. Our `global` planner has no paper column.", ""]

    L += ["## Ratios measured in this bench", "",
          "Ratios of the medians above, all from this one bench (same machine, same load).", "",
          "| category (scene) | C-NBV / G-NBV s/step | paper | global / G-NBV viewpoints | global / G-NBV total planning time |",
          "|---|--:|--:|--:|--:|"]
    rr = ratio_rows(doc, aggs)
    for r in rr:
        L.append(f"| {_scene_label(r['scene'], r['category'])} | {_num(r['cnbv_gnbv_step'], 1)} | "
                 f"{_num(r['paper_cnbv_gnbv_step'], 1)} | {_num(r['global_gnbv_viewpoints'], 2)} | "
                 f"{_num(r['global_gnbv_planning'], 2)} |")
    if len(rr) > 1:
        def med(k):
            return _median([r[k] for r in rr])
        L.append(f"| median over scenes | {_num(med('cnbv_gnbv_step'), 1)} | {_num(med('paper_cnbv_gnbv_step'), 1)} | "
                 f"{_num(med('global_gnbv_viewpoints'), 2)} | {_num(med('global_gnbv_planning'), 2)} |")
    L.append("")

    eq = equal_coverage_rows(doc, aggs)
    if eq:
        L += ["## Feature guidance at equal coverage", "",
              "What G-NBV and the feature-agnostic `global` planner needed to reach the same drawing coverage: the "
              "lower of their two median final coverages (from each run's coverage after every view). Viewpoints "
              "exclude the initial view; planning time is eq. 10 up to that view. Medians over the runs that "
              "reached the level (reached/runs).", "",
              "| category (scene) | coverage level (%) | G-NBV viewpoints | global viewpoints | ratio | "
              "G-NBV planning (s) | global planning (s) | ratio |", "|---|--:|--:|--:|--:|--:|--:|--:|"]
        for r in eq:
            g, b = r["gnbv"], r["global"]
            L.append(f"| {_scene_label(r['scene'], r['category'])} | {_num(r['level'], 1)} | "
                     f"{_count(g['viewpoints'])} ({g['reached']}/{g['runs']}) | {_count(b['viewpoints'])} "
                     f"({b['reached']}/{b['runs']}) | {_num(r['viewpoints_ratio'], 2)} | {_num(g['planning_s'], 2)} | "
                     f"{_num(b['planning_s'], 2)} | {_num(r['planning_ratio'], 2)} |")
        if len(eq) > 1:
            L.append(f"| median over scenes | | | | {_num(_median([r['viewpoints_ratio'] for r in eq]), 2)} | | | "
                     f"{_num(_median([r['planning_ratio'] for r in eq]), 2)} |")
        L.append("")

    errs = [r for r in doc["runs"] if r.get("error")]
    if errs:
        L += ["## Errors", "", "| scene | planner | seed | error |", "|---|---|--:|---|"]
        for r in errs:
            L.append(f"| {r['scene']} | {r['planner']} | {r['seed']} | {_first_line(r['error'], 200)} |")
        L.append("")

    cut_runs = [r for r in doc["runs"] if r.get("cut")]
    if cut_runs:
        L += ["## The cut", "",
              "What each scan hands to the torch (planners/cutpath: ladder graph within the torch's tilt tolerances, "
              "split into runs where the arm cannot go on), measured against the scene's true centerline: cut coverage "
              "= share of the true line within 5 mm of a cuttable cut; path to line = distance of the cuts from the "
              "line (gaps excluded); line to path max includes the gaps.", "",
              "| scene | planner | seed | cut (% of drawing) | cut coverage (%) | path to line mean / max (mm) | "
              "line to path max (mm) | cuts / strokes | uncut by reason (mm) | planning (s) | dry-run contacts | "
              "tip error max (mm) |",
              "|---|---|--:|--:|--:|--:|--:|--:|---|--:|--:|--:|"]
        for r in cut_runs:
            c, a = r["cut"], r["cut"].get("accuracy") or {}
            uncut = ", ".join(f"{k} {1000 * v:.0f}" for k, v in sorted(c["uncut_m_by_reason"].items())) or "-"
            cov = a.get("cut_coverage")
            L.append(f"| {r['scene']} | {r['planner']} | {r['seed']} | {_num(100 * (c['fraction'] or 0.0), 1)} | "
                     f"{_num(None if cov is None else 100 * cov, 1)} | {_num(a.get('path_to_line_mean_mm'), 2)} / "
                     f"{_num(a.get('path_to_line_max_mm'), 2)} | {_num(a.get('line_to_path_max_mm'), 1)} | "
                     f"{c['cuts']} / {a.get('strokes', NA)} | {uncut} | {_num(c['planning_s'], 2)} | "
                     f"{_count(c.get('dry_run_contacts'))} | {_num(c.get('dry_run_tip_error_max_mm'), 3)} |")
        L.append("")

    L += ["## Every run", "",
          "views = captured views incl. the initial one; peak mem = tracemalloc peak during the run above what was "
          "traced at its start (Python and numpy allocations only).", "",
          "| scene | planner | seed | views | viewpoints | planning (s) | s/step | capture (s) | motion planning (s) | "
          "motion (s) | displacement (cm) | coverage | % | terminated by | peak mem (MiB) | wall (s) | run folder |",
          "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|--:|--:|---|"]
    for r in doc["runs"]:
        c = r["coverage"]
        L.append(f"| {r['scene']} | {r['planner']} | {r['seed']} | {r['views']} | {r['viewpoints']} | "
                 f"{_num(r['planning_s'], 2)} | {_num(r['step_s'], 2)} | {_num(r['capture_s'], 2)} | "
                 f"{_num(r['motion_planning_s'], 2)} | {_num(r['motion_s'], 1)} | {_num(100 * r['displacement_m'], 1)} | "
                 f"{c['hit']}/{c['total']} | {_num(c['percent'], 1)} | {r['terminated_by'] or NA} | "
                 f"{_num(r.get('peak_memory_mb'), 0)} | {_num(r['wall_s'], 1)} | {r['run_dir'] or NA} |")
    L.append("")
    L += ["## Figures", "", "![coverage](coverage.png)", "", "![planning time per step](step_time.png)", ""]
    for scene in ([] if b.get("generated") else _order(doc, "scenes")):
        L += [f"![{scene}](table3_{scene}.png)", ""]
    return "\n".join(L)


# --- plots ------------------------------------------------------------------------------------------

def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grouped(doc: dict, aggs, path: Path, value, lo, hi, paper_idx: int, ylabel: str, title: str, log: bool) -> None:
    import numpy as np

    plt = _plt()
    scenes, planners = _order(doc, "scenes"), _order(doc, "planners")
    x = np.arange(len(scenes))
    w = 0.8 / max(len(planners), 1)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(scenes) + 2), 4.2))
    paper_labelled = False
    for i, p in enumerate(planners):
        xs = x - 0.4 + w * (i + 0.5)
        for j, s in enumerate(scenes):
            a = aggs.get((s, p))
            if a is None:
                continue
            v = value(a)
            if v is None or (log and v <= 0):
                ax.text(xs[j], 0.02, "error" if a.n_ok == 0 else "n/a", rotation=90, ha="center", va="bottom",
                        fontsize=7, color="0.3", transform=ax.get_xaxis_transform())
                continue
            ax.bar(xs[j], v, w * 0.9, color=PLANNER_COLORS.get(p, "0.5"), label=PLANNER_LABELS.get(p, p))
            lo_v, hi_v = lo(a), hi(a)
            if lo_v is not None and hi_v is not None:
                ax.errorbar(xs[j], v, yerr=[[v - lo_v], [hi_v - v]], fmt="none", ecolor="k", capsize=3, lw=1)
            pr = PAPER_TABLE_II.get(a.category, {}).get(p)
            if pr is not None:
                ax.plot(xs[j], pr[paper_idx], marker="D", ms=5, mfc="white", mec="k", ls="none",
                        label=None if paper_labelled else "paper (Table II)")
                paper_labelled = True
    ax.set_xticks(x)
    ax.set_xticklabels([f"{s}\ncat. {aggs_cat(aggs, s)}" if aggs_cat(aggs, s) else s for s in scenes], fontsize=8)
    if log:
        ax.set_yscale("log")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    handles, labels = ax.get_legend_handles_labels()
    seen = {}
    for h, lab in zip(handles, labels):
        if lab and lab not in seen:
            seen[lab] = h
    if seen:
        ax.legend(seen.values(), seen.keys(), fontsize=8, loc="best")
    ax.grid(axis="y", alpha=0.3, which="both" if log else "major")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def aggs_cat(aggs, scene: str) -> int | None:
    return next((a.category for (s, _), a in aggs.items() if s == scene), None)


def coverage_plot(doc: dict, path: Path, aggs=None) -> None:
    aggs = aggregate(doc) if aggs is None else aggs
    _grouped(doc, aggs, path, lambda a: a.percent, lambda a: a.percent_min, lambda a: a.percent_max, 6,
             "coverage (%)  [eq. 13]", "Coverage per category: median over seeds, whiskers min-max", log=False)


def step_time_plot(doc: dict, path: Path, aggs=None) -> None:
    aggs = aggregate(doc) if aggs is None else aggs
    _grouped(doc, aggs, path, lambda a: a.step_s, lambda a: a.step_s_min, lambda a: a.step_s_max, 2,
             "planning time per step (s, log)  [eq. 11]",
             "Planning time per step: median over seeds, whiskers min-max", log=True)


def median_coverage_run(doc: dict, scene: str, planner: str, base: Path) -> dict | None:
    """The run whose coverage is the (lower) median over the seeds, among runs that have a picture;
    error-free runs first."""
    runs = [r for r in doc["runs"] if r["scene"] == scene and r["planner"] == planner and r.get("run_dir")
            and (base / r["run_dir"] / "coverage.png").is_file()]
    ok = [r for r in runs if not r.get("error")] or runs
    if not ok:
        return None
    ok.sort(key=lambda r: (r["coverage"]["percent"], r["seed"]))
    return ok[(len(ok) - 1) // 2]


def table3_figure(doc: dict, scene: str, base: Path, path: Path) -> None:
    """The paper's Table III for one scene: a row per planner, the run folder's coverage.png (three
    views of viewpoints and covered/missed ground-truth voxels) of its median-coverage seed."""
    plt = _plt()
    planners = [p for p in _order(doc, "planners") if any(r["scene"] == scene and r["planner"] == p
                                                           for r in doc["runs"])]
    n = max(len(planners), 1)
    fig, axes = plt.subplots(n, 1, figsize=(12, 4.3 * n), squeeze=False)
    for ax, p in zip(axes[:, 0], planners):
        ax.set_axis_off()
        r = median_coverage_run(doc, scene, p, base)
        label = PLANNER_LABELS.get(p, p)
        if r is None:
            errs = [x["error"] for x in doc["runs"] if x["scene"] == scene and x["planner"] == p and x.get("error")]
            msg = _first_line(errs[0], 110) if errs else "no picture"
            ax.text(0.5, 0.5, f"{label}: {msg}", ha="center", va="center", fontsize=10, wrap=True,
                    transform=ax.transAxes)
            continue
        ax.imshow(plt.imread(base / r["run_dir"] / "coverage.png"))
        c = r["coverage"]
        ax.set_title(f"{label}, seed {r['seed']} (median coverage): {r['viewpoints']} viewpoints ({r['views']} views), "
                     f"{100 * r['displacement_m']:.1f} cm, {c['hit']}/{c['total']} = {c['percent']:.1f} %"
                     + ("  [ERROR]" if r.get("error") else ""), fontsize=11, loc="left")
    if not planners:
        axes[0, 0].set_axis_off()
    fig.suptitle(f"{scene}: viewpoints (magenta), covered (green) and missed (red) ground-truth voxels", fontsize=12)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_report(doc: dict, out_dir: str | Path) -> list[Path]:
    """bench.md and the PNGs next to bench.json; run folders resolve against out_dir."""
    out = Path(out_dir)
    aggs = aggregate(doc)
    written = [out / "bench.md", out / "coverage.png", out / "step_time.png"]
    (out / "bench.md").write_text(render_markdown(doc))
    coverage_plot(doc, out / "coverage.png", aggs)
    step_time_plot(doc, out / "step_time.png", aggs)
    for scene in ([] if (doc.get("bench") or {}).get("generated") else _order(doc, "scenes")):  # a hundred pieces: no
        p = out / f"table3_{scene}.png"
        table3_figure(doc, scene, out, p)
        written.append(p)
    return written
