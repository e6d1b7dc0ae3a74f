"""Beam position samples and the per-subscriber streams that carry them."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass


@dataclass(frozen=True)
class BeamSample:
    """One position report of the beam.

    Attributes:
        time_s: event-loop clock when the TPDO arrived, s.
        angle_deg: beam angle, continuous (not wrapped), deg.
        speed_deg_s: beam speed (velocity actual of the same TPDO), deg/s.
        statusword: the latest statusword (0x6041).
    """

    time_s: float
    angle_deg: float
    speed_deg_s: float
    statusword: int


_END = object()


class SampleStream:
    """One subscriber's queue of :class:`BeamSample`; drops the oldest sample when full, so a
    slow reader always gets the newest positions. Ends (StopAsyncIteration) after :meth:`end`.

    Args:
        subscribers: the publisher's set of live streams; the stream adds itself and leaves it
            when it ends or is closed.
        maxsize: queue length in samples.
    """

    def __init__(self, subscribers: set[SampleStream], maxsize: int) -> None:
        self._subscribers = subscribers
        self._queue: asyncio.Queue[object] = asyncio.Queue(maxsize)
        self.dropped = 0
        subscribers.add(self)

    def put(self, sample: BeamSample) -> None:
        self._put(sample)

    def end(self) -> None:
        """No more samples: the reader stops after the queued ones."""
        self._put(_END)

    def _put(self, item: object) -> None:
        if self._queue.full():
            self._queue.get_nowait()
            self.dropped += 1
        self._queue.put_nowait(item)

    def __aiter__(self) -> SampleStream:
        return self

    async def __anext__(self) -> BeamSample:
        item = await self._queue.get()
        if item is _END:
            self._subscribers.discard(self)
            raise StopAsyncIteration
        return item  # type: ignore[return-value]

    async def aclose(self) -> None:
        self._subscribers.discard(self)
