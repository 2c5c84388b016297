"""The cell config: which cell, which drivers, how fast, where results go. YAML validated by pydantic."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from configs import CONFIG_DIR
from planners.config import load_yaml_model
from planners.motion.collision import CollisionConfig
from sim.config import TwinConfig


class MotionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    speed_factor: float = Field(0.5, gt=0, le=1, description="scales the Panda's velocity/acceleration/jerk limits")
    ik_margin_rad: float = Field(0.05, ge=0, le=0.5)
    ik_seeds: int = Field(6, ge=1, le=64)
    check_collisions: bool = Field(True, description="plan moves clear of floor, robot and the scanned scene (FCL)")
    collision: CollisionConfig = Field(default_factory=CollisionConfig)
    self_filter_pad_m: float = Field(0.02, ge=0, le=0.2, description="drop returns this close to the arm's "
                                     "own collision hulls (0: keep them)")
    retract_m: float = Field(0.10, ge=0, le=0.5, description="back-off along the optical axis for via waypoints")
    park_q: tuple[float, float, float, float, float, float, float] | None = Field(
        None, description="joints of a clear pose above the cell, the last via (default: the twin's home)")


class CellConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    cell_id: str = Field("sim-1", pattern=r"^[A-Za-z0-9_-]{1,64}$")
    mode: Literal["sim"] = "sim"
    twin: TwinConfig = Field(default_factory=TwinConfig)
    motion: MotionConfig = Field(default_factory=MotionConfig)
    planners_config: str = Field("planners.yaml", description="path, relative to this file")
    runs_dir: str = "runs"
    rerun_connect: str | None = Field(None, description="optional live viewer address, e.g. rerun+http://127.0.0.1:9876/proxy")


DEFAULT_CELL_CONFIG = CONFIG_DIR / "cell.sim.yaml"


def load_cell_config(path: str | Path | None = None) -> tuple[CellConfig, Path]:
    """The config and the file it came from (relative paths inside it resolve against that file)."""
    p = Path(path) if path else DEFAULT_CELL_CONFIG
    return load_yaml_model(p, CellConfig), p  # type: ignore[return-value]
