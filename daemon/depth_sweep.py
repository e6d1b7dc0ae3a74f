"""The depth sweep: rotate the beam over ``rig.depth_sweep`` while every depth camera streams.

Frames are thinned on the fly to one per ``SPACING_DEG`` of beam rotation per camera (the TSDF's
own frame spacing: 30 fps frames a fraction of a degree apart add little to the fusion but a
whole sweep of them would hold about 1 GB), then tagged with the beam angle from the encoder
trace recorded during the move. A camera that stops delivering ends the sweep with
``DepthStreamStalled``.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import structlog

from daemon.beam import BeamTracker
from daemon.errors import SweepFailed
from drivers.depth.base import DepthCamera, DepthFrame
from drivers.depth.errors import DepthStreamStalled
from planner.rig import Rig
from planner.sweep import BeamTrace, Sweep, tag_frames
from planner.tsdf import FRAME_SPACING_DEG

log = structlog.get_logger("daemon.depth_sweep")


@dataclass(frozen=True)
class SweepRecord:
    """The sweep's frames (tagged) and its encoder trace (N, 3) [time_s, angle_deg, speed_deg_s]."""

    sweep: Sweep
    trace: np.ndarray
    frames_seen: dict[str, int]
    started_s: float
    ended_s: float


class DepthSweeper:
    """Runs one depth sweep on a drive already at ``rig.depth_sweep.start_deg`` and at rest."""

    SPACING_DEG = FRAME_SPACING_DEG
    MIN_FRAMES_PER_CAMERA = 8
    STOP_TIMEOUT_S = 2.0
    FRAME_TIMEOUT_S = 1.0
    """A camera silent this long during the sweep has stalled."""

    def __init__(self, rig: Rig, drive: Any, tracker: BeamTracker, cameras: Sequence[DepthCamera]) -> None:
        self.rig = rig
        self.drive = drive
        self.tracker = tracker
        self.cameras = list(cameras)

    async def run(self) -> SweepRecord:
        loop = asyncio.get_running_loop()
        sweep = self.rig.depth_sweep
        kept: list[DepthFrame] = []
        seen = {c.id: 0 for c in self.cameras}
        mark = self.tracker.mark()
        started = loop.time()
        for camera in self.cameras:
            await camera.start()
        collectors = [
            asyncio.create_task(self._collect(c, kept, seen), name=f"sweep-{c.id}") for c in self.cameras
        ]
        motion = asyncio.create_task(self.drive.move_to(
            sweep.end_deg, sweep.speed_deg_s, self.rig.motor.max_acceleration_deg_s2))
        try:
            while not motion.done():
                done, _ = await asyncio.wait({motion, *collectors}, return_when=asyncio.FIRST_COMPLETED)
                for task in done:
                    task.result()  # a stalled camera or a drive error ends the sweep here
        finally:
            if not motion.done():
                motion.cancel()
                await asyncio.gather(motion, return_exceptions=True)
            for task in collectors:
                task.cancel()
            await asyncio.gather(*collectors, return_exceptions=True)
            for camera in self.cameras:
                async with asyncio.timeout(self.STOP_TIMEOUT_S):
                    await camera.stop()
        ended = loop.time()
        trace = self.tracker.trace(mark)
        beam_trace = BeamTrace.from_samples(_Row(t, a) for t, a, _ in trace)
        inside = [f for f in kept if beam_trace.covers(f.timestamp_s)]
        counts = {c.id: sum(1 for f in inside if f.camera_id == c.id) for c in self.cameras}
        for camera_id, n in counts.items():
            if n < self.MIN_FRAMES_PER_CAMERA:
                raise SweepFailed(camera_id, n, self.MIN_FRAMES_PER_CAMERA)
        log.info("depth_sweep_done", frames=len(inside), seen=seen, duration_s=ended - started)
        return SweepRecord(tag_frames(inside, beam_trace, self.rig), trace, seen, started, ended)

    async def _collect(self, camera: DepthCamera, kept: list[DepthFrame], seen: dict[str, int]) -> None:
        last_angle: float | None = None
        stream = camera.frames().__aiter__()
        while True:
            try:
                async with asyncio.timeout(self.FRAME_TIMEOUT_S):
                    frame = await stream.__anext__()
            except TimeoutError:
                raise DepthStreamStalled(camera.id, seen[camera.id], self.FRAME_TIMEOUT_S) from None
            except StopAsyncIteration:
                raise DepthStreamStalled(camera.id, seen[camera.id], None) from None
            seen[camera.id] += 1
            angle = self.tracker.angle_deg
            if angle is None or not np.any(frame.depth):
                continue
            if last_angle is None or abs(angle - last_angle) >= self.SPACING_DEG:
                kept.append(frame)
                last_angle = angle


@dataclass(frozen=True)
class _Row:
    time_s: float
    angle_deg: float
