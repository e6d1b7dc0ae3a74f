"""Asyncio streams over a serial port: pyserial sets the line up, the event loop does the I/O.

The port is opened and configured (115200 8N1, raw, no flow control) with pyserial; reading and
writing then go through asyncio pipe transports on its file descriptor, so no thread polls the
port and the same :class:`OperatorPanel` code runs over a tty, a pty or a socketpair. Opening
the port and the last close of its descriptor run in a thread: both may wait on the device (a
USB serial adapter's open, a tty's close draining its output), and the event loop carries the
heartbeats.
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
    """A StreamWriter whose close() also closes the separate read transport of the same line, and
    the line's own descriptor ``line_fd`` (the last one open, so the one that may wait) in a thread."""

    def __init__(self, transport: asyncio.WriteTransport, protocol: asyncio.BaseProtocol,
                 reader: asyncio.StreamReader, loop: asyncio.AbstractEventLoop,
                 read_transport: asyncio.ReadTransport, line_fd: int) -> None:
        super().__init__(transport, protocol, reader, loop)
        self._line_loop = loop
        self._read_transport = read_transport
        self._line_fd = line_fd
        self._line_closed: asyncio.Future[None] | None = None

    def close(self) -> None:
        self._read_transport.close()
        super().close()
        if self._line_closed is None:
            try:
                self._line_closed = self._line_loop.run_in_executor(None, os.close, self._line_fd)
            except RuntimeError:  # the loop's executor is already shut down: the process is ending
                os.close(self._line_fd)

    async def wait_closed(self) -> None:
        await super().wait_closed()
        if self._line_closed is not None:
            await self._line_closed


async def open_fd_streams(fd: int) -> tuple[asyncio.StreamReader, FdStreamWriter]:
    """Asyncio streams over a tty/pty file descriptor; takes ownership of ``fd``.

    The transports read and write duplicates of ``fd``; ``fd`` itself stays open until the
    writer is closed, and is then closed in a thread."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(loop=loop)
    try:
        read_fd = os.dup(fd)
        read_transport, _ = await loop.connect_read_pipe(
            lambda: asyncio.StreamReaderProtocol(reader, loop=loop), os.fdopen(read_fd, "rb", 0)
        )
    except BaseException:
        os.close(fd)
        raise
    try:
        transport, protocol = await loop.connect_write_pipe(
            _WriteProtocol, os.fdopen(os.dup(fd), "wb", 0)
        )
    except BaseException:
        read_transport.close()
        os.close(fd)
        raise
    return reader, FdStreamWriter(transport, protocol, reader, loop, read_transport, fd)


async def open_serial(
    path: str, *, baudrate: int = BAUDRATE, name: str = "panel"
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Open the tty at ``path`` (8N1, ``baudrate``) as an asyncio (reader, writer) pair.

    Input already waiting in the port is discarded so the first line read is a fresh one.
    Raises PanelDisconnected naming the path when the port cannot be opened.
    """
    opening = asyncio.ensure_future(asyncio.to_thread(_open_port, path, baudrate))
    try:
        fd = await asyncio.shield(opening)
    except asyncio.CancelledError:  # given up on (a timeout): the port, once open, is closed again
        opening.add_done_callback(_close_opened)
        raise
    except (serial.SerialException, OSError) as exc:
        raise PanelDisconnected(name, f"cannot open {path} at {baudrate} 8N1: {exc}") from exc
    try:
        return await open_fd_streams(fd)
    except OSError as exc:
        raise PanelDisconnected(name, f"cannot open {path} at {baudrate} 8N1: {exc}") from exc


def _close_opened(opening: asyncio.Future[int]) -> None:
    if not opening.cancelled() and opening.exception() is None:
        asyncio.get_running_loop().run_in_executor(None, os.close, opening.result())


def _open_port(path: str, baudrate: int) -> int:
    """Open and configure the port with pyserial (blocking: runs in a thread); a descriptor of
    the configured line, which holds its exclusive lock."""
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
        return os.dup(port.fileno())  # the duplicate keeps the configured line (and its lock)
    finally:
        port.close()
