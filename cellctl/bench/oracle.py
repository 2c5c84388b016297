"""`cellctl bench --oracle`: how many views a planner that knew the piece would need.

The planners see a piece for the first time; this bench does not. For every scene it casts the
true mesh (Open3D) from a dense set of camera poses round the painted line (shells 0.3-0.6 m,
every 7.5 degrees from 25 degrees below the aim, kept where the arm can take them: ``ArmTakes``),
each aimed at one of `AIMS` points of the paint (its centre and the farthest-point samples of it:
on a basket one aim at the centre frames neither end of the line well),
with the twin's camera: its field of view, range and grazing limit. The searches run twice: over
every pose the arm takes, and over those above the planners' camera floor (`min_camera_z_m`), so
the price of that floor is measured rather than assumed. Each position sees a set of
the ground truth's coverage voxels. From the scene's initial view, views are added greedily (the
one that adds most), starting from each of the `firsts` best first views, and by a beam search;
the best coverage after 1, 2, 3, 4 views is kept. So the figures are what an all-knowing planner
reaches with a noise-free camera, bounded by this candidate set and these searches: a reference
for the planners' viewpoint counts, not a proof of the optimum.

Beside it, G-NBV's first step is put to the truth: its candidates after the initial view (the
noise-free twin, as `--scoring` renders it) are cast the same way, and how much of the line not yet
seen its top-ranked views would show is set against the best view in its own candidate set. This
tells a gain that misranks from a candidate set that lacks the view."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from scipy.stats import spearmanr

from cellctl.bench.scoring import gnbv_states
from cellctl.config import CellConfig, MotionConfig
from cellctl.scan.cut import torch_shape
from planners.clouds import frame_to_base_cloud, voxel_keys
from planners.paint_color import PaintSegmenter
from planners.config import PlannersConfig
from planners.gnbv import GuidedNBV
from planners.motion.collision import CollisionChecker, RobotCollisionModel
from planners.motion.ik_batch import solve_axis_ik_batch, spread_seeds
from planners.motion.kinematics import Kinematics
from planners.motion.reach_map import reach_map_for
from planners.views import look_at_rotations, poses_from, quarter_turn
from sim.config import D435Config
from sim.scenes import load_scene
from sim.twin import Twin

RADII_M = (0.3, 0.4, 0.5, 0.6)
STEP_DEG = 7.5
AIMS = 5
LOWEST_DEG = -25.0  # candidates from this elevation below their aim: the arm's collision model, not a height, decides
SCENE_VOXEL_M = 0.01  # the true piece, voxelized for the collision check


def aim_points(gt: np.ndarray, n: int = AIMS) -> np.ndarray:
    """The paint's centre and n - 1 farthest-point samples of it (the line's ends first)."""
    aims = [gt.mean(axis=0)]
    d = np.linalg.norm(gt - aims[0], axis=1)
    for _ in range(n - 1):
        aims.append(gt[int(np.argmax(d))])
        d = np.minimum(d, np.linalg.norm(gt - aims[-1], axis=1))
    return np.array(aims)


def candidate_eyes(centre: np.ndarray, min_z: float, step_deg: float = STEP_DEG) -> np.ndarray:
    """Camera positions on shells round ``centre``, above ``min_z``, every ``step_deg`` from
    ``LOWEST_DEG`` of elevation."""
    el = np.radians(np.arange(LOWEST_DEG, 90.0, step_deg))
    az = np.radians(np.arange(0.0, 360.0, step_deg))
    E, A = np.meshgrid(el, az, indexing="ij")
    dirs = np.column_stack([(np.cos(E) * np.cos(A)).ravel(), (np.cos(E) * np.sin(A)).ravel(), np.sin(E).ravel()])
    eyes = np.vstack([centre + r * dirs for r in RADII_M])
    return eyes[eyes[:, 2] > min_z]


def twin_arm(scene, twin_cfg):
    """(the twin's arm model, its start configuration): the same for every scene; a twin is opened for them."""
    with Twin(scene, twin_cfg) as twin:
        return twin.arm.model, twin.arm.joint_positions()


def reachable_candidates(gt: np.ndarray, reach, min_z: float, step_deg: float = STEP_DEG) -> tuple[np.ndarray, np.ndarray]:
    """(eyes, aims): the candidate positions round each aim point of the paint, above ``min_z``, kept
    where ``reach`` says the arm can look from there at the aim."""
    eyes, aims = [], []
    for aim in aim_points(gt):
        e = candidate_eyes(aim, min_z, step_deg)
        axes = aim - e
        e = e[reach.reachable(e, axes / np.linalg.norm(axes, axis=1, keepdims=True))]
        eyes.append(e)
        aims.append(np.broadcast_to(aim, e.shape))
    return np.vstack(eyes), np.vstack(aims)


class ArmTakes:
    """Which camera poses the arm can take, as the scan's view motion does: an IK solution inside the
    joint limits (the scan's own margin) at the pose's roll or its half turn (the image frames the
    same rectangle), else at any roll about the optical axis, clear of the floor, of itself, of the
    torch on the hand and of the piece given to ``piece`` (voxelized, with the scan's clearance). The
    capability map alone is optimistic: it knows neither the floor nor the piece, and a pose it
    passes may have no solution at all. The arm's models are built once; only the piece changes."""

    def __init__(self, arm_model, q_start: np.ndarray, mcfg: MotionConfig, pcfg: PlannersConfig):
        self.kin = Kinematics.from_arm_model(arm_model)
        robot = RobotCollisionModel.from_arm_model(arm_model, mcfg.collision, torch=torch_shape(pcfg.cutpath))
        self.checker = CollisionChecker(robot, mcfg.collision)
        self.margin = mcfg.ik_margin_rad
        self.seeds = spread_seeds(self.kin, q_start, mcfg.ik_seeds, self.margin)

    def piece(self, mesh_vertices: np.ndarray, mesh_faces: np.ndarray) -> ArmTakes:
        """The piece the arm must keep clear of: its surface, voxelized at ``SCENE_VOXEL_M``."""
        mesh = trimesh.Trimesh(np.asarray(mesh_vertices, np.float64), np.asarray(mesh_faces, np.int64), process=False)
        v = SCENE_VOXEL_M
        pts = trimesh.sample.sample_surface(mesh, max(20_000, int(mesh.area / (v / 4) ** 2)), seed=0)[0]
        self.checker.set_scene(np.unique(np.floor(pts / v).astype(np.int64), axis=0) * v + v / 2, v)
        return self

    def __call__(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(taken (N,) bool, the camera poses (N,4,4) the arm takes there) for camera poses (N,4,4):
        one batch per seed and roll, over the poses still open."""
        P, Z, X = poses[:, :3, 3], poses[:, :3, 2], poses[:, :3, 0]
        taken = np.zeros(len(poses), dtype=bool)
        Q_taken = np.zeros((len(poses), self.kin.dof))
        for roll in (1.0, -1.0, None):  # the pose's roll, its half turn, then any roll
            for q0 in self.seeds:
                todo = np.flatnonzero(~taken)
                if len(todo) == 0:
                    break
                Q, ok = solve_axis_ik_batch(self.kin, P[todo], Z[todo], np.tile(q0, (len(todo), 1)), margin=self.margin,
                                            x_axes=None if roll is None else roll * X[todo])
                free = np.zeros(len(todo), dtype=bool)
                if ok.any():
                    free[ok] = self.checker.free(Q[ok])
                taken[todo[free]] = True
                Q_taken[todo[free]] = Q[free]
        actual = np.array(poses, dtype=np.float64, copy=True)
        if taken.any():
            actual[taken] = self.kin.fk_batch(Q_taken[taken])
        return taken, actual


class TrueViews:
    """Which ground-truth coverage voxels a camera at an eye, aimed at the paint, sees of the true mesh."""

    def __init__(self, mesh_vertices: np.ndarray, mesh_faces: np.ndarray, gt: np.ndarray, voxel: float,
                 cam: D435Config):
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh_vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(mesh_faces, np.uint32)))
        self.gt = np.asarray(gt, dtype=np.float64)
        self.normals = self.scene.compute_closest_points(
            o3d.core.Tensor(self.gt.astype(np.float32)))["primitive_normals"].numpy().astype(np.float64)
        self.keys, self.voxel_of = np.unique(voxel_keys(self.gt, voxel), return_inverse=True)
        self.cam = cam
        self.centre = self.gt.mean(axis=0)

    def seen(self, eye: np.ndarray, aim: np.ndarray | None = None) -> np.ndarray:
        """(V,) bool over the coverage voxels, for the camera at ``eye`` looking at ``aim``
        (the paint's centre by default), roll with the image's up to world up."""
        aim = self.centre if aim is None else aim
        z = (aim - eye) / np.linalg.norm(aim - eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
        return self._seen(eye, x, np.cross(z, x), z)

    def seen_pose(self, T: np.ndarray) -> np.ndarray:
        """``seen`` for a camera pose T (4,4), its roll included (the image's wide axis along x)."""
        return self._seen(T[:3, 3], T[:3, 0], T[:3, 1], T[:3, 2])

    def _seen(self, eye: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        c = self.cam
        d = self.gt - eye
        dist = np.linalg.norm(d, axis=1)
        u = d / dist[:, None]
        cz = u @ z
        ok = (cz > 0) & (np.abs(np.arctan2(u @ x, cz)) < math.radians(c.hfov_deg / 2))
        ok &= np.abs(np.arctan2(u @ y, cz)) < math.radians(c.vfov_deg / 2)
        depth = dist * cz
        ok &= (depth > c.min_range_m) & (depth < c.max_range_m)
        ok &= np.abs(np.einsum("ij,ij->i", u, self.normals)) > math.cos(math.radians(c.max_incidence_deg))
        rays = np.hstack([np.repeat(eye[None], len(u), 0), u]).astype(np.float32)
        ok &= np.abs(self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() - dist) < 0.002
        out = np.zeros(len(self.keys), dtype=bool)
        out[np.unique(self.voxel_of[ok])] = True
        return out


class TwinViews:
    """The same question asked of the twin's own sensor: a frame rendered at the pose (noise-free
    depth, with the D435's range, grazing and depth-discontinuity dropouts) whose pixels pass the
    planners' paint filter. Thin stock loses its silhouette to the discontinuity rule, which a
    mesh cast does not model: on the basket this is what bounds coverage."""

    def __init__(self, twin: Twin, gt: np.ndarray, voxel: float, pcfg, T0: np.ndarray) -> None:
        self.twin, self.voxel = twin, voxel
        self.keys = np.unique(voxel_keys(np.asarray(gt, dtype=np.float64), voxel))
        # the paint's colour fitted on the initial view, as a scan fits it
        self.paint = PaintSegmenter(pcfg.paint)
        cloud = self._cloud(T0)
        self.paint.fit_view(cloud.rgb, cloud.xyz, pcfg.grid.lo_m[2], workspace=(pcfg.grid.lo_m, pcfg.grid.hi_m))

    def _cloud(self, T: np.ndarray):
        cam = self.twin.camera
        rgb, raw = cam.render(T)
        return frame_to_base_cloud(rgb, cam.sensor_depth(raw), cam.K, T)

    def seen_pose(self, T: np.ndarray) -> np.ndarray:
        cloud = self._cloud(T)
        paint = self.paint.paint_points(cloud.rgb, cloud.xyz)
        return np.isin(self.keys, np.unique(voxel_keys(cloud.xyz[paint], self.voxel)))


def rolled_poses(eyes: np.ndarray, aims: np.ndarray) -> np.ndarray:
    """(2N,4,4): each eye looking at its aim with the image's up to world up, and rolled 90 deg
    (the arm keeps a planned roll with motion.framed_views)."""
    R = look_at_rotations(eyes, aims)
    return np.stack([poses_from(eyes, R), poses_from(eyes, quarter_turn(R))], axis=1).reshape(-1, 4, 4)


def greedy_best(S: np.ndarray, start: np.ndarray, views: int, firsts: int) -> list[tuple[float, list[int]]]:
    """For n = 1..views: (the best coverage share after n views added greedily to ``start``, from
    each of the ``firsts`` best first views; the rows of ``S`` it took)."""
    gain = (S & ~start).sum(axis=1)
    best = [(-1.0, [])] * views
    for a in np.argsort(-gain)[:firsts]:
        cov, picks = start | S[a], [int(a)]
        for n in range(views):
            if n:
                b = int(np.argmax((S & ~cov).sum(axis=1)))
                cov, picks = cov | S[b], picks + [b]
            if cov.mean() > best[n][0]:
                best[n] = (float(cov.mean()), list(picks))
    return best


def beam_best(S: np.ndarray, start: np.ndarray, views: int, width: int = 400,
              expand: int = 60) -> list[tuple[float, list[int]]]:
    """For n = 1..views: the best coverage share of n views added to ``start`` by a beam search (the
    ``width`` best distinct coverages kept per n, each grown by its ``expand`` views of most new
    voxels), with the rows it took. Greedy picks the view of most new voxels and can leave two
    stragglers that no single view joins; the beam keeps the sets that leave joinable ones."""
    beams, best = [(start, [])], []
    for _ in range(views):
        grown = []
        for cov, picks in beams:
            new = (S & ~cov).sum(axis=1)
            for a in np.argsort(-new, kind="stable")[:expand]:
                grown.append((cov | S[a], picks + [int(a)]))
        grown.sort(key=lambda g: -int(g[0].sum()))
        kept, beams = set(), []
        for cov, picks in grown:
            if cov.tobytes() not in kept and len(beams) < width:
                kept.add(cov.tobytes())
                beams.append((cov, picks))
        best.append((float(beams[0][0].mean()), beams[0][1]))
    return best


def first_step(tv: TrueViews, state, pcfg: PlannersConfig) -> dict:
    """G-NBV's plan on ``state`` against the truth: the share of the ground truth's voxels that the
    drawing lacks and each candidate would see, for its top five by Q and the best of its set."""
    have = np.isin(tv.keys, np.unique(voxel_keys(state.drawing.xyz, float(pcfg.coverage_voxel_m))))
    plan = GuidedNBV(pcfg).next_view(state)
    if plan.stop or len(plan.poses) == 0:
        return {"candidates": 0}
    new = np.array([100 * (tv.seen(T[:3, 3], T[:3, 3] + T[:3, 2]) & ~have).mean() for T in plan.poses])
    best = int(np.argmax(new))
    rho = spearmanr(plan.gain, new).correlation if len(new) > 2 else float("nan")
    return {"candidates": int(len(new)), "drawing_percent": round(100 * float(have.mean()), 1),
            "top5_new_percent": np.round(new[:5], 1).tolist(), "best_new_percent": round(float(new[best]), 1),
            "best_rank": best + 1, "best_eye": np.round(plan.poses[best][:3, 3], 3).tolist(),
            "gain_rank_correlation": None if not np.isfinite(rho) else round(float(rho), 2)}


def _searched(S: np.ndarray, start: np.ndarray, poses: np.ndarray, views: int, firsts: int) -> dict:
    """The better of greedy and beam after 1..views views over the candidates S (rows of ``poses``)."""
    if len(S) == 0:
        return {"candidates": 0, "percent_after": [round(100 * float(start.mean()), 1)] * views,
                "all_candidates_percent": round(100 * float(start.mean()), 1), "eyes": [], "looking": []}
    best = [max(g, b, key=lambda r: r[0]) for g, b in zip(greedy_best(S, start, views, firsts),
                                                          beam_best(S, start, views))]
    return {"candidates": int(len(S)), "percent_after": [round(100 * b[0], 1) for b in best],
            "all_candidates_percent": round(100 * float((S.any(axis=0) | start).mean()), 1),
            "eyes": [[np.round(poses[i][:3, 3], 3).tolist() for i in b[1]] for b in best],
            "looking": [[np.round(poses[i][:3, 2], 3).tolist() for i in b[1]] for b in best]}


def measure(cfg: CellConfig, pcfg: PlannersConfig, scenes: list[str], views: int = 4, firsts: int = 150,
            sensor: str = "cast", step_deg: float = STEP_DEG) -> dict:
    """``sensor``: "cast" (the true mesh cast with the camera's field, range and grazing limit, two
    poses per millisecond) or "twin" (each candidate rendered by the twin at two rolls, about 0.3 s
    each; G-NBV's first step is then left out). Each scene's row holds the searches over every pose
    the arm takes, and under ``above_floor`` the same over those above the planners' camera floor."""
    if sensor not in ("cast", "twin"):
        raise ValueError(f"sensor must be 'cast' or 'twin', got {sensor!r}")
    voxel = pcfg.coverage_voxel_m
    floor = pcfg.nbv.min_camera_z_m
    twin_cfg = cfg.twin.model_copy(update={"camera": cfg.twin.camera.model_copy(update={"noise": False})})
    rows = []
    takes = ArmTakes(*twin_arm(load_scene(scenes[0]), twin_cfg), cfg.motion, pcfg)
    reach = reach_map_for(takes.kin)  # a cheap first cut before the IK
    for name in scenes:
        scene = load_scene(name)
        eyes, aims = reachable_candidates(scene.gt_points, reach, cfg.motion.collision.floor_margin_m, step_deg)
        poses = rolled_poses(eyes, aims)
        offered = len(poses)
        taken, actual = takes.piece(scene.full_mesh.vertices, scene.full_mesh.faces)(poses)
        poses = actual[taken]
        T0 = scene.initial_view_candidates[0]
        if sensor == "cast":
            tv = TrueViews(scene.full_mesh.vertices, scene.full_mesh.faces, scene.gt_points, voxel, twin_cfg.camera)
            S = np.array([tv.seen_pose(T) for T in poses], dtype=bool).reshape(len(poses), -1)
            start = tv.seen(T0[:3, 3], T0[:3, 3] + T0[:3, 2])
            first = first_step(tv, gnbv_states(cfg, pcfg, name)[0], pcfg)
        else:
            with Twin(scene, twin_cfg) as twin:
                tv = TwinViews(twin, scene.gt_points, voxel, pcfg, T0)
                S = np.array([tv.seen_pose(T) for T in poses], dtype=bool).reshape(len(poses), -1)
                start = tv.seen_pose(T0)
            first = None
        high = poses[:, 2, 3] >= floor
        rows.append({"scene": name, "category": scene.category, "voxels": int(len(tv.keys)),
                     "initial_percent": round(100 * float(start.mean()), 1), "offered": offered,
                     **_searched(S, start, poses, views, firsts),
                     "above_floor": _searched(S[high], start, poses[high], views, firsts),
                     "gnbv_first_step": first})
    return {"voxel_m": voxel, "radii_m": list(RADII_M), "step_deg": step_deg, "lowest_deg": LOWEST_DEG,
            "aims": AIMS, "firsts": firsts, "sensor": sensor, "camera_floor_m": floor, "scenes": rows}


def write(result: dict, out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    (out / "oracle.json").write_text(json.dumps(result, indent=1))
    n = len(result["scenes"][0]["percent_after"]) if result["scenes"] else 0
    twin = result.get("sensor") == "twin"
    camera = ("the twin's own frames (noise-free depth with its range, grazing and depth-discontinuity dropouts, the "
              "paint filter), each position at two rolls" if twin else "the true mesh cast with the twin's camera "
              "without noise (field of view, range, grazing limit)")
    floor = result.get("camera_floor_m")
    lines = ["# What a planner that knew the piece would need (`cellctl bench --oracle`)", "",
             "Coverage % of the ground truth's voxels after the initial view and n more, the better of greedy from "
             f"each of the {result['firsts']} best first views and a beam search, over camera poses on shells "
             f"{result['radii_m']} m every {result['step_deg']} deg from {result.get('lowest_deg', 5.0)} deg of "
             f"elevation, each aimed at one of {result['aims']} points of the paint (its centre and farthest-point "
             f"samples), kept where the arm can take them (collision-free IK: floor, itself, torch, the true piece); "
             f"seen by {camera}. Each scene twice: every pose the arm takes, and only those above the planners' camera "
             f"floor ({floor} m). \"offered\": poses before the arm's check; \"all\": every candidate together, the most "
             "any number of these views can show.", "",
             "| scene | category | voxels | poses | offered | candidates | initial | "
             + " | ".join(f"{k} views" for k in range(1, n + 1)) + " | all |", "|---|---|--:|---|--:|--:|--:|" + "--:|" * (n + 1)]
    for r in result["scenes"]:
        for where, q in (("the arm takes", r), (f"above {floor} m", r.get("above_floor"))):
            if q is None:
                continue
            lines.append(f"| {r['scene']} | {r['category'] or '-'} | {r['voxels']} | {where} | {r.get('offered', '')} | "
                         f"{q['candidates']} | {r['initial_percent']} | " + " | ".join(str(p) for p in q["percent_after"])
                         + f" | {q.get('all_candidates_percent', '')} |")
    if not twin:
        lines += ["", "## G-NBV's first step against the truth", "",
                  "After the initial view (noise-free twin; every candidate, no reach filter): the share of the ground truth's voxels the drawing lacks that "
                  "each candidate would see, for G-NBV's top five by Q and for the best candidate of its own set.", "",
                  "| scene | candidates | drawing after the initial view (%) | top five by Q (% new) | best candidate (% new) | its rank by Q | rank correlation of gain and truth |",
                  "|---|--:|--:|---|--:|--:|--:|"]
        for r in result["scenes"]:
            f = r.get("gnbv_first_step") or {}
            if not f.get("candidates"):
                lines.append(f"| {r['scene']} | 0 | | | | | |")
                continue
            lines.append(f"| {r['scene']} | {f['candidates']} | {f['drawing_percent']} | "
                         + ", ".join(str(x) for x in f["top5_new_percent"])
                         + f" | {f['best_new_percent']} | {f['best_rank']} | {f['gain_rank_correlation']} |")
    path = out / "oracle.md"
    path.write_text("\n".join(lines) + "\n")
    return path
