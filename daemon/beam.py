"""Following the beam: the live encoder stream, the recorded trace, angle waits and predictions.

Every trigger of the capture rotation is timed from this stream, never from the plan alone: the
crossing time of a capture angle is extrapolated from the latest encoder sample, so a drive
that runs a little slow or fast still fires every camera at its angle.
"""

from __future__ import annotations

import asyncio
import math
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from daemon.errors import BeamTimeout

if TYPE_CHECKING:
    from drivers.motor.samples import BeamSample

log = structlog.get_logger("daemon.beam")


class BeamTracker:
    """Subscribes to ``drive.samples()`` and keeps the encoder trace of the current run.

    The trace is (time_s, angle_deg, speed_deg_s) per sample, the event-loop clock and the
    unwrapped beam angle; :meth:`mark` starts a fresh trace segment for each phase of a scan.
    """

    def __init__(self, drive: Any, *, name: str = "beam") -> None:
        self.drive = drive
        self.name = name
        self.latest: BeamSample | None = None
        self._times: list[float] = []
        self._angles: list[float] = []
        self._speeds: list[float] = []
        self._waiters: list[tuple[float, int, asyncio.Future[BeamSample]]] = []
        self._task: asyncio.Task[None] | None = None
        self._new_sample = asyncio.Event()

    async def start(self) -> None:
        if self.latest is None:
            self.latest = self.drive.latest
        if self._task is None:
            self._task = asyncio.create_task(self._follow(), name=f"{self.name}-tracker")
            await asyncio.sleep(0)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None

    async def _follow(self) -> None:
        async for sample in self.drive.samples():
            self.latest = sample
            self._times.append(sample.time_s)
            self._angles.append(sample.angle_deg)
            self._speeds.append(sample.speed_deg_s)
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
        return len(self._times)

    def trace(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(N, 3) float [time_s, angle_deg, speed_deg_s] of samples ``start:stop``."""
        sl = slice(start, stop)
        return np.column_stack(
            [np.asarray(self._times[sl]), np.asarray(self._angles[sl]), np.asarray(self._speeds[sl])]
        ).reshape(-1, 3)

    def angle_at(self, time_s: float | np.ndarray) -> float | np.ndarray:
        """Beam angle (deg) at event-loop time(s), linear between encoder samples."""
        return np.interp(time_s, self._times, self._angles)

    def speed_at(self, time_s: float | np.ndarray) -> float | np.ndarray:
        """Beam speed (deg/s) at event-loop time(s), linear between encoder samples."""
        return np.interp(time_s, self._times, self._speeds)

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
            return await asyncio.wait_for(future, timeout_s)
        except TimeoutError as exc:
            raise BeamTimeout(self.name, angle_deg, self.angle_deg, timeout_s) from exc
