"""`cellctl calibrate paint` (docs/HARDWARE.md): the yard's paint from one picture of a sample; the work is
cellctl.scan.paint_sample's, shared with the service's ``paint/commission``."""

from __future__ import annotations

import sys
from pathlib import Path

from cellctl.config import cell_planners_config, load_cell_config
from cellctl.scan.paint_sample import commission_and_write, picture
from drivers.interfaces import DeviceError


def cli_paint(args) -> int:
    """`cellctl calibrate paint`: 0 written, 1 refused (the message says why), 2 bad arguments or config."""
    from PIL import Image

    cfg, cfg_path = load_cell_config(args.config)
    sample = {"finish": args.finish, "paint": args.paint, "light": args.light, "no_paint": args.no_paint}
    try:
        run, out, done = commission_and_write(cfg, cfg_path, args.name, out=Path(args.out) if args.out else None,
                                              twin_sample=sample, seed=args.seed)
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
        rows.append(("paint to metal", f"ΔE76 {cal.delta_e:.1f} (at least "
                                       f"{cell_planners_config(cfg, cfg_path).paint.min_delta_e:g})"))
    if cal.metal_pass_share is not None:
        rows.append(("metal as paint", f"{100 * cal.metal_pass_share:.2f} % of the rim"))
    rows.append(("picture", str(pic)))
    if not cal.ok:
        for k, v in rows:
            print(f"  {k:<15}{v}")
        print(f"cellctl calibrate paint: not written ({out} is unchanged): {cal.reason}", file=sys.stderr)
        return 1
    rows.insert(0, ("paint", f"{cal.paint.name}: L*a*b* {list(cal.paint.lab_mean)}"))
    rows += [(k, v) for k, v in done.items()]
    for k, v in rows:
        print(f"  {k:<15}{v}")
    return 0
