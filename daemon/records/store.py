"""The scan store: one folder per scan, written so that a crash never leaves it inconsistent.

Layout of ``<root>/<YYYYmmdd-HHMMSS>-<scan id>/``::

    manifest.json     what the scan is and the state of every image (rewritten after each image)
    plan.json         the focus plan
    mesh.ply          the subject's surface from the depth sweep
    trace.npz         the encoder trace (time_s, angle_deg[, speed_deg_s])
    depth_sweep.json  depth sweep metadata
    events.jsonl      the scan's event log (one JSON object a line, fsync'd per line)
    images/           <camera id>-a<angle index><suffix>, pulled from the phones

This module is the only reader and writer of a scan folder: the daemon writes it through
:class:`ScanFolder`; reports, navigation and the CLI read it with :func:`read_folder`.

Every file is written atomically (daemon/records/atomic.py: temp file in the same folder, fsync,
rename, fsync of the folder), so a reader sees the previous or the new version, never a
torn one. The manifest
says ``incomplete`` and ``in_progress: true`` from the moment the folder exists until the scan
ends; :meth:`ScanStore.recover` closes folders a killed daemon left in progress. A scan for a
patient keeps the patient and the study in its manifest, and only there; folders are readable by
the store's group (the operators) and nobody else (:attr:`ScanStore.FOLDER_MODE`).
"""

from __future__ import annotations

import asyncio
import functools
import hashlib
import io
import json
import math
import os
import re
import secrets
import shutil
import stat
import zipfile
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from daemon.clinic.patient import ScanSubject
from daemon.faults import Cause
from daemon.records.atomic import AtomicWriter, StoreError, StoreFull, fsync_dir, raise_for, sha256_of
from daemon.records.folder_writer import FolderWriter
from daemon.records.manifest import (
    MANIFEST,
    ImageRecord,
    ImageStatus,
    Manifest,
    ManifestError,
    ManifestRenderer,
    MissingReason,
    ScanEnd,
    json_bytes,
    json_safe,
)
from daemon.utc import utc_now, utc_stamp
from planner.files import read_at_most
from planner.rig import Rig

RESERVE = ".reserve"
#: The textured body (glTF binary) in a scan folder.
BODY = "body.glb"
MAX_MANIFEST_BYTES = 64 * 1024 * 1024  # a 336-image manifest is ~150 KB
SCAN_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")
"""A scan (or calibration rotation) id: opaque, never patient data."""
_FOLDER = re.compile(r"^\d{8}-\d{6}-(?P<scan_id>[A-Za-z0-9][A-Za-z0-9_-]{0,63})$")

log = structlog.get_logger(__name__)


class ScanFileError(StoreError):
    """A file of a scan folder that a reader needs is missing or unreadable."""


def new_scan_id() -> str:
    """An opaque scan id (12 hex digits): never patient data (the patient is in the manifest)."""
    return secrets.token_hex(6)


def calibration_digest(rig: Rig) -> str:
    """sha256 over the calibration files the rig names: the phones' focus tables and the system
    calibration (camera poses and lenses); a missing file counts by name."""
    h = hashlib.sha256()
    for name in sorted({p.focus_calibration for p in rig.phones} | {rig.calibration.file}):
        path = rig.resolve(name)
        h.update(name.encode() + b"\0")
        h.update(path.read_bytes() if path.is_file() else b"<missing>")
    return h.hexdigest()


def mesh_bytes(mesh: Any) -> bytes:
    """PLY bytes of a mesh (PLY bytes pass through)."""
    return mesh if isinstance(mesh, bytes) else mesh.export(file_type="ply")


def trace_bytes(time_s: np.ndarray, angle_deg: np.ndarray, speed_deg_s: np.ndarray | None = None) -> bytes:
    """trace.npz bytes: host loop time (s), beam angle (deg) and, if given, speed (deg/s)."""
    arrays = {"time_s": np.asarray(time_s, float), "angle_deg": np.asarray(angle_deg, float)}
    if speed_deg_s is not None:
        arrays["speed_deg_s"] = np.asarray(speed_deg_s, float)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub reads **arrays as maybe allow_pickle
    return buffer.getvalue()


@functools.cache
def _writer_thread() -> ThreadPoolExecutor:
    """The store's one writer thread: large files are written in the order they are asked for."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="store-writer")


class ScanFolder:
    """One scan's folder. All writes go through the store's AtomicWriter."""

    def __init__(self, path: Path, manifest: Manifest, writer: AtomicWriter) -> None:
        self.path = path
        self.manifest = manifest
        self.writer = writer
        self._index = {(i.camera_index, i.angle_index): i for i in manifest.images}
        self._renderer = ManifestRenderer()
        self._ordered: FolderWriter | None = None
        self._events_listing = False

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
        """Rewrite manifest.json atomically (in the background, see :meth:`save_in_background`).

        On a full disk the folder's reserve file is released once so the manifest can still
        record what was captured; without a reserve StoreFull leaves the previous manifest.
        """
        if self._ordered is not None:
            self._ordered.raise_failure()
            self._queue_manifest()
        else:
            self._write_manifest(self._renderer.render(self.manifest))

    def _queue_manifest(self, *, done: bool = False) -> asyncio.Future[None] | None:
        """The manifest as it is now (rendered here: a consistent snapshot), queued for writing."""
        assert self._ordered is not None
        data = self._renderer.render(self.manifest)
        return self._ordered.manifest(lambda: self._write_manifest(data), done=done)

    def _write_manifest(self, data: bytes) -> None:
        try:
            self.writer.write(self.path / MANIFEST, data)
        except StoreFull as exc:
            if not self.reserve_path.exists():
                raise
            self.reserve_path.unlink()
            log.warning("store_reserve_released", scan_id=self.scan_id, path=exc.path,
                        bytes_needed=exc.bytes_needed)
            self.writer.write(self.path / MANIFEST, data)

    def save_in_background(self, enabled: bool = True) -> None:
        """From now on every write of the folder (events.jsonl lines, whole files, the manifest)
        leaves the event loop: they are queued in order for the store's writer thread
        (daemon/records/folder_writer.py), saves asked for while one waits are coalesced (a capture
        rotation saves twice per image, 14 times at each angle, each write an fdatasync and a
        folder fsync), and a file is listed in the manifest once it is durable. A failed write
        is raised by the next one. Needs the running event loop. Turning it off (and
        :meth:`finish`) waits for what is queued and raises its error; :meth:`close` ends the
        scan without waiting on the loop."""
        if enabled and self._ordered is None:
            self._ordered = FolderWriter(self.writer, _writer_thread())
        elif not enabled and self._ordered is not None:
            ordered, self._ordered = self._ordered, None
            ordered.wait()

    def _write_file(self, key: str, name: str, data: bytes) -> Path:
        """Write a whole file of the scan, list it in the manifest as key, save the manifest
        (in the background: listed once the file is durable)."""
        path = self.path / name
        if self._ordered is None:
            self.writer.write(path, data)
            self.manifest.files[key] = name
            self.save()
            return path
        ordered = self._ordered
        ordered.raise_failure()

        def listed(written: asyncio.Future[None]) -> None:
            failure = written.exception()
            if failure is not None:
                ordered.keep_failure(failure)
            elif self._ordered is ordered:
                self.manifest.files[key] = name
                self._queue_manifest()

        ordered.file(lambda: self.writer.write(path, data)).add_done_callback(listed)
        return path

    def write_body(self, data: bytes) -> Path:
        """body.glb: the mesh textured from the scan's images (analysis/body_texture.py), listed
        in the manifest as ``body``; written atomically, so a reader sees the old file or the new."""
        return self._write_file("body", BODY, data)

    def write_calibration(self, data: bytes) -> Path:
        """calibration.yaml: the system calibration the scan planned and reconstructed with."""
        return self._write_file("calibration", "calibration.yaml", data)

    async def write_plan(self, plan: dict[str, Any], summary: dict[str, Any]) -> Path:
        """plan.json (the whole plan, JSON-able) and its summary into the manifest."""
        self.manifest.plan_summary = json_safe(summary)
        return await self._write_off_loop("plan", "plan.json", lambda: json_bytes(plan))

    async def write_mesh(self, mesh: Any) -> Path:
        """mesh.ply from PLY bytes or any object with ``export(file_type="ply") -> bytes``."""
        return await self._write_off_loop("mesh", "mesh.ply", lambda: mesh_bytes(mesh))

    async def write_trace(self, time_s: np.ndarray, angle_deg: np.ndarray,
                          speed_deg_s: np.ndarray | None = None, *, save: bool = True) -> Path:
        """trace.npz: (N,) encoder samples, host loop time s and beam angle deg."""
        return await self._write_off_loop("trace", "trace.npz",
                                          lambda: trace_bytes(time_s, angle_deg, speed_deg_s), save=save)

    async def write_json(self, key: str, name: str, value: Any, *, save: bool = True) -> Path:
        """Any other JSON file of the scan (captures, QA report), listed in the manifest as key."""
        return await self._write_off_loop(key, name, lambda: json_bytes(value), save=save)

    async def _write_off_loop(self, key: str, name: str, make: Callable[[], bytes], *, save: bool = True) -> Path:
        """The large files of a scan: their bytes are made (``make()``: export, compress,
        serialise) and written with their fsyncs in the store's writer thread, one file at a time
        in the order asked, so the event loop and the heartbeats it carries never wait for the
        disk. Only listing the file in the manifest (and saving it) runs on the loop. ``make``
        must read values nobody changes meanwhile (a finished mesh, a copied trace)."""
        path = self.path / name
        if self._ordered is not None:
            await self._ordered.file(lambda: self.writer.write(path, make()))
        else:
            await asyncio.get_running_loop().run_in_executor(_writer_thread(), lambda: self.writer.write(path, make()))
        self.manifest.files[key] = name
        if save:
            self.save()
        return path

    async def write_depth_sweep(self, metadata: dict[str, Any]) -> Path:
        """depth_sweep.json: what the sweep delivered and fused (written off the loop: its fsync
        would land right where the fusion's last step and the reposition start)."""
        return await self._write_off_loop("depth_sweep", "depth_sweep.json", lambda: json_bytes(metadata))

    def write_derived(self, relative: str, data: bytes) -> Path:
        """A file derived from the scan's data (the QA report under ``report/``): written
        atomically, not listed in the manifest (it can always be regenerated)."""
        path = self.path / relative
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise_for(path.parent, exc, 0)
        self.writer.write(path, data)
        return path

    def log_event(self, event: str, **fields: Any) -> None:
        """Append one line to events.jsonl (fdatasync'd; in the background, queued): what
        happened, with wall-clock UTC."""
        record = {"utc": utc_stamp(), "event": event, **json_safe(fields)}
        line = (json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n").encode()
        path = self.path / "events.jsonl"
        if self._ordered is None:
            self.writer.append_line(path, line)
            self.manifest.files.setdefault("events", "events.jsonl")
            return
        ordered = self._ordered
        ordered.raise_failure()
        first = "events" not in self.manifest.files and not self._events_listing
        written = ordered.append(path, line, done=first)
        if written is not None:
            self._events_listing = True

            def listed(future: asyncio.Future[None]) -> None:
                self._events_listing = False
                failure = future.exception()
                if failure is not None:
                    ordered.keep_failure(failure)
                elif self._ordered is ordered:
                    self.manifest.files.setdefault("events", "events.jsonl")
                    self._queue_manifest()

            written.add_done_callback(listed)

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
        found = self.find_image(camera_index, angle_index)
        if found is None:
            raise StoreError(self.path, f"no planned image for camera {camera_index} at angle "
                                        f"index {angle_index}")
        return found

    def find_image(self, camera_index: int, angle_index: int) -> ImageRecord | None:
        """The planned image of a camera at a capture angle, None if the scan has none."""
        return self._index.get((camera_index, angle_index))

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
            if value is not None and name in _TYPED:
                value = _TYPED[name](value)
            setattr(image, name, value)
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
                       status: ImageStatus = ImageStatus.FAILED,
                       reason: MissingReason = MissingReason.PULL_FAILED) -> ImageRecord:
        return self.update_image(camera_index, angle_index, status=status, error=error, missing_reason=reason)

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

    # ------------------------------------------------------------------ reading

    def listed(self, key: str) -> Path | None:
        """The path of the file the manifest lists as ``key`` (None if not listed).

        Raises ScanFileError if it is listed but not on disk.
        """
        name = self.manifest.files.get(key)
        if name is None:
            return None
        path = self.path / name
        if not path.is_file():
            raise ScanFileError(path, f"listed in the manifest as {key!r} but missing")
        return path

    def read_plan(self) -> dict[str, Any] | None:
        """plan.json as written by :meth:`write_plan` (None if the scan ended before planning)."""
        path = self.listed("plan")
        if path is None:
            return None
        try:
            result: dict[str, Any] = json.loads(path.read_bytes())
            return result
        except (OSError, ValueError) as exc:
            raise ScanFileError(path, f"unreadable: {exc}") from exc

    def read_trace(self) -> dict[str, np.ndarray] | None:
        """trace.npz: (N,) ``time_s``, ``angle_deg`` and ``speed_deg_s`` (None if not written)."""
        path = self.listed("trace")
        if path is None:
            return None
        try:
            with path.open("rb") as file:
                if file.read(4) != b"PK\x03\x04":  # an .npz is a zip archive of .npy arrays
                    raise ScanFileError(path, "unreadable: not an .npz archive")
            with np.load(path, allow_pickle=False) as data:
                return {name: data[name] for name in data.files}
        except (OSError, ValueError, zipfile.BadZipFile) as exc:  # cut short: a zip without its directory
            raise ScanFileError(path, f"unreadable: {exc}") from exc

    def read_mesh(self) -> Any:
        """mesh.ply as a ``trimesh.Trimesh`` (mm); ScanFileError if the scan has none."""
        import trimesh  # a second to import: only readers of a scan's mesh need it

        path = self.listed("mesh")
        if path is None:
            raise ScanFileError(self.path / "mesh.ply", "missing (the scan ended before the depth sweep)")
        try:
            return trimesh.load(path, force="mesh", process=False)
        except (OSError, ValueError) as exc:
            raise ScanFileError(path, f"unreadable: {exc}") from exc

    # ------------------------------------------------------------------ end

    def finish(self, state: ScanEnd, causes: Sequence[Cause] = ()) -> None:
        """End the scan: planned images become missing; the manifest leaves 'in progress'.

        ``causes``: why it ended early (none for a complete scan); ``reason`` is their text. A
        scan asked to end ``complete`` with planned images not in the folder ends ``partial``,
        its reason the missing images per phone (a complete scan has every image).
        Blocking (what the background queued is waited for, the last manifest written here):
        on the event loop of a real-time scan, :meth:`close` instead.
        """
        self._end(state, causes)
        ordered, self._ordered = self._ordered, None
        if ordered is not None:
            try:
                ordered.wait()
            except Exception as exc:  # the final save below writes the whole manifest again
                log.warning("manifest_background_write_failed", scan_id=self.scan_id, error=str(exc))
        self.save()
        self.reserve_path.unlink(missing_ok=True)
        self._stored()

    async def close(self, state: ScanEnd, causes: Sequence[Cause] = ()) -> None:
        """:meth:`finish` without waiting on the loop: with background writes on, what is queued,
        the final manifest and the release of the space reserve are written in the store's
        writer thread, and this returns once they are durable (or raises the final write's
        error). Without, the same as :meth:`finish` (a virtual-time scan stays deterministic)."""
        ordered = self._ordered
        if ordered is None:
            self.finish(state, causes)
            return
        self._end(state, causes)
        try:
            await ordered.drain()
        except Exception as exc:  # the final save below writes the whole manifest again
            log.warning("manifest_background_write_failed", scan_id=self.scan_id, error=str(exc))
        final = self._queue_manifest(done=True)
        assert final is not None
        try:
            await final
            await ordered.file(lambda: self.reserve_path.unlink(missing_ok=True))
        finally:
            self._ordered = None
        self._stored()

    def _end(self, state: ScanEnd, causes: Sequence[Cause]) -> None:
        for image in self.manifest.images:
            if image.status is ImageStatus.PLANNED:
                image.missing_reason = image.why_missing()
                image.status = ImageStatus.MISSING
                image.error = image.error or f"not captured: scan ended {state.value}"
            image.missing_reason = image.why_missing()
        missing = self.manifest.missing_summary(ended=True)
        if state is ScanEnd.COMPLETE and missing is not None:
            state = ScanEnd.PARTIAL
        self.manifest.state = state
        self.manifest.causes = list(causes)
        self.manifest.reason = "; ".join(map(str, causes)) or (missing if state is ScanEnd.PARTIAL else None)
        self.manifest.in_progress = False
        self.manifest.ended_utc = utc_stamp()

    def _stored(self) -> None:
        log.info("scan_stored", scan_id=self.scan_id, state=self.manifest.state.value, path=str(self.path),
                 **self.manifest.counts())


class ScanStore:
    """The folder that holds every scan (``root``), one sub-folder per scan."""

    RESERVE_BYTES = 4 << 20

    def __init__(self, root: Path | str, *, writer: AtomicWriter | None = None,
                 reserve_bytes: int | None = None) -> None:
        self.root = Path(root)
        self.writer = writer or AtomicWriter()
        self.reserve_bytes = self.RESERVE_BYTES if reserve_bytes is None else reserve_bytes

    FOLDER_MODE = 0o750
    """A scan folder (and its images/): the daemon writes, the store's group (the operators) reads,
    nobody else; the store's set-group-id bit is kept, so its group is the operators'."""

    def create(self, rig: Rig, *, scan_id: str | None = None, now: datetime | None = None,
               subject: ScanSubject | None = None) -> ScanFolder:
        """A new scan folder with an initial manifest (incomplete, in progress) and its space
        reserve: when this returns, the scan can be stored. ``subject``: the patient and the
        order the scan is for (its study UIDs are made here, once).

        Raises StoreError (StoreFull, StoreWriteError) naming the path when the store cannot
        take a scan; a folder begun before the failure is removed again, so nothing is left
        "in progress".
        """
        scan_id = scan_id or new_scan_id()
        if not isinstance(scan_id, str) or not SCAN_ID.match(scan_id):
            shown = repr(scan_id)[:80] if isinstance(scan_id, str) else f"a {type(scan_id).__name__}"
            raise StoreError(self.root, f"scan id {shown} must be 1-64 of [A-Za-z0-9_-]")
        now = now or utc_now()
        path = self.root / f"{now:%Y%m%d-%H%M%S}-{scan_id}"
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise StoreError(self.root, "the scan store is not a folder") from None
        except OSError as exc:
            raise_for(self.root, exc, 0)
        try:
            path.mkdir(mode=self.FOLDER_MODE)
        except FileExistsError:
            raise StoreError(path, "scan folder already exists") from None
        except OSError as exc:
            raise_for(path, exc, 0)
        try:
            try:
                self._private(path)
                (path / "images").mkdir(mode=self.FOLDER_MODE)
                self._private(path / "images")
                fsync_dir(self.root)
            except OSError as exc:
                raise_for(path, exc, 0)
            created = now.isoformat()
            manifest = Manifest(
                scan_id=scan_id, created_utc=created, rig_digest=rig.digest,
                calibration_digest=calibration_digest(rig), cameras=[p.id for p in rig.phones],
                patient=None if subject is None else subject.patient,
                study=None if subject is None else subject.study(scan_id, created),
            )
            folder = ScanFolder(path, manifest, self.writer)
            folder.save()
            self._reserve(folder.reserve_path)
        except BaseException:
            shutil.rmtree(path, ignore_errors=True)  # holds nothing yet: no half-made scan stays behind
            raise
        return folder

    def _private(self, folder: Path) -> None:
        """FOLDER_MODE whatever the umask, keeping the set-group-id bit the store gave it."""
        os.chmod(folder, self.FOLDER_MODE | (folder.stat().st_mode & stat.S_ISGID))

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
        return read_folder(path, writer=self.writer)

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
            if (path / "trace.npz").is_file():  # saved while the scan ran (Scan.TRACE_SAVE_S)
                folder.manifest.files.setdefault("trace", "trace.npz")
            folder.manifest.state = ScanEnd.INCOMPLETE
            folder.manifest.reason = reason_here
            folder.manifest.in_progress = False
            folder.manifest.ended_utc = utc_stamp()
            try:
                folder.log_event("scan_recovered", reason=reason_here, **folder.manifest.counts())
            except StoreError as exc:  # the manifest below still says what happened
                log.error("scan_recovery_event_not_written", path=str(path), error=str(exc))
            folder.save()
            log.warning("scan_recovered", scan_id=folder.scan_id, path=str(path),
                        reason=reason_here, **folder.manifest.counts())
            recovered.append(folder)
        return recovered


def read_folder(path: Path | str, *, writer: AtomicWriter | None = None) -> ScanFolder:
    """The scan folder at ``path`` with its typed manifest; ManifestError if it has none."""
    path = Path(path)
    manifest = path / MANIFEST
    if not manifest.is_file():
        raise ManifestError(manifest, "missing: not a scan folder")
    try:
        raw = read_at_most(manifest, MAX_MANIFEST_BYTES, "manifest", lambda problem: ManifestError(manifest, problem))
        data = json.loads(raw)
    except (OSError, ValueError, RecursionError) as exc:
        raise ManifestError(manifest, f"unreadable: {str(exc)[:200]}") from exc
    return ScanFolder(path, Manifest.from_dict(data, manifest), writer or AtomicWriter())


_TYPED: dict[str, Any] = {"status": ImageStatus, "missing_reason": MissingReason}
"""Image fields held as enums (update_image takes their values too)."""


def _settle_images(folder: ScanFolder, images: Iterable[ImageRecord]) -> None:
    for image in images:
        if image.status is ImageStatus.PLANNED:
            image.status = ImageStatus.MISSING
            image.error = "not captured: scan interrupted"
            image.missing_reason = MissingReason.NOT_REACHED
        elif image.status is ImageStatus.CAPTURED:
            image.error = "not pulled from the phone: scan interrupted"
            image.missing_reason = MissingReason.NOT_PULLED
        elif image.status is ImageStatus.PULLED:
            path = folder.path / (image.file or "")
            ok = (image.file and path.is_file() and path.stat().st_size == image.size_bytes
                  and sha256_of(path) == image.sha256)
            if ok:
                image.status = ImageStatus.VERIFIED
            else:
                image.status = ImageStatus.FAILED
                image.error = "pulled file does not match its size and checksum after interruption"
                image.missing_reason = MissingReason.PULL_FAILED
