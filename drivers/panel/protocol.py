"""The operator panel's line protocol: framing, CRC-8, grammar of each direction.

A line is ``SS VERB[ ARG]...*CC\\n`` in printable ASCII: ``SS`` the sender's sequence number
(two upper-case hex digits, +1 per new line, wrapping at FF), ``CC`` the CRC-8 (polynomial
0x07, initial value 0, no reflection: CRC-8/SMBUS) of every byte before ``*``, as two upper-case
hex digits. Parsing is strict: one space between fields, no ``\\r``, at most
:data:`MAX_LINE_BYTES` bytes, and each verb's arguments must match the grammar of the direction
the line travels. The contract for the panel firmware is docs/panel-protocol.md.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

from drivers.panel.errors import PanelProtocolError

PROTOCOL_VERSION = 1
PRODUCT = "TBP-PANEL"
MAX_LINE_BYTES = 64  # including the final newline
HEARTBEAT_PERIOD_S = 0.2  # both directions
HEARTBEAT_TIMEOUT_S = 0.6  # both directions: three heartbeats missed
EVENT_RESEND_S = 0.1  # the panel repeats an unacknowledged event this often
EVENT_RESENDS = 5  # ... at most this many times


class StatusLed(enum.Enum):
    """What the panel's status LED shows (the firmware chooses colours and blink patterns)."""

    OFF = "OFF"
    IDLE = "IDLE"
    BUSY = "BUSY"
    SCANNING = "SCANNING"
    FAULT = "FAULT"


class PanelSignal(enum.Enum):
    """Argument of the panel's ``EVT`` line: a button edge or an e-stop change."""

    START = "START"
    STOP = "STOP"
    ESTOP_ON = "ESTOP_ON"
    ESTOP_OFF = "ESTOP_OFF"


_BIT = re.compile(r"[01]")
_SEQ = re.compile(r"[0-9A-F]{2}")
_VERSION = re.compile(r"[1-9][0-9]{0,2}")
_REASON = re.compile(r"[A-Z][A-Z_]{0,23}")
_LED = re.compile("|".join(led.value for led in StatusLed))
_SIGNAL = re.compile("|".join(signal.value for signal in PanelSignal))
_PRODUCT = re.compile(re.escape(PRODUCT))

# verb -> argument patterns, for lines the panel sends and lines the host sends.
FROM_PANEL: dict[str, tuple[re.Pattern[str], ...]] = {
    "HELLO": (_PRODUCT, _VERSION, _BIT),  # product, protocol version, e-stop pressed
    "HB": (_BIT, _BIT, _LED),  # e-stop pressed, light on, status LED shown
    "EVT": (_SIGNAL,),
    "ACK": (_SEQ,),  # sequence number of the host line acknowledged
    "NAK": (_SEQ, _REASON),
}
FROM_HOST: dict[str, tuple[re.Pattern[str], ...]] = {
    "HELLO": (_VERSION,),
    "HB": (),
    "LED": (_LED,),
    "LIGHT": (_BIT,),
    "ACK": (_SEQ,),  # sequence number of the panel EVT acknowledged
    "BYE": (),
}

_FRAME = re.compile(rb"([0-9A-F]{2}) ([A-Z]+)((?: [!-)+-~]+)*)\*([0-9A-F]{2})\n")


@dataclass(frozen=True)
class Line:
    """One protocol line: sender's sequence number (0-255), verb and arguments."""

    seq: int
    verb: str
    args: tuple[str, ...] = ()


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS (poly 0x07, init 0, no reflection, no final xor) of ``data``."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _check_grammar(
    verb: str, args: tuple[str, ...], grammar: dict[str, tuple[re.Pattern[str], ...]]
) -> str | None:
    """The grammar problem of ``verb args``, or None when they are valid."""
    patterns = grammar.get(verb)
    if patterns is None:
        return f"unknown verb {verb!r}"
    if len(args) != len(patterns):
        return f"{verb} takes {len(patterns)} argument(s), got {len(args)}"
    for i, (arg, pattern) in enumerate(zip(args, patterns)):
        if not pattern.fullmatch(arg):
            return f"{verb} argument {i + 1} {arg!r} does not match {pattern.pattern!r}"
    return None


def encode(line: Line, grammar: dict[str, tuple[re.Pattern[str], ...]]) -> bytes:
    """The wire bytes of ``line`` (with CRC and newline); ValueError if it breaks ``grammar``."""
    if not 0 <= line.seq <= 0xFF:
        raise ValueError(f"sequence number {line.seq} outside 0..255")
    problem = _check_grammar(line.verb, line.args, grammar)
    if problem is not None:
        raise ValueError(problem)
    body = " ".join((f"{line.seq:02X}", line.verb, *line.args)).encode("ascii")
    raw = body + b"*%02X\n" % crc8(body)
    if len(raw) > MAX_LINE_BYTES:
        raise ValueError(f"line of {len(raw)} bytes exceeds {MAX_LINE_BYTES}")
    return raw


def parse(
    raw: bytes, grammar: dict[str, tuple[re.Pattern[str], ...]], *, device: str = "panel"
) -> Line:
    """Parse one received line (including its ``\\n``); PanelProtocolError if anything is off."""
    if len(raw) > MAX_LINE_BYTES:
        raise PanelProtocolError(device, raw, f"line of {len(raw)} bytes exceeds {MAX_LINE_BYTES}")
    match = _FRAME.fullmatch(raw)
    if match is None:
        raise PanelProtocolError(device, raw, "malformed frame")
    seq, verb, args, crc = match.groups()
    body = raw[: raw.rindex(b"*")]
    expected = crc8(body)
    if int(crc, 16) != expected:
        raise PanelProtocolError(
            device, raw, f"checksum {crc.decode()} where the line's CRC-8 is {expected:02X}"
        )
    line = Line(int(seq, 16), verb.decode(), tuple(args.decode().split()))
    problem = _check_grammar(line.verb, line.args, grammar)
    if problem is not None:
        raise PanelProtocolError(device, raw, problem)
    return line


def next_seq(seq: int) -> int:
    """The sequence number after ``seq`` (wraps 0xFF -> 0x00)."""
    return (seq + 1) & 0xFF
