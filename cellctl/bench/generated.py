"""The generated-pieces bench (`cellctl bench --generated N`): per piece and over all of them, the cell's
cut beside the cut oracle's, and the cell's own report beside the truth.

Figures per piece: scan coverage; the cell's self-reported cut share (what the operator is told:
``CutPathSummary.told_share``, the line on the paint under the flame), the painted area's share
(``PaintCheck.cut_share``) and its line's own share; the true cut coverage (the true line within 5 mm of
the flame's path at every lit sample); the oracle's; the flame's largest distance from the true line and
the tip's range off the true metal over the lit motion; cuts and fragments (cuts under
``FRAGMENT_M``); gaps by reason; cut planning time. Over all pieces: the medians and 5th percentiles
the issue's targets are stated in."""

from __future__ import annotations

import numpy as np

from planners.metrics import FRAGMENT_M
ON_LINE_MM = 5.0  # the flame within this of the true line
STANDOFF_TOL_MM = 3.0  # the tip within standoff +- this of the metal


def piece_rows(doc: dict) -> list[dict]:
    """One row per generated piece's run (error rows included, their figures None)."""
    pieces, oracles = doc.get("pieces") or {}, doc.get("cut_oracles") or {}
    standoff_mm = 1e3 * (doc.get("config", {}).get("planners", {}).get("cutpath", {}).get("standoff_m") or 0.01)
    rows = []
    for r in doc["runs"]:
        meta = pieces.get(r["scene"], {})
        c = r.get("cut") or {}
        a = c.get("accuracy") or {}
        p = c.get("paint") or {}
        o = oracles.get(r["scene"]) or {}
        true = a.get("cut_coverage")
        told = p.get("line_share") if p.get("line_share") is not None else p.get("cut_share")  # older bench.json
        ocov = o.get("cut_coverage")
        lengths = c.get("cut_lengths_m") or []
        tip_lo, tip_hi = a.get("tip_to_metal_min_mm"), a.get("tip_to_metal_max_mm")
        short = sum(1 for x in lengths if x < FRAGMENT_M)
        rows.append({
            "ref": r["scene"], "family": meta.get("family"), "lines": meta.get("lines") or meta.get("line_kind"),
            "seed": r["seed"], "error": r.get("error") or c.get("error") or o.get("error"),
            "scan_percent": r["coverage"]["percent"],
            "self_share": told, "area_share": p.get("cut_share"), "own_share": c.get("fraction"),
            "true_coverage": true, "oracle_coverage": ocov,
            "ratio": None if true is None or not ocov else true / ocov,
            "flame_to_line_max_mm": a.get("path_to_line_max_mm"), "pose_to_line_max_mm": a.get("pose_to_line_max_mm"),
            "tip_to_metal_mm": None if tip_lo is None else (tip_lo, tip_hi),
            "standoff_ok": None if tip_lo is None else (abs(tip_lo - standoff_mm) <= STANDOFF_TOL_MM
                                                        and abs(tip_hi - standoff_mm) <= STANDOFF_TOL_MM),
            "self_error_points": None if true is None or told is None else 100 * (told - true),
            "unseen_borders": (c.get("unseen_paint") or {}).get("borders"),
            "off_centre_m": p.get("flame_off_centre_m"), "off_paint_m": p.get("flame_off_paint_m"),
            "cuts": c.get("cuts"), "short_cuts": short,  # an older bench.json: its fragments are its short cuts
            "fragments": a.get("fragments") if a.get("fragments") is not None else short,
            "uncut_m_by_reason": c.get("uncut_m_by_reason") or {},
            "oracle_uncut_m_by_reason": o.get("uncut_m_by_reason") or {},
            "planning_s": c.get("planning_s"), "oracle_planning_s": o.get("planning_s"),
        })
    return rows


def _pct(values, q: float) -> float | None:
    v = [x for x in values if x is not None]
    return float(np.percentile(v, q)) if v else None


def overall(rows: list[dict]) -> dict:
    """The figures the issue's targets are stated in, over the pieces with a cut measured."""
    ok = [r for r in rows if r["true_coverage"] is not None]
    ratios = [r["ratio"] for r in ok if r["ratio"] is not None]
    flame = [r["flame_to_line_max_mm"] for r in ok if r["flame_to_line_max_mm"] is not None]
    errs = [abs(r["self_error_points"]) for r in ok if r["self_error_points"] is not None]

    def share_off(r):  # None: not measured
        return None if r["self_error_points"] is None else abs(r["self_error_points"]) > 3.0

    def flame_off(r):
        return None if r["flame_to_line_max_mm"] is None else r["flame_to_line_max_mm"] > ON_LINE_MM

    def flame_warned(r):
        return (r["off_centre_m"] or 0) > 0 or (r["off_paint_m"] or 0) > 0
    return {
        "pieces": len(rows), "measured": len(ok), "errors": sum(1 for r in rows if r["error"]),
        "true_coverage_median": _pct([r["true_coverage"] for r in ok], 50),
        "oracle_coverage_median": _pct([r["oracle_coverage"] for r in ok], 50),
        "ratio_median": _pct(ratios, 50), "ratio_p5": _pct(ratios, 5),
        "flame_within_5mm": sum(1 for x in flame if x <= ON_LINE_MM), "flame_measured": len(flame),
        "flame_max_median_mm": _pct(flame, 50),
        "standoff_ok": sum(1 for r in ok if r["standoff_ok"]),
        "self_within_3_points": sum(1 for x in errs if x <= 3.0), "self_measured": len(errs),
        "self_error_max_points": max(errs) if errs else None,
        # the cell's own warnings beside where its figures are off: the paint running on unseen beside its
        # share, the flame leaving the paint or its centre beside the flame leaving the true line
        "self_off": sum(1 for r in ok if share_off(r)),
        "self_off_flagged": sum(1 for r in ok if share_off(r) and r["unseen_borders"]),
        "self_near_flagged": sum(1 for r in ok if share_off(r) is False and r["unseen_borders"]),
        "flame_warned": sum(1 for r in ok if flame_off(r) and flame_warned(r)),
        "flame_near_warned": sum(1 for r in ok if flame_off(r) is False and flame_warned(r)),
        "fragments": sum(r["fragments"] for r in ok), "pieces_with_fragments": sum(1 for r in ok if r["fragments"]),
        "short_cuts": sum(r["short_cuts"] for r in ok),
        "planning_median_s": _pct([r["planning_s"] for r in ok], 50),
        "scan_percent_median": _pct([r["scan_percent"] for r in rows], 50),
    }


def seed_spread(rows: list[dict]) -> dict[str, float]:
    """Per piece run with several seeds: the range (max - min) of its true cut coverage, in points."""
    by: dict[str, list[float]] = {}
    for r in rows:
        if r["true_coverage"] is not None:
            by.setdefault(r["ref"], []).append(100 * r["true_coverage"])
    return {ref: max(v) - min(v) for ref, v in by.items() if len(v) > 1}


def _f(x, nd: int = 1, scale: float = 1.0) -> str:
    return "–" if x is None else f"{scale * x:.{nd}f}"


def _reasons(d: dict) -> str:
    return ", ".join(f"{k} {1000 * v:.0f}" for k, v in sorted(d.items())) or "-"


def section(doc: dict) -> list[str]:
    """bench.md's "Generated pieces" section: the overall figures, then a row per piece."""
    rows = piece_rows(doc)
    if not rows:
        return []
    o = overall(rows)
    spread = seed_spread(rows)
    g = (doc.get("bench") or {}).get("generated") or {}
    L = ["## Generated pieces", "",
         f"{o['pieces']} pieces of generator seed {g.get('gen_seed')} ({o['errors']} with an error). The cell's cut is "
         "measured on the flame spot at every sample of its planned motion with the flame lit; the oracle is the "
         "same cut planner given the true paint, the true surface and the true piece as its collision scene "
         "(cellctl/bench/cut_oracle.py). Self-reported = what the operator is told: the line the paint gives, where it "
         "lies on the band's centre, within 5 mm of the flame on the band's centre (the paint no line follows counted "
         "uncut); paint area = the share of the painted area under the flame's path (the independent check); own "
         "line = the share its skeleton's length claims.", "",
         "| figure | value |", "|---|--:|",
         f"| true cut coverage, median (%) | {_f(o['true_coverage_median'], 1, 100)} |",
         f"| oracle's cut coverage, median (%) | {_f(o['oracle_coverage_median'], 1, 100)} |",
         f"| true / oracle, median | {_f(o['ratio_median'], 3)} |",
         f"| true / oracle, 5th percentile | {_f(o['ratio_p5'], 3)} |",
         f"| flame within {ON_LINE_MM:g} mm of the true line over the whole lit motion | {o['flame_within_5mm']} of "
         f"{o['flame_measured']} pieces (median of the max {_f(o['flame_max_median_mm'], 1)} mm) |",
         f"| of the others, the cell warned that the flame leaves the paint or its centre | {o['flame_warned']} of "
         f"{o['flame_measured'] - o['flame_within_5mm']} (and on {o['flame_near_warned']} within {ON_LINE_MM:g} mm) |",
         f"| tip within standoff +- {STANDOFF_TOL_MM:g} mm of the true metal, lit | {o['standoff_ok']} of {o['measured']} |",
         f"| self-reported share within 3 points of the true | {o['self_within_3_points']} of {o['self_measured']} "
         f"(worst {_f(o['self_error_max_points'], 1)} points) |",
         f"| of those off by more, the cell warned that the paint runs on unseen | {o['self_off_flagged']} of "
         f"{o['self_off']} (and on {o['self_near_flagged']} within 3) |",
         f"| fragments (cuts under {1000 * FRAGMENT_M:.0f} mm along longer paint) | {o['fragments']} on "
         f"{o['pieces_with_fragments']} pieces (cuts under {1000 * FRAGMENT_M:.0f} mm in all: {o['short_cuts']}) |",
         f"| cut planning, median (s) | {_f(o['planning_median_s'], 2)} |",
         *([f"| true cut coverage's range over the seeds, per piece: max (points) | {_f(max(spread.values()), 1)} "
            f"({sum(1 for v in spread.values() if v <= 5.0)} of {len(spread)} pieces within 5) |"] if spread else []),
         f"| scan coverage, median (%) | {_f(o['scan_percent_median'], 1)} |", "",
         "| piece | family | lines | scan (%) | self-reported (%) | paint area (%) | own line (%) | true (%) | oracle (%) | true/oracle | "
         "flame to line max (mm) | at poses (mm) | tip off metal (mm) | cuts | fragments | uncut by reason (mm) | "
         "oracle uncut (mm) | paint runs on unseen (borders) | cut planning (s) |",
         "|---|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|---|--:|--:|"]
    for r in rows:
        lines = r["lines"]
        lines = ", ".join(lines) if isinstance(lines, (list, tuple)) else (lines or "–")
        tip = "–" if r["tip_to_metal_mm"] is None else f"{r['tip_to_metal_mm'][0]:.1f}-{r['tip_to_metal_mm'][1]:.1f}"
        err = f" **error**: {str(r['error']).splitlines()[0][:80]}" if r["error"] else ""
        L.append(f"| {r['ref']} | {r['family'] or '–'} | {lines} | {_f(r['scan_percent'])} | "
                 f"{_f(r['self_share'], 1, 100)} | {_f(r['area_share'], 1, 100)} | {_f(r['own_share'], 1, 100)} | {_f(r['true_coverage'], 1, 100)} | "
                 f"{_f(r['oracle_coverage'], 1, 100)} | {_f(r['ratio'], 2)} | {_f(r['flame_to_line_max_mm'])} | "
                 f"{_f(r['pose_to_line_max_mm'])} | {tip} | {r['cuts'] if r['cuts'] is not None else '–'} | "
                 f"{r['fragments']} | {_reasons(r['uncut_m_by_reason'])} | {_reasons(r['oracle_uncut_m_by_reason'])} | "
                 f"{'–' if r['unseen_borders'] is None else r['unseen_borders']} | {_f(r['planning_s'], 2)}{err} |")
    L.append("")
    return L
