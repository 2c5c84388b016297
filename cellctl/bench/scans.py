"""`cellctl bench`: every (scene, planner, seed) scanned in the twin, one run folder each, collected in
bench.json and reported side by side with the paper's Table II (see cellctl/bench/report.py).

Runs are sequential in this process, so timings are not skewed by runs competing for cores. A run
that fails (planner import error, exception, or `ScanResult.error`) becomes an error row; the bench
goes on. bench.json is rewritten after every run, so an interrupted bench keeps what it finished.
"""

from __future__ import annotations

import itertools
import math
import resource
import sys
import time
import tracemalloc
from datetime import datetime
from pathlib import Path
from typing import TextIO

from cellctl.bench.machine import code_info, machine_info
from cellctl.config import CellConfig
from cellctl.scan.artifacts import write_json
from cellctl.scan.result import CutSummary, ScanResult
from cellctl.scan.spec import JobSpec
from planners.registry import PLANNERS, planner_class

SCHEMA_VERSION = 1
DEFAULT_PLANNERS: tuple[str, ...] = tuple(PLANNERS)
DEFAULT_SEEDS = 3
QUICK = {"scenes": ("smooth_cylinder", "round_tank"), "planners": ("gnbv", "enpv"), "seeds": 1}
_MIB = 1024 * 1024


def parse_list(value: str | None, allowed: tuple[str, ...], what: str, default: tuple[str, ...]) -> list[str]:
    """'all', None (-> default) or 'a,b' checked against `allowed`; order kept, duplicates dropped."""
    if value is None:
        return list(default)
    if value.strip() == "all":
        return list(allowed)
    items = list(dict.fromkeys(s.strip() for s in value.split(",") if s.strip()))
    if not items:
        raise ValueError(f"--{what}: empty list")
    bad = [s for s in items if s not in allowed]
    if bad:
        raise ValueError(f"--{what}: unknown {', '.join(map(repr, bad))}; choose from {', '.join(allowed)} or 'all'")
    return items


def planner_import_error(name: str) -> str | None:
    """Why the planner cannot be built, or None. A half-written module fails here, not mid-bench."""
    try:
        planner_class(name)
    except Exception as e:  # noqa: BLE001 - any import-time failure is that planner's error row
        return f"planner {name!r} does not import: {type(e).__name__}: {e}"
    return None


def max_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports KiB, macOS bytes)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(r / (_MIB if sys.platform == "darwin" else 1024), 1)


def run_record(scene: str, category: int | None, planner: str, seed: int, result: ScanResult,
               run_dir: str | None, wall_s: float, peak_memory_mb: float | None) -> dict:
    """One row of bench.json. `views` counts every captured view (the initial one included);
    `viewpoints` is the paper's n_viewpoints (§VI-C.1), which excludes the initial view; `step_s` is
    eq. 11 with that divisor. A view of ``result``: the same figures, the cut in brief."""
    views = result.steps
    viewpoints = max(views - 1, 0)
    return {
        "scene": scene, "category": category, "planner": planner, "seed": seed,
        "views": views,
        "viewpoints": viewpoints,
        "planning_s": round(result.planning_s, 4),
        "step_s": round(result.planning_s / viewpoints, 4) if viewpoints else None,
        "capture_s": round(result.capture_s, 4),
        "motion_s": round(result.motion_s, 4),
        "motion_planning_s": round(result.motion_planning_s, 4),
        "displacement_m": round(result.displacement_m, 5),
        "coverage": {"hit": result.coverage_hit, "total": result.coverage_total,
                     "percent": result.coverage_percent},
        "terminated_by": result.terminated_by,
        "motion_contacts": result.motion_contacts,  # the twin's own check of every move
        "cut_feasible_poses": None if not result.cut else [result.cut.feasible_poses, result.cut.poses],
        "cut": cut_record(result.cut),
        # after each captured view (the initial one first): drawing coverage and planning time so far,
        # so planners can be compared at equal coverage, not only at their own stop
        "coverage_by_view": [r.coverage_percent for r in result.records],
        "planning_s_by_view": [round(x, 4) for x in itertools.accumulate(r.planning_s for r in result.records)],
        "peak_memory_mb": peak_memory_mb,
        "process_max_rss_mb": max_rss_mb(),
        "wall_s": round(wall_s, 2),
        "error": result.error,
        "run_dir": run_dir,
    }


def cut_record(cut: CutSummary | None) -> dict | None:
    """What the bench keeps of a scan's cut: how much of the drawing is cut, against the true line,
    the gaps by reason, planning time and (with a dry run) the twin's own check of the motion."""
    if not cut:
        return None
    gaps: dict[str, float] = {}
    for g in cut.gaps:
        if g.length_m > 0:
            gaps[g.reason] = round(gaps.get(g.reason, 0.0) + g.length_m, 4)
    dry = cut.dry_run
    paint = cut.paint
    return {"fraction": cut.cut_fraction, "cuts": cut.feasible_branches, "cut_lengths_m": list(cut.cut_lengths_m),
            "paint": paint and paint.model_dump(exclude={"uncut", "unseen"}),
            "uncut_paint_m_by_reason": _uncut_paint(paint),
            "unseen_paint": paint and {"borders": len(paint.unseen),
                                       "border_m": round(sum(u.border_m for u in paint.unseen), 4)},
            "planning_s": round(cut.planning_s, 3), "uncut_m_by_reason": gaps,
            "accuracy": cut.accuracy and cut.accuracy.model_dump(), "error": cut.error,
            "clearing_views": cut.clearing_views,
            "dry_run_contacts": dry and dry.contacts, "dry_run_tip_error_max_mm": dry and dry.tip_error_max_mm,
            "dry_run_flame_off_paint_max_mm": dry and dry.flame_off_paint_max_mm,
            "dry_run_flame_to_line_max_mm": dry and dry.flame_to_line_max_mm}


def _uncut_paint(paint) -> dict[str, float] | None:
    if paint is None:
        return None
    out: dict[str, float] = {}
    for u in paint.uncut:
        out[u.reason] = round(out.get(u.reason, 0.0) + u.length_m, 4)
    return out


class Progress:
    """A self-drawn bar on stderr: a line per finished run, with elapsed time and ETA. The ETA uses each
    planner's mean wall time so far (planners differ by 10x and more), else the mean of all scans."""

    def __init__(self, planners: list[str | None], stream: TextIO | None = None):
        """`planners`: the planner of each run in order, None for runs that scan nothing."""
        self.planners = planners
        self.total, self.done, self.stream = len(planners), 0, stream if stream is not None else sys.stderr
        self.t0 = time.perf_counter()
        self.walls: dict[str, list[float]] = {}
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def _bar(self, n: int, width: int = 24) -> str:
        fill = int(round(width * n / self.total)) if self.total else width
        return "[" + "#" * fill + "." * (width - fill) + "]"

    def _eta(self) -> str:
        left = [p for p in self.planners[self.done:] if p is not None]
        if not left:
            return "0:00"
        every = [w for ws in self.walls.values() for w in ws]
        if not every:
            return "?"
        mean_all = sum(every) / len(every)
        return _hms(sum(sum(self.walls[p]) / len(self.walls[p]) if p in self.walls else mean_all for p in left))

    def start(self, label: str) -> None:
        line = f"{self._bar(self.done)} {self.done}/{self.total} running {label}  elapsed {self._elapsed()}  ETA {self._eta()}"
        if self.tty:
            self.stream.write("\r\033[K" + line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def finish(self, label: str, rec: dict) -> None:
        p = self.planners[self.done]
        self.done += 1
        if p is not None:
            self.walls.setdefault(p, []).append(rec["wall_s"])
        if rec["error"]:
            status = "ERROR " + rec["error"].splitlines()[0][:100]
        else:
            status = (f"ok  {rec['views']} views  cov {rec['coverage']['percent']:.1f} %  "
                      f"planning {rec['planning_s']:.1f} s")
        line = (f"{self._bar(self.done)} {self.done}/{self.total} {label}: {status}  [{rec['wall_s']:.0f} s]  "
                f"elapsed {self._elapsed()}  ETA {self._eta()}")
        self.stream.write(("\r\033[K" if self.tty else "") + line + "\n")
        self.stream.flush()

    def _elapsed(self) -> str:
        return _hms(time.perf_counter() - self.t0)


def _hms(s: float) -> str:
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def _subdirs(p: Path) -> set[Path]:
    return {c for c in p.iterdir() if c.is_dir()} if p.is_dir() else set()


def run_bench(cfg: CellConfig, cfg_path: Path, scenes: list[str], planners: list[str], seeds: int, out: Path, *,
              memory: bool = True, quick: bool = False, stream: TextIO | None = None,
              dry_run_cut: bool = False, cut_oracle: bool = False, generated: dict | None = None) -> dict:
    """Run the grid, write OUT/bench.json (after every run) and OUT/runs/seed<k>/<run folders>;
    returns the bench document. The report is written by the caller (cellctl.bench.report).
    ``cut_oracle``: each scene's cut planned from its truth too (``cut_oracle.oracle_cut``), under
    ``cut_oracles``; ``generated``: the generator's n and seed, when the scenes are generated pieces
    (their family and lines under ``pieces``)."""
    from cellctl.scan.run import run_job
    from cellctl.config import cell_planners_config
    from sim.scenes import load_scene

    if seeds < 1:
        raise ValueError("--seeds must be >= 1")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pcfg = cell_planners_config(cfg, cfg_path)
    # Scenes are built once per process and cached, so loading them here costs the runs nothing;
    # it also fails early on a bad name and gives the category.
    categories = {name: load_scene(name).category for name in scenes}
    import_errors = {p: planner_import_error(p) for p in planners}

    t_start = time.perf_counter()
    doc = {
        "schema_version": SCHEMA_VERSION,
        "created": datetime.now().astimezone().isoformat(timespec="seconds"),
        "complete": False,
        "bench": {"scenes": scenes, "planners": planners, "seeds": list(range(seeds)), "quick": quick,
                  "memory": memory, "noise": True, "dry_run_cut": dry_run_cut, "cut_oracle": cut_oracle,
                  "generated": generated},
        "pieces": _pieces(scenes) if generated else {},
        "cut_oracles": {},
        "config": {"cell_config_path": str(cfg_path), "cell": cfg.model_dump(mode="json"),
                   "planners": pcfg.model_dump(mode="json")},
        "machine": machine_info(),
        "code": code_info(),
        "process": {},
        "runs": [],
    }
    json_path = out / "bench.json"
    grid = [(s, p, k) for s in scenes for p in planners for k in range(seeds)]
    bar = Progress([None if import_errors[p] else p for _, p, _ in grid], stream)
    if memory:
        tracemalloc.start()
    try:
        for scene, planner, seed in grid:
            label = f"{scene} / {planner} / seed {seed}"
            bar.start(label)
            if import_errors[planner]:
                rec = run_record(scene, categories[scene], planner, seed,
                                 ScanResult(scene=scene, planner=planner, error=import_errors[planner],
                                            terminated_by="error"),
                                 None, 0.0, None)
            else:
                rec = _one_run(cfg, cfg_path, scene, categories[scene], planner, seed, out, memory, run_job,
                               dry_run_cut)
            if cut_oracle and scene not in doc["cut_oracles"]:
                doc["cut_oracles"][scene] = _cut_oracle(cfg, pcfg, scene)
            doc["runs"].append(rec)
            doc["process"] = {"max_rss_mb": max_rss_mb(), "wall_s": round(time.perf_counter() - t_start, 1)}
            write_json(json_path, doc)
            bar.finish(label, rec)
        doc["complete"] = True
    finally:
        if memory:
            tracemalloc.stop()
        doc["process"] = {"max_rss_mb": max_rss_mb(), "wall_s": round(time.perf_counter() - t_start, 1)}
        write_json(json_path, doc)
    return doc


def _pieces(scenes: list[str]) -> dict:
    """The generator's description of each generated piece (family, lines), by reference."""
    from sim.scenes.scrap import generate, parse_ref

    out = {}
    for ref in scenes:
        key = parse_ref(ref)
        if key is not None:
            name, _, meta = generate(*key)
            out[ref] = {"name": name, **meta}
    return out


_ARM: dict = {}


def _cut_oracle(cfg: CellConfig, pcfg, scene_ref: str) -> dict:
    """The cut oracle of one scene; an error is recorded, not raised (the bench goes on)."""
    import numpy as np

    from cellctl.bench.cut_oracle import oracle_cut
    from cellctl.bench.oracle import twin_arm
    from sim.scenes import load_scene

    try:
        scene = load_scene(scene_ref)
        if "model" not in _ARM:  # the same arm for every scene: one twin opened for its model
            _ARM["model"] = twin_arm(scene, cfg.twin)[0]
        park = np.asarray(cfg.twin.home_q, dtype=np.float64)
        return oracle_cut(scene, _ARM["model"], park, cfg.motion.collision, pcfg, park_q=park)
    except Exception as e:  # noqa: BLE001 - the bench records it and goes on
        return {"error": f"{type(e).__name__}: {e}"}


def _one_run(cfg, cfg_path, scene, category, planner, seed, out: Path, memory: bool, run_job,
             dry_run_cut: bool = False) -> dict:
    runs_root = out / "runs" / f"seed{seed}"
    before = _subdirs(runs_root)
    base = 0
    if memory:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
    t0 = time.perf_counter()
    run_dir: Path | None
    try:
        result, run_dir = run_job(JobSpec(cfg, cfg_path, scene, planner, seed=seed, noise=True, out=str(runs_root),
                                          dry_run_cut=dry_run_cut))
    except Exception as e:  # noqa: BLE001 - the bench records it and goes on
        import traceback

        result = ScanResult(scene=scene, planner=planner, terminated_by="error",
                            error=f"{type(e).__name__}: {e}\n" + traceback.format_exc(limit=6))
        new = sorted(_subdirs(runs_root) - before)
        run_dir = new[-1] if new else None
    wall = time.perf_counter() - t0
    peak = round(max(tracemalloc.get_traced_memory()[1] - base, 0) / _MIB, 1) if memory else None
    rel = None
    if run_dir is not None:
        run_dir = Path(run_dir)
        try:
            rel = str(run_dir.resolve().relative_to(out.resolve()))
        except ValueError:
            rel = str(run_dir.resolve())
    return run_record(scene, category, planner, seed, result, rel, wall, peak)


def default_out_dir() -> Path:
    return Path("bench") / time.strftime("%Y%m%d-%H%M%S")


def summary_line(doc: dict) -> str:
    runs = doc["runs"]
    errors = sum(1 for r in runs if r["error"])
    wall = doc.get("process", {}).get("wall_s", math.nan)
    rss = doc.get("process", {}).get("max_rss_mb", math.nan)
    return f"{len(runs)} runs, {errors} errors, {wall:.0f} s wall, max RSS {rss:.0f} MiB"


def scoring_bench(args, out: Path) -> int:
    from cellctl.bench import scoring as sb
    from cellctl.config import load_cell_config
    from cellctl.config import cell_planners_config
    from sim.scenes import SCENE_NAMES

    cfg, cfg_path = load_cell_config(args.config)
    pcfg = cell_planners_config(cfg, cfg_path)
    scenes = parse_list(args.scenes, SCENE_NAMES, "scenes", SCENE_NAMES)
    result = sb.measure(cfg, pcfg, scenes, repeats=max(args.seeds or 3, 1))
    print(sb.write(result, out))
    print(f"median speed-up {result['median_speedup']:.2f}x, same best view in {result['same_best_view']} of "
          f"{result['states']} states")
    return 0


def oracle_bench(args, out: Path) -> int:
    from cellctl.bench import oracle as ob
    from cellctl.config import load_cell_config
    from cellctl.config import cell_planners_config
    from sim.scenes import SCENE_NAMES

    cfg, cfg_path = load_cell_config(args.config)
    pcfg = cell_planners_config(cfg, cfg_path)
    scenes = parse_list(args.scenes, SCENE_NAMES, "scenes", SCENE_NAMES)
    print(ob.write(ob.measure(cfg, pcfg, scenes, sensor=args.oracle_sensor, step_deg=args.oracle_step_deg), out))
    return 0


def cli_bench(args) -> int:
    """`cellctl bench` (parser in cellctl/cli.py). Exit 0: all runs ok; 1: some run failed; 130: interrupted."""
    from cellctl.bench import report as bench_report
    from cellctl.config import load_cell_config
    from sim.scenes import SCENE_NAMES

    if args.report:
        doc = bench_report.load_bench(args.report)
        for path in bench_report.write_report(doc, Path(args.report).parent):
            print(path)
        return 0
    if getattr(args, "service", None) is not None:
        scene = args.scenes if args.scenes and args.scenes != "all" else "basket"
        if "," in scene:
            raise ValueError("--service scans one scene: give --scenes NAME")
        return service_bench(args.service, Path(args.out) if args.out else default_out_dir(), clients=args.clients,
                             hz=20.0 if args.hz is None else args.hz, scene=scene)
    if getattr(args, "load", False):
        from cellctl.bench.load import cli_load

        return cli_load(args, Path(args.out) if args.out else default_out_dir())
    if getattr(args, "scoring", False):
        return scoring_bench(args, Path(args.out) if args.out else default_out_dir())
    if getattr(args, "appearance", False):
        from cellctl.bench.appearance import cli_appearance

        return cli_appearance(args, Path(args.out) if args.out else default_out_dir())
    if getattr(args, "oracle", False):
        return oracle_bench(args, Path(args.out) if args.out else default_out_dir())
    q = QUICK if args.quick else {}
    generated = getattr(args, "generated", None)
    if generated is not None:
        from sim.scenes.scrap import scrap_refs

        if generated < 1 or args.scenes:
            raise ValueError("--generated N takes N >= 1 pieces and no --scenes")
        q = {"scenes": tuple(scrap_refs(generated, args.gen_seed)), "planners": ("gnbv",), "seeds": 1}
        scenes = list(q["scenes"])
    else:
        scenes = parse_list(args.scenes, SCENE_NAMES, "scenes", q.get("scenes", SCENE_NAMES))
    planners = parse_list(args.planners, DEFAULT_PLANNERS, "planners", q.get("planners", DEFAULT_PLANNERS))
    seeds = args.seeds if args.seeds is not None else q.get("seeds", DEFAULT_SEEDS)
    if seeds < 1:
        raise ValueError("--seeds must be >= 1")
    out = Path(args.out) if args.out else default_out_dir()
    cfg, cfg_path = load_cell_config(args.config)
    print(f"bench: {len(scenes)} scenes x {len(planners)} planners x {seeds} seeds = "
          f"{len(scenes) * len(planners) * seeds} runs -> {out}", file=sys.stderr)
    try:
        doc = run_bench(cfg, cfg_path, scenes, planners, seeds, out, memory=not args.no_memory, quick=args.quick,
                        dry_run_cut=getattr(args, "dry_run_cut", False),
                        cut_oracle=generated is not None and not getattr(args, "no_cut_oracle", False),
                        generated=None if generated is None else {"n": generated, "gen_seed": args.gen_seed})
    except KeyboardInterrupt:
        if (out / "bench.json").is_file():
            bench_report.write_report(bench_report.load_bench(out / "bench.json"), out)
        print(f"\ninterrupted; the finished runs are in {out}", file=sys.stderr)
        return 130
    bench_report.write_report(doc, out)
    print(f"{summary_line(doc)}\n{out / 'bench.md'}")
    return 0 if not any(r["error"] for r in doc["runs"]) else 1


def service_bench(n: int, out: Path, *, clients: int = 10, hz: float = 20.0, scene: str = "basket") -> int:
    """The service figures, written to OUT/service.json and service.md: status round trip and
    submit-to-first-event latency of a real `cellctl serve` on loopback (cellctl.bench.latency), then
    the status round trip of ``clients`` sessions at ``hz`` each, idle and during a whole scan job
    of ``scene`` with G-NBV."""
    from cellctl.bench.latency import measure, status_under_scan

    if n < 1 or clients < 1 or not 0 < hz <= 1000:
        raise ValueError("--service N and --clients must be >= 1, --hz in (0, 1000]")
    out.mkdir(parents=True, exist_ok=True)
    r = measure(n)
    load = status_under_scan(clients, hz, scene=scene)
    doc = {"schema_version": 1, "created": datetime.now().astimezone().isoformat(timespec="seconds"),
           "machine": machine_info(), "code": code_info(), "service": r, "status_under_scan": load}
    write_json(out / "service.json", doc)

    def row(name, st):
        return (f"| {name} | {st['median']:.2f} | {st['p90']:.2f} | {st['p99']:.2f} | {st['max']:.2f} | {st['n']} |"
                if st else f"| {name} | – | – | – | – | 0 |")
    busy = f"{clients} clients at {hz:g} Hz"
    md = ["# Service latency on loopback", "", f"- created {doc['created']}; {doc['machine']['cpus']} CPUs; "
          f"service start-up {r.get('service_startup_s')} s; SIGTERM to exit {r.get('sigterm_to_exit_s')} s", "",
          "| figure (ms) | median | p90 | p99 | max | n |", "|---|--:|--:|--:|--:|--:|",
          row("status round trip, cell idle", r.get("status_rtt_idle_ms")),
          row("status round trip, during a scan", r.get("status_rtt_busy_ms")),
          row("submit to first event, during a scan", r.get("submit_to_first_event_ms")),
          row(f"status round trip, {busy}, cell idle", load.get("status_rtt_idle_ms")),
          row(f"status round trip, {busy}, during a scan", load.get("status_rtt_scan_ms")), "",
          f"Submit to first event with the cell idle: {r.get('submit_to_first_event_idle_ms')} ms; submit to the "
          f"first exploration step (twin built, first view): {r.get('job_start_ms')} ms.", "",
          f"The scan under {busy}: {load['scene']} with {load['planner']}, {load.get('views')} views, "
          f"{load.get('job_s')} s from submit to its end ({load.get('job_state')}); queries failed or unanswered: "
          f"{load.get('failed_or_unanswered')}.", ""]
    (out / "service.md").write_text("\n".join(md))
    print("\n".join(md))
    return 0
