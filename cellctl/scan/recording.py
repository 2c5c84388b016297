"""Rerun recording of a scan: clouds, camera frusta, frontier, candidates, chosen views, drawing, the
cut, all on a `step` timeline in the robot base frame ("world"), and a blueprint that opens on what
matters: the 3-D view framed on the piece, the camera with the detected paint over it, coverage per step.

Once the piece is known (``log_scene``), each view's cloud is cropped to the piece's box (plus a margin)
and what lies on its support plane (table, floor) is dimmed, so the picture is the piece, not the cell."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

log = logging.getLogger("cellctl.scan.recording")
_PAINT = np.array([230, 30, 30], dtype=np.uint8)


# What scan.rrd keeps of each view, so a job writes tens of MB, not hundreds: the colour image as JPEG,
# the depth in whole millimetres (the D435's own resolution at the cell's range) and the view's cloud
# thinned to one point per RECORD_VOXEL_M cell. The clouds in drawing.ply and surface.ply keep the
# scan's own resolution (planners.yaml grid.surface_voxel_m).
JPEG_QUALITY = 90
RECORD_VOXEL_M = 0.004
ROI_MARGIN_M = 0.1  # context kept round the piece's box
SUPPORT_BAND_M = 0.01  # points this close above the piece's lowest point lie on what it stands on
PAINT_OVERLAY = (0, 230, 255, 210)  # cyan: stands out on red paint and grey steel
LABEL_SPACING_M = 0.04  # gap labels nearer than this to one already shown are left out (they would overlap)


def depth_mm(depth: np.ndarray) -> np.ndarray:
    """Metres (NaN: no return) -> uint16 millimetres (0: no return; beyond 65.5 m clipped)."""
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(np.rint(d * 1000.0), 0, 65535).astype(np.uint16)


def thin(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied ``voxel`` cell (the first of each)."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(np.asarray(xyz) / voxel).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def _send_blueprint(rec: rr.RecordingStream, blueprint: rrb.Blueprint) -> None:
    """``rec.send_blueprint(blueprint)`` without its leak: rerun-sdk 0.41 never frees the temporary
    stream it logs the blueprint into (two native threads and its buffers per call, for good), unless
    that stream is disconnected; so this does what send_blueprint does and then disconnects it."""
    import rerun_bindings as bindings
    from rerun.recording_stream import RecordingStream

    if not (hasattr(RecordingStream, "_from_native") and hasattr(blueprint, "_log_to_stream")):
        rec.send_blueprint(blueprint)  # another rerun version: its own way (tests/test_load.py counts threads)
        return
    stream = RecordingStream._from_native(bindings.new_blueprint(
        application_id=rec.get_application_id(), make_default=False, make_thread_default=False,
        default_enabled=True))
    try:
        stream.set_time("blueprint", sequence=0)
        blueprint._log_to_stream(stream)
        bindings.send_blueprint(stream.memory_recording().storage, True, True, recording=rec.to_native())
    finally:
        stream.disconnect()


def blueprint(lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> rrb.Blueprint:
    """The 3-D view (framed on the box lo..hi when the piece is known: the eye 1.8 box radii off its
    centre, from the front right and above), the camera with the paint overlay, and the coverage plot.
    The scan's working layers (frontier, candidates, ground truth) start hidden; one click shows them."""
    eye = None
    if lo is not None and hi is not None:
        centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 0.1)
        direction = np.array([1.0, -1.2, 0.9]) / np.linalg.norm([1.0, -1.2, 0.9])
        eye = rrb.EyeControls3D(position=centre + 1.8 * radius * direction, look_target=centre,
                                eye_up=[0.0, 0.0, 1.0])
    hidden = {path: rrb.EntityBehavior(visible=False) for path in
              ("world/frontier", "world/candidates", "world/truth", "world/camera/image/depth")}
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="piece, drawing and cut", eye_controls=eye,
                              background=[250, 250, 250], overrides=hidden),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", name="camera: detected paint in cyan",
                                  overrides={"world/camera/image/depth": rrb.EntityBehavior(visible=False)}),
                rrb.TimeSeriesView(origin="coverage", name="coverage per view"),
                row_shares=[3, 2],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class ScanRecorder:
    def __init__(self, path: str | Path, name: str, connect: str | None = None):
        self.rec = rr.RecordingStream("scrapcell", recording_id=None)
        self.rec.save(str(path))
        if connect:
            self.rec.connect_grpc(connect)
        self.rec.send_recording_name(name)
        _send_blueprint(self.rec, blueprint())
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log("world/camera/image", rr.AnnotationContext([(0, "not paint", (0, 0, 0, 0)),
                                                                    (1, "paint", PAINT_OVERLAY)]), static=True)
        self._path: list[np.ndarray] = []
        self._roi: tuple[np.ndarray, np.ndarray] | None = None  # the piece's box (lo, hi), once known

    def log_scene(self, vertices: np.ndarray, faces: np.ndarray, gt_points: np.ndarray) -> None:
        """The piece as the scene describes it (twin: ground truth; real cell: the expected piece), for
        context only (the planner never sees it); it frames the 3-D view and crops the clouds."""
        lo, hi = np.min(vertices, axis=0), np.max(vertices, axis=0)
        self._roi = (lo, hi)
        _send_blueprint(self.rec, blueprint(lo, hi))
        self.rec.log("world/truth/object", rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces,
                                                       albedo_factor=[150, 150, 150, 90]), static=True)
        self.rec.log("world/truth/drawing", rr.Points3D(gt_points, colors=[255, 200, 0], radii=0.001), static=True)

    def log_robot_geometry(self, robot) -> None:
        """The arm as its collision hulls (what the planner keeps clear), one entity per link; the
        link transforms follow per view (log_robot_pose)."""
        for part in robot.parts:
            self.rec.log(f"world/robot/{part.link}/{part.name.replace('#', '_')}",
                         rr.Mesh3D(vertex_positions=part.vertices, triangle_indices=part.faces,
                                   albedo_factor=[235, 235, 240, 200] if not part.tool else [40, 40, 40, 230]),
                         static=True)

    def log_robot_pose(self, step: int, links: tuple[str, ...], poses: np.ndarray) -> None:
        rec = self.rec
        rec.set_time("step", sequence=step)
        for link, T in zip(links, poses):  # ~10 links
            rec.log(f"world/robot/{link}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))

    def log_view(self, step: int, T_base_cam: np.ndarray, K: np.ndarray, size: tuple[int, int],
                 color: np.ndarray, depth: np.ndarray, cloud_xyz: np.ndarray, cloud_rgb: np.ndarray,
                 paint: np.ndarray | None = None) -> None:
        """One view; ``paint``: the (H, W) pixels the paint filter took, drawn over the colour image."""
        rec = self.rec
        rec.set_time("step", sequence=step)
        rec.log("world/camera", rr.Transform3D(translation=T_base_cam[:3, 3], mat3x3=T_base_cam[:3, :3]))
        rec.log("world/camera/image", rr.Pinhole(image_from_camera=K, resolution=list(size),
                                                 camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.15))
        rec.log("world/camera/image/rgb", rr.Image(color).compress(jpeg_quality=JPEG_QUALITY))
        rec.log("world/camera/image/depth", rr.DepthImage(depth_mm(depth), meter=1000.0))
        if paint is not None:
            rec.log("world/camera/image/paint", rr.SegmentationImage(np.asarray(paint, dtype=np.uint8)))
        xyz, rgb = self.crop(np.asarray(cloud_xyz), np.asarray(cloud_rgb))
        keep = thin(xyz, RECORD_VOXEL_M)
        rec.log(f"world/captures/{step}", rr.Points3D(xyz[keep], colors=rgb[keep], radii=RECORD_VOXEL_M / 2))
        self._path.append(T_base_cam[:3, 3].copy())
        rec.log("world/viewpoints", rr.Points3D(np.array(self._path), colors=[40, 160, 255], radii=0.01,
                                                labels=[str(i) for i in range(len(self._path))]))
        if len(self._path) > 1:
            rec.log("world/view_path", rr.LineStrips3D([np.array(self._path)], colors=[220, 0, 220], radii=0.003))

    def crop(self, xyz: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The points inside the piece's box (plus ROI_MARGIN_M), with those on its support plane dimmed
        to a pale grey; unchanged until the piece is known."""
        if self._roi is None or len(xyz) == 0:
            return xyz, rgb
        lo, hi = self._roi
        inside = np.all((xyz >= lo - ROI_MARGIN_M) & (xyz <= hi + ROI_MARGIN_M), axis=1)
        xyz, rgb = xyz[inside], np.array(rgb[inside], dtype=np.uint8)
        support = xyz[:, 2] < lo[2] + SUPPORT_BAND_M
        rgb[support] = (0.3 * rgb[support] + 0.7 * 225).astype(np.uint8)
        return xyz, rgb

    def log_coverage(self, step: int, drawing_points: int, percent: float | None) -> None:
        """The coverage plot, one value per view: the share of the true line seen (twin), or where there is
        no ground truth (a real cell) the drawing's point count."""
        rec = self.rec
        rec.set_time("step", sequence=step)
        if percent is not None:
            rec.log("coverage/percent_of_true_line", rr.Scalars(float(percent)))
        else:
            rec.log("coverage/drawing_points", rr.Scalars(float(drawing_points)))

    def log_plan(self, step: int, frontier: np.ndarray, voxel: float, candidates: np.ndarray,
                 quality: np.ndarray, target: np.ndarray | None, drawing_xyz: np.ndarray) -> None:
        rec = self.rec
        rec.set_time("step", sequence=step)
        rec.log("world/drawing", rr.Points3D(drawing_xyz, colors=_PAINT, radii=0.002))
        if len(frontier):
            rec.log("world/frontier", rr.Boxes3D(centers=frontier, half_sizes=np.full(3, voxel / 2),
                                                 colors=[0, 220, 120]))
        else:
            rec.log("world/frontier", rr.Clear(recursive=False))
        if len(candidates):
            q = (quality - quality.min()) / max(float(np.ptp(quality)), 1e-12)
            colors = np.stack([255 * (1 - q), 255 * q, 60 * np.ones_like(q)], axis=1).astype(np.uint8)
            rec.log("world/candidates", rr.Points3D(candidates[:, :3, 3], colors=colors, radii=0.006))
        else:
            rec.log("world/candidates", rr.Clear(recursive=False))
        if target is not None:
            rec.log("world/target", rr.Points3D([target], colors=[255, 255, 0], radii=0.012))

    def log_cut(self, step: int, path) -> None:
        """The cutting path: each cut in order (green if it can run, orange if its approach or
        retract cannot), the torch axis at every 5th pose coloured by its tilt from the normal
        (white upright to magenta at the cone's edge), and every uncut gap in red with its reason."""
        rec = self.rec
        rec.set_time("step", sequence=step)
        max_tilt = np.radians(max(path.config.get("lead_lag_max_deg", 20.0), path.config.get("side_tilt_max_deg", 10.0), 1.0))
        for i, b in enumerate(path.branches):
            if len(b) == 0:
                continue
            colour = [40, 200, 60] if b.feasible else [240, 150, 30]
            tilt = b.tilt_rad if b.tilt_rad is not None else np.zeros(len(b))
            label = f"cut {i}" if b.feasible else f"cut {i}: cannot run"  # short: labels must not pile up
            rec.log(f"world/cut/cut{i}", rr.LineStrips3D([b.points], colors=colour, radii=0.004, labels=[label]))
            rec.log(f"world/cut/cut{i}/about", rr.TextDocument(
                f"cut {i}: {b.length_m:.3f} m, tilt up to {np.degrees(tilt.max()):.0f} deg"
                + ("" if b.feasible else f" ({'; '.join(b.issues)})")))
            k = np.arange(0, len(b), 5)
            f = np.clip(tilt[k] / max_tilt, 0.0, 1.0)[:, None]
            rgb = ((1 - f) * np.array([235, 235, 235]) + f * np.array([220, 40, 220])).astype(np.uint8)
            rec.log(f"world/cut/cut{i}/torch", rr.Arrows3D(origins=b.poses[k, :3, 3] - 0.04 * b.poses[k, :3, 2],
                                                            vectors=0.04 * b.poses[k, :3, 2], colors=rgb,
                                                            radii=0.0015))
        labelled: list[np.ndarray] = []  # one label per spot: gaps side by side share it

        def label(at: np.ndarray, text: str) -> list[str] | None:
            if any(np.linalg.norm(at - p) < LABEL_SPACING_M for p in labelled):
                return None
            labelled.append(at)
            return [text]

        for j, g in enumerate(path.gaps):
            if g.length_m <= 0:
                rec.log(f"world/cut/gap{j}", rr.Points3D([g.start], colors=[240, 150, 30], radii=0.006,
                                                         labels=label(np.asarray(g.start), g.reason)))
                continue
            line = g.points if g.points is not None and len(g.points) > 1 else np.stack([g.start, g.end])
            rec.log(f"world/cut/gap{j}", rr.LineStrips3D([line], colors=[255, 0, 200], radii=0.007,
                                                         labels=label(np.asarray(line[len(line) // 2]),
                                                                      f"uncut {1000 * g.length_m:.0f} mm: {g.reason}")))

    def flush(self) -> None:
        """Until what was logged is in the file: a step is reported only after this, so a worker that
        dies after the report has lost none of the step's recording (Rerun's file sink writes behind)."""
        if self.rec is not None:
            try:
                self.rec.flush(timeout_sec=10.0)  # a file: milliseconds; a live viewer that stalls: not forever
            except Exception as e:  # noqa: BLE001 - the scan goes on; the recording is the record, not the job
                log.warning("recording: flush did not complete: %s", e)

    def close(self) -> None:
        """Flush and finish the file, then free the stream: Rerun keeps a dropped stream (and the
        blueprint stream send_blueprint made) with two native threads each until it is swept, so a
        service running scan after scan leaked 4 threads and ~2 MB per job (docs/RELIABILITY.md, Load)."""
        from rerun_bindings import flush_and_cleanup_orphaned_recordings  # what rr.init does for the same reason

        if self.rec is None:
            return
        self.rec.flush()
        self.rec.disconnect()
        self.rec = None
        flush_and_cleanup_orphaned_recordings()
