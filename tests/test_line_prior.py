"""Where the unseen line most likely lies on a cylinder, and which views would image it."""

from __future__ import annotations

import numpy as np

from planners.config import GridConfig, PlannersConfig
from planners.cutpath.geometry import Surface
from planners.grid import OccupancyGrid
from planners.line_prior import MIN_INLIERS, LinePrior, fit_cylinder, line_prior, seen_counts
from planners.views import look_at_rotations

R_PIPE = 0.12
AXIS_X, AXIS_Z = 0.45, 0.12  # the pipe lies along y
K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
SIZE = (320, 240)


def _pipe(theta_deg: tuple[float, float], y: tuple[float, float], step: float = 0.004, noise: float = 0.0, seed: int = 0):
    """Points of the pipe's surface (theta from +z toward +x) and their angles and y."""
    th = np.radians(np.arange(theta_deg[0], theta_deg[1] + 1e-9, np.degrees(step / R_PIPE)))
    yy = np.arange(y[0], y[1] + 1e-9, step)
    T, Y = np.meshgrid(th, yy, indexing="ij")
    r = R_PIPE + np.random.default_rng(seed).normal(0.0, noise, T.size)
    pts = np.column_stack([AXIS_X + r * np.sin(T.ravel()), Y.ravel(), AXIS_Z + r * np.cos(T.ravel())])
    return pts, T.ravel(), Y.ravel()


def _line_theta(y):
    """The painted line: a gentle helix, 40 deg of turn over 0.5 m."""
    return np.radians(-20.0 + 80.0 * (np.asarray(y) + 0.3))


def test_a_noisy_pipe_fits_its_cylinder_and_an_angle_bracket_does_not():
    pts, _, _ = _pipe((-60, 60), (-0.2, 0.1), noise=0.001)
    eye = np.tile([AXIS_X, 0.0, 0.6], (len(pts), 1))
    cyl, share = fit_cylinder(pts, Surface(pts, eye, None, 0.01).normals(pts))
    assert share >= MIN_INLIERS
    assert abs(cyl.radius - R_PIPE) < 0.005
    assert abs(cyl.axis[1]) > np.cos(np.radians(3.0))
    a = np.arange(0.0, 0.2, 0.004)
    A, B = np.meshgrid(a, np.arange(-0.1, 0.1, 0.004), indexing="ij")
    bracket = np.vstack([np.column_stack([A.ravel(), B.ravel(), np.zeros(A.size)]),  # an angle: two plates
                         np.column_stack([np.zeros(A.size), B.ravel(), A.ravel()])])
    eye = np.tile([0.3, 0.0, 0.3], (len(bracket), 1))
    _, share = fit_cylinder(bracket, Surface(bracket, eye, None, 0.01).normals(bracket))
    assert share < MIN_INLIERS


def _pipe_state(seen_to_y: float = 0.0):
    """The pipe seen from above for y in [-0.3, seen_to_y], its line painted on it; the rest of
    the pipe unknown to the grid."""
    from painted_state import painted_state

    cfg = PlannersConfig()
    grid = OccupancyGrid(cfg.grid)
    cam = np.array([AXIS_X, -0.15, 0.6])
    pts, th, y = _pipe((-60, 60), (-0.3, seen_to_y), step=0.003)
    grid.integrate(cam, pts.astype(np.float32))
    paint = np.abs(R_PIPE * (th - _line_theta(y))) <= 0.01
    return cfg, painted_state(grid, pts, paint, cam, np.array([AXIS_X, -0.15, AXIS_Z + R_PIPE]), K, SIZE)


def test_the_line_goes_on_along_its_helix_into_the_unknown():
    """Past the seen end (y = 0) the prior follows the helix on the fitted pipe, in unknown cells;
    past the other end too, as far as the grid is unknown there."""
    _, state = _pipe_state()
    prior = line_prior(state.drawing.xyz, state.surface.xyz, state.surface.origin, state.grid, 0.2)
    assert prior is not None and prior.inliers >= MIN_INLIERS
    ahead = prior.xyz[:, 1] > 0.01
    assert ahead.sum() >= 20, "the continuation past the seen end"
    p = prior.xyz[ahead]
    th = np.arctan2(p[:, 0] - AXIS_X, p[:, 2] - AXIS_Z)
    assert np.all(np.abs(np.hypot(p[:, 0] - AXIS_X, p[:, 2] - AXIS_Z) - R_PIPE) < 0.01), "on the pipe"
    assert np.all(np.abs(R_PIPE * (th - _line_theta(p[:, 1]))) < 0.015), "on the helix"
    radial = np.column_stack([np.sin(th), np.zeros(len(th)), np.cos(th)])
    assert np.all(np.einsum("ij,ij->i", prior.normals[ahead], radial) > 0.99), "outward normals"
    ijk, _ = state.grid.index_of(prior.xyz)
    assert state.grid.unknown[tuple(ijk.T)].all()


def test_the_prior_ends_where_a_seen_surface_shows_no_paint():
    """A plate seen across the way on, without paint: the line did not go on through it."""
    _, state = _pipe_state()
    grid = state.grid
    wall = np.array([[x, 0.08, z] for x in np.arange(0.3, 0.6, 0.005) for z in np.arange(0.1, 0.35, 0.005)])
    grid.integrate(np.array([0.45, 0.3, 0.3]), wall.astype(np.float32))
    prior = line_prior(state.drawing.xyz, state.surface.xyz, state.surface.origin, grid, 0.2)
    assert prior is not None
    assert prior.xyz[:, 1].max() < 0.08, "nothing past the plate"
    assert (prior.xyz[:, 1] > 0.01).sum() >= 3, "the way up to it still counts (less the cells just behind the plate)"


def test_seen_counts_need_the_frame_a_square_enough_look_and_a_clear_line_of_sight():
    grid = OccupancyGrid(GridConfig(lo_m=(0, 0, 0), hi_m=(0.6, 0.6, 0.6), voxel_m=0.01))
    pts = np.array([[0.3 + dx, 0.3, 0.1] for dx in np.arange(-0.02, 0.021, 0.005)])
    prior = LinePrior(pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1)), 1.0, 0.005)
    eyes = np.array([[0.3, 0.3, 0.45],    # above, looking down: all
                     [0.3, 0.3, 0.45],    # the same place looking away: none
                     [0.3, 0.69, 0.13],   # 85 deg off the normal: none
                     [0.3, 0.3, 0.45]])   # above, with a plate in between (added below): none
    aims = np.array([[0.3, 0.3, 0.1], [0.3, 0.3, 0.6], [0.3, 0.3, 0.1], [0.3, 0.3, 0.1]])
    R = look_at_rotations(eyes, aims)
    flat = np.zeros(int(np.prod(grid.shape)), dtype=np.uint8)
    counts = seen_counts(eyes[:3], R[:3], prior, K, SIZE, 0.8, 60.0, grid, flat)
    assert counts.tolist() == [len(pts), 0, 0]
    occ = np.zeros(grid.shape, dtype=bool)
    occ[20:40, 20:40, 25] = True  # a plate at z = 0.25
    assert seen_counts(eyes[3:], R[3:], prior, K, SIZE, 0.8, 60.0, grid, occ.reshape(-1).view(np.uint8))[0] == 0


def _first_view_share(on: bool) -> float:
    """Share of the true line's next 15 cm past the seen end that G-NBV's first choice would image
    (in frame, within range and 60 deg of its normal)."""
    from planners.gnbv import GuidedNBV

    cfg, state = _pipe_state()
    cfg = cfg.model_copy(update={"nbv": cfg.nbv.model_copy(update={"line_prior_m": 0.2 if on else 0.0})})
    plan = GuidedNBV(cfg).next_view(state)
    assert not plan.stop
    y = np.arange(0.005, 0.15, 0.005)
    th = _line_theta(y)
    true = np.column_stack([AXIS_X + R_PIPE * np.sin(th), y, AXIS_Z + R_PIPE * np.cos(th)])
    truth = LinePrior(true, np.column_stack([np.sin(th), np.zeros(len(th)), np.cos(th)]), 1.0, 0.005)
    T = plan.poses[0]
    flat = state.grid.occupied.reshape(-1).view(np.uint8)
    return seen_counts(T[None, :3, 3], T[None, :3, :3], truth, state.K, state.image_size, 0.8, 60.0,
                       state.grid, flat)[0] / len(true)


def test_gnbv_with_the_prior_frames_where_the_line_goes_on():
    print("share of the next 15 cm imaged: defaults", _first_view_share(False), "prior", _first_view_share(True))
    assert _first_view_share(True) >= 0.9
