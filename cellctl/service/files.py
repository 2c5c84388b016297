"""An ended job's files, served over the API in chunks: the cut (cut_path.json, cut_trajectory.npz), the
drawing, the recording, any file of the job's folder by name. Base64 chunks keep every reply under the
cell's 1 MiB message cap; the whole file's SHA-256 lets a client check what it joined.

Only the folder's own regular files are served (no path, no symlink), and only once the job has ended:
before that they are still being written. Hashes are computed once per file (ended jobs' files do not
change; a changed size or mtime computes it again)."""

from __future__ import annotations

import base64
import hashlib
import re
import threading
from pathlib import Path

from cellctl.service.api import (CHUNK_MAX, FILE_NAME_PATTERN, ApiError, FileChunk, FileChunkRequest, FileInfo,
                                 FileList)

_NAME = re.compile(FILE_NAME_PATTERN)
_READ = 1 << 20  # hashing reads this much at a time


class JobFiles:
    def __init__(self):
        self._hashes: dict[tuple[str, int, int], str] = {}  # (path, size, mtime_ns) -> sha256
        self._lock = threading.Lock()

    def listing(self, job_id: str, folder: Path | None) -> FileList:
        files = [self._info(p) for p in _files(folder)][:100]
        return FileList(job_id=job_id, files=files, chunk_max=CHUNK_MAX)

    def chunk(self, job_id: str, folder: Path | None, name: str, req: FileChunkRequest) -> FileChunk:
        path = self._path(job_id, folder, name)
        info = self._info(path)
        with open(path, "rb") as f:
            f.seek(req.offset)
            data = f.read(min(req.length, max(info.size - req.offset, 0)))
        return FileChunk(job_id=job_id, name=name, offset=req.offset, length=len(data), size=info.size,
                         sha256=info.sha256, eof=req.offset + len(data) >= info.size,
                         data=base64.b64encode(data).decode("ascii"))

    def _path(self, job_id: str, folder: Path | None, name: str) -> Path:
        if not _NAME.match(name):
            raise ApiError("invalid_request", f"file name {name!r}: a file of the job's folder, no path "
                           f"({FILE_NAME_PATTERN})")
        path = next((p for p in _files(folder) if p.name == name), None)
        if path is None:
            raise ApiError("not_found", f"job {job_id} has no file {name!r} (its files are listed on "
                           f".../jobs/{job_id}/files)")
        return path

    def _info(self, path: Path) -> FileInfo:
        st = path.stat()
        key = (str(path), st.st_size, st.st_mtime_ns)
        with self._lock:
            digest = self._hashes.get(key)
        if digest is None:
            h = hashlib.sha256()
            with open(path, "rb") as f:
                while block := f.read(_READ):
                    h.update(block)
            digest = h.hexdigest()
            with self._lock:
                self._hashes[key] = digest
        return FileInfo(name=path.name, size=st.st_size, sha256=digest)


def _files(folder: Path | None) -> list[Path]:
    """The folder's regular files that a name may ask for, by name (symlinks are not followed)."""
    if folder is None or not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if p.is_file() and not p.is_symlink() and _NAME.match(p.name)),
                  key=lambda p: p.name)
