"""A simulated rig phone: an adbd (drivers/sim/adbd.py) plus the capture agent, lens and sensor clock.

The agent starts only the way the real one does: the host runs ``CLASSPATH=<jar> app_process /
com.tbp.CaptureAgent ...`` on a shell stream; the jar must be on the phone (pushed, or
installed beforehand with ``agent_installed=True``). It then prints its READY line, listens on
``localabstract:tbp-capture`` and lives until that shell stream closes.

Timing, all on the event loop's clock: the lens travels for LENS_BASE_S + LENS_S_PER_DIOPTER *
|change| (times ``lens_slowdown``) and settles for LENS_SETTLE_S; a capture starts exposing
CAPTURE_LATENCY_S (+ seeded jitter) after the request and the file is written ENCODE_S after the
exposure. The sensor clock has its own offset and drift (seeded); a clock ping reads it after a
seeded one-way delay, so round trips are not zero. Each image is the subject ray
cast from ``pose(t)`` (time -> (4, 4) camera-to-world, provided by the sim wiring so the phone
knows nothing of the motor) and blurred by its distance from the focal plane; with a
``board`` (drivers/sim/focus_target.py: a board on a stand in front of the phone, for the focus
calibration's sweep) the picture is that board instead, and with a ``picture_source`` (the sim
wiring's calibration cuboid, seen from ``pose(t)``) it is what the source renders.

Faults: those of the adbd (refuse_auth, vanish(), disconnect_after_bytes) plus crash_agent()
(the agent process dies; adbd stays up, so a reconnect starts it again), lens_slowdown,
fail_captures (the next n captures answer CAPTURE_FAILED), answer_delay_s (every agent answer
is held back that long, as on a congested USB hub) and mute_agent (requests go unanswered, as
when the camera HAL hangs).
"""

from __future__ import annotations

import asyncio
import random
import weakref
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import structlog

from drivers.adb.streams import AdbStream
from drivers.phone import protocol
from drivers.phone.errors import AgentProtocolError
from drivers.sim.adbd import SimulatedAdbd
from drivers.sim.focus_target import BoardStand
from drivers.sim.phone_render import PhoneRenderer, SubjectScene, empty_rig_picture, encode_jpeg
from planner.rig import Optics, load_rig

log = structlog.get_logger("drivers.sim.phone")

PoseSource = Callable[[float], np.ndarray]
PictureSource = Callable[[np.ndarray | None, float, np.random.Generator], np.ndarray]
"""(camera-to-world pose at the exposure, sharpest distance of the lens in mm, noise) -> (H, W[, 3])
uint8: what the phone photographs when it is not the subject (the calibration cuboid)."""
_SCENES: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()


def _scene_for(subject: Any) -> SubjectScene:
    """One ray-casting scene per subject mesh, shared by every simulated phone."""
    scene = _SCENES.get(subject)
    if scene is None:
        scene = _SCENES[subject] = SubjectScene(subject)
    return scene


class SimulatedPhone(SimulatedAdbd):
    """One rig phone: adbd, capture agent, lens, sensor clock and camera."""

    LENS_BASE_S = 0.012
    LENS_S_PER_DIOPTER = 0.010
    LENS_SETTLE_S = 0.03
    CAPTURE_LATENCY_S = 0.045
    CAPTURE_JITTER_S = 0.003
    ENCODE_S = 0.12
    LINK_DELAY_S = 0.0003  # one way, USB/ADB and agent thread hand-off, before jitter
    IMAGE_DIR = "/sdcard/DCIM/tbp"

    def __init__(self, serial: str, *, subject: Any | None = None, pose: PoseSource | None = None,
                 seed: int = 0, optics: Optics | None = None, known_keys: Iterable[bytes | str] = (),
                 accept_new_keys: bool = True, agent_installed: bool = True,
                 render_size: tuple[int, int] | None = (192, 256), min_focus_diopters: float = 10.0,
                 focus_calibration_quality: int = 1, timestamp_source: str = "realtime",
                 model: str = "TBP Simulated Phone") -> None:
        super().__init__(serial, properties={"ro.product.model": model}, known_keys=known_keys,
                         accept_new_keys=accept_new_keys, seed=seed)
        self.subject = subject
        self.pose = pose
        self.seed = seed
        self.board: BoardStand | None = None
        self.picture_source: PictureSource | None = None
        self.optics = optics or load_rig().optics  # the default rig's phones
        self.render_size = render_size
        self.min_focus_diopters = min_focus_diopters
        self.focus_calibration_quality = focus_calibration_quality
        self.timestamp_source = timestamp_source
        rng = random.Random(seed * 7919 + 17)
        self.clock_offset_s = rng.uniform(1_000.0, 200_000.0)
        self.clock_drift_ppm = rng.uniform(-30.0, 30.0)
        # The lens focuses at 1000 / (offset + gain * commanded diopters) mm: a per-phone error
        # that `tbp calibrate focus` measures (about 0.1 D and 3 %, as uncalibrated Camera2 units).
        self.focus_offset_diopters = rng.gauss(0.0, 0.08)
        self.focus_gain = 1.0 + rng.gauss(0.0, 0.03)
        self._jitter = random.Random(seed * 104729 + 3)
        self.lens_diopters = 0.0
        self.lens_slowdown = 1.0
        self.fail_captures = 0
        self.mute_agent = False
        self.answer_delay_s = 0.0
        self.agent_version = protocol.PROTOCOL_VERSION
        self._agent_sessions: set[AdbStream] = set()
        self._agent_crashed = asyncio.Event()
        self.agent_running = False
        self.captures: list[dict[str, Any]] = []
        self._renderer: PhoneRenderer | None = None
        self._camera_lock = asyncio.Lock()
        if agent_installed:
            self.fs.write(protocol.AGENT_PATH, b"PK\x03\x04 tbp capture agent (simulated)")
        self.commands["app_process"] = self._app_process

    # ---------------------------------------------------------------- clock
    def sensor_ns(self, loop_time_s: float) -> int:
        """The phone's sensor clock (ns) at a host loop time: own offset and drift."""
        return int(round((self.clock_offset_s + loop_time_s * (1.0 + self.clock_drift_ppm * 1e-6)) * 1e9))

    def loop_time_of(self, sensor_ns: int) -> float:
        """Inverse of :meth:`sensor_ns`: ground truth for clock-sync tests."""
        return (sensor_ns * 1e-9 - self.clock_offset_s) / (1.0 + self.clock_drift_ppm * 1e-6)

    def _now_ns(self) -> int:
        return self.sensor_ns(asyncio.get_running_loop().time())

    # ---------------------------------------------------------------- agent process
    async def _app_process(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        jar = env.get("CLASSPATH", "")
        if protocol.AGENT_CLASS not in argv or self.fs.read(jar) is None:
            await stream.write(f"Error: Could not find or load main class {' '.join(argv[2:3])} "
                               f"(CLASSPATH={jar!r})\n".encode())
            return
        socket_name = next((a.split("=", 1)[1] for a in argv if a.startswith("socket=")), protocol.SOCKET_NAME)
        self.listeners[socket_name] = self._agent_session
        self.agent_running = True
        self._agent_crashed = asyncio.Event()
        log.info("sim_phone_agent_started", serial=self.serial, socket=socket_name)
        try:
            await stream.write(f"{protocol.READY_PREFIX} {socket_name} {protocol.PROTOCOL_VERSION}\n".encode())
            stdin = asyncio.create_task(_discard(stream))  # the agent ignores stdin
            crashed = asyncio.create_task(self._agent_crashed.wait())
            try:
                await asyncio.wait({stdin, crashed}, return_when=asyncio.FIRST_COMPLETED)
            finally:  # also when adbd closes the stream's task: the waits must not outlive it
                for task in (stdin, crashed):
                    task.cancel()
                await asyncio.gather(stdin, crashed, return_exceptions=True)
        finally:
            self.listeners.pop(socket_name, None)
            self.agent_running = False
            for session in list(self._agent_sessions):  # its sockets close with the process
                await session.close()
            log.info("sim_phone_agent_stopped", serial=self.serial)

    def crash_agent(self) -> None:
        """Fault: the agent process dies (its socket and shell stream close; adbd stays up)."""
        if self.agent_running:
            self._agent_crashed.set()

    async def _agent_session(self, stream: AdbStream) -> None:
        self._agent_sessions.add(stream)
        try:
            await self._serve_agent(stream)
        finally:
            self._agent_sessions.discard(stream)

    async def _serve_agent(self, stream: AdbStream) -> None:
        while self.agent_running:
            line = await stream.readline(protocol.MAX_LINE)
            if not line:
                return
            try:
                request = protocol.parse_request(line, device=self.serial)
            except AgentProtocolError as exc:
                await stream.write(protocol.encode_error(0, "BAD_REQUEST", str(exc)))
                continue
            if self.mute_agent:
                continue
            try:
                answer = await self._handle(request)
            except (ValueError, TypeError, RuntimeError, OSError) as exc:  # the real agent answers so too
                log.error("sim_phone_agent_error", serial=self.serial, op=request.op, error=repr(exc))
                answer = protocol.encode_error(request.id, "CAMERA_ERROR", f"{request.op}: {exc!r}")
            if self.answer_delay_s > 0:
                await asyncio.sleep(self.answer_delay_s)
            await stream.write(answer)

    async def _handle(self, request: protocol.AgentRequest) -> bytes:
        handlers = {"hello": self._hello, "focus": self._focus, "capture": self._capture,
                    "clock": self._clock, "delete": self._delete}
        handler = handlers.get(request.op)
        if handler is None:
            return protocol.encode_error(request.id, "UNKNOWN_OP", f"unknown op {request.op!r}")
        return await handler(request)

    async def _hello(self, request: protocol.AgentRequest) -> bytes:
        return protocol.encode_result(
            request.id, agent_version=self.agent_version, model=self.properties["ro.product.model"],
            serial=self.serial, min_focus_diopters=self.min_focus_diopters,
            focus_distance_calibration=self.focus_calibration_quality, timestamp_source=self.timestamp_source,
            exposure_s=self.optics.exposure_s, iso=self.optics.iso,
            image_width=self._image_size()[0], image_height=self._image_size()[1])

    async def _clock(self, request: protocol.AgentRequest) -> bytes:
        await asyncio.sleep(self.LINK_DELAY_S * (1.0 + self._jitter.random()))
        device_ns = self._now_ns()
        await asyncio.sleep(self.LINK_DELAY_S * (1.0 + self._jitter.random()))
        return protocol.encode_result(request.id, device_ns=device_ns)

    async def _delete(self, request: protocol.AgentRequest) -> bytes:
        path = request.params.get("path")
        if not isinstance(path, str) or not path.startswith(self.IMAGE_DIR + "/"):
            return protocol.encode_error(request.id, "BAD_REQUEST", f"delete path {path!r} outside {self.IMAGE_DIR}")
        if not self.fs.remove(path):
            return protocol.encode_error(request.id, "NOT_FOUND", f"{path} does not exist")
        return protocol.encode_result(request.id)

    async def _focus(self, request: protocol.AgentRequest) -> bytes:
        target = request.params.get("diopters")
        if isinstance(target, bool) or not isinstance(target, (int, float)) or not np.isfinite(target):
            return protocol.encode_error(request.id, "BAD_REQUEST", f"diopters must be a number, got {target!r}")
        if not 0.0 <= target <= self.min_focus_diopters:
            return protocol.encode_error(request.id, "FOCUS_OUT_OF_RANGE",
                                         f"{target} D outside [0, {self.min_focus_diopters}] D")
        async with self._camera_lock:
            travel = (self.LENS_BASE_S + self.LENS_S_PER_DIOPTER * abs(target - self.lens_diopters))
            await asyncio.sleep(travel * self.lens_slowdown + self.LENS_SETTLE_S)
            self.lens_diopters = float(target)
            return protocol.encode_result(request.id, diopters=self.lens_diopters, lens_state=0,
                                          stationary_at_ns=self._now_ns())

    async def _capture(self, request: protocol.AgentRequest) -> bytes:
        loop = asyncio.get_running_loop()
        exposure = float(request.params.get("exposure_s", self.optics.exposure_s))
        async with self._camera_lock:
            latency = max(self.CAPTURE_LATENCY_S + self._jitter.gauss(0.0, self.CAPTURE_JITTER_S), 0.005)
            await asyncio.sleep(latency)
            start = loop.time()
            if self.fail_captures > 0:
                self.fail_captures -= 1
                return protocol.encode_error(request.id, "CAPTURE_FAILED",
                                             "CameraCaptureSession.CaptureCallback.onCaptureFailed reason 0")
            pose = self.pose(start + exposure / 2) if self.pose is not None else None
            focus_diopters = self.lens_diopters
            await asyncio.sleep(exposure)
            jpeg = await loop.run_in_executor(None, self._picture, pose, focus_diopters, len(self.captures))
            await asyncio.sleep(self.ENCODE_S)
            path = f"{self.IMAGE_DIR}/IMG_{len(self.captures):05d}.jpg"
            self.fs.write(path, jpeg, mtime=int(self.sensor_ns(start) // 1_000_000_000))
            record = {"path": path, "start_s": start, "sensor_timestamp_ns": self.sensor_ns(start),
                      "exposure_s": exposure, "focus_diopters": focus_diopters, "size": len(jpeg)}
            self.captures.append(record)
        return protocol.encode_result(request.id, sensor_timestamp_ns=record["sensor_timestamp_ns"],
                                      exposure_s=exposure, focus_diopters=focus_diopters, path=path,
                                      size=len(jpeg))

    # ---------------------------------------------------------------- pictures
    def sharp_distance_mm(self, diopters: float) -> float:
        """Where the lens is sharpest (mm) at a commanded focus (diopters): this phone's true lens."""
        measured = self.focus_offset_diopters + self.focus_gain * diopters
        return 1000.0 / measured if measured > 1e-4 else 1e7

    def _image_size(self) -> tuple[int, int]:
        return self.render_size or (self.optics.image_width_px // 32, self.optics.image_height_px // 32)

    def _picture(self, pose: np.ndarray | None, focus_diopters: float, index: int) -> bytes:
        if self.picture_source is not None:
            rng = np.random.default_rng([self.seed, index, 0x5CE7E])
            picture = self.picture_source(pose, self.sharp_distance_mm(focus_diopters), rng)
            return encode_jpeg(picture if picture.ndim == 3 else np.repeat(picture[:, :, None], 3, axis=2))
        if self.board is not None:
            rng = np.random.default_rng([self.seed, index, 0xB0A2D])
            return encode_jpeg(self.board.picture(self.sharp_distance_mm(focus_diopters), self.optics, rng))
        width, height = self._image_size()
        if self.subject is None or pose is None or self.render_size is None:
            return encode_jpeg(empty_rig_picture(width, height, seed=index))
        if self._renderer is None:
            self._renderer = PhoneRenderer(_scene_for(self.subject), self.optics, width, height)
        return encode_jpeg(self._renderer.render(pose, self.sharp_distance_mm(focus_diopters)))


async def _discard(stream: AdbStream) -> None:
    """Read and drop everything until the peer closes the stream."""
    while await stream.read():
        pass
