"""Every thread's stack while the event loop is late, taken safely: an engineer's diagnostic.

A watcher thread sleeps until the loop's current lag sample (daemon/server/looplag.py) is
``warn_s`` overdue; if that sample is still running then, the watcher takes every thread's
stack with the interpreter lock held (``sys._current_frames``) and appends it to a file in
the fault handler's layout (``Thread 0x... (most recent call first):``, the loop's own thread
headed ``Loop thread 0x...``).

Taken under the interpreter lock, a dump is always consistent. The interpreter's fault
handler (``faulthandler.dump_traceback_later``) reads other threads' frames without the lock,
and a thread whose stack grows or shrinks meanwhile can crash the process: tests/test_looplag.py
crashes it in under a second with deep recursion on other threads. The price: while some
thread holds the lock inside C code, the watcher waits for it too, and the dump shows where
the threads are once it is released. ``after_ms`` says how long past due the stacks were
taken: tens of milliseconds there is itself the sign of a thread holding the lock.

The watcher wakes about once per ``period + warn_s`` and takes nothing while the loop keeps
time.
"""

from __future__ import annotations

import math
import sys
import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TextIO

import structlog

from daemon.utc import utc_stamp

log = structlog.get_logger("daemon.server.stallstacks")

IDLE_S = 0.05
"""How often the watcher looks again while no sample is due (one stall is dumped once)."""


@dataclass(frozen=True)
class StallDump:
    """The dump taken during one lag sample."""

    sample: int
    loop_frame: str | None
    """The loop thread's most recent frame, ``file:line in function`` (the file without its
    folder), e.g. ``selectors.py:468 in select`` (still in its selector's wait)."""
    after_ms: float
    """How long past the sample's due time the stacks were taken."""


def place(frame: FrameType) -> str:
    """A frame as ``file:line in function``, the file without its folder."""
    return f"{Path(frame.f_code.co_filename).name}:{frame.f_lineno} in {frame.f_code.co_name}"


def format_dump(stacks: dict[int, traceback.StackSummary], loop_thread: int, header: str) -> str:
    """The fault handler's layout: a header, then each thread's frames most recent first."""
    lines = [header]
    for thread_id, stack in stacks.items():
        who = "Loop thread" if thread_id == loop_thread else "Thread"
        lines.append(f"{who} 0x{thread_id:016x} (most recent call first):")
        lines += [f'  File "{f.filename}", line {f.lineno} in {f.name}' for f in reversed(stack)]
        lines.append("")
    return "\n".join(lines) + "\n"


class StallStacks:
    """Appends every thread's stack to ``path`` while a lag sample of ``loop_thread`` is overdue.

    The loop calls :meth:`arm` at the start of each sample, :meth:`disarm` as soon as it is over
    and then :meth:`taken`; :meth:`start` and :meth:`stop` bracket the monitor's run."""

    def __init__(self, path: Path, loop_thread: int, clock: Callable[[], float]) -> None:
        self.path = path
        self.loop_thread = loop_thread
        self.clock = clock
        """The loop's clock (``loop.time``), which the samples' due times are on."""
        self._armed: tuple[int, float] = (0, math.inf)
        """(sample, due): replaced whole by the loop thread, read whole by the watcher."""
        self._taken: StallDump | None = None
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._file: TextIO | None = None

    def start(self) -> bool:
        """Open the file and start the watcher; False (logged) where the file cannot be written."""
        try:
            self._file = self.path.open("a")
        except OSError as exc:
            log.error("loop_stall_tracebacks_unwritable", path=str(self.path), error=str(exc))
            return False
        self._thread = threading.Thread(target=self._watch, name="loop-stall-stacks", daemon=True)
        self._thread.start()
        return True

    def arm(self, sample: int, due: float) -> None:
        """Sample ``sample`` is late once the clock passes ``due``."""
        self._armed = (sample, due)

    def disarm(self) -> None:
        """The sample armed last is over (its stall, if any, ended)."""
        self._armed = (0, math.inf)

    def taken(self, sample: int) -> StallDump | None:
        """The dump taken during ``sample``; None if none was (the watcher, itself waiting for a
        CPU or for the interpreter lock, had not taken it before the sample ended)."""
        taken = self._taken
        return taken if taken is not None and taken.sample == sample else None

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    def _watch(self) -> None:
        assert self._file is not None
        dumped = 0
        try:
            while not self._stopping.is_set():
                sample, due = self._armed
                wait = due - self.clock()
                if sample == dumped or wait > 0:
                    # Not yet due: look again at its due time. This stall already dumped, or no
                    # sample armed: look again a while on.
                    self._stopping.wait(IDLE_S if sample == dumped or math.isinf(wait) else wait)
                    continue
                frames = sys._current_frames()  # noqa: SLF001 - the interpreter's own snapshot, under its lock
                if self._armed[0] != sample:
                    continue  # the sample ended before the stacks were taken: they show the loop after it
                after_ms = round((self.clock() - due) * 1000, 1)
                loop_top = frames.get(self.loop_thread)
                # Kept first, in the few steps the lock allows before the loop's thread may take it
                # back and ask for this sample's dump.
                self._taken = StallDump(sample, place(loop_top) if loop_top is not None else None, after_ms)
                dumped = sample
                me = threading.get_ident()
                stacks = {tid: traceback.extract_stack(f) for tid, f in frames.items() if tid != me}
                del frames, loop_top
                self._file.write(format_dump(stacks, self.loop_thread,
                                             f"Loop stall at {utc_stamp()}: stacks taken {after_ms} ms past due"))
                self._file.flush()
        except OSError as exc:
            log.error("loop_stall_tracebacks_unwritable", path=str(self.path), error=str(exc))
        finally:
            self._file.close()
