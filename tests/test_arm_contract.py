"""The Arm contract (tests/arm_contract.py) on every implementation: the pybullet twin and the franky
adapter (drivers/panda) talking libfranka's protocol to franky-sim's MuJoCo FR3, embedded on a free
loopback address. Module-scoped: one twin, then one simulator + connection, for all cases."""

from __future__ import annotations

import pytest

from arm_contract import CASES, franky_under_test, twin_under_test

HARNESSES = {"twin": twin_under_test, "franky": franky_under_test}


@pytest.fixture(scope="module", params=list(HARNESSES))
def arm_under_test(request):
    with HARNESSES[request.param]() as h:
        yield h


@pytest.mark.parametrize("case", list(CASES))
def test_arm_contract(arm_under_test, case):
    CASES[case](arm_under_test)


def test_a_job_that_fails_on_an_arm_error_leaves_the_arm_stopped_and_recovered(arm_under_test):
    """What ScanJob does after any error (cellctl.scan.job.stop_and_recover): the arm is stopped, and a
    Franka that now refuses motions until recover_from_errors is recovered and the job records it, so
    the next job can move; the twin has nothing to recover."""
    import numpy as np

    from arm_contract import HOME_Q, run_in_thread, smooth_trajectory, wait_until_moving
    from cellctl.scan.job import stop_and_recover
    from drivers.interfaces import TrajectoryError

    h = arm_under_test
    arm = h.arm
    h.go_to(HOME_Q)
    th, out = run_in_thread(arm.execute, smooth_trajectory(HOME_Q, HOME_Q + np.array([0.3, 0, 0, 0.2, 0, 0, 0]), 4.0))
    wait_until_moving(arm, HOME_Q)
    h.fault(lambda: not th.is_alive())
    th.join(60.0)  # a liveness bound
    assert not th.is_alive() and isinstance(out[0], TrajectoryError), out
    stopped, notes = stop_and_recover(arm)
    assert stopped
    if hasattr(arm, "recover"):
        assert [k for k, _ in notes] == ["arm_recovered"], notes
        assert not arm.needs_recovery and arm.events[-1]["kind"] == "recovered"
    else:
        assert notes == []
    q = arm.joint_positions()
    assert arm.execute(smooth_trajectory(q, HOME_Q, 1.5)) < h.tracking_tolerance
