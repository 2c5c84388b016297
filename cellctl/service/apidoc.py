"""docs/API.md, generated from the pydantic models of cellctl.service.api so the document cannot drift from
the code (a test compares the committed file with this output).

    python -m cellctl.service.apidoc > docs/API.md
"""

from __future__ import annotations

import json
import sys

from pydantic import BaseModel

from planners.paint_separation import PaintSeparation

from cellctl.service import api
from cellctl.service.api import (ERROR_CODES, MAX_MESSAGE_BYTES, MAX_PAYLOAD_BYTES, SCHEMA_VERSION, Artifacts,
                                 CancelReply, CancelRequest, CellStatus, CutAccuracy, CutGap, CutPathSummary,
                                 DryRunSummary, ErrorDetail, ErrorReply, FileChunk, FileChunkRequest, FileInfo, FileList, JobBrief, JobEvent, JobList, JobRecord,
                                 ListJobsRequest, Progress, ResultSummary, ScanDrawingRequest, SubmitReply, Transition)
from cellctl.service.api import CommissionPaintReply, CommissionPaintRequest, PaintModel, PaintReply

J = "20250314T101500Z-3f9a1c"  # example job id
T0 = "2025-03-14T10:15:00.120Z"


def examples() -> dict[str, BaseModel]:
    """Fixed example messages (no clock, no randomness: the document must be reproducible)."""
    req = ScanDrawingRequest(scene="smooth_cylinder", planner="gnbv", max_steps=12, noise=True,
                             requested_by="tablet-2", request_id="tablet-2:5f0c1d7e-9a41-4e0b-8f7a-3c2b1a0d9e8f")
    result = ResultSummary(scene="smooth_cylinder", planner="gnbv", steps=5, terminated_by="quality",
                           coverage_percent=97.9, coverage_hit=238, coverage_total=243, planning_s=5.61, step_s=1.4,
                           capture_s=1.3, motion_planning_s=0.42, motion_s=9.8, displacement_m=0.61,
                           cut=CutPathSummary(branches=1, feasible_branches=1, poses=129, feasible_poses=129,
                                              length_m=0.637, planning_s=2.1, cut_fraction=0.941,
                                              drawing_length_m=0.677,
                                              gaps=[CutGap(branch=0, length_m=0.040, reason="out of reach",
                                                           detail="the torch pose is beyond the arm's reach at "
                                                                  "every tilt (8 out of reach; 8 poses in all)",
                                                           start=[0.712, 0.221, 0.141], end=[0.690, 0.197, 0.152])],
                                              warnings=[]))
    return {
        "request": req,
        "submit_reply": SubmitReply(job_id=J, queue_position=1),
        "submit_again": SubmitReply(job_id=J, state="running", duplicate=True),
        "file_list": FileList(job_id=J, chunk_max=api.CHUNK_MAX, files=[
            FileInfo(name="cut_path.json", size=183214, sha256="5e0c" + "1" * 56 + "9a2f"),
            FileInfo(name="scan.rrd", size=18260931, sha256="a41b" + "2" * 56 + "07c3")]),
        "file_chunk": FileChunk(job_id=J, name="cut_path.json", offset=0, length=21, size=183214,
                                sha256="5e0c" + "1" * 56 + "9a2f", eof=False, data="eyJzY2hlbWFfdmVyc2lvbiI6IDEs"),
        "error_invalid": ErrorReply(code="invalid_request", message="invalid request: planner: Input should be "
                                    "'gnbv', 'cnbv', 'enpv' or 'global'",
                                    details=[ErrorDetail(loc="planner", msg="Input should be 'gnbv', 'cnbv', 'enpv' "
                                                                            "or 'global'")]),
        "error_queue_full": ErrorReply(code="queue_full", message="8 jobs are waiting (service.queue_max = 8); "
                                                                  "submit again when one has started"),
        "record": JobRecord(
            job_id=J, cell_id="sim-1", request=req, state="done", created_at=T0, updated_at="2025-03-14T10:15:31.906Z",
            transitions=[Transition(state="queued", at=T0), Transition(state="running", at="2025-03-14T10:15:00.135Z"),
                         Transition(state="done", at="2025-03-14T10:15:31.904Z")],
            progress=Progress(phase="done", seq=9, step=4, max_steps=12, coverage_percent=97.9, drawing_points=4210,
                              at="2025-03-14T10:15:31.906Z"),
            result=result,
            artifacts=Artifacts(dir=f"/var/lib/scrapcell/jobs/{J}",
                                files=["coverage.png", "cut_path.csv", "cut_path.json", "cut_trajectory.npz",
                                       "drawing.ply", "paint_check.png", "paint_view0.png", "paint_view1.png",
                                       "paint_view2.png", "paint_view3.png", "paint_view4.png", "result.json",
                                       "scan.rrd", "surface.ply", "view0.png"])),
        "list_request": ListJobsRequest(limit=5, state="done"),
        "list": JobList(cell_id="sim-1", total=42, limit=5, jobs=[
            JobBrief(job_id=J, state="done", created_at=T0, updated_at="2025-03-14T10:15:31.906Z",
                     scene="smooth_cylinder", planner="gnbv", coverage_percent=97.9)]),
        "cancel_request": CancelRequest(reason="wrong part on the table"),
        "cancel_reply": CancelReply(job_id=J, state="cancelling"),
        "status": CellStatus(cell_id="sim-1", version="0.1.0", mode="sim", arm_ready=True, camera_ready=True,
                             ready=True,
                             devices="pybullet twin (arm and D435), built per job", accepting_jobs=True,
                             queue_length=1, queue_max=8, running_job=J, jobs_total=42,
                             started_at="2025-03-14T08:00:00.000Z", uptime_s=8100.12),
        "status_not_ready": CellStatus(
            cell_id="real-1", version="0.1.0", mode="real", arm_ready=False, camera_ready=True, ready=False,
            not_ready_reason="arm: Franka at 172.16.0.2: connection to the FCI port 1337 refused: FCI is not active "
                             "(Desk answers on port 443: open Desk, unlock the joints and activate FCI)",
            devices="franky panda at 172.16.0.2; RealSense D435 141722071234 848x480@30", accepting_jobs=True,
            queue_length=0, queue_max=8, jobs_total=42, started_at="2025-03-14T08:00:00.000Z", uptime_s=31.5),
        "error_not_ready": ErrorReply(code="cell_not_ready", message="the cell is not ready, nothing was queued: arm: "
                                      "Franka at 172.16.0.2: connection to the FCI port 1337 refused: FCI is not "
                                      "active (...); submit again once status shows ready (the devices are checked "
                                      "every 10 s)"),
        "event_step": JobEvent(job_id=J, seq=3, phase="scanning", state="running", step=1, max_steps=12,
                               coverage_percent=87.2, drawing_points=3665, time="2025-03-14T10:15:06.512Z"),
        "event_done": JobEvent(job_id=J, seq=9, phase="done", state="done", step=4, max_steps=12,
                               coverage_percent=97.9, drawing_points=4210, time="2025-03-14T10:15:31.906Z"),
    }


def _json(m: BaseModel) -> str:
    return "```json\n" + json.dumps(m.model_dump(mode="json", exclude_none=True), indent=2) + "\n```"


def _type(prop: dict, defs: dict) -> str:
    if "$ref" in prop:
        name = prop["$ref"].split("/")[-1]
        return f"[{name}](#{name.lower()})"
    if "anyOf" in prop:
        return " \\| ".join(_type(p, defs) for p in prop["anyOf"])
    if "const" in prop:
        return f"`{json.dumps(prop['const'])}`"
    if "enum" in prop:
        return " \\| ".join(f"`{json.dumps(v)}`" for v in prop["enum"])
    t = prop.get("type", "any")
    if t == "array":
        return f"array of {_type(prop.get('items', {}), defs)}"
    if t == "object" and "additionalProperties" in prop:
        return f"object of {_type(prop['additionalProperties'], defs)}"
    return t


def _constraints(prop: dict) -> str:
    out = []
    for p in [prop, *prop.get("anyOf", [])]:
        for k, label in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("maxLength", "length ≤"),
                         ("maxItems", "items ≤")):
            if k in p:
                out.append(f"{label} {p[k]}")
        if "pattern" in p:
            out.append(f"pattern `{p['pattern']}`")
    return ", ".join(out)


def field_table(model: type[BaseModel]) -> str:
    schema = model.model_json_schema(mode="serialization")
    defs = schema.get("$defs", {})
    required = set(schema.get("required", []))
    rows = ["| field | type | required / default | constraints | meaning |", "|---|---|---|---|---|"]
    for name, prop in schema["properties"].items():
        if name in required:
            req = "**required**"
        elif "default" in prop:
            req = f"`{json.dumps(prop['default'])}`"
        else:
            req = "optional"
        desc = (prop.get("description") or "").replace("|", "\\|").replace("\n", " ")
        cons = _constraints(prop).replace("|", "\\|")
        rows.append(f"| `{name}` | {_type(prop, defs)} | {req} | {cons} | {desc} |")
    return "\n".join(rows)


MODELS: list[type[BaseModel]] = [ScanDrawingRequest, SubmitReply, ListJobsRequest, JobList, JobBrief, JobRecord,
                                 Transition, Progress, ResultSummary, CutPathSummary, CutGap, CutAccuracy,
                                 DryRunSummary, PaintSeparation, Artifacts, FileList, FileInfo, FileChunkRequest, FileChunk,
                                 CancelRequest, CancelReply, CellStatus, PaintReply, PaintModel, CommissionPaintRequest,
                                 CommissionPaintReply, JobEvent, ErrorReply, ErrorDetail]


def render() -> str:
    ex = examples()
    k = "cell/<cell_id>"
    parts = [f"""# scrapcell job API over Zenoh (schema version {SCHEMA_VERSION})

<!-- Generated by `python -m cellctl.service.apidoc > docs/API.md` from cellctl/service/api.py. Do not edit by hand:
     tests/test_api_models.py fails when this file and the models disagree. -->

An operator tablet submits "scan drawing" to a cell (a Panda + D435 behind `cellctl serve`) and gets the
cutting path back. Transport: [Zenoh](https://zenoh.io) 1.x (eclipse-zenoh 1.10.2). Every payload is UTF-8
JSON (Zenoh encoding `application/json`), every reply carries `schema_version` ({SCHEMA_VERSION}; in a request it
may be left out, and means {SCHEMA_VERSION}), unknown
fields are refused and types are strict (`"5"` is not `5`). Python clients: `cellctl.service.client.CellClient`;
command line: `cellctl submit|jobs|status --cell <cell_id> --connect <endpoint>`.

## Connecting

- The cell is either a Zenoh **peer** listening on `service.listen` (default `tcp/127.0.0.1:7447`), or a
  **client** of a Zenoh router at `service.connect`. A tablet opens a client session that connects to the
  cell's endpoint or to the router. With explicit endpoints multicast scouting is off.
- **The yard router speaks TLS only** (`tls/<router-host>:7447`, deploy/README.md). A client's Zenoh config
  needs the yard's CA certificate as `transport.link.tls.root_ca_certificate` (the router's certificate
  and its name are checked against it) and its own `transport.auth.usrpwd.user` / `password`;
  `deploy/zenoh/operator.json5` is such a config. Zenoh reports every failed open alike ("Unable to
  connect"); `CellClient` and `cellctl` (`--ca FILE`) tell apart a certificate problem
  (`CertificateProblem`: expired, not signed by that CA, not made for that name, or a `tcp/` endpoint on
  a TLS port), a refused login (`SessionRefused`) and a router that is down (`CellUnreachable`).
- `{k}/alive` is a liveliness token: present while the service is up and ready for jobs.
- **Access control.** When the router enforces Zenoh access control, a denied query is not answered at
  all (no error reply): the querier sees **no reply within its timeout** (in practice often at once).
  Clients report that as "no reply ... (waited up to 5 s): the cell is down, or access control denied
  this request" (`NoReply`, `cellctl` exit status 3). Error replies (below) come from the cell itself.
  A query on a key that no queryable serves (wrong cell id) also gets no reply.
- The service itself needs, on a router with access control (flows as the router sees them): ingress
  `declare_queryable` on `{k}/jobs/**` and `{k}/status`, `put` on `{k}/jobs/*/events`, `liveliness_token`
  on `{k}/alive` and `reply` on those keys; egress `query` (and `declare_subscriber`) on `{k}/**`. Rules
  per key expression (e.g. a viewer that may only query `cell/*/status` and `cell/*/jobs`) work: queries
  are checked against their own key. `deploy/zenoh/router.json5` gives each cell exactly that on its own
  keys, and nothing else.
- **Starting and reconnecting.** In client mode `zenoh.open` fails at once when nothing answers at the
  endpoints (the router or cell is down): try again later. If an open session gets no answer after the
  cell or router restarted, close it and open a new one. `{k}/alive` tells whether the cell is up: a liveliness `get` on it answers
  while it is, a liveliness subscriber hears it come and go (read the records of the jobs you follow
  when it comes back, see "Job states").
- **What a client needs** on a router with access control: `query` on `{k}/status`, `{k}/jobs`,
  `{k}/jobs/*`, `{k}/jobs/*/files`, `{k}/jobs/*/files/*`, `{k}/paint` (and, to command, `{k}/jobs/submit` and
  `{k}/jobs/*/cancel`, `{k}/paint/commission`), `declare_subscriber` on `{k}/jobs/*/events`, and the liveliness query and
  subscriber on `{k}/alive`.
- **Rate limit.** The yard router drops a session's submit that follows its previous submit (to any cell)
  within 0.2 s, and likewise for cancels; a paint commissioning within 1 s of the last: the dropped query gets no reply. Reads are not limited.

## Key expressions

| key expression | kind | query payload | reply |
|---|---|---|---|
| `{k}/jobs/submit` | queryable | [ScanDrawingRequest](#scandrawingrequest) (required) | [SubmitReply](#submitreply), at once |
| `{k}/jobs` | queryable | [ListJobsRequest](#listjobsrequest) (optional) | [JobList](#joblist), newest first |
| `{k}/jobs/<job_id>` | queryable | none (ignored) | [JobRecord](#jobrecord) |
| `{k}/jobs/<job_id>/cancel` | queryable | [CancelRequest](#cancelrequest) (optional) | [CancelReply](#cancelreply) |
| `{k}/jobs/<job_id>/files` | queryable | none (ignored) | [FileList](#filelist) (an ended job) |
| `{k}/jobs/<job_id>/files/<name>` | queryable | [FileChunkRequest](#filechunkrequest) (optional) | [FileChunk](#filechunk) |
| `{k}/jobs/<job_id>/events` | publication | - | [JobEvent](#jobevent) samples |
| `{k}/status` | queryable | none (ignored) | [CellStatus](#cellstatus) |
| `{k}/paint` | queryable | none (ignored) | [PaintReply](#paintreply) |
| `{k}/paint/commission` | queryable | [CommissionPaintRequest](#commissionpaintrequest) (required) | [CommissionPaintReply](#commissionpaintreply), after a few seconds |
| `{k}/alive` | liveliness token | - | - |

Any query can instead get an **error reply** (Zenoh `reply_err`) with an [ErrorReply](#errorreply) payload.
Queries on `{k}/jobs/**` must use exact keys (no `*`/`**`): a wildcard gets `invalid_request`.
`cell/*/status` is the one useful wildcard: every cell that hears it answers with its own status, on its
own key `cell/<cell_id>/status`. A query whose key expression spans several of a cell's keys (e.g. `{k}/**`) reaches
each queryable it intersects and gets one reply from each (here a status and an `invalid_request`):
a client must be ready for several replies to one query and tell them apart by their key. Payloads over
{MAX_PAYLOAD_BYTES} bytes get `payload_too_large` on every key (including those that ignore their payload); a
query over {MAX_MESSAGE_BYTES} bytes is dropped by the cell's Zenoh transport (and by the yard router's,
`deploy/zenoh/router.json5`) and gets no reply.

### Submit: `{k}/jobs/submit`

Validates the request, stores the job, queues it and replies at once; the job then runs when the arm is
free (one job at a time, first in first out). Request:

{_json(ex["request"])}

Reply:

{_json(ex["submit_reply"])}

Error replies, e.g. an unknown planner, or a full queue:

{_json(ex["error_invalid"])}

{_json(ex["error_queue_full"])}

A cell whose arm or camera does not answer (`ready: false` in the status) refuses every submit with
`cell_not_ready` and stores nothing; the job is the client's to submit again:

{_json(ex["error_not_ready"])}

To follow a job from its first event, subscribe to `{k}/jobs/*/events` **before** submitting and keep the
events whose `job_id` is the one in the reply (`CellClient.submit(request, on_event=...)` does this). The
`queued` event (seq 0) can arrive before the submit's reply: buffer events until the job id is known.

#### Timeouts and retries

The cell's replies, normal and error, are JSON with Zenoh encoding `application/json`. "No answer" comes in
two forms with eclipse-zenoh 1.10.2: a query that a queryable holds past the client's timeout ends with
**Zenoh's own error reply**, payload the 7 bytes `Timeout`, encoding `zenoh/string` (not JSON, not an
ErrorReply); a query that no queryable serves (the cell is down, a wrong cell id, denied by access
control, dropped by the rate limit) ends **at once with no reply**. A client must treat both as "no
answer", never parse them as an ErrorReply. For reads (`status`, a job, the list, files) just ask again.
For a submit the job may have been queued although the reply was lost: put a **`request_id`** of your
own in every submit (8-64 characters of `A-Z a-z 0-9 _ . : -`, e.g. `<tablet>:<uuid4>`: with the 36
characters of a UUID the tablet's part has at most 27 of those characters) and, on no answer, send the
**same request, request_id and all**, again. The cell keeps each job's request_id with it: a submit whose
request_id it already holds queues nothing and replies with that job, whatever became of it, and
`duplicate: true` (events you missed meanwhile are in its record):

{_json(ex["submit_again"])}

The same request_id with a different request is `invalid_request` (detail `loc: request_id`). An error
reply to a submit stores nothing: the request_id stays free, and the same request may be sent again
later (after `queue_full`, `cell_not_ready`, `shutting_down`). A tablet should wait at least 5 s for a
submit's reply (the cell answers in milliseconds; 5 s covers a busy router or a Wi-Fi roam) and make 3
attempts in all, pausing 0.5 s, then 1 s, between them (never under 0.2 s: the yard router drops a
session's second submit within 0.2 s, with no reply); `CellClient.submit` does exactly this. If there is
still no answer, show the operator that the cell is unreachable and keep the request (with its
request_id) to send once the cell answers again.

### A job: `{k}/jobs/<job_id>`

The job's record, kept in the cell's SQLite store across restarts: request, state and its transitions,
last progress, result summary, error, and the artifacts folder on the cell controller
(`<data_dir>/jobs/<job_id>/`: result.json, drawing.ply, surface.ply, cut_path.json/.csv,
cut_trajectory.npz, scan.rrd, coverage.png, view0.png; paint_check.png, the initial view with what the paint
check took as paint in cyan; paint_view<k>.png, every view k = 0, 1, ... at half the camera's resolution with
what it took as paint in cyan).

{_json(ex["record"])}

### The cut and the other files: `{k}/jobs/<job_id>/files`

Once a job has ended, every file of its folder can be fetched: the cutting path `cut_path.json`
(below), its joint trajectories `cut_trajectory.npz` (NumPy; per cut `branch<i>_<approach|cut|retract>_t`
and `_q`), the drawing and surface clouds `drawing.ply`/`surface.ply`, the Rerun recording `scan.rrd`,
`result.json` (the summary plus every step) and the pictures. Before the job ends: `not_ended`. List them:

{_json(ex["file_list"])}

then ask for each by name, chunk by chunk: a query on `{k}/jobs/<job_id>/files/<name>` with
`{{"offset": 0, "length": {api.CHUNK_DEFAULT}}}` (at most `chunk_max` = {api.CHUNK_MAX} bytes per chunk; no payload: the first
{api.CHUNK_DEFAULT} bytes) replies

{_json(ex["file_chunk"])}

Decode `data` (base64), append it, ask again at the reply's `offset + length` until `eof` (a chunk may
hold fewer bytes than asked for, as the example here, cut short to fit the page), then check the SHA-256
of the joined bytes against `sha256`. An ended job's files do not change; if `sha256` or `size` differ
between chunks anyway, start over. At or past the end a chunk has `length: 0` and `eof: true`. An
unknown name, or a folder that retention has deleted meanwhile, is `not_found`; a name with a path or
starting with `.` is `invalid_request`. `FileList.chunk_max` is the most `length` may ask for.
`CellClient.fetch(job_id, name, path)` and `cellctl jobs fetch <job_id> [--name cut_path.json] [--out DIR]`
do all of this.

**`cut_path.json`** (robot base frame; metres, radians, seconds): `feasible`, `cut_fraction` of the
drawing's `drawing_length_m` that the cuts cover, `gaps` (as in the summary, plus each gap's `points`
and surface `normal`), and `branches`, the cuts in cutting order, each with `points` and `normals` (N×3),
the torch tip `poses` (N×4×4, z into the metal), `times_s` and `speeds_mps` along the cut, the joint
solution at every pose `q` and `qd` (N×7, null where none), the configurations to start and end from
`approach_q`/`retract_q`, the durations of approach, cut and retract, `feasibility` per pose (`ok` or why
not) and `feasible` for the whole cut (an approach, the cut and a retract are all collision-free and
within the arm's limits). Cut only `feasible` branches.

### Job list: `{k}/jobs`

Newest first, at most `limit` (≤ {api.LIST_LIMIT_MAX}); optional payload:

{_json(ex["list_request"])}

{_json(ex["list"])}

### Cancel: `{k}/jobs/<job_id>/cancel`

A queued job is cancelled at once (`state: "cancelled"`). A running job's scan stops at once (the arm
is stopped mid-move, the partial result and artifacts are kept, no cut is planned): the reply says
`cancelling` and the final `cancelled` follows as an event and in the record. A job that already ended:
`not_cancellable`; an unknown id: `not_found`.

{_json(ex["cancel_request"])}

{_json(ex["cancel_reply"])}

### Events: `{k}/jobs/<job_id>/events`

One event per phase change and per exploration step. `seq` counts 0, 1, 2, ... per job without gaps
(a gap means a lost event: read the record). Phases in order: `queued` → `scanning` (once when the job
starts, then once per step) → `planning-cut` → one of `done`, `failed`, `cancelled`, `interrupted`.
The record is written before the event is published: after a terminal event the record is final.

{_json(ex["event_step"])}

{_json(ex["event_done"])}

### Status: `{k}/status`

{_json(ex["status"])}

`ready` says whether a job submitted now could start. In modes `fcisim` and `real` the service probes the
arm (one libfranka connection: reachable, FCI active, right model and kinematics) and the camera (the
configured D435 connected, with its modes) when it starts, every 10 s while no job runs and right after a
refused submit or a finished job; `not_ready_reason` then says what is missing:

{_json(ex["status_not_ready"])}

### The paint: `{k}/paint` and `{k}/paint/commission`

The cell finds the line by its paint's colour. `{k}/paint` says which paint that is; `{k}/paint/commission`
learns a new one from one picture of a sample: the paint sprayed on a piece of the yard's scrap, held
0.25-0.5 m in front of the camera with the paint in the middle of the picture and bare metal all round it
(`cellctl calibrate paint` does the same from the command line; docs/HARDWARE.md says how the picture is
read). Nothing moves. Only an idle cell takes it (a running or queued job holds the camera: `cell_busy`).
The reply comes when the picture is read, a few seconds later (use a query timeout of 60 s): `ok` true and
the new paint, which every job submitted after it uses (the cell's config is pointed at the written file,
so a restart keeps it), or `ok` false and the `reason` (no paint in the sample, paint the cell cannot tell
from this metal), the cell's paint unchanged. Either way `picture_png_base64` is the picture with what the
paint takes as paint in cyan. On a twin cell `twin_finish`, `twin_paint`, `twin_light` and `twin_no_paint`
describe the sample held in front of the twin's camera; a real cell refuses them (`invalid_request`).

```json
{{"schema_version": 1, "name": "pink", "requested_by": "ana"}}
```

## Job states

`queued` → `running` → (`cancelling` →) `done` | `failed` | `cancelled` | `interrupted`; a queued job can
go straight to `cancelled` (or `interrupted`, see below). A record's `artifacts` is absent until the job
has a folder, and again once retention has deleted it (`service.retention_days`, `service.retention_gb`:
oldest ended jobs first, never the last one); it never names a folder that does not exist.

- `done`: the scan ended by itself (quality, frontier, max_steps, ...); `result.cut` says what will be cut:
  `paint.line_share`, the share of the line the paint gives (counted where it lies on the paint band's
  centre, the paint no line follows counted uncut; its length `paint.line_on_paint_m`) within 5 mm of
  the flame where the flame runs on the band's centre (measured at every sample of the planned motion
  with the flame lit): the share the operator is told; `paint.cut_share`, the share of the painted area
  under the flame's path, an independent check (where the two disagree by more than 3 points a warning
  says so); `paint.uncut` the pieces of paint left, where and
  why; `paint.unseen` the borders where the paint the scan saw runs on into surface it never measured
  (`centre`, `border_m`, `wall_m`: the height of a measured wall standing over the border, 0 at a rim),
  longest first: where any is listed, both shares are of less than the whole line (the cell cannot
  say how much less) and a warning says where to look; `cut_fraction`, the share of the drawing's length
  the cell's own line says it covers; `feasible_branches` cuts, the `gaps`
  left uncut with their reasons, `warnings` in words (its own `error` when no cut could be planned). When
  not all of the paint will be cut, the `done` transition's `note` and the final event's `message` start
  with `warning:` and give the told share (`paint.line_share`; `cut_fraction` where no paint check was
  made) and what is left by reason (e.g. `warning: 94.1 % of the drawing will be cut in 1 cuts; uncut:
  40 mm out of reach`); so do they, even at 100 %, when `paint.unseen` lists a border (`...; the paint
  runs on unseen at 2 borders: the share is of the paint seen`).
- `failed`: the scan failed (`error`), or ran longer than `service.job_timeout_s` (`error` starts with
  `timeout:`); the partial result is kept. **A piece whose paint the cell cannot tell from its metal**
  (rust the paint's colour, the wrong paint, no paint in the initial view) fails right after the initial
  view, before any further move, with `result.terminated_by` = `paint_not_separable`, `error` starting
  `ScanError: paint_not_separable:` and the reason in words, `result.paint` (PaintSeparation) with what was
  measured, no `cut`, and `paint_check.png` in its files: the camera image, what was taken as paint in
  cyan. Show the operator that picture; recommission the paint (`cellctl calibrate paint`) or mark the
  piece again. A piece that passes but only just (paint and metal within `paint.warn_delta_e`) ends `done`
  with `result.paint.warnings` naming the risk.
- `cancelled`: by a cancel request; the partial result is kept.
- `interrupted`: the job was running when the service stopped (SIGTERM/SIGINT: the scan is stopped,
  its partial result kept) or died (found running at the next start; what it wrote is kept and listed).
  Never silently lost: resubmit it. Jobs still **queued** when the service stopped or died keep their
  place and run after it restarts, each with a `queued` event saying so (`service.requeue_after_restart`,
  on by default; off, they end `interrupted` too).
- **After a restart** (the `{k}/alive` token goes and comes back) the events the restarted cell published
  before your session reconnected are not sent again: read the records of the jobs you follow (the
  record's `progress.seq` is the last event's `seq`). Likewise after a gap in `seq`. A client without
  events polls the record every 1-2 s.

## Error codes

| code | when |
|---|---|
""" + "\n".join(f"| `{c}` | {m} |" for c, m in ERROR_CODES.items()) + """

## Messages
"""]
    for m in MODELS:
        doc = (m.__doc__ or "").strip()
        parts.append(f"### {m.__name__}\n\n" + (f"{doc}\n\n" if doc else "") + field_table(m) + "\n")
    return "\n".join(parts)


def main() -> None:
    sys.stdout.write(render())


if __name__ == "__main__":
    main()
