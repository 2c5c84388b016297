"""`cellctl`: the command line of the cell controller."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from planners.config import ConfigError


def _scan(args: argparse.Namespace) -> int:
    from cellctl.config import load_cell_config
    from cellctl.scan_run import run_scan_in_twin

    cfg, cfg_path = load_cell_config(args.config)
    result, run_dir = run_scan_in_twin(cfg, cfg_path, args.scene, args.planner, seed=args.seed,
                                       noise=not args.no_noise, out=args.out, max_steps=args.max_steps,
                                       progress=not args.quiet, cut=not args.no_cut,
                                       dry_run_cut=args.dry_run_cut)
    _print_summary(result, run_dir)
    return 0 if result.error is None else 1


def _bench(args: argparse.Namespace) -> int:
    from cellctl.bench import cli_bench

    return cli_bench(args)


def _print_summary(r, run_dir: Path) -> None:
    rows = [
        ("scene", r.scene), ("planner", r.planner),
        ("views", f"{r.steps} captured (initial included; the paper's viewpoints: {max(r.steps - 1, 0)})"),
        ("planning time", f"{r.planning_s:.2f} s total, {r.step_s:.3f} s per viewpoint (eq. 11)"),
        ("capture time", f"{r.capture_s:.2f} s"),
        ("motion planning", f"{r.motion_planning_s:.2f} s"),
        ("motion time", f"{r.motion_s:.2f} s"),
        ("displacement", f"{100 * r.displacement_m:.1f} cm"),
        ("coverage", f"{r.coverage_hit}/{r.coverage_total} voxels = {r.coverage_percent:.1f} %"),
        ("terminated by", r.terminated_by),
    ]
    if r.cut:
        c = r.cut
        rows.append(("cut path", f"{c['feasible_branches']}/{c['branches']} branches feasible, "
                                 f"{c['feasible_poses']}/{c['poses']} poses, {c['length_m']:.3f} m"
                                 + (f"; infeasible: {c['infeasible']}" if c["infeasible"] else "")
                                 + (f"; {c['error']}" if c["error"] else "")))
        if c.get("dry_run"):
            d = c["dry_run"]
            rows.append(("dry-run cut", f"{d['motions']} motions, tip error max {d['tip_error_max_mm']} mm "
                                        f"(median {d['tip_error_median_mm']}), off the path max "
                                        f"{d['path_error_max_mm']} mm, {len(d['contacts'])} contacts"))
    if r.error:
        rows.append(("error", r.error))
    rows.append(("run folder", str(run_dir)))
    w = max(len(k) for k, _ in rows)
    print()
    for k, v in rows:
        print(f"  {k:<{w}}  {v}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cellctl", description="scrapcell cell controller")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("scan", help="scan a drawing in the pybullet twin and write a run folder")
    s.add_argument("--scene", required=True, help="built-in scene name or path to a scene .yaml")
    s.add_argument("--planner", default="gnbv", help="next-view planner (default: gnbv)")
    s.add_argument("--config", default=None, help="cell config YAML (default: configs/cell.sim.yaml)")
    s.add_argument("--out", default=None, help="runs folder (default: the config's runs_dir)")
    s.add_argument("--seed", type=int, default=None, help="sensor noise seed (default: the config's)")
    s.add_argument("--no-noise", action="store_true", help="turn the D435 depth noise off")
    s.add_argument("--max-steps", type=int, default=None, help="override the planner's step limit")
    s.add_argument("--quiet", action="store_true", help="no per-step progress lines")
    s.add_argument("--no-cut", action="store_true", help="stop after the scan: no cutting path")
    s.add_argument("--dry-run-cut", action="store_true",
                   help="run the cutting path in the twin (torch off) and report the tip's tracking error")
    s.set_defaults(func=_scan)
    b = sub.add_parser("bench", help="scan every (scene, planner, seed) in the twin and report beside the paper's "
                                     "Table II", description="Exit status: 0 all runs ok, 1 some run failed "
                                     "(recorded as an error row), 2 bad arguments or config.")
    b.add_argument("--scenes", default=None, help="'all' or a comma list of built-in scenes (default: all)")
    b.add_argument("--planners", default=None, help="'all' or a comma list of planners (default: enpv,cnbv,gnbv,global)")
    b.add_argument("--seeds", type=int, default=None, help="sensor noise seeds 0..N-1 per pair (default: 3)")
    b.add_argument("--out", default=None, help="output folder (default: bench/<timestamp>)")
    b.add_argument("--quick", action="store_true",
                   help="smooth_cylinder,round_tank x gnbv,enpv x 1 seed (explicit options still win)")
    b.add_argument("--config", default=None, help="cell config YAML (default: configs/cell.sim.yaml)")
    b.add_argument("--no-memory", action="store_true", help="do not trace allocations (tracemalloc) during runs")
    b.add_argument("--report", default=None, metavar="BENCH_JSON",
                   help="only rewrite bench.md and the plots next to this bench.json, no scans")
    b.set_defaults(func=_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ConfigError as e:
        print(f"cellctl: invalid config:\n{e}", file=sys.stderr)
        return 2
    except ValueError as e:  # scene errors and bad arguments carry their own explanation
        print(f"cellctl: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
