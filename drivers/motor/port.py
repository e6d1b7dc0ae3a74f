"""CAN frame ports for asyncio: the one narrow interface the CANopen layer talks through.

* :class:`PythonCanPort` wraps any python-can bus (``socketcan`` on the rig, ``slcan`` for serial
  adapters, ``virtual`` in tests, ``socketcand`` for a simulator in another process). python-can's
  :class:`can.Notifier` delivers frames into the event loop (its reader thread is used only for
  real buses).
* :class:`LazyCanPort` opens its bus on first use, so a drive object can exist before its
  bus does (a CAN adapter not plugged in yet, a socketcand bridge not up): the daemon's drive
  is made at start-up and connected, or not, under the bring-up's timeout.
* :class:`LoopbackCanBus` is an in-process, thread-free bus: every frame sent on one of its ports
  is queued on every other port in the same call, so nothing is ever "in flight" and a
  virtual-time event loop can jump safely.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import Awaitable, Callable
from typing import Any, Protocol, runtime_checkable

import can
import structlog

from drivers.motor.errors import CanBusError

log = structlog.get_logger(__name__)


@runtime_checkable
class CanPort(Protocol):
    """An asyncio CAN frame port."""

    name: str

    async def send(self, msg: can.Message) -> None:
        """Put one frame on the bus."""

    async def recv(self) -> can.Message:
        """The next frame from the bus; raises :class:`CanBusError` once the port is closed."""

    def close(self) -> None:
        """Stop the port (idempotent); a pending ``recv`` raises :class:`CanBusError`."""


_CLOSED = object()


class LoopbackCanBus:
    """An in-process CAN bus without threads: ports deliver frames to each other immediately.

    Like a real bus, a sender does not receive its own frames. Frames are stamped with the
    event loop's clock at sending.
    """

    def __init__(self, name: str = "loopback") -> None:
        self.name = name
        self._ports: list[LoopbackPort] = []

    def port(self, name: str | None = None) -> LoopbackPort:
        """A new port attached to this bus."""
        port = LoopbackPort(self, name or f"{self.name}{len(self._ports)}")
        self._ports.append(port)
        return port

    def _deliver(self, sender: LoopbackPort, msg: can.Message) -> None:
        for port in self._ports:
            if port is not sender and not port.closed:
                port._queue.put_nowait(msg)

    def _detach(self, port: LoopbackPort) -> None:
        if port in self._ports:
            self._ports.remove(port)


class LoopbackPort:
    """One node's attachment to a :class:`LoopbackCanBus`."""

    def __init__(self, bus: LoopbackCanBus, name: str) -> None:
        self.name = name
        self.closed = False
        self._bus = bus
        self._queue: asyncio.Queue[Any] = asyncio.Queue()

    async def send(self, msg: can.Message) -> None:
        if self.closed:
            raise CanBusError(self.name, "closed", f"cannot send 0x{msg.arbitration_id:03X}")
        frame = can.Message(
            timestamp=asyncio.get_running_loop().time(),
            arbitration_id=msg.arbitration_id,
            is_extended_id=msg.is_extended_id,
            is_remote_frame=msg.is_remote_frame,
            data=bytes(msg.data),
            is_rx=True,
            channel=self._bus.name,
        )
        self._bus._deliver(self, frame)

    async def recv(self) -> can.Message:
        if self.closed:
            raise CanBusError(self.name, "closed", "port is closed")
        item = await self._queue.get()
        if item is _CLOSED:
            raise CanBusError(self.name, "closed", "port closed while receiving")
        return item

    def recv_ready(self) -> list[can.Message]:
        """The frames already waiting, without waiting for more (a bridge sends them in one write)."""
        frames = []
        while not self._queue.empty():
            item = self._queue.get_nowait()
            if item is _CLOSED:  # nothing follows it: left for the next recv to raise
                self._queue.put_nowait(item)
                break
            frames.append(item)
        return frames

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._bus._detach(self)
        self._queue.put_nowait(_CLOSED)


async def _bridge_answers(host: str, port: int, name: str) -> None:
    try:
        _, writer = await asyncio.open_connection(host, port)
    except OSError as exc:
        raise CanBusError(name, "closed", f"socketcand bridge {host}:{port} does not answer: "
                                          f"{exc.strerror or exc}") from exc
    writer.close()
    with contextlib.suppress(OSError):  # the probe's own hang-up
        await writer.wait_closed()


class _Reader(can.AsyncBufferedReader):
    """python-can's asyncio reader, also waking ``recv`` on bus errors and on close."""

    def on_error(self, exc: Exception) -> None:
        self.buffer.put_nowait(exc)  # type: ignore[arg-type]

    def wake_closed(self) -> None:
        self.buffer.put_nowait(_CLOSED)  # type: ignore[arg-type]


class PythonCanPort:
    """A :class:`CanPort` over a python-can bus; the port owns the bus and shuts it down on close.

    Must be created inside the running event loop (the notifier schedules frames into it).
    """

    RECEIVE_CYCLE_S = 0.05  # the notifier thread's receive timeout: bounds how long close() blocks

    def __init__(self, bus: can.BusABC, *, name: str | None = None) -> None:
        self.name = name or str(getattr(bus, "channel_info", "can"))
        self.bus = bus
        self.closed = False
        self._reader = _Reader()
        self._notifier = can.Notifier(
            bus, [self._reader], timeout=self.RECEIVE_CYCLE_S, loop=asyncio.get_running_loop()
        )

    @classmethod
    def open(cls, interface: str, channel: str, *, name: str | None = None, **kwargs: Any) -> PythonCanPort:
        """Open a python-can bus by interface name (``socketcan``, ``slcan``, ``virtual``,
        ``socketcand``...) and wrap it; the interface's SDK is imported only when chosen."""
        try:
            bus = can.Bus(interface=interface, channel=channel, **kwargs)
        except (can.CanError, OSError, ValueError) as exc:
            raise CanBusError(name or channel, "closed", f"cannot open {interface} {channel}: {exc}") from exc
        return cls(bus, name=name or f"{interface}:{channel}")

    @classmethod
    async def connect(cls, interface: str, channel: str, *, name: str | None = None,
                      **kwargs: Any) -> PythonCanPort:
        """:meth:`open` without blocking the loop: a socketcand bridge's port is tried first (a
        refused connection fails at once, where python-can would retry for 10 s), then the bus
        is opened in a thread."""
        name = name or f"{interface}:{channel}"
        if interface == "socketcand":
            await _bridge_answers(kwargs["host"], kwargs["port"], name)
        loop = asyncio.get_running_loop()
        try:
            bus = await loop.run_in_executor(None, functools.partial(can.Bus, interface=interface,
                                                                     channel=channel, **kwargs))
        except (can.CanError, OSError, ValueError) as exc:
            raise CanBusError(name, "closed", f"cannot open {interface} {channel}: {exc}") from exc
        return cls(bus, name=name)

    async def send(self, msg: can.Message) -> None:
        if self.closed:
            raise CanBusError(self.name, "closed", f"cannot send 0x{msg.arbitration_id:03X}")
        try:
            self.bus.send(msg)
        except (can.CanError, OSError) as exc:
            raise CanBusError(self.name, "open", f"send 0x{msg.arbitration_id:03X} failed: {exc}") from exc

    async def recv(self) -> can.Message:
        if self.closed:
            raise CanBusError(self.name, "closed", "port is closed")
        item: Any = await self._reader.get_message()
        if item is _CLOSED:
            raise CanBusError(self.name, "closed", "port closed while receiving")
        if isinstance(item, Exception):
            raise CanBusError(self.name, "failed", f"bus receive failed: {item}") from item
        return item

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._notifier.stop(timeout=4 * self.RECEIVE_CYCLE_S)
        finally:
            self._reader.wake_closed()
            self.bus.shutdown()


class LazyCanPort:
    """A :class:`CanPort` that opens its bus (``await opener()``, e.g. :meth:`PythonCanPort.connect`)
    on the first send or receive; an open that fails raises its :class:`CanBusError` there, and
    the next use tries again. Closing closes the bus for good."""

    def __init__(self, opener: Callable[[], Awaitable[CanPort]], name: str) -> None:
        self.name = name
        self.closed = False
        self._opener = opener
        self._port: CanPort | None = None
        self._opening: asyncio.Lock | None = None

    async def _opened(self) -> CanPort:
        if self._opening is None:
            self._opening = asyncio.Lock()
        async with self._opening:  # the first send and the first receive open one bus
            if self.closed:
                raise CanBusError(self.name, "closed", "port is closed")
            if self._port is None:
                port = await self._opener()
                if self.closed:  # closed while opening
                    port.close()
                    raise CanBusError(self.name, "closed", "port closed while opening")
                self._port = port
            return self._port

    async def send(self, msg: can.Message) -> None:
        await (await self._opened()).send(msg)

    async def recv(self) -> can.Message:
        return await (await self._opened()).recv()

    def close(self) -> None:
        self.closed = True
        port, self._port = self._port, None
        if port is not None:
            port.close()
