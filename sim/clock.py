"""Virtual time for simulated scans: an asyncio event loop whose clock jumps when every task waits.

The daemon, the drivers and the in-process simulators read time only through the event loop
(``loop.time()``, ``asyncio.sleep``, ``asyncio.timeout``). Run them on a :class:`VirtualTimeLoop`
and a whole scan happens in simulated time: whenever nothing is ready to run and no byte is waiting
to be read, the clock jumps straight to the next timer. The order of events then depends only on
the simulated timeline, never on how fast or loaded the machine is, so the same seed gives the
same scan (the approach of Klipper's batch mode and ophyd-async's simulated runs).

Two things stop the clock instead of advancing it:

* a job handed to ``run_in_executor`` (ray casting, TSDF, planning): simulated time stands still
  until it finishes, so its real duration never leaks into the timeline;
* nothing scheduled at all: the loop then waits for real I/O (a control-socket client, say).

With ``time_scale`` set, the jumps are paced (:class:`Pace`) so that virtual time runs at
``time_scale`` times real time, and a person can watch a simulated scan at, for example, 10x real
time; the timeline is the same either way.
"""

from __future__ import annotations

import asyncio
import selectors
import time
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


class VirtualTimeStall(RuntimeError):
    """Every task waits, no timer is scheduled and no real I/O arrived within the idle limit."""


class TasksLeftPending(RuntimeError):
    """The main coroutine returned while tasks it started were still pending (a leak: a
    device stream, a watchdog or a worker nobody stopped)."""

    def __init__(self, names: list[str]) -> None:
        self.names = names
        super().__init__(f"{len(names)} task(s) still pending when the run ended: {', '.join(names)}")


class Pace:
    """When, in real time, each jump of a paced virtual clock is due (``time_scale`` virtual
    seconds per real second).

    The due times run on from one jump to the next, so a jump shorter than the selector's
    resolution (epoll waits whole milliseconds: a 0.1 ms jump would cost 1 ms, and a scan's
    200 Hz position samples and heartbeats make thousands of such jumps a virtual second) is
    made up by the jumps after it instead of slowing the clock. A loop that falls further than
    ``slack_s`` behind (it cannot keep up, or the clock stood still for a compute job) is paced
    from then on: it never races to catch up.
    """

    def __init__(self, time_scale: float, slack_s: float = 0.05) -> None:
        self.time_scale = time_scale
        self.slack_s = slack_s
        self._due: float | None = None

    def wait(self, jump_s: float, now: float) -> float:
        """Real seconds to wait at real time ``now`` before a jump of ``jump_s`` virtual seconds."""
        if self._due is None or now - self._due > self.slack_s:
            self._due = now
        self._due += jump_s / self.time_scale
        return max(0.0, self._due - now)

    def restart(self, now: float | None = None) -> None:
        """Pace the next jump from ``now`` (None: from the next jump's own start): real I/O
        ended a wait early, or the clock stood still."""
        self._due = now


class _PacedSelector:
    """Wraps the loop's selector: polls real I/O, then advances virtual time instead of sleeping."""

    def __init__(self, real: selectors.BaseSelector, loop: VirtualTimeLoop) -> None:
        self._real = real
        self._loop = loop

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        events = self._real.select(0)
        if events or timeout == 0:
            return events
        loop = self._loop
        pace = loop.pace
        if loop.pending_jobs:
            if pace is not None:
                pace.restart()
            return self._real.select(None)
        if timeout is None:
            if pace is not None:
                pace.restart()
            events = self._real.select(loop.idle_real_timeout)
            if not events and loop.idle_real_timeout is not None:
                raise VirtualTimeStall(
                    f"virtual time stalled at t={loop.time():.6f} s: every task waits, no timer is "
                    f"scheduled and no I/O arrived within {loop.idle_real_timeout:g} s"
                )
            return events
        if pace is None:
            loop.advance(timeout)
            return []
        started = time.monotonic()
        wait = pace.wait(timeout, started)
        events = self._real.select(wait) if wait > 0 else []
        if events:
            ended = time.monotonic()
            loop.advance(min(timeout, (ended - started) * pace.time_scale))
            pace.restart(ended)
        else:
            loop.advance(timeout)
        return events


class VirtualTimeLoop(asyncio.SelectorEventLoop):
    """A selector event loop on a virtual clock (seconds, starting at ``start``).

    ``compute_stops_clock``: jobs in the executor take no virtual time (a scan report adds their
    measured compute time back where it reports wall durations).

    Args:
        time_scale: None runs as fast as possible; X paces virtual time at X times real time.
        start: the virtual clock's reading when the loop is created, s.
        idle_real_timeout: with nothing scheduled, how long (real s) to wait for outside I/O before
            raising :class:`VirtualTimeStall`; None waits for ever (a daemon waiting for commands).
    """

    compute_stops_clock = True
    pace: Pace | None
    """How jumps are paced in real time (None: not at all); follows :attr:`time_scale`."""

    def __init__(
        self,
        *,
        time_scale: float | None = None,
        start: float = 0.0,
        idle_real_timeout: float | None = None,
    ) -> None:
        super().__init__()
        if time_scale is not None and not time_scale > 0:
            self.close()
            raise ValueError(f"time_scale must be positive or None, got {time_scale!r}")
        self.time_scale = time_scale
        self.idle_real_timeout = idle_real_timeout
        self.pending_jobs = 0
        self._now = float(start)
        self._selector = _PacedSelector(self._selector, self)  # type: ignore[has-type]

    @property
    def time_scale(self) -> float | None:
        """Virtual seconds per real second (None: as fast as possible); may change while running."""
        return None if self.pace is None else self.pace.time_scale

    @time_scale.setter
    def time_scale(self, scale: float | None) -> None:
        self.pace = None if scale is None else Pace(scale)

    def time(self) -> float:
        return self._now

    def advance(self, seconds: float) -> None:
        """Move the virtual clock forward (never back)."""
        if seconds > 0:
            self._now += seconds

    def run_in_executor(self, executor: Any, func: Any, *args: Any) -> asyncio.Future[Any]:
        future = super().run_in_executor(executor, func, *args)
        self.pending_jobs += 1
        future.add_done_callback(self._job_done)
        return future

    def _job_done(self, _future: asyncio.Future[Any]) -> None:
        self.pending_jobs -= 1


def run_virtual(
    coro: Coroutine[Any, Any, T],
    *,
    time_scale: float | None = None,
    idle_real_timeout: float | None = None,
    debug: bool | None = None,
) -> T:
    """Run a coroutine to completion on a fresh :class:`VirtualTimeLoop` (like ``asyncio.run``).

    Raises :class:`TasksLeftPending`, naming them, if the coroutine returns while tasks it
    started are still pending (they are cancelled first, as ``asyncio.run`` would). A task
    nothing refers to any more may be collected before that check; asyncio then logs "Task
    was destroyed but it is pending".
    """
    with asyncio.Runner(
        debug=debug,
        loop_factory=lambda: VirtualTimeLoop(
            time_scale=time_scale, idle_real_timeout=idle_real_timeout
        ),
    ) as runner:
        return runner.run(_no_task_left(coro))


async def _no_task_left(coro: Coroutine[Any, Any, T]) -> T:
    result = await coro
    await asyncio.sleep(0)  # callbacks of tasks that have just finished run
    this = asyncio.current_task()
    pending = sorted((t for t in asyncio.all_tasks() if t is not this and not t.done()),
                     key=lambda t: t.get_name())
    if pending:
        names = [f"{t.get_name()} ({_what(t)})" for t in pending]
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)
        raise TasksLeftPending(names)
    return result


def _what(task: asyncio.Task[Any]) -> str:
    """What a task runs: the coroutine's name, or the closing of an async generator that was
    dropped without ``aclose()`` (``async for ... break`` without ``contextlib.aclosing``)."""
    coro = task.get_coro()
    name = getattr(coro, "__qualname__", None)
    return name if name else f"{type(coro).__name__}: an async generator closed by the garbage collector"
