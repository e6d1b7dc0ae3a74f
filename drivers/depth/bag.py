"""Playback of RealSense recordings (``.db3``, legacy ``.bag``) through the DepthCamera interface.

The file is opened as a playback device and its depth sensor streamed directly (a pipeline's
frame syncer holds frames back, which stalls a playback with real time off after two frames).
With real time off librealsense reads the next frame only when the previous one has been handed
over, and the hand-over waits for room in the frame queue, so a slow consumer (fusion) loses no
frame and a fast one is not held to the recording's pace. Frame times keep the recording's own
spacing: the device timestamps are moved onto the event-loop clock by one offset taken at the
first frame. ``frames()`` ends at the end of the file.

A sweep recording has a beam-angle file beside it (``drivers.depth.beam_angles``): every frame
then carries the angle it was recorded at in ``DepthFrame.beam_angle_deg``. A sweep recording holds
depth only: with ``infrared`` on, ``start()`` raises InfraredUnavailable.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from drivers.depth.base import DepthSource
from drivers.depth.beam_angles import BeamAngles, beam_angles_path, read_beam_angles
from drivers.depth.errors import InfraredUnavailable, RecordingUnreadable
from drivers.depth.realsense import END_OF_STREAM, Opened, RawFrame, RealSenseStream, import_pyrealsense2
from planner.rig import DepthCamera as DepthCameraConfig
from planner.rig import DepthCameraModel


class BagPlayback(RealSenseStream):
    """Depth frames from a RealSense recording, replayed from its start at every ``start()``.

    Args:
        path: the recording (``.db3``; ``.bag`` from SDKs before 2.58 plays too).
        camera_id: the rig camera the recording stands in for (names frames and errors).
        realtime: replay at the recorded pace (frames a slow consumer misses are dropped) instead
            of as fast as the consumer takes them. Default (None): at the recorded pace only when
            the recording has no beam-angle file, since its frames must then be tagged with the
            live encoder and so arrive in step with the beam.
    """

    HAND_OVER_POLL_S = 0.5  # how often a waiting hand-over checks whether the stream was stopped

    def __init__(self, path: Path | str, *, camera_id: str, realtime: bool | None = None) -> None:
        super().__init__(camera_id)
        self.path = Path(path)
        self.requested_realtime = realtime
        self.realtime = bool(realtime)
        self.beam_angles: BeamAngles | None = None
        self._offset_s: float | None = None
        self._ended: list[asyncio.Task[None]] = []
        self._playing = 0  # which start() the SDK's status callbacks belong to

    @classmethod
    def for_source(cls, camera: DepthCameraConfig, source: DepthSource, model: DepthCameraModel) -> BagPlayback:
        """The rig camera ``camera`` played from the hardware file's recording (the ``recording``
        kind; its pace follows the recording's beam-angle file)."""
        if source.path is None:
            raise RecordingUnreadable(camera.id, "-", "the hardware file names no recording")
        return cls(source.path, camera_id=camera.id)

    async def start(self) -> None:
        """Replay the recording from its start; InfraredUnavailable with ``infrared`` on (a depth
        sweep's recording has no infrared stream)."""
        if self.infrared:
            raise InfraredUnavailable(self.id, f"the recording {self.path} holds depth only")
        # A new generation before anything else: an end-of-file report of the previous start that
        # reaches the loop while this start opens the file is then recognised as stale.
        self._playing += 1
        await super().start()

    def _open(self, rs: ModuleType, on_frame: Callable[[Any], None]) -> Opened:
        if not self.path.is_file():
            raise RecordingUnreadable(self.id, self.path, "no recording at this path")
        angles_file = beam_angles_path(self.path)
        self.beam_angles = read_beam_angles(angles_file, self.id) if angles_file.is_file() else None
        self.realtime = self.beam_angles is None if self.requested_realtime is None else self.requested_realtime
        self._offset_s = None
        context = self._sdk_context(rs)
        try:
            playback = context.load_device(str(self.path))
        except RuntimeError as exc:
            raise RecordingUnreadable(self.id, self.path, f"not a RealSense recording: {exc}") from exc
        playback.set_real_time(self.realtime)
        playing = self._playing
        playback.set_status_changed_callback(lambda status: self._on_status(status, playing))
        sensor = playback.first_depth_sensor()
        profiles = [p for p in sensor.get_stream_profiles()
                    if p.stream_type() == rs.stream.depth and p.format() == rs.format.z16]
        if not profiles:
            raise RecordingUnreadable(self.id, self.path, "the recording holds no Z16 depth stream")
        sensor.open(profiles[0])
        sensor.start(on_frame)

        def close() -> None:
            # The playback object lives until here (dropping it drops its end-of-file callback).
            # Pausing first lets the SDK's reader thread finish its queued reads: a playback device
            # destroyed with a read still queued aborts the process (librealsense 2.59,
            # "pure virtual method called" on the reader thread).
            playback.pause()
            sensor.stop()
            sensor.close()
            playback.set_status_changed_callback(lambda _status: None)
            context.unload_device(str(self.path))

        return Opened(sensor, profiles[0], close)

    def _recorded_angle(self, frame_number: int, device_ms: float) -> float | None:
        if self.beam_angles is None:
            return None
        return self.beam_angles.angle_of(beam_angles_path(self.path), frame_number, device_ms)

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
        # A frame read before start() knows the scale and intrinsics waits for them here, holding
        # the reader back: set aside, it would let the reader run ahead and overflow the queue.
        await self._described.wait()
        if self._stopping or self._queue is None or self.depth_unit_mm is None or self.intrinsics is None:
            return
        await self._queue.put(self._frame(raw, self.depth_unit_mm, self.intrinsics))

    def _on_status(self, status: Any, playing: int) -> None:
        """SDK thread: the file reached its end -> frames() ends after the frames already queued.

        The SDK also reports "stopped" when stop() stops the sensor; that report may reach the loop
        after the next start() began, so it carries the start it belongs to (counted on the loop,
        before the next file is opened) and a stale one is ignored.
        """
        loop = self._loop
        if loop is not None and getattr(status, "name", str(status)).endswith("stopped"):
            try:
                loop.call_soon_threadsafe(self._end_of_file, playing)
            except RuntimeError:  # the loop is closed: nobody reads this playback any more
                pass

    async def stop(self) -> None:
        """Stop playback and release the file (idempotent)."""
        for task in self._ended:
            task.cancel()
        self._ended.clear()
        await super().stop()

    def _end_of_file(self, playing: int) -> None:
        if self._queue is not None and not self._stopping and playing == self._playing:
            self._ended.append(asyncio.get_running_loop().create_task(self._queue.put(END_OF_STREAM)))


class RecordingFinder:
    """The ``recording`` kind's finder: the recording is a file, and pyrealsense2, which plays it,
    can be imported."""

    async def find(self, camera_id: str, source: DepthSource) -> str:
        """The recording's size in words; DepthBackendMissing or RecordingUnreadable naming the camera."""
        import_pyrealsense2(camera_id)  # named before READY; a dictionary look-up once loaded
        if source.path is None or not source.path.is_file():
            raise RecordingUnreadable(camera_id, source.path or "-", "no recording at this path")
        return f"recording, {source.path.stat().st_size} bytes"

    async def close(self) -> None:
        """Nothing to release."""
