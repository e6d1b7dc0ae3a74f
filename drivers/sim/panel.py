"""A simulated operator panel: the firmware side of the panel line protocol.

It sends ``HB`` every 200 ms, reports button presses and e-stop changes as ``EVT`` lines that it
repeats until the host acknowledges them, obeys ``LED``/``LIGHT``/``BYE`` and, once a host has
greeted it, shows FAULT and switches the lights off when the host's heartbeat stops - the
behaviour docs/panel-protocol.md asks of the real firmware. It runs over any asyncio stream pair
(a socketpair in the simulated rig) or over a pty whose slave the host opens like a real tty.

Faults: stop/resume heartbeats, garbage bytes, corrupted checksums, ignored commands, NAKs,
another protocol version, a pulled cable.

``tbp sim panel`` serves one on a pty and prints the path.
"""

from __future__ import annotations

import asyncio
import os
import random
import tty
from collections.abc import Callable
from typing import Any

import structlog

from drivers.panel import protocol
from drivers.panel.errors import PanelProtocolError
from drivers.panel.protocol import FROM_HOST, FROM_PANEL, Line, PanelSignal, StatusLed
from drivers.panel.serial_link import open_fd_streams

log = structlog.get_logger(__name__)


class SimulatedPanel:
    """The panel firmware on (reader, writer).

    Args:
        reader, writer: the panel's end of the link.
        estop: the e-stop is pressed at power-on.
        protocol_version: the version it answers HELLO with.
        noise: fraction of the lines it sends that arrive with a broken checksum.
        seed: seeds the choice of those lines.
        name: used in logs.
    """

    HEARTBEAT_PERIOD_S = protocol.HEARTBEAT_PERIOD_S
    HOST_TIMEOUT_S = protocol.HEARTBEAT_TIMEOUT_S
    EVENT_RESEND_S = protocol.EVENT_RESEND_S
    EVENT_RESENDS = protocol.EVENT_RESENDS
    MAX_UNSENT_BYTES = 4096  # a UART with nobody listening drops what does not fit

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        *,
        estop: bool = False,
        protocol_version: int = protocol.PROTOCOL_VERSION,
        noise: float = 0.0,
        seed: int = 0,
        name: str = "sim-panel",
    ) -> None:
        self._reader, self._writer = reader, writer
        self.name = name
        self.estop = estop
        self.protocol_version = protocol_version
        self.led = StatusLed.OFF
        self.light = False
        self.host_seen = False  # a host greeted the panel and has not said BYE
        self.host_lost = False
        self.on_change: Callable[[SimulatedPanel], None] | None = None  # LED, light or host changed
        self.received: list[Line] = []  # every valid host line, for assertions
        self.bad_lines = 0
        self.heartbeats = True
        self.ignore_commands = False
        self.nak_reason: str | None = None
        self.corrupt_next = 0
        self.noise = noise
        self._rng = random.Random(seed)
        self.dropped_bytes = 0
        self._seq = 0
        self._last_raw = b""
        self._pty_slave: int | None = None
        self._unacked: dict[int, bytes] = {}
        self._last_host_line = 0.0
        self._closed = False
        self._tasks: list[asyncio.Task[Any]] = []
        self._log = log.bind(panel=name)

    # ------------------------------------------------------------------ operator

    def press_start(self) -> None:
        self._event(PanelSignal.START)

    def press_stop(self) -> None:
        self._event(PanelSignal.STOP)

    def press_estop(self) -> None:
        if not self.estop:
            self.estop = True
            self._event(PanelSignal.ESTOP_ON)

    def release_estop(self) -> None:
        if self.estop:
            self.estop = False
            self._event(PanelSignal.ESTOP_OFF)

    # ------------------------------------------------------------------ faults

    def stop_heartbeats(self) -> None:
        self.heartbeats = False

    def resume_heartbeats(self) -> None:
        self.heartbeats = True

    def send_garbage(self, raw: bytes) -> None:
        """Put ``raw`` on the line as it is (noise, a half line, a firmware bug)."""
        self._write(raw)

    def corrupt_lines(self, n: int) -> None:
        """Send the next ``n`` lines with a wrong checksum."""
        self.corrupt_next = n

    def disconnect(self) -> None:
        """Pull the cable: the host sees the stream end."""
        self._closed = True
        self._writer.close()

    # ------------------------------------------------------------------ running

    async def run(self) -> None:
        """Serve the link until it ends or the task is cancelled."""
        self._last_host_line = asyncio.get_running_loop().time()
        heartbeat = asyncio.create_task(self._heartbeat_loop(), name=f"{self.name}-hb")
        try:
            await self._read_loop()
        finally:
            heartbeat.cancel()
            for task in self._tasks:
                task.cancel()
            await asyncio.gather(heartbeat, *self._tasks, return_exceptions=True)

    async def _heartbeat_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while not self._closed:
            if self.heartbeats:
                self._send("HB", "1" if self.estop else "0", "1" if self.light else "0",
                           self.led.value)
            if (self.host_seen and not self.host_lost
                    and loop.time() - self._last_host_line > self.HOST_TIMEOUT_S):
                self.host_lost = True
                self.led, self.light = StatusLed.FAULT, False
                self._log.warning("sim_panel_host_lost")
                self._changed()
            await asyncio.sleep(self.HEARTBEAT_PERIOD_S)

    async def _read_loop(self) -> None:
        buffer = b""
        while not self._closed:
            try:
                chunk = await self._reader.read(256)
            except (OSError, ConnectionError):
                return
            if not chunk:
                return
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            for raw in lines:
                self._receive(raw + b"\n")
            if len(buffer) > protocol.MAX_LINE_BYTES:
                self.bad_lines += 1
                buffer = b""

    def _receive(self, raw: bytes) -> None:
        before = (self.led, self.light, self.host_lost)
        self._obey(raw)
        if (self.led, self.light, self.host_lost) != before:
            self._changed()

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change(self)

    def _obey(self, raw: bytes) -> None:
        try:
            line = protocol.parse(raw, FROM_HOST, device=self.name)
        except PanelProtocolError as exc:
            self.bad_lines += 1
            self._log.info("sim_panel_bad_line", error=str(exc))
            return
        self.received.append(line)
        self._last_host_line = asyncio.get_running_loop().time()
        self.host_seen = line.verb != "BYE"
        if self.host_lost:
            self.host_lost = False
            self._log.info("sim_panel_host_back")
        if line.verb == "ACK":
            self._unacked.pop(int(line.args[0], 16), None)
            return
        if line.verb == "HB":
            return
        if self.ignore_commands:
            return
        if line.verb == "HELLO":
            self._send("HELLO", protocol.PRODUCT, str(self.protocol_version),
                       "1" if self.estop else "0")
            return
        if line.verb == "BYE":
            self.led, self.light = StatusLed.OFF, False
            return
        if self.nak_reason is not None:
            self._send("NAK", f"{line.seq:02X}", self.nak_reason)
            return
        if line.verb == "LED":
            self.led = StatusLed(line.args[0])
        elif line.verb == "LIGHT":
            self.light = line.args[0] == "1"
        self._send("ACK", f"{line.seq:02X}")

    # ------------------------------------------------------------------ sending

    def _event(self, signal_: PanelSignal) -> None:
        seq = self._send("EVT", signal_.value)
        self._unacked[seq] = self._last_raw
        task = asyncio.get_running_loop().create_task(self._resend(seq))
        self._tasks.append(task)
        task.add_done_callback(self._tasks.remove)

    async def _resend(self, seq: int) -> None:
        for _ in range(self.EVENT_RESENDS):
            await asyncio.sleep(self.EVENT_RESEND_S)
            raw = self._unacked.get(seq)
            if raw is None:
                return
            self._write(raw)
        self._unacked.pop(seq, None)

    def _send(self, verb: str, *args: str) -> int:
        seq = self._seq
        self._seq = protocol.next_seq(seq)
        raw = protocol.encode(Line(seq, verb, args), FROM_PANEL)
        self._last_raw = raw  # a resend repeats the line as meant, not as the noise left it
        noisy = self.noise > 0 and self._rng.random() < self.noise
        if self.corrupt_next > 0 or noisy:
            self.corrupt_next = max(0, self.corrupt_next - 1)
            body, crc = raw[:-3], int(raw[-3:-1], 16)
            raw = body + b"%02X\n" % (crc ^ 0x5A)
        self._write(raw)
        return seq

    def _write(self, raw: bytes) -> None:
        if self._closed or self._writer.is_closing():
            return
        if self._writer.transport.get_write_buffer_size() > self.MAX_UNSENT_BYTES:
            self.dropped_bytes += len(raw)
            return
        self._writer.write(raw)

    # ------------------------------------------------------------------ pty

    @classmethod
    async def on_pty(cls, **options: Any) -> tuple[SimulatedPanel, str]:
        """A panel on the master side of a new pty; returns it and the slave's path for the host."""
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline until the host configures the port
        path = os.ttyname(slave)
        reader, writer = await open_fd_streams(master)
        panel = cls(reader, writer, **options)
        panel._pty_slave = slave  # held open: the master never reads EIO between host sessions
        return panel, path

    def close(self) -> None:
        """Close the link (and the pty slave this panel holds); idempotent."""
        self._closed = True
        self._writer.close()
        if self._pty_slave is not None:
            os.close(self._pty_slave)
            self._pty_slave = None
