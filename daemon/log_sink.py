"""Where the daemon's log lines go: a bounded queue written out by one thread.

The event loop carries the drive's and the panel's heartbeats, so logging must never wait for
the reader of stdout (journald, a pipe, a terminal). A line is rendered on the thread that logs
it and put in a bounded queue; one writer thread writes the lines out, in order. When the
queue is full the line is dropped and counted, and the writer puts a line saying how many were
dropped before the next line it writes: nothing is lost silently, and a stuck journal costs
the loop one ``put_nowait``.
"""

from __future__ import annotations

import atexit
import queue
import threading
from collections.abc import Callable
from typing import TextIO

_STOP = object()


class LineSink:
    """Lines to ``stream``, written by one thread from a queue of at most ``capacity`` lines.

    Args:
        stream: the text stream the lines go to (without their newline, which the sink adds).
        dropped_line: renders the line that says ``n`` lines were dropped.
        capacity: lines queued at most; beyond it a line is dropped and counted.
    """

    CLOSE_TIMEOUT_S = 5.0

    def __init__(self, stream: TextIO, dropped_line: Callable[[int], str], *, capacity: int = 10_000) -> None:
        self.stream = stream
        self.dropped_line = dropped_line
        self.capacity = capacity
        self._queue: queue.Queue[object] = queue.Queue(capacity)
        self._lock = threading.Lock()
        self._dropped = 0
        self.dropped_total = 0
        self._closed = False
        self._thread = threading.Thread(target=self._write_lines, name="log-writer", daemon=True)
        self._thread.start()
        atexit.register(self.close)

    def put(self, line: str) -> None:
        """Queue one line; never blocks (a full queue drops it and counts it). After
        :meth:`close` lines are written at once (the last words of a process that is ending)."""
        if self._closed:
            with self._lock:
                self._write([line])
            return
        try:
            self._queue.put_nowait(line)
        except queue.Full:
            with self._lock:
                self._dropped += 1
                self.dropped_total += 1

    def _take_dropped(self) -> int:
        with self._lock:
            dropped, self._dropped = self._dropped, 0
        return dropped

    def _write_lines(self) -> None:
        while True:
            lines = [self._queue.get()]
            while len(lines) < 256:  # what has queued up meanwhile goes out in one write
                try:
                    lines.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            stop = _STOP in lines
            text = [line for line in lines if line is not _STOP]
            dropped = self._take_dropped()
            if dropped:
                text.insert(0, self.dropped_line(dropped))
            if text:
                self._write(text)  # type: ignore[arg-type]
            for _ in lines:
                self._queue.task_done()
            if stop:
                return

    def _write(self, lines: list[str]) -> None:
        try:
            self.stream.write("\n".join(lines) + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # stdout gone (a closed pipe): nobody reads the lines any more
            self.dropped_total += len(lines)

    def flush(self) -> None:
        """Wait until every line queued so far is written (blocks)."""
        self._queue.join()

    def close(self) -> None:
        """Write out what is queued (waiting at most CLOSE_TIMEOUT_S) and stop the writer; idempotent."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        try:
            self._queue.put(_STOP, timeout=self.CLOSE_TIMEOUT_S)
        except queue.Full:
            return
        self._thread.join(self.CLOSE_TIMEOUT_S)


class DirectSink:
    """Lines written at once on the calling thread (tests, and tools that log a few lines)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self._lock = threading.Lock()

    def put(self, line: str) -> None:
        with self._lock:
            self.stream.write(line + "\n")
            self.stream.flush()

    def close(self) -> None:
        """Nothing is queued."""
