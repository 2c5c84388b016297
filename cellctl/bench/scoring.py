"""`cellctl bench --scoring`: what coarse-to-fine candidate scoring saves, measured in one process.

For every scene, the grid after its initial view and after the view G-NBV picks next (both rendered
by the twin at the poses themselves, no arm motion) is planned from twice per repeat: with every
candidate cast with the full ray bundle (`coarse_ray_factor: 1`, the paper's way) and with the
configured coarse-to-fine scoring. The figures are medians of the same states in the same process,
so the ratio does not depend on the machine's load at the time, and the chosen views are compared."""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np

from cellctl.config import CellConfig
from cellctl.scan.job import ScanJob
from planners.base import ScanState
from planners.config import PlannersConfig
from planners.gnbv import GuidedNBV
from sim.scenes import load_scene
from sim.twin import Twin


def gnbv_states(cfg: CellConfig, pcfg: PlannersConfig, scene_name: str) -> list[ScanState]:
    """The scan state after the initial view and after the next one G-NBV (exact scoring) picks."""
    scene = load_scene(scene_name)
    twin_cfg = cfg.twin.model_copy(update={"camera": cfg.twin.camera.model_copy(update={"noise": False}),
                                           "execution": "teleport"})
    states = []
    with Twin(scene, twin_cfg) as twin:
        job = ScanJob(twin.arm, twin.camera, "gnbv", pcfg, cfg.motion)
        q = twin.arm.joint_positions()  # the arm stays at home, out of every view
        T = scene.initial_view_candidates[0]
        viewpoints: list[np.ndarray] = []
        exact = pcfg.model_copy(update={"nbv": pcfg.nbv.model_copy(update={"coarse_ray_factor": 1})})
        for k in range(2):
            cloud = job.process(twin.camera.capture_at(T), T, q)
            viewpoints.append(T[:3, 3])
            state = ScanState(k, job.grid, job.surface, job.drawing, cloud, T, scene.initial_view_candidates[0],
                              job.K, job.image_size, np.array(viewpoints))
            states.append(_snapshot(state))
            plan = GuidedNBV(exact).next_view(state)
            if plan.stop or not len(plan.poses):
                break
            T = plan.poses[0]
    return states


def _snapshot(state: ScanState) -> ScanState:
    """A copy whose grid later views do not change."""
    import copy

    return copy.deepcopy(state)


def _plan(pcfg: PlannersConfig, state: ScanState) -> tuple[float, np.ndarray | None, float]:
    planner = GuidedNBV(pcfg)
    t = time.perf_counter()
    plan = planner.next_view(state)
    dt = time.perf_counter() - t
    pose = plan.poses[0] if len(plan.poses) else None
    return dt, pose, float(plan.gain[0]) if len(plan.gain) else 0.0


def measure(cfg: CellConfig, pcfg: PlannersConfig, scenes: list[str], repeats: int = 3) -> dict:
    exact = pcfg.model_copy(update={"nbv": pcfg.nbv.model_copy(update={"coarse_ray_factor": 1})})
    rows = []
    for name in scenes:
        for state in gnbv_states(cfg, pcfg, name):
            _plan(pcfg, state)  # warm caches (numba, allocator) before either is timed
            t_exact, t_c2f = [], []
            for _ in range(repeats):  # interleaved, so load drifts hit both alike
                dt, pose_e, gain_e = _plan(exact, state)
                t_exact.append(dt)
                dt, pose_c, gain_c = _plan(pcfg, state)
                t_c2f.append(dt)
            same = pose_e is not None and pose_c is not None and np.allclose(pose_e, pose_c, atol=1e-9)
            moved = float(np.linalg.norm(pose_e[:3, 3] - pose_c[:3, 3])) if pose_e is not None and pose_c is not None \
                else None
            rows.append({"scene": name, "step": state.step, "exact_s": statistics.median(t_exact),
                         "coarse_to_fine_s": statistics.median(t_c2f),
                         "speedup": statistics.median(t_exact) / max(statistics.median(t_c2f), 1e-9),
                         "same_best_view": bool(same), "best_view_offset_m": moved,
                         "best_gain_exact": gain_e, "best_gain_coarse_to_fine": gain_c})
    speedups = [r["speedup"] for r in rows]
    return {"repeats": repeats, "coarse_ray_factor": pcfg.nbv.coarse_ray_factor, "refine_top": pcfg.nbv.refine_top,
            "rays": [pcfg.nbv.rays_w, pcfg.nbv.rays_h], "rows": rows,
            "median_speedup": statistics.median(speedups) if speedups else None,
            "same_best_view": sum(r["same_best_view"] for r in rows), "states": len(rows)}


def write(result: dict, out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    (out / "scoring.json").write_text(json.dumps(result, indent=2))
    lines = [
        "# Coarse-to-fine candidate scoring (G-NBV), same states, same process",
        "",
        f"Every candidate first cast with a {result['coarse_ray_factor']}x sparser ray bundle per axis, the best "
        f"{result['refine_top']} by Q again with the full {result['rays'][0]} x {result['rays'][1]}; against every "
        f"candidate with the full bundle. Medians of {result['repeats']} interleaved plans per state.",
        "",
        "| scene | step | exact (s) | coarse-to-fine (s) | speed-up | same best view | offset (m) |",
        "|---|--:|--:|--:|--:|:-:|--:|",
    ]
    for r in result["rows"]:
        off = "" if r["best_view_offset_m"] is None else f"{r['best_view_offset_m']:.3f}"
        lines.append(f"| {r['scene']} | {r['step']} | {r['exact_s']:.3f} | {r['coarse_to_fine_s']:.3f} | "
                     f"{r['speedup']:.2f}x | {'yes' if r['same_best_view'] else 'no'} | {off} |")
    lines += ["", f"Median speed-up {result['median_speedup']:.2f}x; the same best view in "
              f"{result['same_best_view']} of {result['states']} states.", ""]
    (out / "scoring.md").write_text("\n".join(lines))
    return out / "scoring.md"
