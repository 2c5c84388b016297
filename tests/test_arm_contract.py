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
