"""manifest.json: what a scan is and the state of every image, as typed records.

The manifest is rewritten after each image, so its rendering caches the image lines that did
not change. ``from_dict`` refuses a manifest of another format version, naming the file.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from daemon.clinic.patient import Patient, PatientError, Study
from daemon.faults import Cause
from daemon.records.atomic import StoreError

FORMAT_VERSION = 1
MANIFEST = "manifest.json"


class ManifestError(StoreError):
    """A manifest is missing, unreadable or not a manifest of this format."""


class ScanEnd(str, enum.Enum):
    """The manifest's state. INCOMPLETE from the start until the scan ends; a folder a killed
    daemon left stays INCOMPLETE (interrupted). COMPLETE: every planned image is verified.
    PARTIAL: the rotation ran to its end but some planned images are not in the folder
    (:meth:`Manifest.missing_by_phone` says which phone's and why)."""

    COMPLETE = "complete"
    PARTIAL = "partial"
    INCOMPLETE = "incomplete"
    ABORTED = "aborted"
    FAULT = "fault"


class ImageStatus(str, enum.Enum):
    PLANNED = "planned"
    CAPTURED = "captured"
    PULLED = "pulled"
    VERIFIED = "verified"
    FAILED = "failed"
    MISSING = "missing"


class MissingReason(str, enum.Enum):
    """Why a planned image is not in the folder (an image's ``missing_reason``).

    PHONE_DROPPED: its phone had failed several captures in a row and was dropped for the rest
    of the scan (daemon/jobs/capture.py, ``DROP_AFTER_FAILURES``). CAPTURE_MISSED: the phone did not
    take it (an error, no answer, the lens or the trigger too late), retake included.
    PULL_FAILED: taken, but the pull from the phone failed or did not verify. NOT_PULLED: taken
    and still on the phone (the scan ended before its pull). NOT_REACHED: the scan ended before
    its pose (aborted, faulted, interrupted).
    """

    PHONE_DROPPED = "phone_dropped"
    CAPTURE_MISSED = "capture_missed"
    PULL_FAILED = "pull_failed"
    NOT_PULLED = "not_pulled"
    NOT_REACHED = "not_reached"

    @property
    def words(self) -> str:
        return self.value.replace("_", " ")


_REASON_OF_STATUS = {ImageStatus.PLANNED: MissingReason.NOT_REACHED, ImageStatus.CAPTURED: MissingReason.NOT_PULLED,
                     ImageStatus.PULLED: MissingReason.NOT_PULLED, ImageStatus.FAILED: MissingReason.PULL_FAILED,
                     ImageStatus.MISSING: MissingReason.CAPTURE_MISSED}


def json_safe(value: Any) -> Any:
    """JSON-safe: non-finite floats become null, numpy scalars become Python numbers."""
    if isinstance(value, (Cause, Patient, Study)):
        return value.as_dict()
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_bytes(value: Any) -> bytes:
    return (json.dumps(json_safe(value), indent=1, allow_nan=False) + "\n").encode()


class ManifestRenderer:
    """manifest.json bytes: indented JSON with one image record a line (readable, diffable).

    Image lines are cached by the record's field values, so rewriting the manifest after
    each image re-serialises only the records that changed (about 1 ms instead of 12 ms).
    """

    def __init__(self) -> None:
        self._lines: dict[int, tuple[tuple[Any, ...], str]] = {}

    def render(self, manifest: Manifest) -> bytes:
        head = {f.name: getattr(manifest, f.name) for f in dataclasses.fields(manifest)
                if f.name != "images"}
        head["counts"] = manifest.counts()
        head["missing_by_phone"] = manifest.missing_by_phone()
        head_text = json.dumps(json_safe(head), indent=1, allow_nan=False)
        lines = []
        for n, image in enumerate(manifest.images):
            values = tuple(vars(image).values())
            cached = self._lines.get(n)
            if cached is None or cached[0] != values:
                cached = (values, json.dumps(json_safe(vars(image)), allow_nan=False))
                self._lines[n] = cached
            lines.append(cached[1])
        body = ",\n  ".join(lines)
        return f'{head_text[:-2]},\n "images": [\n  {body}\n ]\n}}\n'.encode()


@dataclass
class ImageRecord:
    """One planned image (pose) and what became of it. Times: sensor ns, host loop s."""

    camera_id: str
    camera_index: int
    angle_index: int
    planned_angle_deg: float
    focus_mm: float
    focus_diopters: float
    status: ImageStatus = ImageStatus.PLANNED
    actual_angle_deg: float | None = None
    sensor_timestamp_ns: int | None = None
    host_time_s: float | None = None
    phone_path: str | None = None
    file: str | None = None
    size_bytes: int | None = None
    sha256: str | None = None
    attempts: int = 0
    error: str | None = None
    missing_reason: MissingReason | None = None
    """Set once the image is known not to reach the folder (None while it may, and once verified)."""

    def why_missing(self) -> MissingReason | None:
        """Why this image is not in a closed scan's folder: its recorded reason, or its status's
        (None for a verified image)."""
        if self.status is ImageStatus.VERIFIED:
            return None
        return self.missing_reason or _REASON_OF_STATUS[self.status]


@dataclass
class Manifest:
    """manifest.json as a dataclass (see the module docstring)."""

    scan_id: str
    created_utc: str
    rig_digest: str
    calibration_digest: str
    cameras: list[str]
    format_version: int = FORMAT_VERSION
    state: ScanEnd = ScanEnd.INCOMPLETE
    in_progress: bool = True
    reason: str | None = None
    causes: list[Cause] = field(default_factory=list)
    ended_utc: str | None = None
    plan_summary: dict[str, Any] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    patient: Patient | None = None
    """Who the scan is of (None: no patient was given)."""
    study: Study | None = None
    """The DICOM study and series the scan is (given with a patient)."""
    images: list[ImageRecord] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        out = {s.value: 0 for s in ImageStatus}
        for image in self.images:
            out[image.status.value] += 1
        return out

    def missing_by_phone(self, *, ended: bool | None = None) -> dict[str, dict[str, int]]:
        """Images not in the folder, per camera id and :class:`MissingReason` value (cameras and
        reasons without any left out). While the scan runs (``ended`` False; by default: not
        ``in_progress``) only images already known lost count; once it ended, every planned
        image that is not verified."""
        ended = not self.in_progress if ended is None else ended
        out: dict[str, dict[str, int]] = {}
        for image in self.images:
            reason = image.why_missing() if ended else image.missing_reason
            if reason is not None and image.status is not ImageStatus.VERIFIED:
                per_phone = out.setdefault(image.camera_id, {})
                per_phone[reason.value] = per_phone.get(reason.value, 0) + 1
        order = {camera: n for n, camera in enumerate(self.cameras)}
        return {camera: out[camera] for camera in sorted(out, key=lambda c: (order.get(c, len(order)), c))}

    def missing_summary(self, *, ended: bool | None = None) -> str | None:
        """The images not in the folder in words (None when there are none): "39 of 336 images
        missing: cam2 39 (36 phone dropped, 3 capture missed)"."""
        return missing_text(self.missing_by_phone(ended=ended), len(self.images))

    @classmethod
    def from_dict(cls, data: Any, path: Path) -> Manifest:
        """The manifest in ``data`` (parsed JSON); ManifestError naming the first field that is
        missing, of the wrong type, or a file name outside the scan folder (a tampered or
        corrupted manifest is refused here, not deep inside a report)."""
        if not isinstance(data, dict):
            raise ManifestError(path, f"not a manifest: a JSON {type(data).__name__}, not an object")
        if data.get("format_version") != FORMAT_VERSION:
            raise ManifestError(path, f"format_version {json.dumps(data.get('format_version'))[:40]}; "
                                      f"this daemon reads {FORMAT_VERSION}")
        _check_fields(data, _MANIFEST_FIELDS, "", path)
        if not isinstance(data["images"], list):
            raise ManifestError(path, "images: not a list")
        for n, image in enumerate(data["images"]):
            if not isinstance(image, dict):
                raise ManifestError(path, f"images[{n}]: not an object")
            _check_fields(image, _IMAGE_FIELDS, f"images[{n}].", path)
        for key, name in data.get("files", {}).items():
            _check_inside(name, f"files.{key}", path)
        try:
            images = [
                ImageRecord(**{**i, "status": ImageStatus(i["status"]), "missing_reason":
                               MissingReason(i["missing_reason"]) if i.get("missing_reason") else None})
                for i in data["images"]
            ]
            names = {f.name for f in dataclasses.fields(cls)} - {"images", "state", "causes", "patient", "study"}
            return cls(
                **{k: data[k] for k in names if k in data},
                state=ScanEnd(data["state"]),
                causes=[Cause.from_dict(c) for c in data.get("causes", [])],
                patient=None if data.get("patient") is None else Patient.from_dict(data["patient"]),
                study=None if data.get("study") is None else Study.from_dict(data["study"]),
                images=images,
            )
        except PatientError as exc:  # names the field, never the value
            raise ManifestError(path, f"not a valid manifest: {exc}") from exc
        except (KeyError, TypeError, ValueError) as exc:
            raise ManifestError(path, f"not a valid manifest: {exc}") from exc


def missing_text(by_phone: dict[str, dict[str, int]], planned: int) -> str | None:
    """:meth:`Manifest.missing_by_phone` in words, out of ``planned`` images."""
    if not by_phone:
        return None
    total = sum(sum(reasons.values()) for reasons in by_phone.values())
    phones = []
    for camera, reasons in by_phone.items():
        detail = ", ".join(f"{n} {MissingReason(r).words}" for r, n in
                           sorted(reasons.items(), key=lambda item: (-item[1], item[0])))
        phones.append(f"{camera} {sum(reasons.values())} ({detail})")
    return f"{total} of {planned} images missing: {'; '.join(phones)}"


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


_IS_STR = (lambda v: isinstance(v, str))
_FieldRule = tuple[Any, bool, bool]  # (check, None allowed, may be absent)
_MANIFEST_FIELDS: dict[str, _FieldRule] = {
    "scan_id": (_IS_STR, False, False),
    "created_utc": (_IS_STR, False, False),
    "rig_digest": (_IS_STR, False, False),
    "calibration_digest": (_IS_STR, False, False),
    "cameras": (lambda v: isinstance(v, list) and all(isinstance(c, str) for c in v), False, False),
    "state": (_IS_STR, False, False),
    "in_progress": (lambda v: isinstance(v, bool), False, True),
    "reason": (_IS_STR, True, True),
    "ended_utc": (_IS_STR, True, True),
    "plan_summary": (lambda v: isinstance(v, dict), False, True),
    "files": (lambda v: isinstance(v, dict) and all(isinstance(n, str) for n in v.values()), False, True),
    "causes": (lambda v: isinstance(v, list) and all(isinstance(c, dict) for c in v), False, True),
    "patient": (lambda v: isinstance(v, dict), True, True),
    "study": (lambda v: isinstance(v, dict), True, True),
    "images": (lambda v: isinstance(v, list), False, False),
}
_IMAGE_FIELDS: dict[str, _FieldRule] = {
    "camera_id": (_IS_STR, False, False),
    "camera_index": (_count, False, False),
    "angle_index": (_count, False, False),
    "planned_angle_deg": (_number, True, False),
    "focus_mm": (_number, True, False),
    "focus_diopters": (_number, True, False),
    "status": (_IS_STR, False, False),
    "actual_angle_deg": (_number, True, True),
    "sensor_timestamp_ns": (lambda v: isinstance(v, int) and not isinstance(v, bool), True, True),
    "host_time_s": (_number, True, True),
    "phone_path": (_IS_STR, True, True),
    "file": (_IS_STR, True, True),
    "size_bytes": (_count, True, True),
    "sha256": (_IS_STR, True, True),
    "attempts": (_count, False, True),
    "error": (_IS_STR, True, True),
    "missing_reason": (_IS_STR, True, True),
}


def _check_fields(data: dict[str, Any], table: dict[str, _FieldRule], prefix: str, path: Path) -> None:
    for name, (check, none_allowed, may_be_absent) in table.items():
        if name not in data:
            if may_be_absent:
                continue
            raise ManifestError(path, f"{prefix}{name}: missing")
        value = data[name]
        if (value is None and none_allowed) or check(value):
            continue
        raise ManifestError(path, f"{prefix}{name}: {json.dumps(value)[:60]} is not a valid value")
    if data.get("file") is not None and prefix:
        _check_inside(data["file"], f"{prefix}file", path)


def _check_inside(name: Any, key: str, path: Path) -> None:
    """A file name from a manifest must stay inside its scan folder."""
    parts = Path(name).parts if isinstance(name, str) and name else ("..",)
    if Path(name).is_absolute() or ".." in parts:
        raise ManifestError(path, f"{key}: {str(name)[:60]!r} is not a file inside the scan folder")
