"""Lesion marks: named points a dermatologist places on a scan's body, kept beside the scan.

``<scan folder>/marks.json`` holds the marks and, optionally, the earlier scan of the same
person to compare with (the store knows no patients: the dermatologist names the earlier
scan). The file is written atomically and is not listed in the manifest: marks are notes
about a scan, never a change to its images or its record.
"""

from __future__ import annotations

import json
import math
import re
import secrets
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from daemon.atomic import AtomicWriter
from daemon.utc import utc_stamp

MARKS = "marks.json"
FORMAT_VERSION = 1
MAX_MARKS = 500
MAX_NAME = 80
_MARK_ID = re.compile(r"^[0-9a-f]{10}$")


class MarkError(ValueError):
    """A mark or a marks file is not valid; names the field and the value."""


@dataclass(frozen=True)
class Mark:
    """One lesion mark. point_mm: (3,) on the scan's mesh, rig frame, mm."""

    id: str
    name: str
    point_mm: tuple[float, float, float]
    created_utc: str
    carried_from: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "point_mm": list(self.point_mm)}


@dataclass
class MarkBook:
    """The content of one scan's marks.json."""

    marks: list[Mark] = field(default_factory=list)
    previous_scan: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"format_version": FORMAT_VERSION, "previous_scan": self.previous_scan,
                "marks": [m.as_dict() for m in self.marks]}


def check_name(name: Any) -> str:
    if not isinstance(name, str) or not name.strip():
        raise MarkError(f"mark name {name!r}: give a name (1-{MAX_NAME} characters)")
    name = " ".join(name.split())
    if len(name) > MAX_NAME or not name.isprintable():
        raise MarkError(f"mark name {name[:100]!r}: at most {MAX_NAME} printable characters")
    return name


def check_point(point: Any) -> tuple[float, float, float]:
    if (not isinstance(point, (list, tuple)) or len(point) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in point)
            or not all(math.isfinite(v) for v in point)):
        raise MarkError(f"mark point {point!r}: expected [x, y, z], three finite numbers in mm")
    return (float(point[0]), float(point[1]), float(point[2]))


def new_mark(name: Any, point: Any, carried_from: dict[str, Any] | None = None) -> Mark:
    return Mark(secrets.token_hex(5), check_name(name), check_point(point), utc_stamp(), carried_from)


def read_marks(folder: Path) -> MarkBook:
    """The scan's marks (an empty book when it has none); MarkError if the file is corrupt."""
    path = folder / MARKS
    if not path.is_file():
        return MarkBook()
    try:
        data = json.loads(path.read_text())
        if data.get("format_version") != FORMAT_VERSION:
            raise MarkError(f"{path}: format_version {data.get('format_version')!r}, expected {FORMAT_VERSION}")
        marks = [Mark(str(m["id"]), check_name(m["name"]), check_point(m["point_mm"]), str(m["created_utc"]),
                      m.get("carried_from")) for m in data["marks"]]
        previous = data.get("previous_scan")
        return MarkBook(marks, str(previous) if previous else None)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise MarkError(f"{path}: unreadable marks file: {exc}") from exc


def write_marks(folder: Path, book: MarkBook) -> None:
    if len(book.marks) > MAX_MARKS:
        raise MarkError(f"{len(book.marks)} marks on one scan; at most {MAX_MARKS}")
    text = json.dumps(book.as_dict(), indent=1, allow_nan=False) + "\n"
    AtomicWriter().write(folder / MARKS, text.encode())


def check_mark_id(mark_id: str) -> str:
    if not _MARK_ID.match(mark_id):
        raise MarkError(f"mark id {mark_id[:40]!r}: expected 10 hex digits")
    return mark_id
