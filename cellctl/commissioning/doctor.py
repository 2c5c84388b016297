"""`cellctl doctor`: is this PC ready to drive the real cell? One line per check, what is missing and how
to fix it (docs/HARDWARE.md has the long form), exit status 0 when everything is ready, 1 otherwise.

Checks: libusb (Open3D's RealSense support loads it), the RealSense udev rules, the connected RealSense
cameras against the config's ``camera:`` block, which libfranka franky was built with (a Panda and an FR3
need different builds), a PREEMPT_RT kernel when ``arm.realtime`` is on, and the FCI host: reachable, FCI
active, the robot's model and kinematics (``drivers.panda.probe``, one libfranka connection), and the
yard network: the CA certificate the cell trusts and the router's certificate and name as it presents
them over TLS."""

from __future__ import annotations

import ctypes.util
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from cellctl.config import CellConfig
from cellctl.scan.modes import MODES

UDEV_RULES = Path("/etc/udev/rules.d/99-realsense-libusb.rules")
# the librealsense Debian package installs its rules here instead
UDEV_RULES_ALTERNATIVES = (Path("/lib/udev/rules.d/60-librealsense2-udev-rules.rules"),
                           Path("/usr/lib/udev/rules.d/60-librealsense2-udev-rules.rules"))
PANDA_FRANKY = ("pip install --force-reinstall franky-control==2.0.0 --extra-index-url "
                "https://timschneider42.github.io/franky/whl/libfranka-0.9.2/")


@dataclass
class Check:
    name: str
    ok: bool
    detail: str
    fix: str = ""


def check_libusb() -> Check:
    found = ctypes.util.find_library("usb-1.0")
    if found is None:
        try:
            out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, timeout=10).stdout
            found = next((ln.split("=>")[-1].strip() for ln in out.splitlines() if "libusb-1.0.so" in ln), None)
        except (OSError, subprocess.SubprocessError):
            pass
    if found:
        return Check("libusb", True, f"libusb-1.0 found ({found})")
    return Check("libusb", False, "libusb-1.0 is missing: Open3D cannot load its RealSense support",
                 "sudo apt-get install libusb-1.0-0 (`make setup` does it)")


def check_udev() -> Check:
    for p in (UDEV_RULES, *UDEV_RULES_ALTERNATIVES):
        if p.is_file():
            return Check("udev rules", True, f"{p}")
    return Check("udev rules", False, f"{UDEV_RULES} is missing: only root may open the D435 through libusb",
                 "copy 99-realsense-libusb.rules (librealsense's config/ folder) to /etc/udev/rules.d/, then "
                 "`sudo udevadm control --reload-rules && sudo udevadm trigger` and replug the camera "
                 "(docs/HARDWARE.md, Host setup)")


def check_realsense(cfg: CellConfig | None) -> Check:
    try:
        from drivers.realsense import check_devices, list_devices
        from drivers.realsense.config import RealSenseConfig

        devices = list_devices()
    except Exception as e:  # noqa: BLE001 - a broken Open3D/libusb install is a finding, not a crash
        return Check("RealSense", False, f"cannot enumerate RealSense devices: {type(e).__name__}: {e}",
                     "check libusb and the Open3D install (`make setup`)")
    listed = ", ".join(f"{d.name} {d.serial}" for d in devices) or "none"
    camera = cfg.camera if cfg is not None and cfg.camera is not None else RealSenseConfig()
    problems = check_devices(camera, devices)
    if problems:
        fix = ("plug the D435 into a USB3 port, check `lsusb` lists 8086:0b07, install the udev rules"
               if not devices else "set camera.serial or the camera modes to what the device offers")
        return Check("RealSense", False, f"connected: {listed}. " + "; ".join(problems), fix)
    return Check("RealSense", True, f"connected: {listed}; the configured modes are offered")


def libfranka_version() -> str | None:
    """The libfranka franky was built with: a version attribute of franky's module if it has one, else the
    version of the libfranka library bundled in the franky-control wheel (libfranka-<hash>.so.<version>)."""
    try:
        import franky
    except ImportError:
        return None
    for mod in (franky, getattr(franky, "_franky", None)):
        for attr in ("libfranka_version", "LIBFRANKA_VERSION", "__libfranka_version__"):
            v = getattr(mod, attr, None)
            if v:
                return str(v)
    from importlib import metadata

    try:
        files = metadata.distribution("franky-control").files or []
    except metadata.PackageNotFoundError:
        files = []
    for f in files:
        m = re.search(r"libfranka[^/]*\.so\.(\d+\.\d+(?:\.\d+)?)$", str(f))
        if m:
            return m.group(1)
    return None


def check_franky(cfg: CellConfig | None) -> Check:
    try:
        from importlib import metadata

        franky_version = metadata.version("franky-control")
    except Exception:  # noqa: BLE001
        return Check("franky", False, "franky (franky-control) is not installed", "pip install -e . (`make setup`)")
    lf = libfranka_version()
    if lf is None:
        return Check("franky", False, f"franky-control {franky_version}: cannot tell which libfranka it was built "
                                      f"with", "reinstall franky-control (docs/HARDWARE.md, libfranka versions)")
    speaks = "panda" if tuple(int(x) for x in lf.split(".")[:2]) < (0, 10) else "fr3"
    detail = (f"franky-control {franky_version} built with libfranka {lf} "
              f"({'Panda, system <= 4.2' if speaks == 'panda' else 'FR3 controllers'})")
    model = cfg.arm.model if cfg is not None and cfg.arm is not None else None
    if model is not None and model != speaks:
        fix = (PANDA_FRANKY if model == "panda" else
               "pip install --force-reinstall franky-control==2.0.0 (the PyPI wheel, libfranka 0.21.2)")
        return Check("franky", False, f"{detail}, but arm.model is {model}: libfranka would refuse the robot",
                     f"{fix} (docs/HARDWARE.md, libfranka versions)")
    return Check("franky", True, detail)


def check_realtime(cfg: CellConfig | None) -> Check | None:
    if cfg is None or cfg.arm is None or not cfg.arm.realtime:
        return None
    rt = Path("/sys/kernel/realtime")
    is_rt = (rt.is_file() and rt.read_text().strip() == "1") or "PREEMPT_RT" in os.uname().version
    if is_rt:
        return Check("real-time kernel", True, f"{os.uname().release} is PREEMPT_RT")
    return Check("real-time kernel", False, f"kernel {os.uname().release} is not PREEMPT_RT: libfranka refuses to "
                                            f"run with arm.realtime: true",
                 "install a PREEMPT_RT kernel and put the user in a group with rtprio 99 / memlock "
                 "(docs/HARDWARE.md, Robot, network and FCI)")


def check_robot(cfg: CellConfig | None, cfg_path: Path) -> Check:
    if cfg is None or cfg.arm is None:
        return Check("robot", False, f"{cfg_path} has no arm: block: the FCI host is unknown",
                     "use a real-mode config (configs/cell.real.yaml) with arm.host set")
    if MODES[cfg.mode].starts_simulator(cfg):
        return Check("robot", True, "fcisim: the cell starts franky-sim itself; no FCI host to reach")
    from drivers.panda import probe

    st = probe(cfg.arm)
    if st.ready:
        return Check("robot", True, st.message)
    msg = st.message
    if "unreachable" in msg:
        fix = (f"power the robot, connect this PC to the controller's FCI port with a static address in its "
               f"subnet, check arm.host ({cfg.arm.host}) in {cfg_path}")
    elif "FCI is not active" in msg:
        fix = "open Desk (https://<arm.host>), unlock the joints, release the enabling device, activate FCI"
    else:
        fix = "see docs/HARDWARE.md, Failures and recovery"
    return Check("robot", False, msg, fix)


def _configured_ca(cfg: CellConfig, cfg_dir: Path) -> Path | None:
    """service.tls_ca_file, else the root_ca_certificate of service.zenoh_config_file (what the cell uses)."""
    scfg = cfg.service
    if scfg.tls_ca_file:
        return scfg.tls_ca_path(cfg_dir)
    if scfg.zenoh_config_file:
        import zenoh

        from cellctl.tls import configured_ca

        try:
            ca = configured_ca(zenoh.Config.from_file(str(scfg.zenoh_config_path(cfg_dir))))
        except Exception:  # noqa: BLE001 - an unreadable file is reported by `cellctl serve`
            return None
        return Path(ca) if ca else None
    return None


def check_network(cfg: CellConfig | None, cfg_path: Path) -> Check | None:
    """The yard router listens on TLS only: the CA this cell trusts is there and in date, and each router
    endpoint presents a certificate that CA signed, in date, for the name the cell connects to."""
    from cellctl import tls

    if cfg is None or cfg.service.zenoh_mode != "client":
        return None
    eps = cfg.service.connect
    plain = [ep for ep in eps if not tls.is_tls(ep)]
    if plain:
        return Check("yard network", False, f"{', '.join(plain)}: plain TCP, yet the yard router listens on TLS only "
                     f"(and passwords would cross the network readable)",
                     f"connect to tls/<router-host>:7447 and set service.tls_ca_file in {cfg_path} (deploy/README.md)")
    ca = _configured_ca(cfg, cfg_path.parent)
    if ca is None:
        return Check("yard network", False, f"{', '.join(eps)} is TLS but no CA certificate is configured",
                     f"set service.tls_ca_file in {cfg_path} to the yard's ca.crt (deploy/make-certs.sh)")
    try:
        warnings = tls.check_ca(ca)
    except tls.CertificateError as e:
        return Check("yard network", False, str(e), "give the yard's current ca.crt (deploy/README.md, Certificates)")
    found = [tls.probe(ep, ca) for ep in eps]
    bad = [p for p in found if p.kind != "ok"]
    if bad:
        fix = "start the router (systemctl start scrapcell-router), check the address and the firewall" \
            if all(p.kind == "down" for p in bad) else "deploy/README.md, Certificates"
        return Check("yard network", False, "; ".join(p.message for p in bad), fix)
    warnings += [p.warning for p in found if p.warning]
    return Check("yard network", True, f"CA {ca}; " + "; ".join(f"{p.endpoint}: {p.message}" for p in found) +
                 "".join(f"; WARNING: {w}" for w in warnings))


def run_checks(cfg: CellConfig | None, cfg_path: Path) -> list[Check]:
    checks = [check_libusb(), check_udev(), check_realsense(cfg), check_franky(cfg), check_realtime(cfg),
              check_robot(cfg, cfg_path), check_network(cfg, cfg_path)]
    return [c for c in checks if c is not None]


def cli_doctor(args) -> int:
    from cellctl.config import load_cell_config
    from configs import CONFIG_DIR

    cfg_path = Path(args.config) if args.config else CONFIG_DIR / "cell.real.yaml"
    cfg, _ = load_cell_config(cfg_path)  # an invalid config: exit 2 with the field named (cellctl.cli)
    print(f"cellctl doctor: {cfg_path} (cell {cfg.cell_id}, mode {cfg.mode})")
    checks = run_checks(cfg, cfg_path)
    w = max(len(c.name) for c in checks)
    for c in checks:
        print(f"  {'ok     ' if c.ok else 'MISSING'} {c.name:<{w}}  {c.detail}")
        if not c.ok and c.fix:
            print(f"          {'':<{w}}  fix: {c.fix}")
    missing = [c.name for c in checks if not c.ok]
    if missing:
        print(f"not ready: {', '.join(missing)} (docs/HARDWARE.md, Running the cell)")
        return 1
    print("ready: every check passed")
    sys.stdout.flush()
    return 0
