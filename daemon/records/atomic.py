"""Atomic file writes for the scan store, and its error tree.

A whole file is written to a temp file in the same folder, fsync'd, renamed over the old one
and the folder fsync'd, so a reader (or a daemon restarted after a crash) sees the previous
or the new version, never a torn one. A full disk (ENOSPC, EDQUOT) becomes StoreFull naming
the path and the bytes needed.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
from pathlib import Path

from daemon.errors import DaemonError


class StoreError(DaemonError):
    """Base of the store's errors; names the path involved."""

    def __init__(self, path: Path | str, message: str) -> None:
        self.path = str(path)
        super().__init__(f"scan store: {self.path}: {message}")


class StoreFull(StoreError):
    """No space left on the store's disk (ENOSPC); nothing already stored was lost."""

    def __init__(self, path: Path | str, bytes_needed: int, bytes_free: int | None = None) -> None:
        self.bytes_needed = bytes_needed
        self.bytes_free = bytes_free
        free = "" if bytes_free is None else f", {bytes_free} bytes free"
        super().__init__(path, f"disk full: {bytes_needed} bytes needed{free}")


class StoreWriteError(StoreError):
    """A write failed for another reason than a full disk (permissions, I/O error)."""


def fsync_dir(path: Path) -> None:
    """Make a rename or a new entry in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def raise_for(path: Path, exc: OSError, needed: int) -> None:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        free = None
        try:
            free = shutil.disk_usage(path.parent).free
        except OSError:
            pass
        raise StoreFull(path, needed, free) from exc
    raise StoreWriteError(path, f"{exc.strerror or exc} (errno {exc.errno})") from exc


class AtomicWriter:
    """Writes whole files atomically and appends fdatasync'd lines; ENOSPC becomes StoreFull."""

    def write(self, path: Path, data: bytes) -> None:
        tmp = path.with_name(f".{path.name}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
            try:
                self._write_all(fd, data)
                os.fdatasync(fd)  # data and size on disk; the name is made durable below
            finally:
                os.close(fd)
            os.replace(tmp, path)
            fsync_dir(path.parent)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise_for(path, exc, len(data))

    def append_line(self, path: Path, line: bytes) -> None:
        self.append_lines(path, [line])

    def append_lines(self, path: Path, lines: list[bytes]) -> None:
        """Append ``lines`` (each ending in a newline) and fdatasync once."""
        data = b"".join(lines)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o640)
            try:
                self._write_all(fd, data)
                os.fdatasync(fd)
            finally:
                os.close(fd)
        except OSError as exc:
            raise_for(path, exc, len(data))

    def _write_all(self, fd: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]


def sha256_of(path: Path) -> str:
    """SHA-256 (hex) of a file's content, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
