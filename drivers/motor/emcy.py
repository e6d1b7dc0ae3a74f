"""CANopen emergency (EMCY) framing and the meaning of the error codes (CiA 301 / CiA 402)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

ERROR_RESET = 0x0000
FOLLOWING_ERROR = 0x8611
HEARTBEAT_ERROR = 0x8130
PDO_LENGTH_ERROR = 0x8210
EMERGENCY_STOP = 0x5441

_CODES = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x2320: "short circuit at outputs",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature device",
    0x4310: "excess temperature drive",
    0x5441: "emergency stop input (drive disabled by safety input)",
    0x6320: "parameter error",
    0x7305: "incremental sensor 1 fault",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8611: "following error",
    0x8612: "reference limit",
    0x9000: "external error",
}

_CLASSES = {
    0x10: "generic error",
    0x20: "current",
    0x21: "current, device input side",
    0x22: "current inside the device",
    0x23: "current, device output side",
    0x30: "voltage",
    0x40: "temperature",
    0x50: "device hardware",
    0x60: "device software",
    0x70: "additional modules",
    0x80: "monitoring",
    0x81: "communication",
    0x86: "position control",
    0x90: "external error",
    0xF0: "additional functions",
    0xFF: "device specific",
}


def emcy_meaning(code: int) -> str:
    """The meaning of an EMCY error code: the exact code if known, else its class."""
    if code in _CODES:
        return _CODES[code]
    for key in (code >> 8, (code >> 8) & 0xF0):
        if key in _CLASSES:
            return f"{_CLASSES[key]} (0x{code:04X})"
    return f"unknown error code 0x{code:04X}"


@dataclass(frozen=True)
class Emcy:
    """One emergency message: error code, error register (0x1001), vendor bytes (5)."""

    code: int
    register: int
    vendor: bytes = bytes(5)

    @property
    def meaning(self) -> str:
        return emcy_meaning(self.code)


class EmcyFrameError(ValueError):
    """An EMCY frame that is not 8 bytes."""


def emcy_frame(emcy: Emcy) -> bytes:
    if len(emcy.vendor) > 5:
        raise ValueError(f"EMCY vendor data has {len(emcy.vendor)} bytes, at most 5")
    return struct.pack("<HB", emcy.code, emcy.register) + emcy.vendor.ljust(5, b"\0")


def parse_emcy(data: bytes) -> Emcy:
    if len(data) != 8:
        raise EmcyFrameError(f"EMCY frame has {len(data)} bytes, expected 8: {bytes(data).hex()}")
    code, register = struct.unpack_from("<HB", data)
    return Emcy(code, register, bytes(data[3:8]))
