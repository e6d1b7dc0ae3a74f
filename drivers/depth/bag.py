"""Playback of RealSense ``.bag`` recordings through the DepthCamera interface.

The recording is replayed with real time off: librealsense reads the next frame only when the
previous one has been handed over, and the hand-over waits for room in the frame queue, so a
slow consumer (fusion) loses no frame and a fast one is not held to the recording's pace.
Frame times keep the recording's own spacing: the device timestamps are moved onto the
event-loop clock by one offset taken at the first frame. ``frames()`` ends at the end of the file.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from pathlib import Path
from types import ModuleType
from typing import Any

from drivers.depth.errors import DepthCameraError
from drivers.depth.realsense import END_OF_STREAM, RawFrame, RealSenseStream


class BagPlayback(RealSenseStream):
    """Depth frames from a ``.bag`` file, as fast as the consumer takes them (``realtime=False``).

    Args:
        path: the recording.
        camera_id: the rig camera the recording stands in for (names frames and errors).
        realtime: replay at the recorded pace instead (frames a slow consumer misses are dropped).
    """

    HAND_OVER_POLL_S = 0.5  # how often a waiting hand-over checks whether the stream was stopped

    def __init__(self, path: Path | str, *, camera_id: str, realtime: bool = False) -> None:
        super().__init__(camera_id)
        self.path = Path(path)
        self.realtime = realtime
        self._offset_s: float | None = None
        self._ended: list[asyncio.Task[None]] = []

    def _configure(self, rs: ModuleType) -> tuple[Any, Any]:
        if not self.path.is_file():
            raise DepthCameraError(self.id, f"no recording at {self.path}")
        config = rs.config()
        config.enable_device_from_file(str(self.path), False)  # no repeat: the file ends
        config.enable_stream(rs.stream.depth)
        self._offset_s = None
        return rs.pipeline(), config

    def _started(self, profile: Any) -> None:
        playback = profile.get_device().as_playback()
        playback.set_real_time(self.realtime)
        playback.set_status_changed_callback(self._on_status)

    def _host_time(self, device_ms: float, arrival_s: float) -> float:
        if self._offset_s is None:
            self._offset_s = arrival_s - device_ms / 1000.0
        return device_ms / 1000.0 + self._offset_s

    def _hand_over(self, loop: asyncio.AbstractEventLoop, raw: RawFrame) -> None:
        """From the SDK thread: block until the frame is queued (back-pressure on the file reader)."""
        if self.realtime:
            super()._hand_over(loop, raw)
            return
        try:
            queued = asyncio.run_coroutine_threadsafe(self._offer(raw), loop)
        except RuntimeError:  # the loop is closed: nobody will read this frame
            return
        while True:
            try:
                queued.result(timeout=self.HAND_OVER_POLL_S)
                return
            except concurrent.futures.TimeoutError:
                if self._stopping:
                    queued.cancel()
                    return

    async def _offer(self, raw: RawFrame) -> None:
        if self._stopping or self._queue is None:
            return
        if self.depth_unit_mm is None or self.intrinsics is None:
            self._early.append(raw)
            return
        await self._queue.put(self._frame(raw, self.depth_unit_mm, self.intrinsics))

    def _on_status(self, status: Any) -> None:
        """SDK thread: the file reached its end -> frames() ends after the frames already queued."""
        loop = self._loop
        if loop is not None and getattr(status, "name", str(status)).endswith("stopped"):
            loop.call_soon_threadsafe(self._end_of_file)

    async def stop(self) -> None:
        """Stop playback and release the file (idempotent)."""
        for task in self._ended:
            task.cancel()
        self._ended.clear()
        await super().stop()

    def _end_of_file(self) -> None:
        if self._queue is not None and not self._stopping:
            self._ended.append(asyncio.get_running_loop().create_task(self._queue.put(END_OF_STREAM)))
