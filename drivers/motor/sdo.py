"""SDO expedited transfers (CiA 301): byte-exact framing and an asyncio client.

Only expedited transfers (at most 4 data bytes) are needed: every CiA 402 object the beam
drive uses fits. The client serialises requests (one outstanding transfer per server, as
the protocol requires) and waits on the event loop, never on a thread.
"""

from __future__ import annotations

import asyncio
import enum
import struct
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from drivers.motor.errors import SdoAbort, SdoProtocolError, SdoTimeout

# Expedited download command bytes by data length, and the reverse.
_DOWNLOAD_CMD = {4: 0x23, 3: 0x27, 2: 0x2B, 1: 0x2F}
_UPLOAD_REPLY_CMD = {4: 0x43, 3: 0x47, 2: 0x4B, 1: 0x4F}
UPLOAD_REQUEST = 0x40
DOWNLOAD_REPLY = 0x60
ABORT = 0x80


class SdoKind(enum.Enum):
    DOWNLOAD = "download"  # client request: write
    UPLOAD = "upload"  # client request: read
    DOWNLOAD_REPLY = "download reply"
    UPLOAD_REPLY = "upload reply"
    ABORT = "abort"


@dataclass(frozen=True)
class SdoMessage:
    """A decoded SDO frame. ``data`` holds the expedited payload (None when the size is not
    indicated, 4 raw bytes in ``raw``), ``code`` the abort code."""

    kind: SdoKind
    index: int
    subindex: int
    data: bytes = b""
    code: int = 0
    size_indicated: bool = True
    expedited: bool = True
    raw: bytes = bytes(4)


def _header(command: int, index: int, subindex: int) -> bytes:
    return struct.pack("<BHB", command, index, subindex)


def download_request(index: int, subindex: int, data: bytes) -> bytes:
    """Expedited download (write) request, 8 bytes."""
    if len(data) not in _DOWNLOAD_CMD:
        raise ValueError(f"expedited download carries 1-4 bytes, got {len(data)}")
    return _header(_DOWNLOAD_CMD[len(data)], index, subindex) + data.ljust(4, b"\0")


def upload_request(index: int, subindex: int) -> bytes:
    """Upload (read) initiate request, 8 bytes."""
    return _header(UPLOAD_REQUEST, index, subindex) + bytes(4)


def download_reply(index: int, subindex: int) -> bytes:
    return _header(DOWNLOAD_REPLY, index, subindex) + bytes(4)


def upload_reply(index: int, subindex: int, data: bytes) -> bytes:
    """Expedited upload reply with the size indicated, 8 bytes."""
    if len(data) not in _UPLOAD_REPLY_CMD:
        raise ValueError(f"expedited upload carries 1-4 bytes, got {len(data)}")
    return _header(_UPLOAD_REPLY_CMD[len(data)], index, subindex) + data.ljust(4, b"\0")


def abort_frame(index: int, subindex: int, code: int) -> bytes:
    return _header(ABORT, index, subindex) + struct.pack("<I", code)


def parse_sdo(data: bytes, *, from_client: bool) -> SdoMessage:
    """Decode one SDO frame (initiate and abort frames; segmented transfers are reported as
    ``expedited=False``). ``from_client`` chooses request (0x600+n) or reply (0x580+n) meaning."""
    if len(data) != 8:
        raise ValueError(f"SDO frame has {len(data)} bytes, expected 8: {bytes(data).hex()}")
    command, index, subindex = struct.unpack_from("<BHB", data)
    raw = bytes(data[4:8])
    specifier = command >> 5
    if command == ABORT:
        return SdoMessage(SdoKind.ABORT, index, subindex, code=struct.unpack("<I", raw)[0], raw=raw)
    expedited = bool(command & 0x02)
    size_indicated = bool(command & 0x01)
    length = 4 - ((command >> 2) & 0x03) if size_indicated else 4
    carries_data = (from_client and specifier == 1) or (not from_client and specifier == 2)
    if carries_data:  # an initiate download request or an initiate upload reply
        kind = SdoKind.DOWNLOAD if from_client else SdoKind.UPLOAD_REPLY
        return SdoMessage(kind, index, subindex, raw[:length] if expedited else b"",
                          size_indicated=size_indicated, expedited=expedited, raw=raw)
    if from_client and specifier == 2:
        return SdoMessage(SdoKind.UPLOAD, index, subindex, raw=raw)
    if not from_client and specifier == 3:
        return SdoMessage(SdoKind.DOWNLOAD_REPLY, index, subindex, raw=raw)
    raise ValueError(f"unsupported SDO command byte 0x{command:02X}")


SendFrame = Callable[[int, bytes], Awaitable[None]]


class SdoClient:
    """Expedited SDO client for one server node, fed by the owner's frame dispatcher.

    Args:
        send: coroutine sending (cob_id, data) on the bus.
        node_id: the server's node id.
        device: name used in errors.
        state: callable giving the device's current state text for errors.
        response_timeout_s: how long a transfer waits for the server's reply.
    """

    RESPONSE_TIMEOUT_S = 0.5

    def __init__(self, send: SendFrame, node_id: int, *, device: str, state: Callable[[], str],
                 response_timeout_s: float = RESPONSE_TIMEOUT_S) -> None:
        self._send = send
        self.response_timeout_s = response_timeout_s
        self.node_id = node_id
        self.device = device
        self._state = state
        self._lock = asyncio.Lock()
        self._reply: asyncio.Future[bytes] | None = None
        self._expected = (0, 0)
        self.stale_replies = 0

    def device_state(self) -> str:
        """The device's current state as text (what errors name)."""
        return self._state()

    def on_frame(self, data: bytes) -> None:
        """Hand a frame received on 0x580 + node to the waiting transfer. A frame for another
        object (the late answer to a request that already timed out) is counted and dropped."""
        if self._reply is None or self._reply.done():
            self.stale_replies += 1
            return
        if len(data) == 8 and struct.unpack_from("<HB", data, 1) != self._expected:
            self.stale_replies += 1
            return
        self._reply.set_result(bytes(data))

    async def _transfer(self, request: bytes, index: int, subindex: int) -> SdoMessage:
        async with self._lock:
            self._reply = asyncio.get_running_loop().create_future()
            self._expected = (index, subindex)
            try:
                await self._send(0x600 + self.node_id, request)
                try:
                    async with asyncio.timeout(self.response_timeout_s):
                        data = await self._reply
                except TimeoutError:
                    raise SdoTimeout(
                        self.device, self._state(), index, subindex, self.response_timeout_s
                    ) from None
            finally:
                self._reply = None
        try:
            reply = parse_sdo(data, from_client=False)
        except ValueError as exc:
            raise SdoProtocolError(self.device, self._state(), f"0x{index:04X}:{subindex}: {exc}") from None
        if reply.kind is SdoKind.ABORT:
            raise SdoAbort(self.device, self._state(), reply.index, reply.subindex, reply.code)
        if (reply.index, reply.subindex) != (index, subindex):
            raise SdoProtocolError(
                self.device,
                self._state(),
                f"reply for 0x{reply.index:04X}:{reply.subindex} to a request for 0x{index:04X}:{subindex}",
            )
        return reply

    async def upload(self, index: int, subindex: int) -> bytes:
        """Read an object's raw bytes (expedited)."""
        reply = await self._transfer(upload_request(index, subindex), index, subindex)
        if reply.kind is not SdoKind.UPLOAD_REPLY or not reply.expedited:
            raise SdoProtocolError(
                self.device,
                self._state(),
                f"0x{index:04X}:{subindex}: expected an expedited upload reply, got {reply.kind.value}",
            )
        return reply.data

    async def download(self, index: int, subindex: int, data: bytes) -> None:
        """Write an object's raw bytes (expedited)."""
        reply = await self._transfer(download_request(index, subindex, data), index, subindex)
        if reply.kind is not SdoKind.DOWNLOAD_REPLY:
            raise SdoProtocolError(
                self.device,
                self._state(),
                f"0x{index:04X}:{subindex}: expected a download reply, got {reply.kind.value}",
            )

    async def read(self, index: int, subindex: int, fmt: str) -> int:
        """Read an integer object; ``fmt`` is its struct format (``<H``, ``<i``...)."""
        data = await self.upload(index, subindex)
        if len(data) != struct.calcsize(fmt):
            raise SdoProtocolError(
                self.device,
                self._state(),
                f"0x{index:04X}:{subindex}: {len(data)} bytes, expected {struct.calcsize(fmt)}",
            )
        return int(struct.unpack(fmt, data)[0])

    async def write(self, index: int, subindex: int, fmt: str, value: int) -> None:
        """Write an integer object; ``fmt`` is its struct format."""
        await self.download(index, subindex, struct.pack(fmt, value))
