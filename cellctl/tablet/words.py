"""The job API's terms in the words a worker reads on the tablet."""

from __future__ import annotations

import datetime as dt

from cellctl.service.api import JobRecord

PHASES = {"queued": "Waiting in the queue", "scanning": "Scanning the piece", "planning-cut": "Planning the cut",
          "done": "Done", "failed": "Failed", "cancelled": "Cancelled", "interrupted": "Interrupted"}
STOPPED_BY = {"quality": "the drawing is fully seen", "frontier": "nothing more to see", "max_steps": "the view limit",
              "unreachable": "no view left the arm can reach", "cancelled": "an operator cancelled it",
              "timeout": "the job took too long", "interrupted": "the cell stopped", "error": "an error"}
GAP_REASONS = {"out of reach": "the arm cannot reach it", "joint limits": "the arm's joints cannot turn that far",
               "collision": "the torch would hit the piece", "singular": "the arm cannot hold the torch steady there",
               "reconfigure": "the torch lifts and lands again", "too short": "too short to cut"}
STATE_COLOURS = {"queued": "grey-8", "running": "blue-8", "cancelling": "orange-9", "done": "green-8",
                 "failed": "red-9", "cancelled": "grey-8", "interrupted": "orange-9"}


def when(ts: str | None) -> str:
    """An API timestamp as local wall-clock time."""
    if not ts:
        return "-"
    try:
        return dt.datetime.fromisoformat(ts.replace("Z", "+00:00")).astimezone().strftime("%d %b %H:%M:%S")
    except ValueError:
        return ts


def elapsed(rec: JobRecord | None, now: dt.datetime | None = None) -> str:
    """Time since the job started running (to its end once it ended)."""
    if rec is None:
        return "-"
    started = next((t.at for t in rec.transitions if t.state == "running"), None)
    if started is None:
        return "not started"
    t0 = dt.datetime.fromisoformat(started.replace("Z", "+00:00"))
    ended = rec.updated_at if rec.state in {"done", "failed", "cancelled", "interrupted"} else None
    t1 = dt.datetime.fromisoformat(ended.replace("Z", "+00:00")) if ended else (now or dt.datetime.now(dt.timezone.utc))
    s = max(0, int((t1 - t0).total_seconds()))
    return f"{s // 60} min {s % 60:02d} s" if s >= 60 else f"{s} s"


def gap_reason(reason: str) -> str:
    return GAP_REASONS.get(reason, reason)
