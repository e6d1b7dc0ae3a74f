"""ADB wire framing: byte-exact headers, checksums, magic, banners and sync requests."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.adb.errors import AdbProtocolError
from drivers.adb.message import (
    A_AUTH,
    A_CLSE,
    A_OKAY,
    A_OPEN,
    A_WRTE,
    COMMAND_NAMES,
    HEADER_SIZE,
    AdbMessage,
    checksum,
    connect_message,
    decode,
    decode_header,
    parse_banner,
)
from drivers.adb.sync import data_chunks, request


def test_cnxn_bytes_exact() -> None:
    msg = connect_message(b"host::")
    assert msg.encode() == bytes.fromhex(
        "434e584e" "01000001" "00001000" "07000000" "32020000" "bcb1a7b1") + b"host::\0"


def test_auth_signature_header_exact() -> None:
    payload = bytes(range(256))
    msg = AdbMessage(A_AUTH, 2, 0, payload)
    assert msg.encode()[:HEADER_SIZE] == bytes.fromhex(
        "41555448" "02000000" "00000000" "00010000" "807f0000" "beaaabb7")


def test_open_and_wrte_exact_and_checksum_skipped_after_handshake() -> None:
    open_msg = AdbMessage(A_OPEN, 1, 0, b"shell:echo hi\0")
    assert open_msg.encode(with_checksum=False) == (
        b"OPEN" + struct.pack("<IIII", 1, 0, 14, 0) + struct.pack("<I", A_OPEN ^ 0xFFFFFFFF) + b"shell:echo hi\0")
    wrte = AdbMessage(A_WRTE, 7, 3, b"abc")
    assert wrte.encode() == b"WRTE" + struct.pack("<IIIII", 7, 3, 3, 294, A_WRTE ^ 0xFFFFFFFF) + b"abc"
    # CNXN and AUTH always carry the checksum
    assert struct.unpack("<6I", connect_message(b"host::").header(with_checksum=False))[4] == 562


def test_okay_and_clse_have_no_payload() -> None:
    assert AdbMessage(A_OKAY, 5, 9).encode() == b"OKAY" + struct.pack("<IIIII", 5, 9, 0, 0, A_OKAY ^ 0xFFFFFFFF)
    assert AdbMessage(A_CLSE, 0, 9).encode() == b"CLSE" + struct.pack("<IIIII", 0, 9, 0, 0, A_CLSE ^ 0xFFFFFFFF)


@settings(deadline=None)
@given(st.sampled_from(sorted(COMMAND_NAMES)), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1),
       st.binary(max_size=3000), st.booleans())
def test_encode_decode_round_trip(command: int, arg0: int, arg1: int, payload: bytes, with_checksum: bool) -> None:
    msg = AdbMessage(command, arg0, arg1, payload)
    assert decode(msg.encode(with_checksum=with_checksum)) == msg


@settings(deadline=None)
@given(st.binary(max_size=5000))
def test_checksum_is_byte_sum(payload: bytes) -> None:
    assert checksum(payload) == sum(payload) % 2**32


def test_bad_magic_refused() -> None:
    raw = bytearray(AdbMessage(A_OKAY, 1, 2).encode())
    raw[20] ^= 0x01
    with pytest.raises(AdbProtocolError, match="bad magic"):
        decode(bytes(raw))


def test_bad_checksum_refused() -> None:
    raw = bytearray(AdbMessage(A_WRTE, 1, 2, b"hello").encode())
    raw[-1] ^= 0x01
    with pytest.raises(AdbProtocolError, match="checksum"):
        decode(bytes(raw))


def test_unknown_command_and_oversize_refused() -> None:
    bogus = struct.pack("<6I", 0x41414141, 0, 0, 0, 0, 0x41414141 ^ 0xFFFFFFFF)
    with pytest.raises(AdbProtocolError, match="unknown command"):
        decode_header(bogus)
    big = struct.pack("<6I", A_WRTE, 1, 1, 5000, 0, A_WRTE ^ 0xFFFFFFFF)
    with pytest.raises(AdbProtocolError, match="limit 4096"):
        decode_header(big, max_payload=4096)
    with pytest.raises(AdbProtocolError, match="header is 23 bytes"):
        decode_header(bogus[:23])


@settings(deadline=None)
@given(st.binary(min_size=HEADER_SIZE, max_size=HEADER_SIZE))
def test_random_headers_never_crash(raw: bytes) -> None:
    try:
        header = decode_header(raw)
    except AdbProtocolError:
        return
    assert header.command in COMMAND_NAMES


def test_parse_banner() -> None:
    kind, props = parse_banner(b"device::ro.product.name=p;ro.product.model=Pixel 8;features=shell_v2,cmd\0")
    assert kind == "device"
    assert props == {"ro.product.name": "p", "ro.product.model": "Pixel 8", "features": "shell_v2,cmd"}


def test_sync_requests_exact() -> None:
    assert request(b"STAT", "/sdcard/a.jpg") == b"STAT\x0d\x00\x00\x00/sdcard/a.jpg"
    assert request(b"RECV", "/x") == b"RECV\x02\x00\x00\x00/x"
    assert request(b"SEND", "/x,33188") == b"SEND\x08\x00\x00\x00/x,33188"
    assert data_chunks(b"ab") == b"DATA\x02\x00\x00\x00ab"
    with pytest.raises(ValueError, match="1024"):
        request(b"STAT", "/" + "a" * 1024)


@settings(deadline=None)
@given(st.binary(max_size=200_000))
def test_data_chunks_at_most_64k(data: bytes) -> None:
    framed, out, pos = data_chunks(data), [], 0
    while pos < len(framed):
        ident, length = struct.unpack_from("<4sI", framed, pos)
        assert ident == b"DATA" and 0 < length <= 65536
        out.append(framed[pos + 8:pos + 8 + length])
        pos += 8 + length
    assert b"".join(out) == data
