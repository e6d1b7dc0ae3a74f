"""CANopen network management framing (CiA 301): COB-IDs, NMT commands, heartbeat / boot-up.

Pure functions over bytes so the framing is testable byte for byte.
"""

from __future__ import annotations

import enum

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080


def emcy_cob_id(node_id: int) -> int:
    return 0x080 + node_id


def tpdo_cob_id(number: int, node_id: int) -> int:
    """Default COB-ID of TPDO ``number`` (1-4)."""
    return 0x080 + 0x100 * number + node_id


def rpdo_cob_id(number: int, node_id: int) -> int:
    """Default COB-ID of RPDO ``number`` (1-4)."""
    return 0x100 + 0x100 * number + node_id


def sdo_response_cob_id(node_id: int) -> int:
    """Server -> client (0x580 + n)."""
    return 0x580 + node_id


def sdo_request_cob_id(node_id: int) -> int:
    """Client -> server (0x600 + n)."""
    return 0x600 + node_id


def heartbeat_cob_id(node_id: int) -> int:
    return 0x700 + node_id


class NmtCommand(enum.IntEnum):
    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(enum.IntEnum):
    """The state byte of a heartbeat (boot-up is the one-off 0x00)."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class CommunicationErrorBehaviour(enum.IntEnum):
    """0x1029:1 (CiA 301): the NMT state a node enters on a communication error (a lost
    heartbeat, bus off)."""

    PRE_OPERATIONAL = 0  # only from OPERATIONAL; PDOs stop
    NO_CHANGE = 1
    STOPPED = 2  # only NMT and heartbeat go on


class NmtFrameError(ValueError):
    """A frame that claims to be NMT or heartbeat but is malformed."""


def nmt_frame(command: NmtCommand, node_id: int) -> bytes:
    """The two data bytes of an NMT command on COB-ID 0; node 0 addresses every node."""
    if not 0 <= node_id <= 127:
        raise ValueError(f"NMT node id {node_id} outside 0..127")
    return bytes([int(command), node_id])


def parse_nmt(data: bytes) -> tuple[NmtCommand, int]:
    """(command, node id) from an NMT frame's data."""
    if len(data) != 2:
        raise NmtFrameError(f"NMT frame has {len(data)} bytes, expected 2: {bytes(data).hex()}")
    try:
        command = NmtCommand(data[0])
    except ValueError:
        raise NmtFrameError(f"unknown NMT command 0x{data[0]:02X}") from None
    return command, data[1]


def heartbeat_frame(state: NmtState) -> bytes:
    return bytes([int(state)])


def parse_heartbeat(data: bytes) -> NmtState:
    """The NMT state from a heartbeat / boot-up frame (the node-guarding toggle bit is ignored)."""
    if len(data) != 1:
        raise NmtFrameError(f"heartbeat has {len(data)} bytes, expected 1: {bytes(data).hex()}")
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError:
        raise NmtFrameError(f"unknown heartbeat state 0x{data[0]:02X}") from None


def consumer_heartbeat_value(producer_node: int, time_ms: int) -> int:
    """The u32 of a heartbeat consumer entry 0x1016:k: bits 23-16 node, 15-0 time (ms)."""
    if not 1 <= producer_node <= 127 or not 0 <= time_ms <= 0xFFFF:
        raise ValueError(f"consumer entry node {producer_node} / {time_ms} ms out of range")
    return (producer_node << 16) | time_ms


def parse_consumer_heartbeat(value: int) -> tuple[int, int]:
    """(producer node, time ms) from a 0x1016:k value; time 0 disables the entry."""
    return (value >> 16) & 0xFF, value & 0xFFFF
