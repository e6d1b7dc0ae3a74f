"""The operator panel as the host sees it: buttons and e-stop in, status LED and lights out.

:class:`OperatorPanel` speaks the line protocol of :mod:`drivers.panel.protocol` over any asyncio
(reader, writer) pair: a serial port (:func:`drivers.panel.serial_link.open_serial`), a pty, or a
socketpair to the simulated panel. It answers the panel's heartbeat with its own, watches the
panel's, turns button and e-stop lines into :class:`PanelEvent` values for every subscriber and
waits for the panel to acknowledge each command.

A single bad line (noise on the cable) is dropped and counted; if only bad lines arrive the
heartbeat stops counting and the loss error carries the count and the last parse error. Bad lines
are logged through :class:`~drivers.noise.NoiseLog`: at most one record per BAD_LINE_LOG_PERIOD_S,
each with the number of bad lines it stands for, so a noisy cable cannot flood the journal.
"""

from __future__ import annotations

import asyncio
import enum
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import structlog

from drivers.noise import NoiseLog
from drivers.panel import protocol
from drivers.panel.errors import (
    PanelCommandRefused,
    PanelDisconnected,
    PanelError,
    PanelHeartbeatLost,
    PanelProtocolError,
    PanelStateError,
    PanelTimeout,
)
from drivers.panel.protocol import FROM_HOST, FROM_PANEL, Line, PanelSignal, StatusLed
from drivers.panel.serial_link import open_serial

log = structlog.get_logger(__name__)


class PanelEvent(enum.Enum):
    """What the panel tells the host."""

    START_PRESSED = "start pressed"
    STOP_PRESSED = "stop pressed"
    ESTOP_PRESSED = "e-stop pressed"
    ESTOP_RELEASED = "e-stop released"
    HEARTBEAT_LOST = "heartbeat lost"
    RECONNECTED = "reconnected"


class LinkState(enum.Enum):
    """The host's view of the link."""

    NEW = "new"
    CONNECTING = "connecting"  # greeting the panel (first connect or after a reopen)
    CONNECTED = "connected"
    LOST = "lost"  # heartbeat missing; recovers when it returns
    DISCONNECTED = "disconnected"  # the stream ended; final unless the panel can be reopened
    CLOSED = "closed"


_SIGNAL_EVENTS = {
    PanelSignal.START: PanelEvent.START_PRESSED,
    PanelSignal.STOP: PanelEvent.STOP_PRESSED,
}
_END = object()
Reopen = Callable[[], Awaitable[tuple[asyncio.StreamReader, asyncio.StreamWriter]]]


class OperatorPanel:
    """The push-button operator panel on one serial link.

    Args:
        reader, writer: asyncio streams to the panel (see :func:`open_serial`).
        name: names the panel in errors and logs.
        reopen: opens the link again after it ended (a USB panel unplugged and plugged back);
            the panel then retries every ``REOPEN_PERIOD_S`` and reports RECONNECTED.
            Without it the end of the stream is final.

    ``estop_active`` is True while the e-stop is pressed and also whenever the e-stop state is
    unknown (not connected, heartbeat lost): a safety input that cannot be read counts as pressed.
    """

    CONNECT_TIMEOUT_S = 2.0
    HELLO_RETRY_S = 0.5
    ACK_TIMEOUT_S = 0.3
    COMMAND_ATTEMPTS = 3
    HEARTBEAT_PERIOD_S = protocol.HEARTBEAT_PERIOD_S
    HEARTBEAT_TIMEOUT_S = protocol.HEARTBEAT_TIMEOUT_S
    EVENT_MEMORY_S = 5.0  # an EVT sequence number seen this recently is a resend
    BYE_TIMEOUT_S = 0.2
    REOPEN_PERIOD_S = 1.0
    READ_CHUNK = 256
    BAD_LINE_LOG_PERIOD_S = 10.0

    def __init__(
        self,
        reader: asyncio.StreamReader | None,
        writer: asyncio.StreamWriter | None,
        *,
        name: str = "panel",
        reopen: Reopen | None = None,
    ) -> None:
        self.name = name
        self._reader = reader
        self._writer = writer
        self._reopen = reopen
        self._reconnect_task: asyncio.Task[None] | None = None
        self._connected_once = False
        self.state = LinkState.NEW
        self.fault: PanelHeartbeatLost | None = None
        self.bad_lines = 0
        self.last_error: PanelProtocolError | None = None
        self.status_led: StatusLed | None = None  # last status the panel acknowledged
        self.light_on: bool | None = None  # last light state the panel acknowledged
        self.reported_led: StatusLed | None = None  # as in the panel's latest heartbeat
        self.reported_light: bool | None = None
        self._estop = False
        self._seq = 0
        self._pending: dict[int, asyncio.Future[Line]] = {}
        self._hello: asyncio.Future[Line] | None = None
        self._heartbeat_seen = asyncio.Event()
        self._events_seen: dict[int, float] = {}
        self._subscribers: list[asyncio.Queue[Any]] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._log = log.bind(panel=name)
        self._bad_line_log = NoiseLog(self._log, "panel_bad_line", self.BAD_LINE_LOG_PERIOD_S)

    # ------------------------------------------------------------------ public API

    @property
    def estop_active(self) -> bool:
        return self._estop or self.state is not LinkState.CONNECTED

    @classmethod
    async def open(cls, path: str, *, name: str = "panel") -> OperatorPanel:
        """An unconnected panel on the serial port ``path`` that reopens the port when it vanishes."""

        async def reopen() -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
            return await open_serial(path, name=name)

        return cls(*await reopen(), name=name, reopen=reopen)

    @classmethod
    def at(cls, path: str, *, baudrate: int = 115200, name: str = "panel") -> OperatorPanel:
        """A panel on the serial port ``path``, opened by :meth:`connect` (so a panel that is not
        plugged in yet can be connected later) and reopened whenever it vanishes."""

        async def reopen() -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
            return await open_serial(path, baudrate=baudrate, name=name)

        return cls(None, None, name=name, reopen=reopen)

    async def connect(self) -> None:
        """Greet the panel (HELLO, protocol version), then keep and watch the heartbeats."""
        if self.state is not LinkState.NEW:
            raise PanelStateError(self.name, self.state.value, "connect")
        if self._writer is None:
            if self._reopen is None:
                raise PanelStateError(self.name, self.state.value, "connect without a link")
            self._reader, self._writer = await self._reopen()
        try:
            await self._open_session()
        except BaseException:
            await self._stop_tasks()
            if self.state is LinkState.CONNECTING:  # type: ignore[comparison-overlap]  # _open_session moves it on
                self.state = LinkState.NEW
            if self._reopen is not None and self._writer is not None:  # the next connect reopens the port
                self._writer.close()
                self._reader = self._writer = None
            raise

    def liveness(self) -> list[str]:
        """What of the link's own tasks is not running (empty: all well). A lost panel is the safety
        system's business (it latches FAULT); a link that stopped watching is ill health."""
        if self.state in (LinkState.CONNECTED, LinkState.LOST):
            running = {t.get_name() for t in self._tasks if not t.done()}
            return [f"{self.name}: task {self.name}{role} not running" for role in ("-read", "-hb", "-watchdog")
                    if f"{self.name}{role}" not in running]
        reopening = self._reconnect_task is not None and not self._reconnect_task.done()
        if self.state is LinkState.DISCONNECTED and self._reopen is not None and self._connected_once and not reopening:
            return [f"{self.name}: link down and not being reopened"]
        return []

    async def _open_session(self) -> None:
        """Read, greet, then heartbeat and watch on the current streams."""
        self.state = LinkState.CONNECTING
        self._events_seen.clear()  # a re-plugged panel may have restarted its sequence numbers
        self._tasks.append(asyncio.create_task(self._read_loop(), name=f"{self.name}-read"))
        hello, attempts = await self._handshake()
        self.state, self.fault = LinkState.CONNECTED, None
        self._connected_once = True
        self._set_estop(hello.args[2] == "1")
        self._tasks.append(asyncio.create_task(self._heartbeat_loop(), name=f"{self.name}-hb"))
        self._tasks.append(asyncio.create_task(self._watchdog_loop(), name=f"{self.name}-watchdog"))
        self._log.info("panel_connected", estop=self._estop, hello_attempts=attempts)

    async def _handshake(self) -> tuple[Line, int]:
        """HELLO until the panel answers with our protocol version; (its HELLO, attempts)."""
        loop = asyncio.get_running_loop()
        started, attempts = loop.time(), 0
        hello: Line | None = None
        while hello is None:
            if self.state is LinkState.DISCONNECTED:
                raise self.fault  # type: ignore[misc]
            if loop.time() - started >= self.CONNECT_TIMEOUT_S:
                raise PanelTimeout(self.name, f"HELLO {protocol.PROTOCOL_VERSION}",
                                   self.HELLO_RETRY_S, attempts)
            self._hello = loop.create_future()
            attempts += 1
            await self._send("HELLO", str(protocol.PROTOCOL_VERSION))
            try:
                # asyncio.timeout, not wait_for: on 3.11 wait_for drops a cancel landing with the answer
                async with asyncio.timeout(self.HELLO_RETRY_S):
                    hello = await asyncio.shield(self._hello)
            except TimeoutError:
                continue
        version = int(hello.args[1])
        if version != protocol.PROTOCOL_VERSION:
            raise PanelProtocolError(
                self.name, protocol.encode(hello, FROM_PANEL),
                f"panel speaks protocol {version}, host speaks {protocol.PROTOCOL_VERSION}",
            )
        return hello, attempts

    def events(self) -> AsyncIterator[PanelEvent]:
        """Events from now on, each subscriber its own queue; starts with the current conditions
        (HEARTBEAT_LOST while the link is down, ESTOP_PRESSED while the e-stop is held)."""
        queue: asyncio.Queue[Any] = asyncio.Queue()
        if self.state is LinkState.CLOSED:
            queue.put_nowait(_END)
        else:
            if self.fault is not None:
                queue.put_nowait(PanelEvent.HEARTBEAT_LOST)
            elif self._estop:
                queue.put_nowait(PanelEvent.ESTOP_PRESSED)
            if self.state is LinkState.DISCONNECTED and self._reopen is None:
                queue.put_nowait(_END)
            else:
                self._subscribers.append(queue)
        return self._drain(queue)

    async def set_status(self, led: StatusLed) -> None:
        """Show ``led`` on the status LED; returns when the panel acknowledged it."""
        await self._command("LED", led.value)
        self.status_led = led

    async def set_light(self, on: bool) -> None:
        """Switch the LED light panel that illuminates the subject; returns when acknowledged."""
        await self._command("LIGHT", "1" if on else "0")
        self.light_on = on

    async def close(self) -> None:
        """Say BYE (the panel then shows OFF and switches the lights off) and release the link."""
        if self.state is LinkState.CLOSED:
            return
        if self.state in (LinkState.CONNECTED, LinkState.LOST):
            try:  # BYE is not acknowledged: a panel that misses it shows FAULT on its own
                async with asyncio.timeout(self.BYE_TIMEOUT_S):
                    await self._send("BYE")
            except (TimeoutError, PanelDisconnected) as exc:
                self._log.warning("panel_bye_not_sent", error=str(exc))
        self.state = LinkState.CLOSED
        if self._reconnect_task is not None:
            self._reconnect_task.cancel()
            await asyncio.gather(self._reconnect_task, return_exceptions=True)
        await self._stop_tasks()
        self._bad_line_log.flush()
        if self._writer is None:  # never opened
            self._end_subscribers()
            return
        self._writer.close()
        try:
            await self._writer.wait_closed()
        except (OSError, ConnectionError) as exc:  # the link was already broken; nothing to release
            self._log.info("panel_link_closed_broken", error=str(exc))
        self._end_subscribers()
        self._log.info("panel_closed")

    # ------------------------------------------------------------------ sending

    async def _send(self, verb: str, *args: str) -> int:
        seq = self._seq
        self._seq = protocol.next_seq(seq)
        raw = protocol.encode(Line(seq, verb, args), FROM_HOST)
        if self.state is LinkState.DISCONNECTED:
            raise self.fault  # type: ignore[misc]
        if self._writer is None:  # never opened
            raise PanelStateError(self.name, self.state.value, f"send {verb}")
        try:
            self._writer.write(raw)
            await self._writer.drain()
        except (OSError, ConnectionError) as exc:
            self._disconnected(f"write failed: {type(exc).__name__}: {exc}")
            raise self.fault from exc  # type: ignore[misc]
        return seq

    async def _command(self, verb: str, arg: str) -> None:
        if self.state in (LinkState.NEW, LinkState.CONNECTING, LinkState.CLOSED):
            raise PanelStateError(self.name, self.state.value, f"send {verb} {arg}")
        loop = asyncio.get_running_loop()
        for _attempt in range(self.COMMAND_ATTEMPTS):
            future: asyncio.Future[Line] = loop.create_future()
            seq = self._seq
            self._pending[seq] = future
            try:
                await self._send(verb, arg)
                async with asyncio.timeout(self.ACK_TIMEOUT_S):
                    answer = await future
            except TimeoutError:
                self._log.warning("panel_ack_missing", command=f"{verb} {arg}", seq=seq)
                continue
            finally:
                self._pending.pop(seq, None)
            if answer.verb == "NAK":
                raise PanelCommandRefused(self.name, f"{verb} {arg}", answer.args[1])
            return
        timeout = PanelTimeout(self.name, f"{verb} {arg}", self.ACK_TIMEOUT_S, self.COMMAND_ATTEMPTS)
        if self.fault is not None:  # the lost heartbeat is the cause worth reporting
            raise self.fault from timeout
        raise timeout

    async def _heartbeat_loop(self) -> None:
        while True:
            try:
                await self._send("HB")
            except PanelDisconnected:  # latched as the fault and announced by _disconnected
                return
            await asyncio.sleep(self.HEARTBEAT_PERIOD_S)

    # ------------------------------------------------------------------ receiving

    async def _read_loop(self) -> None:
        buffer = b""
        while True:
            if self._reader is None:  # never opened
                raise PanelStateError(self.name, self.state.value, "read")
            try:
                chunk = await self._reader.read(self.READ_CHUNK)
            except (OSError, ConnectionError) as exc:
                self._disconnected(f"read failed: {type(exc).__name__}: {exc}")
                return
            if not chunk:
                self._disconnected("end of stream")
                return
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            for raw in lines:
                self._receive(raw + b"\n")
            if len(buffer) > protocol.MAX_LINE_BYTES:  # no newline in sight: drop it as one bad line
                self._bad_line(PanelProtocolError(self.name, buffer, "line without end"))
                buffer = b""

    def _receive(self, raw: bytes) -> None:
        try:
            line = protocol.parse(raw, FROM_PANEL, device=self.name)
        except PanelProtocolError as exc:
            self._bad_line(exc)
            return
        handler = getattr(self, f"_on_{line.verb.lower()}")
        handler(line)

    def _bad_line(self, error: PanelProtocolError) -> None:
        self.bad_lines += 1
        self.last_error = error
        self._bad_line_log.report(error=str(error))

    def _on_hello(self, line: Line) -> None:
        if self._hello is not None and not self._hello.done():
            self._hello.set_result(line)

    def _on_hb(self, line: Line) -> None:
        self._heartbeat_seen.set()
        self.reported_light = line.args[1] == "1"
        self.reported_led = StatusLed(line.args[2])
        if self.state is LinkState.LOST:
            self.state, self.fault = LinkState.CONNECTED, None
            self._log.info("panel_reconnected")
            self._emit(PanelEvent.RECONNECTED)
        if self.state is LinkState.CONNECTED:
            self._set_estop(line.args[0] == "1")

    def _on_evt(self, line: Line) -> None:
        loop = asyncio.get_running_loop()
        self._spawn_send("ACK", f"{line.seq:02X}")
        now = loop.time()
        self._events_seen = {s: t for s, t in self._events_seen.items()
                             if now - t < self.EVENT_MEMORY_S}
        if line.seq in self._events_seen:
            return
        self._events_seen[line.seq] = now
        signal = PanelSignal(line.args[0])
        if signal in _SIGNAL_EVENTS:
            self._emit(_SIGNAL_EVENTS[signal])
        else:
            self._set_estop(signal is PanelSignal.ESTOP_ON)

    def _on_ack(self, line: Line) -> None:
        self._answer(line)

    def _on_nak(self, line: Line) -> None:
        self._answer(line)

    def _answer(self, line: Line) -> None:
        future = self._pending.get(int(line.args[0], 16))
        if future is not None and not future.done():
            future.set_result(line)

    def _set_estop(self, pressed: bool) -> None:
        if pressed == self._estop:
            return
        self._estop = pressed
        self._log.warning("panel_estop", pressed=pressed)
        self._emit(PanelEvent.ESTOP_PRESSED if pressed else PanelEvent.ESTOP_RELEASED)

    def _spawn_send(self, verb: str, *args: str) -> None:
        task = asyncio.create_task(self._send_quietly(verb, *args))
        self._tasks.append(task)
        task.add_done_callback(self._forget)

    async def _send_quietly(self, verb: str, *args: str) -> None:
        try:
            await self._send(verb, *args)
        except PanelDisconnected:  # already latched as the fault and announced
            return

    def _forget(self, task: asyncio.Task[None]) -> None:
        if task in self._tasks:
            self._tasks.remove(task)

    # ------------------------------------------------------------------ loss

    async def _watchdog_loop(self) -> None:
        loop = asyncio.get_running_loop()
        last = loop.time()
        while True:
            self._heartbeat_seen.clear()
            try:
                async with asyncio.timeout(self.HEARTBEAT_TIMEOUT_S):
                    await self._heartbeat_seen.wait()
                last = loop.time()
            except TimeoutError:
                if self.state is LinkState.CONNECTED:
                    self.fault = PanelHeartbeatLost(
                        self.name, loop.time() - last, self.bad_lines, self.last_error
                    )
                    self.state = LinkState.LOST
                    self._log.error("panel_heartbeat_lost", error=str(self.fault))
                    self._emit(PanelEvent.HEARTBEAT_LOST)

    def _disconnected(self, cause: str) -> None:
        if self.state in (LinkState.DISCONNECTED, LinkState.CLOSED):
            return
        self.state = LinkState.DISCONNECTED
        self.fault = PanelDisconnected(self.name, cause)
        self._log.error("panel_disconnected", error=str(self.fault))
        for future in self._pending.values():
            if not future.done():
                future.set_exception(self.fault)
        if self._hello is not None and not self._hello.done():
            self._hello.set_exception(self.fault)
        reconnecting = self._reconnect_task is not None and not self._reconnect_task.done()
        if not reconnecting:  # a failed reopen attempt has already been announced
            self._emit(PanelEvent.HEARTBEAT_LOST)
        current = asyncio.current_task()
        for task in self._tasks:
            if task is not current:
                task.cancel()
        if self._reopen is None:
            self._end_subscribers()
        elif not reconnecting and self._connected_once:
            self._reconnect_task = asyncio.create_task(self._reconnect_loop(),
                                                       name=f"{self.name}-reconnect")

    async def _reconnect_loop(self) -> None:
        """Reopen the link every REOPEN_PERIOD_S until the panel answers HELLO again."""
        while True:
            await asyncio.sleep(self.REOPEN_PERIOD_S)
            try:
                if self._writer is not None:
                    self._writer.close()
                self._reader, self._writer = await self._reopen()  # type: ignore[misc]
                await self._stop_tasks()
                await self._open_session()
            except (PanelError, OSError) as exc:
                self.state = LinkState.DISCONNECTED
                self._log.info("panel_reopen_failed", error=str(exc))
                continue
            self._log.info("panel_reconnected", how="reopened")
            self._emit(PanelEvent.RECONNECTED)
            return

    # ------------------------------------------------------------------ plumbing

    def _emit(self, event: PanelEvent) -> None:
        self._log.info("panel_event", panel_event=event.name)
        for queue in self._subscribers:
            queue.put_nowait(event)

    def _end_subscribers(self) -> None:
        for queue in self._subscribers:
            queue.put_nowait(_END)
        self._subscribers.clear()

    async def _drain(self, queue: asyncio.Queue[Any]) -> AsyncIterator[PanelEvent]:
        try:
            while (item := await queue.get()) is not _END:
                yield item
        finally:
            if queue in self._subscribers:
                self._subscribers.remove(queue)

    async def _stop_tasks(self) -> None:
        current = asyncio.current_task()
        tasks = [t for t in self._tasks if t is not current]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self._tasks.clear()

