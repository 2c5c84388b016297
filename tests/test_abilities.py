"""The arms' optional abilities (drivers.interfaces: Recoverable, ContactLog, MotionLog, EventLog,
MotionCounter): every arm and camera, and every wrapper, provides exactly the ones it should, checked
by isinstance and by the members themselves; a wrapper passes on only what the wrapped arm has; and the
scan code neither probes abilities with getattr nor hides what a wrapper forwards behind __getattr__."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from arm_contract import _far_box_scene, franky_config
from cellctl.scan.job import stop_and_recover
from drivers.interfaces import (ABILITY_FORWARDERS, Arm, ArmAbilities, ArmModel, ContactLog, EventLog,
                                JointTrajectory, MotionCounter, MotionLog, Recoverable, RGBDCamera)
from sim.faults import ArmFaults, FaultsConfig, FaultyArm, FaultyCamera

ROOT = Path(__file__).resolve().parents[1]
ABILITIES = tuple(ABILITY_FORWARDERS)
PROTOCOLS = (Arm, RGBDCamera, *ABILITIES)
TWIN_ARM = {Arm, ContactLog, MotionLog}
FRANKY_ARM = {Arm, Recoverable, EventLog, MotionLog, MotionCounter}


def members(protocol: type) -> set[str]:
    """The names a protocol asks for: its annotated attributes and its methods."""
    return set(protocol.__dict__.get("__annotations__", {})) | {
        n for n, v in vars(protocol).items() if callable(v) and not n.startswith("_")}


def provided(obj) -> set[type]:
    """The protocols ``obj`` satisfies, by isinstance; asserted to agree with the members it really has."""
    by_isinstance = {p for p in PROTOCOLS if isinstance(obj, p)}
    by_members = {p for p in PROTOCOLS if all(hasattr(obj, n) for n in members(p))}
    assert by_isinstance == by_members, (type(obj).__name__, by_isinstance ^ by_members)
    return by_isinstance


def test_the_ability_names_are_what_the_scan_uses():
    assert members(Recoverable) == {"needs_recovery", "recover"}
    assert members(ContactLog) == {"last_motion_contacts"}
    assert members(MotionLog) == {"last_motion_desired", "last_motion_actual"}
    assert members(EventLog) == {"events"}
    assert members(MotionCounter) == {"motions_sent"}


# ----------------------------------------------------------------------------- wrappers around stand-ins
class PlainArm:
    """Only the Arm protocol (and a stray ``needs_recovery`` without ``recover``: not Recoverable)."""

    def __init__(self) -> None:
        z = np.zeros(7)
        self.model = ArmModel("arm.urdf", "base", "flange", tuple(f"j{i}" for i in range(7)), z, z, z, z, z,
                              np.eye(4))
        self.needs_recovery = "a stray attribute"
        self.stopped = 0

    def joint_positions(self) -> np.ndarray:
        return np.zeros(7)

    def execute(self, trajectory: JointTrajectory) -> float:
        return 0.0

    def stop(self) -> None:
        self.stopped += 1

    def camera_pose(self) -> np.ndarray:
        return np.eye(4)


class RecoveringArm(PlainArm):
    """A Franka-like arm: it recovers and logs its events."""

    def __init__(self) -> None:
        super().__init__()
        self.needs_recovery = "reflex: joint_reflex"
        self.events: list[dict] = []

    def recover(self) -> dict:
        self.needs_recovery = None
        self.events.append({"kind": "recovered", "message": "after a reflex"})
        return self.events[-1]


def test_a_wrapper_around_an_arm_without_recovery_is_not_recoverable():
    plain = PlainArm()
    wrapped = FaultyArm(plain, ArmFaults())
    assert provided(plain) == {Arm} and provided(wrapped) == {Arm}
    assert ArmAbilities.of(wrapped) == ArmAbilities()
    assert not hasattr(wrapped, "needs_recovery")  # the stray attribute is not passed on either
    assert stop_and_recover(wrapped) == (True, []) and plain.stopped == 1 and plain.needs_recovery


def test_a_wrapper_around_a_recoverable_arm_recovers_it():
    arm = RecoveringArm()
    wrapped = FaultyArm(arm, ArmFaults())
    assert provided(wrapped) == {Arm, Recoverable, EventLog} and isinstance(wrapped, FaultyArm)
    assert wrapped.events is arm.events and wrapped.needs_recovery == arm.needs_recovery
    abilities = ArmAbilities.of(wrapped)
    assert abilities.recovery is wrapped and abilities.events is wrapped and abilities.contacts is None
    stopped, notes = stop_and_recover(wrapped, abilities)
    assert stopped and notes == [("arm_recovered", "after reflex: joint_reflex: after a reflex")], notes
    assert arm.needs_recovery is None and wrapped.needs_recovery is None and arm.stopped == 1
    # a wrapper of a wrapper passes on what the inner one passes on
    assert provided(FaultyArm(wrapped, ArmFaults())) == {Arm, Recoverable, EventLog}
    # the class picked for one arm does not lend its abilities to another arm
    again = type(wrapped)(PlainArm(), ArmFaults())
    assert provided(again) == {Arm} and isinstance(again, FaultyArm)


# ----------------------------------------------------------------------------- the twin and franky
@pytest.fixture(scope="module")
def faulty_twin():
    """A twin whose arm and camera are both wrapped (faults that never fire in these tests)."""
    from sim.config import D435Config, TwinConfig
    from sim.twin import Twin

    faults = FaultsConfig.model_validate({"arm": {"reflex_on_motion": [1000]}, "camera": {"drop_frames": [1000]}})
    camera = D435Config.model_validate({"width": 640, "height": 480, "hfov_deg": 55.0, "noise": False})
    with Twin(_far_box_scene(), TwinConfig(execution="teleport", faults=faults, camera=camera)) as twin:
        yield twin


def test_the_twin_and_its_faulty_wrappers_provide_exactly_the_twins_abilities(faulty_twin):
    from sim.twin import TwinArm, TwinCamera

    arm, camera = faulty_twin.arm, faulty_twin.camera
    assert isinstance(arm, FaultyArm) and type(arm._arm) is TwinArm
    assert isinstance(camera, FaultyCamera) and type(camera._camera) is TwinCamera
    assert provided(arm._arm) == TWIN_ARM and provided(arm) == TWIN_ARM
    assert provided(camera._camera) == {RGBDCamera} and provided(camera) == {RGBDCamera}
    # what the faulty arm passes on is the twin arm's, also after a motion
    q = arm.joint_positions()
    arm.execute(JointTrajectory(np.array([0.0, 0.5]), np.array([q, q + 0.05])))
    assert arm.last_motion_desired is arm._arm.last_motion_desired and len(arm.last_motion_desired) == 2
    assert arm.last_motion_actual is arm._arm.last_motion_actual
    assert arm.last_motion_contacts is arm._arm.last_motion_contacts
    assert arm.flange_index == arm._arm.flange_index
    assert np.array_equal(arm.joint_velocities(), arm._arm.joint_velocities())  # twin only, passed on
    arm.reset(q)
    assert np.allclose(arm.joint_positions(), q)
    assert arm.mirror(q + 0.01) == [] and np.allclose(arm.joint_positions(), q + 0.01)
    arm.reset(q)
    # the twin camera's extras, through the faulty camera
    T = arm.camera_pose()
    frame = camera.capture_at(T)
    assert np.array_equal(camera.last_truth, camera._camera.last_truth, equal_nan=True)
    assert np.array_equal(camera.render_truth(T), camera.last_truth, equal_nan=True)
    rgb, raw = camera.render(T)
    assert np.array_equal(rgb, frame.color) and np.array_equal(camera.K, camera.intrinsics.matrix())
    assert np.array_equal(camera.sensor_depth(raw), camera.last_truth, equal_nan=True)


def test_the_franky_adapter_and_the_fcisim_wrappers_provide_exactly_their_abilities(faulty_twin):
    pytest.importorskip("franky")
    from cellctl.scan.devices import MirroredCamera, TwinCheckedArm
    from drivers.panda.arm import FrankaArm

    franky = FrankaArm(franky_config("127.0.0.1"), connect=False)  # built, never connected
    assert provided(franky) == FRANKY_ARM
    checked = TwinCheckedArm(franky, faulty_twin.arm)
    assert provided(checked) == FRANKY_ARM | {ContactLog}
    assert checked.events is franky.events and checked.motions_sent == franky.motions_sent == 0
    assert checked.last_motion_actual is franky.last_motion_actual and checked.last_motion_contacts == []
    franky.needs_recovery = "reflex: test"
    assert checked.needs_recovery == "reflex: test"
    franky.needs_recovery = None
    abilities = ArmAbilities.of(checked)
    assert abilities == ArmAbilities(recovery=checked, contacts=checked, motion_log=checked, events=checked)
    # the twin check replays what the arm measured: an arm that keeps no count of its motions is refused
    with pytest.raises(TypeError, match="MotionCounter"):
        TwinCheckedArm(faulty_twin.arm, faulty_twin.arm)

    camera = MirroredCamera(faulty_twin.camera, faulty_twin.arm, faulty_twin.arm)
    assert provided(camera) == {RGBDCamera}
    camera.capture()
    assert np.array_equal(camera.last_truth, faulty_twin.camera.last_truth, equal_nan=True)


def test_the_live_and_recorded_cameras_declare_rgbd_camera():
    from drivers.realsense.bag import RealSenseBag
    from drivers.realsense.sensor import RealSenseCamera

    for cls in (RealSenseCamera, RealSenseBag):
        assert RGBDCamera in cls.__mro__ and "capture" in vars(cls), cls
        assert not any(p in cls.__mro__ for p in (Arm, *ABILITIES)), cls


# ----------------------------------------------------------------------------- no probing, no __getattr__
ABILITY_NAMES = set().union(*(members(p) for p in ABILITIES))
WRAPPER_MODULES = ("cellctl/scan/devices.py", "sim/faults.py")


def probes(source: str) -> list[str]:
    """``getattr``/``hasattr`` calls whose attribute name is a string literal naming an ability member."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr")
                and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                and node.args[1].value in ABILITY_NAMES):
            found.append(f"line {node.lineno}: {node.func.id}(..., {node.args[1].value!r})")
    return found


def dynamic_lookups(source: str) -> list[str]:
    """Classes that define ``__getattr__`` or ``__getattribute__``."""
    return [f"{node.name}.{f.name} (line {f.lineno})" for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.ClassDef) for f in node.body
            if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)) and f.name in ("__getattr__", "__getattribute__")]


def test_the_checkers_see_what_they_look_for():
    src = ("x = getattr(arm, 'needs_recovery', None)\n"
           "y = hasattr(arm, 'last_motion_contacts')\n"
           "z = getattr(branch, 'approach')\n"
           "class W:\n"
           "    def __getattr__(self, name):\n"
           "        return 1\n")
    assert probes(src) == ["line 1: getattr(..., 'needs_recovery')", "line 2: hasattr(..., 'last_motion_contacts')"]
    assert dynamic_lookups(src) == ["W.__getattr__ (line 5)"]


def test_the_scan_code_does_not_probe_abilities_with_getattr():
    files = sorted((ROOT / "cellctl" / "scan").rglob("*.py"))
    assert files
    bad = [f"{f.relative_to(ROOT)}: {p}" for f in files for p in probes(f.read_text())]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("module", WRAPPER_MODULES)
def test_the_wrappers_forward_explicitly(module):
    assert dynamic_lookups((ROOT / module).read_text()) == []
