"""The occupancy grid and frontier on synthetic scans whose answer is known."""

import numpy as np

from planners.config import GridConfig
from planners.grid import OccupancyGrid, frontier_clusters


def _grid():
    return OccupancyGrid(GridConfig(lo_m=(0, 0, 0), hi_m=(0.4, 0.4, 0.4), voxel_m=0.01))


def _floor_scan(x_max=0.4):
    """Points on the plane z = 0.1 seen from a camera at (0.2, 0.2, 0.35)."""
    xs = np.arange(0.1, x_max, 0.004) + 0.001
    ys = np.arange(0.1, 0.3, 0.004) + 0.001
    X, Y = np.meshgrid(xs, ys)
    return np.array([0.2, 0.2, 0.35]), np.stack([X.ravel(), Y.ravel(), np.full(X.size, 0.105)], 1)


def test_one_scan_gives_free_occupied_and_unknown_cells():
    g = _grid()
    origin, pts = _floor_scan()
    g.integrate(origin, pts)
    ijk = lambda p: tuple(np.floor(np.asarray(p) / 0.01).astype(int))  # noqa: E731
    assert g.occupied[ijk([0.2, 0.2, 0.105])]  # the surface
    assert g.free[ijk([0.2, 0.2, 0.25])]  # between camera and surface
    assert g.unknown[ijk([0.2, 0.2, 0.05])]  # behind the surface
    assert g.unknown[ijk([0.02, 0.38, 0.38])]  # never looked at
    p = g.probability()
    assert p[ijk([0.2, 0.2, 0.105])] > 0.5 > p[ijk([0.2, 0.2, 0.25])]
    assert p[ijk([0.2, 0.2, 0.05])] == 0.5


def test_frontier_sits_where_the_drawing_leaves_the_seen_area():
    g = _grid()
    origin, pts = _floor_scan(x_max=0.3)  # the view stops at x = 0.3
    g.integrate(origin, pts)
    stripe = pts[(np.abs(pts[:, 1] - 0.2) < 0.01) & (pts[:, 0] > 0.15)]  # a stripe starting in view, cut by its edge
    g.set_drawing(stripe)
    f = g.frontier()
    labels, n = frontier_clusters(f, 3)
    assert n >= 1
    xs = g.centers(np.argwhere(labels > 0))[:, 0]
    assert xs.min() > 0.26  # only at the cut end, not along the stripe or behind the surface
    # once the rest of the plane and the stripe's end are seen, the frontier is gone
    _, more = _floor_scan(x_max=0.4)
    g.integrate(np.array([0.3, 0.2, 0.35]), more)
    g.integrate(origin, more)
    g.set_drawing(more[(np.abs(more[:, 1] - 0.2) < 0.01) & (more[:, 0] > 0.15) & (more[:, 0] < 0.34)])
    _, n_after = frontier_clusters(g.frontier(), 3)
    assert n_after == 0


def test_a_segment_is_blocked_only_by_the_cells_it_crosses():
    """planners.raycast.segments_blocked: the sight-line check the planners' visibility rests on."""
    from planners.raycast import segments_blocked

    shape = np.array([10, 10, 10], dtype=np.int64)
    blocked = np.zeros(1000, dtype=np.uint8)
    blocked[(5 * 10 + 5) * 10 + 5] = 1  # the cell (5, 5, 5) of 1 cm cells from the origin
    starts = np.array([[0.005, 0.055, 0.055], [0.005, 0.015, 0.055], [0.055, 0.055, 0.055]])
    ends = np.array([[0.095, 0.055, 0.055], [0.095, 0.015, 0.055], [0.055, 0.055, 0.055]])
    out = segments_blocked(starts, ends, np.zeros(3), 0.01, shape, blocked)
    assert out.tolist() == [True, False, False]  # through it; beside it; a point (no segment)
