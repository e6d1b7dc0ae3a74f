"""Message transports under an ADB connection: asyncio streams (TCP, socketpair) and USB bulk.

A transport moves whole :class:`~drivers.adb.message.AdbMessage` objects; the USB one sends
header and payload as separate bulk transfers, the stream one writes them back to back.
"""

from __future__ import annotations

import asyncio
from typing import Protocol

from drivers.adb.errors import ConnectionLost
from drivers.adb.message import HEADER_SIZE, MAX_PAYLOAD, AdbMessage, decode_header, finish_message


class AdbTransport(Protocol):
    """What an ADB connection needs from a link: message send/receive and close."""

    name: str

    async def send(self, message: AdbMessage, *, with_checksum: bool = True) -> None: ...

    async def recv(self, max_payload: int = MAX_PAYLOAD) -> AdbMessage: ...

    async def close(self) -> None: ...


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
        if self.closed or self.writer.is_closing():
            raise ConnectionLost(self.name, "closed", f"cannot send {message.name}: transport closed")
        self.writer.write(message.header(with_checksum=with_checksum))
        if message.payload:
            self.writer.write(message.payload)
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


async def open_tcp(host: str, port: int, *, timeout_s: float = 5.0) -> StreamTransport:
    """Connect to an adbd over TCP (wireless debugging, ``adb tcpip``, or the simulated phone)."""
    name = f"{host}:{port}"
    try:
        async with asyncio.timeout(timeout_s):
            reader, writer = await asyncio.open_connection(host, port)
    except (OSError, TimeoutError) as exc:
        raise ConnectionLost(name, "connecting", f"TCP connect failed: {exc!r}") from exc
    return StreamTransport(reader, writer, name=name)
