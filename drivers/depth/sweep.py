"""Record a depth sweep: stream every depth camera and the beam position while the beam rotates.

The daemon starts the rotation and hands its awaitable here together with the motor's live
sample stream; frames are thinned to the TSDF's spacing as they arrive, then tagged with the
beam angle interpolated in the recorded trace (``planner.sweep``). Frames outside the trace
(the camera started before the first motor sample or after the last) are left out and counted.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Sequence
from typing import Any

import structlog

from drivers.depth.base import DepthCamera, DepthFrame
from drivers.depth.errors import DepthStreamStalled
from planner.rig import Rig
from planner.shape_errors import BadTrace
from planner.sweep import BeamTrace, Sweep, tag_frame
from planner.tsdf import FRAME_SPACING_DEG

log = structlog.get_logger(__name__)


class SweepCollector:
    """Collects one sweep; FRAME_TIMEOUT_S is how long a camera may go without a frame.

    spacing_deg: keep a camera's frame only when the beam (latest motor sample) has turned this far
    since its last kept frame, as the TSDF would (0 keeps every frame): a whole 30 fps sweep of
    three cameras would hold about 1 GB. Frames before the first motor sample and empty frames are
    not kept.
    """

    FRAME_TIMEOUT_S = 1.0

    def __init__(self, cameras: Sequence[DepthCamera], rig: Rig, *, spacing_deg: float = FRAME_SPACING_DEG) -> None:
        self.cameras = list(cameras)
        self.rig = rig
        self.spacing_deg = spacing_deg
        self.frames: dict[str, list[DepthFrame]] = {c.id: [] for c in self.cameras}
        self.received: dict[str, int] = {c.id: 0 for c in self.cameras}
        self.samples: list[Any] = []

    async def _read(self, camera: DepthCamera) -> None:
        stream = camera.frames().__aiter__()
        kept = self.frames[camera.id]
        last_angle: float | None = None
        while True:
            try:
                async with asyncio.timeout(self.FRAME_TIMEOUT_S):
                    frame = await stream.__anext__()
            except TimeoutError:
                raise DepthStreamStalled(camera.id, self.received[camera.id], self.FRAME_TIMEOUT_S) from None
            except StopAsyncIteration:
                raise DepthStreamStalled(camera.id, self.received[camera.id], None) from None
            self.received[camera.id] += 1
            if not self.samples or not frame.depth.any():
                continue
            angle = float(self.samples[-1].angle_deg)
            if last_angle is None or abs(angle - last_angle) >= self.spacing_deg - 1e-9:
                kept.append(frame)
                last_angle = angle

    async def _trace(self, samples: AsyncIterator[Any]) -> None:
        async for sample in samples:
            self.samples.append(sample)

    async def run(self, motion: Awaitable[Any], beam_samples: AsyncIterator[Any]) -> Sweep:
        """Start the cameras, await the motion while recording, stop the cameras, tag the frames.

        Raises DepthStreamStalled (a camera stopped delivering) or the motion's own error; the
        cameras are stopped either way.
        """
        trace_task = asyncio.ensure_future(self._trace(beam_samples))
        readers: list[asyncio.Task[None]] = []
        motion_task: asyncio.Future[Any] | None = None
        try:
            for camera in self.cameras:
                await camera.start()
            readers = [asyncio.ensure_future(self._read(c)) for c in self.cameras]
            motion_task = asyncio.ensure_future(motion)
            readers_and_motion = {motion_task, *readers}
            while True:
                done, _ = await asyncio.wait(readers_and_motion, return_when=asyncio.FIRST_COMPLETED)
                if motion_task in done:
                    motion_task.result()
                    break
                for task in done:
                    task.result()
        finally:
            pending: list[asyncio.Future[Any]] = [trace_task, *readers]
            if motion_task is None:
                if asyncio.iscoroutine(motion):
                    motion.close()
            elif not motion_task.done():
                pending.append(motion_task)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
            for camera in self.cameras:
                await camera.stop()
        return self._tag()

    def _tag(self) -> Sweep:
        try:
            trace = BeamTrace.from_samples(self.samples)
        except BadTrace as exc:
            raise BadTrace(f"depth sweep recorded {len(self.samples)} beam samples: {exc}") from exc
        frames = [f for received in self.frames.values() for f in received]
        inside = [f for f in frames if trace.covers(f.timestamp_s)]
        sweep = Sweep(tuple(tag_frame(f, trace, self.rig) for f in inside), trace)
        log.info(
            "depth_sweep.collected",
            frames=len(inside),
            received=self.received,
            outside_trace=len(frames) - len(inside),
            per_camera=sweep.per_camera(),
            start_deg=round(float(trace.angle_deg[0]), 2),
            end_deg=round(float(trace.angle_deg[-1]), 2),
        )
        return sweep


async def collect_sweep(
    cameras: Sequence[DepthCamera],
    motion: Awaitable[Any],
    beam_samples: AsyncIterator[Any],
    rig: Rig,
    *,
    spacing_deg: float = FRAME_SPACING_DEG,
) -> Sweep:
    """Record a sweep while ``motion`` (e.g. ``drive.move_to(end, speed, accel)``) runs.

    beam_samples: the motor's live stream (``drive.samples()``), items with time_s and angle_deg.
    spacing_deg: frames kept per degree of beam rotation (see :class:`SweepCollector`).
    """
    return await SweepCollector(cameras, rig, spacing_deg=spacing_deg).run(motion, beam_samples)
