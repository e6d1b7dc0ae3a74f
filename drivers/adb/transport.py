"""Message transports under an ADB connection: asyncio streams (TCP, socketpair) and USB bulk.

A transport moves whole :class:`~drivers.adb.message.AdbMessage` objects; the USB one sends
header and payload as separate bulk transfers, the stream ones write them back to back.
:class:`StreamTransport` wraps any reader/writer pair; :class:`SocketTransport` (what
:func:`open_tcp` returns) receives each payload straight into its own buffer with a buffered
protocol, one copy less per byte, which is what bulk pulls are limited by.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from typing import Protocol

from drivers.adb.errors import AdbError, ConnectionLost
from drivers.adb.message import A_WRTE, HEADER_SIZE, MAX_PAYLOAD, AdbMessage, Header, decode_header, finish_message


class AdbTransport(Protocol):
    """What an ADB connection needs from a link: message send/receive and close."""

    name: str

    async def send(self, message: AdbMessage, *, with_checksum: bool = True) -> None: ...

    async def recv(self, max_payload: int = MAX_PAYLOAD) -> AdbMessage: ...

    async def close(self) -> None: ...


def _write(sink: asyncio.StreamWriter | asyncio.WriteTransport, name: str, closed: bool, message: AdbMessage,
           with_checksum: bool) -> None:
    """A message's header and payload written back to back, with no await between, so messages
    never interleave; ConnectionLost once the link is closed."""
    if closed or sink.is_closing():
        raise ConnectionLost(name, "closed", f"cannot send {message.name}: transport closed")
    sink.write(message.header(with_checksum=with_checksum))
    if message.payload:
        sink.write(message.payload)


class StreamTransport:
    """ADB over an asyncio reader/writer pair: TCP (adbd port 5555, simulators) or a socketpair.

    Writes are not interleaved: each message's header and payload go out in one synchronous
    writer.write sequence before any await.
    """

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, name: str = "adb") -> None:
        self.reader = reader
        self.writer = writer
        self.name = name
        self.closed = False

    async def send(self, message: AdbMessage, *, with_checksum: bool = True) -> None:
        _write(self.writer, self.name, self.closed, message, with_checksum)
        try:
            await self.writer.drain()
        except (ConnectionError, OSError) as exc:
            raise ConnectionLost(self.name, "sending", f"{message.name}: {exc!r}") from exc

    async def recv(self, max_payload: int = MAX_PAYLOAD) -> AdbMessage:
        try:
            header = decode_header(await self.reader.readexactly(HEADER_SIZE), device=self.name,
                                   max_payload=max_payload)
            payload = await self.reader.readexactly(header.data_length) if header.data_length else b""
        except asyncio.IncompleteReadError as exc:
            raise ConnectionLost(self.name, "receiving",
                                 f"peer closed the link ({len(exc.partial)} bytes of a message read)") from exc
        except (ConnectionError, OSError) as exc:
            raise ConnectionLost(self.name, "receiving", repr(exc)) from exc
        return finish_message(header, payload, device=self.name)

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.writer.close()
        try:
            await self.writer.wait_closed()
        except (ConnectionError, OSError):
            pass  # the peer already dropped the link; closing our end is all that is left


class _MessageReceiver(asyncio.BufferedProtocol):
    """Parses ADB messages as bytes arrive: headers into a fixed buffer, each payload into a fresh one."""

    QUEUE_HIGH = 8  # messages waiting for recv() before the socket stops being read
    POOL_PER_SIZE = 4  # recycled payload buffers kept per size

    def __init__(self, name: str) -> None:
        self.name = name
        self.max_payload = MAX_PAYLOAD
        self.transport: asyncio.Transport | None = None
        self.messages: deque[AdbMessage] = deque()
        self.error: AdbError | None = None
        self.arrived = asyncio.Event()
        self.paused = False
        self._header = bytearray(HEADER_SIZE)
        self._target = self._header
        self._filled = 0
        self._pending: Header | None = None
        self._drained = asyncio.Event()
        self._drained.set()
        self.credit_hook: Callable[[Header], AdbMessage | None] | None = None
        self._free: dict[int, list[bytearray]] = {}

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def _buffer(self, size: int) -> bytearray:
        """A payload buffer: a recycled one of this size if any (fresh memory costs page faults:
        about as much CPU as the copy from the kernel itself)."""
        free = self._free.get(size)
        return free.pop() if free else bytearray(size)

    def recycle(self, buffer: bytearray) -> None:
        free = self._free.setdefault(len(buffer), [])
        if len(free) < self.POOL_PER_SIZE:
            free.append(buffer)

    def get_buffer(self, sizehint: int) -> memoryview:
        return memoryview(self._target)[self._filled:]

    def buffer_updated(self, nbytes: int) -> None:
        self._filled += nbytes
        if self._filled < len(self._target):
            return
        try:
            if self._pending is None:
                header = decode_header(bytes(self._header), device=self.name, max_payload=self.max_payload)
                if header.data_length:
                    self._pending, self._target, self._filled = header, self._buffer(header.data_length), 0
                    if header.command == A_WRTE and self.credit_hook is not None:
                        credit = self.credit_hook(header)
                        if credit is not None and self.transport is not None:
                            self.transport.write(credit.header(with_checksum=False))
                    return
                message = finish_message(header, b"", device=self.name)
            else:
                message = finish_message(self._pending, self._target, device=self.name)
        except AdbError as exc:
            self.connection_lost(exc)
            if self.transport is not None:
                self.transport.abort()
            return
        self._pending, self._target, self._filled = None, self._header, 0
        self.messages.append(message)
        self.arrived.set()
        if len(self.messages) >= self.QUEUE_HIGH and self.transport is not None and not self.paused:
            self.paused = True
            self.transport.pause_reading()

    def connection_lost(self, exc: BaseException | None) -> None:
        if self.error is None:
            self.error = exc if isinstance(exc, AdbError) else ConnectionLost(
                self.name, "receiving", f"peer closed the link ({exc!r})" if exc else "peer closed the link")
        self.arrived.set()
        self._drained.set()

    def pause_writing(self) -> None:
        self._drained.clear()

    def resume_writing(self) -> None:
        self._drained.set()


class SocketTransport:
    """ADB over a connected stream socket (TCP) with a buffered protocol: payloads land in place.

    Early credit: when a WRTE header arrives, ``credit_hook`` (set by the stream multiplexer) may
    return the OKAY for it at once, before its payload is in. The sender then streams the next
    payload right behind this one instead of idling a round trip per MiB; the receiver still
    grants credit only while it has room (see StreamMux.READ_WINDOW).
    """

    def __init__(self, transport: asyncio.Transport, receiver: _MessageReceiver, *, name: str) -> None:
        self._transport = transport
        self._receiver = receiver
        self.name = name
        self.closed = False

    def recycle(self, buffer: bytearray) -> None:
        """Take back a payload buffer whose stream is done with it, for the next payload of its size."""
        self._receiver.recycle(buffer)

    @property
    def credit_hook(self) -> Callable[[Header], AdbMessage | None] | None:
        return self._receiver.credit_hook

    @credit_hook.setter
    def credit_hook(self, hook: Callable[[Header], AdbMessage | None] | None) -> None:
        self._receiver.credit_hook = hook

    async def send(self, message: AdbMessage, *, with_checksum: bool = True) -> None:
        _write(self._transport, self.name, self.closed, message, with_checksum)
        await self._receiver._drained.wait()
        if self._receiver.error is not None and self._transport.is_closing():
            raise ConnectionLost(self.name, "sending", f"{message.name}: {self._receiver.error}")

    async def recv(self, max_payload: int = MAX_PAYLOAD) -> AdbMessage:
        receiver = self._receiver
        receiver.max_payload = max_payload
        while not receiver.messages:
            if receiver.error is not None:
                raise receiver.error
            receiver.arrived.clear()
            await receiver.arrived.wait()
        message = receiver.messages.popleft()
        if receiver.paused and len(receiver.messages) < receiver.QUEUE_HIGH // 2:
            receiver.paused = False
            self._transport.resume_reading()
        return message

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._transport.close()


async def open_tcp(host: str, port: int, *, timeout_s: float = 5.0) -> SocketTransport:
    """Connect to an adbd over TCP (wireless debugging, ``adb tcpip``, or the simulated phone)."""
    name = f"{host}:{port}"
    loop = asyncio.get_running_loop()
    try:
        async with asyncio.timeout(timeout_s):
            transport, receiver = await loop.create_connection(lambda: _MessageReceiver(name), host, port)
    except (OSError, TimeoutError) as exc:
        raise ConnectionLost(name, "connecting", f"TCP connect failed: {exc!r}") from exc
    return SocketTransport(transport, receiver, name=name)
