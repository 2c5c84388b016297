"""The all-knowing reference: views cast on the true mesh, added greedily."""

from __future__ import annotations

import numpy as np
import trimesh

from cellctl.oracle_bench import TrueViews, greedy_best
from sim.config import D435Config


def test_greedy_from_each_good_first_view_finds_the_pair_plain_greedy_misses():
    """Voxel 0 seen already. Plain greedy takes the view of 4 new voxels first and then cannot
    finish in two; starting from the second-best view, two views see all."""
    start = np.zeros(7, dtype=bool)
    start[0] = True
    S = np.zeros((3, 7), dtype=bool)
    S[0, [1, 2, 3, 4]] = True
    S[1, [1, 2, 5]] = True
    S[2, [3, 4, 6]] = True
    assert greedy_best(S, start, views=2, firsts=1)[1][0] < 1.0
    best = greedy_best(S, start, views=2, firsts=3)
    assert best[0] == (5 / 7, [0])
    assert best[1][0] == 1.0 and sorted(best[1][1]) == [1, 2]


def test_a_camera_sees_the_paint_on_top_of_a_plate_from_above_not_from_below():
    plate = trimesh.creation.box([0.2, 0.2, 0.01])
    x, y = np.meshgrid(np.linspace(-0.05, 0.05, 11), np.linspace(-0.05, 0.05, 11))
    paint = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 0.005)])
    tv = TrueViews(plate.vertices, plate.faces, paint, 0.01, D435Config(noise=False))
    assert tv.seen(np.array([0.0, 0.01, 0.5])).all()
    assert not tv.seen(np.array([0.0, 0.01, -0.5])).any(), "the plate hides its top from below"
    assert not tv.seen(np.array([0.6, 0.0, 0.006])).any(), "at 89 deg the D435 returns nothing"
    assert not tv.seen(np.array([0.0, 0.01, 0.1])).all(), "0.1 m up, a 42 deg image frames part of it"
