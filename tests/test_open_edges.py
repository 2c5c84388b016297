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


def test_the_cone_round_a_rim_points_halfway_round_it_and_none_inside_a_seen_plate():
    """A flange's top (z = 0, y >= -0.05) seen from above, a stripe painted across it up to the
    rim at y = -0.05: the paint near the rim asks for views halfway round it, between the top's
    normal (+z) and the way out past the rim (-y), where the outer face turns away from the views
    that saw the top. Paint in the middle of the seen top, and too few points, ask for nothing."""
    from planners.open_edges import round_edge_axis

    x, y = np.meshgrid(np.arange(-0.05, 0.05 + 1e-9, STEP), np.arange(-0.05, 0.05 + 1e-9, STEP))
    top = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    paint = top[np.abs(top[:, 0]) <= 0.01]
    eye = np.tile([0.0, 0.0, 0.4], (len(paint), 1))
    axis = round_edge_axis(paint, eye, top, np.array([0.0, -0.055, 0.0]), 0.03, 0.005)
    assert axis is not None and np.allclose(axis, [0.0, -np.sqrt(0.5), np.sqrt(0.5)], atol=0.05)
    assert round_edge_axis(paint, eye, top, np.array([0.0, 0.0, 0.0]), 0.015, 0.005) is None
    assert round_edge_axis(paint[:3], eye[:3], top, np.array([0.0, -0.05, 0.0]), 0.03, 0.005) is None


def test_open_edges_take_no_nonsense():
    with pytest.raises(ValueError, match="radius_m"):
        open_paint_edges(np.zeros((3, 3)), np.ones((3, 3)), np.zeros((10, 3)), 0.0)
    assert len(open_paint_edges(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((10, 3)), 0.005).index) == 0


def test_a_view_further_round_the_edge_scores_more_and_one_along_it_little():
    """One open point, its surface facing +z and going on unseen towards +y, seen from 45 deg on
    the -y side: a view from 45 deg on the +y side looks 90 deg further round, one from straight
    above 45 deg; one along the edge (from +x) sees the edge edge-on, one from behind the surface
    or from further back on the seen side nothing."""
    from planners.open_edges import OpenEdges, round_the_edge

    pts = OpenEdges(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 1.0, 0.0]]), np.zeros(1, int))
    origins = np.array([[0.0, -0.3, 0.3]])
    eyes = np.array([[0.0, 0.3, 0.3], [0.0, 0.0, 0.4], [0.4, 0.0, 0.02], [0.0, 0.3, -0.3], [0.0, -0.4, 0.2]])
    more = np.degrees(round_the_edge(eyes, pts, origins)[:, 0])
    assert more[0] == pytest.approx(90.0) and more[1] == pytest.approx(45.0)
    assert 0.0 < more[2] < 5.0
    assert more[3] == 0.0 and more[4] == 0.0


def _rod_state(band: float = 0.0125):
    """A 16 mm rod across the table at z = 0.15 seen from above, its paint ending at the flanks
    where the camera's view of the rod ended (60 deg round each side); every other cell of the grid
    observed: the grid's frontier has nothing left."""
    from painted_state import painted_state

    from planners.config import PlannersConfig
    from planners.grid import OccupancyGrid

    cfg = PlannersConfig()
    grid = OccupancyGrid(cfg.grid)
    cam = np.array([0.45, 0.0, 0.55])
    rod, _ = _rod(60.0, length=0.2)
    rod = rod + np.array([0.45, 0.0, 0.15])
    grid.integrate(cam, rod.astype(np.float32))
    grid.logodds[grid.logodds == 0] = -2.0  # the rest observed free: no frontier
    paint = np.abs(rod[:, 0] - 0.45) <= band
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    return cfg, painted_state(grid, rod, paint, cam, np.array([0.45, 0.0, 0.15]), K, (320, 240), step=1)


def test_cnbv_looks_round_the_rod_when_the_grid_frontier_is_done():
    """With nothing left on the grid, C-NBV (open_edge_views) plans a view from a flank's side,
    lower than the view that saw the rod; G-NBV (not listed) stops; the next plan looks at the
    other flank, and the one after stops: one view per group of open paint."""
    from planners.cnbv import ConstrainedNBV
    from planners.gnbv import GuidedNBV

    cfg, state = _rod_state()
    assert not state.grid.frontier(cfg.nbv.frontier_reach_voxels).any()
    assert GuidedNBV(cfg).next_view(state).stop
    cnbv = ConstrainedNBV(cfg)
    first = cnbv.next_view(state)
    assert not first.stop and first.gain[0] > 0
    eye = first.poses[0, :3, 3]
    side = np.sign(first.target[1])
    assert side * eye[1] > 0.15 and eye[2] < 0.45, "from the flank's side, lower down"
    second = cnbv.next_view(state)
    assert not second.stop and np.sign(second.target[1]) == -side
    assert cnbv.next_view(state).stop


def test_joint_edge_views_score_every_border_at_once_and_stop_when_none_is_worth_a_view():
    """The rod's two open flanks in one plan: its candidates round the centre of all the open
    paint, each scored on both flanks, the best from a flank's side and lower down, worth what the
    per-group plan's best is (the flanks face apart: no view sees round both). A direction taken is not offered again, and when no candidate
    sees enough of the border further round, there is no plan. Positions the runner could not
    reach are not offered again."""
    import dataclasses

    from planners.open_edges import EdgeViews

    cfg, state = _rod_state(band=0.04)  # 8 cm of paint along the rod: each flank's border is worth a view
    joint = cfg.nbv.model_copy(update={"joint_edge_views": True})
    poses, q, gain, centre = EdgeViews(joint, cfg.grid.surface_voxel_m).plan_joint(state, None)
    assert abs(centre[1]) < 0.003 and np.all(np.diff(q) <= 1e-12)
    eye = poses[0, :3, 3]
    assert abs(eye[1]) > 0.15 and eye[2] < 0.45, "from a flank's side, lower down"
    assert gain[0] == pytest.approx(EdgeViews(cfg.nbv).plan(state)[2][0], rel=0.05), "as much as one flank's own best"
    taken = dataclasses.replace(state, viewpoints=np.vstack([state.viewpoints, eye]))
    again = EdgeViews(joint, 0.002).plan_joint(taken, None)[0][:, :3, 3]
    u = (eye - centre) / np.linalg.norm(eye - centre)
    w = (again - centre) / np.linalg.norm(again - centre, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(w @ u, -1, 1))).min() >= cfg.nbv.revisit_angle_deg - 1e-6
    near_top = lambda eyes, c: np.linalg.norm(eyes - eye, axis=1) < 1e-3  # noqa: E731 (the runner failed there)
    assert not np.any(np.linalg.norm(EdgeViews(joint, 0.002).plan_joint(state, None, near_top)[0][:, :3, 3]
                                     - eye, axis=1) < 1e-3)
    strict = joint.model_copy(update={"min_view_growth_voxels": 10_000})
    assert EdgeViews(strict, 0.002).plan_joint(state, None) is None


def test_the_cone_does_not_turn_round_the_end_of_a_rod_s_seen_front():
    """A 16 mm rod along x seen from above up to x = 0 (the rest hidden), painted across its top
    +-60 deg: the open paint at x = 0 has one way out (+x), but its normals spread round the rod
    (resultant 0.8), so there is no one face to look round from and the cone keeps the normal.
    On a 60 mm pipe painted +-25 deg the normals agree (0.97): the cone turns round the end."""
    from planners.open_edges import round_edge_axis

    def rod(r, paint_deg):
        th = np.arange(-85.0, 85.0 + 1e-9, np.degrees(STEP / r))
        X, T = np.meshgrid(np.arange(-0.05, 0.0 + 1e-9, STEP), np.radians(th))
        surf = np.column_stack([X.ravel(), r * np.sin(T.ravel()), r * np.cos(T.ravel())])
        paint = surf[(np.abs(T.ravel()) <= np.radians(paint_deg)) & (X.ravel() >= -0.02)]
        return surf, paint, np.tile([0.0, 0.0, 0.4], (len(paint), 1))

    surf, paint, eye = rod(0.008, 60.0)
    assert round_edge_axis(paint, eye, surf, np.array([0.003, 0.0, 0.008]), 0.03, 0.005) is None
    surf, paint, eye = rod(0.03, 25.0)
    axis = round_edge_axis(paint, eye, surf, np.array([0.003, 0.0, 0.03]), 0.03, 0.005)
    assert axis is not None and axis[0] > 0.6 and axis[2] > 0.6


def test_joint_edge_views_end_when_the_last_one_found_less_than_it_was_counted_on_for():
    """The first joint plan is judged by the prior (one drawing cell per cell-long border seen
    round). The view taken is then measured: where it found nothing, the same open paint is not
    worth another view; where it found as much as its count promised, the next is offered. A
    camera that is not at any planned candidate (the runner went elsewhere) measures nothing."""
    import copy
    import dataclasses

    from planners.open_edges import EdgeViews

    cfg, state = _rod_state(band=0.04)
    joint = cfg.nbv.model_copy(update={"joint_edge_views": True})
    after = lambda grid, pose: dataclasses.replace(state, step=state.step + 1, grid=grid,  # noqa: E731
                                                   camera_pose=pose,
                                                   viewpoints=np.vstack([state.viewpoints, pose[:3, 3]]))

    views = EdgeViews(joint, cfg.grid.surface_voxel_m)
    poses = views.plan_joint(state, None)[0]
    assert views.edge_yield.per_point is None
    assert views.plan_joint(after(state.grid, poses[0]), None) is None, "it found nothing: no more edge views"
    assert views.edge_yield.per_point == 0.0

    views = EdgeViews(joint, cfg.grid.surface_voxel_m)
    poses = views.plan_joint(state, None)[0]
    grown = copy.deepcopy(state.grid)
    free = np.argwhere(~grown.drawing)[:40]
    grown.drawing[free[:, 0], free[:, 1], free[:, 2]] = True  # 40 new drawing cells: more than promised
    assert views.plan_joint(after(grown, poses[0]), None) is not None
    assert views.edge_yield.per_point > cfg.grid.surface_voxel_m / cfg.grid.voxel_m

    views = EdgeViews(joint, cfg.grid.surface_voxel_m)
    views.plan_joint(state, None)
    elsewhere = np.eye(4)
    elsewhere[:3, 3] = [0.0, 0.6, 0.9]
    assert views.plan_joint(after(state.grid, elsewhere), None) is not None and views.edge_yield.per_point is None


def test_a_disc_is_centred_inside_a_surface_and_shifted_at_its_border():
    """planners.discs: inside a sampled plane the neighbours' centroid is the point; at the plane's
    edge it moves 4r/(3 pi) inward, in the tangent plane, and the normal is the plane's."""
    from scipy.spatial import cKDTree

    from planners.discs import discs

    g = np.arange(-0.05, 0.0500001, 0.001)
    X, Y = np.meshgrid(g, g)
    plane = np.c_[X.ravel(), Y.ravel(), np.zeros(X.size)]
    r = 0.01
    d = discs(np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]), cKDTree(plane), r, 1000)
    assert np.allclose(np.abs(d.normals[:, 2]), 1.0, atol=1e-6)
    assert np.linalg.norm(d.shift[0]) < 0.02 * r  # grid rounding at the disc's rim
    assert d.shift[1][0] == pytest.approx(-4 * r / (3 * np.pi), rel=0.1) and abs(d.shift[1][2]) < 1e-9
    assert d.count[0] > 1.8 * d.count[1]


def test_paint_running_into_a_wall_is_seen_from_its_own_side_and_counts_the_wall():
    """An angle seen from above: a plate (z = 0, x <= 0.02) and an 8 mm wall standing at x = 0.02,
    6 cm tall, whose face toward the paint was grazing (not measured: only its top and back).
    A stripe painted along x up to the wall's foot. The paint at the foot is open, but the surface
    does not turn away there as at a rim: the way round is reversed (back toward the paint's side,
    from where the wall's face is seen), and the wall's height is what may carry the paint on.
    The same stripe up to a plate's real rim (no wall) keeps its way out and no wall."""
    x, y = np.meshgrid(np.arange(-0.05, 0.02 + 1e-9, STEP), np.arange(-0.05, 0.05 + 1e-9, STEP))
    plate = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    yb, zb = np.meshgrid(np.arange(-0.05, 0.05 + 1e-9, STEP), np.arange(0.0, 0.06 + 1e-9, STEP))
    back = np.column_stack([np.full(yb.size, 0.028), yb.ravel(), zb.ravel()])  # the wall's far face
    top = np.column_stack([np.full(51, 0.024), np.arange(-0.05, 0.05 + 1e-9, STEP), np.full(51, 0.06)])
    paint = plate[np.abs(plate[:, 1]) <= 0.01]
    eye = np.tile([-0.1, 0.0, 0.4], (len(paint), 1))
    walled = open_paint_edges(paint, eye, np.concatenate([plate, back, top]), 0.005)
    foot = paint[walled.index, 0] > 0.02 - 0.0025
    assert foot.sum() >= 5, "the paint at the wall's foot is open"
    assert np.all(walled.outward[foot, 0] < -0.9), "seen from the paint's side, toward the wall"
    assert np.all(walled.wall[foot] >= 0.05), "the wall stands 6 cm over the border"
    rim = open_paint_edges(paint, eye, plate, 0.005)
    at = paint[rim.index, 0] > 0.02 - 0.0025
    assert at.sum() >= 5 and np.all(rim.outward[at, 0] > 0.9) and np.all(rim.wall == 0.0)


def test_the_paint_left_running_on_unseen_is_told_with_its_border():
    """What a scan leaves unresolved: a stripe 20 mm wide seen up to a line across it has one border
    where it runs on unseen, about the stripe's width long; the same stripe ending on a plate seen
    in full has none; running into a wall's foot, the border says how high the wall stands."""
    from planners.open_edges import unseen_paint

    x, y = np.meshgrid(np.arange(-0.05, 0.05 + 1e-9, STEP), np.arange(-0.05, 0.05 + 1e-9, STEP))
    plate = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    paint = plate[(np.abs(plate[:, 1]) <= 0.01) & (np.abs(plate[:, 0]) <= 0.03 + 1e-9)]
    eye = np.tile([0.0, 0.0, 0.4], (len(paint), 1))
    assert unseen_paint(paint, eye, plate, 0.005, 0.01) == []
    short, seen = plate[plate[:, 0] <= 0.02 + 1e-9], paint[paint[:, 0] <= 0.02 + 1e-9]
    (u,) = unseen_paint(seen, eye[:len(seen)], short, 0.005, 0.01)
    assert 0.014 <= u.border_m <= 0.024 and u.centre[0] > 0.015 and abs(u.centre[1]) < 0.006 and u.wall_m == 0.0
    yb, zb = np.meshgrid(np.arange(-0.05, 0.05 + 1e-9, STEP), np.arange(0.0, 0.06 + 1e-9, STEP))
    back = np.column_stack([np.full(yb.size, 0.028), yb.ravel(), zb.ravel()])
    (w,) = unseen_paint(seen, eye[:len(seen)], np.concatenate([short, back]), 0.005, 0.01)
    assert w.wall_m >= 0.05
