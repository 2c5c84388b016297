"""The all-knowing reference: views cast on the true mesh, added greedily."""

from __future__ import annotations

import numpy as np
import trimesh

from cellctl.bench.oracle import TrueViews, beam_best, greedy_best
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


def test_the_beam_finds_three_views_that_see_all_where_greedy_from_every_first_view_leaves_two_stragglers():
    """View 0 sees the most; after it every second view leaves two voxels no third view joins. The
    beam keeps the pair (1, 3) whose leftovers one view (2) joins."""
    S = np.zeros((4, 9), dtype=bool)
    for row, seen in enumerate(([0, 1, 3, 5, 7], [0, 2, 5, 6], [1, 4, 6, 7], [3, 5, 6, 7, 8])):
        S[row, seen] = True
    start = np.zeros(9, dtype=bool)
    assert greedy_best(S, start, views=3, firsts=4)[2][0] == 8 / 9
    best = beam_best(S, start, views=3)
    assert best[0] == (5 / 9, [0])
    assert best[2][0] == 1.0 and sorted(best[2][1]) == [1, 2, 3]


def test_a_camera_sees_the_paint_on_top_of_a_plate_from_above_not_from_below():
    plate = trimesh.creation.box([0.2, 0.2, 0.01])
    x, y = np.meshgrid(np.linspace(-0.05, 0.05, 11), np.linspace(-0.05, 0.05, 11))
    paint = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 0.005)])
    tv = TrueViews(plate.vertices, plate.faces, paint, 0.01, D435Config(noise=False))
    assert tv.seen(np.array([0.0, 0.01, 0.5])).all()
    assert not tv.seen(np.array([0.0, 0.01, -0.5])).any(), "the plate hides its top from below"
    assert not tv.seen(np.array([0.6, 0.0, 0.006])).any(), "at 89 deg the D435 returns nothing"
    assert not tv.seen(np.array([0.0, 0.01, 0.1])).all(), "0.1 m up, a 42 deg image frames part of it"


def test_gnbv_first_step_is_put_to_the_truth_of_the_stripe():
    """The stripe of test_nbv_planners runs out of its first view at y = 0 and on to y = 0.2 on
    the table: G-NBV's top view shows some of what lies past the cut, none shows more than the
    best, and the report names the best one's rank among the candidates."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_nbv_planners import _state

    from cellctl.bench.oracle import first_step

    cfg, state = _state()
    table = trimesh.creation.box([0.4, 0.7, 0.02])
    table.apply_translation([0.45, -0.05, 0.09])
    ys = np.arange(-0.25, 0.2, 0.004)
    xs = np.arange(0.44, 0.46 + 1e-9, 0.004)
    X, Y = np.meshgrid(xs, ys)
    stripe = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 0.10)])
    tv = TrueViews(table.vertices, table.faces, stripe, cfg.coverage_voxel_m, D435Config(noise=False))
    f = first_step(tv, state, cfg)
    assert f["candidates"] > 10 and 20.0 < f["drawing_percent"] < 80.0
    assert f["top5_new_percent"][0] > 0.0
    assert f["best_new_percent"] >= max(f["top5_new_percent"])
    assert 1 <= f["best_rank"] <= f["candidates"]


def test_the_twins_own_frames_lose_thin_rods_silhouettes_that_a_mesh_cast_keeps():
    """From the basket's initial view the twin's sensor (depth-discontinuity dropouts at every rod's
    silhouette, the paint filter) shows part of what the cast shows, never voxels the cast misses
    by much; a camera looking away shows nothing. Both rolls of a pose look the same way."""
    from pathlib import Path

    from cellctl.bench.oracle import TwinViews, rolled_poses
    from cellctl.config import load_cell_config
    from planners.config import load_planners_config
    from sim.scenes import load_scene
    from sim.twin import Twin

    cfg, path = load_cell_config(Path(__file__).parents[1] / "configs" / "cell.sim.yaml")
    pcfg = load_planners_config(path.parent / cfg.planners_config)
    cam = cfg.twin.camera.model_copy(update={"noise": False})
    scene = load_scene("basket")
    T0 = scene.initial_view_candidates[0]
    cast = TrueViews(scene.full_mesh.vertices, scene.full_mesh.faces, scene.gt_points, 0.01, cam)
    seen_cast = cast.seen(T0[:3, 3], T0[:3, 3] + T0[:3, 2])
    with Twin(scene, cfg.twin.model_copy(update={"camera": cam})) as twin:
        tv = TwinViews(twin, scene.gt_points, 0.01, pcfg, T0)
        seen = tv.seen_pose(T0)
        away = T0.copy()
        away[:3, :3] = T0[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # turned round: the sky
        assert not tv.seen_pose(away).any()
    assert np.array_equal(tv.keys, cast.keys)
    assert 0.2 < seen.mean() < seen_cast.mean(), "the silhouettes' dropouts cost coverage"
    assert (seen & ~seen_cast).sum() <= 0.05 * len(seen)
    P = rolled_poses(np.array([[0.3, -0.3, 0.4]]), np.array([[0.5, 0.0, 0.1]]))
    assert P.shape == (2, 4, 4) and np.allclose(P[0][:3, 2], P[1][:3, 2])
    assert abs(P[0][:3, 0] @ P[1][:3, 0]) < 1e-9 and np.allclose(P[1][:3, :3].T @ P[1][:3, :3], np.eye(3))
    assert np.linalg.det(P[1][:3, :3]) > 0.99


def test_the_image_s_roll_decides_what_a_wide_short_frame_holds():
    """A stripe along x under a camera 0.3 m up: with the image's wide axis along the stripe it is
    framed whole (69 degrees wide); rolled a quarter turn, the 42-degree side frames about two thirds."""
    plate = trimesh.creation.box([0.8, 0.2, 0.01])
    xs = np.arange(-0.18, 0.18 + 1e-9, 0.01)
    stripe = np.column_stack([xs, np.zeros_like(xs), np.full(xs.size, 0.005)])
    tv = TrueViews(plate.vertices, plate.faces, stripe, 0.01, D435Config(noise=False))
    along = np.eye(4)
    along[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down, x along the stripe
    along[:3, 3] = [0.0, 0.0, 0.3]
    across = along.copy()
    across[:3, :3] = along[:3, :3] @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert tv.seen_pose(along).all()
    assert 0.5 < tv.seen_pose(across).mean() < 0.9


def test_the_arm_takes_a_view_from_above_and_refuses_one_at_the_table_one_in_the_piece_one_out_of_reach():
    """The twin's Panda with its camera and torch, a block on the table in front of it: a camera 0.4 m
    above the block looking down is taken, and the pose the arm takes there is the one asked for (up
    to the roll); 4 cm above the table looking level, the wrist would be in the table; 1.5 m out,
    beyond reach. A camera 20 cm up at the block's centre is taken with the block elsewhere, and
    refused inside it."""
    from pathlib import Path

    from cellctl.bench.oracle import ArmTakes, twin_arm
    from cellctl.config import load_cell_config
    from planners.config import load_planners_config
    from planners.views import look_at_rotations, poses_from
    from sim.scenes import load_scene

    cfg, path = load_cell_config(Path(__file__).parents[1] / "configs" / "cell.sim.yaml")
    pcfg = load_planners_config(path.parent / cfg.planners_config)
    model, q0 = twin_arm(load_scene("t_piece"), cfg.twin)
    eyes = np.array([[0.45, 0.0, 0.7], [0.5, 0.35, 0.04], [1.5, 0.0, 0.5], [0.5, 0.0, 0.2]])
    aims = np.array([[0.5, 0.0, 0.3], [0.5, 0.0, 0.04], [1.5, 0.0, 0.0], [0.5, 0.3, 0.2]])
    poses = poses_from(eyes, look_at_rotations(eyes, aims))
    block = trimesh.creation.box([0.2, 0.2, 0.3])
    elsewhere = block.copy()
    block.apply_translation([0.5, 0.0, 0.15])
    elsewhere.apply_translation([-0.6, 0.6, 0.15])
    takes = ArmTakes(model, q0, cfg.motion, pcfg)
    taken, actual = takes.piece(block.vertices, block.faces)(poses)
    assert taken.tolist() == [True, False, False, False]
    assert np.allclose(actual[0][:3, 3], eyes[0], atol=1e-3)
    assert actual[0][:3, 2] @ poses[0][:3, 2] > np.cos(np.radians(0.5))
    taken, _ = takes.piece(elsewhere.vertices, elsewhere.faces)(poses)
    assert taken.tolist() == [True, False, False, True]
