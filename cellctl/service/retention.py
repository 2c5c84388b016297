"""Keep the cell's disk from filling: ended jobs' folders are deleted by age and by total size, oldest
first (``service.retention_days``, ``service.retention_gb``). A queued or running job's folder is never
touched, nor the last ended job's, so the cut just planned can always be fetched. Records stay in the
store; a record whose folder is gone names none (``JobRecord.artifacts``)."""

from __future__ import annotations

import logging
import os
import shutil
from datetime import datetime, timezone
from pathlib import Path

from cellctl.service.store import JobStore

log = logging.getLogger("cellctl.service.retention")


def folder_bytes(path: Path) -> int:
    total = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:
                pass
    return total


def prune(store: JobStore, jobs_root: Path, *, max_age_days: float | None, max_gb: float | None,
          now: datetime | None = None) -> list[str]:
    """Delete the folders retention asks for; returns their job ids, oldest first."""
    if max_age_days is None and max_gb is None:
        return []
    now = now or datetime.now(timezone.utc)
    ended = [(j, at, d) for j, at, d in store.ended_folders() if d.is_dir()][:-1]  # the last ended job stays
    removed: list[str] = []

    def remove(job_id: str, folder: Path, why: str) -> None:
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(job_id)
        log.info("job %s: folder deleted (%s)", job_id, why)

    if max_age_days is not None:
        for job_id, at, folder in list(ended):
            age_days = (now - datetime.fromisoformat(at.replace("Z", "+00:00"))).total_seconds() / 86400
            if age_days > max_age_days:
                remove(job_id, folder, f"ended {age_days:.1f} days ago, service.retention_days {max_age_days:g}")
        ended = [e for e in ended if e[0] not in removed]
    if max_gb is not None:
        limit = max_gb * 1e9
        total = folder_bytes(jobs_root) if jobs_root.is_dir() else 0
        for job_id, _at, folder in ended:
            if total <= limit:
                break
            size = folder_bytes(folder)
            remove(job_id, folder, f"the jobs' folders held {total / 1e9:.2f} GB, service.retention_gb {max_gb:g}")
            total -= size
    return removed
