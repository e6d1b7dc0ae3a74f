"""Stream multiplexing over one ADB link: OPEN/OKAY/WRTE/CLSE with per-stream flow control.

Both halves use :class:`StreamMux`: the host opens services, the simulated adbd accepts them.
Flow control follows adbd: a writer sends one WRTE and waits for the peer's OKAY before the
next. A reader answers OKAY at once while its consumer has nothing else queued (so the sender
prepares the next payload while this one is consumed), otherwise only when the consumer takes
a payload: a slow consumer throttles the sender with at most READ_WINDOW payloads buffered.
The window is enforced, not trusted: each stream counts the WRTEs its peer may still send (one
when it opens, one more per OKAY sent), and a WRTE beyond that is an AdbProtocolError that ends
the link, so a device ignoring flow control cannot fill the host's memory.
"""

from __future__ import annotations

import asyncio
import itertools
from collections import deque
from collections.abc import Awaitable, Callable

import structlog

from drivers.adb.errors import (
    AdbError,
    AdbLimitExceeded,
    AdbProtocolError,
    AdbTimeout,
    ConnectionLost,
    StreamClosed,
    StreamRefused,
)
from drivers.adb.message import A_CLSE, A_OKAY, A_OPEN, A_WRTE, MAX_PAYLOAD_LEGACY, AdbMessage, Header
from drivers.adb.transport import AdbTransport

log = structlog.get_logger("drivers.adb.streams")

ServiceHandler = Callable[["AdbStream"], Awaitable[None]]
ServiceResolver = Callable[[str], ServiceHandler | None]


class AdbStream:
    """One service stream: bytes in both directions until either side sends CLSE."""

    def __init__(self, mux: StreamMux, local_id: int, service: str) -> None:
        self.mux = mux
        self.local_id = local_id
        self.remote_id = 0
        self.service = service
        self.state = "opening"
        self._opened: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._ready = asyncio.Event()
        self._ready.set()
        self._payloads: deque[bytes | bytearray] = deque()
        self._arrived = asyncio.Event()
        self._chunk: bytes | bytearray = b""
        self._pos = 0
        self._error: AdbError | None = None
        self._okay_owed = False
        self._credit_given = False
        self._peer_credit = 0  # WRTEs the peer may send before our next OKAY
        self.bytes_read = 0
        self.bytes_written = 0

    def __repr__(self) -> str:
        return f"AdbStream({self.service!r}, {self.local_id}->{self.remote_id}, {self.state})"

    # ---------------------------------------------------------------- writing
    async def write(self, data: bytes | bytearray | memoryview) -> None:
        """Send data as WRTE messages of at most the link's payload size, each acknowledged."""
        view = memoryview(data)
        if not view.readonly:  # transports may keep a reference past this call (Python 3.12's do)
            view = memoryview(bytes(view))
        step = self.mux.max_payload
        for start in range(0, len(view), step):
            await self._wait_ready()
            self._ready.clear()
            chunk = view[start:start + step]  # immutable bytes: slices need no copy
            await self.mux.send(AdbMessage(A_WRTE, self.local_id, self.remote_id, chunk))
            self.bytes_written += len(chunk)

    async def _wait_ready(self) -> None:
        try:
            async with asyncio.timeout(self.mux.WRITE_TIMEOUT_S):
                while not self._ready.is_set():
                    self._raise_if_closed()
                    await self._ready.wait()
        except TimeoutError:
            raise AdbTimeout(self.mux.name, self.state, f"OKAY for WRTE on {self.service!r}",
                             self.mux.WRITE_TIMEOUT_S) from None
        self._raise_if_closed()

    def _raise_if_closed(self) -> None:
        if self._error is not None:
            raise self._error
        if self.state == "closed":
            raise StreamClosed(self.mux.name, self.state, f"stream {self.service!r} is closed")

    # ---------------------------------------------------------------- reading
    # The current payload (_chunk) may be a receive buffer the transport recycles once the stream
    # moves past it (_drop_chunk); everything returned to callers is a copy, except readview's
    # view, which is valid until the next read.
    async def read(self) -> bytes:
        """The next received bytes (any length); b"" once the peer closed the stream."""
        if self._pos < len(self._chunk):
            data = bytes(self._chunk[self._pos:])
            self._drop_chunk()
            return data
        self._drop_chunk()
        return bytes(await self._next_payload())

    def _drop_chunk(self) -> None:
        if isinstance(self._chunk, bytearray):
            self.mux.recycle(self._chunk)
        self._chunk, self._pos = b"", 0

    async def _advance(self) -> bool:
        """Make the next payload current, recycling the exhausted one; False at end of stream."""
        self._drop_chunk()
        self._chunk = await self._next_payload()
        return bool(self._chunk)

    async def _next_payload(self) -> bytes | bytearray:
        while not self._payloads:
            if self._error is not None:
                raise self._error
            if self.state == "closed":
                return b""
            self._arrived.clear()
            await self._arrived.wait()
        payload = self._payloads.popleft()
        if self._okay_owed and len(self._payloads) < self.mux.READ_WINDOW and self.state == "open":
            self._okay_owed = False
            await self.mux.grant(self)
        self.bytes_read += len(payload)
        return payload

    async def readexactly(self, n: int) -> bytes:
        """Exactly n bytes; StreamClosed if the stream ends first."""
        parts: list[bytes] = []
        have = 0
        while True:
            take = min(n - have, len(self._chunk) - self._pos)
            if take:
                parts.append(bytes(self._chunk[self._pos:self._pos + take]))
                self._pos += take
                have += take
            if have == n:
                return parts[0] if len(parts) == 1 else b"".join(parts)
            if not await self._advance():
                raise StreamClosed(self.mux.name, self.state, f"{self.service!r} ended after {have} of {n} bytes")

    async def readview(self, n: int) -> memoryview:
        """Exactly n bytes, without copying when they lie in one received payload (bulk data path).

        The view is valid until the next read on this stream: use it (hash, write) before then.
        """
        if len(self._chunk) - self._pos == 0 and n:
            await self._advance()
        if len(self._chunk) - self._pos >= n:
            view = memoryview(self._chunk)[self._pos:self._pos + n]
            self._pos += n
            return view
        return memoryview(await self.readexactly(n))

    async def readline(self, limit: int = 1 << 20) -> bytes:
        """Bytes up to and including b"\\n"; whatever is left (maybe b"") at end of stream."""
        parts: list[bytes] = []
        size = 0
        while True:
            if self._pos >= len(self._chunk) and not await self._advance():
                return b"".join(parts)
            end = self._chunk.find(b"\n", self._pos)
            if end >= 0:
                parts.append(bytes(self._chunk[self._pos:end + 1]))
                self._pos = end + 1
                return b"".join(parts)
            parts.append(bytes(self._chunk[self._pos:]))
            size += len(self._chunk) - self._pos
            self._pos = len(self._chunk)
            if size > limit:
                raise AdbProtocolError(self.mux.name, self.state,
                                       f"line on {self.service!r} longer than {limit} bytes")

    async def read_all(self, limit: int) -> bytes:
        """Everything until the peer closes the stream, at most ``limit`` bytes.

        Raises AdbLimitExceeded (after closing the stream) when the peer sends more.
        """
        parts = []
        size = 0
        while data := await self.read():
            size += len(data)
            if size > limit:
                await self.close()
                raise AdbLimitExceeded(self.mux.name, "open", f"output of {self.service!r}", limit)
            parts.append(data)
        return b"".join(parts)

    # ---------------------------------------------------------------- closing
    async def close(self) -> None:
        """Send CLSE (once) and forget the stream; idempotent."""
        if self.state == "closed":
            return
        was_open = self.state == "open"
        self._mark_closed()
        if was_open and not self.mux.lost:
            try:
                await self.mux.send(AdbMessage(A_CLSE, self.local_id, self.remote_id))
            except ConnectionLost:
                pass  # the link is gone, so the peer has dropped the stream too

    def _mark_closed(self) -> None:
        self.state = "closed"
        self.mux.streams.pop(self.local_id, None)
        self._arrived.set()
        self._ready.set()
        if not self._opened.done():
            self._opened.set_exception(self._error or StreamRefused(self.mux.name, "opening", self.service))
            self._opened.exception()  # retrieved here so an abandoned open never warns

    def _fail(self, error: AdbError) -> None:
        self._error = error
        self._mark_closed()


class StreamMux:
    """Routes stream messages on one link by local id; opens (host) and accepts (device) streams."""

    OPEN_TIMEOUT_S = 5.0
    WRITE_TIMEOUT_S = 10.0
    READ_WINDOW = 1  # payloads a stream may hold unread and still acknowledged

    def __init__(self, transport: AdbTransport, *, name: str, resolver: ServiceResolver | None = None) -> None:
        self.transport = transport
        self.name = name
        self.resolver = resolver
        self.streams: dict[int, AdbStream] = {}
        self.max_payload = MAX_PAYLOAD_LEGACY
        self.with_checksum = True
        self.lost: AdbError | None = None
        self._ids = itertools.count(1)
        self._send_lock = asyncio.Lock()
        self._handlers: set[asyncio.Task[None]] = set()
        self._abandoned: set[int] = set()  # local ids of OPENs that timed out
        if hasattr(transport, "credit_hook"):
            transport.credit_hook = self._early_credit

    def recycle(self, buffer: bytearray) -> None:
        """Hand a consumed receive buffer back to the transport, when it keeps a pool."""
        pool = getattr(self.transport, "recycle", None)
        if pool is not None:
            pool(buffer)

    def _early_credit(self, header: Header) -> AdbMessage | None:
        """The OKAY for a WRTE whose payload is still arriving, when its stream has room for it."""
        stream = self.streams.get(header.arg1)
        if stream is None or stream.state != "open" or stream.remote_id != header.arg0 or \
                stream._credit_given or len(stream._payloads) >= self.READ_WINDOW or self.lost is not None:
            return None
        stream._credit_given = True
        stream._peer_credit += 1
        return AdbMessage(A_OKAY, stream.local_id, stream.remote_id)

    async def grant(self, stream: AdbStream) -> None:
        """OKAY: the peer may send this stream one more WRTE."""
        stream._peer_credit += 1
        await self.send(AdbMessage(A_OKAY, stream.local_id, stream.remote_id))

    async def send(self, message: AdbMessage) -> None:
        if self.lost is not None:
            raise self.lost
        async with self._send_lock:
            await self.transport.send(message, with_checksum=self.with_checksum)

    async def open(self, service: str) -> AdbStream:
        """OPEN a service and wait for the peer's OKAY; StreamRefused on CLSE."""
        if self.lost is not None:
            raise self.lost
        stream = AdbStream(self, next(self._ids), service)
        self.streams[stream.local_id] = stream
        await self.send(AdbMessage(A_OPEN, stream.local_id, 0, service.encode() + b"\0"))
        try:
            async with asyncio.timeout(self.OPEN_TIMEOUT_S):
                await stream._opened
        except TimeoutError:
            self.streams.pop(stream.local_id, None)
            self._abandoned.add(stream.local_id)
            raise AdbTimeout(self.name, "opening", f"OKAY for OPEN {service!r}", self.OPEN_TIMEOUT_S) from None
        return stream

    async def run(self) -> None:
        """Receive and route messages until the link fails; every stream then fails with the cause."""
        try:
            while True:
                await self._dispatch(await self.transport.recv(self.max_payload))
        except AdbError as exc:
            self._lose(exc if isinstance(exc, ConnectionLost) else
                       ConnectionLost(self.name, "online", f"link broken: {exc}"))
        except asyncio.CancelledError:
            self._lose(ConnectionLost(self.name, "closed", "connection closed"))
            raise
        finally:
            for task in list(self._handlers):
                task.cancel()

    def _lose(self, error: AdbError) -> None:
        if self.lost is None:
            self.lost = error
        for stream in list(self.streams.values()):
            stream._fail(self.lost)

    async def _dispatch(self, msg: AdbMessage) -> None:
        if msg.command == A_OPEN:
            await self._accept(msg)
            return
        if msg.command not in (A_OKAY, A_WRTE, A_CLSE):
            raise AdbProtocolError(self.name, "online", f"unexpected {msg.name} on an open connection")
        stream = self.streams.get(msg.arg1)
        if stream is None:
            if msg.command == A_WRTE:  # data for a stream we closed: tell the peer it is gone
                await self.send(AdbMessage(A_CLSE, 0, msg.arg0))
            elif msg.command == A_OKAY and msg.arg1 in self._abandoned:  # a late answer to a timed-out OPEN
                self._abandoned.discard(msg.arg1)
                await self.send(AdbMessage(A_CLSE, msg.arg1, msg.arg0))
            return
        if msg.command == A_OKAY:
            if stream.state == "opening":
                stream.remote_id = msg.arg0
                stream.state = "open"
                stream._peer_credit = 1  # an open stream may carry one WRTE each way
                stream._opened.set_result(None)
            else:
                stream._ready.set()
        elif msg.command == A_WRTE:
            if stream._peer_credit <= 0:
                raise AdbProtocolError(self.name, "online",
                                       f"WRTE on {stream.service!r} beyond its flow-control window "
                                       f"({len(stream._payloads)} payloads unread, no OKAY outstanding)")
            stream._peer_credit -= 1
            payload = msg.payload  # bytes or a receive buffer from a transport; a view only if handed over in memory
            stream._payloads.append(bytes(payload) if isinstance(payload, memoryview) else payload)
            stream._arrived.set()
            if stream._credit_given:
                stream._credit_given = False
            elif len(stream._payloads) <= self.READ_WINDOW:
                await self.grant(stream)
            else:
                stream._okay_owed = True
        else:
            stream._mark_closed()

    async def _accept(self, msg: AdbMessage) -> None:
        service = bytes(msg.payload).rstrip(b"\0").decode("utf-8", "replace")
        handler = self.resolver(service) if self.resolver is not None else None
        if handler is None or msg.arg0 == 0:
            await self.send(AdbMessage(A_CLSE, 0, msg.arg0))
            return
        stream = AdbStream(self, next(self._ids), service)
        stream.remote_id = msg.arg0
        stream.state = "open"
        stream._opened.set_result(None)
        self.streams[stream.local_id] = stream
        await self.grant(stream)
        task = asyncio.create_task(self._serve(handler, stream), name=f"adb-{self.name}-{service[:24]}")
        self._handlers.add(task)
        task.add_done_callback(self._handlers.discard)

    async def _serve(self, handler: ServiceHandler, stream: AdbStream) -> None:
        try:
            await handler(stream)
        except AdbError as exc:
            log.info("adb_service_ended", device=self.name, service=stream.service, error=str(exc))
        finally:
            await stream.close()

    async def close(self) -> None:
        """Close every stream and the transport; returns once the service handlers have ended."""
        for stream in list(self.streams.values()):
            await stream.close()
        handlers = [task for task in self._handlers if task is not asyncio.current_task()]
        for task in handlers:
            task.cancel()
        await self.transport.close()
        await asyncio.gather(*handlers, return_exceptions=True)
