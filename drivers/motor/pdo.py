"""PDO mapping and codec (CiA 301): which objects a PDO carries and how its bytes decode.

A mapping is a tuple of :class:`MappedObject` (index, sub-index, struct format); its bytes are
the objects packed little-endian back to back, at most 8 bytes.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass

# Communication (0x1800 + k, 0x1400 + k) and mapping (0x1A00 + k, 0x1600 + k) parameter
# objects of TPDO and RPDO k+1.
TPDO_COMMUNICATION = 0x1800
TPDO_MAPPING = 0x1A00
RPDO_COMMUNICATION = 0x1400
RPDO_MAPPING = 0x1600
COB_ID_INVALID = 0x8000_0000
# TPDO: sent on the manufacturer-specific event (the event timer); RPDO: acts on reception.
TRANSMISSION_EVENT_DRIVEN = 0xFF


@dataclass(frozen=True)
class MappedObject:
    """One object in a PDO: index, sub-index and its struct format (``<H``, ``<i``...)."""

    index: int
    subindex: int
    fmt: str

    @property
    def bits(self) -> int:
        return struct.calcsize(self.fmt) * 8

    @property
    def entry(self) -> int:
        """The u32 mapping entry written to 0x1A0k:n: index << 16 | sub-index << 8 | bits."""
        return map_entry(self.index, self.subindex, self.bits)


def map_entry(index: int, subindex: int, bits: int) -> int:
    return (index << 16) | (subindex << 8) | bits


def parse_map_entry(value: int) -> tuple[int, int, int]:
    """(index, sub-index, bits) from a u32 mapping entry."""
    return (value >> 16) & 0xFFFF, (value >> 8) & 0xFF, value & 0xFF


@functools.lru_cache(maxsize=64)
def _layout(mapping: tuple[MappedObject, ...]) -> str:
    return "<" + "".join(m.fmt.lstrip("<") for m in mapping)


def pdo_length(mapping: tuple[MappedObject, ...]) -> int:
    return struct.calcsize(_layout(mapping))


def encode_pdo(mapping: tuple[MappedObject, ...], values: tuple[int, ...]) -> bytes:
    """The PDO's data bytes for one value per mapped object."""
    if len(values) != len(mapping):
        raise ValueError(f"{len(values)} values for {len(mapping)} mapped objects")
    data = struct.pack(_layout(mapping), *values)
    if len(data) > 8:
        raise ValueError(f"PDO of {len(data)} bytes exceeds 8")
    return data


def decode_pdo(mapping: tuple[MappedObject, ...], data: bytes) -> tuple[int, ...]:
    """The mapped objects' values from a PDO's data bytes (length must match exactly)."""
    expected = pdo_length(mapping)
    if len(data) != expected:
        raise ValueError(f"PDO has {len(data)} bytes, mapping expects {expected}: {bytes(data).hex()}")
    return tuple(int(v) for v in struct.unpack(_layout(mapping), data))
