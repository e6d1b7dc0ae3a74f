"""How late the event loop runs, per scan state: the daemon's real-time budget, measured.

The drive's heartbeat (100 ms, lost after 300 ms) and the panel's are produced on the event
loop, so anything that holds the loop (compute on its interpreter lock, a large write, an
fsync) shows here first. A sleep of ``period_s`` that wakes late by more than ``warn_s`` is
logged as ``loop_lag`` with the state it happened in; leaving a state logs that state's
``loop_lag_summary`` (samples, p50, p99, max); ``tbp status`` shows the same per state. A
``loop_lag`` line says why the loop was late: ``cpu_ms`` the loop thread ran meanwhile (code
on the loop), ``runqueue_ms`` it waited for a CPU (the machine was busy: the process was not
scheduled), neither (it was blocked: a system call, or waiting for the interpreter lock a thread
held), and ``process_cpu_ms`` the daemon's threads ran together (a thread computing while holding
the interpreter lock holds the loop too). For a blocked loop the machine's side is given too:
``pressure_ms``, how long some task on the machine waited for a CPU meanwhile (the kernel's CPU
pressure; a thread holding the interpreter lock may have been one), and ``steal_ms``, CPU time
the hypervisor gave elsewhere (summed over the CPUs). A garbage collection that long is logged
as ``gc_pause``.

Where the time went is only visible during the stall. With ``TBP_LOOP_STALL_TRACEBACKS=FILE`` in
the daemon's environment (a diagnostic for engineers), a stall past ``warn_s`` appends every
thread's stack to FILE, taken while the loop is still held, under the interpreter lock
(daemon/server/stallstacks.py); the ``loop_lag`` line names the file, says as ``loop_frame``
where the loop thread was (``selectors.py:468 in select``: still in its selector's wait, its
timer due ``warn_s`` before) and as ``stacks_after_ms`` how long past due the stacks were taken
(long when a thread held the interpreter lock in C code).
"""

from __future__ import annotations

import asyncio
import gc
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import structlog

from daemon.server.stallstacks import StallStacks

log = structlog.get_logger("daemon.server.looplag")

WARN_S = 0.05
"""A wake this late is logged as ``loop_lag`` (and a collection this long as ``gc_pause``)."""


def freeze_startup_heap() -> int:
    """Move every object alive now (modules, classes, drivers, the rig) out of the collector's
    reach; returns how many. Call once the daemon is built, before it serves.

    A full (generation 2) collection walks every tracked object, and the daemon's imports alone
    are 80,000 to 140,000: about 20 ms on a quiet core, measured at 67-178 ms with the other core busy,
    on the loop, at whatever moment allocation tips the threshold (a capture, a heartbeat). What
    lives from the start lives until the end, so collecting it is wasted work: frozen, a full
    collection walks only what scans made since.
    """
    gc.collect()
    gc.freeze()
    frozen = gc.get_freeze_count()
    log.info("startup_heap_frozen", objects=frozen)
    return frozen


def _open_kernel_file(path: str) -> int | None:
    """A descriptor on a /proc file, re-read with pread at each sample; None where the kernel has none."""
    try:
        return os.open(path, os.O_RDONLY)
    except OSError:
        return None


class ThreadTimes:
    """The calling thread's CPU time and time spent waiting for a CPU (s), from the kernel's
    /proc/thread-self/schedstat; the wait is None where the kernel does not report it."""

    def __init__(self) -> None:
        self._fd = _open_kernel_file("/proc/thread-self/schedstat")

    def read(self) -> tuple[float, float | None]:
        if self._fd is not None:
            try:
                cpu_ns, wait_ns, _ = os.pread(self._fd, 128, 0).split()
                return int(cpu_ns) / 1e9, int(wait_ns) / 1e9
            except (OSError, ValueError):
                pass
        return time.thread_time(), None

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class MachineTimes:
    """The machine's CPU contention so far (s): time some task waited for a CPU (the kernel's
    /proc/pressure/cpu ``some`` total) and CPU time stolen by the hypervisor (/proc/stat, all
    CPUs); each None where the kernel does not report it."""

    def __init__(self) -> None:
        self._tick_s = 1.0 / os.sysconf("SC_CLK_TCK")
        self._pressure = _open_kernel_file("/proc/pressure/cpu")
        self._stat = _open_kernel_file("/proc/stat")

    def read(self) -> tuple[float | None, float | None]:
        pressure = steal = None
        try:
            if self._pressure is not None:
                some = os.pread(self._pressure, 256, 0).split(b"\n", 1)[0]
                pressure = int(some.rsplit(b"total=", 1)[1]) / 1e6
            if self._stat is not None:
                fields = os.pread(self._stat, 256, 0).split(b"\n", 1)[0].split()
                steal = int(fields[8]) * self._tick_s if fields[0] == b"cpu" and len(fields) > 8 else None
        except (OSError, ValueError, IndexError):
            pass
        return pressure, steal

    def close(self) -> None:
        for fd in (self._pressure, self._stat):
            if fd is not None:
                os.close(fd)
        self._pressure = self._stat = None


def _ms_between(before: float | None, after: float | None) -> float | None:
    return None if before is None or after is None else round((after - before) * 1000, 1)


@dataclass
class StateLag:
    """Lag samples (s) of one state as a histogram on a geometric scale (bins 5 % wide from
    50 us to 20 s): constant memory however long the state lasts, and a summary that costs
    no more than the bins, cheap enough for every ``tbp status``. Percentiles are the upper
    edge of the bin holding them (at most 5 % high), never above the exact maximum."""

    FLOOR_S = 5e-5
    RATIO = 1.05
    BINS = 270  # FLOOR_S * RATIO ** BINS is about 25 s

    counts: list[int] = field(default_factory=lambda: [0] * (StateLag.BINS + 1))
    count: int = 0
    max_s: float = 0.0

    def add(self, lag_s: float) -> None:
        self.count += 1
        self.max_s = max(self.max_s, lag_s)
        index = 0 if lag_s <= self.FLOOR_S else 1 + int(math.log(lag_s / self.FLOOR_S) / math.log(self.RATIO))
        self.counts[min(index, self.BINS)] += 1

    def percentile_s(self, q: float) -> float:
        """The q-quantile (0 < q <= 1, nearest rank), as its bin's upper edge capped at the maximum."""
        rank = max(1, math.ceil(q * self.count))
        seen = 0
        for index, n in enumerate(self.counts):
            seen += n
            if seen >= rank:
                return min(self.FLOOR_S * self.RATIO ** index, self.max_s)
        return self.max_s

    def summary(self) -> dict[str, float | int]:
        return {"samples": self.count, "p50_ms": round(self.percentile_s(0.5) * 1000, 2),
                "p99_ms": round(self.percentile_s(0.99) * 1000, 2), "max_ms": round(self.max_s * 1000, 2)}


class LoopLagMonitor:
    """Samples the loop's lateness every ``period_s`` under the state ``state()`` names."""

    def __init__(self, state: Callable[[], str], *, period_s: float = 0.01, warn_s: float = WARN_S,
                 tracebacks: Path | None = None) -> None:
        self.state = state
        self.period_s = period_s
        self.warn_s = warn_s
        self.tracebacks = tracebacks
        """Where every thread's stack is appended during a stall past ``warn_s`` (None: nowhere)."""
        self.last_s = 0.0
        self.worst_since_s = 0.0
        """The worst lag since :meth:`take_worst` last ran (the watchdog's view between two pings)."""
        self.by_state: dict[str, StateLag] = {}
        self._current: str | None = None
        self._gc_started = 0.0

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        gc.callbacks.append(self._collection)
        times, machine = ThreadTimes(), MachineTimes()
        stacks = None
        if self.tracebacks is not None:
            stacks = StallStacks(self.tracebacks, threading.get_ident(), loop.time)
            if not stacks.start():
                stacks = None
        sample = 0
        try:
            while True:
                sample += 1
                before, (cpu0, wait0), (pressure0, steal0) = loop.time(), times.read(), machine.read()
                process0 = time.process_time()
                if stacks is not None:
                    stacks.arm(sample, before + self.period_s + self.warn_s)
                await asyncio.sleep(self.period_s)
                if stacks is not None:
                    stacks.disarm()
                lag_s = max(loop.time() - before - self.period_s, 0.0)
                if lag_s > self.warn_s:
                    (cpu1, wait1), (pressure1, steal1) = times.read(), machine.read()
                    process1 = time.process_time()
                    where: dict[str, str | float | None] = {}
                    if stacks is not None:
                        dump = stacks.taken(sample)
                        where = {"tracebacks": str(self.tracebacks), "loop_frame": None}
                        if dump is not None:
                            where.update(loop_frame=dump.loop_frame, stacks_after_ms=dump.after_ms)
                    self.record(self.state(), lag_s, cpu_ms=_ms_between(cpu0, cpu1),
                                runqueue_ms=_ms_between(wait0, wait1), process_cpu_ms=_ms_between(process0, process1),
                                pressure_ms=_ms_between(pressure0, pressure1), steal_ms=_ms_between(steal0, steal1),
                                **where)
                else:
                    self.record(self.state(), lag_s)
        finally:
            if stacks is not None:
                stacks.stop()
            times.close()
            machine.close()
            gc.callbacks.remove(self._collection)

    def _collection(self, phase: str, info: dict[str, int]) -> None:
        """gc callback: a collection that holds the loop longer than ``warn_s`` is logged as
        ``gc_pause`` (generation, objects collected), so a ``loop_lag`` can be told from it."""
        now = time.perf_counter()
        if phase == "start":
            self._gc_started = now
            return
        held = now - self._gc_started
        if held > self.warn_s:
            log.warning("gc_pause", lag_state=self.state(), generation=info.get("generation"),
                        collected=info.get("collected"), pause_ms=round(held * 1000, 1))

    def record(self, state: str, lag_s: float, **why: float | str | None) -> None:
        if state != self._current:
            if self._current is not None and self._current in self.by_state:
                log.info("loop_lag_summary", lag_state=self._current, **self.by_state[self._current].summary())
            self._current = state
        self.last_s = lag_s
        self.worst_since_s = max(self.worst_since_s, lag_s)
        self.by_state.setdefault(state, StateLag()).add(lag_s)
        if lag_s > self.warn_s:
            log.warning("loop_lag", lag_state=state, lag_ms=round(lag_s * 1000, 1), **why)

    def take_worst(self) -> float:
        """The worst lag since the last call (s); starts the next interval."""
        worst, self.worst_since_s = self.worst_since_s, 0.0
        return worst

    def summary(self) -> dict[str, dict[str, float | int]]:
        return {state: lag.summary() for state, lag in self.by_state.items()}
