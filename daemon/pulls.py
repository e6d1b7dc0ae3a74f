"""Background image pulls: phone -> scan folder, verified by size and checksum.

The capture rotation must never wait for a file transfer, so every captured image is queued
here and pulled by a few asyncio workers while the beam keeps turning. A pull is the
daemon's coroutine ``pull(phone_path, dest) -> (size_bytes, sha256)`` (PhoneCamera.pull);
the store then checks the file on disk against that size, the size the phone reported at
capture, and its own SHA-256. A failed pull (an error, a mismatch, or no answer within
PULL_TIMEOUT_S) is retried RETRIES times, then recorded in the
manifest as failed with the error. A full disk is not retried: it is recorded, the image
stays 'captured' (still on the phone) and :meth:`PullQueue.join` raises the StoreFull
(likewise any StoreError that kept the manifest from being rewritten).
"""

from __future__ import annotations

import asyncio
import errno
import hashlib
import shutil
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

import structlog

from daemon.atomic import StoreError, StoreFull
from daemon.manifest import ImageStatus
from daemon.store import ScanFolder

PullFn = Callable[[str, Path], Awaitable[tuple[int, str]]]
_CHUNK = 1 << 20

log = structlog.get_logger(__name__)


class ImagePullFailed(StoreError):
    """An image could not be pulled and verified after every retry."""

    def __init__(self, path: Path | str, camera_id: str, angle_index: int, attempts: int,
                 cause: str) -> None:
        self.camera_id = camera_id
        self.angle_index = angle_index
        self.attempts = attempts
        self.cause = cause
        super().__init__(path, f"{camera_id} angle {angle_index}: pull failed after "
                               f"{attempts} attempt(s): {cause}")


class VerifyFailed(StoreError):
    """A pulled file does not match the expected size or checksum."""


async def file_sha256(path: Path) -> str:
    """SHA-256 of a file, yielding to the event loop between 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
            await asyncio.sleep(0)
    return h.hexdigest()


@dataclass(frozen=True)
class PullJob:
    camera_index: int
    angle_index: int
    phone_path: str
    pull: PullFn
    expected_size: int | None


class PullQueue:
    """An asyncio queue of pulls served by ``workers`` tasks; use ``async with``."""

    RETRIES = 2
    RETRY_DELAY_S = 0.5
    PULL_TIMEOUT_S = 120.0
    SPACE_MARGIN_BYTES = 1 << 20

    def __init__(self, folder: ScanFolder, *, workers: int = 2,
                 on_verified: Callable[[int], None] | None = None) -> None:
        self.folder = folder
        self.n_workers = workers
        self.on_verified = on_verified
        self.verified = 0
        self.failures: list[ImagePullFailed] = []
        self.fatal: StoreError | None = None
        self._queue: asyncio.Queue[PullJob] = asyncio.Queue()
        self._tasks: list[asyncio.Task[None]] = []

    async def __aenter__(self) -> PullQueue:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def start(self) -> None:
        if not self._tasks:
            self._tasks = [asyncio.create_task(self._worker(), name=f"pull-{i}")
                           for i in range(self.n_workers)]

    def submit(self, camera_index: int, angle_index: int, phone_path: str, pull: PullFn, *,
               expected_size: int | None = None) -> None:
        """Queue one captured image (never blocks the capture)."""
        self.folder.image(camera_index, angle_index)  # refuses unknown images up front
        self._queue.put_nowait(PullJob(camera_index, angle_index, phone_path, pull, expected_size))

    async def join(self) -> None:
        """Wait until every queued pull is done; raises the StoreError (disk full, manifest
        unwritable) that stopped the pulls, if any."""
        await self._queue.join()
        if self.fatal is not None:
            raise self.fatal

    async def close(self) -> None:
        """Stop the workers (queued pulls not yet started stay 'captured')."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []

    async def _worker(self) -> None:
        while True:
            job = await self._queue.get()
            try:
                await self._serve(job)
            except StoreError as exc:  # the manifest could not be rewritten: join() raises it
                self.fatal = self.fatal or exc
                log.error("pull_store_failed", angle_index=job.angle_index,
                          camera_index=job.camera_index, error=str(exc))
            finally:
                self._queue.task_done()

    async def _serve(self, job: PullJob) -> None:
        folder = self.folder
        image = folder.image(job.camera_index, job.angle_index)
        dest = folder.image_dest(job.camera_index, job.angle_index, job.phone_path)
        if self.fatal is not None:
            folder.update_image(job.camera_index, job.angle_index, error=str(self.fatal))
            return
        cause = ""
        for attempt in range(1, self.RETRIES + 2):
            folder.update_image(job.camera_index, job.angle_index, attempts=attempt, save=False)
            try:
                self._check_space(dest, job.expected_size)
                async with asyncio.timeout(self.PULL_TIMEOUT_S):
                    size, sha = await job.pull(job.phone_path, dest)
                await self._verify(dest, size, sha, job.expected_size)
            except StoreFull as exc:
                self._disk_full(job, exc)
                return
            except OSError as exc:
                if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                    self._disk_full(job, StoreFull(dest, job.expected_size or 0))
                    return
                cause = f"{type(exc).__name__}: {exc}"
            except TimeoutError:
                cause = f"TimeoutError: no pull within {self.PULL_TIMEOUT_S:g} s"
            except Exception as exc:  # the phone's typed errors: recorded, then retried
                cause = f"{type(exc).__name__}: {exc}"
            else:
                folder.update_image(
                    job.camera_index, job.angle_index, status=ImageStatus.VERIFIED,
                    file=str(dest.relative_to(folder.path)), size_bytes=size, sha256=sha,
                    error=None,
                )
                self.verified += 1
                if self.on_verified is not None:
                    self.on_verified(self.verified)
                return
            log.warning("pull_retry", device=image.camera_id, angle_index=job.angle_index,
                        attempt=attempt, error=cause)
            if attempt <= self.RETRIES:
                await asyncio.sleep(self.RETRY_DELAY_S)
        dest.unlink(missing_ok=True)  # a file that failed verification is not an image
        failure = ImagePullFailed(dest, image.camera_id, job.angle_index, self.RETRIES + 1, cause)
        self.failures.append(failure)
        folder.record_failure(job.camera_index, job.angle_index, str(failure))

    def _check_space(self, dest: Path, expected: int | None) -> None:
        if expected is None:
            return
        free = shutil.disk_usage(dest.parent).free
        if free < expected + self.SPACE_MARGIN_BYTES:
            raise StoreFull(dest, expected + self.SPACE_MARGIN_BYTES, free)

    async def _verify(self, dest: Path, size: int, sha: str, expected: int | None) -> None:
        if not dest.is_file():
            raise VerifyFailed(dest, "pull returned but the file is not there")
        on_disk = dest.stat().st_size
        if on_disk != size or (expected is not None and on_disk != expected):
            raise VerifyFailed(dest, f"size {on_disk} bytes on disk, {size} pulled, "
                                     f"{expected} reported by the phone")
        digest = await file_sha256(dest)
        if digest != sha:
            raise VerifyFailed(dest, f"sha256 {digest} on disk, {sha} pulled")

    def _disk_full(self, job: PullJob, exc: StoreFull) -> None:
        self.fatal = self.fatal or exc
        # The image is still on the phone: keep it 'captured' and say why it was not pulled.
        try:
            self.folder.update_image(job.camera_index, job.angle_index, error=str(exc))
        except StoreFull:
            self.folder.update_image(job.camera_index, job.angle_index, error=str(exc), save=False)
        log.error("store_full", device=self.folder.image(job.camera_index, job.angle_index).camera_id,
                  angle_index=job.angle_index, path=exc.path, bytes_needed=exc.bytes_needed)
