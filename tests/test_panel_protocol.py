"""Panel line protocol: byte-exact framing, CRC-8, strict parsing of both directions."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.panel import PanelProtocolError
from drivers.panel.protocol import FROM_HOST, FROM_PANEL, MAX_LINE_BYTES, Line, crc8, encode, next_seq, parse

GRAMMARS = {"panel": FROM_PANEL, "host": FROM_HOST}


def test_crc8_is_crc8_smbus() -> None:
    assert crc8(b"123456789") == 0xF4  # the catalogued check value of CRC-8/SMBUS
    assert crc8(b"") == 0


def test_byte_exact_lines() -> None:
    assert encode(Line(5, "HB", ("0", "1", "IDLE")), FROM_PANEL) == b"05 HB 0 1 IDLE*99\n"
    body = b"FF LED SCANNING"
    assert encode(Line(255, "LED", ("SCANNING",)), FROM_HOST) == body + b"*%02X\n" % crc8(body)
    assert encode(Line(0, "BYE"), FROM_HOST) == b"00 BYE*%02X\n" % crc8(b"00 BYE")


@st.composite
def valid_lines(draw: st.DrawFn, grammar: dict) -> Line:
    verb = draw(st.sampled_from(sorted(grammar)))
    args = tuple(draw(st.from_regex(p, fullmatch=True)) for p in grammar[verb])
    return Line(draw(st.integers(0, 255)), verb, args)


@pytest.mark.parametrize("direction", sorted(GRAMMARS))
@given(data=st.data())
def test_round_trip(direction: str, data: st.DataObject) -> None:
    grammar = GRAMMARS[direction]
    line = data.draw(valid_lines(grammar))
    raw = encode(line, grammar)
    assert raw.endswith(b"\n") and len(raw) <= MAX_LINE_BYTES
    assert parse(raw, grammar) == line


@given(raw=st.binary(max_size=100))
def test_garbage_is_a_typed_error_or_a_valid_line(raw: bytes) -> None:
    try:
        line = parse(raw, FROM_PANEL, device="p1")
    except PanelProtocolError as exc:
        assert exc.device == "p1" and exc.line == raw
        return
    assert encode(line, FROM_PANEL) == raw


@given(data=st.data())
def test_any_changed_byte_is_refused(data: st.DataObject) -> None:
    raw = bytearray(encode(data.draw(valid_lines(FROM_PANEL)), FROM_PANEL))
    i = data.draw(st.integers(0, len(raw) - 1))
    raw[i] = data.draw(st.integers(0, 255).filter(lambda b: b != raw[i]))
    with pytest.raises(PanelProtocolError):
        parse(bytes(raw), FROM_PANEL)


@pytest.mark.parametrize(
    ("raw", "problem"),
    [
        (b"05 HB 0 1 IDLE*98\n", "checksum 98 where the line's CRC-8 is 99"),
        (b"05 HB 0 1 IDLE*99\r\n", "malformed frame"),
        (b"05 HB 0 1 IDLE*99", "malformed frame"),
        (b"05  HB 0 1 IDLE*99\n", "malformed frame"),
        (b"5 HB 0 1 IDLE*99\n", "malformed frame"),
        (b"05 HB 0 1 IDLE*99\n" + b" " * 60, "exceeds"),
    ],
)
def test_framing_errors(raw: bytes, problem: str) -> None:
    with pytest.raises(PanelProtocolError, match=problem):
        parse(raw, FROM_PANEL)


def _framed(body: bytes) -> bytes:
    return body + b"*%02X\n" % crc8(body)


@pytest.mark.parametrize(
    ("body", "problem"),
    [
        (b"01 LED IDLE", "unknown verb 'LED'"),  # a host verb arriving from the panel
        (b"01 HB 0 1", "HB takes 3 argument"),
        (b"01 HB 2 1 IDLE", "argument 1 '2'"),
        (b"01 HB 0 1 BLINK", "argument 3 'BLINK'"),
        (b"01 EVT PANIC", "argument 1 'PANIC'"),
        (b"01 ACK 1f", "argument 1 '1f'"),
        (b"01 HELLO TBP-PANEL 0 0", "argument 2 '0'"),
    ],
)
def test_grammar_errors_from_the_panel(body: bytes, problem: str) -> None:
    with pytest.raises(PanelProtocolError, match=problem):
        parse(_framed(body), FROM_PANEL)


def test_host_grammar_refuses_panel_verbs() -> None:
    with pytest.raises(PanelProtocolError, match="unknown verb 'EVT'"):
        parse(_framed(b"01 EVT START"), FROM_HOST)
    assert parse(_framed(b"01 LIGHT 1"), FROM_HOST) == Line(1, "LIGHT", ("1",))


def test_encode_refuses_what_parse_would_refuse() -> None:
    with pytest.raises(ValueError, match="sequence number 256"):
        encode(Line(256, "HB"), FROM_HOST)
    with pytest.raises(ValueError, match="LIGHT argument 1 'on'"):
        encode(Line(1, "LIGHT", ("on",)), FROM_HOST)
    with pytest.raises(ValueError, match="unknown verb 'HB'"):
        encode(Line(1, "HB", ("x",)), {})


def test_sequence_numbers_wrap() -> None:
    assert next_seq(0) == 1 and next_seq(0xFF) == 0
