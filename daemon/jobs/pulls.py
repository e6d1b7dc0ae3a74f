"""The one way a picture comes off a phone: pulled, verified by size and checksum, retried.

:func:`pull_verified` pulls one picture with the phone driver's coroutine ``pull(phone_path,
dest) -> (size_bytes, sha256)`` (PhoneCamera.pull), then checks the file on disk against that
size, the size the phone reported at capture, and its own SHA-256 (read in a thread: hashing
never holds the event loop). A failed pull (an error, a mismatch, or no answer within
``timeout_s``) is retried ``retries`` times, then raises :class:`ImagePullFailed`. A full disk is
not retried: it raises :class:`StoreFull` and the picture stays on the phone.

:class:`PullQueue` runs these pulls in the background, so a rotation never waits for a file
transfer, and records each in a :class:`PullLedger`: the scan's manifest (:class:`ScanImages`)
or the calibration rotation's captures.json. The focus sweep pulls each picture with
:func:`pull_verified` directly (it measures the picture before taking the next).
"""

from __future__ import annotations

import asyncio
import errno
import hashlib
import shutil
from collections.abc import Awaitable, Callable, Hashable
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, Protocol, TypeVar

import structlog

from daemon.records.atomic import StoreError, StoreFull
from daemon.records.manifest import ImageStatus
from daemon.records.store import ScanFolder
from daemon.tasks import stop_tasks

PullFn = Callable[[str, Path], Awaitable[tuple[int, str]]]
_CHUNK = 1 << 20
K = TypeVar("K", bound=Hashable)
ImageKey = tuple[int, int]  # (camera index, angle index): what a ledger files a picture under

log = structlog.get_logger(__name__)


class ImagePullFailed(StoreError):
    """An image could not be pulled and verified after every retry."""

    def __init__(self, path: Path | str, camera_id: str, angle_index: int | None, attempts: int,
                 cause: str) -> None:
        self.camera_id = camera_id
        self.angle_index = angle_index
        self.attempts = attempts
        self.cause = cause
        where = camera_id if angle_index is None else f"{camera_id} angle {angle_index}"
        super().__init__(path, f"{where}: pull failed after {attempts} attempt(s): {cause}")


class VerifyFailed(StoreError):
    """A pulled file does not match the expected size or checksum."""


def file_sha256(path: Path) -> str:
    """SHA-256 of a file, read in 1 MiB chunks (call it in a thread)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class Pull(Generic[K]):
    """One picture on a phone and where it goes. ``key``: what the ledger files it under;
    ``delete``: remove it from the phone once verified (None: it stays there)."""

    key: K
    camera_id: str
    angle_index: int | None
    phone_path: str
    dest: Path
    pull: PullFn
    expected_size: int | None = None
    delete: Callable[[str], Awaitable[None]] | None = None


@dataclass(frozen=True)
class PullPolicy:
    """retries after the first attempt, the wait between them, the longest a pull may take (s),
    and the free space kept beyond a picture's size (bytes)."""

    retries: int = 2
    retry_delay_s: float = 0.5
    timeout_s: float = 120.0
    space_margin_bytes: int = 1 << 20


async def pull_verified(job: Pull[K], policy: PullPolicy = PullPolicy(),
                        on_attempt: Callable[[int], None] | None = None) -> tuple[int, str]:
    """Pull ``job`` into ``job.dest`` and verify it; (size in bytes, sha256 hex).

    Raises StoreFull (not retried: the picture stays on the phone) or, after every retry,
    ImagePullFailed (a file that failed verification is removed)."""
    cause = ""
    for attempt in range(1, policy.retries + 2):
        if on_attempt is not None:
            on_attempt(attempt)
        try:
            await asyncio.to_thread(_make_room, job.dest, job.expected_size, policy.space_margin_bytes)
            async with asyncio.timeout(policy.timeout_s):
                size, sha = await job.pull(job.phone_path, job.dest)
            await asyncio.to_thread(_verify, job.dest, size, sha, job.expected_size)
        except StoreFull:
            raise
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise StoreFull(job.dest, job.expected_size or 0) from exc
            cause = f"{type(exc).__name__}: {exc}"
        except TimeoutError:
            cause = f"TimeoutError: no pull within {policy.timeout_s:g} s"
        except Exception as exc:  # the phone's typed errors: recorded, then retried
            cause = f"{type(exc).__name__}: {exc}"
        else:
            return size, sha
        log.warning("pull_retry", device=job.camera_id, angle_index=job.angle_index, attempt=attempt, error=cause)
        if attempt <= policy.retries:
            await asyncio.sleep(policy.retry_delay_s)
    await asyncio.to_thread(job.dest.unlink, missing_ok=True)  # a file that failed verification is not an image
    raise ImagePullFailed(job.dest, job.camera_id, job.angle_index, policy.retries + 1, cause)


def _make_room(dest: Path, expected: int | None, margin: int) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    if expected is None:
        return
    free = shutil.disk_usage(dest.parent).free
    if free < expected + margin:
        raise StoreFull(dest, expected + margin, free)


def _verify(dest: Path, size: int, sha: str, expected: int | None) -> None:
    if not dest.is_file():
        raise VerifyFailed(dest, "pull returned but the file is not there")
    on_disk = dest.stat().st_size
    if on_disk != size or (expected is not None and on_disk != expected):
        raise VerifyFailed(dest, f"size {on_disk} bytes on disk, {size} pulled, {expected} reported by the phone")
    digest = file_sha256(dest)
    if digest != sha:
        raise VerifyFailed(dest, f"sha256 {digest} on disk, {sha} pulled")


class PullLedger(Protocol):
    """Where a job records what happens to its pulls (raising StoreError stops the queue)."""

    def attempt(self, job: Pull[ImageKey], attempt: int) -> None:
        """Attempt number ``attempt`` (1-based) starts."""

    def verified(self, job: Pull[ImageKey], size: int, sha256: str) -> None:
        """The picture is on disk and verified."""

    def failed(self, job: Pull[ImageKey], failure: ImagePullFailed) -> None:
        """Every attempt failed; the picture stays on the phone."""

    def not_pulled(self, job: Pull[ImageKey], error: StoreError) -> None:
        """Not pulled because the store cannot take it (disk full); the picture stays on the phone."""

    def not_deleted(self, job: Pull[ImageKey], error: Exception) -> None:
        """Verified, but the phone did not delete its copy."""


class PullQueue:
    """An asyncio queue of pulls served by ``workers`` tasks, recorded in ``ledger``; use
    ``async with`` or :meth:`start` and :meth:`close`.

    A full disk is recorded (the picture stays on the phone) and stops the pulls: later ones are
    recorded as not pulled and :meth:`join` raises the StoreFull, as it does any StoreError that
    kept the ledger from recording.
    """

    CLOSE_TIMEOUT_S = 5.0

    def __init__(self, ledger: PullLedger, *, workers: int = 2, policy: PullPolicy = PullPolicy(),
                 on_verified: Callable[[int], object] | None = None) -> None:
        self.ledger = ledger
        self.n_workers = workers
        self.policy = policy
        self.on_verified = on_verified
        self.verified = 0
        self.failures: list[ImagePullFailed] = []
        self.fatal: StoreError | None = None
        self._queue: asyncio.Queue[Pull[ImageKey]] = asyncio.Queue()
        self._tasks: list[asyncio.Task[None]] = []

    async def __aenter__(self) -> PullQueue:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def start(self) -> None:
        if not self._tasks:
            self._tasks = [asyncio.create_task(self._worker(), name=f"pull-{i}") for i in range(self.n_workers)]

    def submit(self, job: Pull[ImageKey]) -> None:
        """Queue one captured picture (never blocks the capture)."""
        self._queue.put_nowait(job)

    async def join(self) -> None:
        """Wait until every queued pull is done; raises the StoreError (disk full, ledger
        unwritable) that stopped the pulls, if any."""
        await self._queue.join()
        if self.fatal is not None:
            raise self.fatal

    async def close(self) -> None:
        """Stop the workers (queued pulls not yet started stay on the phones); a worker that
        does not stop within CLOSE_TIMEOUT_S is logged and left cancelled."""
        tasks, self._tasks = self._tasks, []
        await stop_tasks(tasks, self.CLOSE_TIMEOUT_S)

    async def _worker(self) -> None:
        while True:
            job = await self._queue.get()
            try:
                await self._serve(job)
            except StoreError as exc:  # the ledger could not be rewritten: join() raises it
                self.fatal = self.fatal or exc
                log.error("pull_store_failed", device=job.camera_id, angle_index=job.angle_index, error=str(exc))
            finally:
                self._queue.task_done()

    async def _serve(self, job: Pull[ImageKey]) -> None:
        ledger = self.ledger
        if self.fatal is not None:
            ledger.not_pulled(job, self.fatal)
            return
        try:
            size, sha = await pull_verified(job, self.policy, lambda attempt: ledger.attempt(job, attempt))
        except StoreFull as exc:
            self.fatal = self.fatal or exc
            ledger.not_pulled(job, exc)
            log.error("store_full", device=job.camera_id, angle_index=job.angle_index, path=exc.path,
                      bytes_needed=exc.bytes_needed)
            return
        except ImagePullFailed as failure:
            self.failures.append(failure)
            ledger.failed(job, failure)
            return
        ledger.verified(job, size, sha)
        self.verified += 1
        if self.on_verified is not None:
            self.on_verified(self.verified)
        if job.delete is not None:
            try:
                await job.delete(job.phone_path)
            except Exception as exc:  # the picture is safe here; the phone keeps a copy
                ledger.not_deleted(job, exc)


class ScanImages:
    """The pull ledger of a scan: its manifest's image records."""

    def __init__(self, folder: ScanFolder) -> None:
        self.folder = folder

    def pull(self, camera_index: int, angle_index: int, phone_path: str, pull: PullFn, *,
             expected_size: int | None = None) -> Pull[ImageKey]:
        """The pull of a planned image (refuses unknown images up front)."""
        image = self.folder.image(camera_index, angle_index)
        return Pull((camera_index, angle_index), image.camera_id, angle_index, phone_path,
                    self.folder.image_dest(camera_index, angle_index, phone_path), pull, expected_size)

    def attempt(self, job: Pull[ImageKey], attempt: int) -> None:
        c, k = job.key
        self.folder.update_image(c, k, attempts=attempt, save=False)

    def verified(self, job: Pull[ImageKey], size: int, sha256: str) -> None:
        c, k = job.key
        self.folder.update_image(c, k, status=ImageStatus.VERIFIED, file=str(job.dest.relative_to(self.folder.path)),
                                 size_bytes=size, sha256=sha256, error=None)

    def failed(self, job: Pull[ImageKey], failure: ImagePullFailed) -> None:
        c, k = job.key
        self.folder.record_failure(c, k, str(failure))

    def not_pulled(self, job: Pull[ImageKey], error: StoreError) -> None:
        """The image is still on the phone: it stays 'captured', with the reason."""
        c, k = job.key
        try:
            self.folder.update_image(c, k, error=str(error))
        except StoreFull:
            self.folder.update_image(c, k, error=str(error), save=False)

    def not_deleted(self, job: Pull[ImageKey], error: Exception) -> None:
        """A scan does not delete pictures on the phones."""
