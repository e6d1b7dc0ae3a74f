"""Reading a configuration YAML file with every size bounded.

Rig files, calibration files, target files and focus tables are read the same way: at most
``max_bytes`` bytes, flow collections ([ ], { }) nested at most 32 deep (PyYAML's scanner is
quadratic in that depth), safe_load only, and any failure (unreadable, too large, not YAML, a
5000-digit number, nesting thousands deep) turned into the caller's typed error naming the file.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

MAX_FLOW_NESTING = 32
_FLOW_SYNTAX = re.compile(rb"[\[\]{}'\"#\n]")


def flow_nesting(text: bytes) -> int:
    """Deepest nesting of YAML flow collections ([ ] and { }) outside quotes and comments."""
    depth = deepest = 0
    quote: bytes | None = None
    comment = False
    for match in _FLOW_SYNTAX.finditer(text):
        char = match.group()
        if comment:
            comment = char != b"\n"
        elif quote is not None:
            quote = None if char == quote else quote
        elif char in (b"'", b'"'):
            quote = char
        elif char == b"#":
            comment = True
        elif char in (b"[", b"{"):
            depth += 1
            deepest = max(deepest, depth)
        elif char in (b"]", b"}"):
            depth -= 1
    return deepest


def read_yaml(path: Path, *, max_bytes: int, what: str,
              error: Callable[[str], Exception]) -> tuple[Any, bytes]:
    """(parsed document, raw bytes) of a YAML file; ``error(problem)`` builds the exception raised.

    what: the kind of file, for messages ("rig file", "focus table").
    """
    try:
        with open(path, "rb") as f:
            text = f.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"cannot read: {exc.strerror or exc}") from exc
    if len(text) > max_bytes:
        raise error(f"larger than {max_bytes} bytes: not a {what}")
    if flow_nesting(text) > MAX_FLOW_NESTING:
        raise error(f"lists or mappings nested more than {MAX_FLOW_NESTING} deep: not a {what}")
    try:
        return yaml.safe_load(text), text
    except yaml.YAMLError as exc:
        raise error(f"not valid YAML: {str(exc)[:300]}") from exc
    except (ValueError, RecursionError) as exc:
        raise error(f"not a {what}: {type(exc).__name__}: {str(exc)[:200]}") from exc
