"""Commissioning the yard's paint (`cellctl calibrate paint`, and the service's ``paint/commission``): one
picture of the paint on a piece of its scrap, held in front of the camera; the paint's colour model is
learned from it (planners/paint_calibration.py) and written to paint.yaml beside the cell config, which
reads it (``paint_file``). Nothing moves: the operator holds the sample, the arm stays where it is.

In the twin (modes sim and fcisim) the sample is a plate of a named finish with a stroke of a named
paint under a named light, placed square in front of the camera at the arm's home pose; on a real cell
(mode real) the D435 takes the picture.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellctl.config_files import backup, point_config_at, write_record
from cellctl.config import CellConfig, cell_planners_config
from cellctl.scan.modes import MODES
from configs import CONFIG_DIR
from drivers.interfaces import DeviceError, RGBDFrame
from planners.paint_calibration import PaintCalibration, calibrate_paint, regions, sample_mask

FLUSH_FRAMES = 5  # a live camera's first frames after opening are still settling exposure and white balance


@dataclass
class PaintSampleRun:
    calibration: PaintCalibration
    frame: RGBDFrame
    sample: np.ndarray  # (H, W) bool: the pixels of the sample
    paint: np.ndarray  # (H, W) bool: what the new model takes as paint (all False when refused)
    source: str  # "twin" or the camera's mode


def capture_in_twin(cfg: CellConfig, finish: str, paint: str | None, light: str, seed: int = 0) -> RGBDFrame:
    """The twin's camera, at the arm's home pose, looking at a sample of ``finish`` with a stroke of
    ``paint`` (None: bare metal) under ``light``."""
    import trimesh

    from sim.appearance import Appearance
    from sim.scenes.model import Scene
    from sim.scenes.sample import paint_sample
    from sim.twin import Twin

    twin_cfg = MODES[cfg.mode].twin_config(cfg, cfg.twin)
    empty = Scene(name="paint-sample", category=None, object_mesh=trimesh.Trimesh(), paint_mesh=trimesh.Trimesh(),
                  drawing_polylines=[], drawing_width=0.02, gt_points=np.zeros((0, 3), np.float32),
                  extremities=np.zeros((0, 3)))
    with Twin(empty, twin_cfg) as twin:  # where the camera is, to hold the sample in front of it
        twin.arm.reset(twin_cfg.home_q)
        T_base_cam = twin.arm.camera_pose()
    scene = paint_sample(T_base_cam, Appearance(finish, paint or "red", light, seed), painted=paint is not None)
    with Twin(scene, twin_cfg) as twin:
        twin.arm.reset(twin_cfg.home_q)
        return twin.camera.capture()


def capture_on_cell(cfg: CellConfig) -> RGBDFrame:
    """A picture from the cell's D435 (or its .bag), after the exposure settled."""
    from drivers.realsense import open_camera

    if cfg.camera is None:
        raise DeviceError(f"mode {cfg.mode} has no camera block to take the sample's picture with")
    with open_camera(cfg.camera) as cam:
        for _ in range(FLUSH_FRAMES):
            cam.capture()
        return cam.capture()


def commission(frame: RGBDFrame, cfg: CellConfig, cfg_path: Path, name: str, source: str,
               seed: int = 0) -> PaintSampleRun:
    """Learn the paint from one picture; the check's limits are the cell's planners config's."""
    from planners.paint_color import PaintSegmenter

    base = cell_planners_config(cfg, cfg_path).paint
    depth = np.asarray(frame.depth)
    if not np.isfinite(depth).any():
        raise DeviceError("the camera gave no depth in the sample's picture (NaN everywhere): is the sample "
                          "0.25-0.5 m in front of it?")
    sample = sample_mask(depth)
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    cal = calibrate_paint(frame.color, sample, base, name=name, seed=seed,
                          source=f"cellctl calibrate paint {stamp} ({source}, cell {cfg.cell_id})")
    paint = np.zeros(sample.shape, dtype=bool)
    if cal.ok:
        paint = PaintSegmenter(cal.paint).mask(frame.color.reshape(-1, 3)).reshape(sample.shape) & sample
    return PaintSampleRun(cal, frame, sample, paint, source)


def picture(run: PaintSampleRun) -> np.ndarray:
    """The sample's picture for the operator: what the new model takes as paint in cyan, the middle
    (where the paint is held) and the rim (the metal it is told from) outlined."""
    from cellctl.scan.artifacts import paint_overlay

    out = paint_overlay(run.frame.color, run.paint)
    out[~run.sample] //= 3
    centre, rim = regions(run.sample.shape)
    for region, colour in ((centre, (255, 255, 0)), (~rim, (255, 255, 255))):
        edge = region ^ _eroded(_eroded(region))  # 2 px: still a line at half size
        out[edge] = colour
    return out


def _eroded(m: np.ndarray) -> np.ndarray:
    e = m.copy()
    e[1:, :] &= m[:-1, :]
    e[:-1, :] &= m[1:, :]
    e[:, 1:] &= m[:, :-1]
    e[:, :-1] &= m[:, 1:]
    return e


def record(run: PaintSampleRun) -> dict:
    """What paint.yaml holds: the ``paint`` colour the config reads, and the calibration's record."""
    cal = run.calibration
    p = cal.paint
    return {"paint": {"name": p.name, "lab_mean": list(p.lab_mean), "lab_cov": [list(r) for r in p.lab_cov],
                      "source": p.source},
            "delta_e": cal.delta_e, "metal_lab": cal.metal_lab, "metal_pass_share": cal.metal_pass_share,
            "paint_pixels": cal.paint_pixels, "colours": cal.colours, "source": run.source}


def write_paint_file(path: Path, run: PaintSampleRun) -> Path:
    header = ("# the yard's paint, commissioned by `cellctl calibrate paint` from one picture of a sample (CIELAB, D65).\n"
              "# The cell config reads it with paint_file; the check's limits stay in the planners config.\n")
    return write_record(path, record(run), header)


def commission_and_write(cfg: CellConfig, cfg_path: Path, name: str, *, out: Path | None = None,
                         twin_sample: dict | None = None, seed: int = 0) -> tuple[PaintSampleRun, Path, dict]:
    """Take the picture (the twin's sample ``twin_sample`` {finish, paint, light, no_paint}, or the cell's
    camera), learn the paint, and when accepted write it and point the config at it. Returns the run, the
    paint file and what was done ({written, previous, config}: words)."""
    from sim.appearance import PAINTS

    out = Path(out) if out else (cfg_path.parent / cfg.paint_file if cfg.paint_file else cfg_path.parent / "paint.yaml")
    twin = MODES[cfg.mode].twin
    t = twin_sample or {}
    if not twin and any(t.get(k) for k in ("finish", "paint", "light", "no_paint")):
        raise ValueError("the twin's sample (finish, paint, light, no paint) is for a cell in the twin; on a real "
                         "cell hold the sample in front of the camera")
    if twin:
        paint = None if t.get("no_paint") else (t.get("paint") or name)
        if paint is not None and paint not in PAINTS:
            raise ValueError(f"the twin has no paint {paint!r}; say which of {', '.join(PAINTS)} the sample is "
                             f"painted with")
        frame = capture_in_twin(cfg, t.get("finish") or "rust_red", paint, t.get("light") or "normal", seed)
    else:
        frame = capture_on_cell(cfg)
    run = commission(frame, cfg, cfg_path, name, "twin" if twin else cfg.mode, seed=seed)
    done: dict = {}
    if run.calibration.ok:
        old = backup(out)
        write_paint_file(out, run)
        done["written"] = str(out)
        if old is not None:
            done["previous"] = str(old)
        if cfg_path.resolve().parent == CONFIG_DIR.resolve():  # the shipped configs stay as shipped
            done["config"] = (f"{cfg_path.name} is a shipped config and is left as it is: in a copy of it, set "
                              f"paint_file: {out.resolve()}")
        else:
            done["config"] = point_config_at(cfg_path, out, "paint_file", "calibrate paint")
    return run, out, done


def png_bytes(image: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return buf.getvalue()
