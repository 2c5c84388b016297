"""The cell's modes without a robot: the config refuses a mode without the devices it drives (naming the
field), a real cell whose robot does not answer starts anyway, reports itself not ready with the reason and
refuses jobs with `cell_not_ready` (a real `cellctl serve` on loopback, nothing mocked), and `cellctl
doctor` says what this machine lacks (no camera, no robot here).

Tests of: cellctl.config, cellctl.scan.modes, cellctl.scan.devices, cellctl.service.readiness,
cellctl.commissioning.doctor, configs.loading.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from arm_contract import free_loopback_address
from cellctl.service.client import CellError
from cellctl.config import load_cell_config
from cellctl.commissioning.doctor import UDEV_RULES, UDEV_RULES_ALTERNATIVES
from cellctl.service.loopback import ROOT, ServiceProcess
from configs import CONFIG_DIR
from planners.config import ConfigError

ARM = yaml.safe_load((CONFIG_DIR / "cell.real.yaml").read_text())["arm"]


def real_cell(host: str) -> dict:
    """configs/cell.real.yaml with the arm at ``host`` and a short connect timeout."""
    doc = yaml.safe_load((CONFIG_DIR / "cell.real.yaml").read_text())
    doc.pop("service")
    doc["arm"] = {**doc["arm"], "host": host, "connect_timeout_s": 1.0}
    return doc


@pytest.mark.parametrize("name", ["cell.sim.yaml", "cell.fcisim.yaml", "cell.real.yaml"])
def test_the_shipped_configs_load(name):
    cfg, _ = load_cell_config(CONFIG_DIR / name)
    assert cfg.mode == name.split(".")[1]
    assert (cfg.arm is None) == (cfg.mode == "sim") and (cfg.camera is None) == (cfg.mode != "real")


@pytest.mark.parametrize("doc, field", [
    ({"mode": "fcisim"}, "arm: mode fcisim needs an `arm:` block"),
    ({"mode": "real", "arm": ARM}, "camera: mode real needs a `camera:` block"),
    ({"mode": "real", "camera": {}}, "arm: mode real needs an `arm:` block"),
    ({"mode": "real", "arm": ARM, "camera": {"bag": "x.bag"}}, "camera.bag"),
    ({"mode": "fcisim", "arm": {**ARM, "realtime": False}}, "arm.model: franky-sim simulates an FR3"),
    ({"mode": "fcisim", "arm": {**ARM, "model": "fr3"}}, "arm.realtime: must be false"),
    ({"mode": "fcisim", "arm": {**ARM, "model": "fr3", "realtime": False}}, "arm.host: with fcisim.simulator "
                                                                            "embedded"),
    ({"mode": "robot"}, "mode: Input should be 'sim', 'fcisim' or 'real'"),
    ({"mode": "real", "arm": {**ARM, "host": "no host"}, "camera": {}}, "arm.host"),
    ({"mode": "real", "arm": ARM, "camera": {"fps": 7}}, "camera.fps"),
    ({"mode": "fcisim", "arm": {**ARM, "model": "fr3", "realtime": False, "host": "127.0.0.1"},
      "fcisim": {"simulator": "elsewhere"}}, "fcisim.simulator"),
])
def test_each_mode_needs_its_devices(tmp_path, doc, field):
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError) as e:
        load_cell_config(p)
    assert str(p) in str(e.value) and field in str(e.value), str(e.value)


def test_fcisim_with_an_external_simulator_may_point_anywhere(tmp_path):
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump({"mode": "fcisim", "fcisim": {"simulator": "external"},
                                 "arm": {**ARM, "model": "fr3", "realtime": False, "host": "10.0.0.7"}}))
    cfg, _ = load_cell_config(p)
    assert cfg.arm.host == "10.0.0.7"


def test_a_real_cell_without_a_robot_is_not_ready_and_refuses_jobs(tmp_path):
    host = free_loopback_address()  # nothing listens on 1337 there: what a controller with FCI off does
    svc = ServiceProcess(tmp_path, cell_id="real-1", cell=real_cell(host))
    svc.start(timeout_s=120)  # a liveness bound
    try:
        # the refused connection ends the probe at once (arm.connect_timeout_s 1 s bounds it in any case):
        # start-up never waits out libfranka's own 60 s handshake; idle it takes a few seconds of imports
        assert svc.startup_s < 60, svc.startup_s
        with svc.client() as c:
            st = c.status()
            assert st.mode == "real" and not st.ready and not st.arm_ready and not st.camera_ready, st
            assert f"Franka at {host}" in st.not_ready_reason and "FCI is not active" in st.not_ready_reason
            assert "no RealSense device found" in st.not_ready_reason, st.not_ready_reason
            assert st.accepting_jobs and st.devices.startswith("franky panda at")
            with pytest.raises(CellError) as e:
                c.submit({"scene": "smooth_cylinder", "max_steps": 2})
            assert e.value.code == "cell_not_ready" and "nothing was queued" in e.value.message
            assert "FCI is not active" in e.value.message
            listed = c.jobs()
            assert listed.total == 0 and listed.jobs == []
            again = c.status()  # still serving, still honest
            assert not again.ready and again.jobs_total == 0 and again.queue_length == 0
        # exits cleanly without waiting for a device probe in flight: close() would cap that wait at
        # 2 x connect_timeout_s + 15 s = 17 s; idle the exit takes well under a second
        rc, took = svc.stop(signal.SIGTERM, timeout_s=120)
        assert rc == 0 and took < 15, took
    finally:
        svc.kill()
    assert "not ready" in svc.log.read_text()


def _doctor(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cellctl.cli", "doctor", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)  # a liveness bound


def test_doctor_says_when_the_installed_libfranka_cannot_drive_the_configured_robot(tmp_path):
    """The installed franky's libfranka against arm.model: a Panda (FER) needs libfranka < 0.10, an FR3 >= 0.10;
    the other model is MISSING with the franky build to install."""
    from cellctl.commissioning.doctor import libfranka_version

    lf = libfranka_version()
    assert lf is not None
    other = "panda" if tuple(int(x) for x in lf.split(".")[:2]) >= (0, 10) else "fr3"
    doc = real_cell(free_loopback_address())
    doc["arm"]["model"] = other
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump(doc))
    out = _doctor("--config", str(p)).stdout
    line = next(ln for ln in out.splitlines() if ln.split()[1:2] == ["franky"])
    assert line.startswith("  MISSING") and f"arm.model is {other}" in line, out
    assert ("libfranka-0.9.2" if other == "panda" else "franky-control==2.0.0") in out


def test_doctor_says_what_is_missing_here(tmp_path):
    host = free_loopback_address()
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump(real_cell(host)))
    t0 = time.monotonic()
    run = _doctor("--config", str(p))
    took = time.monotonic() - t0
    out = run.stdout
    assert run.returncode == 1, (run.returncode, out, run.stderr)
    lines = {ln.split()[1]: ln for ln in out.splitlines() if ln.startswith("  ok") or ln.startswith("  MISSING")}
    assert lines["RealSense"].startswith("  MISSING") and "no RealSense device found" in out
    assert lines["robot"].startswith("  MISSING") and f"Franka at {host}" in out and "FCI is not active" in out
    assert "activate FCI" in out  # the fix
    assert "built with libfranka" in lines["franky"]
    lf = lines["franky"].split("built with libfranka ")[1].split()[0]
    fits_fr3 = tuple(int(x) for x in lf.split(".")[:2]) >= (0, 10)  # the FER (Panda) needs < 0.10, the FR3 >= 0.10
    assert lines["franky"].startswith("  ok" if fits_fr3 == (real_cell(host)["arm"]["model"] == "fr3") else
                                      "  MISSING"), lines["franky"]
    # this machine's own state, whatever it is, reported as such
    rules = UDEV_RULES.is_file() or any(r.is_file() for r in UDEV_RULES_ALTERNATIVES)
    assert lines["udev"].startswith("  ok" if rules else "  MISSING"), lines["udev"]
    if not rules:
        assert str(UDEV_RULES) in out and "udevadm control --reload-rules" in out
    assert "libusb" in lines
    if not Path("/sys/kernel/realtime").is_file():  # arm.realtime: true needs PREEMPT_RT
        assert "real-time" in lines and "PREEMPT_RT" in out
    assert out.rstrip().splitlines()[-1].startswith("not ready: ")
    # every probe is bounded by its timeout (the arm's 1 s here): the doctor never waits out libfranka's own
    # 60 s handshake; idle it takes a few seconds of imports
    assert took < 60, took


def test_doctor_refuses_an_invalid_config(tmp_path):
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump({"mode": "real"}))
    run = _doctor("--config", str(p))
    assert run.returncode == 2 and "arm: mode real needs an `arm:` block" in run.stderr, run.stderr


def test_the_twin_mirrors_joints_beyond_its_own_limits_and_refuses_junk():
    """fcisim renders from the FR3's measured joints, which may lie outside the Panda URDF's limits (joint 7
    up to 3.02 rad): the twin poses its robot there, and its camera pose is the arm model's."""
    import numpy as np

    from arm_contract import HOME_Q, _far_box_scene
    from cellctl.scan.fcisim import FrankySim
    from configs.chain import Chain
    from sim.config import TwinConfig
    from sim.twin import Twin

    q = HOME_Q.copy()
    q[6] = 2.95  # the FR3 allows it (3.0159), the Panda URDF stops at 2.8973
    with Twin(_far_box_scene(), TwinConfig()) as twin:
        assert twin.arm.mirror(q) == []
        assert np.allclose(twin.arm.joint_positions(), q)
        fk = Chain.from_urdf(twin.arm.model.urdf_path, twin.arm.model.joint_names, "panda_hand")
        assert np.allclose(twin.arm.camera_pose(), fk.poses(q[None])[0] @ twin.arm.model.T_flange_cam, atol=1e-6)
        for bad in (q[:6], np.full(7, np.nan), np.zeros((0, 7))):
            with pytest.raises(ValueError, match="mirror\\(\\) needs finite joint samples"):
                twin.arm.mirror(bad)
    with pytest.raises(ValueError, match="loopback"):
        FrankySim("10.0.0.2")
    with pytest.raises(ValueError, match="7 joint angles"):
        FrankySim("127.0.0.1", [0.0] * 6)


def test_a_module_being_imported_by_another_thread_counts_as_available(monkeypatch):
    """A status query while a job thread imports pybullet for the first time: the module sits in
    sys.modules without a spec, importlib's find_spec raises, and the service answered internal_error."""
    import importlib.util
    import sys
    import types

    from cellctl.scan.devices import module_available

    half = types.ModuleType("scrapcell_half_imported")
    half.__spec__ = None  # what a C extension's module looks like while its import runs
    monkeypatch.setitem(sys.modules, "scrapcell_half_imported", half)
    with pytest.raises(ValueError):
        importlib.util.find_spec("scrapcell_half_imported")
    assert module_available("scrapcell_half_imported")
    assert module_available("numpy")
    assert not module_available("scrapcell_no_such_module")


def test_a_setting_given_twice_is_refused_with_both_lines(tmp_path):
    """YAML keeps the last of two equal keys without a word: a cell ran unframed although its file
    said `framed_views: true` a line above `framed_views: false`."""
    text = (CONFIG_DIR / "cell.sim.yaml").read_text().replace("motion:\n", "motion:\n  framed_views: true\n", 1)
    p = tmp_path / "cell.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_cell_config(p)
    msg = str(e.value)
    first = text.splitlines().index("  framed_views: true") + 1
    assert str(p) in msg and "duplicate key 'framed_views'" in msg and f"line {first}" in msg, msg


def test_each_mode_is_one_class_that_the_config_the_api_and_the_devices_read():
    """cellctl.scan.modes is the one registry: the config's and the status's mode fields list its modes,
    each mode defines its own opening, readiness and description, and open_devices goes through it."""
    from typing import get_args

    from cellctl.config import CellConfig
    from cellctl.scan.devices import check_readiness, open_devices
    from cellctl.scan.modes import MODES, DeviceMode
    from cellctl.service.api import CellStatus
    from sim.config import TwinConfig
    from sim.scenes import load_scene

    assert list(MODES) == ["sim", "fcisim", "real"]
    assert set(get_args(CellConfig.model_fields["mode"].annotation)) == set(MODES)
    assert set(CellStatus.model_json_schema()["properties"]["mode"]["enum"]) == set(MODES)
    for mode in MODES.values():
        assert all(getattr(type(mode), f) is not getattr(DeviceMode, f) for f in ("open", "readiness", "describe"))
        assert mode.summary in CellStatus.model_fields["mode"].description
    cfg = CellConfig()
    assert check_readiness(cfg).ready
    with open_devices(cfg, load_scene("smooth_cylinder"), TwinConfig()) as dev:
        assert dev.mode == "sim" and dev.twin is not None and dev.description == MODES["sim"].describe(cfg)


def test_the_idle_probe_asks_the_controller_without_opening_a_libfranka_session():
    """The service probes an idle cell's arm every few seconds: that must not take the controller's one FCI
    session (nor set its collision behaviour, as every session of the adapter does). The full check is the
    job's own connection. franky-sim's protocol log shows what each probe did to the controller."""
    import logging

    from arm_contract import franky_config, franky_sim_server

    from drivers.panda import probe

    class Sessions(logging.Handler):
        count = 0

        def emit(self, record: logging.LogRecord) -> None:
            self.count += record.getMessage().startswith("Received SetCollisionBehavior")

    sessions = Sessions()
    proto = logging.getLogger("franky_sim.franka_robot_protocol")
    proto.addHandler(sessions)
    try:
        with franky_sim_server() as (_server, robot, _moves):
            cfg = franky_config(robot.hostname)
            cheap = probe(cfg, full=False)
            assert cheap.ready and "robot server version 10" in cheap.message, cheap
            assert sessions.count == 0
            full = probe(cfg)
            assert full.ready and "joints" in full.message, full
            assert sessions.count >= 1  # the full check opens a session: the count sees one
            wrong = probe(cfg.model_copy(update={"model": "panda"}), full=False)
            assert not wrong.ready and "so it is an FR3" in wrong.message
        gone = probe(cfg, full=False)
        assert not gone.ready and "FCI is not active" in gone.message
    finally:
        proto.removeHandler(sessions)
