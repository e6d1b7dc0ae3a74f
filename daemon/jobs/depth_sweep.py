"""The depth sweep: rotate the beam over ``rig.depth_sweep`` while every depth camera streams.

Every camera is started before the beam moves (a camera that fails to start stops the ones
already streaming, and the beam never moves). Frames are thinned on the fly to one per
``SPACING_DEG`` of beam rotation per camera (the TSDF's own frame spacing), then posed: a live
frame at the beam angle the encoder trace recorded at the frame's time, a frame played back from
a sweep recording at the angle it was recorded at (``DepthFrame.beam_angle_deg``), so a recording
replays as the sweep it was whatever its playback pace. A camera silent for ``FRAME_TIMEOUT_S``
ends the sweep with ``DepthStreamStalled``; a recording that ends before the beam does is done.
Whatever ends the sweep, every camera is stopped before ``run()`` returns or raises.

With a ``sink`` (the scan's TSDF, daemon/offload/fusion.py), frames are posed while the beam turns:
every ``FEED_PERIOD_S`` the kept frames the encoder trace already covers go to the sink, so the
fusion keeps up with the sweep; the few posed at its end are left in ``SweepRecord.unfed``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import structlog

from daemon.errors import SweepFailed
from daemon.rig.beam import BeamTracker
from daemon.rig.devices import DepthCamera, Drive
from daemon.tasks import despite_cancel, stop_tasks
from drivers.depth.base import DepthFrame
from drivers.depth.errors import DepthCameraError, DepthStreamStalled
from planner.calibration.model import Calibration
from planner.rig import Rig
from planner.sweep import AngleSpacing, BeamTrace, PosedDepth, Sweep, pose_frame, tag_frame
from planner.tsdf import FRAME_SPACING_DEG

log = structlog.get_logger("daemon.jobs.depth_sweep")


@dataclass(frozen=True)
class SweepRecord:
    """The sweep's posed frames, its encoder trace (N, 3) [time_s, angle_deg, speed_deg_s], the frames
    each camera delivered, and per camera where its angles came from ("encoder" or "recording")."""

    sweep: Sweep
    trace: np.ndarray
    frames_seen: dict[str, int]
    angle_source: dict[str, str]
    started_s: float
    ended_s: float
    unfed: tuple[PosedDepth, ...] = ()
    """Posed frames the sink has not had yet (each camera's in time order; all of them without a sink)."""


class DepthSweeper:
    """Runs one depth sweep on a drive already at ``rig.depth_sweep.start_deg`` and at rest."""

    SPACING_DEG = FRAME_SPACING_DEG
    MIN_FRAMES_PER_CAMERA = 8
    STOP_TIMEOUT_S = 6.0
    """Longer than a RealSense stream's own stop timeout, so its typed error arrives first."""
    FRAME_TIMEOUT_S = 1.0
    """A camera silent this long during the sweep has stalled."""
    FEED_PERIOD_S = 0.5
    """How often posed frames go to the sink during the sweep."""

    def __init__(self, rig: Rig, drive: Drive, tracker: BeamTracker, cameras: Sequence[DepthCamera],
                 calibration: Calibration | None = None,
                 sink: Callable[[list[PosedDepth]], Awaitable[None]] | None = None) -> None:
        self.rig = rig
        self.calibration = calibration
        self.drive = drive
        self.tracker = tracker
        self.cameras = list(cameras)
        self.sink = sink
        self._unposed: list[DepthFrame] = []
        self._posed: list[PosedDepth] = []
        self._fed = 0  # self._posed[:_fed] went to the sink
        self._outside = 0
        self._source: dict[str, str] = {}
        self._seen: dict[str, int] = {}
        self._spacing = AngleSpacing(self.SPACING_DEG)

    async def run(self) -> SweepRecord:
        """Stream, move, stop the cameras, pose the frames. Raises the first failure (a camera that
        does not start or stalls, the drive's error, SweepFailed for too few frames), every camera
        stopped; a camera that also fails to stop is named in the error's notes."""
        loop = asyncio.get_running_loop()
        sweep = self.rig.depth_sweep
        self._unposed, self._posed, self._fed, self._outside = [], [], 0, 0
        self._source = {c.id: "encoder" for c in self.cameras}
        self._seen = {c.id: 0 for c in self.cameras}
        self._spacing = AngleSpacing(self.SPACING_DEG)
        mark = self.tracker.mark()
        started = loop.time()
        tasks: list[asyncio.Task[Any]] = []
        feeding = asyncio.Event()  # set: the beam stopped, the feeder ends after its current batch
        feeder: asyncio.Task[None] | None = None
        try:
            for camera in self.cameras:
                await camera.start()
            tasks = [asyncio.create_task(self._collect(c), name=f"sweep-{c.id}") for c in self.cameras]
            motion = asyncio.create_task(self.drive.move_to(
                sweep.end_deg, sweep.speed_deg_s, self.rig.motor.max_acceleration_deg_s2), name="sweep-motion")
            tasks.append(motion)
            if self.sink is not None:
                feeder = asyncio.create_task(self._feed(self.sink, mark, feeding), name="sweep-feed")
                tasks.append(feeder)
            pending: set[asyncio.Task[Any]] = set(tasks)
            while not motion.done():
                done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                for task in done:
                    task.result()  # a stalled camera, a drive error or a failed fusion ends the sweep here
            feeding.set()
            if feeder is not None:
                await feeder  # its batch in flight is fused; nothing is fed twice or concurrently
        except BaseException as error:
            await self._wind_down(tasks, error)
            raise
        await self._wind_down(tasks, None)
        ended = loop.time()
        trace = self.tracker.trace(mark)
        record = self._pose(trace, started, ended)
        log.info("depth_sweep_done", frames=len(record.sweep.frames), seen=self._seen,
                 angle_source=record.angle_source, duration_s=ended - started)
        return record

    async def _collect(self, camera: DepthCamera) -> None:
        stream = camera.frames().__aiter__()
        while True:
            try:
                async with asyncio.timeout(self.FRAME_TIMEOUT_S):
                    frame = await stream.__anext__()
            except TimeoutError:
                raise DepthStreamStalled(camera.id, self._seen[camera.id], self.FRAME_TIMEOUT_S) from None
            except StopAsyncIteration:  # only a recording ends by itself
                log.info("depth_sweep_recording_ended", camera=camera.id, frames=self._seen[camera.id])
                return
            self._seen[camera.id] += 1
            angle = frame.beam_angle_deg if frame.beam_angle_deg is not None else self.tracker.angle_deg
            if angle is None or not np.any(frame.depth):
                continue
            if self._spacing.keep(camera.id, angle):
                self._unposed.append(frame)

    async def _feed(self, sink: Callable[[list[PosedDepth]], Awaitable[None]], mark: int,
                    stopped: asyncio.Event) -> None:
        """Every FEED_PERIOD_S until ``stopped``: pose what the trace covers, hand it to the sink."""
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.FEED_PERIOD_S):
                    await stopped.wait()
            if stopped.is_set():
                return
            trace = self.tracker.trace(mark)
            if len(trace) >= 2:
                self._pose_ready(BeamTrace.from_columns(trace[:, 0], trace[:, 1]), final=False)
            # In time order, cameras by id at equal times: frames that arrive together reach this
            # list in whichever order their tasks ran, and the TSDF's sums depend on the order.
            batch = sorted(self._posed[self._fed:], key=lambda f: (f.timestamp_s, f.camera_id))
            if batch:
                self._fed = len(self._posed)
                await sink(batch)

    def _pose_ready(self, beam: BeamTrace, *, final: bool) -> None:
        """Pose the kept frames ``beam`` covers (recorded ones at their own angle); a frame before
        the trace, or at the end (``final``) after it, is dropped; the rest wait for more trace."""
        waiting: list[DepthFrame] = []
        for frame in self._unposed:
            if frame.beam_angle_deg is not None:
                self._posed.append(pose_frame(frame, frame.beam_angle_deg, self.rig, self.calibration))
                self._source[frame.camera_id] = "recording"
            elif beam.covers(frame.timestamp_s):
                self._posed.append(tag_frame(frame, beam, self.rig, self.calibration))
            elif final or frame.timestamp_s < beam.start_s:
                self._outside += 1  # streamed before the first or after the last encoder sample
            else:
                waiting.append(frame)
        self._unposed = waiting

    async def _wind_down(self, tasks: list[asyncio.Task[Any]], error: BaseException | None) -> None:
        """Cancel what still runs and stop every camera (idempotent stops), even those never started,
        to the end even if the sweep is stopped again meanwhile (a camera left streaming would refuse
        the next scan's start)."""
        bound = self.STOP_TIMEOUT_S * (len(self.cameras) + 1)
        await despite_cancel(self._release(tasks, error), bound)

    async def _release(self, tasks: list[asyncio.Task[Any]], error: BaseException | None) -> None:
        failures: list[DepthCameraError] = [
            DepthCameraError(task.get_name(), f"sweep task did not stop within {self.STOP_TIMEOUT_S:g} s")
            for task in await stop_tasks(tasks, self.STOP_TIMEOUT_S)]
        for camera in self.cameras:
            try:
                async with asyncio.timeout(self.STOP_TIMEOUT_S):
                    await camera.stop()
            except TimeoutError:
                failures.append(DepthCameraError(camera.id, f"did not stop within {self.STOP_TIMEOUT_S} s"))
            except DepthCameraError as exc:
                failures.append(exc)
        if not failures:
            return
        if error is None:
            first, *rest = failures
            for failure in rest:
                first.add_note(f"also: {failure}")
            raise first
        for failure in failures:  # the sweep's own error stays the one raised
            error.add_note(f"while stopping the depth cameras: {failure}")
            log.error("depth_sweep_stop_failed", camera=failure.camera_id, error=str(failure))

    def _pose(self, trace: np.ndarray, started: float, ended: float) -> SweepRecord:
        beam = BeamTrace.from_columns(trace[:, 0], trace[:, 1])
        self._pose_ready(beam, final=True)
        unfed = sorted(self._posed[self._fed:], key=lambda f: (f.camera_id, f.timestamp_s))
        posed = sorted(self._posed, key=lambda f: (f.camera_id, f.timestamp_s))
        sweep = Sweep(tuple(posed), beam)
        counts = sweep.per_camera()
        for camera in self.cameras:
            if counts.get(camera.id, 0) < self.MIN_FRAMES_PER_CAMERA:
                raise SweepFailed(camera.id, counts.get(camera.id, 0), self.MIN_FRAMES_PER_CAMERA)
        if self._outside:
            log.info("depth_sweep_frames_outside_trace", frames=self._outside)
        return SweepRecord(sweep, trace, dict(self._seen), dict(self._source), started, ended, tuple(unfed))
