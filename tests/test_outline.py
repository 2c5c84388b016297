"""The line from the paint's outline (planners.cutpath.outline, graph.curve_graph): sharp tips kept where the
skeleton of the merged paint cuts a chord."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from planners.config import CutPathConfig
from planners.cutpath import build_cut_path
from planners.cutpath.geometry import Surface
from planners.cutpath.graph import LOOP, curve_graph
from planners.cutpath.outline import line_core, outline
from planners.metrics import cut_accuracy, dense_polylines

Z = 0.1
EYE = np.array([0.45, 0.0, 0.6])


def zigzag(tip_deg: float, arm: float = 0.15, turns: int = 2, start=(0.35, -0.15)) -> np.ndarray:
    """A zigzag of straight arms ``arm`` long whose tips have an included angle of ``tip_deg``."""
    h = np.radians(tip_deg) / 2
    k = np.arange(turns + 2)
    x = start[0] + k * arm * np.sin(h)
    y = np.where(k % 2 == 0, start[1], start[1] + arm * np.cos(h))
    return np.column_stack([x, y, np.full(len(k), Z)])


def sprayed(poly: np.ndarray, half: float = 0.01, cell: float = 0.002, noise: float = 0.0005, margin: float = 0.05):
    """(paint, surface): a plate sampled every ``cell`` with noise, and its points within ``half`` of the line."""
    lo, hi = poly[:, :2].min(0) - margin, poly[:, :2].max(0) + margin
    g = np.stack(np.meshgrid(*(np.arange(a, b, cell) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 2)
    rng = np.random.default_rng(0)
    surf = np.column_stack([g + rng.normal(0, noise, g.shape), Z + rng.normal(0, noise, len(g))])
    d = cKDTree(dense_polylines([poly], 0.0005)[:, :2]).query(g)[0]
    return surf[d <= half], surf


@pytest.mark.parametrize("tip_deg, skeleton_fails", [(30, True), (40, False), (60, False)])
def test_a_zigzag_s_sharp_tips_are_cut_not_chorded(tip_deg, skeleton_fails):
    """Where the arms' paint merges the skeleton cuts across the tips, the outline does not (and since
    a turn is rebuilt from its legs, ``tips.py``, the skeleton's chord at 40 degrees neither)."""
    poly = zigzag(tip_deg)
    paint, surf = sprayed(poly)
    out = build_cut_path(paint, surf, CutPathConfig(), viewpoint=EYE)
    old = build_cut_path(paint, surf, CutPathConfig(line_from="skeleton"), viewpoint=EYE)
    a = cut_accuracy([poly], [b.points for b in out.branches])
    b = cut_accuracy([poly], [b.points for b in old.branches])
    assert a["cut_coverage"] >= 0.97 and a["path_to_line_max_mm"] <= 3.0, a
    if skeleton_fails:  # the skeleton's chords
        assert b["cut_coverage"] < a["cut_coverage"] or b["path_to_line_max_mm"] > 3.0, b


@pytest.mark.parametrize("tip_deg", [20, 25])
def test_a_zigzag_s_sharper_tips_are_cut_within_the_tolerance(tip_deg):
    """Tips down to 20 degrees, whose legs' paint merges for 50 mm: the line reaches them and keeps
    within 5 mm of the worker's line (the cut's tolerance)."""
    poly = zigzag(tip_deg)
    paint, surf = sprayed(poly)
    out = build_cut_path(paint, surf, CutPathConfig(), viewpoint=EYE)
    a = cut_accuracy([poly], [b.points for b in out.branches])
    assert a["cut_coverage"] >= 0.97 and a["path_to_line_max_mm"] <= 5.0, a


def test_the_outline_measures_the_spray_and_moves_onto_the_line():
    poly = np.array([[0.35, -0.1, Z], [0.55, 0.05, Z]])
    paint, surf = sprayed(poly, half=0.012)
    s = Surface(surf, None, EYE, 0.02)
    o = outline(paint, s.normals(paint), metal=s.tree)
    # between the outline points, which sit a little inside the paint's last points: the line is what counts
    assert o.half_width_m == pytest.approx(0.012, abs=0.0025)
    d = cKDTree(dense_polylines([poly], 0.0005)).query(o.line)[0]
    assert np.percentile(d, 90) < 0.002, np.percentile(d, [50, 90, 100])
    core, _ = line_core(paint, s.normals(paint), s.tree)
    assert 0.2 * len(paint) < len(core) < 0.6 * len(paint)


def test_paint_that_stops_with_the_metal_is_no_outline():
    """A line sprayed off the plate's edge: where the paint ends at the edge there is no bare metal
    beyond, so the edge is not taken for a side of the band."""
    poly = np.array([[0.35, 0.0, Z], [0.55, 0.0, Z]])
    paint, surf = sprayed(poly)
    keep = surf[:, 0] <= 0.5  # the plate ends at x = 0.5: the line runs off it
    paint, surf = paint[paint[:, 0] <= 0.5], surf[keep]
    s = Surface(surf, None, EYE, 0.02)
    o = outline(paint, s.normals(paint), metal=s.tree)
    at_edge = o.points[:, 0] > 0.497
    assert len(o.points) > 50 and not (o.inward[at_edge, 0] < -0.7).any()  # no side facing back from the edge
    # the cut then runs to the edge (leaves the metal), not half a spray width short of it
    out = build_cut_path(paint, surf, CutPathConfig(), viewpoint=EYE)
    assert len(out.branches) == 1 and out.branches[0].points[:, 0].max() > 0.495


def test_the_curve_graph_closes_a_ring_its_spanning_tree_left_open():
    th = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    ring = np.column_stack([0.45 + 0.1 * np.cos(th), 0.1 * np.sin(th), np.full_like(th, Z)])
    paint = np.vstack([ring + [dx, dy, 0] for dx in (-0.004, 0, 0.004) for dy in (-0.004, 0, 0.004)])
    g = curve_graph(ring, paint=cKDTree(paint), bridge_m=0.06)
    assert len(g.branches) == 1 and g.kinds == [LOOP]
