"""The cut measured against the paint the cell saw (planners.cutpath.paint_report), the flame along the
whole motion, and the generated-pieces report (cellctl.bench.generated)."""

import numpy as np
import pytest

from cellctl.bench.generated import FRAGMENT_M, overall, piece_rows, section
from planners.cutpath.model import Gap
from planners.cutpath.paint_report import NOT_IN_CUT, FlamePath, flame_path, paint_report

VOXEL = 0.002
HALF = 0.01  # a 20 mm spray


def _band(polyline: np.ndarray, half: float = HALF, voxel: float = VOXEL) -> np.ndarray:
    """The paint of a line sprayed on the plane z = 0: every voxel centre within ``half`` of the polyline."""
    lo, hi = polyline[:, :2].min(axis=0) - half - voxel, polyline[:, :2].max(axis=0) + half + voxel
    g = np.stack(np.meshgrid(*(np.arange(a, b, voxel) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 2)
    a, b = polyline[:-1, :2], polyline[1:, :2]
    ab = b - a
    t = np.clip(np.einsum("nkj,kj->nk", g[:, None] - a[None], ab) / np.einsum("kj,kj->k", ab, ab), 0, 1)
    d = np.linalg.norm(g[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(axis=1)
    pts = g[d <= half]
    return np.column_stack([pts, np.zeros(len(pts))])


def _flame(spots: np.ndarray, standoff: float = 0.01) -> FlamePath:
    axes = np.tile([0.0, 0.0, -1.0], (len(spots), 1))
    return FlamePath(spots - standoff * axes, axes, spots)


def _line(a, b, step=0.0005):
    n = int(np.linalg.norm(np.subtract(b, a)) / step) + 1
    return np.linspace(a, b, n)


def _report(paint, flames, gaps=None):
    normals = np.tile([0.0, 0.0, 1.0], (len(paint), 1))
    return paint_report(paint, normals, VOXEL, HALF, 0.005, flames, paint, gaps)


def test_a_cut_along_the_whole_line_covers_its_paint_and_measures_its_length():
    line = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    paint = _band(line)
    rep = _report(paint, [_flame(_line(line[0], line[1]))])
    assert rep.cut_share >= 0.99 and rep.uncut == []
    assert rep.line_length_m == pytest.approx(0.3, rel=0.1)
    assert rep.flame_off_paint_max_mm <= VOXEL * 1e3 and rep.flame_off_paint_m == 0.0  # within a cell of a paint point
    assert rep.tip_to_surface_min_mm == pytest.approx(10.0, abs=0.5)


def test_paint_past_a_cut_s_end_is_uncut_beyond_the_tolerance_and_a_gap_names_why():
    line = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    paint = _band(line)
    rep = _report(paint, [_flame(_line([0.0, 0.0, 0.0], [0.15, 0.0, 0.0]))])
    # half the line's paint, plus the tolerance past the cut's end (not half a spray width more)
    assert rep.cut_share == pytest.approx((0.15 + 0.005 + HALF) / (0.3 + 2 * HALF), abs=0.04)
    assert len(rep.uncut) == 1 and rep.uncut[0].reason == NOT_IN_CUT
    assert rep.uncut[0].length_m == pytest.approx(0.14, rel=0.15)
    gap = Gap(0, np.array([0.15, 0, 0]), np.array([0.3, 0, 0]), 0.15, "collision", "the piece is in the way",
              _line([0.16, 0, 0], [0.3, 0, 0], 0.005))
    rep = _report(paint, [_flame(_line([0.0, 0.0, 0.0], [0.15, 0.0, 0.0]))], [gap])
    assert rep.uncut[0].reason == "collision" and rep.uncut[0].detail == "the piece is in the way"


def test_a_chord_across_a_sharp_tip_leaves_its_paint_uncut():
    """A zigzag's 20-degree tip: the arms' paint near the tip is beside a chord, farther out it is not."""
    half_angle = np.radians(10)
    tip = np.array([0.2, 0.0, 0.0])
    arm = 0.15 * np.array([-np.cos(half_angle), np.sin(half_angle), 0])
    vee = np.array([tip + arm, tip, tip + arm * [1, -1, 1]])
    paint = _band(vee)
    whole = _report(paint, [_flame(np.vstack([_line(vee[0], vee[1]), _line(vee[1], vee[2])]))])
    assert whole.cut_share >= 0.98
    # the cut turns back 8 cm before the tip, where the arms are 28 mm apart
    turn = tip + 0.08 * np.array([-1, 0, 0])
    short = _report(paint, [_flame(np.vstack([_line(vee[0], turn), _line(turn, vee[2])]))])
    assert short.cut_share < whole.cut_share - 0.05
    assert short.uncut and short.uncut[0].reason == NOT_IN_CUT


def test_a_flame_that_swings_off_the_line_is_measured_off_the_paint():
    line = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    paint = _band(line)
    swing = np.vstack([_line([0.0, 0.0, 0.0], [0.1, 0.0, 0.0]), _line([0.1, 0.0, 0.0], [0.1, 0.045, 0.0]),
                       _line([0.1, 0.045, 0.0], [0.1, 0.0, 0.0]), _line([0.1, 0.0, 0.0], [0.3, 0.0, 0.0])])
    rep = _report(paint, [_flame(swing)])
    assert rep.flame_off_paint_max_mm == pytest.approx(35.0, abs=1.5)
    assert rep.flame_off_paint_m == pytest.approx(2 * 0.03, abs=0.006)


def test_a_flame_inside_the_paint_but_beside_its_centre_is_told_off_the_line():
    """A cut 8 mm beside the centre of a 20 mm band: never off the paint (the band reaches 10 mm), but
    off the line; the paint it passes is not counted cut. On the centre: within a cell of it."""
    line = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    paint = _band(line)
    on = _report(paint, [_flame(_line([0.0, 0.0, 0.0], [0.3, 0.0, 0.0]))])
    assert on.flame_off_centre_max_mm <= 1e3 * VOXEL and on.flame_off_centre_m == 0.0 and on.cut_share >= 0.99
    beside = _report(paint, [_flame(_line([0.0, 0.008, 0.0], [0.3, 0.008, 0.0]))])
    assert beside.flame_off_paint_m == 0.0, "the flame never leaves the paint"
    assert beside.flame_off_centre_max_mm == pytest.approx(8.0, abs=1.5)
    assert beside.flame_off_centre_m >= 0.25 and beside.cut_share < 0.2
    # half of it on the centre, half beside: half the paint is cut
    half = _report(paint, [_flame(np.vstack([_line([0.0, 0.0, 0.0], [0.15, 0.0, 0.0]),
                                             _line([0.15, 0.008, 0.0], [0.3, 0.008, 0.0])]))])
    assert half.cut_share == pytest.approx(0.5, abs=0.08)
    # a zigzag's sharp tip: the slab across the spot holds both arms, the centre is not measured there,
    # and at the apex, where the band rounds off, a blip shorter than half its width is no stretch off the line
    vee = np.array([[0.05, 0.026, 0.0], [0.2, 0.0, 0.0], [0.05, -0.026, 0.0]])
    tip = _report(_band(vee), [_flame(np.vstack([_line(vee[0], vee[1]), _line(vee[1], vee[2])]))])
    assert tip.flame_off_centre_m == 0.0 and tip.cut_share >= 0.95


def test_no_paint_is_an_error():
    with pytest.raises(ValueError, match="no paint"):
        paint_report(np.zeros((0, 3)), np.zeros((0, 3)), VOXEL, HALF, 0.005, [])


def test_the_flame_spot_is_the_standoff_ahead_of_the_torch_tip():
    from configs.panda import PANDA_URDF
    from planners.cutpath import torch_kinematics
    from planners.motion.limits import PANDA_Q_READY

    kin = torch_kinematics(str(PANDA_URDF))
    Q = PANDA_Q_READY + np.linspace(0.0, 0.3, 5)[:, None]
    f = flame_path(kin, Q, 0.01)
    for k, q in enumerate(Q):
        T = kin.fk(q)
        assert np.allclose(f.tips[k], T[:3, 3]) and np.allclose(f.spots[k], T[:3, 3] + 0.01 * T[:3, 2])
    assert flame_path(kin, np.zeros((0, 7)), 0.01).spots.shape == (0, 3)


def _doc():
    def run(ref, cov, share, own, flame, tips, lengths, err=None):
        return {"scene": ref, "seed": 0, "error": err, "coverage": {"percent": 99.0},
                "cut": None if err else {"fraction": own, "cuts": len(lengths), "cut_lengths_m": lengths,
                                         "planning_s": 1.0, "uncut_m_by_reason": {"collision": 0.02},
                                         "paint": {"cut_share": share},
                                         "accuracy": {"cut_coverage": cov, "path_to_line_max_mm": flame,
                                                      "pose_to_line_max_mm": 2.0, "tip_to_metal_min_mm": tips[0],
                                                      "tip_to_metal_max_mm": tips[1]}}}
    return {"bench": {"generated": {"n": 3, "gen_seed": 4}},
            "config": {"planners": {"cutpath": {"standoff_m": 0.01}}},
            "pieces": {"scrap:4:0": {"family": "plate", "lines": ["zigzag"]}},
            "cut_oracles": {"scrap:4:0": {"cut_coverage": 0.9}, "scrap:4:1": {"cut_coverage": 0.8},
                            "scrap:4:2": {"error": "ValueError: x"}},
            "runs": [run("scrap:4:0", 0.81, 0.83, 1.0, 14.0, (6.0, 22.0), [0.3, 0.01]),
                     run("scrap:4:1", 0.8, 0.79, 0.8, 3.0, (9.0, 11.0), [0.5]),
                     run("scrap:4:2", None, None, None, None, None, [], err="boom")]}


def test_the_generated_report_sets_the_cell_beside_the_oracle_and_the_truth():
    rows = piece_rows(_doc())
    assert rows[0]["ratio"] == pytest.approx(0.9) and rows[1]["ratio"] == pytest.approx(1.0)
    assert rows[0]["fragments"] == 1 and 0.01 < FRAGMENT_M and rows[1]["fragments"] == 0
    assert rows[0]["standoff_ok"] is False and rows[1]["standoff_ok"] is True
    assert rows[0]["self_error_points"] == pytest.approx(2.0) and rows[2]["error"] == "boom"
    o = overall(rows)
    assert o["measured"] == 2 and o["errors"] == 1 and o["flame_within_5mm"] == 1 and o["standoff_ok"] == 1
    assert o["self_within_3_points"] == 2 and o["pieces_with_fragments"] == 1
    md = "\n".join(section(_doc()))
    assert "| scrap:4:0 | plate | zigzag |" in md and "**error**: boom" in md
    # a share off by more than 3 points, and whether the cell warned that its paint runs on unseen
    doc = _doc()
    doc["runs"][1]["cut"]["paint"]["cut_share"] = 0.95
    doc["runs"][1]["cut"]["unseen_paint"] = {"borders": 2, "border_m": 0.04}
    o = overall(piece_rows(doc))
    assert o["self_off"] == 1 and o["self_off_flagged"] == 1 and o["self_near_flagged"] == 0
    assert "| 1 of 1 (and on 0 within 3) |" in "\n".join(section(doc))


def test_the_operator_is_told_the_share_of_the_paint_not_the_line_s_own():
    from cellctl.scan.result import CutPathSummary, PaintCheck, ResultSummary, UncutPaintSummary
    from cellctl.service.server import cut_warning

    paint = PaintCheck(cut_share=0.82, line_length_m=0.61, spray_width_mm=20.0,
                       uncut=[UncutPaintSummary(centre=[0.4, 0.0, 0.1], length_m=0.11, reason="not followed")])
    cut = CutPathSummary(branches=1, feasible_branches=1, poses=90, feasible_poses=90, length_m=0.45, planning_s=1.0,
                         cut_fraction=1.0, drawing_length_m=0.45, paint=paint)
    assert cut.told_share == 0.82 and cut.told_length_m == 0.61
    r = ResultSummary(scene="s", planner="gnbv", steps=2, terminated_by="frontier", coverage_percent=100.0,
                      coverage_hit=1, coverage_total=1, planning_s=1.0, step_s=1.0, capture_s=0.1,
                      motion_planning_s=0.1, motion_s=1.0, displacement_m=0.1, cut=cut)
    note = cut_warning(r)
    assert note.startswith("warning: 82.0 % of the drawing") and "110 mm not followed" in note
    # without a paint check (an old result) the line's own share is all there is
    bare = r.model_copy(update={"cut": cut.model_copy(update={"paint": None, "cut_fraction": 0.9})})
    assert bare.cut.told_share == 0.9 and cut_warning(bare).startswith("warning: 90.0 %")
    # all the paint seen is cut, but it runs on past what the scan measured: the share is of less than the line
    from cellctl.scan.result import UnseenPaintSummary
    full = paint.model_copy(update={"cut_share": 1.0, "uncut": []})
    done = r.model_copy(update={"cut": cut.model_copy(update={"paint": full})})
    assert cut_warning(done) is None
    under = full.model_copy(update={"unseen": [UnseenPaintSummary(centre=[0.5, 0.0, 0.2], border_m=0.02, wall_m=0.1)]})
    told = cut_warning(r.model_copy(update={"cut": cut.model_copy(update={"paint": under})}))
    assert told.startswith("warning: 100.0 %") and "runs on unseen at 1 border" in told


def test_the_generated_report_gives_each_piece_s_spread_over_seeds():
    from cellctl.bench.generated import seed_spread

    doc = _doc()
    again = {**doc["runs"][0], "seed": 1,
             "cut": {**doc["runs"][0]["cut"], "accuracy": {**doc["runs"][0]["cut"]["accuracy"], "cut_coverage": 0.74}}}
    doc["runs"].append(again)
    rows = piece_rows(doc)
    assert seed_spread(rows) == {"scrap:4:0": pytest.approx(7.0)}
    assert "| true cut coverage's range over the seeds, per piece: max (points) | 7.0 (0 of 1 pieces within 5) |" \
        in "\n".join(section(doc))


def test_the_told_share_is_the_line_on_the_band_centre_under_the_flame_and_a_loop_beside_it_is_no_line():
    """The told share (``line_share``) judges the measured line as the truth judges the true one: half a
    line cut is half (plus the tolerance past the cut's end), and a loop of the line wandering inside the
    band beside its centre, left uncut, is not counted as line the cut missed."""
    line = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    paint = _band(line)
    normals = np.tile([0.0, 0.0, 1.0], (len(paint), 1))
    half = paint_report(paint, normals, VOXEL, HALF, 0.005, [_flame(_line(line[0], [0.15, 0.0, 0.0]))], paint,
                        line=[line])
    assert half.line_share == pytest.approx((0.15 + 0.005) / 0.3, abs=0.03)
    assert half.line_on_paint_m == pytest.approx(0.3, abs=0.01)
    whole = [_flame(_line(line[0], line[1]))]
    loop = np.array([[0.1, 0.0, 0.0], [0.12, 0.008, 0.0], [0.16, 0.008, 0.0], [0.18, 0.0, 0.0]])
    rep = paint_report(paint, normals, VOXEL, HALF, 0.005, whole, paint, line=[line, loop])
    assert rep.line_share >= 0.97, rep.line_share  # the loop's stretch 8 mm beside the centre is no line
    none = paint_report(paint, normals, VOXEL, HALF, 0.005, [], paint, line=[line])
    assert none.line_share == 0.0
    # one uncut stretch listed twice (the gaps of two branches over the same paint, 1 mm apart) is one
    twice = paint_report(paint, normals, VOXEL, HALF, 0.005, [_flame(_line(line[0], [0.15, 0.0, 0.0]))], paint,
                         line=[np.array([[0.0, 0.0, 0.0], [0.15, 0.0, 0.0]]), np.array([[0.15, 0.0, 0.0], [0.3, 0.0, 0.0]]),
                               np.array([[0.15, 0.001, 0.0], [0.3, 0.001, 0.0]])])
    assert twice.line_share == pytest.approx(half.line_share, abs=0.02)
    assert twice.line_on_paint_m == pytest.approx(0.3, abs=0.01)
