"""The scan store: one folder per scan, written so that a crash never leaves it inconsistent.

Layout of ``<root>/<YYYYmmdd-HHMMSS>-<scan id>/``::

    manifest.json     what the scan is and the state of every image (rewritten after each image)
    plan.json         the focus plan
    mesh.ply          the subject's surface from the depth sweep
    trace.npz         the encoder trace (time_s, angle_deg[, speed_deg_s])
    depth_sweep.json  depth sweep metadata
    events.jsonl      the scan's event log (one JSON object a line, fsync'd per line)
    images/           <camera id>-a<angle index><suffix>, pulled from the phones

Every file is written atomically (daemon/atomic.py: temp file in the same folder, fsync,
rename, fsync of the folder), so a reader sees the previous or the new version, never a
torn one. The manifest
says ``incomplete`` and ``in_progress: true`` from the moment the folder exists until the scan
ends; :meth:`ScanStore.recover` closes folders a killed daemon left in progress. The subject
is identified only by an opaque scan id: no patient data is written here.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import io
import json
import math
import os
import re
import secrets
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from daemon.atomic import AtomicWriter, StoreError, StoreFull, fsync_dir, raise_for, sha256_of
from daemon.utc import utc_now, utc_stamp
from planner.rig import Rig

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
RESERVE = ".reserve"
_SCAN_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")
_FOLDER = re.compile(r"^\d{8}-\d{6}-(?P<scan_id>[A-Za-z0-9][A-Za-z0-9_-]{0,63})$")

log = structlog.get_logger(__name__)


class ManifestError(StoreError):
    """A manifest is unreadable or not a manifest of this format."""


class ScanEnd(str, enum.Enum):
    """The manifest's state. INCOMPLETE from the start until the scan ends."""

    COMPLETE = "complete"
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


def new_scan_id() -> str:
    """An opaque scan id (12 hex digits): the only identity of a subject in the store."""
    return secrets.token_hex(6)


def _clean(value: Any) -> Any:
    """JSON-safe: non-finite floats become null, numpy scalars become Python numbers."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _json_bytes(value: Any) -> bytes:
    return (json.dumps(_clean(value), indent=1, allow_nan=False) + "\n").encode()


class _ManifestRenderer:
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
        head_text = json.dumps(_clean(head), indent=1, allow_nan=False)
        lines = []
        for n, image in enumerate(manifest.images):
            values = tuple(vars(image).values())
            cached = self._lines.get(n)
            if cached is None or cached[0] != values:
                cached = (values, json.dumps(_clean(vars(image)), allow_nan=False))
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
    ended_utc: str | None = None
    plan_summary: dict[str, Any] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    images: list[ImageRecord] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        out = {s.value: 0 for s in ImageStatus}
        for image in self.images:
            out[image.status.value] += 1
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any], path: Path) -> Manifest:
        if data.get("format_version") != FORMAT_VERSION:
            raise ManifestError(path, f"format_version {data.get('format_version')!r}; "
                                      f"this daemon reads {FORMAT_VERSION}")
        try:
            images = [
                ImageRecord(**{**i, "status": ImageStatus(i["status"])}) for i in data["images"]
            ]
            names = {f.name for f in dataclasses.fields(cls)} - {"images", "state"}
            return cls(
                **{k: data[k] for k in names if k in data},
                state=ScanEnd(data["state"]),
                images=images,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ManifestError(path, f"not a valid manifest: {exc}") from exc


def calibration_digest(rig: Rig) -> str:
    """sha256 over the focus calibration files the rig names (a missing file counts by name)."""
    h = hashlib.sha256()
    for name in sorted({p.focus_calibration for p in rig.phones}):
        path = rig.resolve(name)
        h.update(name.encode() + b"\0")
        h.update(path.read_bytes() if path.is_file() else b"<missing>")
    return h.hexdigest()


class ScanFolder:
    """One scan's folder. All writes go through the store's AtomicWriter."""

    def __init__(self, path: Path, manifest: Manifest, writer: AtomicWriter) -> None:
        self.path = path
        self.manifest = manifest
        self.writer = writer
        self._index = {(i.camera_index, i.angle_index): i for i in manifest.images}
        self._renderer = _ManifestRenderer()

    @property
    def scan_id(self) -> str:
        return self.manifest.scan_id

    @property
    def images_dir(self) -> Path:
        return self.path / "images"

    # ------------------------------------------------------------------ whole files

    @property
    def reserve_path(self) -> Path:
        return self.path / RESERVE

    def save(self) -> None:
        """Rewrite manifest.json atomically.

        On a full disk the folder's reserve file is released once so the manifest can still
        record what was captured; without a reserve StoreFull leaves the previous manifest.
        """
        data = self._renderer.render(self.manifest)
        try:
            self.writer.write(self.path / MANIFEST, data)
        except StoreFull as exc:
            if not self.reserve_path.exists():
                raise
            self.reserve_path.unlink()
            log.warning("store_reserve_released", scan_id=self.scan_id, path=exc.path,
                        bytes_needed=exc.bytes_needed)
            self.writer.write(self.path / MANIFEST, data)

    def _write_file(self, key: str, name: str, data: bytes) -> Path:
        """Write a whole file of the scan, list it in the manifest as key, save the manifest."""
        path = self.path / name
        self.writer.write(path, data)
        self.manifest.files[key] = name
        self.save()
        return path

    def write_plan(self, plan: dict[str, Any], summary: dict[str, Any]) -> Path:
        """plan.json (the whole plan, JSON-able) and its summary into the manifest."""
        self.manifest.plan_summary = _clean(summary)
        return self._write_file("plan", "plan.json", _json_bytes(plan))

    def write_mesh(self, mesh: Any) -> Path:
        """mesh.ply from PLY bytes or any object with ``export(file_type="ply") -> bytes``."""
        data = mesh if isinstance(mesh, bytes) else mesh.export(file_type="ply")
        return self._write_file("mesh", "mesh.ply", data)

    def write_trace(self, time_s: np.ndarray, angle_deg: np.ndarray,
                    speed_deg_s: np.ndarray | None = None) -> Path:
        """trace.npz: (N,) encoder samples, host loop time s and beam angle deg."""
        arrays = {"time_s": np.asarray(time_s, float), "angle_deg": np.asarray(angle_deg, float)}
        if speed_deg_s is not None:
            arrays["speed_deg_s"] = np.asarray(speed_deg_s, float)
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        return self._write_file("trace", "trace.npz", buffer.getvalue())

    def write_depth_sweep(self, metadata: dict[str, Any]) -> Path:
        return self._write_file("depth_sweep", "depth_sweep.json", _json_bytes(metadata))

    def write_json(self, key: str, name: str, value: Any, *, save: bool = True) -> Path:
        """Any other JSON file of the scan (captures, QA report), listed in the manifest as key."""
        path = self.path / name
        self.writer.write(path, _json_bytes(value))
        self.manifest.files[key] = name
        if save:
            self.save()
        return path

    def log_event(self, event: str, **fields: Any) -> None:
        """Append one line to events.jsonl (fsync'd): what happened, with wall-clock UTC."""
        record = {"utc": utc_stamp(), "event": event, **_clean(fields)}
        line = (json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n").encode()
        self.writer.append_line(self.path / "events.jsonl", line)
        self.manifest.files.setdefault("events", "events.jsonl")

    # ------------------------------------------------------------------ images

    def plan_images(self, angles_deg: Sequence[float], focus_mm: np.ndarray) -> None:
        """Every pose as a planned image. focus_mm: (A*C,) angle-major or (A, C), mm."""
        cams = self.manifest.cameras
        focus = np.asarray(focus_mm, dtype=float).reshape(len(angles_deg), len(cams))
        self.manifest.images = [
            ImageRecord(
                camera_id=cams[c], camera_index=c, angle_index=k,
                planned_angle_deg=float(angles_deg[k]), focus_mm=float(focus[k, c]),
                focus_diopters=1000.0 / float(focus[k, c]) if focus[k, c] > 0 else math.inf,
            )
            for k in range(len(angles_deg)) for c in range(len(cams))
        ]
        self._index = {(i.camera_index, i.angle_index): i for i in self.manifest.images}
        self.save()

    def image(self, camera_index: int, angle_index: int) -> ImageRecord:
        try:
            return self._index[(camera_index, angle_index)]
        except KeyError:
            raise StoreError(self.path, f"no planned image for camera {camera_index} at angle "
                                        f"index {angle_index}") from None

    def image_dest(self, camera_index: int, angle_index: int, phone_path: str) -> Path:
        """Where an image from the phone goes: images/<camera id>-a<NN><suffix of phone_path>."""
        image = self.image(camera_index, angle_index)
        suffix = Path(phone_path).suffix or ".jpg"
        return self.images_dir / f"{image.camera_id}-a{angle_index:02d}{suffix}"

    def update_image(self, camera_index: int, angle_index: int, *, save: bool = True,
                     **changes: Any) -> ImageRecord:
        """Change an image's fields and (by default) rewrite the manifest."""
        image = self.image(camera_index, angle_index)
        for name, value in changes.items():
            if not hasattr(image, name):
                raise StoreError(self.path, f"image record has no field {name!r}")
            setattr(image, name, ImageStatus(value) if name == "status" else value)
        if save:
            self.save()
        return image

    def record_capture(self, camera_index: int, angle_index: int, *, sensor_timestamp_ns: int,
                       host_time_s: float, actual_angle_deg: float | None, phone_path: str,
                       size_bytes: int, focus_diopters: float | None = None) -> ImageRecord:
        """The phone took the image (still on the phone)."""
        changes: dict[str, Any] = dict(
            status=ImageStatus.CAPTURED, sensor_timestamp_ns=int(sensor_timestamp_ns),
            host_time_s=float(host_time_s), actual_angle_deg=actual_angle_deg,
            phone_path=phone_path, size_bytes=int(size_bytes), error=None,
        )
        if focus_diopters is not None:
            changes["focus_diopters"] = float(focus_diopters)
        return self.update_image(camera_index, angle_index, **changes)

    def record_failure(self, camera_index: int, angle_index: int, error: str, *,
                       status: ImageStatus = ImageStatus.FAILED) -> ImageRecord:
        return self.update_image(camera_index, angle_index, status=status, error=error)

    def check(self) -> list[str]:
        """Re-read the folder against its manifest; returns the problems found (none: consistent).

        Listed files must exist; every verified image's file must have its recorded size
        and SHA-256; a folder still marked in progress is reported too.
        """
        problems = []
        if self.manifest.in_progress:
            problems.append("still marked in progress (running, or left by a killed daemon)")
        for key, name in self.manifest.files.items():
            if not (self.path / name).is_file():
                problems.append(f"{key} file {name} is listed but missing")
        for image in self.manifest.images:
            if image.status is not ImageStatus.VERIFIED:
                continue
            who = f"{image.camera_id} angle {image.angle_index}"
            path = self.path / (image.file or "")
            if not image.file or not path.is_file():
                problems.append(f"{who}: verified image file {image.file} is missing")
            elif path.stat().st_size != image.size_bytes:
                problems.append(f"{who}: {image.file} has {path.stat().st_size} bytes, "
                                f"manifest says {image.size_bytes}")
            elif sha256_of(path) != image.sha256:
                problems.append(f"{who}: {image.file} does not match its SHA-256")
        return problems

    # ------------------------------------------------------------------ end

    def finish(self, state: ScanEnd, reason: str | None = None) -> None:
        """End the scan: planned images become missing; the manifest leaves 'in progress'."""
        for image in self.manifest.images:
            if image.status is ImageStatus.PLANNED:
                image.status = ImageStatus.MISSING
                image.error = image.error or f"not captured: scan ended {state.value}"
        self.manifest.state = state
        self.manifest.reason = reason
        self.manifest.in_progress = False
        self.manifest.ended_utc = utc_stamp()
        self.save()
        self.reserve_path.unlink(missing_ok=True)
        log.info("scan_stored", scan_id=self.scan_id, state=state.value, path=str(self.path),
                 **self.manifest.counts())


class ScanStore:
    """The folder that holds every scan (``root``), one sub-folder per scan."""

    RESERVE_BYTES = 4 << 20

    def __init__(self, root: Path | str, *, writer: AtomicWriter | None = None,
                 reserve_bytes: int | None = None) -> None:
        self.root = Path(root)
        self.writer = writer or AtomicWriter()
        self.reserve_bytes = self.RESERVE_BYTES if reserve_bytes is None else reserve_bytes

    def create(self, rig: Rig, *, scan_id: str | None = None,
               now: datetime | None = None) -> ScanFolder:
        """A new scan folder with an initial manifest (incomplete, in progress)."""
        scan_id = scan_id or new_scan_id()
        if not _SCAN_ID.match(scan_id):
            raise StoreError(self.root, f"scan id {scan_id!r} must be 1-64 of [A-Za-z0-9_-]")
        now = now or utc_now()
        path = self.root / f"{now:%Y%m%d-%H%M%S}-{scan_id}"
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            path.mkdir()
            (path / "images").mkdir()
            fsync_dir(self.root)
        except FileExistsError:
            raise StoreError(path, "scan folder already exists") from None
        except OSError as exc:
            raise_for(path, exc, 0)
        manifest = Manifest(
            scan_id=scan_id, created_utc=now.isoformat(), rig_digest=rig.digest,
            calibration_digest=calibration_digest(rig), cameras=[p.id for p in rig.phones],
        )
        folder = ScanFolder(path, manifest, self.writer)
        folder.save()
        self._reserve(folder.reserve_path)
        return folder

    def _reserve(self, path: Path) -> None:
        """Set disk space aside so the manifest can still be rewritten when the disk fills."""
        if self.reserve_bytes <= 0:
            return
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o600)
            try:
                os.posix_fallocate(fd, 0, self.reserve_bytes)
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as exc:
            path.unlink(missing_ok=True)
            raise_for(path, exc, self.reserve_bytes)

    def folders(self) -> list[Path]:
        """Scan folders under the root, oldest first."""
        if not self.root.is_dir():
            return []
        return sorted(p for p in self.root.iterdir() if p.is_dir() and _FOLDER.match(p.name))

    def open(self, path: Path | str) -> ScanFolder:
        path = Path(path)
        try:
            data = json.loads((path / MANIFEST).read_bytes())
        except (OSError, ValueError) as exc:
            raise ManifestError(path / MANIFEST, f"unreadable: {exc}") from exc
        return ScanFolder(path, Manifest.from_dict(data, path / MANIFEST), self.writer)

    def recover(self, reason: str = "the daemon stopped while the scan was in progress"
                ) -> list[ScanFolder]:
        """Close every folder left in progress: mark it incomplete with ``reason``.

        Leftover temp files are removed; planned images become missing; images still on a
        phone stay 'captured' with an error saying they were not pulled; a pulled image
        whose file checks out by size and checksum becomes verified. Returns the folders
        that were recovered.
        """
        recovered = []
        for path in self.folders():
            leftovers = [*path.glob(".*.tmp"), *path.glob("images/.*"), *path.glob("images/*.tmp"),
                         *path.glob("images/*.part")]
            for tmp in leftovers:
                tmp.unlink(missing_ok=True)
            (path / RESERVE).unlink(missing_ok=True)
            try:
                folder = self.open(path)
            except ManifestError as exc:
                if (path / MANIFEST).exists():
                    log.error("scan_folder_unreadable", path=str(path), error=str(exc))
                    continue
                folder = ScanFolder(
                    path,
                    Manifest(scan_id=path.name.split("-", 2)[2], created_utc="", rig_digest="",
                             calibration_digest="", cameras=[]),
                    self.writer,
                )
                reason_here = f"{reason}; no manifest had been written"
            else:
                if not folder.manifest.in_progress:
                    continue
                reason_here = reason
            _settle_images(folder, folder.manifest.images)
            folder.manifest.state = ScanEnd.INCOMPLETE
            folder.manifest.reason = reason_here
            folder.manifest.in_progress = False
            folder.manifest.ended_utc = utc_stamp()
            folder.save()
            log.warning("scan_recovered", scan_id=folder.scan_id, path=str(path),
                        reason=reason_here, **folder.manifest.counts())
            recovered.append(folder)
        return recovered


def _settle_images(folder: ScanFolder, images: Iterable[ImageRecord]) -> None:
    for image in images:
        if image.status is ImageStatus.PLANNED:
            image.status = ImageStatus.MISSING
            image.error = "not captured: scan interrupted"
        elif image.status is ImageStatus.CAPTURED:
            image.error = "not pulled from the phone: scan interrupted"
        elif image.status is ImageStatus.PULLED:
            path = folder.path / (image.file or "")
            ok = (image.file and path.is_file() and path.stat().st_size == image.size_bytes
                  and sha256_of(path) == image.sha256)
            if ok:
                image.status = ImageStatus.VERIFIED
            else:
                image.status = ImageStatus.FAILED
                image.error = "pulled file does not match its size and checksum after interruption"
