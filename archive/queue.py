"""The daemon's export queue: every completed scan for a patient goes to the site's archive by
itself, through outages, rejections and restarts, each instance confirmed once.

The queue lives on disk beside the scans, ``<store>/.export/``: one JSON record per scan folder
(state, attempts, the SOP Instance UIDs the archive confirmed, the last error), written
atomically after every confirmed instance, and ``since`` (when the queue was first started: scans
taken before are not sent by themselves; ``tbp export`` sends them). Every POLL_S the store is
looked at for completed scans without a record, so a scan that ended while the daemon was
stopping is found at the next start: nothing is lost. A transfer cut off (the archive killed, the
network gone, the association aborted) is retried after ``retry.first_s``, doubling up to
``retry.max_s``, and resumes after the last confirmed instance; only the one instance in flight
when the cut came can reach the archive twice, and the archive keeps it once (the same UID). A
refusal that waiting will not cure (an AE title the archive does not know, a SOP class it does
not take, a scan that cannot be exported) marks the scan ``failed`` with the peer and the reason,
shown in the status and on the console; it is tried again when the daemon restarts. Any other
failure (a library's or this code's) is logged with its trace, shown as a problem and retried like
an outage: the queue never stops by itself.

The export itself runs in a thread of its own (pynetdicom and HTTP are blocking), one scan at a
time; the event loop only waits for its answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import structlog

from archive.instances import ExportError, Instance, StudyBuilder
from daemon.clinic.dimse import DicomPeerError
from daemon.clinic.site import Site
from daemon.records.atomic import AtomicWriter, StoreError
from daemon.records.manifest import ScanEnd
from daemon.records.store import ScanStore
from daemon.utc import utc_stamp

log = structlog.get_logger("archive.queue")

QUEUE_DIR = ".export"
PENDING, SENDING, SENT, FAILED = "pending", "sending", "sent", "failed"


@dataclass
class ExportRecord:
    """One scan's way to the archive."""

    folder: str
    destination: str
    state: str = PENDING
    attempts: int = 0
    total: int | None = None
    sent: list[str] = field(default_factory=list)
    error: str | None = None
    updated_utc: str = ""

    def summary(self) -> dict[str, Any]:
        return {"folder": self.folder, "state": self.state, "attempts": self.attempts, "sent": len(self.sent),
                "total": self.total, "error": self.error}


class ExportQueue:
    """The export queue of one store for the site's archive; ``start()`` and ``close()`` as the
    daemon's attached servers (cli/daemon.py attaches it when the site file has an archive)."""

    POLL_S = 5.0

    def __init__(self, store: ScanStore, site: Site, *, rig_path: Path | str | None = None,
                 export: Callable[..., None] | None = None) -> None:
        assert site.archive is not None
        self.store = store
        self.site = site
        self.archive = site.archive
        self.rig_path = rig_path
        self.dir = store.root / QUEUE_DIR
        self.writer = AtomicWriter()
        self.records: dict[str, ExportRecord] = {}
        self.since = ""
        self._export = export or self._send
        self._task: asyncio.Task[None] | None = None
        self._retry_at: dict[str, float] = {}
        self._wake = asyncio.Event()
        self.current: str | None = None

    # ------------------------------------------------------------------ life

    async def start(self) -> None:
        await asyncio.to_thread(self._load)
        self._task = asyncio.create_task(self._run(), name="export-queue")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None

    def status(self) -> dict[str, Any]:
        """For ``tbp status`` and the console: where completed scans go and how far they are."""
        records = list(self.records.values())
        count = {s: sum(r.state == s for r in records) for s in (PENDING, SENDING, SENT, FAILED)}
        loop = asyncio.get_running_loop()
        waits = [t - loop.time() for t in self._retry_at.values()]
        return {"destination": str(self.archive), "deidentify": self.archive.deidentify, "counts": count,
                "sending": None if self.current is None else self.records[self.current].summary(),
                "retry_in_s": round(max(0.0, min(waits)), 1) if waits else None,
                "problems": [r.summary() for r in records if r.error and r.state != SENT][-10:]}

    # ------------------------------------------------------------------ disk

    def _load(self) -> None:
        self.dir.mkdir(mode=0o750, parents=True, exist_ok=True)
        since = self.dir / "since"
        if not since.is_file():
            self.writer.write(since, (utc_stamp() + "\n").encode())
        self.since = since.read_text().strip()
        for path in sorted(self.dir.glob("*.json")):
            try:
                record = ExportRecord(**json.loads(path.read_text()))
            except (OSError, ValueError, TypeError) as exc:
                log.error("export_record_unreadable", path=str(path), error=str(exc))
                continue
            if record.state == SENDING:  # the daemon stopped mid-transfer: resume
                record.state = PENDING
            if record.state == FAILED:  # tried again at each start (a configuration may be fixed)
                record.state = PENDING
            self.records[record.folder] = record

    def _save(self, record: ExportRecord) -> None:
        record.updated_utc = utc_stamp()
        self.writer.write(self.dir / f"{record.folder}.json", json.dumps(asdict(record)).encode())

    def _discover(self) -> list[ExportRecord]:
        """Completed scans for a patient taken since the queue began, not yet in it (in a thread)."""
        found = []
        for path in self.store.folders():
            if path.name in self.records:
                continue
            try:
                manifest = self.store.open(path).manifest
            except StoreError:
                continue
            if manifest.in_progress or manifest.state is not ScanEnd.COMPLETE or manifest.patient is None:
                continue
            if manifest.created_utc < self.since:
                continue
            record = ExportRecord(path.name, str(self.archive))
            self._save(record)
            found.append(record)
        return found

    # ------------------------------------------------------------------ work

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            for record in await asyncio.to_thread(self._discover):
                self.records[record.folder] = record
                log.info("export_queued", folder=record.folder, destination=record.destination)
            due = [r for r in self.records.values()
                   if r.state == PENDING and self._retry_at.get(r.folder, 0.0) <= loop.time()]
            if due:
                await self._attempt(due[0])
                continue
            waits = [t - loop.time() for t in self._retry_at.values()] + [self.POLL_S]
            with contextlib.suppress(TimeoutError):  # asyncio.timeout: a cancel is never swallowed
                async with asyncio.timeout(max(0.01, min(waits))):
                    await self._wake.wait()
            self._wake.clear()

    async def _attempt(self, record: ExportRecord) -> None:
        loop = asyncio.get_running_loop()
        record.state, record.attempts = SENDING, record.attempts + 1
        self.current = record.folder
        await asyncio.to_thread(self._save, record)
        log.info("export_started", folder=record.folder, attempt=record.attempts, confirmed=len(record.sent))
        try:
            await _in_thread(lambda: self._export(record, self._confirmed(record)))
        except DicomPeerError as exc:
            record.error = str(exc)
            if exc.retry:
                wait = self._retry_in(record)
                record.state = PENDING
                self._retry_at[record.folder] = loop.time() + wait
                log.warning("export_retry", folder=record.folder, error=str(exc), retry_in_s=wait,
                            confirmed=len(record.sent))
            else:
                record.state = FAILED
                log.error("export_failed", folder=record.folder, error=str(exc))
        except (ExportError, StoreError) as exc:
            record.state, record.error = FAILED, str(exc)
            log.error("export_failed", folder=record.folder, error=str(exc))
        except Exception as exc:  # a fault of a library or of this code: shown, retried, never the queue's end
            record.error = f"{self.archive}: unexpected {type(exc).__name__}: {exc}"
            wait = self._retry_in(record)
            record.state = PENDING
            self._retry_at[record.folder] = loop.time() + wait
            log.exception("export_retry", folder=record.folder, error=record.error, retry_in_s=wait,
                          confirmed=len(record.sent))
        else:
            record.state, record.error = SENT, None
            self._retry_at.pop(record.folder, None)
            log.info("export_sent", folder=record.folder, instances=len(record.sent), attempts=record.attempts)
        finally:
            self.current = None
        await asyncio.to_thread(self._save, record)

    def _retry_in(self, record: ExportRecord) -> float:
        return min(self.archive.retry_first_s * 2 ** (record.attempts - 1), self.archive.retry_max_s)

    def _confirmed(self, record: ExportRecord) -> Callable[[Instance], None]:
        def confirmed(instance: Instance) -> None:  # in the export's thread
            record.sent.append(instance.sop_instance_uid)
            self._save(record)

        return confirmed

    def _send(self, record: ExportRecord, on_sent: Callable[[Instance], None]) -> None:
        """Make the scan's study and send what the archive has not confirmed (in the thread)."""
        from archive.deidentify import deidentified, new_uid
        from archive.send import send_dimse, send_stow

        builder = StudyBuilder(self.store.root / record.folder, self.rig_path)
        instances = deidentified(builder) if self.archive.deidentify else builder.instances()
        record.total = len(instances)
        done = frozenset(record.sent)
        if self.archive.pacs is not None:
            send_dimse(instances, self.site.ae_title, self.archive.pacs, tls=self.site.tls, done=done, on_sent=on_sent)
        else:
            assert self.archive.dicomweb is not None
            study = builder.study.study_instance_uid
            send_stow(instances, self.archive.dicomweb, new_uid(study) if self.archive.deidentify else study,
                      tls=self.site.tls, done=done, on_sent=on_sent)


async def _in_thread(work: Callable[[], None]) -> None:
    """Run ``work`` in a thread of its own and wait for it without holding the loop's clock (a
    virtual-time loop keeps its timers running, unlike with ``run_in_executor``)."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()

    def run() -> None:
        try:
            work()
        except BaseException as exc:  # handed to the waiting task, raised there
            loop.call_soon_threadsafe(lambda error=exc: done.done() or done.set_exception(error))
        else:
            loop.call_soon_threadsafe(lambda: done.done() or done.set_result(None))

    threading.Thread(target=run, name="archive-export", daemon=True).start()
    await asyncio.shield(done)
