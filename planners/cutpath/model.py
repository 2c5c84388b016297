"""The cut path handed to the executor, and its files: cut_path.json (everything, plain lists) and
cut_path.csv (one row per torch pose, for people and spreadsheets)."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from planners.motion.trajectory import JointPath

SCHEMA_VERSION = 2

OK, UNPLANNED, UNREACHABLE, JUMP, COLLISION, VELOCITY = "ok", "unplanned", "unreachable", "jump", "collision", "velocity"
REASONS = (OK, UNPLANNED, UNREACHABLE, JUMP, COLLISION, VELOCITY)

#: then one column per joint, q1 .. q<dof>, radians (empty where unsolved)
CSV_COLUMNS = ("branch", "index", "x", "y", "z", "nx", "ny", "nz", "tip_x", "tip_y", "tip_z",
               "qx", "qy", "qz", "qw", "speed_mps", "time_s", "feasible", "reason")


@dataclass
class Branch:
    """One cut between two nodes ("J<i>" junction, "E<i>" free end, "L<i>" a closed loop's start).
    Row k of every array is torch pose k; q rows are NaN where no joint solution was found."""

    points: np.ndarray  # (N,3) on the surface, metres, base frame
    normals: np.ndarray  # (N,3) outward unit normals (the torch points along -normal)
    poses: np.ndarray  # (N,4,4) T_base_torch: tip `standoff` off the surface, z into the metal, x along travel
    speeds: np.ndarray  # (N,) m/s along the drawing
    start: str
    end: str
    closed: bool = False
    feasibility: list[str] = field(default_factory=list)  # per pose: one of REASONS
    q: np.ndarray | None = None  # (N,dof)
    times: np.ndarray | None = None  # (N,) s from the first pose
    qd: np.ndarray | None = None  # (N,dof) rad/s, finite differences over `times`
    approach_q: np.ndarray | None = None  # joint solution of the backed-off pose before the cut
    retract_q: np.ndarray | None = None
    approach: JointPath | None = None  # from the previous branch's retract (or the start) to pose 0, via approach_q
    cut: JointPath | None = None  # the cut itself, sampled every dt
    retract: JointPath | None = None  # last pose -> retract_q
    issues: list[str] = field(default_factory=list)  # what keeps a branch from running, beyond the per-pose reasons
    tilt_rad: np.ndarray | None = None  # (N,) torch axis from the inward normal, as the ladder chose it
    source: int | None = None  # index of the drawing branch this run was cut from
    stored_feasible: bool | None = None  # the verdict a file read back holds (its trajectories are not stored)

    def __post_init__(self) -> None:
        n = len(self.points)
        if not self.feasibility:
            self.feasibility = [UNPLANNED] * n
        if self.q is None:
            self.q = np.full((n, 7), np.nan)
        if self.times is None:
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))])
            self.times = s / np.maximum(self.speeds, 1e-12) if n else np.zeros(0)
        if self.qd is None:
            self.qd = np.full_like(self.q, np.nan)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum()) if len(self.points) > 1 else 0.0

    @property
    def feasible(self) -> bool:
        """Every pose solved, continuous and free, and the approach and retract planned."""
        if self.stored_feasible is not None and self.approach is None and self.retract is None:
            return self.stored_feasible
        return (len(self.points) > 0 and all(f == OK for f in self.feasibility) and not self.issues
                and self.approach is not None and self.retract is not None)

    def reversed(self) -> "Branch":
        """The same cut run the other way (poses turned about their z so x still points along
        travel); joint data is dropped: it belongs to the other direction."""
        T = self.poses[::-1].copy()
        T[:, :3, 0:2] *= -1.0
        return Branch(self.points[::-1].copy(), self.normals[::-1].copy(), T, self.speeds[::-1].copy(),
                      self.end, self.start, self.closed)


@dataclass
class Gap:
    """A stretch of a drawing branch left uncut, and why (planners.cutpath.ladder.GAP_REASONS, or
    "too short"). A "reconfigure" gap has length 0: the torch lifts and lands again there."""

    branch: int  # index of the drawing branch
    start: np.ndarray  # (3,) last cut point before it (the branch's start if none)
    end: np.ndarray  # (3,) first cut point after it (the branch's end if none)
    length_m: float
    reason: str
    detail: str = ""
    points: np.ndarray | None = None  # (K,3) the uncut stretch along the drawing, start to end
    normal: np.ndarray | None = None  # (3,) mean outward surface normal over it (where the torch would be)

    def to_json_dict(self) -> dict:
        return {"branch": self.branch, "start": _lists(self.start), "end": _lists(self.end),
                "length_m": round(float(self.length_m), 4), "reason": self.reason, "detail": self.detail,
                "points": _lists(self.points), "normal": _lists(self.normal)}


@dataclass
class CutPath:
    """All branches of one drawing, with the junction and end positions they run between. After
    planning (``plan_cut``) the branches are the cuttable runs in cutting order and ``gaps`` what
    is left uncut."""

    branches: list[Branch]
    junctions: np.ndarray  # (J,3)
    endpoints: np.ndarray  # (E,3)
    config: dict = field(default_factory=dict)  # the CutPathConfig it was made with
    gaps: list[Gap] = field(default_factory=list)
    drawing_length_m: float | None = None  # the drawing's branches before planning split them
    notes: list[str] = field(default_factory=list)  # what the operator should know about the drawing
    spray_width_m: float | None = None  # as the paint's outline measured it (None: not measured there)

    @property
    def feasible(self) -> bool:
        return bool(self.branches) and all(b.feasible for b in self.branches)

    @property
    def length_m(self) -> float:
        return float(sum(b.length_m for b in self.branches))

    @property
    def cut_length_m(self) -> float:
        """Length the torch will cut: the feasible runs."""
        return float(sum(b.length_m for b in self.branches if b.feasible))

    @property
    def cut_fraction(self) -> float:
        """Share of the drawing's length that will be cut (0 when there is no drawing)."""
        total = self.drawing_length_m if self.drawing_length_m is not None else self.length_m
        return min(1.0, self.cut_length_m / total) if total > 0 else 0.0

    # ------------------------------------------------------------------ files

    def to_json_dict(self) -> dict:
        """Plain lists and numbers only; NaN (no joint solution) becomes null. Dense joint
        trajectories are left out (the executor re-times approach and retract anyway): their
        end configurations and durations are in."""
        def dur(p: JointPath | None):
            return None if p is None else float(p.duration)

        branches = []
        for i, b in enumerate(self.branches):
            branches.append({
                "index": i, "start": b.start, "end": b.end, "closed": bool(b.closed),
                "length_m": b.length_m, "feasible": b.feasible, "issues": list(b.issues),
                "points": _lists(b.points), "normals": _lists(b.normals), "poses": _lists(b.poses),
                "speeds_mps": _lists(b.speeds), "times_s": _lists(b.times), "feasibility": list(b.feasibility),
                "q": _lists(b.q), "qd": _lists(b.qd),
                "approach_q": _lists(b.approach_q), "retract_q": _lists(b.retract_q),
                "approach_duration_s": dur(b.approach), "cut_duration_s": dur(b.cut),
                "retract_duration_s": dur(b.retract),
                "tilt_deg": None if b.tilt_rad is None else _lists(np.degrees(b.tilt_rad)),
                "source": b.source,
            })
        return {
            "schema_version": SCHEMA_VERSION,
            "units": {"length": "m", "angle": "rad", "time": "s", "speed": "m/s"},
            "frame": "robot base",
            "feasible": self.feasible,
            "length_m": self.length_m,
            "drawing_length_m": self.drawing_length_m,
            "cut_length_m": self.cut_length_m,
            "cut_fraction": round(self.cut_fraction, 4),
            "gaps": [g.to_json_dict() for g in self.gaps],
            "notes": list(self.notes),
            "spray_width_m": self.spray_width_m,
            "junctions": _lists(self.junctions),
            "endpoints": _lists(self.endpoints),
            "config": self.config,
            "branches": branches,
        }

    @classmethod
    def from_json_dict(cls, d: dict) -> "CutPath":
        """Inverse of to_json_dict (joint trajectories are not stored, so they come back None)."""
        version = d.get("schema_version")
        if version != SCHEMA_VERSION:
            raise ValueError(f"cut path schema_version {version!r} is not {SCHEMA_VERSION}")

        def arr(x, shape_tail):
            return None if x is None else np.array(x, dtype=np.float64).reshape((-1, *shape_tail))

        branches = []
        for b in d["branches"]:
            n = len(b["points"])
            dof = len(b["q"][0]) if n else 7
            br = Branch(arr(b["points"], (3,)), arr(b["normals"], (3,)), arr(b["poses"], (4, 4)),
                        np.array(b["speeds_mps"], dtype=np.float64), b["start"], b["end"], bool(b["closed"]),
                        list(b["feasibility"]), arr(b["q"], (dof,)), np.array(b["times_s"], dtype=np.float64),
                        arr(b["qd"], (dof,)))
            br.approach_q = None if b["approach_q"] is None else np.array(b["approach_q"], dtype=np.float64)
            br.retract_q = None if b["retract_q"] is None else np.array(b["retract_q"], dtype=np.float64)
            br.issues = list(b["issues"])
            br.tilt_rad = None if b.get("tilt_deg") is None else np.radians(np.array(b["tilt_deg"], dtype=np.float64))
            br.source = b.get("source")
            br.stored_feasible = bool(b["feasible"])
            branches.append(br)
        gaps = [Gap(int(g["branch"]), np.array(g["start"], dtype=np.float64), np.array(g["end"], dtype=np.float64),
                    float(g["length_m"]), str(g["reason"]), str(g.get("detail", "")),
                    None if g.get("points") is None else np.array(g["points"], dtype=np.float64).reshape(-1, 3),
                    None if g.get("normal") is None else np.array(g["normal"], dtype=np.float64))
                for g in d.get("gaps", [])]
        return cls(branches, arr(d["junctions"], (3,)), arr(d["endpoints"], (3,)), dict(d.get("config", {})), gaps,
                   d.get("drawing_length_m"), list(d.get("notes", [])), d.get("spray_width_m"))

    def write(self, folder: str | Path) -> tuple[Path, Path]:
        """cut_path.json and cut_path.csv in `folder` (created). Returns their paths."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        jpath, cpath = folder / "cut_path.json", folder / "cut_path.csv"
        jpath.write_text(json.dumps(self.to_json_dict(), indent=1, allow_nan=False))
        with cpath.open("w", newline="") as f:
            w = csv.writer(f)
            dof = max((b.q.shape[1] for b in self.branches), default=7)
            w.writerow([*CSV_COLUMNS, *(f"q{i}" for i in range(1, dof + 1))])
            for i, b in enumerate(self.branches):
                if len(b) == 0:
                    continue
                quat = Rotation.from_matrix(b.poses[:, :3, :3]).as_quat()  # x, y, z, w
                for k in range(len(b)):  # file rows
                    q = ["" if not math.isfinite(v) else f"{v:.6f}" for v in b.q[k]]
                    w.writerow([i, k, *(f"{v:.6f}" for v in b.points[k]), *(f"{v:.6f}" for v in b.normals[k]),
                                *(f"{v:.6f}" for v in b.poses[k, :3, 3]), *(f"{v:.8f}" for v in quat[k]),
                                f"{b.speeds[k]:.6f}", f"{b.times[k]:.4f}", int(b.feasibility[k] == OK),
                                b.feasibility[k], *q])
        return jpath, cpath

    @classmethod
    def read(cls, folder: str | Path) -> "CutPath":
        path = Path(folder)
        path = path / "cut_path.json" if path.is_dir() else path
        return cls.from_json_dict(json.loads(path.read_text()))


def _lists(a):
    """ndarray -> nested lists with NaN as None (strict JSON); None stays None."""
    if a is None:
        return None
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 0:
        return None if not math.isfinite(float(a)) else float(a)
    out = a.astype(object)
    out[~np.isfinite(a)] = None
    return out.tolist()
