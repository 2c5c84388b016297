"""`cellctl`: the command line of the cell controller."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import get_args

from cellctl.service.api import LIST_LIMIT_MAX, JobState
from configs import CONFIG_DIR
from planners.config import ConfigError
from planners.registry import DEFAULT_PLANNER, PLANNERS


JOB_STATES = get_args(JobState)


def _list_limit(text: str) -> int:
    n = int(text)
    if not 1 <= n <= LIST_LIMIT_MAX:
        raise argparse.ArgumentTypeError(f"{n} is not in 1..{LIST_LIMIT_MAX}")
    return n


def _scan(args: argparse.Namespace) -> int:
    from cellctl.config import load_cell_config
    from cellctl.scan.run import run_job
    from cellctl.scan.spec import Hooks, JobSpec
    from drivers.interfaces import DeviceError

    cfg, cfg_path = load_cell_config(args.config)
    try:
        result, run_dir = run_job(JobSpec(cfg, cfg_path, args.scene, args.planner, seed=args.seed,
                                          noise=not args.no_noise, out=args.out, max_steps=args.max_steps,
                                          cut=not args.no_cut, dry_run_cut=args.dry_run_cut, record=args.record),
                                  Hooks(progress=not args.quiet))
    except DeviceError as e:  # fcisim/real: the arm or camera did not open (the message says why)
        print(f"cellctl scan: {e}", file=sys.stderr)
        return 3
    _print_summary(result, run_dir)
    return 0 if result.error is None else 1


def _replay(args: argparse.Namespace) -> int:
    import json

    from cellctl.config import load_cell_config
    from cellctl.scan.replay import compare
    from cellctl.scan.run import run_job
    from cellctl.scan.spec import Hooks, JobSpec
    from drivers.interfaces import DeviceError

    folder = Path(args.folder)
    try:
        rec = json.loads((folder / "result.json").read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{folder}: no readable result.json of a recorded job ({e})") from None
    cfg, cfg_path = load_cell_config(args.config)
    spec = JobSpec(cfg, cfg_path, rec["scene_ref"], rec["planner"], out=args.out, cut=rec.get("cut") is not None,
                   replay_from=folder)
    try:
        result, run_dir = run_job(spec, Hooks(progress=not args.quiet))
    except DeviceError as e:
        print(f"cellctl replay: {e}", file=sys.stderr)
        return 3
    c = compare(folder, run_dir)
    print(f"replayed {folder} into {run_dir}")
    for key, (a, b) in ((k, v) for k, v in c.items() if k != "drawing_distance_mm"):
        print(f"  {key:<18} recorded {a}  replayed {b}")
    if c["drawing_distance_mm"]:
        med, p99 = c["drawing_distance_mm"]
        print(f"  drawing            replayed points lie {med:.2f} mm (median), {p99:.2f} mm (99 %) from the recorded")
    return 0 if result.error is None else 1


def _scene(args: argparse.Namespace) -> int:
    from sim.appearance import split_look
    from sim.scenes.scrap import parse_ref, scrap_refs, write_scene_file

    if args.scene_cmd == "write":
        bad = [r for r in args.refs if parse_ref(split_look(r)[0]) is None]
        if bad:
            raise ValueError(f"not a generated piece: {', '.join(map(repr, bad))} (write "
                             f"scrap:<gen_seed>:<index>[@<finish>,<paint>,<light>[,<seed>] | @drawn])")
        for ref in args.refs:
            path = write_scene_file(ref, args.out)
            print(f"{ref} -> {path} (load it with --scene {path})")
        return 0
    from cellctl.bench.scrap_sheet import write_sheet

    refs = args.refs or scrap_refs(args.count, args.gen_seed)
    print(f"{len(refs)} pieces -> {write_sheet(refs, args.out, cols=args.cols)}")
    return 0


def _bench(args: argparse.Namespace) -> int:
    from cellctl.bench.scans import cli_bench

    return cli_bench(args)


def _serve(args: argparse.Namespace) -> int:
    from cellctl.config import load_cell_config
    from cellctl.service.server import serve
    from cellctl.service.store import StoreError

    cfg, cfg_path = load_cell_config(args.config)
    try:
        return serve(cfg, cfg_path, args.data_dir, listen=args.listen, connect=args.connect)
    except StoreError as e:
        print(f"cellctl serve: {e}", file=sys.stderr)
        return 1


def _doctor(args: argparse.Namespace) -> int:
    from cellctl.commissioning.doctor import cli_doctor

    return cli_doctor(args)


def _calibrate(args: argparse.Namespace) -> int:
    from cellctl.commissioning.handeye import cli_board, cli_hand_eye

    if args.what == "paint":
        from cellctl.commissioning.paint import cli_paint

        return cli_paint(args)

    return cli_hand_eye(args) if args.what == "hand-eye" else cli_board(args)


def _client(args: argparse.Namespace):
    from cellctl.service.client import CellClient

    return CellClient(args.cell, args.connect or ["tcp/127.0.0.1:7447"], timeout_s=args.reply_timeout,
                      zenoh_config_file=args.zenoh_config, tls_ca=args.ca)


def _remote(fn):
    """Client subcommands: a refusal, no reply or no network is one clear line and an exit status
    (2 refused, 3 no reply/unreachable), never a traceback."""
    def run(args: argparse.Namespace) -> int:
        from cellctl.service.client import CellError, CellUnreachable, NoReply

        try:
            with _client(args) as client:
                return fn(client, args)
        except CellError as e:
            print(f"cellctl: cell {args.cell} refused: {e.code}: {e.message}", file=sys.stderr)
            return 2
        except (NoReply, CellUnreachable, TimeoutError) as e:
            print(f"cellctl: {e}", file=sys.stderr)
            return 3
    return run


@_remote
def _submit(client, args: argparse.Namespace) -> int:
    req = {"scene": args.scene, "planner": args.planner, "noise": not args.no_noise,
           "dry_run_cut": args.dry_run_cut}
    if args.max_steps is not None:
        req["max_steps"] = args.max_steps
    if args.seed is not None:
        req["seed"] = args.seed
    if args.request_id is not None:
        req["request_id"] = args.request_id
    if not args.wait:
        reply = client.submit(req)
        print(reply.job_id)
        where = (f"already submitted with this request id: {reply.state}" if reply.duplicate
                 else f"queued at position {reply.queue_position}")
        print(f"{where}; follow it with: cellctl jobs show {reply.job_id} --cell {args.cell}", file=sys.stderr)
        return 0
    bar = _ProgressBar(sys.stderr)
    reply = client.submit(req, on_event=bar)
    rec = client.wait(reply.job_id, args.timeout)
    bar.finish()
    note = rec.transitions[-1].note if rec.transitions else None
    print(f"job {rec.job_id}: {rec.state}" + (f" ({note})" if note else ""))
    if rec.result is not None:
        _print_summary(rec.result, Path(rec.artifacts.dir) if rec.artifacts else Path("?"))
    elif rec.error:
        print(f"  error  {rec.error}")
    return 0 if rec.state == "done" else 1


class _ProgressBar:
    """Fed by job events on Zenoh's thread: one redrawn line on a terminal, a line per event otherwise."""

    def __init__(self, stream):
        self.stream, self.tty, self.open = stream, stream.isatty(), False

    def __call__(self, ev) -> None:
        frac = (ev.step + 1) / ev.max_steps if ev.step is not None and ev.max_steps else 0.0
        if ev.phase == "done":
            frac = 1.0
        n = int(24 * min(frac, 1.0))
        step = f"view {ev.step + 1} of {ev.max_steps}" if ev.step is not None and ev.max_steps else ""
        cov = f"coverage {ev.coverage_percent:.1f} %" if ev.coverage_percent is not None else ""
        line = f"[{'#' * n:<24}] {ev.phase:<12} {step:<14} {cov}"
        if self.tty:
            self.stream.write("\r" + line.ljust(78))
            self.open = True
        else:
            self.stream.write(f"{ev.job_id} #{ev.seq} {line.rstrip()}\n")
        self.stream.flush()

    def finish(self) -> None:
        if self.open:
            self.stream.write("\n")
            self.open = False


@_remote
def _jobs_list(client, args: argparse.Namespace) -> int:
    res = client.jobs(limit=args.limit, state=args.state)
    print(f"{'job':<24} {'state':<11} {'scene':<18} {'planner':<7} {'coverage':>8}  created")
    for j in res.jobs:
        cov = f"{j.coverage_percent:.1f} %" if j.coverage_percent is not None else "-"
        print(f"{j.job_id:<24} {j.state:<11} {j.scene[:18]:<18} {j.planner:<7} {cov:>8}  {j.created_at}"
              + (f"  {j.error}" if j.error else ""))
    print(f"({len(res.jobs)} of {res.total})", file=sys.stderr)
    return 0


@_remote
def _jobs_show(client, args: argparse.Namespace) -> int:
    print(client.job(args.job_id).model_dump_json(indent=2))
    return 0


@_remote
def _jobs_fetch(client, args: argparse.Namespace) -> int:
    listing = client.files(args.job_id)
    names = [f.name for f in listing.files]
    wanted = args.name or names
    missing = [n for n in wanted if n not in names]
    if missing:
        print(f"cellctl jobs fetch: job {args.job_id} has no {', '.join(missing)}; it has {', '.join(names) or 'no files'}",
              file=sys.stderr)
        return 1
    out = Path(args.out) / args.job_id
    out.mkdir(parents=True, exist_ok=True)
    for name in wanted:
        info = client.fetch(args.job_id, name, out / name)
        print(f"{out / name}  {info.size} bytes  sha256 {info.sha256}")
    return 0


@_remote
def _jobs_cancel(client, args: argparse.Namespace) -> int:
    reply = client.cancel(args.job_id, args.reason)
    print(f"job {reply.job_id}: {reply.state}")
    return 0


@_remote
def _status(client, args: argparse.Namespace) -> int:
    st = client.status()
    for k, v in st.model_dump().items():
        print(f"  {k:<15} {v}")
    return 0


def _print_summary(r, run_dir: Path) -> None:
    """A ScanResult, or its API summary (cellctl.scan.result): the same fields."""
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
    if c := r.cut:
        uncut: dict[str, float] = {}
        for g in c.gaps:
            if g.length_m > 0:
                uncut[g.reason] = uncut.get(g.reason, 0.0) + g.length_m
        what = f"{100 * c.cut_fraction:.1f} % of the {c.drawing_length_m:.3f} m drawing, " if c.drawing_length_m else ""
        rows.append(("cut path", what + f"{c.feasible_branches} cuts"
                                 + (f" ({c.branches - c.feasible_branches} not runnable)"
                                    if c.branches > c.feasible_branches else "")
                                 + ("; uncut: " + ", ".join(f"{1000 * v:.0f} mm {k}" for k, v in sorted(uncut.items()))
                                    if uncut else "")
                                 + (f"; {c.error}" if c.error else "")))
        if p := c.paint:
            left = sum(u.length_m for u in p.uncut)
            rows.append(("cut vs paint", f"{100 * c.told_share:.1f} % of the {1000 * c.told_length_m:.0f} mm line on "
                                         f"the paint is cut; the flame passes over {100 * p.cut_share:.1f} % of the "
                                         f"painted area ({p.spray_width_mm:.0f} mm wide); "
                                         f"{1000 * left:.0f} mm of it uncut; the lit flame at most "
                                         f"{p.flame_off_paint_max_mm} mm off the paint"))
        for msg in c.warnings:
            rows.append(("warning", msg))
        if a := c.accuracy:
            rows.append(("cut vs true line", f"{100 * a.cut_coverage:.1f} % of the line within 5 mm of the flame; "
                                             f"flame to line mean {a.path_to_line_mean_mm} mm, max "
                                             f"{a.path_to_line_max_mm} mm over the lit motion ({a.pose_to_line_max_mm} "
                                             f"mm at the poses); tip {a.tip_to_metal_min_mm}-{a.tip_to_metal_max_mm} "
                                             f"mm off the metal; {a.cuts} cuts for {a.strokes} strokes"))
        if d := c.dry_run:
            rows.append(("dry-run cut", f"{d.motions} motions, tip error max {d.tip_error_max_mm} mm "
                                        f"(median {d.tip_error_median_mm}), off the path max "
                                        f"{d.path_error_max_mm} mm, {d.contacts} contacts; the executed flame at most "
                                        f"{d.flame_off_paint_max_mm} mm off the paint"
                                        + (f", {d.flame_to_line_max_mm} mm off the true line"
                                           if d.flame_to_line_max_mm is not None else "")))
    if r.error:
        rows.append(("error", r.error))
    rows.append(("run folder", str(run_dir)))
    w = max(len(k) for k, _ in rows)
    print()
    for k, v in rows:
        print(f"  {k:<{w}}  {v}")


def _client_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cell", required=True, help="cell id (cell_id in the cell's config)")
    p.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="Zenoh endpoint of the cell or its router (default: tcp/127.0.0.1:7447; repeatable)")
    p.add_argument("--reply-timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for a reply (default: 5); no reply = cell down or access denied")
    p.add_argument("--zenoh-config", default=None, metavar="JSON5",
                   help="Zenoh client config with your credentials (transport/auth/usrpwd) for a yard router")
    p.add_argument("--ca", default=None, metavar="FILE",
                   help="the yard's CA certificate, for a tls/ endpoint (deploy/make-certs.sh; or set "
                        "transport.link.tls.root_ca_certificate in the --zenoh-config file)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cellctl", description="scrapcell cell controller")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("scan", help="scan a drawing on the config's devices (mode sim: the pybullet twin; fcisim, "
                                    "real: see docs/HARDWARE.md) and write a run folder")
    s.add_argument("--scene", required=True, help="built-in scene name or path to a scene .yaml")
    s.add_argument("--planner", default=DEFAULT_PLANNER, choices=tuple(PLANNERS),
                   help=f"next-view planner (default: {DEFAULT_PLANNER})")
    s.add_argument("--config", default=None, help="cell config YAML (default: configs/cell.sim.yaml)")
    s.add_argument("--out", default=None, help="runs folder (default: the config's runs_dir)")
    s.add_argument("--seed", type=int, default=None, help="sensor noise seed (default: the config's)")
    s.add_argument("--no-noise", action="store_true", help="turn the D435 depth noise off")
    s.add_argument("--max-steps", type=int, default=None, help="override the planner's step limit")
    s.add_argument("--quiet", action="store_true", help="no per-step progress lines")
    s.add_argument("--no-cut", action="store_true", help="stop after the scan: no cutting path")
    s.add_argument("--dry-run-cut", action="store_true",
                   help="run the cutting path in the twin (torch off) and report the tip's tracking error")
    s.add_argument("--record", action="store_true",
                   help="record the job's frames (capture.bag) and arm positions (capture_arm.jsonl) into its folder, "
                        "so that `cellctl replay` can run it again")
    s.set_defaults(func=_scan)

    rp = sub.add_parser("replay", help="run a recorded job (cellctl scan --record) again from its folder: its bag "
                                       "through the RealSense bag player, its arm positions, the same scan code")
    rp.add_argument("folder", help="the recorded job's folder (result.json, capture.bag, capture_arm.jsonl)")
    rp.add_argument("--config", default=None, help="cell config YAML (its planners config; default: "
                                                   "configs/cell.sim.yaml)")
    rp.add_argument("--out", default=None, help="runs folder for the replay (default: the config's runs_dir)")
    rp.add_argument("--quiet", action="store_true", help="no per-step progress lines")
    rp.set_defaults(func=_replay)
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
    b.add_argument("--dry-run-cut", action="store_true",
                   help="run every scan's cut in the twin (torch off): contacts and tip error in the cut table")
    b.add_argument("--service", type=int, nargs="?", const=100, default=None, metavar="N",
                   help="instead of scans: the job API's latency on loopback (N status queries, default 100), then "
                        "the status round trip of --clients sessions at --hz during a whole scan job")
    b.add_argument("--load", action="store_true",
                   help="instead of scans: the load test of the job API on loopback (load.json, load.md; "
                        "docs/RELIABILITY.md)")
    b.add_argument("--jobs", type=int, default=200, help="with --load: jobs submitted in all (default: 200)")
    b.add_argument("--clients", type=int, default=10, help="with --load or --service: client sessions (default: 10)")
    b.add_argument("--hz", type=float, default=None,
                   help="with --load: status and jobs queries per second, each (default: 50); with --service: "
                        "status queries per second of each client during a scan (default: 20)")
    b.add_argument("--queue-max", type=int, default=8, help="with --load: the service's queue_max (default: 8)")
    b.add_argument("--job-profile", choices=("initial_view", "scan"), default="initial_view",
                   help="with --load: service.job_profile; initial_view (0.3 s jobs, default) or scan (full jobs, "
                        "max_steps 1)")
    b.add_argument("--scoring", action="store_true",
                   help="instead of scans: G-NBV's coarse-to-fine candidate scoring against exact scoring on the "
                        "same states, in one process (scoring.json, scoring.md)")
    b.add_argument("--oracle", action="store_true",
                   help="instead of scans: the coverage an all-knowing planner reaches after 1-4 views (the true "
                        "mesh cast from every pose the arm takes, and from those above the planners' camera floor; oracle.json, "
                        "oracle.md)")
    b.add_argument("--oracle-sensor", choices=("cast", "twin"), default="cast",
                   help="with --oracle: cast the true mesh (default, minutes) or render each candidate with the twin's "
                        "own sensor, its depth-discontinuity dropouts included (about 0.3 s per pose)")
    b.add_argument("--oracle-step-deg", type=float, default=7.5,
                   help="with --oracle: spacing of the candidate positions on their shells (default: 7.5)")
    b.add_argument("--appearance", action="store_true",
                   help="instead: the built-in shapes (--scenes) in the twin's finishes, paints and lights "
                        "(sim.appearance), every finish x paint pair, each paint commissioned first; refused or "
                        "coverage, flame to line and paint from metal per case (appearance.json, appearance.md)")
    b.add_argument("--finishes", default=None, help="with --appearance: 'all' or a comma list (default: all)")
    b.add_argument("--paints", default=None, help="with --appearance: 'all' or a comma list (default: all)")
    b.add_argument("--lights", default=None, help="with --appearance: 'all' or a comma list (default: all)")
    b.add_argument("--generated", type=int, default=None, metavar="N",
                   help="instead of built-in scenes: the first N generated scrap pieces of --gen-seed (sim.scenes.scrap; "
                        "default planner gnbv, 1 seed), each with the cut oracle beside the cell's cut")
    b.add_argument("--gen-seed", type=int, default=0, help="with --generated: the generator's seed (default: 0)")
    b.add_argument("--no-cut-oracle", action="store_true",
                   help="with --generated: skip the cut oracle (the planner given the true paint and piece)")
    b.add_argument("--report", default=None, metavar="BENCH_JSON",
                   help="only rewrite bench.md and the plots next to this bench.json, no scans")
    b.set_defaults(func=_bench)

    sc = sub.add_parser("scene", help="generated scrap pieces (scrap:<gen_seed>:<index>, docs/SCENES.md): keep one "
                                      "as a scene file, or draw a sheet of them")
    scsub = sc.add_subparsers(dest="scene_cmd", required=True)
    sw = scsub.add_parser("write", help="write generated pieces as scene files (<name>.yaml beside <name>.obj), "
                                        "e.g. to keep a failing piece as a regression test")
    sw.add_argument("refs", nargs="+", metavar="REF", help="generated pieces, e.g. scrap:0:17, or with a look: "
                                                         "scrap:0:17@rust_red,pink,dim or scrap:0:17@drawn")
    sw.add_argument("--out", required=True, help="folder for the .yaml and .obj files")
    ss = scsub.add_parser("sheet", help="a PNG sheet of generated pieces, paint in red")
    ss.add_argument("refs", nargs="*", metavar="REF", help="pieces to draw (default: the first --count of --gen-seed)")
    ss.add_argument("--count", type=int, default=12, help="without REFs: how many pieces (default: 12)")
    ss.add_argument("--gen-seed", type=int, default=0, help="without REFs: the generator's seed (default: 0)")
    ss.add_argument("--cols", type=int, default=4, help="panels per row (default: 4)")
    ss.add_argument("--out", required=True, help="the PNG to write")
    sc.set_defaults(func=_scene)

    sv = sub.add_parser("serve", help="run the cell-controller service: the job API over Zenoh (docs/API.md)",
                        description="Runs until SIGINT/SIGTERM; the running job is then interrupted (partial "
                                    "result kept) and the Zenoh session closed.")
    sv.add_argument("--config", default=None, help="cell config YAML (default: configs/cell.sim.yaml)")
    sv.add_argument("--data-dir", default=None, help="jobs.sqlite and job folders (default: service.data_dir)")
    sv.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                    help="override service.listen (repeatable), e.g. tcp/127.0.0.1:7447")
    sv.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                    help="override service.connect (repeatable)")
    sv.set_defaults(func=_serve)

    su = sub.add_parser("submit", help="submit a job to a running cell")
    su_kind = su.add_subparsers(dest="kind", required=True)
    sd = su_kind.add_parser("scan-drawing", help="scan the painted line and plan its cutting path")
    _client_args(sd)
    sd.add_argument("--scene", required=True, help="twin: built-in scene name or scene .yaml path on the cell")
    sd.add_argument("--planner", default=DEFAULT_PLANNER, choices=tuple(PLANNERS),
                    help=f"next-view planner (default: {DEFAULT_PLANNER})")
    sd.add_argument("--max-steps", type=int, default=None)
    sd.add_argument("--seed", type=int, default=None)
    sd.add_argument("--no-noise", action="store_true")
    sd.add_argument("--dry-run-cut", action="store_true")
    sd.add_argument("--request-id", default=None, metavar="KEY",
                    help="your key for this job (8-64 of A-Z a-z 0-9 _ . : -): the same command run again with it "
                         "gets the same job back instead of a second one (default: a new random key, retried on "
                         "a lost reply)")
    sd.add_argument("--wait", action="store_true", help="follow the job (progress on stderr) and print its result")
    sd.add_argument("--timeout", type=float, default=3600.0, metavar="S", help="with --wait: give up after S s")
    sd.set_defaults(func=_submit)

    j = sub.add_parser("jobs", help="list, show or cancel a cell's jobs")
    jsub = j.add_subparsers(dest="jobs_cmd", required=True)
    jl = jsub.add_parser("list", help="newest first")
    _client_args(jl)
    jl.add_argument("--limit", type=_list_limit, default=20, metavar=f"1..{LIST_LIMIT_MAX}")
    jl.add_argument("--state", default=None, choices=JOB_STATES, help="only jobs in this state")
    jl.set_defaults(func=_jobs_list)
    js = jsub.add_parser("show", help="the job record as JSON")
    js.add_argument("job_id")
    _client_args(js)
    js.set_defaults(func=_jobs_show)
    jf = jsub.add_parser("fetch", help="copy an ended job's files (the cut, the drawing, the recording, ...) "
                                       "from the cell, each checked against its SHA-256")
    jf.add_argument("job_id")
    jf.add_argument("--out", default=".", metavar="DIR", help="into DIR/<job_id>/ (default: the current directory)")
    jf.add_argument("--name", action="append", default=None, metavar="FILE",
                    help="only this file (repeatable), e.g. --name cut_path.json; default: all of them")
    _client_args(jf)
    jf.set_defaults(func=_jobs_fetch)
    jc = jsub.add_parser("cancel", help="cancel a queued or running job")
    jc.add_argument("job_id")
    jc.add_argument("--reason", default=None)
    _client_args(jc)
    jc.set_defaults(func=_jobs_cancel)

    dr = sub.add_parser("doctor", help="is this PC ready for the real cell? RealSense, libusb, udev, libfranka, "
                                       "the FCI host",
                        description="Exit status: 0 every check passed, 1 something is missing (each line says "
                                    "how to fix it), 2 invalid config.")
    dr.add_argument("--config", default=None, help="cell config YAML (default: configs/cell.real.yaml)")
    dr.set_defaults(func=_doctor)
    st = sub.add_parser("status", help="a cell's health: arm, camera, queue, running job")
    _client_args(st)
    st.set_defaults(func=_status)
    r = sub.add_parser("router", help="run a Zenoh router for the yard (cells and tablets connect to it)")
    r.add_argument("--config", default=None, help="router JSON5 config (default: deploy/zenoh/router.json5)")
    r.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="listen endpoint, TLS only, e.g. tls/0.0.0.0:7447 (repeatable; default: the config's)")
    r.add_argument("--users", default=None, help="user:password file (default: the config's dictionary_file)")
    r.add_argument("--tls-cert", default=None, help="the router's certificate (default: the config's; "
                   "deploy/make-certs.sh makes it)")
    r.add_argument("--tls-key", default=None, help="the router's private key (default: the config's)")
    r.set_defaults(func=_router)
    tb = sub.add_parser("tablet", help="serve the operator's tablet web app (a Zenoh client of the cells, "
                                       "README, 'For operators')")
    tb.add_argument("--config", default=str(CONFIG_DIR / "tablet.yaml"), help="tablet config (configs/tablet.yaml)")
    tb.add_argument("--add-user", metavar="NAME", default=None,
                    help="add (or replace) a page login instead of serving; the password is asked for, or read "
                         "from stdin")
    tb.add_argument("--remove-user", metavar="NAME", default=None,
                    help="take a page login away (a lost tablet): the running app logs it out within a second")
    tb.add_argument("--role", choices=("operator", "viewer"), default="operator",
                    help="with --add-user: an operator starts and cancels jobs, a viewer only watches")
    tb.set_defaults(func=_tablet)

    cal = sub.add_parser("calibrate", help="calibrate the cell (hand-eye, the yard's paint)")
    cal_kind = cal.add_subparsers(dest="what", required=True)
    he = cal_kind.add_parser("hand-eye", help="solve the camera's pose on the flange from views of a ChArUco board "
                                              "and write the hand-eye file (docs/HARDWARE.md)",
                             description="Exit status: 0 written, 1 calibration failed (board not seen, too few "
                                         "views), 2 bad arguments or config.")
    he.add_argument("--config", default=None, help="cell config YAML (default: configs/cell.sim.yaml)")
    he.add_argument("--poses", type=int, default=12, metavar="N", help="views of the board to use (default: 12, "
                                                                        "at least 5)")
    he.add_argument("--out", default=None, metavar="YAML",
                    help="hand-eye file to write (default: hand_eye.yaml beside the cell config)")
    he.add_argument("--method", default="best", choices=("best", "tsai", "park", "horaud", "andreff", "daniilidis"),
                    help="calibrateHandEye method (default: best = every method, lowest reprojection RMS)")
    he.add_argument("--seed", type=int, default=0, help="seed of the view poses (default: 0)")
    he.add_argument("--quiet", action="store_true", help="no per-view progress lines")
    he.add_argument("--board-pose", type=float, nargs=6, default=None, metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
                    help="where the board lies in the base frame (m, fixed-axis deg), to aim the views at; its "
                         "frame is OpenCV's: origin at the outer corner of the top-left square, x along the printed "
                         "columns, y along the rows, z into the board (a board lying face up has roll 180); "
                         "default: located from where the arm stands")
    he.add_argument("--max-residual-mm", type=float, default=2.0, metavar="MM",
                    help="write only if the board, seen through the result, moves at most this RMS between views "
                         "(default: 2)")
    he.add_argument("--max-residual-deg", type=float, default=0.5, metavar="DEG",
                    help="... and turns at most this RMS (default: 0.5)")
    he.add_argument("--max-reproj-px", type=float, default=1.0, metavar="PX",
                    help="... and its corners reproject within this RMS (default: 1)")
    he.add_argument("--max-scale-error-percent", type=float, default=1.0, metavar="PCT",
                    help="... and the depth camera finds the board within this of the size --square-mm gives "
                         "(default: 1)")
    cb = cal_kind.add_parser("board", help="write the ChArUco board to print for hand-eye")
    cb.add_argument("--out", default="charuco.png", help="PNG to write (default: charuco.png)")
    cb.add_argument("--dpi", type=int, default=300, help="print resolution tagged in the PNG (default: 300)")
    for a in (he, cb):
        a.add_argument("--square-mm", type=float, default=40.0, help="square side as printed (default: 40)")
        a.add_argument("--marker-mm", type=float, default=30.0, help="marker side as printed (default: 30)")
        a.set_defaults(func=_calibrate)
    cp = cal_kind.add_parser("paint", help="commission the yard's marking paint from one picture of a sample (paint "
                                           "sprayed on a piece of the yard's scrap, held in the middle of the "
                                           "picture, bare metal round it) and write paint.yaml (docs/HARDWARE.md)",
                             description="Nothing moves. Exit status: 0 written, 1 refused (no paint in the sample, "
                                         "paint the cell cannot tell from this metal, no picture), 2 bad arguments "
                                         "or config.")
    cp.add_argument("--name", required=True, help="what the yard calls the paint (e.g. pink); in the twin also the "
                                                  "sample's paint unless --paint says otherwise")
    cp.add_argument("--config", default=None, help="cell config YAML (default: configs/cell.sim.yaml); it is "
                                                   "pointed at the written file (paint_file)")
    cp.add_argument("--out", default=None, metavar="YAML", help="paint file to write (default: paint.yaml beside "
                                                                "the cell config)")
    cp.add_argument("--picture", default=None, metavar="PNG", help="the sample's picture with what was taken as "
                                                                   "paint (default: <out>_sample.png)")
    cp.add_argument("--seed", type=int, default=0, help="seed of the colour clustering (and the twin's sample)")
    tw = cp.add_argument_group("the twin's sample (modes sim and fcisim)")
    tw.add_argument("--finish", default=None, help="its metal (sim.appearance FINISHES; default rust_red)")
    tw.add_argument("--paint", default=None, help="its paint (sim.appearance PAINTS; default --name)")
    tw.add_argument("--light", default=None, help="the light on it (sim.appearance LIGHTS; default normal)")
    tw.add_argument("--no-paint", action="store_true", help="a sample of bare metal (it is refused)")
    cp.set_defaults(func=_calibrate)
    rec = sub.add_parser("record", help="record the live RealSense D435 to a .bag (replayable offline)",
                         description="Exit status: 0 recorded, 2 bad arguments or camera config, 3 no camera or "
                                     "the camera failed (the message says what to check).")
    rec.add_argument("--seconds", type=_positive_seconds, required=True, metavar="N", help="how long to record")
    rec.add_argument("--out", default=None, metavar="FILE.bag", help="output bag (default: d435-<timestamp>.bag)")
    rec.add_argument("--camera-config", default=None, metavar="YAML",
                     help="camera config, or a cell config with a camera: block (default: configs/camera.d435.yaml)")
    rec.set_defaults(func=_record)
    return p


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0.0 < value <= 3600.0:  # also refuses nan and inf
        raise argparse.ArgumentTypeError(f"{text} must be in (0, 3600] seconds")
    return value


def _record(args: argparse.Namespace) -> int:
    """Record the live D435 to a .bag through Open3D's RealSenseSensor (the bag replays through
    drivers.realsense.RealSenseBag). No camera: one clear line and exit status 3."""
    import time

    from configs import CONFIG_DIR
    from drivers.interfaces import DeviceError
    from drivers.realsense.config import load_realsense_config
    from drivers.realsense.sensor import RealSenseCamera

    cfg = load_realsense_config(args.camera_config or CONFIG_DIR / "camera.d435.yaml")
    out = Path(args.out or time.strftime("d435-%Y%m%d-%H%M%S.bag"))
    if out.suffix.lower() != ".bag":
        raise ValueError(f"--out {out}: the file name must end in .bag")
    if out.exists():
        raise ValueError(f"--out {out} exists already; choose another file")
    frames = 0
    try:
        with RealSenseCamera(cfg, record_to=out, record="all") as cam:
            end = time.monotonic() + args.seconds
            while time.monotonic() < end:
                cam.capture()
                frames += 1
    except DeviceError as e:
        print(f"cellctl record: {e}", file=sys.stderr)
        return 3
    print(f"{out}: {frames} frames in {args.seconds:g} s from RealSense {cam.serial}")
    return 0


def _router(args: argparse.Namespace) -> int:
    from cellctl.service.router import main as router_main

    argv = (["--config", args.config] if args.config else []) + [a for e in (args.listen or []) for a in ("--listen", e)]
    for flag in ("users", "tls_cert", "tls_key"):
        if getattr(args, flag):
            argv += ["--" + flag.replace("_", "-"), getattr(args, flag)]
    return router_main(argv)


def _tablet(args: argparse.Namespace) -> int:
    from cellctl.tablet.config import load_config

    cfg = load_config(args.config)
    if args.remove_user:
        from cellctl.tablet.accounts import remove_user

        remove_user(cfg.accounts_file, args.remove_user)
        print(f"{args.remove_user} removed from {cfg.accounts_file}; its open pages log out within a second")
        return 0
    if args.add_user:
        import getpass

        from cellctl.tablet.accounts import add_user

        if sys.stdin.isatty():
            password = getpass.getpass(f"password for {args.add_user}: ")
            if getpass.getpass("again: ") != password:
                raise ValueError("the two passwords differ")
        else:  # scripts pipe it in, so it shows in no process list
            password = sys.stdin.readline().rstrip("\n")
        acct = add_user(cfg.accounts_file, args.add_user, args.role, password)
        print(f"{acct.user} ({acct.role}) written to {cfg.accounts_file}; a running tablet app reads it at once")
        return 0
    from cellctl.service.logs import setup
    from cellctl.tablet.app import serve

    setup()
    serve(cfg)
    return 0


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
