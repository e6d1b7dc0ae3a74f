"""ADB wire messages: the 24-byte header, payload checksum and magic.

Header: six u32 little-endian words - command, arg0, arg1, data_length, data_check
(byte sum of the payload) and magic (command XOR 0xFFFFFFFF). Once both sides speak
version >= 0x01000001 the checksum may be 0; CNXN and AUTH always carry it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from drivers.adb.errors import AdbProtocolError

A_CNXN = 0x4E584E43
A_AUTH = 0x48545541
A_OPEN = 0x4E45504F
A_OKAY = 0x59414B4F
A_WRTE = 0x45545257
A_CLSE = 0x45534C43
A_STLS = 0x534C5453

COMMAND_NAMES = {A_CNXN: "CNXN", A_AUTH: "AUTH", A_OPEN: "OPEN", A_OKAY: "OKAY",
                 A_WRTE: "WRTE", A_CLSE: "CLSE", A_STLS: "STLS"}

A_VERSION = 0x01000001
A_VERSION_MIN = 0x01000000
A_VERSION_SKIP_CHECKSUM = 0x01000001
MAX_PAYLOAD = 1024 * 1024
MAX_PAYLOAD_LEGACY = 4096

AUTH_TOKEN = 1
AUTH_SIGNATURE = 2
AUTH_RSAPUBLICKEY = 3

HEADER = struct.Struct("<6I")
HEADER_SIZE = HEADER.size


def checksum(payload: bytes | bytearray | memoryview) -> int:
    """Byte sum of the payload modulo 2**32 (ADB's data_check, not a CRC)."""
    if len(payload) < 256:
        return sum(bytes(payload)) & 0xFFFFFFFF
    return int(np.frombuffer(payload, dtype=np.uint8).sum(dtype=np.uint64)) & 0xFFFFFFFF


@dataclass(frozen=True)
class AdbMessage:
    """One ADB message: command word, two arguments and the payload."""

    command: int
    arg0: int
    arg1: int
    payload: bytes | bytearray | memoryview = b""

    @property
    def name(self) -> str:
        return COMMAND_NAMES.get(self.command, f"0x{self.command:08X}")

    def header(self, *, with_checksum: bool = True) -> bytes:
        """The 24-byte header; ``with_checksum=False`` writes data_check 0 (version >= 0x01000001)."""
        check = checksum(self.payload) if with_checksum or self.command in (A_CNXN, A_AUTH) else 0
        return HEADER.pack(self.command, self.arg0, self.arg1, len(self.payload), check,
                           self.command ^ 0xFFFFFFFF)

    def encode(self, *, with_checksum: bool = True) -> bytes:
        """Header followed by payload, as sent over TCP."""
        return self.header(with_checksum=with_checksum) + bytes(self.payload)

    def __repr__(self) -> str:
        return f"AdbMessage({self.name}, {self.arg0}, {self.arg1}, {len(self.payload)} bytes)"


@dataclass(frozen=True)
class Header:
    """A decoded header whose payload has not been read yet."""

    command: int
    arg0: int
    arg1: int
    data_length: int
    data_check: int


def decode_header(data: bytes, *, device: str = "adb", max_payload: int = MAX_PAYLOAD) -> Header:
    """Parse and check a 24-byte header (magic, known command, length limit)."""
    if len(data) != HEADER_SIZE:
        raise AdbProtocolError(device, "framing", f"header is {len(data)} bytes, not {HEADER_SIZE}")
    command, arg0, arg1, length, check, magic = HEADER.unpack(data)
    if magic != command ^ 0xFFFFFFFF:
        raise AdbProtocolError(device, "framing",
                               f"bad magic 0x{magic:08X} for command 0x{command:08X}")
    if command not in COMMAND_NAMES:
        raise AdbProtocolError(device, "framing", f"unknown command 0x{command:08X}")
    if length > max_payload:
        raise AdbProtocolError(device, "framing",
                               f"{COMMAND_NAMES[command]} payload {length} bytes > limit {max_payload}")
    return Header(command, arg0, arg1, length, check)


def finish_message(header: Header, payload: bytes | bytearray, *, device: str = "adb") -> AdbMessage:
    """Join a header and its payload (kept, not copied), verifying a non-zero checksum."""
    if len(payload) != header.data_length:
        raise AdbProtocolError(device, "framing",
                               f"payload {len(payload)} bytes, header says {header.data_length}")
    if header.data_check and checksum(payload) != header.data_check:
        raise AdbProtocolError(device, "framing",
                               f"{COMMAND_NAMES[header.command]} checksum 0x{checksum(payload):08X} "
                               f"!= header 0x{header.data_check:08X}")
    return AdbMessage(header.command, header.arg0, header.arg1, payload)


def decode(data: bytes, *, device: str = "adb") -> AdbMessage:
    """Decode one complete message (header + payload) from bytes."""
    header = decode_header(data[:HEADER_SIZE], device=device)
    return finish_message(header, data[HEADER_SIZE:], device=device)


def agreed(peer_version: int, peer_max_payload: int, own_max_payload: int) -> tuple[int, int]:
    """(version, max payload in bytes) both ends use once they have exchanged CNXN: the older
    version, and the smaller maximum, never below the 4096 bytes every end accepts."""
    return min(peer_version, A_VERSION), max(min(peer_max_payload, own_max_payload), MAX_PAYLOAD_LEGACY)


def checksummed(version: int) -> bool:
    """Whether messages of this (agreed) version carry a payload checksum."""
    return version < A_VERSION_SKIP_CHECKSUM


def connect_message(banner: bytes, *, version: int = A_VERSION, max_payload: int = MAX_PAYLOAD) -> AdbMessage:
    """CNXN(version, maxdata, "<system-identity>\\0")."""
    return AdbMessage(A_CNXN, version, max_payload, banner + b"\0")


def parse_banner(payload: bytes) -> tuple[str, dict[str, str]]:
    """'device::k=v;k=v;features=a,b' -> ('device', {k: v}); the trailing NUL is optional."""
    text = payload.rstrip(b"\0").decode("utf-8", "replace")
    kind, _, rest = text.partition(":")
    _, _, props = rest.partition(":")
    fields = {}
    for item in props.split(";"):
        key, sep, value = item.partition("=")
        if sep:
            fields[key] = value
    return kind, fields
