"""The lazy roadmap for air moves (planners/motion/roadmap.py), on a joint space whose obstacles
are known exactly."""

from __future__ import annotations

import numpy as np

from planners.motion.roadmap import roadmap_route

LO, HI = np.array([-3.0, -3.0, -1.0]), np.array([3.0, 3.0, 1.0])


def wall(Q: np.ndarray) -> np.ndarray:
    """Free unless in the slab |x| < 0.3 with y > -1.5: the only way past is round its end."""
    Q = np.atleast_2d(Q)
    return ~((np.abs(Q[:, 0]) < 0.3) & (Q[:, 1] > -1.5))


def straight(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = int(np.ceil(np.abs(b - a).max() / 0.02)) + 1
    return a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)


def test_a_route_round_the_wall_whose_every_motion_is_clear():
    a, b = np.array([-2.0, 1.0, 0.0]), np.array([2.0, 1.0, 0.0])
    assert not wall(straight(a, b)).all()
    route = roadmap_route(a, b, wall, straight, LO, HI)
    assert route is not None
    np.testing.assert_array_equal(route[0], a)
    np.testing.assert_array_equal(route[-1], b)
    assert all(wall(straight(u, v)).all() for u, v in zip(route[:-1], route[1:]))
    assert min(q[1] for q in route) < -1.5, "it goes round the end of the wall"
    assert len(route) <= 6, "the route is shortened to a few waypoints"
    again = roadmap_route(a, b, wall, straight, LO, HI)
    assert all(np.array_equal(u, v) for u, v in zip(route, again)), "same inputs, same route"


def test_no_route_to_a_goal_that_is_walled_in():
    def box(Q):
        Q = np.atleast_2d(Q)
        ring = (np.abs(Q[:, :2] - 2.0).max(axis=1) < 0.6) & (np.abs(Q[:, :2] - 2.0).max(axis=1) > 0.4)
        return ~ring

    assert roadmap_route(np.array([-2.0, -2.0, 0.0]), np.array([2.0, 2.0, 0.0]), box, straight, LO, HI) is None


def test_a_motion_the_caller_cannot_make_is_never_taken():
    a, b = np.array([-2.0, 1.0, 0.0]), np.array([2.0, 1.0, 0.0])

    def only_low(u, v):  # e.g. a motion that would leave the joint limits: no samples, not taken
        return None if max(u[1], v[1]) > 2.0 else straight(u, v)

    route = roadmap_route(a, b, wall, only_low, LO, HI)
    assert route is not None and all(q[1] <= 2.0 for q in route)
