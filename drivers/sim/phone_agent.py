"""The Python twin of the capture agent (agent/, docs/capture-agent-protocol.md) in a simulated phone.

It answers as the real agent's core does, so the driver's tests agree against either: lines of
at most 64 KiB (a longer one is dropped and answered BAD_REQUEST with id 0, and the session goes
on), a malformed line BAD_REQUEST with id 0, focus and capture one at a time in arrival order
with at most CAMERA_QUEUE_LIMIT waiting or running (one more is CAMERA_BUSY), hello, clock and
delete answered without waiting for the camera, answers leaving one at a time (each held back
``answer_delay_s``), images named IMG_nnnnn.jpg numbered on from the highest in the folder, and
deletes only of a file directly in the folder. The camera is the phone's (drivers/sim/phone.py).
"""

from __future__ import annotations

import asyncio
import math
import re
from collections.abc import Awaitable
from typing import TYPE_CHECKING

import structlog

from drivers.adb.streams import AdbStream
from drivers.phone import protocol
from drivers.phone.errors import AgentProtocolError

if TYPE_CHECKING:
    from drivers.sim.phone import SimulatedPhone

log = structlog.get_logger("drivers.sim.phone_agent")


class CaptureFailure(Exception):
    """The camera's onCaptureFailed (the simulated phone's fail_captures fault), answered CAPTURE_FAILED
    by either agent."""

CAMERA_QUEUE_LIMIT = 8  # agent/src/core/com/tbp/agent/Agent.java
SIMULATED_JAR = b"PK\x03\x04 tbp capture agent (simulated)"
HELLO_FIELDS = ("model", "serial", "min_focus_diopters", "focus_distance_calibration", "timestamp_source",
                "exposure_s", "iso", "image_width", "image_height")
_IMAGE = re.compile(r"IMG_(\d{5,9})\.jpg")


class LineFramer:
    """A connection's bytes as lines of at most ``max_line`` bytes ('\\n' included), as the agent
    frames them: a longer line is dropped as it arrives and reported by its size at its newline."""

    def __init__(self, max_line: int = protocol.MAX_LINE) -> None:
        self.max_line = max_line
        self._buffer = bytearray()
        self._dropped = -1  # >= 0 while dropping a line that grew past max_line

    def feed(self, data: bytes) -> list[bytes | int]:
        """Complete lines (bytes) and sizes of dropped lines (int), in order."""
        out: list[bytes | int] = []
        start = 0
        while (end := data.find(b"\n", start)) >= 0:
            piece = end + 1 - start
            if self._dropped >= 0:
                out.append(self._dropped + piece)
                self._dropped = -1
            elif len(self._buffer) + piece > self.max_line:
                out.append(len(self._buffer) + piece)
                self._buffer.clear()
            else:
                out.append(bytes(self._buffer + data[start:end + 1]))
                self._buffer.clear()
            start = end + 1
        rest = len(data) - start
        if rest:
            if self._dropped >= 0:
                self._dropped += rest
            elif len(self._buffer) + rest >= self.max_line:
                self._dropped = len(self._buffer) + rest
                self._buffer.clear()
            else:
                self._buffer += data[start:]
        return out


class Refused(Exception):
    """A request answered with an error: the protocol's code and a message."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def image_name(path: object) -> str:
    """The file name a delete may remove: a plain name directly in the image folder."""
    prefix = "/sdcard/DCIM/tbp/"
    name = path[len(prefix):] if isinstance(path, str) and path.startswith(prefix) else ""
    if name in ("", ".", "..") or "/" in name or "\0" in name:
        raise Refused("BAD_REQUEST", f"delete path {path!r} is not a file in /sdcard/DCIM/tbp")
    return name


def number(request: protocol.AgentRequest, name: str) -> float:
    value = request.params.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Refused("BAD_REQUEST", f"{request.op}: {name!r} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise Refused("BAD_REQUEST", f"{request.op}: {name!r} must be finite, got {value!r}")
    return float(value)


class TwinRuntime:
    """Runs the Python twin when the host starts the agent (the jar's content is not looked at)."""

    def __init__(self, phone: SimulatedPhone) -> None:
        self.phone = phone
        self._process: _TwinProcess | None = None

    @property
    def running(self) -> bool:
        return self._process is not None

    def installed_jar(self) -> bytes:
        return SIMULATED_JAR

    def crash(self) -> None:
        if self._process is not None:
            self._process.crashed.set()

    async def app_process(self, argv: list[str], env: dict[str, str], stream: AdbStream) -> None:
        jar = env.get("CLASSPATH", "")
        if protocol.AGENT_CLASS not in argv or self.phone.fs.read(jar) is None:
            await stream.write(f"Error: Could not find or load main class {' '.join(argv[2:3])} "
                               f"(CLASSPATH={jar!r})\n".encode())
            return
        socket_name = next((a.split("=", 1)[1] for a in argv if a.startswith("socket=")), protocol.SOCKET_NAME)
        self._process = process = _TwinProcess(self.phone)
        try:
            await process.run(socket_name, stream)
        finally:
            self._process = None


class _TwinProcess:
    """One run of the twin, from app_process to the end of its shell stream."""

    def __init__(self, phone: SimulatedPhone) -> None:
        self.phone = phone
        self.crashed = asyncio.Event()
        self._sessions: set[AdbStream] = set()
        self._camera = asyncio.Lock()  # FIFO: camera operations run in arrival order
        self._camera_ops = 0
        highest = max((int(m.group(1)) for name in phone.fs.list(phone.IMAGE_DIR)
                       if (m := _IMAGE.fullmatch(name))), default=-1)
        self._next_image = highest + 1

    async def run(self, socket_name: str, shell: AdbStream) -> None:
        phone = self.phone
        phone.listeners[socket_name] = self._session
        log.info("sim_phone_agent_started", serial=phone.serial, socket=socket_name)
        try:
            await shell.write(f"{protocol.READY_PREFIX} {socket_name} {protocol.PROTOCOL_VERSION}\n".encode())
            stdin = asyncio.create_task(_discard(shell))  # the agent reads nothing from its shell stream
            crashed = asyncio.create_task(self.crashed.wait())
            try:
                await asyncio.wait({stdin, crashed}, return_when=asyncio.FIRST_COMPLETED)
            finally:  # also when adbd closes the stream's task: the waits must not outlive it
                for task in (stdin, crashed):
                    task.cancel()
                await asyncio.gather(stdin, crashed, return_exceptions=True)
        finally:
            phone.listeners.pop(socket_name, None)
            for session in list(self._sessions):  # its sockets close with the process
                await session.close()
            log.info("sim_phone_agent_stopped", serial=phone.serial)

    async def _session(self, stream: AdbStream) -> None:
        self._sessions.add(stream)
        answers: asyncio.Queue[bytes] = asyncio.Queue()
        work: set[asyncio.Task[None]] = set()
        writer = asyncio.create_task(self._write_answers(stream, answers))
        framer = LineFramer()
        try:
            while data := await stream.read():
                for line in framer.feed(data):
                    if isinstance(line, int):
                        answers.put_nowait(protocol.encode_error(0, "BAD_REQUEST",
                                                                 f"line of {line} bytes > {protocol.MAX_LINE}"))
                    else:
                        self._handle(line, answers, work)
        finally:
            for task in (*work, writer):
                task.cancel()
            await asyncio.gather(*work, writer, return_exceptions=True)
            self._sessions.discard(stream)

    async def _write_answers(self, stream: AdbStream, answers: asyncio.Queue[bytes]) -> None:
        while True:
            answer = await answers.get()
            if self.phone.answer_delay_s > 0:
                await asyncio.sleep(self.phone.answer_delay_s)
            await stream.write(answer)

    def _handle(self, line: bytes, answers: asyncio.Queue[bytes], work: set[asyncio.Task[None]]) -> None:
        try:
            request = protocol.parse_request(line, device=self.phone.serial)
        except AgentProtocolError as exc:
            answers.put_nowait(protocol.encode_error(0, "BAD_REQUEST", str(exc)))
            return
        try:
            later = self._answer(request)
        except Refused as exc:
            answers.put_nowait(protocol.encode_error(request.id, exc.code, str(exc)))
            return
        if isinstance(later, bytes):
            answers.put_nowait(later)
            return
        task = asyncio.create_task(self._finish(request, later, answers))
        work.add(task)
        task.add_done_callback(work.discard)

    async def _finish(self, request: protocol.AgentRequest, answer: Awaitable[bytes],
                      answers: asyncio.Queue[bytes]) -> None:
        try:
            line = await answer
        except Refused as exc:
            line = protocol.encode_error(request.id, exc.code, str(exc))
        except CaptureFailure as exc:
            line = protocol.encode_error(request.id, "CAPTURE_FAILED", str(exc))
        except (ValueError, TypeError, RuntimeError, OSError) as exc:  # the real agent answers so too
            log.error("sim_phone_agent_error", serial=self.phone.serial, op=request.op, error=repr(exc))
            line = protocol.encode_error(request.id, "CAMERA_ERROR", f"{request.op}: {exc!r}")
        answers.put_nowait(line)

    def _answer(self, request: protocol.AgentRequest) -> bytes | Awaitable[bytes]:
        """The answer now, or the coroutine that answers later (camera and clock)."""
        phone, op = self.phone, request.op
        if op == "hello":
            info = phone.camera_info()
            return protocol.encode_result(request.id, agent_version=phone.agent_version,
                                          **{name: info[name] for name in HELLO_FIELDS})
        if op == "delete":
            name = image_name(request.params.get("path"))
            if not phone.fs.remove(f"{phone.IMAGE_DIR}/{name}"):
                raise Refused("NOT_FOUND", f"{phone.IMAGE_DIR}/{name} does not exist")
            return protocol.encode_result(request.id)
        if op == "clock":
            return self._clock(request.id)
        if op == "focus":
            return self._camera_op(self._focus(request.id, self._focus_target(request)))
        if op == "capture":
            return self._camera_op(self._capture(request.id, *self._exposure(request)))
        raise Refused("UNKNOWN_OP", f"unknown op {op!r}")

    def _focus_target(self, request: protocol.AgentRequest) -> float:
        diopters = number(request, "diopters")
        if not 0.0 <= diopters <= self.phone.min_focus_diopters:
            raise Refused("FOCUS_OUT_OF_RANGE", f"{diopters} D outside [0, {self.phone.min_focus_diopters}] D")
        return diopters

    def _exposure(self, request: protocol.AgentRequest) -> tuple[float, int]:
        phone = self.phone
        exposure = phone.optics.exposure_s
        if "exposure_s" in request.params:
            exposure = number(request, "exposure_s")
            low, high = phone.EXPOSURE_RANGE_S
            if not low <= exposure <= high:
                raise Refused("BAD_REQUEST", f"capture: exposure_s {exposure} outside the sensor's [{low}, {high}] s")
        iso = phone.optics.iso
        if "iso" in request.params:
            iso = request.params["iso"]
            low, high = phone.ISO_RANGE
            if isinstance(iso, bool) or not isinstance(iso, int):
                raise Refused("BAD_REQUEST", f"capture: 'iso' must be an integer, got {iso!r}")
            if not low <= iso <= high:
                raise Refused("BAD_REQUEST", f"capture: iso {iso} outside the sensor's [{low}, {high}]")
        return exposure, iso

    def _camera_op(self, operation: Awaitable[bytes]) -> Awaitable[bytes]:
        if self._camera_ops >= CAMERA_QUEUE_LIMIT:
            operation.close()  # type: ignore[attr-defined]
            raise Refused("CAMERA_BUSY", f"{CAMERA_QUEUE_LIMIT} camera operations already queued")
        self._camera_ops += 1
        return self._in_turn(operation)

    async def _in_turn(self, operation: Awaitable[bytes]) -> bytes:
        try:
            async with self._camera:
                return await operation
        finally:
            self._camera_ops -= 1

    async def _clock(self, request_id: int) -> bytes:
        return protocol.encode_result(request_id, device_ns=await self.phone.read_clock())

    async def _focus(self, request_id: int, diopters: float) -> bytes:
        used, stationary_ns = await self.phone.move_lens(diopters)
        return protocol.encode_result(request_id, diopters=used, lens_state=0, stationary_at_ns=stationary_ns)

    async def _capture(self, request_id: int, exposure_s: float, iso: int) -> bytes:
        phone = self.phone
        still = await phone.expose(exposure_s)
        while phone.fs.read(path := f"{phone.IMAGE_DIR}/IMG_{self._next_image:05d}.jpg") is not None:
            self._next_image += 1  # never overwrite an image not yet pulled
        phone.fs.write(path, still.jpeg, mtime=int(still.sensor_timestamp_ns // 1_000_000_000))
        self._next_image += 1
        phone.captures[-1]["path"] = path
        return protocol.encode_result(request_id, sensor_timestamp_ns=still.sensor_timestamp_ns,
                                      exposure_s=still.exposure_s, focus_diopters=still.focus_diopters,
                                      path=path, size=len(still.jpeg))


async def _discard(stream: AdbStream) -> None:
    """Read and drop everything until the peer closes the stream."""
    while await stream.read():
        pass
