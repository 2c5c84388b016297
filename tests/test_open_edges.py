"""The frontier finer than the grid: paint where the measured surface stops."""

from __future__ import annotations

import numpy as np
import pytest

from planners.open_edges import open_paint_edges

STEP = 0.002  # the accumulated clouds' de-duplication


def _rod(arc_deg: float, radius=0.008, length=0.06):
    """A rod along x, seen from +z: its surface sampled on the arc within ``arc_deg`` of the top."""
    a = np.radians(np.arange(-arc_deg, arc_deg + 1e-9, np.degrees(STEP / radius)))
    x = np.arange(-length / 2, length / 2 + 1e-9, STEP)
    A, X = np.meshgrid(a, x, indexing="ij")
    pts = np.column_stack([X.ravel(), radius * np.sin(A.ravel()), radius * np.cos(A.ravel())])
    return pts, A.ravel()


def test_paint_on_a_rod_seen_from_above_is_open_at_the_flanks_only():
    """A 16 mm rod seen from above up to 60 deg round each side, painted on a band across it: the
    open points are the band's ends at +-60 deg, each pointing on round the rod (away from the
    top); the band's middle and its edges along the rod (the surface goes on there) are not open."""
    surface, ang = _rod(60.0)
    band = np.abs(surface[:, 0]) <= 0.0125
    paint, a = surface[band], ang[band]
    eye = np.tile([0.0, 0.0, 0.5], (len(paint), 1))
    e = open_paint_edges(paint, eye, surface, 0.005)
    flank = np.abs(np.degrees(a[e.index])) > 40.0
    assert len(e.index) > 0 and flank.all(), "only the flanks are open"
    assert (np.abs(np.degrees(a)) > 58.0).sum() <= 2 * len(e.index), "most of the last ring is"
    side = np.sign(paint[e.index, 1])
    assert np.all(side * e.outward[:, 1] > 0.5), "the way on is round the rod, away from the top"
    assert np.allclose(np.linalg.norm(e.normals, axis=1), 1.0)
    radial = paint[e.index] - np.column_stack([paint[e.index, 0], np.zeros((len(e.index), 2))])
    assert np.all(np.einsum("ij,ij->i", e.normals, radial / np.linalg.norm(radial, axis=1, keepdims=True)) > 0.95)


def test_a_fully_seen_plate_has_no_open_paint_but_one_cut_short_has():
    """A plate seen in full, painted along a stripe that ends on it: nothing is open. The same
    plate seen only up to a line across the stripe: the paint on that line is open, pointing beyond
    it. (Paint that runs off a plate's real edge is open too: from the cloud alone an edge and
    the end of what was seen look alike; a view settles which.)"""
    x, y = np.meshgrid(np.arange(-0.05, 0.05 + 1e-9, STEP), np.arange(-0.05, 0.05 + 1e-9, STEP))
    plate = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    paint = plate[(np.abs(plate[:, 1]) <= 0.01) & (np.abs(plate[:, 0]) <= 0.03 + 1e-9)]
    eye = np.tile([0.0, 0.0, 0.4], (len(paint), 1))
    assert len(open_paint_edges(paint, eye, plate, 0.005).index) == 0
    short = plate[plate[:, 0] <= 0.02 + 1e-9]
    seen = paint[paint[:, 0] <= 0.02 + 1e-9]
    e = open_paint_edges(seen, eye[:len(seen)], short, 0.005)
    assert len(e.index) > 0 and np.all(seen[e.index, 0] > 0.02 - 0.0025)
    assert np.all(e.outward[:, 0] > 0.9)


def test_open_edges_take_no_nonsense():
    with pytest.raises(ValueError, match="radius_m"):
        open_paint_edges(np.zeros((3, 3)), np.ones((3, 3)), np.zeros((10, 3)), 0.0)
    assert len(open_paint_edges(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((10, 3)), 0.005).index) == 0
