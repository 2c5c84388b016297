"""What a scan-drawing job is and how its caller follows it: light to import, so the service builds a
job's spec without loading the scan's libraries (the worker process loads them)."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from cellctl.config import CellConfig
from cellctl.scan.result import StepRecord


@dataclass(frozen=True)
class JobSpec:
    """What one scan-drawing job is, whoever asks for it (the CLI, the bench, the service's worker, to
    which it is pickled). ``profile``: "scan", the whole job, or "initial_view", its first view only (a
    cheap real job for load tests). ``run_dir``: write into this folder (the service's per-job folder),
    else into a new stamped one under ``out`` (default: the cell's runs_dir). ``arm_host``: fcisim, a
    franky-sim already running there (the service's own) instead of the config's choice. ``record``: the
job's captured frames and arm positions go into its folder; ``replay_from``: run on such a recording
instead of the mode's devices (cellctl.scan.replay)."""

    cfg: CellConfig
    cfg_path: Path
    scene: str  # a built-in scene name or a scene .yaml
    planner: str
    profile: str = "scan"
    seed: int | None = None
    noise: bool = True
    max_steps: int | None = None
    cut: bool = True
    dry_run_cut: bool = False
    run_dir: Path | None = None
    out: str | None = None
    arm_host: str | None = None
    record: bool = False  # write the job's frames and arm positions into its folder (cellctl.scan.replay)
    replay_from: Path | None = None  # a recorded job's folder: its recording is the devices


@dataclass(frozen=True)
class Hooks:
    """How a caller follows and stops a running job: ``cancel``, set from another thread, ends the scan
    early ("cancelled", partial result kept, no cut); ``on_step`` gets every StepRecord, ``on_phase``
    "scanning" / "planning-cut"; ``progress`` prints each step and the cut to stderr (the CLI)."""

    cancel: threading.Event | None = None
    stopped_as: Callable[[], str] | None = None  # what a cancel means, for terminated_by (default "cancelled")
    on_step: Callable[[StepRecord], None] | None = None
    on_phase: Callable[[str], None] | None = None
    progress: bool = False

    def stop_label(self) -> str:
        """The result's terminated_by after a cancel: the caller's word for it, else "cancelled"."""
        return (self.stopped_as() if self.stopped_as is not None else None) or "cancelled"
