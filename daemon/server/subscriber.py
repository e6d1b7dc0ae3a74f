"""One control-socket subscription: the daemon's events to one client through a bounded send queue.

A subscriber that stops reading must cost the daemon a bounded amount of memory and never hold
anything else up. Its events wait in a queue of at most ``max_pending`` lines (beyond the socket's
buffers and the transport's 64 KiB high-water mark); one more and the subscriber is dropped: told
``SubscriberTooSlow`` (if it still reads, it learns why) and its connection closed; the control
server logs it with its peer (pid, uid) and how many events were pending. The connection carries
only events: a byte from the client ends the subscription with a ``ProtocolError`` line, so what a
client sends after ``subscribe`` is never accumulated.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import socket
import struct
from collections import deque
from collections.abc import AsyncIterator, Callable
from typing import Any

from daemon.errors import DaemonError

_CREDENTIALS = struct.Struct("3i")
LINGER_MAX_BYTES = 64 * 1024


def peer_of(writer: asyncio.StreamWriter) -> dict[str, int | None]:
    """The client's pid and uid (SO_PEERCRED of the Unix socket), None where the kernel says nothing."""
    sock = writer.get_extra_info("socket")
    try:
        pid, uid, _gid = _CREDENTIALS.unpack(
            sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _CREDENTIALS.size))
    except (AttributeError, OSError, struct.error):
        return {"peer_pid": None, "peer_uid": None}
    return {"peer_pid": pid, "peer_uid": uid}


async def hang_up(writer: asyncio.StreamWriter, grace_s: float, reader: asyncio.StreamReader | None = None) -> None:
    """Close a connection so the client can still read what it was sent, for at most grace_s.

    reader: the client may still be sending. Closing a Unix socket with unread bytes resets the
    connection before the client reads its answer, so the write side is shut (the client reads
    EOF after the answer) and what it sends is read and discarded until it hangs up. Past
    grace_s, or past LINGER_MAX_BYTES discarded, the connection is aborted: a client that never
    reads, or floods, cannot keep the descriptor (nor the loop: a flood of ready input never lets a
    virtual-time loop reach a timer)."""
    if writer.transport.is_closing():
        return
    task = asyncio.current_task()
    if grace_s <= 0 or (task is not None and task.cancelling()):
        writer.transport.abort()
        return
    try:
        async with asyncio.timeout(grace_s):
            if reader is not None:
                if writer.can_write_eof():
                    writer.write_eof()
                discarded = 0
                while discarded <= LINGER_MAX_BYTES and (data := await reader.read(LINGER_MAX_BYTES)):
                    discarded += len(data)
                if discarded > LINGER_MAX_BYTES:
                    writer.transport.abort()
                    return
            writer.close()
            await writer.wait_closed()
    except (TimeoutError, ConnectionError):
        writer.transport.abort()


class Ended(enum.Enum):
    """Why a subscription ended."""

    HUNG_UP = "hung up"  # the client closed, or the connection broke
    SENT_DATA = "sent data"  # answered ProtocolError
    TOO_SLOW = "too slow"  # answered SubscriberTooSlow
    EVENTS_ENDED = "events ended"  # the daemon is closing


class Subscriber:
    """Streams ``events`` to one client: the reply line first, then one line per event.

    encode: an object (reply, event or error) as its JSON line. Use :meth:`run`; it returns when the
    client hangs up, sends anything, falls ``max_pending`` events behind, or the events end, with
    the error line (if any) written and the connection still open.
    """

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 events: AsyncIterator[Any], encode: Callable[[dict[str, Any]], bytes], *,
                 max_pending: int) -> None:
        self.reader = reader
        self.writer = writer
        self.events = events
        self.encode = encode
        self.max_pending = max_pending
        self.pending: deque[bytes] = deque()
        self.dropped_pending = 0  # events waiting when it was dropped as too slow
        self._ready = asyncio.Event()

    async def run(self, first: asyncio.Future[Any], reply: bytes) -> Ended:
        """first: the handler's first event, already awaited (subscribed before ``reply`` was made)."""
        self._queue(reply)
        pump = asyncio.ensure_future(self._pump(first))
        hangup = asyncio.ensure_future(self.reader.read(1))  # b"": the client hung up
        tasks = {pump, hangup, asyncio.ensure_future(self._send())}
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        if pump in done and isinstance(pump.exception(), _TooSlow):
            self.dropped_pending = len(self.pending)
            self.pending.clear()
            self._error("SubscriberTooSlow", f"{self.dropped_pending} events were waiting for this subscriber "
                                             f"(at most {self.max_pending}): it is dropped; read events as they come")
            return Ended.TOO_SLOW
        if hangup in done and not hangup.exception() and hangup.result():
            self._error("ProtocolError", "a subscription carries only events; send requests on another connection")
            return Ended.SENT_DATA
        return Ended.EVENTS_ENDED if pump in done and not pump.exception() else Ended.HUNG_UP

    def _queue(self, line: bytes) -> None:
        self.pending.append(line)
        self._ready.set()

    async def _pump(self, first: asyncio.Future[Any]) -> None:
        try:
            event = await first
            while True:
                if len(self.pending) >= self.max_pending:
                    raise _TooSlow
                self._queue(self.encode({"event": event}))
                event = await anext(self.events)
        except StopAsyncIteration:  # the daemon's events end (it is closing)
            return

    async def _send(self) -> None:
        while True:
            while not self.pending:
                self._ready.clear()
                await self._ready.wait()
            self.writer.write(self.pending.popleft())
            await self.writer.drain()

    def _error(self, error_type: str, message: str) -> None:
        self.writer.write(self.encode({"id": None, "ok": False, "error": {"type": error_type, "message": message}}))


class _TooSlow(DaemonError):
    """The subscriber's send queue is full (internal: the subscriber is dropped, never raised out)."""


async def close_events(events: AsyncIterator[Any]) -> None:
    closer = getattr(events, "aclose", None)
    if closer is not None:
        with contextlib.suppress(RuntimeError):
            await closer()
