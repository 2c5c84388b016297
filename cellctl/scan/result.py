"""The one record of a scan job, and the views of it.

``ScanResult`` is what a job found: the run folder's result.json is it, dumped (``ResultFile`` adds the
job's header); the API's ``ResultSummary`` is its base class, and ``ScanResult.summary()`` is the same
object seen through that class (pydantic serialises a value by its declared type, so the step records,
logs and the gaps' points stay behind), clipped to the API's bounds; the bench's rows read its fields.

The summaries are strict and closed, like every message of the API (cellctl.service.api sends them as
they are); the records below them are lenient: the scan writes numpy numbers into them as it goes, and
they are converted on assignment. Pydantic only: a tablet app imports this through the API module."""

from __future__ import annotations

from typing import Annotated, Any, Literal, get_args

from annotated_types import MaxLen
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

from planners.paint_separation import PaintSeparation

SCHEMA_VERSION = 1


class Summary(BaseModel):
    """As the API sends it: unknown fields refused, strict types, finite numbers."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


Line = Annotated[str, Field(max_length=500)]  # one line for the operator
_RECORD = ConfigDict(extra="forbid", strict=False, validate_assignment=True, allow_inf_nan=True)


# --- what the API sends --------------------------------------------------------------------------
class DryRunSummary(Summary):
    motions: int = Field(ge=0)
    contacts: int = Field(ge=0, description="robot-scene contacts the twin saw")
    tip_error_max_mm: float | None = None
    tip_error_median_mm: float | None = None
    path_error_max_mm: float | None = None
    path_error_median_mm: float | None = None
    flame_off_paint_max_mm: float | None = Field(None, ge=0, description="the executed cut's flame spot to the "
                                                                         "nearest paint the scan saw, largest")
    flame_to_line_max_mm: float | None = Field(None, ge=0, description="the same to the true line (twin only)")


class CutGap(Summary):
    """A stretch of the drawing the torch will not cut, and why."""

    branch: int = Field(ge=0, description="which branch of the drawing")
    length_m: float = Field(ge=0, description="0 for a reconfiguration: the torch lifts and lands again there")
    reason: str = Field(max_length=64, description="out of reach, joint limits, collision, singular, reconfigure, "
                                                   "too short")
    detail: str = Field("", max_length=500)
    start: list[float] = Field(min_length=3, max_length=3, description="last cut point before it, robot base, m")
    end: list[float] = Field(min_length=3, max_length=3, description="first cut point after it, robot base, m")


class CutAccuracy(Summary):
    """The cuts against the painted line's true centerline (twin only): the flame spot at every sample
    of the planned cut motion, lit (``pose_to_line_max_mm``: at the planned poses only)."""

    strokes: int = Field(ge=0, description="strokes of the true drawing")
    cuts: int = Field(ge=0)
    line_on_metal_m: float | None = Field(None, ge=0)
    cut_coverage: float = Field(ge=0, le=1, description="share of the true line within 5 mm of a cut")
    path_to_line_mean_mm: float | None = Field(None, ge=0)
    path_to_line_max_mm: float | None = Field(None, ge=0)
    line_to_path_mean_mm: float | None = Field(None, ge=0)
    line_to_path_max_mm: float | None = Field(None, ge=0, description="includes the uncut gaps")
    pose_to_line_max_mm: float | None = Field(None, ge=0, description="the planned cut poses only")
    tip_to_metal_min_mm: float | None = Field(None, ge=0, description="the torch tip to the true surface, lit")
    tip_to_metal_max_mm: float | None = Field(None, ge=0)
    fragments: int | None = Field(None, ge=0, description="cuts under 20 mm along a longer piece of the line's paint")


class UncutPaintSummary(Summary):
    """A piece of paint no cut passes over: where, how much line it holds, and why."""

    centre: list[float] = Field(min_length=3, max_length=3, description="a paint point in it, robot base, m")
    length_m: float = Field(ge=0, description="its painted area over the spray width")
    reason: str = Field(max_length=64, description="the reason of the plan's gap there (out of reach, joint limits, "
                                                   "collision, ...), or 'not followed': no cut's line goes there")
    detail: str = Field("", max_length=500)


class UnseenPaintSummary(Summary):
    """A border where the paint the scan saw runs into surface it never measured: the line may go on
    there, unseen (or runs off a real edge of the piece: from the scan alone the two look alike)."""

    centre: list[float] = Field(min_length=3, max_length=3, description="a paint point on the border, robot base, m")
    border_m: float = Field(ge=0, description="the border's length")
    wall_m: float = Field(0.0, ge=0, description="height of the measured wall standing over it (the paint runs "
                                                 "to the foot of a face the scan did not see), 0 at a rim")


class PaintCheck(Summary):
    """The cut against what the cell saw (never against its own line alone), computed at every sample of
    the planned motion with the flame lit: the line the paint gives where it lies on the band's centre,
    within the tolerance of the flame (``line_share``, what the operator is told), and the painted area
    under the flame (``cut_share``), an independent check."""

    line_share: float | None = Field(None, ge=0, le=1, description="share of the line the paint gives (where it lies "
                                     "on the paint's band centre, plus paint no line follows) within the line "
                                     "tolerance of the lit flame on the band's centre: the share the operator is told")
    line_on_paint_m: float | None = Field(None, ge=0, description="that line's length, the paint no line follows "
                                          "included")

    cut_share: float = Field(ge=0, le=1, description="share of the painted area within half the spray width plus "
                                                     "the line tolerance of a runnable cut's flame path")
    line_length_m: float = Field(ge=0, description="the line's length as the paint shows it: area over spray width")
    spray_width_mm: float = Field(ge=0, description="as measured across the paint")
    uncut: list[UncutPaintSummary] = Field(default_factory=list, max_length=100, description="longest first")
    flame_off_paint_max_mm: float | None = Field(None, ge=0, description="the flame spot's largest distance from "
                                                                         "any paint, over every lit sample")
    flame_off_paint_m: float = Field(0.0, ge=0, description="flame travel off the paint by more than the tolerance")
    flame_off_centre_max_mm: float | None = Field(None, ge=0, description="the flame spot's largest distance from "
                                                  "the paint band's centre across its travel, where both edges "
                                                  "of the band are measured")
    flame_off_centre_m: float = Field(0.0, ge=0, description="flame travel beside the band's centre by more than "
                                                             "the tolerance: paint it passes there is not counted cut")
    tip_to_surface_min_mm: float | None = Field(None, ge=0, description="the torch tip's clearance from the scanned "
                                                                        "surface while lit, least")
    tip_to_surface_max_mm: float | None = Field(None, ge=0)
    unseen: list[UnseenPaintSummary] = Field(default_factory=list, max_length=100, description="where the paint "
                                             "runs on past what the scan measured, longest first: there "
                                             "``line_share`` and ``cut_share`` are shares of less than the "
                                             "whole line")


class CutPathSummary(Summary):
    """What will be cut. ``branches`` are the cuts in cutting order (runs of the drawing the arm can
    follow in one go), ``feasible_branches`` those with an approach and a retract too."""

    branches: int = Field(ge=0)
    feasible_branches: int = Field(ge=0)
    poses: int = Field(ge=0)
    feasible_poses: int = Field(ge=0)
    length_m: float = Field(ge=0)
    planning_s: float = Field(ge=0)
    infeasible: dict[str, int] = Field(default_factory=dict, description="pose count per reason")
    error: str | None = Field(None, max_length=2000)
    dry_run: DryRunSummary | None = None
    cut_fraction: float = Field(0.0, ge=0, le=1, description="share of the drawing's length the cuts cover")
    drawing_length_m: float = Field(0.0, ge=0)
    gaps: list[CutGap] = Field(default_factory=list, max_length=200, description="what is left uncut, and why")
    warnings: list[Line] = Field(default_factory=list, max_length=50, description="what the operator should know")
    clearing_views: int = Field(0, ge=0, description="views taken after the scan to see the torch's way")
    cut_lengths_m: list[float] = Field(default_factory=list, max_length=200, description="each runnable cut's "
                                       "length, in cutting order")
    paint: PaintCheck | None = Field(None, description="the cut against the paint the cell saw")
    accuracy: CutAccuracy | None = None

    @property
    def told_share(self) -> float:
        """The share of the line the operator is told will be cut: the line on the paint under the flame
        (``paint.line_share``; the painted area's share in records made before it), where the cut was
        checked against the paint; else the line's own share."""
        if self.paint is None:
            return self.cut_fraction
        return self.paint.line_share if self.paint.line_share is not None else self.paint.cut_share

    @property
    def told_length_m(self) -> float:
        """The line's length the operator is told: the line on the paint, where measured."""
        if self.paint is None:
            return self.drawing_length_m
        return self.paint.line_on_paint_m if self.paint.line_on_paint_m is not None else self.paint.line_length_m


class ResultSummary(Summary):
    """What the scan found; the full result is result.json in the job's artifacts folder."""

    scene: str = Field(max_length=500)
    planner: str = Field(max_length=32)
    steps: int = Field(ge=0, description="views captured, initial one included")
    terminated_by: str = Field(max_length=64, description="why the scan stopped: quality, frontier, max_steps, "
                               "unreachable, error, ...; stopped from outside: cancelled (an operator), timeout "
                               "(service.job_timeout_s), interrupted (the service stopped)")
    coverage_percent: float = Field(ge=0, le=100, description="of the painted line (twin: against ground truth)")
    coverage_hit: int = Field(ge=0)
    coverage_total: int = Field(ge=0)
    planning_s: float = Field(ge=0)
    step_s: float = Field(ge=0, description="planning time per viewpoint")
    capture_s: float = Field(ge=0)
    motion_planning_s: float = Field(ge=0)
    motion_s: float = Field(ge=0)
    displacement_m: float = Field(ge=0)
    motion_contacts: int = Field(0, ge=0)
    cut: CutPathSummary | None = Field(None, description="absent when no cut was planned (cancelled, error, "
                                                         "no drawing)")
    paint: PaintSeparation | None = Field(None, description="the paint as the initial view showed it: whether it can be "
                                     "told from the metal (ok false: terminated_by paint_not_separable, no cut)")
    error: str | None = Field(None, max_length=2000)


# --- what the run folder keeps -------------------------------------------------------------------
class StepRecord(BaseModel):
    """One captured view: what it saw and what each part of the step took."""

    model_config = _RECORD
    step: int
    camera_position: list[float]
    points: int
    drawing_points: int
    frontier_cells: int = 0
    candidates: int = 0
    best_quality: float | None = None
    best_gain: float | None = None
    planning_s: float = 0.0  # eq. 10's share of this step: cloud processing + grid update + view planning
    capture_s: float = 0.0
    process_s: float = 0.0  # of planning_s: clouds, colour filter, grid update
    motion_planning_s: float = 0.0  # IK, collision checks, trajectory (not view planning)
    motion_s: float = 0.0
    tracking_error_rad: float = 0.0
    chosen_rank: int | None = None
    replans: int = 0
    coverage_percent: float | None = None  # against ground truth, when the scene has one (twin)
    reach_error_m: float = 0.0  # camera position reached vs planned
    reach_error_deg: float = 0.0  # optical axis reached vs planned
    contacts: list[dict[str, Any]] = Field(default_factory=list)  # robot-scene contacts the twin saw on this move
    via: str = ""  # how the move went: direct, retract, approach, retract+approach, park


class DryRun(DryRunSummary):
    """The cut run in the twin, torch off: the summary plus every contact it saw."""

    model_config = _RECORD
    contact_log: list[dict[str, Any]] = Field(default_factory=list)  # with the cut and phase it happened in


class GapRecord(CutGap):
    model_config = _RECORD
    points: list[list[float]] = Field(default_factory=list)  # the uncut points, robot base, m
    normal: list[float] | None = None  # the surface's outward normal there


class CutSummary(CutPathSummary):
    """The cut as planned, in full: every gap with its points, every warning, the whole error."""

    model_config = _RECORD
    branches: int = 0
    feasible_branches: int = 0
    poses: int = 0
    feasible_poses: int = 0
    length_m: float = 0.0
    planning_s: float = 0.0
    error: str | None = None
    dry_run: DryRun | None = None
    gaps: list[GapRecord] = Field(default_factory=list)
    warnings: list[str] = Field(default_factory=list)


class ScanResult(ResultSummary):
    """The whole job: the summary's figures, the cut in full, every step and what went wrong."""

    model_config = _RECORD
    steps: int = 0
    terminated_by: str = ""
    coverage_percent: float = 0.0
    coverage_hit: int = 0
    coverage_total: int = 0
    planning_s: float = 0.0
    step_s: float = 0.0  # eq. 11: planning time per viewpoint (the initial view is not one)
    capture_s: float = 0.0
    motion_planning_s: float = 0.0
    motion_s: float = 0.0
    displacement_m: float = 0.0
    motion_contacts: int = 0  # robot-scene contacts the twin reported over all moves (twin only)
    cut: CutSummary | None = None
    error: str | None = None  # whole, with the traceback's last frames when a bug ended the job
    # the arm's joint tracking error (max |commanded - measured|, rad) over every move, initial one included:
    # the twin's position control (a few mrad) or the franky arm's controller (franky-sim lags 0.1 rad per rad/s)
    tracking_error_max_rad: float | None = None
    tracking_error_median_rad: float | None = None
    arm_stopped: bool | None = None  # after an error: whether the arm acknowledged stop() (None: no error)
    incidents: list[dict[str, Any]] = Field(default_factory=list)  # faults met on the way, recovered or not
    arm_events: list[dict[str, Any]] = Field(default_factory=list)  # what the arm itself logged (Franka)
    viewpoints: list[list[float]] = Field(default_factory=list)
    records: list[StepRecord] = Field(default_factory=list)

    def summary(self) -> ResultSummary:
        """This result as the API sends it: its summary fields, long texts and lists cut to the API's bounds."""
        return ResultSummary.model_validate(clip(_SUMMARY.dump_python(self, mode="json"), ResultSummary))


_SUMMARY = TypeAdapter(ResultSummary)


class ResultFile(ScanResult):
    """result.json: the result with the job's header."""

    schema_version: Literal[1] = SCHEMA_VERSION
    cell_id: str = ""
    mode: str = ""
    scene_ref: str = ""
    job_profile: str = "scan"


def clip(data: Any, model: type[BaseModel]) -> Any:
    """``data`` (a dump) with every text and list no longer than ``model``'s fields allow, at any depth."""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for name, info in model.model_fields.items():
        value = out.get(name)
        if value is None:
            continue
        limit = _max_length(info.metadata)
        if limit is not None and isinstance(value, (str, list)):
            value = value[:limit]
        inner = _model_in(info.annotation)
        if inner is not None:
            value = [clip(v, inner) for v in value] if isinstance(value, list) else clip(value, inner)
        elif isinstance(value, list) and (item := _max_length(_item_metadata(info.annotation))) is not None:
            value = [v[:item] if isinstance(v, str) else v for v in value]
        out[name] = value
    return out


def _max_length(metadata) -> int | None:
    for m in metadata:
        if isinstance(m, MaxLen):
            return m.max_length
        if hasattr(m, "metadata"):  # a Field() inside Annotated
            found = _max_length(m.metadata)
            if found is not None:
                return found
    return None


def _item_metadata(annotation) -> tuple:
    """The Annotated metadata of a list's items (list[Annotated[str, Field(max_length=...)]])."""
    args = get_args(annotation)
    return getattr(args[0], "__metadata__", ()) if args else ()


def _model_in(annotation) -> type[BaseModel] | None:
    """The model a field holds (itself, in a list, or optional), if any."""
    for t in (annotation, *getattr(annotation, "__args__", ())):
        for u in (t, *getattr(t, "__args__", ())):
            if isinstance(u, type) and issubclass(u, BaseModel):
                return u
    return None
