"""Asyncio streams over a serial port: pyserial sets the line up, the event loop does the I/O.

The port is opened and configured (115200 8N1, raw, no flow control) with pyserial; reading and
writing then go through asyncio pipe transports on its file descriptor, so no thread polls the
port and the same :class:`OperatorPanel` code runs over a tty, a pty or a socketpair.
"""

from __future__ import annotations

import asyncio
import os

import serial

from drivers.panel.errors import PanelDisconnected

BAUDRATE = 115200


class _WriteProtocol(asyncio.streams.FlowControlMixin):
    """Flow control for the write transport, plus the close waiter StreamWriter.wait_closed needs."""

    def __init__(self) -> None:
        super().__init__()
        self._closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        if not self._closed.done():
            self._closed.set_result(None)

    def _get_close_waiter(self, stream: asyncio.StreamWriter) -> asyncio.Future[None]:
        return self._closed


class FdStreamWriter(asyncio.StreamWriter):
    """A StreamWriter whose close() also closes the separate read transport of the same line."""

    def __init__(self, transport: asyncio.WriteTransport, protocol: asyncio.BaseProtocol,
                 reader: asyncio.StreamReader, loop: asyncio.AbstractEventLoop,
                 read_transport: asyncio.ReadTransport) -> None:
        super().__init__(transport, protocol, reader, loop)
        self._read_transport = read_transport

    def close(self) -> None:
        self._read_transport.close()
        super().close()


async def open_fd_streams(fd: int) -> tuple[asyncio.StreamReader, FdStreamWriter]:
    """Asyncio streams over a tty/pty file descriptor; takes ownership of ``fd``."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(loop=loop)
    write_fd = os.dup(fd)
    read_transport, _ = await loop.connect_read_pipe(
        lambda: asyncio.StreamReaderProtocol(reader, loop=loop), os.fdopen(fd, "rb", 0)
    )
    try:
        transport, protocol = await loop.connect_write_pipe(
            _WriteProtocol, os.fdopen(write_fd, "wb", 0)
        )
    except OSError:
        read_transport.close()
        raise
    return reader, FdStreamWriter(transport, protocol, reader, loop, read_transport)


async def open_serial(
    path: str, *, baudrate: int = BAUDRATE, name: str = "panel"
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Open the tty at ``path`` (8N1, ``baudrate``) as an asyncio (reader, writer) pair.

    Input already waiting in the port is discarded so the first line read is a fresh one.
    Raises PanelDisconnected naming the path when the port cannot be opened.
    """
    try:
        port = serial.Serial(
            path,
            baudrate=baudrate,
            bytesize=serial.EIGHTBITS,
            parity=serial.PARITY_NONE,
            stopbits=serial.STOPBITS_ONE,
            timeout=0,
            xonxoff=False,
            rtscts=False,
            dsrdtr=False,
            exclusive=True,
        )
        try:
            port.reset_input_buffer()
            fd = os.dup(port.fileno())  # the duplicate keeps the configured line (and its lock)
        finally:
            port.close()
        return await open_fd_streams(fd)
    except (serial.SerialException, OSError) as exc:
        raise PanelDisconnected(name, f"cannot open {path} at {baudrate} 8N1: {exc}") from exc
