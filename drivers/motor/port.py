"""CAN frame ports for asyncio: the one narrow interface the CANopen layer talks through.

* :class:`PythonCanPort` wraps any python-can bus (``socketcan`` on the rig, ``slcan`` for serial
  adapters, ``virtual`` in tests, ``socketcand`` for a simulator in another process). Its own
  receive and transmit threads talk to the bus; the event loop only queues frames and takes
  them, so a bus that stops draining never blocks it (a bounded queue turns that into a
  :class:`CanBusError`).
* :class:`LazyCanPort` opens its bus on first use, so a drive object can exist before its
  bus does (a CAN adapter not plugged in yet, a socketcand bridge not up): the daemon's drive
  is made at start-up and connected, or not, under the bring-up's timeout.
* :class:`LoopbackCanBus` is an in-process, thread-free bus: every frame sent on one of its ports
  is queued on every other port in the same call, so nothing is ever "in flight" and a
  virtual-time event loop can jump safely.

The real-time side (:class:`RealtimePort`: :class:`PythonCanPort`, and :class:`LazyCanPort` once
open) serves a guard thread that must act while the event loop stalls; both calls are
thread-safe, may be made from any thread, and never wait on the bus:

* ``send_urgent(msg)`` queues ``msg`` ahead of every ordinary frame, in a small lane of its own
  that drops its oldest frame when full (only the latest heartbeat or quick stop matters);
* ``tap(callback)`` calls ``callback(msg, monotonic_s)`` in the receive thread for every
  received frame, stamped with ``time.monotonic()`` at reception; it returns ``untap()``.

:class:`LoopbackPort` has no real-time side: in virtual time nothing stalls.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import socket
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable, Hashable
from dataclasses import dataclass
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


Tap = Callable[[can.Message, float], None]
"""tap(msg, monotonic_s): a received frame and the time.monotonic() of its reception."""


@runtime_checkable
class RealtimePort(Protocol):
    """The real-time side of a port, for a guard thread that must act while the event loop
    stalls. Both calls are thread-safe and never wait on the bus."""

    def send_urgent(self, msg: can.Message) -> None:
        """Queue ``msg`` ahead of every ordinary frame (the oldest urgent frame is dropped when
        the small urgent lane is full). Raises :class:`CanBusError` on a closed or failed port."""

    def tap(self, callback: Tap) -> Callable[[], None]:
        """Call ``callback(msg, monotonic_s)`` in the receive thread for every received frame;
        returns the function that removes it."""

    def stopped_threads(self) -> list[str]:
        """The names of the port's threads that ended while it is open (empty: all run)."""


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
        message: can.Message = item
        return message

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


@dataclass(frozen=True)
class _Failure:
    """A bus failure on its way from a port thread to ``recv``."""

    text: str
    cause: BaseException


class PythonCanPort:
    """A :class:`CanPort` over a python-can bus; the port owns the bus and shuts it down on close.

    Two threads of the port's own carry the frames, so the event loop never waits on the bus: a
    receive thread hands each frame to the loop (and to the taps), a transmit thread drains a
    bounded queue into the bus, each write bounded by :attr:`SEND_TIMEOUT_S` (python-can's send
    timeout; the serial port's write timeout for slcan; the socket's timeout for socketcand). A
    link that stops draining fills the queue and :meth:`send` raises :class:`CanBusError`; a
    failed write fails the port: the next :meth:`send` and :meth:`recv` raise it.

    Must be created inside the running event loop (the receive thread hands frames to it).
    """

    RECEIVE_CYCLE_S = 0.05  # the receive thread's bus.recv timeout: how soon it sees close()
    SEND_QUEUE_SIZE = 256  # ordinary frames waiting for the bus
    URGENT_QUEUE_SIZE = 4  # urgent frames waiting; the oldest is dropped when full
    SEND_TIMEOUT_S = 0.2  # the longest one write to the bus may take
    RELEASE_WAIT_S = 1.0  # how long opening a bus waits for its previous port to shut it down

    def __init__(self, bus: can.BusABC, *, name: str | None = None, key: Hashable = None) -> None:
        self.name = name or str(getattr(bus, "channel_info", "can"))
        self.bus = bus
        self.closed = False
        self._key = key
        self._loop = asyncio.get_running_loop()
        self._received: asyncio.Queue[Any] = asyncio.Queue()
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._ordinary: deque[can.Message] = deque()
        self._urgent: deque[can.Message] = deque(maxlen=self.URGENT_QUEUE_SIZE)
        self._taps: tuple[Tap, ...] = ()
        self._stopping = False
        self._send_failure: str | None = None
        self._receive_failure: str | None = None
        try:
            _bound_writes(bus, self.SEND_TIMEOUT_S, self.name)
        except CanBusError:
            bus.shutdown()
            raise
        self._receiver = threading.Thread(target=self._receive_loop, name=f"can-rx {self.name}", daemon=True)
        self._transmitter = threading.Thread(target=self._transmit_loop, name=f"can-tx {self.name}", daemon=True)
        self._receiver.start()
        self._transmitter.start()

    @classmethod
    def open(cls, interface: str, channel: str, *, name: str | None = None, **kwargs: Any) -> PythonCanPort:
        """Open a python-can bus by interface name (``socketcan``, ``slcan``, ``virtual``,
        ``socketcand``...) and wrap it; the interface's SDK is imported only when chosen. Waits
        (up to :attr:`RELEASE_WAIT_S`) for a port closed on the same bus to shut it down."""
        name = name or f"{interface}:{channel}"
        key = _bus_key(interface, channel, kwargs)
        _wait_released(key, name, cls.RELEASE_WAIT_S)
        try:
            bus = can.Bus(interface=interface, channel=channel, **kwargs)
        except (can.CanError, OSError, ValueError) as exc:
            raise CanBusError(name, "closed", f"cannot open {interface} {channel}: {exc}") from exc
        return cls(bus, name=name, key=key)

    @classmethod
    async def connect(cls, interface: str, channel: str, *, name: str | None = None,
                      **kwargs: Any) -> PythonCanPort:
        """:meth:`open` without blocking the loop: a socketcand bridge's port is tried first (a
        refused connection fails at once, where python-can would retry for 10 s), then the bus
        is opened in a thread."""
        name = name or f"{interface}:{channel}"
        key = _bus_key(interface, channel, kwargs)
        if interface == "socketcand":
            await _bridge_answers(kwargs["host"], kwargs["port"], name)
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, _wait_released, key, name, cls.RELEASE_WAIT_S)
        try:
            bus = await loop.run_in_executor(None, functools.partial(can.Bus, interface=interface,
                                                                     channel=channel, **kwargs))
        except (can.CanError, OSError, ValueError) as exc:
            raise CanBusError(name, "closed", f"cannot open {interface} {channel}: {exc}") from exc
        return cls(bus, name=name, key=key)

    async def send(self, msg: can.Message) -> None:
        """Queue one frame for the bus (never waits for the bus).

        Raises:
            CanBusError: the port is closed or failed, or its queue is full (the link does not
                drain).
        """
        self._queue(msg, urgent=False)

    def send_urgent(self, msg: can.Message) -> None:
        """Queue one frame ahead of every ordinary frame; thread-safe, never waits. A full urgent
        lane drops its oldest frame."""
        self._queue(msg, urgent=True)

    def tap(self, callback: Tap) -> Callable[[], None]:
        """Call ``callback(msg, monotonic_s)`` in the receive thread for every frame received
        from now on; returns the function that removes it. Thread-safe. A callback that raises
        fails the port's reception (recv raises it)."""
        with self._lock:
            if self.closed:
                raise CanBusError(self.name, "closed", "cannot tap a closed port")
            self._taps = (*self._taps, callback)

        def untap() -> None:
            with self._lock:
                self._taps = tuple(t for t in self._taps if t is not callback)

        return untap

    def stopped_threads(self) -> list[str]:
        if self.closed:
            return []
        return [t.name for t in (self._receiver, self._transmitter) if not t.is_alive()]

    async def recv(self) -> can.Message:
        if self.closed:
            raise CanBusError(self.name, "closed", "port is closed")
        failure = self._send_failure or self._receive_failure
        if failure is not None and self._received.empty():
            raise CanBusError(self.name, "failed", failure)
        item: Any = await self._received.get()
        if item is _CLOSED:
            raise CanBusError(self.name, "closed", "port closed while receiving")
        if isinstance(item, _Failure):
            raise CanBusError(self.name, "failed", item.text) from item.cause
        message: can.Message = item
        return message

    def close(self) -> None:
        """Stop the port without waiting for it: the receive thread stops within
        :attr:`RECEIVE_CYCLE_S`, the transmit thread sends what is queued, then shuts the bus
        down once the receive thread has ended. Idempotent; a pending ``recv`` raises."""
        with self._wake:
            if self.closed:
                return
            self.closed = True
            self._stopping = True
            if self._key is not None:
                with _RELEASING_LOCK:
                    _RELEASING[self._key] = self._transmitter
            self._wake.notify_all()
        self._received.put_nowait(_CLOSED)

    # ------------------------------------------------------------------ threads

    def _queue(self, msg: can.Message, *, urgent: bool) -> None:
        with self._wake:
            if self.closed:
                raise CanBusError(self.name, "closed", f"cannot send 0x{msg.arbitration_id:03X}")
            if self._send_failure is not None:
                raise CanBusError(self.name, "failed",
                                  f"cannot send 0x{msg.arbitration_id:03X}: {self._send_failure}")
            if urgent:
                self._urgent.append(msg)
            elif len(self._ordinary) >= self.SEND_QUEUE_SIZE:
                raise CanBusError(self.name, "open", f"transmit queue full ({self.SEND_QUEUE_SIZE} frames): the "
                                                     f"link does not drain; 0x{msg.arbitration_id:03X} not sent")
            else:
                self._ordinary.append(msg)
            self._wake.notify()

    def _transmit_loop(self) -> None:
        try:
            while True:
                with self._wake:
                    while not (self._urgent or self._ordinary or self._stopping):
                        self._wake.wait()
                    if self._urgent:
                        msg = self._urgent.popleft()
                    elif self._ordinary:
                        msg = self._ordinary.popleft()
                    else:
                        return
                try:
                    self.bus.send(msg, timeout=self.SEND_TIMEOUT_S)
                except Exception as exc:  # every failure of the bus fails the port, reported to send and recv
                    text = f"send 0x{msg.arbitration_id:03X} failed: {exc or type(exc).__name__}"
                    with self._wake:
                        self._send_failure = text
                        self._ordinary.clear()
                        self._urgent.clear()
                    self._to_loop(_Failure(text, exc))
                    with self._wake:
                        while not self._stopping:
                            self._wake.wait()
                    return
        finally:
            self._receiver.join()
            try:
                self.bus.shutdown()
            except Exception as exc:  # the port is closed: nobody is left to raise it to
                log.warning("can_bus_shutdown_failed", port=self.name, error=str(exc))
            with _RELEASING_LOCK:
                if _RELEASING.get(self._key) is threading.current_thread():
                    del _RELEASING[self._key]

    def _receive_loop(self) -> None:
        while not self._stopping:
            try:
                msg = self.bus.recv(self.RECEIVE_CYCLE_S)
            except Exception as exc:  # every failure of the bus fails reception, reported to recv
                self._receive_failed(f"bus receive failed: {exc}", exc)
                return
            if msg is None:
                continue
            stamp = time.monotonic()
            try:
                for tap in self._taps:
                    tap(msg, stamp)
            except Exception as exc:  # a broken tap must not leave its guard blind unnoticed
                self._receive_failed(f"tap {getattr(tap, '__qualname__', tap)!s} failed: {exc!r}", exc)
                return
            if not self._to_loop(msg):
                return

    def _receive_failed(self, text: str, exc: BaseException) -> None:
        self._receive_failure = text
        self._to_loop(_Failure(text, exc))

    def _to_loop(self, item: Any) -> bool:
        """Hand ``item`` to ``recv``; False once the loop is closed (the port's owner is gone,
        so the threads end and the bus is shut down)."""
        try:
            self._loop.call_soon_threadsafe(self._received.put_nowait, item)
        except RuntimeError:
            with self._wake:
                self._stopping = True
                self._wake.notify_all()
            return False
        return True


_RELEASING: dict[Hashable, threading.Thread] = {}
"""Bus key -> the transmit thread of a closed port that has not shut its bus down yet."""
_RELEASING_LOCK = threading.Lock()


def _bus_key(interface: str, channel: str, options: dict[str, Any]) -> Hashable:
    return interface, channel, options.get("host"), options.get("port")


def _wait_released(key: Hashable, name: str, timeout_s: float) -> None:
    """Wait until the bus a closed port still holds is shut down (a serial adapter opened twice
    would lose the new link's frames to the old one, and the old one's close command).

    Raises:
        CanBusError: the old port's transmit thread is stuck in a write for ``timeout_s``.
    """
    with _RELEASING_LOCK:
        thread = _RELEASING.get(key)
    if thread is None:
        return
    thread.join(timeout_s)
    if thread.is_alive():
        raise CanBusError(name, "closed", f"the previous port on this bus has not shut it down within "
                                          f"{timeout_s:g} s: its transmit thread is stuck in a write")


def _bound_writes(bus: can.BusABC, timeout_s: float, name: str) -> None:
    """Give the writes that python-can's ``send(timeout=)`` leaves unbounded a timeout: the
    socketcand client's socket (its ``sendall``), the slcan serial port (open and close commands).

    Raises:
        CanBusError: the installed python-can keeps them where this port cannot reach.
    """
    # python-can's serial and bridge backends (0.2 s to import), only for a port that uses one
    from can.interfaces.slcan import slcanBus
    from can.interfaces.socketcand import SocketCanDaemonBus

    if isinstance(bus, SocketCanDaemonBus):
        sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
        if not isinstance(sock, socket.socket):
            raise CanBusError(name, "closed", f"python-can {can.__version__}'s SocketCanDaemonBus has no socket "
                                              "_SocketCanDaemonBus__socket: its writes cannot be given a timeout")
        sock.settimeout(timeout_s)
    elif isinstance(bus, slcanBus):
        serial_port = getattr(bus, "serialPortOrig", None)
        if serial_port is None or not hasattr(serial_port, "write_timeout"):
            raise CanBusError(name, "closed", f"python-can {can.__version__}'s slcanBus has no serial port "
                                              "serialPortOrig with a write_timeout: its writes cannot be bounded")
        serial_port.write_timeout = timeout_s


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

    def send_urgent(self, msg: can.Message) -> None:
        self._realtime().send_urgent(msg)

    def tap(self, callback: Tap) -> Callable[[], None]:
        return self._realtime().tap(callback)

    def stopped_threads(self) -> list[str]:
        port = self._port
        return port.stopped_threads() if isinstance(port, RealtimePort) else []

    def _realtime(self) -> RealtimePort:
        port = self._port
        if self.closed or port is None:
            raise CanBusError(self.name, "closed", "not open: the real-time side needs the opened bus")
        if not isinstance(port, RealtimePort):
            raise CanBusError(self.name, "open", f"{type(port).__name__} has no real-time side")
        return port

    def close(self) -> None:
        self.closed = True
        port, self._port = self._port, None
        if port is not None:
            port.close()
