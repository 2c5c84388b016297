"""The files a calibration writes beside the cell config: kept atomically, the one replaced kept as a .bak,
and the config pointed at the new one without touching its comments."""

from __future__ import annotations

import datetime
import os
from pathlib import Path

import yaml


def write_record(path: str | Path, record: dict, header: str) -> Path:
    """Atomic write (a crash never leaves half a calibration where the config reads it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(header + yaml.safe_dump(record, sort_keys=False, default_flow_style=None, width=110))
    os.replace(tmp, path)
    return path


def backup(path: Path) -> Path | None:
    """Keep the calibration a new one replaces, beside it with its time (never overwritten)."""
    if not path.is_file():
        return None
    stamp = datetime.datetime.fromtimestamp(path.stat().st_mtime).strftime("%Y%m%dT%H%M%S")
    dest, n = path.with_name(f"{path.name}.{stamp}.bak"), 1
    while dest.exists():
        n += 1
        dest = path.with_name(f"{path.name}.{stamp}-{n}.bak")
    dest.write_bytes(path.read_bytes())
    return dest


def point_config_at(cfg_path: Path, file_path: Path, key: str, command: str) -> str:
    """Make a cell config read a new calibration file under ``key``: a config that names none gets one
    appended (the config kept as a .bak first, its comments untouched); one that names another file is
    left as it is. Returns what happened, in words."""
    from configs.loading import safe_load

    text = cfg_path.read_text()
    current = (safe_load(text) or {}).get(key)
    rel = os.path.relpath(file_path.resolve(), cfg_path.parent.resolve())
    if current and (cfg_path.parent / current).resolve() == file_path.resolve():
        return f"{cfg_path.name} reads it ({key}: {current})"
    if current:
        return f"{cfg_path.name} still reads {current}: set {key}: {rel} there to use the new calibration"
    old = backup(cfg_path)
    stamp = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    tmp = cfg_path.with_name(cfg_path.name + ".tmp")
    tmp.write_text(text + ("" if text.endswith("\n") else "\n") + f"{key}: {rel}   # cellctl {command}, {stamp}\n")
    os.replace(tmp, cfg_path)
    return f"{cfg_path.name} now reads it ({key}: {rel} added; the config before is kept as {old.name})"
