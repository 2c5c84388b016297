"""The cell config: which cell, which drivers, how fast, where results go. YAML validated by pydantic."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from cellctl.scan.modes import MODES, ModeName
from configs import CONFIG_DIR
from drivers.panda.config import FrankaConfig, HandEye
from drivers.realsense.config import RealSenseConfig
from planners.config import ConfigError, PaintColor, PlannersConfig, load_planners_config, load_yaml_model
from planners.motion.collision import CollisionConfig
from sim.config import HandEyeConfig, TwinConfig


class MotionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    speed_factor: float = Field(0.5, gt=0, le=1, description="scales the Panda's velocity/acceleration/jerk limits")
    ik_margin_rad: float = Field(0.05, ge=0, le=0.5)
    ik_seeds: int = Field(6, ge=1, le=64)
    check_collisions: bool = Field(True, description="plan moves clear of floor, robot and the scanned scene (FCL)")
    collision: CollisionConfig = Field(default_factory=CollisionConfig)
    self_filter_pad_m: float = Field(0.02, ge=0, le=0.2, description="drop returns this close to the arm's "
                                     "own collision hulls (0: keep them)")
    via_candidates: int = Field(8, ge=0, le=1000, description="best-ranked views that may be reached via waypoints")
    motion_budget_s: float = Field(60.0, gt=0, le=600, description="safety net: motion planning time per target before it is "
                                   "given up")
    retract_m: float = Field(0.10, ge=0, le=0.5, description="back-off along the optical axis for via waypoints")
    framed_views: bool = Field(False, description="a scan view keeps the planned roll about the optical axis (or its "
                               "half turn) when the arm reaches it, else any roll: the image is 87 x 58 deg")
    park_q: tuple[float, float, float, float, float, float, float] | None = Field(
        None, description="joints of a clear pose above the cell, the last via (default: the twin's home)")


# a Zenoh locator: protocol/address[:port][#params]; no spaces (a typo here is a silent unreachable cell)
ENDPOINT_PATTERN = r"^(tcp|udp|tls|quic|ws|unixsock-stream)/[^\s]{1,250}$"
Endpoint = Annotated[str, Field(pattern=ENDPOINT_PATTERN)]


class ServiceConfig(BaseModel):
    """`cellctl serve`: where jobs are kept and how the cell is reached over Zenoh."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    data_dir: str = Field("runs/service", description="jobs.sqlite and jobs/<job_id>/ (relative to the working "
                          "directory, like runs_dir)")
    zenoh_mode: Literal["peer", "client"] = Field("peer", description="peer: listen on `listen`; client: connect "
                                                  "to a router at `connect`")
    listen: list[Endpoint] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], max_length=8)
    connect: list[Endpoint] = Field(default_factory=list, max_length=8)
    zenoh_config_file: str | None = Field(None, description="optional JSON5 Zenoh config (credentials, TLS) "
                                          "that the fields above are applied on top of; relative to this file")
    tls_ca_file: str | None = Field(None, min_length=1, max_length=500,
                                    description="the yard's CA certificate (deploy/make-certs.sh), needed for a tls/ "
                                    "`connect` endpoint (the yard router listens on TLS only); relative to this file")
    scene_dirs: list[Annotated[str, Field(min_length=1, max_length=500, pattern=r"^[^\x00-\x1f\x7f]+$")]] = Field(
        default_factory=lambda: ["scenes"], max_length=16,
        description="a job may name a scene .yaml only inside these directories, symlinks resolved (relative to "
        "this file; default: scenes/ beside it; [] = built-in scenes only)")
    queue_max: int = Field(8, ge=1, le=1000, description="jobs waiting (the running one not counted)")
    requeue_after_restart: bool = Field(True, description="jobs still queued when the service stopped or died "
                                        "run after it restarts, in their order (the one that was running ends "
                                        "interrupted); false: they end interrupted too, for the operator to submit "
                                        "again")
    record_jobs: bool = Field(False, description="record every job's frames (capture.bag) and arm positions "
                              "(capture_arm.jsonl) into its folder, so `cellctl replay <job folder>` can run it again "
                              "(about 4 MB a view)")
    job_timeout_s: float = Field(900.0, gt=0, le=86400, description="a job running longer is cancelled and failed")
    retention_days: float | None = Field(None, gt=0, le=36500, description="an ended job's folder is deleted this long after "
                                         "it ended (its record stays); none: kept until retention_gb needs room")
    retention_gb: float | None = Field(20.0, gt=0, le=1e6, description="the jobs' folders together stay under this: the "
                                       "oldest ended jobs' folders are deleted first, never a queued or running "
                                       "job's, nor the last ended one's (its cut can always be fetched); none: no "
                                       "bound")
    shutdown_grace_s: float = Field(30.0, gt=0, le=600, description="on SIGTERM, wait this long for the running "
                                    "job to stop")
    rerun_connect: str | None = Field(None, max_length=256, description="live viewer for jobs' recordings "
                                      "(overrides the top-level rerun_connect)")
    job_profile: Literal["scan", "initial_view"] = Field(
        "scan", description="scan: every job is the full scan and cut; initial_view: every job only builds the twin "
        "and captures the scene's initial view (no motion, no planning, no cut), a cheap real job for load tests "
        "(cellctl.scan.initial_view); never on a production cell")

    @model_validator(mode="after")
    def _client_needs_a_router(self) -> "ServiceConfig":
        if self.zenoh_mode == "client" and not self.connect:
            raise ValueError("zenoh_mode client needs at least one `connect` endpoint (the router)")
        if self.zenoh_mode == "peer" and not (self.listen or self.connect):
            raise ValueError("zenoh_mode peer needs a `listen` or `connect` endpoint")
        return self

    def zenoh_config_path(self, cfg_dir: Path) -> Path | None:
        """zenoh_config_file, relative to the cell config's folder ``cfg_dir``."""
        return cfg_dir / self.zenoh_config_file if self.zenoh_config_file else None

    def tls_ca_path(self, cfg_dir: Path) -> Path | None:
        """tls_ca_file, relative to the cell config's folder ``cfg_dir``."""
        return cfg_dir / self.tls_ca_file if self.tls_ca_file else None


class FciSimConfig(BaseModel):
    """mode fcisim: where the franky-sim robot (a MuJoCo FR3 behind libfranka's protocol) runs."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    simulator: Literal["embedded", "external"] = Field(
        "embedded", description="embedded: the cell starts franky-sim itself (a child process) on the first free "
        "loopback address from arm.host on, the arm at twin.home_q; external: a franky-sim server already "
        "runs at arm.host (`python -m cellctl.scan.fcisim`)")
    start_timeout_s: float = Field(60.0, gt=0, le=600, description="embedded: longest wait for the simulator")


class CellConfig(BaseModel):
    """``mode``: sim = the pybullet twin moves and sees; fcisim = the franky adapter drives franky-sim and
    the twin renders the camera from the arm's measured joints; real = the Franka and the D435
    (docs/HARDWARE.md, "Running the cell"). Each mode is a class of cellctl.scan.modes."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    cell_id: str = Field("sim-1", pattern=r"^[A-Za-z0-9_-]{1,64}$")
    mode: ModeName = "sim"
    arm: FrankaConfig | None = Field(None, description="fcisim and real: the franky adapter (drivers.panda)")
    camera: RealSenseConfig | None = Field(None, description="real: the D435 (drivers.realsense)")
    fcisim: FciSimConfig = Field(default_factory=FciSimConfig)
    twin: TwinConfig = Field(default_factory=TwinConfig)
    hand_eye_file: str | None = Field(None, description="T_flange_cam written by `cellctl calibrate hand-eye`, "
                                      "relative to this file; when set it replaces twin.hand_eye")
    motion: MotionConfig = Field(default_factory=MotionConfig)
    planners_config: str = Field("planners.yaml", description="path, relative to this file")
    paint_file: str | None = Field(None, description="the yard's paint as `cellctl calibrate paint` commissioned it, "
                                   "relative to this file; when set its colour replaces the planners config's "
                                   "paint colour (the check's limits stay the planners config's)")
    runs_dir: str = "runs"
    rerun_connect: str | None = Field(None, description="optional live viewer address, e.g. rerun+http://127.0.0.1:9876/proxy")
    service: ServiceConfig = Field(default_factory=ServiceConfig)

    @model_validator(mode="after")
    def _devices_for_the_mode(self) -> "CellConfig":
        """Each mode gets the device blocks it drives; the message names the field to fix."""
        MODES[self.mode].check(self)
        return self


DEFAULT_CELL_CONFIG = CONFIG_DIR / "cell.sim.yaml"


def load_cell_config(path: str | Path | None = None) -> tuple[CellConfig, Path]:
    """The config and the file it came from (relative paths inside it resolve against that file)."""
    p = Path(path) if path else DEFAULT_CELL_CONFIG
    cfg: CellConfig = load_yaml_model(p, CellConfig)  # type: ignore[assignment]
    if cfg.hand_eye_file:
        cfg.twin.hand_eye = HandEyeConfig.from_file(p.parent / cfg.hand_eye_file, ConfigError)
        if cfg.arm is not None:  # the calibration is the camera's pose on the real flange too
            cfg.arm = cfg.arm.model_copy(update={"hand_eye": HandEye(**cfg.twin.hand_eye.model_dump())})
    return cfg, p


PAINT_COLOUR_FIELDS = ("name", "lab_mean", "lab_cov", "source")  # what a paint file sets; the limits are policy


class _PaintFile(BaseModel):
    model_config = ConfigDict(extra="ignore")  # the file's other keys are the calibration's record

    paint: dict


def load_paint_file(path: str | Path, base: PaintColor) -> PaintColor:
    """The paint colour a `cellctl calibrate paint` file holds, on ``base``'s limits."""
    doc = load_yaml_model(path, _PaintFile).paint  # type: ignore[attr-defined]
    unknown = sorted(set(doc) - set(PAINT_COLOUR_FIELDS))
    if unknown:
        raise ConfigError(f"{path}: paint: {', '.join(unknown)} not read from a paint file (it holds "
                          f"{', '.join(PAINT_COLOUR_FIELDS)}; the check's limits are set in the planners config)")
    try:
        return PaintColor(**{**base.model_dump(), **doc})
    except ValueError as e:
        raise ConfigError(f"{path}: paint: {e}") from None


def cell_planners_config(cfg: CellConfig, cfg_path: Path) -> PlannersConfig:
    """The planners config a job of this cell runs with: ``planners_config``, with the paint colour of
    ``paint_file`` when the cell has one commissioned."""
    pcfg = load_planners_config(Path(cfg_path).parent / cfg.planners_config)
    if cfg.paint_file:
        path = Path(cfg_path).parent / cfg.paint_file
        if not path.is_file():
            raise ConfigError(f"{cfg_path}: paint_file {cfg.paint_file}: no such file ({path}); run `cellctl "
                              f"calibrate paint --config {cfg_path}` or remove paint_file")
        pcfg = pcfg.model_copy(update={"paint": load_paint_file(path, pcfg.paint)})
    return pcfg
