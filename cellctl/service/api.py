"""The job API's contract: key expressions and JSON messages (pydantic v2), shared by the service and
its clients. Kept free of numpy/pybullet imports so a tablet app can use it with pydantic alone.

Every message carries ``schema_version``; unknown fields are refused (``extra="forbid"``) and types are
strict (``"5"`` is not 5), so a client bug shows up as an error reply, not as a silently different job.
docs/API.md is generated from this module by ``python -m cellctl.service.apidoc``."""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, Field, ValidationError

from cellctl.scan.modes import ModeName, modes_help
from cellctl.scan.result import (CutAccuracy, CutGap, CutPathSummary, DryRunSummary,  # noqa: F401 - the API's
                                 ResultSummary, Summary)  # result views, defined with the result they view
from planners.registry import DEFAULT_PLANNER, PLANNERS  # names only: no planner is imported

SCHEMA_VERSION = 1
MAX_PAYLOAD_BYTES = 64 * 1024  # a request is a few hundred bytes; anything near this is a bug or an attack
# the cell's Zenoh transport drops a (defragmented) message over this before the service sees it: no query,
# however large, makes the cell buffer more (Zenoh's default is 1 GiB)
MAX_MESSAGE_BYTES = 1024 * 1024
LIST_LIMIT_MAX = 200
CHUNK_MAX = 512 * 1024  # a file chunk's bytes; base64 in JSON keeps its reply under the 1 MiB message cap
CHUNK_DEFAULT = 256 * 1024
FILE_NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}$"  # a file of the job's folder, no path
MAX_JSON_DEPTH = 32  # nesting of a payload's arrays and objects; a request needs 2

CELL_ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
REQUEST_ID_PATTERN = r"^[A-Za-z0-9_.:-]{8,64}$"
# "<UTC time>-<random>": sorts by creation, is one key-expression chunk, cannot collide with "submit"
JOB_ID_PATTERN = r"^[0-9]{8}T[0-9]{6}Z-[0-9a-f]{6}$"
# a built-in scene name, or a scene .yaml path on the cell controller (twin only; the service confines it to
# service.scene_dirs)
SCENE_PATTERN = r"^([a-z0-9_]{1,64}|[^\x00-\x1f\x7f]{1,500}\.ya?ml)$"

PLANNER_NAMES = tuple(PLANNERS)

JobId = Annotated[str, Field(pattern=JOB_ID_PATTERN, description="e.g. 20250314T101500Z-3f9a1c")]
CellId = Annotated[str, Field(pattern=CELL_ID_PATTERN)]
Timestamp = Annotated[str, Field(max_length=40, description="ISO 8601, UTC, milliseconds")]
ShortText = Annotated[str, Field(max_length=2000)]

JobState = Literal["queued", "running", "cancelling", "done", "failed", "cancelled", "interrupted"]
TERMINAL_STATES = frozenset({"done", "failed", "cancelled", "interrupted"})
Phase = Literal["queued", "scanning", "planning-cut", "done", "failed", "cancelled", "interrupted"]
ErrorCode = Literal["bad_json", "invalid_request", "payload_too_large", "unsupported_schema_version", "queue_full",
                    "cell_not_ready", "cell_busy", "not_found", "not_cancellable", "not_ended", "shutting_down", "internal_error"]

ERROR_CODES: dict[str, str] = {
    "bad_json": f"the payload is empty, not UTF-8, or not strict JSON: a syntax error, a key given twice, nesting "
                f"deeper than {MAX_JSON_DEPTH} levels, a lone UTF-16 surrogate escape, NaN or Infinity",
    "invalid_request": "JSON, but not a valid message: missing or unknown field, wrong type, value out of range, "
                       "unknown planner or scene, wildcard or unknown key",
    "payload_too_large": f"the payload is over {MAX_PAYLOAD_BYTES} bytes",
    "unsupported_schema_version": f"schema_version is not {SCHEMA_VERSION}",
    "queue_full": "the job queue is at its configured length (service.queue_max); retry later",
    "cell_not_ready": "the arm or the camera is not ready (robot unreachable, FCI not active, no camera: the message "
                      "and the status's not_ready_reason say which); nothing was queued, submit again once the status "
                      "shows ready",
    "cell_busy": "a job is running or queued, or another commissioning is: the camera is in use; commission the "
                 "paint when the cell is idle",
    "not_found": "no job with this id, or no file of that name in its folder",
    "not_cancellable": "the job already ended (done, failed, cancelled or interrupted)",
    "not_ended": "the job's files are served once it has ended (its folder is still being written)",
    "shutting_down": "the service is stopping and takes no new jobs",
    "internal_error": "a bug in the service; the request was not carried out, the service keeps serving",
}


# --- key expressions ------------------------------------------------------------------------------
class Keys:
    """The key expressions of one cell."""

    def __init__(self, cell_id: str):
        self.cell_id = cell_id
        self.root = f"cell/{cell_id}"
        self.jobs = f"{self.root}/jobs"
        self.jobs_tree = f"{self.root}/jobs/**"  # the one queryable that serves every jobs key
        self.submit = f"{self.jobs}/submit"
        self.all_events = f"{self.jobs}/*/events"
        self.status = f"{self.root}/status"
        self.alive = f"{self.root}/alive"
        self.paint = f"{self.root}/paint"
        self.paint_commission = f"{self.root}/paint/commission"

    def job(self, job_id: str) -> str:
        return f"{self.jobs}/{job_id}"

    def cancel(self, job_id: str) -> str:
        return f"{self.jobs}/{job_id}/cancel"

    def events(self, job_id: str) -> str:
        return f"{self.jobs}/{job_id}/events"

    def files(self, job_id: str) -> str:
        return f"{self.jobs}/{job_id}/files"

    def file(self, job_id: str, name: str) -> str:
        return f"{self.jobs}/{job_id}/files/{name}"


# --- messages -------------------------------------------------------------------------------------
ApiModel = Summary  # every message: unknown fields refused, strict types, finite numbers


class ScanDrawingRequest(ApiModel):
    """Submit on ``cell/<cell_id>/jobs/submit``: scan the painted line and plan its cutting path."""

    schema_version: Literal[1] = SCHEMA_VERSION
    kind: Literal["scan_drawing"] = Field("scan_drawing", description="the only job kind so far")
    scene: str = Field(pattern=SCENE_PATTERN, max_length=500,
                       description="twin only: a built-in scene name (smooth_cylinder, ...) or the path of a "
                                   "scene .yaml on the cell controller (absolute, or relative to the service's "
                                   "working directory) that lies, symlinks resolved, inside one of the cell's "
                                   "scene directories (`service.scene_dirs`, by default `scenes/` beside the "
                                   "cell config); any other path gets `invalid_request`, whether it exists or not")
    planner: Literal[PLANNER_NAMES] = Field(DEFAULT_PLANNER, description="next-view planner")
    max_steps: int | None = Field(None, ge=1, le=200, description="views at most, initial one included "
                                  "(default: planners.yaml)")
    seed: int | None = Field(None, ge=0, le=2**31 - 1, description="twin sensor noise seed (default: the config's)")
    noise: bool = Field(True, description="twin: simulate the D435 depth noise")
    dry_run_cut: bool = Field(False, description="twin: run the cutting path with the torch off and measure the tip")
    requested_by: str | None = Field(None, pattern=r"^[\w .@-]{1,64}$", max_length=64,
                                     description="operator or tablet name, kept in the job record")
    request_id: str | None = Field(None, pattern=REQUEST_ID_PATTERN, max_length=64,
                                   description="the client's key for this job (8-64 of A-Z a-z 0-9 _ . : -, e.g. a "
                                               "UUID), kept with the job: a submit whose request_id the cell already "
                                               "holds creates nothing and gets that job back (`duplicate: true`), so "
                                               "a submit whose reply was lost can be sent again safely; the same "
                                               "request_id with a different request is `invalid_request`")


class ListJobsRequest(ApiModel):
    """Optional payload of a query on ``cell/<cell_id>/jobs`` (no payload: the defaults)."""

    schema_version: Literal[1] = SCHEMA_VERSION
    limit: int = Field(20, ge=1, le=LIST_LIMIT_MAX)
    state: JobState | None = Field(None, description="only jobs in this state")


class CancelRequest(ApiModel):
    """Optional payload of a query on ``cell/<cell_id>/jobs/<job_id>/cancel``."""

    schema_version: Literal[1] = SCHEMA_VERSION
    reason: str | None = Field(None, max_length=200, description="kept in the job's transitions")


class FileInfo(ApiModel):
    name: str = Field(pattern=FILE_NAME_PATTERN, description="e.g. cut_path.json; ask for it on "
                      "`cell/<cell_id>/jobs/<job_id>/files/<name>`")
    size: int = Field(ge=0, description="bytes")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="of the whole file, hex")


class FileList(ApiModel):
    """Reply to ``cell/<cell_id>/jobs/<job_id>/files``: the files of an ended job's folder."""

    schema_version: Literal[1] = SCHEMA_VERSION
    job_id: JobId
    files: list[FileInfo] = Field(max_length=100, description="by name")
    chunk_max: int = Field(ge=1, description="the most bytes one chunk carries")


class FileChunkRequest(ApiModel):
    """Optional payload of a query on ``cell/<cell_id>/jobs/<job_id>/files/<name>`` (none: the first chunk)."""

    schema_version: Literal[1] = SCHEMA_VERSION
    offset: int = Field(0, ge=0, le=2**40, description="byte of the file to start at")
    length: int = Field(CHUNK_DEFAULT, ge=1, le=CHUNK_MAX, description="bytes at most")


class FileChunk(ApiModel):
    """Reply to a file query: ``length`` bytes of the file from ``offset``, base64. Ask for the next
    chunk at ``offset + length`` until ``eof``; check the joined bytes against ``sha256``."""

    schema_version: Literal[1] = SCHEMA_VERSION
    job_id: JobId
    name: str = Field(pattern=FILE_NAME_PATTERN)
    offset: int = Field(ge=0)
    length: int = Field(ge=0, le=CHUNK_MAX, description="bytes in this chunk (0 at or past the end)")
    size: int = Field(ge=0, description="of the whole file")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="of the whole file, hex")
    eof: bool = Field(description="this chunk reaches the end of the file")
    data: str = Field(max_length=(CHUNK_MAX + 2) // 3 * 4, description="the bytes, base64 (RFC 4648, padded)")


class ErrorDetail(ApiModel):
    loc: str = Field(max_length=200, description="the field, dotted (e.g. 'max_steps')")
    msg: str = Field(max_length=500)


class ErrorReply(ApiModel):
    """An error reply (Zenoh ``reply_err``) to any query."""

    schema_version: Literal[1] = SCHEMA_VERSION
    code: ErrorCode
    message: ShortText
    details: list[ErrorDetail] = Field(default_factory=list, max_length=20)


class SubmitReply(ApiModel):
    schema_version: Literal[1] = SCHEMA_VERSION
    job_id: JobId
    state: JobState = Field("queued", description="queued for a new job; a duplicate's job may have moved on")
    queue_position: int | None = Field(None, ge=1, description="1: next to run; null once the job has left the queue")
    duplicate: bool = Field(False, description="true: the request_id was already submitted, job_id is that job "
                                               "and nothing new was queued")


class Transition(ApiModel):
    state: JobState
    at: Timestamp
    note: str | None = Field(None, max_length=500)


class Progress(ApiModel):
    """The job's last event, kept in the record so a late client can catch up."""

    phase: Phase
    seq: int = Field(ge=0, description="of the last event published")
    step: int | None = Field(None, ge=0, description="the last view captured, counted from 0 (the initial view): "
                             "step k is view k + 1")
    max_steps: int | None = Field(None, ge=1, description="views at most, the initial one included")
    coverage_percent: float | None = Field(None, ge=0, le=100)
    drawing_points: int | None = Field(None, ge=0)
    at: Timestamp


class Artifacts(ApiModel):
    dir: str = Field(max_length=1000, description="on the cell controller: <data_dir>/jobs/<job_id>")
    files: list[str] = Field(default_factory=list, max_length=100)


class JobRecord(ApiModel):
    """Reply to ``cell/<cell_id>/jobs/<job_id>``."""

    schema_version: Literal[1] = SCHEMA_VERSION
    job_id: JobId
    cell_id: CellId
    request: ScanDrawingRequest
    state: JobState
    created_at: Timestamp
    updated_at: Timestamp
    transitions: list[Transition] = Field(max_length=50)
    progress: Progress | None = None
    result: ResultSummary | None = None
    error: str | None = Field(None, max_length=2000)
    artifacts: Artifacts | None = None


class JobBrief(ApiModel):
    job_id: JobId
    state: JobState
    created_at: Timestamp
    updated_at: Timestamp
    scene: str = Field(max_length=500)
    planner: str = Field(max_length=32)
    coverage_percent: float | None = Field(None, ge=0, le=100)
    error: str | None = Field(None, max_length=200, description="first line, shortened")


class JobList(ApiModel):
    """Reply to ``cell/<cell_id>/jobs``: newest first."""

    schema_version: Literal[1] = SCHEMA_VERSION
    cell_id: CellId
    jobs: list[JobBrief] = Field(max_length=LIST_LIMIT_MAX)
    total: int = Field(ge=0, description="jobs in the store that match (the list is cut at `limit`)")
    limit: int = Field(ge=1, le=LIST_LIMIT_MAX)


class CancelReply(ApiModel):
    schema_version: Literal[1] = SCHEMA_VERSION
    job_id: JobId
    state: JobState = Field(description="cancelled (was queued) or cancelling (was running: the scan stops at "
                                        "once, the final state follows as an event)")


class CellStatus(ApiModel):
    """Reply to ``cell/<cell_id>/status``."""

    schema_version: Literal[1] = SCHEMA_VERSION
    cell_id: CellId
    version: str = Field(max_length=64, description="scrapcell package version")
    mode: ModeName = Field(description=modes_help())
    twin: bool = Field(False, description="the pybullet twin renders the scene: a job's `scene` picks the piece "
                                          "(a tablet shows a scene picker only then)")
    scenes: list[Annotated[str, Field(max_length=64)]] = Field(
        default_factory=list, max_length=100, description="the built-in scene names this cell loads (a scene .yaml "
                                                          "inside its service.scene_dirs is accepted too)")
    arm_ready: bool
    camera_ready: bool
    ready: bool = Field(description="a submitted job can start: arm and camera answer (fcisim, real: probed at start "
                                    "and every 10 s while idle); false: submits are refused with cell_not_ready")
    not_ready_reason: str | None = Field(None, max_length=1000, description="why not ready, e.g. the robot is "
                                         "unreachable, FCI is not active, no RealSense found")
    devices: str = Field(max_length=200, description="what drives the arm and the camera")
    accepting_jobs: bool
    queue_length: int = Field(ge=0, description="jobs waiting, the running one not counted")
    queue_max: int = Field(ge=1)
    running_job: JobId | None = None
    jobs_total: int = Field(ge=0, description="jobs in the store")
    started_at: Timestamp
    uptime_s: float = Field(ge=0)


class JobEvent(ApiModel):
    """Published on ``cell/<cell_id>/jobs/<job_id>/events``: one per phase change and per scan step."""

    schema_version: Literal[1] = SCHEMA_VERSION
    job_id: JobId
    seq: int = Field(ge=0, description="0, 1, 2, ... per job, no gaps: a gap means an event was lost")
    phase: Phase
    state: JobState
    step: int | None = Field(None, ge=0, description="the view just captured, counted from 0 (the initial view): "
                             "step k is view k + 1 of at most max_steps")
    max_steps: int | None = Field(None, ge=1, description="views at most, the initial one included")
    coverage_percent: float | None = Field(None, ge=0, le=100, description="so far, when known (twin: ground "
                                                                           "truth)")
    drawing_points: int | None = Field(None, ge=0)
    time: Timestamp
    message: str | None = Field(None, max_length=2000)


class PaintModel(ApiModel):
    """The yard's paint as the cell knows it: what every job finds the line by."""

    name: str = Field(max_length=40)
    lab_mean: list[float] = Field(min_length=3, max_length=3, description="L* a* b* (D65), as the sample showed it")
    source: str = Field(max_length=200, description="where it came from: a commissioning's date, or `default`")


class PaintReply(ApiModel):
    """Reply to ``cell/<cell_id>/paint``: the paint the cell's jobs look for."""

    schema_version: Literal[1] = SCHEMA_VERSION
    cell_id: CellId
    paint: PaintModel
    paint_file: str | None = Field(None, max_length=1000, description="the file it was read from on the cell "
                                                                       "controller; null: the planners config's")


class CommissionPaintRequest(ApiModel):
    """Query ``cell/<cell_id>/paint/commission``: learn the yard's paint from one picture of a sample (the paint
    sprayed on a piece of the yard's scrap, held 0.25-0.5 m in front of the camera, the paint in the middle of
    the picture and bare metal all round it; `cellctl calibrate paint`, docs/HARDWARE.md). Nothing moves. Only
    while the cell is idle (else `cell_busy`); it takes a few seconds."""

    schema_version: Literal[1] = SCHEMA_VERSION
    name: str = Field(pattern=r"^[\w -]{1,40}$", max_length=40, description="what the yard calls the paint")
    requested_by: str | None = Field(None, pattern=r"^[\w .@-]{1,64}$", max_length=64)
    twin_finish: str | None = Field(None, pattern=r"^[a-z_]{1,40}$", max_length=40, description="twin only: the sample's metal "
                                    "(sim.appearance FINISHES; default rust_red)")
    twin_paint: str | None = Field(None, pattern=r"^[a-z_]{1,40}$", max_length=40, description="twin only: its paint (default: "
                                   "`name`)")
    twin_light: str | None = Field(None, pattern=r"^[a-z_]{1,40}$", max_length=40, description="twin only: the light (default "
                                   "normal)")
    twin_no_paint: bool = Field(False, description="twin only: a sample of bare metal (it is refused)")


class CommissionPaintReply(ApiModel):
    """Reply to a commissioning: ``ok`` and the new paint, which every following job uses, or the reason it
    was refused (the cell's paint is then unchanged)."""

    schema_version: Literal[1] = SCHEMA_VERSION
    ok: bool
    reason: str | None = Field(None, max_length=1000)
    paint: PaintModel | None = None
    delta_e: float | None = Field(None, ge=0, description="ΔE76 from the paint to the nearest metal colour round it")
    metal_lab: list[list[float]] = Field(default_factory=list, max_length=10, description="the metal's colours")
    picture_png_base64: str | None = Field(None, max_length=700_000, description="the sample's picture at half "
                                           "size, what the new paint takes as paint in cyan (PNG, base64)")


# --- parsing --------------------------------------------------------------------------------------
class ApiError(Exception):
    """A request the service answers with an error reply."""

    def __init__(self, code: str, message: str, details: list[ErrorDetail] | None = None):
        super().__init__(f"{code}: {message}")
        self.code, self.message, self.details = code, message, details or []

    def reply(self) -> ErrorReply:
        return ErrorReply(code=self.code, message=self.message[:2000], details=self.details[:20])


M = TypeVar("M", bound=BaseModel)


def parse_payload(raw: bytes | None, model: type[M], *, required: bool = True) -> M:
    """bytes -> model, or ApiError with a stable code: bad_json, payload_too_large,
    unsupported_schema_version, invalid_request. Strict JSON, decided here and not by whichever parser
    meets the defect first: a key given twice, nesting deeper than MAX_JSON_DEPTH, a lone UTF-16
    surrogate (``"\\ud800"``), NaN or Infinity are all bad_json."""
    if not raw:
        if required:
            raise ApiError("bad_json", "empty payload: expected a JSON object")
        return model()
    if len(raw) > MAX_PAYLOAD_BYTES:
        raise ApiError("payload_too_large", f"payload is {len(raw)} bytes; at most {MAX_PAYLOAD_BYTES} are accepted")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ApiError("bad_json", f"payload is not UTF-8 (invalid byte at offset {e.start})") from None
    try:
        obj = json.loads(text, parse_constant=_no_constant, object_pairs_hook=_unique_keys)
        _strict(obj, MAX_JSON_DEPTH)
    except json.JSONDecodeError as e:
        raise ApiError("bad_json", f"payload is not JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except (ValueError, RecursionError) as e:
        raise ApiError("bad_json", f"payload is not JSON: {e}"[:300]) from None
    if not isinstance(obj, dict):
        raise ApiError("invalid_request", f"expected a JSON object, got {type(obj).__name__}")
    version = obj.get("schema_version", SCHEMA_VERSION)
    if type(version) is not int or version != SCHEMA_VERSION:  # strict: not true, 1.0 or "1"
        raise ApiError("unsupported_schema_version",
                       f"schema_version {json.dumps(version)[:40]} is not supported; this cell speaks {SCHEMA_VERSION}")
    try:
        return model.model_validate_json(text)
    except ValidationError as e:
        raise invalid(e) from None


def invalid(e: ValidationError, prefix: str = "invalid request") -> ApiError:
    details = [ErrorDetail(loc=".".join(str(p) for p in err["loc"])[:200] or "(payload)", msg=err["msg"][:500])
               for err in e.errors(include_url=False, include_input=False)[:20]]
    text = "; ".join(f"{d.loc}: {d.msg}" for d in details)
    return ApiError("invalid_request", f"{prefix}: {text}"[:2000], details)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        twice = next(k for i, k in enumerate(keys) if k in keys[:i])
        raise ValueError(f"key {json.dumps(twice)[:80]} is given twice (which one counts is not defined)")
    return dict(pairs)


def _strict(v: Any, depth: int) -> None:
    """Nesting within ``depth`` levels, and every string (keys too) valid Unicode (a lone surrogate
    escape is legal JSON syntax for a character no UTF-8 text can hold)."""
    if isinstance(v, (dict, list)):
        if depth == 0:
            raise ValueError(f"nested deeper than {MAX_JSON_DEPTH} levels")
        for x in (v.items() if isinstance(v, dict) else v):
            if isinstance(x, tuple):
                _strict(x[0], depth)
                x = x[1]
            _strict(x, depth - 1)
    elif isinstance(v, str):
        try:
            v.encode("utf-8")
        except UnicodeEncodeError:
            raise ValueError("a string holds a lone UTF-16 surrogate (\\ud800-\\udfff)") from None


def dumps(model: BaseModel) -> bytes:
    return model.model_dump_json().encode()
