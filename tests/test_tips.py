"""A sharp turn rebuilt from its legs (planners.cutpath.tips): where a tip's legs share one band of
paint, what follows the paint chords across the tip; the legs carried on meet at the tip."""

import numpy as np
from scipy.spatial import cKDTree

from planners.cutpath.geometry import resample
from planners.cutpath.tips import rebuilt_tips
from planners.metrics import dense_polylines

HALF = 0.009
UP = np.array([0.0, 0.0, 1.0])


def band(poly: np.ndarray, half: float = HALF, cell: float = 0.002) -> np.ndarray:
    """The paint of a line sprayed on the plate z = 0: the grid points within ``half`` of it."""
    lo, hi = poly[:, :2].min(0) - 2 * half, poly[:, :2].max(0) + 2 * half
    g = np.stack(np.meshgrid(*(np.arange(a, b, cell) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 2)
    g = np.column_stack([g, np.zeros(len(g))])
    return g[cKDTree(dense_polylines([poly], 0.0005)).query(g)[0] <= half]


def vee(tip_deg: float, leg: float = 0.12) -> np.ndarray:
    h = np.radians(tip_deg) / 2
    return np.array([[-leg * np.sin(h), leg * np.cos(h), 0], [0, 0, 0], [leg * np.sin(h), leg * np.cos(h), 0.0]])


def test_a_chord_across_a_sharp_tip_is_put_back_on_the_tip():
    """A 20-degree tip whose line (as an outline's linked points take it) turns 25 mm short of the tip:
    the rebuilt line reaches the tip and never leaves the legs."""
    v = vee(20.0)
    paint = band(v)
    cut_at = 0.025 / np.cos(np.radians(10))  # along each leg from the tip
    a, b = v[1] + cut_at * (v[0] - v[1]) / np.linalg.norm(v[0] - v[1]), v[1] + cut_at * (v[2] - v[1]) / np.linalg.norm(v[2] - v[1])
    chorded = resample(np.vstack([v[0], a, b, v[2]]), 0.005)
    before = cKDTree(chorded).query(v[1])[0]
    out, tips = rebuilt_tips(chorded, paint, 0.005, HALF, np.tile(UP, (len(chorded), 1)))
    assert before > 0.02 and len(tips) == 1
    assert np.linalg.norm(tips[0] - v[1]) < 0.003, tips
    off = cKDTree(dense_polylines([v], 0.0005)).query(dense_polylines([out], 0.0005))[0]
    assert off.max() < 0.003, off.max()


def test_a_curve_and_a_line_over_an_edge_are_no_tips():
    """A bend of 60 mm radius turns 90 degrees but is a curve, not a tip; a straight line over a box's
    edge turns 90 degrees in space but not on the metal: both are left as they are."""
    th = np.linspace(0.0, np.pi / 2, 40)
    arc = np.column_stack([0.06 * np.cos(th), 0.06 * np.sin(th), np.zeros_like(th)])
    arc = np.vstack([arc[:1] + np.outer(np.linspace(0.06, 0.0, 12, endpoint=False), [0, -1, 0]), arc,
                     arc[-1:] + np.outer(np.linspace(0.0, 0.06, 12)[1:], [-1, 0, 0])])
    arc = resample(arc, 0.005)
    out, tips = rebuilt_tips(arc, band(arc), 0.005, HALF, np.tile(UP, (len(arc), 1)))
    assert not tips and np.array_equal(out, arc)
    s = np.arange(0.0, 0.1, 0.005)
    edge = np.vstack([np.column_stack([np.zeros_like(s), np.zeros_like(s), 0.1 - s]),  # down the side...
                      np.column_stack([s[1:], np.zeros(len(s) - 1), np.zeros(len(s) - 1)])])  # ...over the top
    normals = np.where((edge[:, 0] < 1e-9)[:, None] & (edge[:, 2] > 1e-9)[:, None], [[-1.0, 0, 0]], [UP])
    paint = np.vstack([edge + [0, dy, 0] for dy in np.linspace(-HALF, HALF, 9)])
    out, tips = rebuilt_tips(edge, paint, 0.005, HALF, normals)
    assert not tips and np.array_equal(out, edge)
