"""One scan folder's writes in the order they are asked for, in the store's writer thread.

During a real-time scan every write of the folder (events.jsonl lines, whole files, the
manifest) is queued here instead of waiting on the event loop for its fdatasync and folder
fsync: the loop carries the heartbeats. One thread runs the queue in order, so the folder is
always consistent on disk: a file is listed in the manifest only once its write is durable
(the caller lists it when the write's future is done, and the manifest written after that is
queued after it), and a manifest asked for while another waits replaces it (the newest state,
written after everything queued before it). Lines appended one after another share one
fdatasync.

A failed write of a file reaches its future; a failed line or manifest write is kept and raised
by the next :meth:`FolderWriter.raise_failure` (the folder's next write asks) or :meth:`drain`.
"""

from __future__ import annotations

import asyncio
import functools
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path

from daemon.records.atomic import AtomicWriter


@dataclass
class _Op:
    """One queued write: ``run()`` in the thread; ``future`` (on the loop) settles when it is done."""

    run: Callable[[], None]
    future: asyncio.Future[None] | None = None
    manifest: bool = False


@dataclass
class _Lines:
    """Lines for one file, appended with one fdatasync."""

    path: Path
    lines: list[bytes] = field(default_factory=list)
    future: asyncio.Future[None] | None = None
    manifest: bool = False


class FolderWriter:
    """The ordered writes of one scan folder (see the module docstring); made on the event loop.

    Args:
        writer: the store's atomic writer (whole files, fdatasync'd lines).
        executor: the store's one writer thread.
    """

    def __init__(self, writer: AtomicWriter, executor: Executor) -> None:
        self.writer = writer
        self.executor = executor
        self._loop = asyncio.get_running_loop()
        self._lock = threading.Lock()
        self._ops: deque[_Op | _Lines] = deque()
        self._running = False
        self._failures: list[BaseException] = []

    # ------------------------------------------------------------------ on the loop

    def file(self, write: Callable[[], None]) -> asyncio.Future[None]:
        """Queue ``write()`` (a whole file, made and written atomically in the thread); the
        future is done once it is durable, or holds its error."""
        future = self._loop.create_future()
        self._queue(_Op(write, future))
        return future

    def append(self, path: Path, line: bytes, *, done: bool = False) -> asyncio.Future[None] | None:
        """Queue one line for ``path``; with ``done`` a future that settles once it is durable."""
        with self._lock:
            last = self._ops[-1] if self._ops else None
            if isinstance(last, _Lines) and last.path == path:  # not started yet: joins its fdatasync
                last.lines.append(line)
                if done and last.future is None:
                    last.future = self._loop.create_future()
                return last.future if done else None
        future = self._loop.create_future() if done else None
        self._queue(_Lines(path, [line], future))
        return future

    def manifest(self, write: Callable[[], None], *, done: bool = False) -> asyncio.Future[None] | None:
        """Queue the manifest's write, replacing one that waits; with ``done`` a future."""
        future = self._loop.create_future() if done else None
        with self._lock:
            for op in [op for op in self._ops if op.manifest]:
                self._ops.remove(op)
                if op.future is not None:  # settled with the write that replaces it
                    replaced = op.future
                    if future is None:
                        future = self._loop.create_future()
                    future.add_done_callback(functools.partial(_settle_like, replaced))
        self._queue(_Op(write, future, manifest=True))
        return future

    def keep_failure(self, error: BaseException) -> None:
        """A write whose future nobody awaits failed: raised like a failed line write."""
        with self._lock:
            self._failures.append(error)

    def raise_failure(self) -> None:
        """Raise the first failed line or manifest write not raised yet (and forget the others)."""
        with self._lock:
            failures, self._failures = self._failures, []
        if failures:
            raise failures[0]

    async def drain(self) -> None:
        """Wait until everything queued so far is written; raise a failure not raised yet."""
        future = self._loop.create_future()
        self._queue(_Op(lambda: None, future))
        await future
        self.raise_failure()

    def wait(self) -> None:
        """:meth:`drain` for a caller that is not a coroutine (blocks: a scan's end, recovery)."""
        done = threading.Event()
        self._queue(_Op(done.set))
        done.wait()
        self.raise_failure()

    def _queue(self, op: _Op | _Lines) -> None:
        with self._lock:
            self._ops.append(op)
            if self._running:
                return
            self._running = True
        self.executor.submit(self._run)

    # ------------------------------------------------------------------ in the thread

    def _run(self) -> None:
        while True:
            with self._lock:
                if not self._ops:
                    self._running = False
                    return
                op = self._ops.popleft()
            error: BaseException | None = None
            try:
                if isinstance(op, _Lines):
                    self.writer.append_lines(op.path, op.lines)
                else:
                    op.run()
            except BaseException as exc:  # the loop gets it: the op's future, or the next write
                error = exc
            if op.future is not None:
                try:
                    self._loop.call_soon_threadsafe(_settle, op.future, error)
                    continue
                except RuntimeError:  # the loop is closed: nobody waits for the future any more
                    pass
            if error is not None:
                with self._lock:
                    self._failures.append(error)


def _settle(future: asyncio.Future[None], error: BaseException | None) -> None:
    if future.done():
        return
    if error is None:
        future.set_result(None)
    else:
        future.set_exception(error)


def _settle_like(target: asyncio.Future[None], source: asyncio.Future[None]) -> None:
    _settle(target, None if source.cancelled() else source.exception())
