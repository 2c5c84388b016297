"""Session script: union, greedy and beam-search best k views over the saved S shards."""
import sys, glob, numpy as np
from cellctl.bench.oracle import beam_best, greedy_best
pat = sys.argv[1]
fs = sorted(glob.glob(pat))
d = [np.load(f) for f in fs]
S = np.vstack([x["S"] for x in d]); poses = np.vstack([x["poses"] for x in d]); start = d[0]["start"]; keys = d[0]["keys"]
V = len(keys)
print(fs, "candidates", len(S), "voxels", V, "initial", start.sum())
allv = S.any(0) | start
print("all: %d/%d = %.1f %%" % (allv.sum(), V, 100 * allv.mean()))
print("never seen voxel keys:", keys[~allv].tolist())
cnt = S.sum(0)
print("rarest seen voxels (count of candidates):", sorted(cnt[allv & ~start])[:12])
best = greedy_best(S, start, 4, 300)
print("greedy:", [round(100 * b[0], 1) for b in best])
for n, (share, picks) in enumerate(beam_best(S, start, 4), 1):
    print(f"beam {n} views: {round(share * V)}/{V} = {100 * share:.1f} %", "eyes", [np.round(poses[i][:3, 3], 3).tolist() for i in picks])
