"""Intel RealSense depth cameras through pyrealsense2 (the optional extra ``realsense``).

:class:`RealSenseStream` holds what live cameras and ``.bag`` playback share: the lazy import
of pyrealsense2, Z16 frames (and with ``infrared`` on, the left imager's Y8 picture) copied out
of librealsense's callback thread and handed to the event loop with ``call_soon_threadsafe``, the
depth scale read from the device, the intrinsics from the stream profile, and device timestamps
mapped onto the host event-loop clock.
:class:`RealSenseCamera` opens one camera by serial at 1280 x 720 Z16 (plus Y8 infrared);
:class:`drivers.depth.bag.BagPlayback` replays a recording through the same interface.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np
import structlog

from drivers.depth.base import DepthFrame, DepthSource
from drivers.depth.errors import DepthCameraError, DepthStreamStalled
from drivers.noise import NoiseLog
from planner.rig import DepthCamera as DepthCameraConfig
from planner.rig import DepthCameraModel

log = structlog.get_logger(__name__)

INSTALL_HINT = "pip install tbp-rig[realsense] (or: pip install pyrealsense2)"
END_OF_STREAM = object()


class RawFrame(NamedTuple):
    """A depth frame copied out of the SDK, not yet stamped on the loop clock."""

    number: int
    device_ms: float
    domain: str
    depth: np.ndarray  # (H, W) uint16 depth units
    beam_angle_deg: float | None  # recorded with the frame (a sweep recording), else None
    infrared: np.ndarray | None  # (H, W) uint8 left infrared image when infrared is on, else None


class DepthBackendMissing(DepthCameraError):
    """The camera's SDK module is not installed."""

    def __init__(self, camera_id: str, module: str, cause: BaseException) -> None:
        self.module = module
        super().__init__(camera_id, f"{module} cannot be imported ({cause}); {INSTALL_HINT}")


class DepthCameraNotFound(DepthCameraError):
    """No connected camera has the configured serial number."""

    def __init__(self, camera_id: str, serial: str, available: list[str]) -> None:
        self.serial, self.available = serial, available
        found = ", ".join(available) if available else "none"
        super().__init__(camera_id, f"no RealSense device with serial {serial!r} (connected: {found})")


def import_pyrealsense2(camera_id: str) -> ModuleType:
    """pyrealsense2, or DepthBackendMissing with the install command."""
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as exc:
        raise DepthBackendMissing(camera_id, "pyrealsense2", exc) from exc


def load_pyrealsense2() -> None:
    """Import pyrealsense2 now, if it is installed: a daemon does it before any device's heartbeat
    runs on its loop (the import holds the interpreter lock 25-35 ms). Without it nothing happens
    here: each camera's finder names the missing backend."""
    with contextlib.suppress(DepthBackendMissing):
        import_pyrealsense2("-")


def copy_image(frame: Any, dtype: type, kind: str) -> np.ndarray:
    """(H, W) copy of a video frame's pixels (the SDK recycles the frame's buffer); ValueError
    naming ``kind`` when they are not H x W of ``dtype``."""
    height, width = frame.get_height(), frame.get_width()
    data = np.asanyarray(frame.get_data())
    if data.dtype != dtype or data.size != height * width:
        raise ValueError(f"expected {width}x{height} {kind}, got {data.dtype} x {data.size}")
    result: np.ndarray = data.reshape(height, width).copy()
    return result


def intrinsics_matrix(intrinsics: Any) -> np.ndarray:
    """(3, 3) float64 pinhole K in pixels from an ``rs.intrinsics`` (fx, fy, ppx, ppy)."""
    return np.array(
        [[intrinsics.fx, 0.0, intrinsics.ppx], [0.0, intrinsics.fy, intrinsics.ppy], [0.0, 0.0, 1.0]]
    )


class HostClockMap:
    """Maps a camera's timestamps (ms) onto the host event-loop clock (s).

    Each frame's arrival on the loop is its device time plus a fixed offset plus a transport
    latency that is never negative; the smallest ``arrival - device`` seen over the last
    ``window_s`` is the offset with the least latency in it. A device clock that runs backwards
    (the camera was reset) starts the estimate afresh.
    """

    def __init__(self, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self._offsets: deque[tuple[float, float]] = deque()  # (arrival_s, offset_s), offsets rising
        self._last_device_ms: float | None = None

    def host_time(self, device_ms: float, arrival_s: float) -> float:
        """The host-clock time of a frame stamped ``device_ms`` that arrived at ``arrival_s``."""
        if self._last_device_ms is not None and device_ms < self._last_device_ms:
            self._offsets.clear()
        self._last_device_ms = device_ms
        device_s = device_ms / 1000.0
        offset = arrival_s - device_s
        while self._offsets and self._offsets[-1][1] >= offset:
            self._offsets.pop()
        self._offsets.append((arrival_s, offset))
        while self._offsets[0][0] < arrival_s - self.window_s:
            self._offsets.popleft()
        return device_s + self._offsets[0][1]


@dataclass(frozen=True)
class Opened:
    """A source streaming into the frame callback: its depth sensor (depth scale), the depth stream
    profile (intrinsics) and how to stop it and release the device or file (blocking)."""

    depth_sensor: Any
    depth_profile: Any
    close: Callable[[], None]


class RealSenseStream(ABC):
    """A pyrealsense2 depth stream (live camera or recording) feeding frames into asyncio.

    Subclasses say which device or file to open (:meth:`_open`) and how frames reach the
    loop. ``FRAME_TIMEOUT_S``: no frame for this long -> DepthStreamStalled from ``frames()``.
    ``infrared``: set before ``start()``; when True every frame carries the left infrared image
    (a source that has none raises InfraredUnavailable from ``start()``).
    """

    FRAME_TIMEOUT_S = 1.0
    START_TIMEOUT_S = 15.0
    STOP_TIMEOUT_S = 5.0
    QUEUE_FRAMES = 16  # frames held for a slow consumer; a live camera drops the oldest beyond
    DROPPED_LOG_PERIOD_S = 10.0  # dropped frames are logged at most once a period, with a count

    def __init__(self, camera_id: str) -> None:
        self.id = camera_id
        self.infrared = False
        self._infrared_streaming = False  # infrared as start() found it, for the SDK's thread
        self.depth_unit_mm: float | None = None
        self.intrinsics: np.ndarray | None = None
        self.timestamp_domain: str | None = None
        self.dropped_frames = 0
        self._close_source: Callable[[], None] | None = None
        self._context: Any = None  # the SDK context, made at the first start and kept (see _sdk_context)
        self._queue: asyncio.Queue[Any] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping = False
        self._failure: BaseException | None = None
        self._early: list[RawFrame] = []
        self._described = asyncio.Event()  # set once start() knows the depth scale and intrinsics
        self._log = log.bind(device=camera_id)
        self._dropped_log = NoiseLog(self._log, "realsense_frame_dropped", self.DROPPED_LOG_PERIOD_S)

    # ------------------------------------------------------------------ DepthCamera protocol

    async def start(self) -> None:
        """Open the device (or file) and start streaming; blocking SDK calls run in the executor."""
        if self._close_source is not None:
            raise DepthCameraError(self.id, "start() while already streaming")
        rs = import_pyrealsense2(self.id)
        loop = self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue(self.QUEUE_FRAMES)
        self._stopping = False
        self._failure = None
        self._early = []
        self._described = asyncio.Event()
        self.depth_unit_mm = self.intrinsics = None
        self._infrared_streaming = self.infrared
        starting = loop.run_in_executor(None, self._open, rs, self._on_frame)
        try:
            async with asyncio.timeout(self.START_TIMEOUT_S):
                opened = await asyncio.shield(starting)
        except TimeoutError:
            self._stopping = True  # frames of a late start are ignored, and the device released
            starting.add_done_callback(lambda job: self._release_late_start(loop, job))
            raise DepthCameraError(self.id, f"did not start streaming within {self.START_TIMEOUT_S} s") from None
        except RuntimeError as exc:  # pyrealsense2 raises rs.error, a RuntimeError
            raise DepthCameraError(self.id, f"start failed: {exc}") from exc
        self._close_source = opened.close
        try:
            self.depth_unit_mm = float(opened.depth_sensor.get_depth_scale()) * 1000.0
            self.intrinsics = intrinsics_matrix(opened.depth_profile.as_video_stream_profile().get_intrinsics())
        except RuntimeError as exc:
            await self.stop()
            raise DepthCameraError(self.id, f"cannot read the stream's scale/intrinsics: {exc}") from exc
        early, self._early = self._early, []
        for raw in early:
            self._arrived(raw)
        self._described.set()
        self._log.info("realsense_started", depth_unit_mm=self.depth_unit_mm,
                       fx=float(self.intrinsics[0, 0]), cx=float(self.intrinsics[0, 2]))

    async def frames(self) -> AsyncIterator[DepthFrame]:
        """Frames in arrival order, stamped on the loop clock; ends after stop() (or a bag's end)."""
        queue = self._queue
        if queue is None:
            raise DepthCameraError(self.id, "frames() before start()")
        count = 0
        while True:
            try:
                async with asyncio.timeout(self.FRAME_TIMEOUT_S):
                    item = await queue.get()
            except TimeoutError:
                raise DepthStreamStalled(self.id, count, self.FRAME_TIMEOUT_S) from None
            if item is END_OF_STREAM:
                return
            if isinstance(item, DepthCameraError):
                raise item
            if isinstance(item, BaseException):
                raise DepthCameraError(self.id, f"frame handling failed: {item}") from item
            count += 1
            yield item

    async def stop(self) -> None:
        """Stop streaming and release the device (idempotent); a waiting frames() then ends."""
        close, self._close_source = self._close_source, None
        self._stopping = True
        self._described.set()  # a hand-over waiting for start() returns and sees the stop
        if close is not None:
            self._discard_queued()  # a callback blocked on a full queue must return for stop()
            loop = asyncio.get_running_loop()
            try:
                async with asyncio.timeout(self.STOP_TIMEOUT_S):
                    await loop.run_in_executor(None, close)
            except TimeoutError:
                raise DepthCameraError(self.id, f"did not stop within {self.STOP_TIMEOUT_S} s") from None
            except RuntimeError as exc:
                raise DepthCameraError(self.id, f"stop failed: {exc}") from exc
            self._dropped_log.flush()
            self._log.info("realsense_stopped", dropped_frames=self.dropped_frames)
        if self._queue is not None:
            self._discard_queued()
            self._queue.put_nowait(END_OF_STREAM)

    def _release_late_start(self, loop: asyncio.AbstractEventLoop, job: asyncio.Future[Opened]) -> None:
        """A start that gave up waiting still owns the device once the SDK call returns: close it."""
        if not job.cancelled() and job.exception() is None:
            self._log.warning("realsense_late_start_stopped")
            loop.run_in_executor(None, job.result().close)

    def _sdk_context(self, rs: ModuleType) -> Any:
        """This stream's ``rs.context``, made once (in the executor, by :meth:`_open`) and kept for
        the stream's life: destroying a context joins the SDK's threads with the interpreter lock
        held, which stopped three depth cameras' event loop for 70-100 ms at every sweep's end."""
        if self._context is None:
            self._context = rs.context()
        return self._context

    # ------------------------------------------------------------------ subclass hooks

    @abstractmethod
    def _open(self, rs: ModuleType, on_frame: Callable[[Any], None]) -> Opened:
        """Blocking (runs in the executor): open the source and stream its depth frames into on_frame."""

    def _hand_over(self, loop: asyncio.AbstractEventLoop, raw: RawFrame) -> None:
        """From the SDK thread: give a converted frame to the loop without blocking (live)."""
        try:
            loop.call_soon_threadsafe(self._arrived, raw)
        except RuntimeError:  # the loop is closed: an exception must not escape into the SDK's thread
            pass

    @abstractmethod
    def _host_time(self, device_ms: float, arrival_s: float) -> float:
        """The host event-loop time of a frame stamped ``device_ms`` that arrived at ``arrival_s``."""

    # ------------------------------------------------------------------ frame path

    def _on_frame(self, frame: Any) -> None:
        """librealsense's callback thread: copy the depth image out, hand it to the loop."""
        loop = self._loop
        if self._stopping or loop is None or self._failure is not None:
            return
        try:
            raw = self._convert(frame)
        except Exception as exc:  # reaches frames() as a typed error, not a dead callback
            try:
                loop.call_soon_threadsafe(self._failed, exc)
            except RuntimeError:  # the loop is closed
                pass
            return
        if raw is not None:
            self._hand_over(loop, raw)

    def _convert(self, frame: Any) -> RawFrame | None:
        infrared_frame = None
        if frame.is_frameset():
            frameset = frame.as_frameset()
            frame = frameset.get_depth_frame()
            if not frame:
                return None
            if self._infrared_streaming:
                infrared_frame = frameset.get_infrared_frame(1)
        elif frame.is_depth_frame():
            frame = frame.as_depth_frame()
        else:
            return None
        depth = copy_image(frame, np.uint16, "Z16 depth")
        infrared = None
        if self._infrared_streaming:
            if not infrared_frame:
                raise ValueError(f"depth frame {frame.get_frame_number()} came without its left infrared image")
            infrared = copy_image(infrared_frame, np.uint8, "Y8 infrared")
            if infrared.shape != depth.shape:
                raise ValueError(f"infrared image {infrared.shape} is not pixel-aligned with depth {depth.shape}")
        domain = frame.get_frame_timestamp_domain()
        number, device_ms = int(frame.get_frame_number()), float(frame.get_timestamp())
        return RawFrame(number, device_ms, getattr(domain, "name", str(domain)), depth,
                        self._recorded_angle(number, device_ms), infrared)

    def _recorded_angle(self, frame_number: int, device_ms: float) -> float | None:
        """The beam angle recorded with this frame (SDK thread); a live camera has none."""
        return None

    def _arrived(self, raw: RawFrame) -> None:
        """On the loop: stamp the frame on the host clock and queue it."""
        queue = self._queue
        if self._stopping or queue is None:
            return
        if self.depth_unit_mm is None or self.intrinsics is None:
            self._early.append(raw)  # came before start() read the scale and intrinsics
            if len(self._early) > self.QUEUE_FRAMES:  # as many as the queue would hold
                self._early.pop(0)
                self.dropped_frames += 1
            return
        frame = self._frame(raw, self.depth_unit_mm, self.intrinsics)
        if queue.full():
            queue.get_nowait()
            self.dropped_frames += 1
            self._dropped_log.report(dropped_frames=self.dropped_frames)
        queue.put_nowait(frame)

    def _frame(self, raw: RawFrame, depth_unit_mm: float, intrinsics: np.ndarray) -> DepthFrame:
        self.timestamp_domain = raw.domain
        return DepthFrame(
            camera_id=self.id,
            frame_number=raw.number,
            timestamp_s=self._host_time(raw.device_ms, asyncio.get_running_loop().time()),
            device_timestamp_ms=raw.device_ms,
            depth=raw.depth,
            depth_unit_mm=depth_unit_mm,
            intrinsics=intrinsics,
            beam_angle_deg=raw.beam_angle_deg,
            infrared=raw.infrared,
        )

    def _failed(self, exc: BaseException) -> None:
        """On the loop: the first failure replaces whatever is queued; frames() raises it."""
        if self._queue is not None and not self._stopping and self._failure is None:
            self._failure = exc
            self._discard_queued()
            self._queue.put_nowait(exc)

    def _discard_queued(self) -> None:
        while self._queue is not None and not self._queue.empty():
            self._queue.get_nowait()


class RealSenseCamera(RealSenseStream):
    """A live RealSense camera of the rig, selected by serial: 1280 x 720 Z16 at ``fps``.

    With ``infrared`` on it also streams the left imager's 1280 x 720 Y8 picture (the depth image's
    own frame) and switches the projector off, so its dot pattern does not cover the calibration
    target; with ``infrared`` off the projector is switched on (a calibration may have left it off).
    Device timestamps (hardware clock, or whatever domain the camera reports) are mapped onto
    the event-loop clock by :class:`HostClockMap`.
    """

    WIDTH_PX = 1280
    HEIGHT_PX = 720

    def __init__(self, camera: DepthCameraConfig, *, fps: float = 30.0) -> None:
        super().__init__(camera.id)
        self.serial = camera.serial
        self.fps = fps
        self._clock = HostClockMap()

    @classmethod
    def for_source(cls, camera: DepthCameraConfig, source: DepthSource, model: DepthCameraModel) -> RealSenseCamera:
        """The rig's camera by its serial at the rig's frame rate (the ``realsense`` kind)."""
        return cls(camera, fps=model.fps)

    def _open(self, rs: ModuleType, on_frame: Callable[[Any], None]) -> Opened:
        context = self._sdk_context(rs)
        serials = [d.get_info(rs.camera_info.serial_number) for d in context.query_devices()]
        if self.serial not in serials:
            raise DepthCameraNotFound(self.id, self.serial, serials)
        config = rs.config()
        config.enable_device(self.serial)
        fps = int(round(self.fps))
        config.enable_stream(rs.stream.depth, self.WIDTH_PX, self.HEIGHT_PX, rs.format.z16, fps)
        if self._infrared_streaming:
            config.enable_stream(rs.stream.infrared, 1, self.WIDTH_PX, self.HEIGHT_PX, rs.format.y8, fps)
        self._clock = HostClockMap()
        pipeline = rs.pipeline(context)
        profile = pipeline.start(config, on_frame)
        try:
            sensor = profile.get_device().first_depth_sensor()
            if sensor.supports(rs.option.emitter_enabled):
                sensor.set_option(rs.option.emitter_enabled, 0.0 if self._infrared_streaming else 1.0)
        except BaseException:
            pipeline.stop()  # start() reports the failure; the device must not stay claimed
            raise
        return Opened(sensor, profile.get_stream(rs.stream.depth), pipeline.stop)

    def _host_time(self, device_ms: float, arrival_s: float) -> float:
        return self._clock.host_time(device_ms, arrival_s)
