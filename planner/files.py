"""Reading a whole file with its size bounded, so that a wrong or hostile file cannot fill the memory."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def read_at_most(path: Path, max_bytes: int, what: str, error: Callable[[str], Exception]) -> bytes:
    """The bytes of the file at ``path``; raises ``error(problem)`` when it holds more than
    ``max_bytes`` (what: the kind of file, for the message, "manifest"). OSError passes through."""
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise error(f"larger than {max_bytes} bytes: not a {what}")
    return data
