"""Following the beam: the live encoder stream, the recorded trace, angle waits and predictions.

Every trigger of the capture rotation is timed from this stream, never from the plan alone: the
crossing time of a capture angle is extrapolated from the latest encoder sample, so a drive
that runs a little slow or fast still fires every camera at its angle.
"""

from __future__ import annotations

import asyncio
import math
from typing import TYPE_CHECKING

import numpy as np
import structlog

from daemon.errors import BeamTimeout
from daemon.rig.devices import Drive

if TYPE_CHECKING:
    from drivers.motor.samples import BeamSample
    from planner.rig import Rig

log = structlog.get_logger("daemon.rig.beam")


TRACE_KEPT_S = 3600.0
"""The tracker keeps the last hour of encoder samples: every scan's trace, bounded memory."""


def trace_capacity(rig: Rig) -> int:
    """Rows of encoder trace the tracker keeps for ``rig``'s position rate (:data:`TRACE_KEPT_S`)."""
    return max(2, int(rig.motor.position_rate_hz * TRACE_KEPT_S))


class TraceBuffer:
    """The encoder trace as rows (time_s, angle_deg, speed_deg_s) in a NumPy array, bounded.

    The drive sends its position at ``position_rate_hz`` (200 Hz) whether or not the beam moves,
    for as long as the service runs: a Python list would grow by gigabytes a day and hand every
    lookup an O(n) conversion. Rows are numbered from the service's start (:attr:`end`); only the
    newest ``capacity`` rows are kept (:func:`trace_capacity`: an hour, far longer than a scan), so once
    the array is full the older half is dropped in one copy.
    """

    def __init__(self, capacity: int = 1 << 19) -> None:
        if capacity < 2:
            raise ValueError(f"trace capacity must be at least 2 rows, got {capacity}")
        self.capacity = capacity
        self._rows = np.empty((min(capacity, 4096), 3))
        self._first = 0  # number of the oldest kept row
        self._count = 0  # rows kept

    @property
    def end(self) -> int:
        """Number of the next row (rows appended since the start)."""
        return self._first + self._count

    @property
    def first(self) -> int:
        """Number of the oldest row still kept."""
        return self._first

    def append(self, time_s: float, angle_deg: float, speed_deg_s: float) -> None:
        if self._count == len(self._rows):
            if len(self._rows) < self.capacity:  # grow by doubling up to the capacity
                grown = np.empty((min(2 * len(self._rows), self.capacity), 3))
                grown[: self._count] = self._rows[: self._count]
                self._rows = grown
            else:  # full: keep the newer half
                drop = self._count // 2
                self._rows[: self._count - drop] = self._rows[drop: self._count]
                self._first += drop
                self._count -= drop
        self._rows[self._count] = (time_s, angle_deg, speed_deg_s)
        self._count += 1

    def rows(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(N, 3) copy of rows ``start:stop`` (row numbers; rows already dropped are not returned)."""
        stop = self.end if stop is None else min(stop, self.end)
        lo, hi = max(start, self._first) - self._first, max(stop, self._first) - self._first
        return self._rows[lo:max(lo, hi)].copy()

    def interpolate(self, time_s: float | np.ndarray, column: int) -> float | np.ndarray:
        """``column`` (1 angle, 2 speed) at time(s) ``time_s``, linear between rows; the first or
        last kept value outside them. O(log n): only the rows around the asked times are read."""
        times = self._rows[: self._count, 0]
        if self._count == 0:
            raise ValueError("the encoder trace is empty")
        t = np.asarray(time_s, dtype=float)
        lo = max(int(np.searchsorted(times, np.min(t), "right")) - 1, 0)
        hi = min(int(np.searchsorted(times, np.max(t), "left")) + 1, self._count)
        return np.interp(time_s, times[lo:hi], self._rows[lo:hi, column])


class BeamTracker:
    """Follows a drive's encoder (``drive.samples()``, from :meth:`start`) and keeps the encoder
    trace of the current run.

    The trace is (time_s, angle_deg, speed_deg_s) per sample, the event-loop clock and the
    unwrapped beam angle (:class:`TraceBuffer`); :meth:`mark` starts a fresh trace segment for
    each phase of a scan.
    """

    def __init__(self, *, name: str = "beam", capacity: int = 1 << 19) -> None:
        self.name = name
        self.latest: BeamSample | None = None
        self._trace = TraceBuffer(capacity)
        self._waiters: list[tuple[float, int, asyncio.Future[BeamSample]]] = []
        self._task: asyncio.Task[None] | None = None
        self._new_sample = asyncio.Event()

    async def start(self, drive: Drive) -> None:
        """Follow ``drive``'s encoder (until :meth:`stop`; a renewed drive is followed anew)."""
        if self.latest is None:
            self.latest = drive.latest
        if self._task is None:
            self._task = asyncio.create_task(self._follow(drive), name=f"{self.name}-tracker")
            await asyncio.sleep(0)

    @property
    def following(self) -> bool:
        """The encoder stream is being followed."""
        return self._task is not None and not self._task.done()

    STOP_TIMEOUT_S = 1.0

    async def stop(self) -> None:
        """Stop following (a cancel of the caller is not swallowed; the follower gets a bound)."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            await asyncio.wait([task], timeout=self.STOP_TIMEOUT_S)

    async def _follow(self, drive: Drive) -> None:
        async for sample in drive.samples():
            self.latest = sample
            self._trace.append(sample.time_s, sample.angle_deg, sample.speed_deg_s)
            self._new_sample.set()
            if self._waiters:
                self._resolve(sample)

    def _resolve(self, sample: BeamSample) -> None:
        keep = []
        for angle, direction, future in self._waiters:
            if future.done():
                continue
            if (sample.angle_deg - angle) * direction >= 0:
                future.set_result(sample)
            else:
                keep.append((angle, direction, future))
        self._waiters = keep

    # ------------------------------------------------------------------ trace

    def mark(self) -> int:
        """Index of the next sample: slice the trace from here with :meth:`trace`."""
        return self._trace.end

    def trace(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(N, 3) float [time_s, angle_deg, speed_deg_s] of samples ``start:stop``."""
        return self._trace.rows(start, stop)

    def angle_at(self, time_s: float | np.ndarray) -> float | np.ndarray:
        """Beam angle (deg) at event-loop time(s), linear between encoder samples."""
        return self._trace.interpolate(time_s, 1)

    def speed_at(self, time_s: float | np.ndarray) -> float | np.ndarray:
        """Beam speed (deg/s) at event-loop time(s), linear between encoder samples."""
        return self._trace.interpolate(time_s, 2)

    # ------------------------------------------------------------------ live

    @property
    def angle_deg(self) -> float | None:
        return None if self.latest is None else self.latest.angle_deg

    def predict_crossing(self, angle_deg: float) -> float:
        """Event-loop time (s) the beam reaches ``angle_deg`` at the latest measured speed.

        inf when the beam is still or moving away from the angle.
        """
        sample = self.latest
        if sample is None:
            return math.inf
        delta = angle_deg - sample.angle_deg
        if delta == 0:
            return sample.time_s
        if sample.speed_deg_s == 0 or delta * sample.speed_deg_s < 0:
            return math.inf
        return sample.time_s + delta / sample.speed_deg_s

    async def next_sample(self) -> BeamSample:
        self._new_sample.clear()
        await self._new_sample.wait()
        assert self.latest is not None
        return self.latest

    async def wait_angle(self, angle_deg: float, timeout_s: float, *, direction: int = 1) -> BeamSample:
        """Wait for the first sample at or past ``angle_deg`` in ``direction`` (+1 or -1)."""
        sample = self.latest
        if sample is not None and (sample.angle_deg - angle_deg) * direction >= 0:
            return sample
        future: asyncio.Future[BeamSample] = asyncio.get_running_loop().create_future()
        self._waiters.append((angle_deg, direction, future))
        try:
            async with asyncio.timeout(timeout_s):  # a cancel landing with the sample still cancels
                return await future
        except TimeoutError as exc:
            raise BeamTimeout(self.name, angle_deg, self.angle_deg, timeout_s) from exc
        finally:
            future.cancel()


async def rebase_angle(tracker: BeamTracker, drive: Drive, near_deg: float) -> None:
    """Renumber the resting beam's angle by whole turns to within half a turn of ``near_deg``."""
    angle = tracker.angle_deg
    if angle is None:
        angle = (await tracker.next_sample()).angle_deg
    turns = round((angle - near_deg) / 360.0)
    if turns:
        await drive.set_zero(angle - 360.0 * turns)
