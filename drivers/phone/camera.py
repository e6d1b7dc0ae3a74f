"""One rig phone as a camera: ADB link, capture agent, focus in millimetres, capture, clock, pull.

connect() brings the phone up the way screen-mirroring tools start their helper: CNXN/AUTH,
check the serial, push the agent jar to /data/local/tmp when it differs, start it with
``app_process`` on a shell stream that stays open (the agent lives as long as that stream), wait
for its READY line, open ``localabstract:tbp-capture`` and say hello. Requests are JSON lines
matched to answers by id, so a focus command may be in flight while a pull runs on its own
sync stream.
"""

from __future__ import annotations

import asyncio
import itertools
import os
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog

from drivers.adb.auth import AdbKey
from drivers.adb.connection import AdbConnection
from drivers.adb.errors import AdbError, AdbLimitExceeded, AuthRefused, ConnectionLost, SyncFail
from drivers.adb.streams import AdbStream
from drivers.adb.transport import AdbTransport, StreamTransport
from drivers.phone import protocol
from drivers.phone.errors import (
    AgentError,
    AgentMissing,
    AgentProtocolError,
    AgentStartFailed,
    CaptureFailed,
    CaptureTimeout,
    FocusFailed,
    FocusOutOfRange,
    FocusTimeout,
    PhoneDisconnected,
    PhoneError,
    PhoneUnauthorized,
    PullFailed,
    RequestTimeout,
    WrongPhone,
)
from drivers.phone.focus import FocusCalibration
from planner.rig import Phone

log = structlog.get_logger("drivers.phone")

TransportFactory = Callable[[], Awaitable[AdbTransport | tuple[asyncio.StreamReader, asyncio.StreamWriter]]]


@dataclass(frozen=True)
class PhoneInfo:
    """The agent's hello: focus range (diopters), calibration quality 0/1/2, timestamp source."""

    serial: str
    model: str
    min_focus_diopters: float
    focus_calibration_quality: int
    timestamp_source: str


@dataclass(frozen=True)
class FocusDone:
    """Lens stationary at the commanded focus; lens_stationary_at_ns on the phone's sensor clock."""

    diopters: float
    focus_mm: float
    lens_stationary_at_ns: int


@dataclass(frozen=True)
class CaptureDone:
    """One image: exposure start (sensor clock ns), exposure (s), focus used, file on the phone."""

    sensor_timestamp_ns: int
    exposure_s: float
    focus_diopters: float
    path: str
    size_bytes: int


@dataclass(frozen=True)
class ClockSample:
    """One clock round trip: host loop time (s) around the phone's sensor clock reading (ns)."""

    host_send_s: float
    device_ns: int
    host_recv_s: float


def _read_jar(path: Path) -> tuple[bytes, int]:
    """The capture agent jar's bytes and modification time (s)."""
    return path.read_bytes(), int(path.stat().st_mtime)


class PhoneCamera:
    """A rig phone's camera over ADB. States: disconnected -> connecting -> ready -> closed."""

    CONNECT_TIMEOUT_S = 15.0
    AGENT_START_TIMEOUT_S = 10.0
    REQUEST_TIMEOUT_S = 2.0
    FOCUS_TIMEOUT_S = 2.0
    CAPTURE_TIMEOUT_S = 3.0
    AGENT_JAR_ENV = "TBP_CAPTURE_AGENT_JAR"
    # Largest image pulled: a 50 MP JPEG at the highest quality is ~25 MB; a phone sending more
    # is refused (PullFailed) before the file fills the scan store or the host's memory.
    MAX_IMAGE_BYTES = 64 * 1024 * 1024
    AGENT_OUTPUT_LINES = 5  # last lines of a failed agent start quoted in AgentStartFailed

    def __init__(self, transport_factory: TransportFactory, phone: Phone, focus_table: FocusCalibration, *,
                 key: AdbKey, agent_jar: Path | None = None) -> None:
        self.transport_factory = transport_factory
        self.phone = phone
        self.name = phone.id
        self.serial = phone.serial
        self.focus_table = focus_table
        self.key = key
        jar = agent_jar or os.environ.get(self.AGENT_JAR_ENV)
        self.agent_jar = Path(jar) if jar else None
        self.state = "disconnected"
        self.info: PhoneInfo | None = None
        self.agent_pushed_bytes = 0  # the jar pushed by the last connect(), 0 when the phone's copy was used
        self.adb: AdbConnection | None = None
        self._agent_shell: AdbStream | None = None
        self._agent: AdbStream | None = None
        self._reader: asyncio.Task[None] | None = None
        self._pending: dict[int, tuple[str, asyncio.Future[protocol.AgentResponse]]] = {}
        self._ids = itertools.count(1)
        self._lost: PhoneError | None = None
        self._log = log.bind(device=phone.id)  # whichever task calls, its lines name the phone

    def __repr__(self) -> str:
        return f"PhoneCamera({self.phone.id}, {self.serial}, {self.state})"

    # ---------------------------------------------------------------- connect
    async def connect(self, timeout_s: float | None = None) -> PhoneInfo:
        """Link, authenticate, start the agent and say hello, within ``timeout_s`` (None:
        CONNECT_TIMEOUT_S; a first connection waits for someone to accept the USB debugging
        prompt); reconnects if already connected."""
        limit = self.CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
        await self._teardown()
        self.state = "connecting"
        self._lost = None
        try:
            async with asyncio.timeout(limit):
                info = await self._bring_up()
        except TimeoutError:
            await self._teardown()
            self.state = "disconnected"
            raise PhoneDisconnected(self.serial, "connecting", f"not ready within {limit:g} s") from None
        except AdbError as exc:
            await self._teardown()
            self.state = "disconnected"
            error = PhoneUnauthorized if isinstance(exc, AuthRefused) else PhoneDisconnected
            raise error(self.serial, "connecting", str(exc)) from exc
        except BaseException:
            await self._teardown()
            self.state = "disconnected"
            raise
        self.info = info
        self.state = "ready"
        self._log.info("phone_ready", serial=self.serial, model=info.model, min_focus_diopters=info.min_focus_diopters,
                 focus_calibration=info.focus_calibration_quality, timestamp_source=info.timestamp_source)
        return info

    async def _bring_up(self) -> PhoneInfo:
        link = await self.transport_factory()
        transport = StreamTransport(*link, name=self.serial) if isinstance(link, tuple) else link
        self.adb = AdbConnection(transport, self.key, name=self.serial)
        await self.adb.connect()
        serial = (await self.adb.shell("getprop ro.serialno")).decode(errors="replace").strip()
        if serial != self.serial:
            raise WrongPhone(self.serial, "connecting", f"device on this link reports serial {serial!r}")
        await self._install_agent(self.adb)
        await self._start_agent(self.adb)
        self._agent = await self.adb.open(f"localabstract:{protocol.SOCKET_NAME}")
        self._reader = asyncio.create_task(self._read_answers(self._agent), name=f"agent-{self.serial}")
        answer = await self._request("hello", self.REQUEST_TIMEOUT_S, version=protocol.PROTOCOL_VERSION)
        version = answer.number("agent_version", device=self.serial, integer=True)
        if version != protocol.PROTOCOL_VERSION:
            raise AgentProtocolError(self.serial, "connecting",
                                     f"agent speaks protocol {version}, this host {protocol.PROTOCOL_VERSION}")
        quality = int(answer.number("focus_distance_calibration", device=self.serial, integer=True))
        source = answer.text("timestamp_source", device=self.serial)
        if quality not in (0, 1, 2) or source not in ("realtime", "unknown"):
            raise AgentProtocolError(self.serial, "connecting",
                                     f"hello with calibration {quality!r} / timestamp source {source!r}")
        return PhoneInfo(answer.text("serial", device=self.serial), answer.text("model", device=self.serial),
                         float(answer.number("min_focus_diopters", device=self.serial)), quality, source)

    async def _install_agent(self, adb: AdbConnection) -> None:
        self.agent_pushed_bytes = 0
        async with await adb.sync() as sync:
            remote = await sync.stat(protocol.AGENT_PATH)
            if self.agent_jar is None:
                if not remote.exists:
                    raise AgentMissing(self.serial, "connecting", f"{protocol.AGENT_PATH} is not on the phone "
                                       f"and no local jar is set (${self.AGENT_JAR_ENV})")
                return
            try:  # read in a thread: a re-probe connects while the loop carries the heartbeats
                jar, mtime = await asyncio.to_thread(_read_jar, self.agent_jar)
            except OSError as exc:
                raise AgentMissing(self.serial, "connecting", f"cannot read {self.agent_jar}: {exc.strerror}") from exc
            if (remote.size, remote.mtime) != (len(jar), mtime):  # the phone's copy is another build
                await sync.push(jar, protocol.AGENT_PATH, mode=0o644, mtime=mtime)
                self.agent_pushed_bytes = len(jar)
                self._log.info("phone_agent_pushed", serial=self.serial, bytes=len(jar))

    async def _start_agent(self, adb: AdbConnection) -> None:
        command = (f"CLASSPATH={protocol.AGENT_PATH} app_process / {protocol.AGENT_CLASS} "
                   f"socket={protocol.SOCKET_NAME} version={protocol.PROTOCOL_VERSION}")
        self._agent_shell = shell = await adb.open(f"shell:{command}")
        output: deque[str] = deque(maxlen=self.AGENT_OUTPUT_LINES)
        try:
            async with asyncio.timeout(self.AGENT_START_TIMEOUT_S):
                while True:
                    line = (await shell.readline()).decode(errors="replace")
                    if not line:
                        break
                    if line.startswith(protocol.READY_PREFIX):
                        return
                    output.append(line.rstrip())
        except TimeoutError:
            output.append(f"(no READY line within {self.AGENT_START_TIMEOUT_S:g} s)")
        raise AgentStartFailed(self.serial, "connecting", "agent output: " + " | ".join(output))

    # ---------------------------------------------------------------- requests
    async def _read_answers(self, stream: AdbStream) -> None:
        try:
            while line := await stream.readline(protocol.MAX_LINE):
                answer = protocol.parse_response(line, device=self.serial)
                pending = self._pending.pop(answer.id, None)
                if pending is not None and not pending[1].done():
                    pending[1].set_result(answer)
                else:  # its request already timed out and raised; the phone caught up since
                    self._log.info("phone_late_answer", serial=self.serial, request_id=answer.id, ok=answer.ok)
            cause: PhoneError = PhoneDisconnected(self.serial, self.state, "the capture agent closed its stream")
        except AdbError as exc:
            cause = PhoneDisconnected(self.serial, self.state, str(exc))
            cause.__cause__ = exc
        except AgentProtocolError as exc:
            cause = exc
        self._lost = cause
        if self.state == "ready":
            self.state = "disconnected"
            self._log.warning("phone_disconnected", serial=self.serial, error=str(cause))
        for _, future in self._pending.values():
            if not future.done():
                future.set_exception(cause)
        self._pending.clear()

    async def _request(self, op: str, timeout_s: float, **params: Any) -> protocol.AgentResponse:
        if self._lost is not None:
            raise self._lost
        if self._agent is None:
            raise PhoneDisconnected(self.serial, self.state, f"cannot {op}: not connected")
        ident = next(self._ids)
        future: asyncio.Future[protocol.AgentResponse] = asyncio.get_running_loop().create_future()
        self._pending[ident] = (op, future)
        try:
            async with asyncio.timeout(timeout_s):
                await self._agent.write(protocol.encode_request(ident, op, **params))
                answer = await future
        except TimeoutError:
            timeout_error = {"focus": FocusTimeout, "capture": CaptureTimeout}.get(op, RequestTimeout)
            raise timeout_error(self.serial, self.state, op, timeout_s) from None
        except ConnectionLost as exc:
            raise PhoneDisconnected(self.serial, self.state, str(exc)) from exc
        except AdbError as exc:
            raise PhoneDisconnected(self.serial, self.state, f"agent stream failed: {exc}") from exc
        finally:
            self._pending.pop(ident, None)
        if not answer.ok:
            error = {"focus": FocusFailed, "capture": CaptureFailed}.get(op, AgentError)
            raise error(self.serial, self.state, answer.code, answer.message, op)
        return answer

    # ---------------------------------------------------------------- camera
    async def set_focus_mm(self, focus_mm: float) -> FocusDone:
        """Command the focus whose calibrated sharpest distance is focus_mm; returns when the lens is still."""
        diopters = self.focus_table.diopters_for(focus_mm, device=self.serial)
        if self.info is not None and diopters > self.info.min_focus_diopters:
            near = self.focus_table.focus_mm(self.info.min_focus_diopters)
            raise FocusOutOfRange(self.serial, self.state, focus_mm, near, self.focus_table.far_mm)
        return await self.set_lens_diopters(diopters)

    async def set_lens_diopters(self, diopters: float) -> FocusDone:
        """Command the lens setting itself (LENS_FOCUS_DISTANCE, diopters), whatever the focus table
        says it focuses at: the focus calibration's sweep; returns when the lens is still."""
        answer = await self._request("focus", self.FOCUS_TIMEOUT_S, diopters=round(float(diopters), 6))
        used = float(answer.number("diopters", device=self.serial))
        return FocusDone(used, self.focus_table.focus_mm(used),
                         int(answer.number("stationary_at_ns", device=self.serial, integer=True)))

    async def capture(self) -> CaptureDone:
        """Take one still now (manual exposure, focus as last set)."""
        answer = await self._request("capture", self.CAPTURE_TIMEOUT_S)
        n = answer.number
        return CaptureDone(int(n("sensor_timestamp_ns", device=self.serial, integer=True)),
                           float(n("exposure_s", device=self.serial)), float(n("focus_diopters", device=self.serial)),
                           answer.text("path", device=self.serial), int(n("size", device=self.serial, integer=True)))

    async def clock_sample(self) -> ClockSample:
        """One round trip: host loop time before and after the phone read its sensor clock."""
        loop = asyncio.get_running_loop()
        sent = loop.time()
        answer = await self._request("clock", self.REQUEST_TIMEOUT_S)
        received = loop.time()
        return ClockSample(sent, int(answer.number("device_ns", device=self.serial, integer=True)), received)

    async def delete(self, phone_path: str) -> None:
        """Remove an image from the phone once it is safely pulled."""
        await self._request("delete", self.REQUEST_TIMEOUT_S, path=phone_path)

    async def pull(self, phone_path: str, dest: Path) -> tuple[int, str]:
        """Copy a file (at most MAX_IMAGE_BYTES) from the phone to dest atomically; (size in bytes, sha256 hex)."""
        if self.adb is None or not self.adb.online:
            raise PhoneDisconnected(self.serial, self.state, f"cannot pull {phone_path}: not connected")
        try:
            async with await self.adb.sync() as sync:
                return await sync.pull(phone_path, Path(dest), max_bytes=self.MAX_IMAGE_BYTES)
        except SyncFail as exc:
            raise PullFailed(self.serial, self.state, f"{phone_path}: {exc.reason}") from exc
        except AdbLimitExceeded as exc:
            raise PullFailed(self.serial, self.state,
                             f"{phone_path}: larger than the {exc.limit}-byte image limit") from exc
        except AdbError as exc:
            raise PhoneDisconnected(self.serial, self.state, f"pull of {phone_path}: {exc}") from exc

    # ---------------------------------------------------------------- closing
    async def _teardown(self) -> None:
        if self._reader is not None:
            self._reader.cancel()
            await asyncio.gather(self._reader, return_exceptions=True)
            self._reader = None
        for op, future in self._pending.values():  # requests in flight end now, not at their timeout
            if not future.done():
                future.set_exception(PhoneDisconnected(self.serial, self.state, f"{op}: link closed by the host"))
        self._pending.clear()
        if self.adb is not None:
            await self.adb.close()  # closes the agent streams; the agent exits with its shell stream
            self.adb = None
        self._agent = self._agent_shell = None

    async def close(self) -> None:
        """Stop the agent and drop the link; idempotent."""
        await self._teardown()
        self.state = "closed"
        self._lost = PhoneDisconnected(self.serial, "closed", "closed")
