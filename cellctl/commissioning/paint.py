"""`cellctl calibrate paint`: one picture of the yard's paint on a piece of its scrap, held in front of the
camera; the paint's colour model is learned from it (planners/paint_calibration.py) and written to
paint.yaml beside the cell config, which reads it (``paint_file``). Nothing moves: the operator holds
the sample, the arm stays where it is.

In the twin (modes sim and fcisim) the sample is a plate of a named finish with a stroke of a named
paint under a named light, placed square in front of the camera at the arm's home pose; on a real cell
(mode real) the D435 takes the picture.
"""

from __future__ import annotations

import datetime
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellctl.commissioning.config_files import backup, point_config_at, write_record
from cellctl.config import CellConfig, cell_planners_config, load_cell_config
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
    from cellctl.commissioning.handeye import _empty_scene
    from sim.appearance import Appearance
    from sim.scenes.sample import paint_sample
    from sim.twin import Twin

    twin_cfg = MODES[cfg.mode].twin_config(cfg, cfg.twin)
    with Twin(_empty_scene(), twin_cfg) as twin:  # where the camera is, to hold the sample in front of it
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
        edge = region ^ _eroded(region)
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


def cli_paint(args) -> int:
    """`cellctl calibrate paint`: 0 written, 1 refused (the message says why), 2 bad arguments or config."""
    from PIL import Image

    cfg, cfg_path = load_cell_config(args.config)
    out = Path(args.out) if args.out else cfg_path.parent / "paint.yaml"
    twin = MODES[cfg.mode].twin
    if not twin and (args.finish or args.paint or args.light or args.no_paint):
        raise ValueError("--finish, --paint, --light and --no-paint describe the twin's sample; on a real cell hold "
                         "the sample in front of the camera")
    try:
        if twin:
            from sim.appearance import PAINTS

            paint = None if args.no_paint else (args.paint or args.name)
            if paint is not None and paint not in PAINTS:
                raise ValueError(f"--name {args.name}: the twin has no paint of that name; say which of "
                                 f"{', '.join(PAINTS)} the sample is painted with (--paint)")
            frame = capture_in_twin(cfg, args.finish or "rust_red", paint, args.light or "normal", args.seed)
        else:
            frame = capture_on_cell(cfg)
        run = commission(frame, cfg, cfg_path, args.name, "twin" if twin else cfg.mode, seed=args.seed)
    except DeviceError as e:
        print(f"cellctl calibrate paint: {e}", file=sys.stderr)
        return 1
    pic = Path(args.picture) if args.picture else out.with_name(out.stem + "_sample.png")
    pic.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(picture(run)).save(pic)
    cal = run.calibration
    rows = [("sample", f"{cal.sample_pixels} pixels, {cal.colours} colours"),
            ("metal", "; ".join(f"L*a*b* {m}" for m in cal.metal_lab) or "-")]
    if cal.paint_pixels:
        rows.append(("paint", f"{cal.paint_pixels} pixels, {100 * (cal.centre_share or 0):.0f} % of the middle"))
    if cal.delta_e is not None:
        rows.append(("paint to metal", f"ΔE76 {cal.delta_e:.1f} (at least {cell_planners_config(cfg, cfg_path).paint.min_delta_e:g})"))
    if cal.metal_pass_share is not None:
        rows.append(("metal as paint", f"{100 * cal.metal_pass_share:.2f} % of the rim"))
    rows.append(("picture", str(pic)))
    if not cal.ok:
        for k, v in rows:
            print(f"  {k:<15}{v}")
        print(f"cellctl calibrate paint: not written ({out} is unchanged): {cal.reason}", file=sys.stderr)
        return 1
    old = backup(out)
    write_paint_file(out, run)
    rows.insert(0, ("paint", f"{cal.paint.name}: L*a*b* {list(cal.paint.lab_mean)}"))
    rows.append(("written", str(out)))
    if old is not None:
        rows.append(("previous", f"kept as {old}"))
    if cfg_path.resolve().parent == CONFIG_DIR.resolve():  # the shipped configs stay as shipped
        rows.append(("config", f"{cfg_path.name} is a shipped config and is left as it is: in a copy of it, set "
                               f"paint_file: {out.resolve()}"))
    else:
        rows.append(("config", point_config_at(cfg_path, out, "paint_file", "calibrate paint")))
    for k, v in rows:
        print(f"  {k:<15}{v}")
    return 0
