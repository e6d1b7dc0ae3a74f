"""Output paths checked before the work: a command that would fail writing its result says so at
once, in one line, instead of after minutes of fusion, planning or evaluation (docs/hardening.md,
rule 4)."""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path


def output_problem(flag: str, path: Path | None, *, folder: bool = False,
                   suffixes: Sequence[str] = (), create: bool = True) -> str | None:
    """Why ``path`` (a file, or a folder with ``folder=True``) cannot be written, or None.

    Creates the missing folders on the way (the command would create them anyway) and proves the
    folder writable with a temporary file, which also holds for root and read-only mounts. With
    ``create=False`` nothing is made: the nearest folder that exists on the way is proved
    writable instead (for a command that may still refuse before it writes).
    """
    if path is None:
        return None
    if suffixes and not folder and path.suffix.lower() not in suffixes:
        return (f"{flag} {path}: cannot write {path.suffix or 'a file without suffix'!r}; "
                f"use one of {', '.join(suffixes)}")
    if not folder and path.is_dir():
        return f"{flag} {path}: is a folder"
    target = path if folder else path.parent
    blocking = next((p for p in (target, *target.parents) if p.exists()), None)
    if blocking is not None and not blocking.is_dir():
        return f"{flag} {path}: {blocking} is not a folder"
    try:
        if create:
            target.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=target if create else blocking):
            pass
    except OSError as exc:
        return f"{flag} {path}: cannot write there: {exc.strerror or exc}"
    return None
