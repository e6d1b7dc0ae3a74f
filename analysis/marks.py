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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from daemon.records.atomic import AtomicWriter
from daemon.utc import utc_stamp

MARKS = "marks.json"
FORMAT_VERSION = 1
MAX_MARKS = 500
MAX_NAME = 80
ON_BODY_MM = 5.0
"""A mark lies on the body: at most this far from the scan's mesh surface."""
SAME_SPOT_MM = 3.0
"""A new mark this near an existing mark of the same scan is the same spot (refused)."""
_MARK_ID = re.compile(r"^[0-9a-f]{10}$")


class MarkError(ValueError):
    """A mark or a marks file is not valid; names the field and the value."""


class MarkOffBody(MarkError):
    """A new mark farther than ON_BODY_MM from the scan's body surface."""

    def __init__(self, point_mm: tuple[float, float, float], distance_mm: float) -> None:
        self.point_mm, self.distance_mm = point_mm, distance_mm
        where = ", ".join(f"{v:.1f}" for v in point_mm)
        super().__init__(f"mark point ({where}) mm is {distance_mm:.1f} mm from this scan's body surface; "
                         f"a mark lies on the body (within {ON_BODY_MM:g} mm of it)")


class MarkDuplicate(MarkError):
    """A new mark within SAME_SPOT_MM of an existing mark of the same scan."""

    def __init__(self, existing: Mark, distance_mm: float) -> None:
        self.existing, self.distance_mm = existing, distance_mm
        super().__init__(f"mark {existing.number} {existing.name!r} is {distance_mm:.1f} mm from this point: "
                         f"the same spot (marks are at least {SAME_SPOT_MM:g} mm apart); rename or delete it instead")


@dataclass(frozen=True)
class Mark:
    """One lesion mark. point_mm: (3,) on the scan's mesh, rig frame, mm."""

    id: str
    name: str
    point_mm: tuple[float, float, float]
    created_utc: str
    carried_from: dict[str, Any] | None = None
    number: int = 0
    """The mark's number on this scan (1, 2, ...; the label on the body), never reused while it lasts."""

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


def new_mark(name: Any, point: Any, carried_from: dict[str, Any] | None = None, number: int = 0) -> Mark:
    return Mark(secrets.token_hex(5), check_name(name), check_point(point), utc_stamp(), carried_from, number)


def place_mark(book: MarkBook, mark: Mark, surface_distance_mm: float) -> Mark:
    """``mark`` numbered after the book's last and added to it, when it lies on the body
    (``surface_distance_mm`` from the scan's mesh) and is no existing mark's spot; raises
    MarkOffBody or MarkDuplicate (naming the existing mark) and leaves the book as it was."""
    if not surface_distance_mm <= ON_BODY_MM:
        raise MarkOffBody(mark.point_mm, surface_distance_mm)
    if book.marks:
        others = np.array([m.point_mm for m in book.marks])
        gaps = np.linalg.norm(others - np.array(mark.point_mm), axis=1)
        nearest = int(np.argmin(gaps))
        if gaps[nearest] < SAME_SPOT_MM:
            raise MarkDuplicate(book.marks[nearest], float(gaps[nearest]))
    placed = replace(mark, number=max((m.number for m in book.marks), default=0) + 1)
    book.marks.append(placed)
    return placed


def numbered(marks: list[Mark]) -> list[Mark]:
    """Marks from a file written without numbers numbered after the highest, in the file's order."""
    top = max((m.number for m in marks), default=0)
    out = []
    for mark in marks:
        if mark.number <= 0:
            top += 1
            mark = replace(mark, number=top)
        out.append(mark)
    return out


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
                      m.get("carried_from"), int(m.get("number", 0))) for m in data["marks"]]
        previous = data.get("previous_scan")
        return MarkBook(numbered(marks), str(previous) if previous else None)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise MarkError(f"{path}: unreadable marks file: {exc}") from exc


def write_marks(folder: Path, book: MarkBook) -> None:
    if len(book.marks) > MAX_MARKS:
        raise MarkError(f"{len(book.marks)} marks on one scan; at most {MAX_MARKS}")
    book.marks = numbered(book.marks)
    text = json.dumps(book.as_dict(), indent=1, allow_nan=False) + "\n"
    AtomicWriter().write(folder / MARKS, text.encode())


def check_mark_id(mark_id: str) -> str:
    if not _MARK_ID.match(mark_id):
        raise MarkError(f"mark id {mark_id[:40]!r}: expected 10 hex digits")
    return mark_id
