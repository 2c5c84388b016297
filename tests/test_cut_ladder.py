"""The cut planner's ladder graph (planners/cutpath/ladder.py), the batched IK under it
(planners/motion/ik_batch.py) and the accuracy metric against the true line (planners.metrics)."""

from __future__ import annotations

import os

import numpy as np
import pybullet_data
import pytest

from planners.config import CutPathConfig
from planners.cutpath import CutPath, build_cut_path, plan_cut, torch_kinematics
from planners.cutpath.ladder import COLLISION, OUT_OF_REACH, RECONFIGURE, plan_ladder, tilt_directions
from planners.cutpath.geometry import arc_length, center_on_paint, pivots, torch_poses
from planners.cutpath.nozzle import NozzleCheck, frustum_distance, nozzle_balls
from planners.metrics import cut_accuracy
from planners.motion.ik_batch import solve_axis_ik_batch
from planners.motion.limits import PANDA_MAX_VELOCITY, PANDA_Q_READY

URDF = os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf")
CFG = CutPathConfig()


@pytest.fixture(scope="module")
def kin():
    return torch_kinematics(URDF, CFG)


def straight(a, b, z=0.1, spacing=0.005):
    """A line on the plate z = const: points, upward normals, nominal torch poses, times."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = int(round(np.linalg.norm(b - a) / spacing)) + 1
    xy = a + np.linspace(0, 1, n)[:, None] * (b - a)
    pts = np.column_stack([xy, np.full(n, z)])
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    poses = torch_poses(pts, normals, CFG.standoff_m)
    times = np.arange(n) * spacing / CFG.travel_speed_mps
    return pts, normals, poses, times


# ----------------------------------------------------------------------------- batched IK
def test_batched_ik_reaches_what_forward_kinematics_says_is_reachable(kin):
    rng = np.random.default_rng(1)
    q_true = rng.uniform(kin.lower + 0.1, kin.upper - 0.1, size=(400, 7))
    T = kin.fk_batch(q_true)
    seeds = q_true + rng.normal(0.0, 0.15, size=q_true.shape)
    Q, ok = solve_axis_ik_batch(kin, T[:, :3, 3], T[:, :3, 2], seeds, margin=0.0)
    assert ok.mean() >= 0.98
    got = kin.fk_batch(Q[ok])
    assert np.abs(got[:, :3, 3] - T[ok, :3, 3]).max() <= 1e-4
    cos = np.einsum("ij,ij->i", got[:, :3, 2], T[ok, :3, 2])
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() <= 0.06
    assert np.all(Q >= kin.lower - 1e-12) and np.all(Q <= kin.upper + 1e-12)


def test_batched_ik_refuses_what_is_out_of_reach(kin):
    far = np.array([[2.0, 0.0, 0.5], [0.0, 0.0, -1.5]])
    Q, ok = solve_axis_ik_batch(kin, far, np.tile([0.0, 0.0, -1.0], (2, 1)), np.tile(PANDA_Q_READY, (2, 1)))
    assert not ok.any()
    assert np.all(np.isfinite(Q))


# ----------------------------------------------------------------------------- tolerances
def test_tilt_directions_stay_in_the_cone_and_start_at_the_normal():
    D = tilt_directions(CFG)
    assert np.allclose(D[0], [0, 0, 1])
    assert np.allclose(np.linalg.norm(D, axis=1), 1.0)
    lead = np.degrees(np.arctan2(D[:, 0], D[:, 2]))
    side = np.degrees(np.arcsin(D[:, 1]))
    assert np.all(np.abs(lead) <= CFG.lead_lag_max_deg + 1e-6) and np.all(np.abs(side) <= CFG.side_tilt_max_deg + 1e-6)
    assert np.isclose(np.abs(lead).max(), CFG.lead_lag_max_deg) and np.isclose(np.abs(side).max(), CFG.side_tilt_max_deg)
    assert len(tilt_directions(CFG.model_copy(update={"tilt_steps": 0}))) == 1


# ----------------------------------------------------------------------------- the ladder
def test_a_reachable_line_is_one_run_held_upright(kin):
    pts, _, poses, times = straight([0.35, -0.15], [0.55, 0.15])
    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, CFG, None, PANDA_MAX_VELOCITY)
    assert [(r.first, r.last) for r in lad.runs] == [(0, len(pts) - 1)]
    assert lad.gaps == []
    run = lad.runs[0]
    assert np.degrees(run.tilt_rad).max() < 1.0, "nothing forces a tilt: the torch stays along the normal"
    assert np.abs(np.diff(run.q, axis=0)).max() <= CFG.max_joint_jump_rad
    tip = kin.fk_batch(run.q)
    np.testing.assert_allclose(tip[:, :3, 3], run.poses[:, :3, 3], atol=2e-4)


def test_rungs_of_many_branches_in_one_call_are_each_branchs_own(kin):
    """solve_rungs batches every branch's IK; no branch's sweep takes a seed from its neighbour's
    layers, so each branch gets exactly what it gets alone. Reversed (Branch.reversed), the rungs
    are the same solutions with the tilts renamed: they still hold the reversed poses."""
    from planners.cutpath.ladder import reversal_permutation, solve_rungs
    from planners.cutpath.model import Branch

    a = straight([0.35, -0.15], [0.55, 0.15])
    b = straight([0.30, 0.20], [0.45, 0.25], z=0.2)
    both = solve_rungs(kin, [a[2], b[2]], PANDA_Q_READY, CFG)
    for (_, _, poses, _), r in zip((a, b), both):
        alone = solve_rungs(kin, [poses], PANDA_Q_READY, CFG)[0]
        np.testing.assert_array_equal(r.ok, alone.ok)
        np.testing.assert_allclose(r.Q, alone.Q, equal_nan=True)
    pts, normals, poses, _ = b
    back = Branch(pts, normals, poses, np.full(len(pts), 0.01), "a", "b").reversed()
    r = both[1].reversed(reversal_permutation(CFG))
    D = tilt_directions(CFG)
    np.testing.assert_allclose(r.axes, np.einsum("nij,oj->noi", back.poses[:, :3, :3], D), atol=1e-12)
    T = kin.fk_batch(r.Q[r.ok])
    np.testing.assert_allclose(T[:, :3, 3], np.broadcast_to(r.tips[..., None, :], r.Q.shape[:3] + (3,))[r.ok], atol=2e-4)
    np.testing.assert_allclose(T[:, :3, 2], np.broadcast_to(r.axes[..., None, :], r.Q.shape[:3] + (3,))[r.ok], atol=2e-3)


def test_the_torch_tilts_within_its_cone_to_clear_an_obstacle(kin):
    """Configurations holding the torch upright are forbidden on the middle third: the ladder
    leans the torch there instead of giving up, and stays one continuous run."""
    pts, _, poses, times = straight([0.35, -0.15], [0.55, 0.15])
    mid = (pts[:, 1] > -0.05) & (pts[:, 1] < 0.05)

    def is_free(Q):
        T = kin.fk_batch(Q)
        upright = T[:, 2, 2] < -np.cos(np.radians(3.0))  # torch axis within 3 deg of straight down
        near = np.abs(T[:, 1, 3]) < 0.05
        return ~(upright & near)

    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, CFG, is_free, PANDA_MAX_VELOCITY)
    assert len(lad.runs) == 1 and lad.runs[0].first == 0 and lad.runs[0].last == len(pts) - 1
    tilt = np.degrees(lad.runs[0].tilt_rad)
    assert tilt[mid].min() >= 3.0 and tilt.max() <= CFG.lead_lag_max_deg + 1e-6
    assert np.all(is_free(lad.runs[0].q))


def test_the_nozzle_balls_contain_the_taper_and_the_head_up_to_the_fine_length():
    torch = CFG.torch
    u, r = nozzle_balls(torch)
    rng = np.random.default_rng(2)
    z = rng.uniform(0.0, torch.fine_length_m, 4000)  # back from the tip
    rho = torch.nozzle_radius_m + (torch.radius_m - torch.nozzle_radius_m) * np.minimum(z / torch.nozzle_length_m, 1)
    a = rng.uniform(0, 2 * np.pi, len(z))
    pts = np.column_stack([rho * np.cos(a), rho * np.sin(a), z])  # on the taper's surface
    d = np.linalg.norm(pts[:, None, :] - np.column_stack([np.zeros((len(u), 2)), u])[None], axis=2)
    assert (d <= r[None] + 1e-12).any(axis=1).all()
    assert (r - u).max() < CFG.standoff_m - CFG.nozzle_margin_m, "upright over flat metal the nozzle is clear"


def test_the_torch_solid_distance_matches_its_sampled_surface():
    """frustum_distance against a dense sampling of the taper, the head's side and both flat ends:
    0 inside, the distance to the nearest sample outside (within the sampling's spacing)."""
    torch = CFG.torch
    L, F, rn, R = torch.nozzle_length_m, torch.fine_length_m, torch.nozzle_radius_m, torch.radius_m
    u = np.linspace(0.0, F, 1201)
    r = rn + (R - rn) * np.minimum(u / L, 1.0)
    side = np.column_stack([u, r])
    ends = np.vstack([np.column_stack([np.zeros(200), np.linspace(0, rn, 200)]),
                      np.column_stack([np.full(200, F), np.linspace(0, R, 200)])])
    profile = np.vstack([side, ends])
    rng = np.random.default_rng(4)
    q = np.column_stack([rng.uniform(-0.02, F + 0.02, 3000), rng.uniform(0.0, R + 0.02, 3000)])
    got = frustum_distance(q[:, 0], q[:, 1], torch)
    r_at = rn + (R - rn) * np.clip(q[:, 0] / L, 0, 1)
    inside = (q[:, 0] >= 0) & (q[:, 0] <= F) & (q[:, 1] <= r_at)
    assert np.all(got[inside] == 0.0) and np.all(got[~inside] > 0.0)
    want = np.linalg.norm(q[~inside, None, :] - profile[None], axis=2).min(axis=1)
    assert np.allclose(got[~inside], want, atol=1e-4)


def test_depth_noise_under_the_tip_does_not_close_the_standoff():
    """Upright 10 mm over a plate whose points scatter up to 5 mm above it (a far view's depth
    noise): the balls round the nozzle reach 7.4 mm in front of the tip and hold such points,
    the torch itself is 10 mm up and clear; a point 1.5 mm in front of the tip is not."""
    floor = _plate(x=(-0.05, 0.05), y=(-0.05, 0.05), z=0.0)
    rng = np.random.default_rng(5)
    noisy = floor + np.column_stack([np.zeros((len(floor), 2)), rng.uniform(0.0, 0.005, len(floor))])
    axis = np.array([[0.0, 0.0, -1.0]])
    tip = np.array([[0.0, 0.0, CFG.standoff_m]])
    u, r = nozzle_balls(CFG.torch)
    assert u[0] - r[0] - CFG.nozzle_margin_m < -0.005, "the first ball holds the noise band"
    assert NozzleCheck(noisy, CFG.torch, CFG.nozzle_margin_m)(tip, axis)[0]
    touching = np.vstack([noisy, [[0.003, 0.0, CFG.standoff_m - 0.0015]]])
    assert not NozzleCheck(touching, CFG.torch, CFG.nozzle_margin_m)(tip, axis)[0]
    beside = np.vstack([noisy, [[CFG.torch.nozzle_radius_m + 0.003, 0.0, CFG.standoff_m + 0.001]]])
    assert NozzleCheck(beside, CFG.torch, CFG.nozzle_margin_m)(tip, axis)[0], "3 mm beside the nozzle is clear"


def test_a_nozzle_leaning_into_a_wall_is_not_clear():
    """A wall 20 mm beside the line: upright the nozzle clears it, leaning 20 deg towards it not."""
    y, z = np.meshgrid(np.arange(-0.05, 0.05, 0.002), np.arange(0.0, 0.08, 0.002))
    wall = np.column_stack([np.full(y.size, 0.020), y.ravel(), z.ravel()])
    x, y = np.meshgrid(np.arange(-0.05, 0.019, 0.002), np.arange(-0.05, 0.05, 0.002))
    floor = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    check = NozzleCheck(np.vstack([wall, floor]), CFG.torch, CFG.nozzle_margin_m)
    lean = np.radians(20.0)
    # the axis points from the tip into the metal; the body lies back along -axis
    axes = np.array([[0.0, 0.0, -1.0], [-np.sin(lean), 0.0, -np.cos(lean)], [np.sin(lean), 0.0, -np.cos(lean)]])
    tips = -CFG.standoff_m * axes  # the tip standoff_m back along the axis from the paint point (0, 0, 0)
    assert check(tips, axes).tolist() == [True, False, True]


def _corner(step=0.002):
    """A 90 deg inside corner: the floor z = 0 for x < 0 and a wall x = 0 6 cm high."""
    x, y = np.meshgrid(np.arange(-0.1, 0.0, step), np.arange(-0.05, 0.05, step))
    floor = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    y, z = np.meshgrid(np.arange(-0.05, 0.05, step), np.arange(0.0, 0.06, step))
    return np.vstack([floor, np.column_stack([np.zeros(y.size), y.ravel(), z.ravel()])])


def test_the_torch_works_into_an_inside_corner_closer_than_a_grid_cell():
    """A line across the floor into a wall: 12 mm from the wall the torch, leaning 20 deg away
    from it, is clear of the measured surface (the 1 cm grid with its margin would close that
    corner); upright there its head hits the wall, and so does a torch 3 mm from the wall."""
    check = NozzleCheck(_corner(), CFG.torch, CFG.nozzle_margin_m)
    lean = np.radians(20.0)
    away = np.array([np.sin(lean), 0.0, -np.cos(lean)])  # tip into the metal, body leaning to -x
    down = np.array([0.0, 0.0, -1.0])
    paint = np.array([[-0.012, 0.0, 0.0], [-0.012, 0.0, 0.0], [-0.003, 0.0, 0.0]])
    axes = np.array([away, down, away])
    assert check(paint - CFG.standoff_m * axes, axes).tolist() == [True, False, False]


def test_unseen_cells_block_the_head_not_the_nozzle():
    """An unseen cell in front of the metal, beside the torch: 2 cm up, beside the nozzle, it does
    not count (the cells next to a surface seen at a slant are often unseen); 5 cm up, beside the
    head, it does, as large as its bounding ball."""
    floor = _plate(x=(-0.05, 0.05), y=(-0.05, 0.05), z=0.0)
    axis = np.array([0.0, 0.0, -1.0])
    tip = np.array([[0.0, 0.0, CFG.standoff_m]])
    clear = [NozzleCheck(floor, CFG.torch, CFG.nozzle_margin_m, np.array([[0.025, 0.0, z]]), 0.01)(tip, axis[None])[0]
             for z in (0.02, 0.06)]
    assert clear == [True, False]
    assert NozzleCheck(floor, CFG.torch, CFG.nozzle_margin_m, np.array([[0.045, 0.0, 0.06]]), 0.01)(tip, axis[None])[0]


def test_a_skeleton_bowing_at_its_end_is_rebuilt_from_its_paint():
    """Thinning bends a skeleton's last few centimetres toward a side of the end cap (6 mm on
    t_piece's branch). The end is rebuilt from the paint of its last two band widths: it ends
    within 1.5 mm of the drawn end and no point of it is more than 1.5 mm off the line; a line
    that turns within that stretch (a quarter circle of 5 cm radius) is followed round its turn,
    within 2 mm."""
    from scipy.spatial import cKDTree

    from planners.cutpath.geometry import end_caps

    surf = _plate(x=(-0.05, 0.25), y=(-0.1, 0.1), z=0.0, step=0.0015)
    n = np.tile([0.0, 0.0, 1.0], (200, 1))
    straight = np.column_stack([np.linspace(0.0, 0.2, 41), np.zeros(41), np.zeros(41)])
    th = np.linspace(0.0, np.pi / 2, 40)
    turning = np.vstack([np.column_stack([np.linspace(0.0, 0.15, 31)[:-1], np.zeros(30)]),
                         np.column_stack([0.15 + 0.05 * np.sin(th), 0.05 - 0.05 * np.cos(th)])])
    turning = np.column_stack([turning, np.zeros(len(turning))])
    for line in (straight, turning):
        d = np.linalg.norm(surf[:, None, :2] - line[None, :, :2], axis=2).min(axis=1)
        paint = surf[d <= 0.01]
        s = arc_length(line)
        bow = np.clip((s - (s[-1] - 0.03)) / 0.02, 0.0, 1.0) * 0.006  # up to 6 mm sideways
        side = np.cross(np.gradient(line, axis=0), [0.0, 0.0, 1.0])
        side /= np.linalg.norm(side, axis=1, keepdims=True)
        skeleton = line + bow[:, None] * side
        skeleton = skeleton[s <= s[-1] - 0.004]  # and stopping short of the paint's end
        out = end_caps(skeleton, paint, cKDTree(surf), 0.01, 0.005, start=False, normals=n[:len(skeleton)])
        truth = cKDTree(np.vstack([a + np.linspace(0, 1, 50)[:, None] * (b - a) for a, b in zip(line[:-1], line[1:])]))
        tol = 0.0015 if line is straight else 0.002  # a 2 cm band turning on a 5 cm radius: its paint lies outward
        assert np.linalg.norm(out[-1] - line[-1]) < tol
        assert truth.query(out)[0].max() < tol


def test_paint_on_the_far_face_of_a_plate_is_not_beside_the_line():
    """A line along the top face of a 12 mm plate whose 2 cm band of paint also wraps onto the
    plate's far face: with the surface normals the band is 1 cm wide on each side, not the
    reach of the paint on the other face."""
    from planners.cutpath.geometry import band_half_width

    top = _plate(x=(0.0, 0.2), y=(-0.01, 0.006), z=0.0, step=0.001)  # the face the line runs on
    far = _plate(x=(0.0, 0.2), y=(-0.004, 0.006), z=-0.012, step=0.001)  # paint round the rim on the far face
    paint = np.vstack([top, far])
    line = np.column_stack([np.linspace(0.01, 0.19, 37), np.zeros(37), np.zeros(37)])
    up = np.tile([0.0, 0.0, 1.0], (len(line), 1))
    assert band_half_width(line, paint, 0.005, normals=up) == pytest.approx(0.01, abs=0.0015)
    assert band_half_width(line, paint, 0.005) > 0.012


def test_a_line_off_the_middle_of_its_paint_is_moved_to_it():
    """A skeleton 3 mm beside the middle of a 2 cm band (what thinning on a 5 mm grid does) comes to
    the middle; at a right-angle corner of the band the points stay where they are."""
    rng = np.random.default_rng(4)
    band = np.column_stack([rng.uniform(0.0, 0.3, 20000), rng.uniform(-0.01, 0.01, 20000), np.zeros(20000)])
    line = np.column_stack([np.arange(0.0, 0.3, 0.005), np.full(60, 0.003), np.zeros(60)])
    out = center_on_paint(line, band, 0.005)
    assert np.abs(out[3:-3, 1]).max() < 0.0008 and np.allclose(out[:, 0], line[:, 0])
    corner = np.vstack([line[:30], np.column_stack([np.full(30, line[29, 0]), line[29, 1] + np.arange(1, 31) * 0.005,
                                                    np.zeros(30)])])
    moved = np.linalg.norm(center_on_paint(corner, band, 0.005) - corner, axis=1)
    assert moved[27:32].max() == 0.0


def test_paint_on_both_faces_of_a_thin_plate_is_not_joined_through_it():
    """A line painted up one face of a 12 mm plate, over its rim and down the other face: gap
    closing must not join the two faces through the metal, or the line would skip the rim."""
    from planners.cutpath.graph import drawing_graph

    z = np.arange(0.0, 0.1, 0.002)
    x = np.arange(-0.01, 0.01, 0.002)
    X, Z = np.meshgrid(x, z)
    faces = [np.column_stack([X.ravel(), np.full(X.size, y), Z.ravel()]) for y in (-0.006, 0.006)]
    Y, X2 = np.meshgrid(np.arange(-0.006, 0.0061, 0.002), x)
    rim = np.column_stack([X2.ravel(), Y.ravel(), np.full(X2.size, 0.1)])
    paint = np.vstack(faces + [rim])
    plate = np.vstack([paint] + [f + [0.04, 0, 0] for f in faces])  # the surface: the faces and the rim
    g = drawing_graph(paint, 0.005, 0.03, 1, surface=plate)
    length = sum(float(np.linalg.norm(np.diff(b, axis=0), axis=1).sum()) for b in g.branches)
    assert length > 0.18, "the line goes up, over the rim and down: about 0.21 m"


def test_a_sharp_edge_is_taken_in_pivot_steps():
    pts = np.array([[0.0, 0, 0], [0.005, 0, 0], [0.010, 0, 0]])
    normals = np.array([[0.0, 0, 1], [0.0, 0, 1], [1.0, 0, 0]])
    p, n = pivots(pts, normals, 10.0)
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n[:-1], n[1:]), -1, 1)))
    assert len(p) == 2 + 9 and turn.max() <= 10.0 + 1e-9
    np.testing.assert_allclose(p[[0, 1, -1]], pts)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.all(np.diff(p[:, 0]) >= 0), "the tip moves on along the chord while the torch turns"
    same, _ = pivots(pts, np.tile([0.0, 0, 1], (3, 1)), 10.0)
    np.testing.assert_array_equal(same, pts)


def test_a_blocked_stretch_splits_the_cut_and_is_reported_not_the_whole_branch(kin):
    pts, _, poses, times = straight([0.35, -0.15], [0.55, 0.15])
    blocked = (pts[:, 1] > -0.02) & (pts[:, 1] < 0.02)

    def is_free(Q):
        return np.abs(kin.fk_batch(Q)[:, 1, 3]) >= 0.02 + 0.02  # tip and tilt cannot get out: 4 cm band

    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, CFG, is_free, PANDA_MAX_VELOCITY)
    assert len(lad.runs) == 2
    gap = [g for g in lad.gaps if g.reason != RECONFIGURE]
    assert len(gap) == 1 and gap[0].reason == COLLISION
    uncut = np.zeros(len(pts), bool)
    uncut[list(gap[0].uncut_layers)] = True
    assert uncut[blocked].all(), "every blocked pose is in the reported gap"
    cut = np.zeros(len(pts), bool)
    for r in lad.runs:
        cut[r.first:r.last + 1] = True
    assert cut.sum() >= 0.6 * len(pts)
    assert not (cut & uncut).any()


def test_a_run_shorter_than_the_least_cut_is_no_cut(kin):
    """Where the torch can hold only a couple of poses 1 mm apart (pivot steps in an inside corner), or
    a stub of a line shorter than ``min_cut_m`` between two gaps, those poses are a pierce for nothing,
    not a cut: they join the gap around them, with its reason. A longer stretch is cut."""
    pts, _, poses, times = straight([0.40, -0.02], [0.40, 0.02], spacing=0.001)

    def only(lo, hi):  # the torch aimed at paint between y = lo and hi, however tilted
        def is_free(Q):
            T = kin.fk_batch(Q)
            y = T[:, 1, 3] + CFG.standoff_m * T[:, 1, 2]
            return (y > lo) & (y < hi)
        return is_free

    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, CFG, only(-0.0025, -0.0005), PANDA_MAX_VELOCITY)
    assert lad.runs == [] and [g.reason for g in lad.gaps] == [COLLISION]
    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, CFG, only(-0.008, 0.0005), PANDA_MAX_VELOCITY)
    assert lad.runs == [] and [g.reason for g in lad.gaps] == [COLLISION]  # 8 mm: a stub
    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, CFG, only(-0.019, 0.0055), PANDA_MAX_VELOCITY)
    assert len(lad.runs) == 1 and lad.runs[0].last - lad.runs[0].first >= CFG.min_cut_m / 0.001 - 1
    short = CFG.model_copy(update={"min_cut_m": 0.005})
    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, short, only(-0.008, 0.0005), PANDA_MAX_VELOCITY)
    assert len(lad.runs) == 1 and lad.runs[0].last - lad.runs[0].first >= 5


def test_a_line_running_out_of_reach_is_cut_as_far_as_the_arm_goes(kin):
    pts, _, poses, times = straight([0.5, 0.0], [1.3, 0.0])
    lad = plan_ladder(kin, poses, times, PANDA_Q_READY, CFG, None, PANDA_MAX_VELOCITY)
    assert len(lad.runs) >= 1 and lad.runs[0].first == 0
    assert lad.gaps[-1].reason == OUT_OF_REACH and lad.gaps[-1].before == len(pts)
    far = np.linalg.norm(pts[:, :2], axis=1) > 1.1
    assert not any(far[r.first:r.last + 1].any() for r in lad.runs)


def test_plan_cut_reports_what_will_be_cut_and_round_trips(kin, tmp_path):
    g = np.mgrid[0.3:0.7:0.002, -0.25:0.25:0.002].reshape(2, -1).T
    surf = np.column_stack([g, np.full(len(g), 0.1)])
    a, b = np.array([0.4, -0.15]), np.array([0.6, 0.15])
    t = np.clip((g - a) @ (b - a) / np.dot(b - a, b - a), 0, 1)
    paint = np.linalg.norm(g - a - t[:, None] * (b - a), axis=1) <= 0.01
    path = build_cut_path(surf[paint], surf, CFG, viewpoint=np.array([0.5, 0.0, 0.6]))
    plan_cut(path, kin, PANDA_Q_READY, CFG)
    assert path.feasible and len(path.branches) == 1 and path.cut_fraction > 0.99
    assert path.branches[0].tilt_rad is not None
    path.write(tmp_path)
    back = CutPath.read(tmp_path)
    assert back.cut_fraction == pytest.approx(path.cut_fraction, abs=1e-4)
    assert back.drawing_length_m == pytest.approx(path.drawing_length_m)
    np.testing.assert_allclose(back.branches[0].tilt_rad, path.branches[0].tilt_rad, atol=1e-9)


def test_a_cut_the_ladder_hands_over_is_clear_where_the_arm_will_be(kin):
    """plan_cut does not check a run's cut again: the ladder checked that very motion (the timed
    spline, a sample per degree of joint travel). Checked here from outside, at every control
    sample, against a wall the torch must tilt away from."""
    from planners.cutpath.plan import _cut_trajectory

    pts, normals, poses, times = straight([0.35, -0.15], [0.55, 0.15])

    def is_free(Q):  # a wall beside the line, leaning over it: the upright torch's flange hits it
        T = kin.fk_batch(Q)
        flange = T[:, :3, 3] - 0.15 * T[:, :3, 2]
        return flange[:, 0] < 0.47 + 0.3 * (flange[:, 2] - 0.1)

    path = CutPath([__import__("planners.cutpath.model", fromlist=["Branch"]).Branch(
        pts, normals, poses, np.full(len(pts), CFG.travel_speed_mps), "a", "b")], np.zeros((0, 3)), np.zeros((0, 3)),
        CFG.model_dump(mode="json"))
    plan_cut(path, kin, PANDA_Q_READY, CFG, is_free=is_free)
    assert path.branches and all(b.feasible for b in path.branches)
    for b in path.branches:
        assert is_free(_cut_trajectory(b, CFG.dt_s).positions).all()


def test_a_run_the_torch_cannot_plunge_into_starts_further_in(kin):
    """Nothing may come within 12 mm of the line's first point from above the torch's working
    height (something overhangs it there), though the torch may stand there: the run starts at the
    first pose it can plunge to, the poses before are a collision gap, and the rest of the run is
    cut, not dropped with its approach."""
    from planners.cutpath.model import Branch

    pts, normals, poses, times = straight([0.45, -0.10], [0.45, 0.10])

    def is_free(Q):
        tip = kin.fk_batch(Q)[:, :3, 3]
        return ~((np.hypot(tip[:, 0] - 0.45, tip[:, 1] + 0.10) < 0.012) & (tip[:, 2] > 0.113))

    path = CutPath([Branch(pts, normals, poses, np.full(len(pts), CFG.travel_speed_mps), "a", "b")],
                   np.zeros((0, 3)), np.zeros((0, 3)), CFG.model_dump(mode="json"))
    plan_cut(path, kin, PANDA_Q_READY, CFG, is_free=is_free)
    assert len(path.branches) == 1 and path.branches[0].feasible, [b.issues for b in path.branches]
    assert path.branches[0].points[:, 1].min() > -0.10 + 0.001  # whichever way it is cut
    gap = [g for g in path.gaps if g.reason == COLLISION]
    assert len(gap) == 1 and gap[0].length_m <= 0.021 and ("plunge" in gap[0].detail or "lift" in gap[0].detail)
    assert path.cut_fraction > 0.89


# ----------------------------------------------------------------------------- accuracy
def test_cut_accuracy_against_a_known_line():
    line = np.column_stack([np.linspace(0, 0.2, 50), np.zeros(50), np.zeros(50)])
    shifted = line + [0.0, 0.002, 0.0]
    a = cut_accuracy([line], [shifted])
    assert a["cut_coverage"] == 1.0
    assert a["path_to_line_mean_mm"] == pytest.approx(2.0, abs=0.01)
    assert a["path_to_line_max_mm"] == pytest.approx(2.0, abs=0.01)
    half = cut_accuracy([line], [shifted[:25]])
    assert half["cut_coverage"] == pytest.approx(0.5, abs=0.03)
    assert half["line_to_path_max_mm"] == pytest.approx(1e3 * (0.2 - line[24, 0]), abs=0.6)
    assert (half["cuts"], half["strokes"]) == (1, 1)
    none = cut_accuracy([line], [])
    assert none["cut_coverage"] == 0.0 and none["path_to_line_mean_mm"] is None
    with pytest.raises(ValueError, match="no polyline"):
        cut_accuracy([], [line])


def test_a_short_cut_is_a_fragment_only_where_its_paint_goes_on():
    """A 10 mm cut on a 200 mm line is a fragment (a pierce for a stub); 15 mm cuts over the bars of a
    grid, where the line lies on metal 16 mm at a time, are whole: the paint is as short."""
    line = np.column_stack([np.linspace(0, 0.2, 201), np.zeros(201), np.zeros(201)])
    assert cut_accuracy([line], [line[:11], line[50:]])["fragments"] == 1
    bars = [np.column_stack([np.arange(x, x + 0.016, 0.001), np.zeros(16), np.zeros(16)]) for x in (0.0, 0.05, 0.1, 0.15)]
    painted = np.vstack([b + [0.0, dy, 0.0] for b in bars for dy in (-0.004, 0.0, 0.004)])
    a = cut_accuracy([line], [b[:15] for b in bars], painted=painted)
    assert a["fragments"] == 0 and a["line_on_metal_m"] == pytest.approx(0.08, abs=0.01)  # 3 mm each side
    assert cut_accuracy([line], [b[:15] for b in bars])["fragments"] == 4  # the same cuts on a plate


# ----------------------------------------------------------------------------- topology
@pytest.mark.parametrize("segments, strokes", [
    ([((0.3, -0.15), (0.6, 0.15)), ((0.3, 0.15), (0.6, -0.15))], [0.42, 0.42]),  # a crossing: two straight cuts
    ([((0.3, 0.0), (0.6, 0.0)), ((0.45, 0.0), (0.45, 0.2))], [0.30, 0.19]),  # a T: the bar in one cut, the stem
    ([((0.3, -0.15), (0.55, 0.0)), ((0.55, 0.0), (0.3, 0.1))], [0.55]),  # an acute corner: one cut, no spurs
    # two lines crossing at 30 deg: the thinned X has two junctions 10 cm apart, still two straight cuts
    ([((0.3, -0.1), (0.6, 0.1)), ((0.3, -0.0097), (0.6, 0.0097))], None),
    # an H: its 8 cm crossbar joins two T junctions and is cut too
    ([((0.35, -0.15), (0.35, 0.15)), ((0.43, -0.15), (0.43, 0.15)), ((0.35, 0.0), (0.43, 0.0))], [0.30, 0.30, 0.06]),
])
def test_strokes_go_through_junctions_and_round_corners(segments, strokes):
    g = np.mgrid[0.25:0.65:0.002, -0.25:0.25:0.002].reshape(2, -1).T
    surf = np.column_stack([g, np.full(len(g), 0.1)])
    paint = np.zeros(len(g), bool)
    for a, b in segments:
        a, b = np.asarray(a), np.asarray(b)
        t = np.clip((g - a) @ (b - a) / np.dot(b - a, b - a), 0, 1)
        paint |= np.linalg.norm(g - a - t[:, None] * (b - a), axis=1) <= 0.01
    path = build_cut_path(surf[paint], surf, CFG, viewpoint=np.array([0.45, 0.0, 0.6]))
    lengths = sorted((b.length_m for b in path.branches), reverse=True)
    if strokes is None:  # the strokes are the segments themselves
        strokes = [float(np.linalg.norm(np.subtract(b, a))) for a, b in segments]
    assert len(lengths) == len(strokes)
    np.testing.assert_allclose(lengths, sorted(strokes, reverse=True), atol=0.03)
    truth = [np.array([[*a, 0.1], [*b, 0.1]]) for a, b in segments]
    acc = cut_accuracy(truth, [b.points for b in path.branches])
    assert acc["path_to_line_max_mm"] <= 5.0 and acc["cut_coverage"] >= 0.9, acc


# ------------------------------------------------------------------ the cut follows the paint (3)
def _plate(x=(0.25, 0.65), y=(-0.2, 0.2), z=0.1, step=0.002):
    g = np.mgrid[x[0]:x[1]:step, y[0]:y[1]:step].reshape(2, -1).T
    return np.column_stack([g, np.full(len(g), z)])


def _cloud(xyz, eyes):
    from planners.clouds import Cloud

    xyz = np.asarray(xyz, np.float32)
    return Cloud(xyz, np.zeros(xyz.shape, np.uint8), np.broadcast_to(np.asarray(eyes, np.float32), xyz.shape).copy())


def _band(points, a, b, width=0.02):
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = points - a
    t = np.clip(d @ (b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return np.linalg.norm(d - t[:, None] * (b - a), axis=1) <= width / 2


def test_a_stroke_ends_at_its_caps_centre_and_a_line_off_an_edge_at_the_edge():
    """A sprayed stroke ends in round caps half its width beyond the line the worker drew: the cut
    ends at the caps' centres, within 2 mm of the drawn ends, not in the caps. A line that runs off
    the plate ends where the metal does."""
    surf = _plate()
    eye = [0.45, 0.0, 0.6]
    a, b = np.array([0.33, -0.05, 0.1]), np.array([0.55, 0.06, 0.1])
    path = build_cut_path(_cloud(surf[_band(surf, a, b)], eye), _cloud(surf, eye), CFG)
    assert len(path.branches) == 1
    p = path.branches[0].points
    ends = sorted([p[0], p[-1]], key=lambda e: e[0])
    assert np.linalg.norm(ends[0] - a) < 0.002 and np.linalg.norm(ends[1] - b) < 0.002
    off = _band(surf, [0.45, 0.0, 0.1], [0.75, 0.0, 0.1])  # clipped by the plate's edge at x = 0.65
    p = build_cut_path(_cloud(surf[off], eye), _cloud(surf, eye), CFG).branches[0].points
    assert max(p[0, 0], p[-1, 0]) > 0.645 and min(p[0, 0], p[-1, 0]) == pytest.approx(0.45, abs=0.002)


def test_an_end_cap_trims_only_the_line_s_last_stretch():
    """A U-shaped stroke whose skeleton runs 8 mm into the cap at one end: trimming takes back
    what lies beyond the cap's centre near that end, not the far leg of the U, which also lies
    "beyond" it along the end's direction."""
    from scipy.spatial import cKDTree

    from planners.cutpath.geometry import end_caps

    th = np.linspace(np.pi, 0.0, 40)
    up = np.column_stack([np.zeros(29), np.linspace(-0.04, 0.1, 29)])  # the far leg is the longer
    arc = np.column_stack([0.03 + 0.03 * np.cos(th), 0.1 + 0.03 * np.sin(th)])
    down = np.column_stack([np.full(21, 0.06), np.linspace(0.1, 0.0, 21)])
    line = np.vstack([up, arc[1:], down[1:]])
    line3 = np.column_stack([line, np.zeros(len(line))])
    surf = _plate(x=(-0.05, 0.11), y=(-0.06, 0.16), z=0.0)
    d = np.linalg.norm(surf[:, None, :2] - line[None], axis=2).min(axis=1)
    paint = surf[d <= 0.01]  # a 2 cm band with round caps at (0, -0.04) and (0.06, 0)
    skeleton = np.vstack([line3, [[0.06, -0.008, 0.0]]])  # into the cap at the end
    out = end_caps(skeleton, paint, cKDTree(surf), 0.01, 0.005, start=False)
    kept = arc_length(skeleton) < arc_length(skeleton)[-1] - 0.04  # before the last two band widths
    np.testing.assert_allclose(out[:kept.sum()], skeleton[kept])
    assert len(out) >= len(line3) - 2, "the far leg is kept"
    assert np.linalg.norm(out[-1] - [0.06, 0.0, 0.0]) < 0.0015
    assert np.linalg.norm(out[:, None, :2] - line[None], axis=2).min(axis=1).max() < 0.001, "on the drawn line"


def test_a_line_over_a_raised_rim_keeps_going_forward():
    """A line over a step 60 mm high and 50 mm wide (a collar on a pipe): four corners close
    together. Each corner is rebuilt from its own two sides; fitted across the next corner it
    landed 35 mm along the line and the cut went back and forth there."""
    x0, h, w = 0.45, 0.06, 0.025
    u = np.arange(0.40, 0.50, 0.002)
    base = _plate(x=(0.40, 0.50), y=(-0.2, 0.2))
    base = base[np.abs(base[:, 1]) > w]
    zs = np.arange(0.1, 0.1 + h, 0.002)
    U, Z = np.meshgrid(u, zs)
    near = np.column_stack([U.ravel(), np.full(U.size, -w), Z.ravel()])
    far = near * [1, -1, 1]
    U, Y = np.meshgrid(u, np.arange(-w, w + 1e-9, 0.002))
    rim = np.column_stack([U.ravel(), Y.ravel(), np.full(U.size, 0.1 + h)])
    parts = [base, near, far, rim]
    eyes = [[0.45, 0.0, 0.7], [0.45, -0.5, 0.13], [0.45, 0.5, 0.13], [0.45, 0.0, 0.7]]
    surf = np.vstack(parts)
    origin = np.vstack([np.tile(e, (len(q), 1)) for q, e in zip(parts, eyes)])
    from planners.clouds import Cloud

    def cl(m):
        return Cloud(surf[m].astype(np.float32), np.zeros((m.sum(), 3), np.uint8), origin[m].astype(np.float32))

    paint = (np.abs(surf[:, 0] - x0) <= 0.01) & (np.abs(surf[:, 1]) <= 0.15)
    path = build_cut_path(cl(paint), cl(np.ones(len(surf), bool)), CFG)
    assert len(path.branches) == 1
    p = path.branches[0].points
    p = p if p[-1, 1] > p[0, 1] else p[::-1]
    assert np.diff(p[:, 1]).min() > -0.001, "the cut never goes back along the line"
    assert np.abs(p[:, 0] - x0).max() < 0.003
    length = 0.3 - 2 * 0.01 + 2 * h  # from cap centre to cap centre, up and down the step
    assert path.branches[0].length_m == pytest.approx(length, abs=0.015)


def test_paint_round_a_thin_bar_is_no_loop_and_crosses_each_bar_along_the_line():
    """Paint wrapped round 8 mm bars (a basket's rods) is not a loop anyone drew: a ring narrower
    than its band would have its hole painted over. Each bar gets a short cut along the line,
    over the bar's top."""
    from planners.cutpath.geometry import painted_over

    th = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring = np.column_stack([np.zeros(24), 0.005 * np.cos(th), 0.005 * np.sin(th)])
    rng = np.random.default_rng(2)
    a, x = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(-0.01, 0.01, 4000)
    wrapped = np.column_stack([x, 0.004 * np.cos(a), 0.004 * np.sin(a)])  # 20 mm of paint along the bar
    assert painted_over(ring, wrapped, 0.005)
    big = 0.06 * np.column_stack([np.cos(th), np.sin(th), np.zeros(24)])
    r = rng.uniform(0.05, 0.07, 20000)
    b = rng.uniform(0, 2 * np.pi, 20000)
    assert not painted_over(big, np.column_stack([r * np.cos(b), r * np.sin(b), np.zeros(20000)]), 0.005)

    rc, rr = 0.2, 0.008  # catalog.basket: rods on a half cylinder, the line round it over 13 of them
    rods = []
    for ang in np.radians(np.arange(-72, 73, 12)):
        c = np.array([0.0, rc * np.sin(ang), rc * np.cos(ang)])
        phi, x = rng.uniform(ang - np.pi / 2, ang + np.pi / 2, 3000), rng.uniform(-0.06, 0.06, 3000)
        rods.append(c + np.column_stack([x, rr * np.sin(phi), rr * np.cos(phi)]))  # the outer half: what is seen
    surf = np.vstack(rods)
    out = surf * [0, 1, 1]
    eye = surf + 0.4 * out / np.linalg.norm(out, axis=1, keepdims=True)
    psi = np.arctan2(surf[:, 1], surf[:, 2])
    m = np.abs(surf[:, 0] - 0.02 * psi) <= 0.0125
    from planners.clouds import Cloud

    def cl(k):
        return Cloud(surf[k].astype(np.float32), np.zeros((k.sum(), 3), np.uint8), eye[k].astype(np.float32))

    path = build_cut_path(cl(m), cl(np.ones(len(surf), bool)), CFG)
    assert not any(b.closed for b in path.branches)
    assert len(path.branches) == 13
    for b in path.branches:
        c = b.points
        psi = np.arctan2(c[:, 1], c[:, 2])
        assert np.abs(c[:, 0] - 0.02 * psi).max() < 0.003, "each cut runs along the line, across its rod"


def test_a_bubble_of_paint_round_a_rim_is_one_stroke():
    """Paint sprayed over the 12 mm rim of an I-beam's flange (a twin scan, i_beam seed 0, the
    drawing cloud within 6 cm of the rim, tests/data): thinning makes two branches between two
    junctions round the rim, a cycle narrower than its band of paint. The longer goes; the line
    stays one stroke from end to end instead of three strokes and a 16 mm cut 5 mm off the line."""
    from planners.cutpath.graph import drawing_graph, through_junctions

    paint = np.load(os.path.join(os.path.dirname(__file__), "data", "i_beam_rim_paint.npz"))["paint"].astype(float)
    g = drawing_graph(paint, 0.005, 0.03, 1, surface=paint)
    assert "junction" not in g.kinds and len(g.branches) == 1
    assert len(through_junctions(g)) == 1


def test_a_collision_gap_says_what_blocks_the_torch(kin):
    """The middle of a line lies under a slab the arm cannot pass (a test collision check that names
    what it hits): the gap left there is a collision, its detail names the blocker, not 'out of reach'."""
    from planners.cutpath.model import Branch

    pts, normals, poses, times = straight([0.45, -0.10], [0.45, 0.10])

    def blocked(Q):
        tip = kin.fk_batch(Q)[:, :3, 3]
        return np.abs(tip[:, 1]) < 0.03

    asked = []

    def explain(Q):
        asked.append(len(Q))
        return ["the arm against the test slab" if b else None for b in blocked(Q)]

    path = CutPath([Branch(pts, normals, poses, np.full(len(pts), CFG.travel_speed_mps), "a", "b")],
                   np.zeros((0, 3)), np.zeros((0, 3)), CFG.model_dump(mode="json"))
    plan_cut(path, kin, PANDA_Q_READY, CFG, is_free=lambda Q: ~blocked(Q), explain=explain)
    gaps = [g for g in path.gaps if g.length_m > 0]
    assert len(gaps) == 1 and gaps[0].reason == COLLISION, gaps
    assert "the arm against the test slab" in gaps[0].detail and asked and max(asked) <= 8, gaps[0].detail
    assert 0.05 <= gaps[0].length_m <= 0.07 and len(path.branches) == 2


def test_centring_on_paint_none_of_which_is_on_the_face_leaves_the_line():
    """Found by `cellctl bench --appearance` (white on mill scale, an I-beam): paint beside the line but all of
    it off the surface's plane by more than a third of its half width (depth noise on a thin band) left no
    paint to centre on, and numpy's bincount of nothing is int64: the cut planning crashed."""
    x = np.linspace(0, 0.2, 41)
    line = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    rng = np.random.default_rng(0)
    px = rng.uniform(0, 0.2, 2000)
    paint = np.column_stack([px, rng.uniform(-0.002, 0.002, 2000), np.full_like(px, 0.002)])
    out = center_on_paint(line, paint, 0.005, normals=np.tile([0, 0, 1.0], (len(line), 1)))
    assert np.allclose(out, line)


@pytest.mark.parametrize("over", ["metal", "air"])
def test_a_dash_s_end_stops_where_its_paint_does(over):
    """Two dashes on one line with bare metal between their paint: the first dash's end stays at its
    cap's centre, where the cut of that dash ends; carried on to the paint of the next dash it ran over
    metal nobody marked (scrap:0:91, a dashed pipe: the flame 31 mm off the line, the oracle's cut too).
    A gap over air (between a grid's bars) is no end of the line: it goes on towards the next bar."""
    from scipy.spatial import cKDTree

    from planners.cutpath.geometry import end_caps

    half, gap = 0.013, 0.012  # paint 12 mm apart: within the end's reach
    start2 = 0.04 + 2 * half + gap
    surf = _plate(x=(-0.05, 0.2), y=(-0.05, 0.05), z=0.0)
    if over == "air":
        surf = surf[(surf[:, 0] < 0.04 + half) | (surf[:, 0] > start2 - half)]
    d1 = np.hypot(np.clip(surf[:, 0], 0.0, 0.04) - surf[:, 0], surf[:, 1])
    d2 = np.hypot(np.clip(surf[:, 0], start2, start2 + 0.04) - surf[:, 0], surf[:, 1])
    paint = surf[(d1 <= half) | (d2 <= half)]
    skeleton = np.column_stack([np.arange(0.0, 0.031, 0.005), np.zeros(7), np.zeros(7)])  # short of its cap
    out = end_caps(skeleton, paint, cKDTree(surf), half, 0.005, start=False)
    if over == "metal":
        assert abs(out[-1, 0] - 0.04) < 0.002, out[-1]
    else:
        assert out[-1, 0] > 0.04 + half, out[-1]


def test_a_line_over_a_bar_s_edge_runs_to_the_edge_though_metal_lies_beyond():
    """A line across a 30 mm bar, its paint cut square by the bar's edges, the next bar 15 mm on: the
    paint stops with the metal, so the cut runs to the edge. Only a round end is a sprayed cap whose
    centre the cut stops at; taking the next bar for the metal going on trimmed the cuts across a
    basket's bars by half a width each (scrap:0:14: 89 -> 74 % of the line)."""
    from scipy.spatial import cKDTree

    from planners.cutpath.geometry import end_caps

    half = 0.01
    surf = np.vstack([_plate(x=(0.0, 0.03), y=(-0.1, 0.1), z=0.0), _plate(x=(0.045, 0.075), y=(-0.1, 0.1), z=0.0)])
    paint = surf[(np.abs(surf[:, 1]) <= half) & (surf[:, 0] <= 0.03)]
    skeleton = np.column_stack([np.arange(0.0, 0.021, 0.005), np.zeros(5), np.zeros(5)])
    normals = np.tile([0.0, 0.0, 1.0], (len(skeleton), 1))
    out = end_caps(skeleton, paint, cKDTree(surf), half, 0.005, start=False, normals=normals)
    assert abs(out[-1, 0] - 0.03) < 0.002, out[-1]


def test_the_nozzle_keeps_off_the_table_the_scan_left_out():
    """The torch's working end, tilted down beside a piece, with no scanned point near it: clear of the
    surface, but its balls reach below the table's plane, which the arm's floor test leaves to it."""
    far = np.array([[1.0, 1.0, 1.0]])  # the scan's surface nowhere near
    axis = np.array([[0.0, 0.0, -1.0]])
    check = NozzleCheck(far, CFG.torch, CFG.nozzle_margin_m, floor_z=0.0)
    high, low = np.array([[0.4, 0.0, 0.05]]), np.array([[0.4, 0.0, 0.001]])
    assert check(high, axis).all() and not check(low, axis).any()
    tilted = np.array([[np.sin(1.2), 0.0, -np.cos(1.2)]])  # lying nearly flat: its side reaches the table
    assert not check(np.array([[0.4, 0.0, 0.004]]), tilted).any()  # the nozzle rim 1.6 mm below the table
    assert check(np.array([[0.4, 0.0, 0.03]]), tilted).all()
    assert NozzleCheck(far, CFG.torch, CFG.nozzle_margin_m)(low, axis).all(), "no floor given: none checked"
