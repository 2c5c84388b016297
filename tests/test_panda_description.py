"""configs/panda.py is the one description of the arm: it matches the URDF it names, and the
driver, the twin and the planners read it rather than their own copies."""

import xml.etree.ElementTree as ET

import numpy as np

from configs import panda


def test_the_description_matches_its_urdf():
    root = ET.parse(panda.PANDA_URDF).getroot()
    joints = {j.get("name"): j for j in root.iter("joint")}
    links = {link.get("name") for link in root.iter("link")}
    assert {panda.BASE_LINK, panda.FLANGE_LINK} <= links
    lims = np.array([[float(joints[n].find("limit").get(k)) for k in ("lower", "upper")] for n in panda.JOINT_NAMES])
    assert np.allclose(lims[:, 0], panda.PANDA_Q_MIN_URDF, atol=1e-4)
    assert np.allclose(lims[:, 1], panda.PANDA_Q_MAX_URDF, atol=1e-4)
    assert np.all(panda.PANDA_Q_MIN_URDF <= panda.PANDA_Q_MIN) and np.all(panda.PANDA_Q_MAX <= panda.PANDA_Q_MAX_URDF)
    assert np.all((panda.PANDA_Q_MIN < panda.PANDA_Q_READY) & (panda.PANDA_Q_READY < panda.PANDA_Q_MAX))
    assert not panda.PANDA_Q_MIN.flags.writeable


def test_driver_twin_and_planners_read_the_one_description():
    import drivers.panda.config as franka
    import planners.motion.limits as limits
    import sim.twin as twin

    for room in (franka, twin):
        assert (room.PANDA_URDF, room.JOINT_NAMES, room.BASE_LINK, room.FLANGE_LINK) == (
            panda.PANDA_URDF, panda.JOINT_NAMES, panda.BASE_LINK, panda.FLANGE_LINK)
    assert limits.PANDA_JOINT_NAMES is panda.JOINT_NAMES and limits.PANDA_Q_MIN is panda.PANDA_Q_MIN
    assert twin.MAX_VELOCITY is panda.PANDA_MAX_VELOCITY and twin.MAX_TORQUE is panda.PANDA_MAX_TORQUE


def test_driver_and_planners_move_the_arm_with_the_one_batched_fk():
    """configs/chain.py is the one batched forward kinematics: the Franka driver's safety checks and the
    planners' kinematics both use it, and it agrees with Pinocchio's own FK row by row."""
    import pytest
    from arm_contract import franky_config

    from configs.chain import Chain
    from drivers.panda import SafetyChecker
    from planners.motion.kinematics import Kinematics

    kin = Kinematics(panda.PANDA_URDF, panda.JOINT_NAMES, panda.FLANGE_LINK, np.eye(4))
    checker = SafetyChecker(franky_config("127.0.0.1"))
    assert isinstance(checker.kin, Chain) and all(isinstance(c, Chain) for c in kin._kernels.values())
    rng = np.random.default_rng(0)
    Q = rng.uniform(panda.PANDA_Q_MIN, panda.PANDA_Q_MAX, size=(64, 7))
    pinocchio_rows = np.stack([kin.fk(q, "flange") for q in Q])
    assert np.allclose(checker.flange_poses(Q), pinocchio_rows, atol=1e-9)
    assert np.allclose(kin.fk_batch(Q, "flange"), pinocchio_rows, atol=1e-9)
    with pytest.raises(ValueError, match="not in"):
        Chain.from_urdf(panda.PANDA_URDF, ("panda_joint1", "no_such_joint"), panda.FLANGE_LINK)
    with pytest.raises(ValueError, match="frame 'no_such_link' not in"):
        Chain.from_urdf(panda.PANDA_URDF, panda.JOINT_NAMES, "no_such_link")
