"""One control-socket subscription: the daemon's events to one client through a bounded send queue.

A subscriber that stops reading must cost the daemon a bounded amount of memory and never hold
anything else up. Its events wait in a queue of at most ``max_pending`` lines (beyond the socket's
buffers and the transport's 64 KiB high-water mark); one more and the subscriber is dropped: told
``SubscriberTooSlow`` (if it still reads, it learns why), logged with its peer (pid, uid) and how
many events were pending, and its connection closed. The connection carries only events: a byte
from the client ends the subscription with a ``ProtocolError`` line, so what a client sends after
``subscribe`` is never accumulated.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from collections import deque
from collections.abc import AsyncIterator, Callable
from typing import Any

import structlog

log = structlog.get_logger("daemon.control")

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


class Subscriber:
    """Streams ``events`` to one client: the reply line first, then one line per event.

    encode: an object (reply, event or error) as its JSON line. Use :meth:`run`; it returns when the
    client hangs up, sends anything, falls ``max_pending`` events behind, or the events end.
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
        self._ready = asyncio.Event()

    async def run(self, first: asyncio.Future[Any], reply: bytes) -> None:
        """first: the handler's first event, already awaited (subscribed before ``reply`` was made)."""
        self._queue(reply)
        tasks = {asyncio.ensure_future(self._pump(first)), asyncio.ensure_future(self._send()),
                 asyncio.ensure_future(self.reader.read(1))}  # b"": the client hung up
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        for task in done:
            self._ended(task)

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

    def _ended(self, task: asyncio.Future[Any]) -> None:
        exc = task.exception() if not task.cancelled() else None
        if isinstance(exc, _TooSlow):
            self._drop()
        elif exc is None and task.result():  # only the reader returns something: the client sent bytes
            self.writer.write(self.encode({"id": None, "ok": False, "error": {
                "type": "ProtocolError",
                "message": "a subscription carries only events; send requests on another connection"}}))
            log.warning("control_subscriber_sent_data", **peer_of(self.writer))

    def _drop(self) -> None:
        unsent = self.writer.transport.get_write_buffer_size()
        log.warning("control_subscriber_dropped", reason="not reading its events",
                    pending_events=len(self.pending), unsent_bytes=unsent, **peer_of(self.writer))
        message = (f"{len(self.pending)} events were waiting for this subscriber (at most "
                   f"{self.max_pending}): it is dropped; read events as they come")
        self.pending.clear()
        self.writer.write(self.encode({"id": None, "ok": False,
                                       "error": {"type": "SubscriberTooSlow", "message": message}}))


class _TooSlow(Exception):
    """The subscriber's send queue is full."""


async def close_events(events: AsyncIterator[Any]) -> None:
    closer = getattr(events, "aclose", None)
    if closer is not None:
        with contextlib.suppress(RuntimeError):
            await closer()
