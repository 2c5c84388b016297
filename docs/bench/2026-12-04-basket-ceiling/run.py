# Session script (issue 16, twelfth step): render shard k of K of the twin oracle on the basket at a finer step.
# Usage, from the repo root: .venv/bin/python docs/bench/2026-12-04-basket-ceiling/run.py 10 0 2 (and 10 1 2 beside it);
# then analyse.py "/tmp/orc/S_10.0_std_*.npz".
# Ran at 68731cf: from the thirteenth step on, the oracle's candidates start 25 deg below their aim and
# pass the arm's own check (oracle.ArmTakes), and oracle.arm_reach is gone: this script runs only at
# that commit (git checkout 68731cf), which reproduces analyse.out.
"""Session script: the twin oracle on the basket at a finer step, shard k of K, saving S."""
import sys, time, numpy as np
from cellctl.bench import oracle as ob
from cellctl.config import load_cell_config
from planners.config import load_planners_config
from sim.scenes import load_scene
from sim.twin import Twin

step, k, K = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
radii = tuple(float(r) for r in sys.argv[4].split(",")) if len(sys.argv) > 4 else ob.RADII_M
ob.RADII_M = radii
cfg, p = load_cell_config("configs/cell.sim.yaml")
pcfg = load_planners_config(p.parent / cfg.planners_config)
twin_cfg = cfg.twin.model_copy(update={"camera": cfg.twin.camera.model_copy(update={"noise": False})})
scene = load_scene("basket")
eyes, aims = ob.reachable_candidates(scene.gt_points, pcfg, ob.arm_reach(scene, twin_cfg), step)
poses = ob.rolled_poses(eyes, aims)
idx = np.arange(len(poses))[k::K]
t = time.time()
with Twin(scene, twin_cfg) as twin:
    tv = ob.TwinViews(twin, scene.gt_points, pcfg.coverage_voxel_m, pcfg.color)
    start = tv.seen_pose(scene.initial_view_candidates[0])
    S = np.array([tv.seen_pose(poses[i]) for i in idx])
np.savez(f"/tmp/orc/S_{step}_{sys.argv[4] if len(sys.argv) > 4 else 'std'}_{k}of{K}.npz", S=S, idx=idx, poses=poses[idx], start=start, keys=tv.keys)
print(len(poses), len(idx), time.time() - t)
