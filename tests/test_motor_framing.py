"""Byte-exact framing of the CANopen layer (SDO, PDO, NMT, heartbeat, EMCY) and the CiA 402 tables."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.motor import cia402, emcy, nmt, pdo, sdo, sdo_aborts
from drivers.motor.cia402 import Cia402State as S

index_st = st.integers(0, 0xFFFF)
sub_st = st.integers(0, 0xFF)


# ---------------------------------------------------------------------- SDO


def test_sdo_expedited_download_transcript() -> None:
    # Controlword 0x6040:0 <- 0x000F (2 bytes): 0x2B, index LE, sub, data LE padded.
    assert sdo.download_request(0x6040, 0, struct.pack("<H", 0x0F)) == bytes.fromhex("2B4060000F000000")
    # Target position 0x607A:0 <- -1000 (4 bytes): 0x23.
    assert sdo.download_request(0x607A, 0, struct.pack("<i", -1000)) == bytes.fromhex("237A600018FCFFFF")
    assert sdo.download_request(0x6060, 0, struct.pack("<b", 3)) == bytes.fromhex("2F60600003000000")
    assert sdo.download_request(0x1016, 1, b"\x01\x02\x03") == bytes.fromhex("2716100101020300")
    assert sdo.download_reply(0x6040, 0) == bytes.fromhex("6040600000000000")


def test_sdo_expedited_upload_transcript() -> None:
    assert sdo.upload_request(0x6041, 0) == bytes.fromhex("4041600000000000")
    assert sdo.upload_reply(0x6041, 0, struct.pack("<H", 0x0237)) == bytes.fromhex("4B41600037020000")
    assert sdo.upload_reply(0x6064, 0, struct.pack("<i", 123456)) == bytes.fromhex("4364600040E20100")
    reply = sdo.parse_sdo(bytes.fromhex("4B41600037020000"), from_client=False)
    assert (reply.kind, reply.index, reply.subindex, reply.data) == (
        sdo.SdoKind.UPLOAD_REPLY,
        0x6041,
        0,
        b"\x37\x02",
    )


def test_sdo_abort_transcript() -> None:
    frame = sdo.abort_frame(0x2000, 0, sdo_aborts.ABORT_NO_OBJECT)
    assert frame == bytes.fromhex("8000200000000206")
    parsed = sdo.parse_sdo(frame, from_client=False)
    assert parsed.kind is sdo.SdoKind.ABORT and parsed.code == 0x06020000
    assert sdo_aborts.abort_meaning(0x06090011) == "sub-index does not exist"


def test_sdo_parse_rejects_bad_frames() -> None:
    with pytest.raises(ValueError, match="expected 8"):
        sdo.parse_sdo(b"\x40\x41\x60", from_client=True)
    with pytest.raises(ValueError, match="unsupported SDO command"):
        sdo.parse_sdo(bytes.fromhex("E041600000000000"), from_client=True)
    with pytest.raises(ValueError, match="1-4 bytes"):
        sdo.download_request(0x6040, 0, b"")


def test_sdo_download_without_size_keeps_four_raw_bytes() -> None:
    request = sdo.parse_sdo(bytes.fromhex("2240600006000000"), from_client=True)
    assert request.kind is sdo.SdoKind.DOWNLOAD and not request.size_indicated
    assert request.raw == bytes.fromhex("06000000")


@given(index_st, sub_st, st.binary(min_size=1, max_size=4))
def test_sdo_download_round_trip(index: int, subindex: int, data: bytes) -> None:
    message = sdo.parse_sdo(sdo.download_request(index, subindex, data), from_client=True)
    assert (message.kind, message.index, message.subindex, message.data) == (
        sdo.SdoKind.DOWNLOAD,
        index,
        subindex,
        data,
    )


@given(index_st, sub_st, st.binary(min_size=1, max_size=4))
def test_sdo_upload_reply_round_trip(index: int, subindex: int, data: bytes) -> None:
    message = sdo.parse_sdo(sdo.upload_reply(index, subindex, data), from_client=False)
    assert (message.index, message.subindex, message.data) == (index, subindex, data)


@given(index_st, sub_st, st.integers(0, 0xFFFFFFFF))
def test_sdo_abort_round_trip(index: int, subindex: int, code: int) -> None:
    message = sdo.parse_sdo(sdo.abort_frame(index, subindex, code), from_client=True)
    assert (message.kind, message.index, message.subindex, message.code) == (
        sdo.SdoKind.ABORT,
        index,
        subindex,
        code,
    )


# ---------------------------------------------------------------------- PDO


def test_pdo_mapping_entries_and_codec() -> None:
    position = pdo.MappedObject(0x6064, 0, "<i")
    velocity = pdo.MappedObject(0x606C, 0, "<i")
    status = pdo.MappedObject(0x6041, 0, "<H")
    assert position.entry == 0x60640020
    assert status.entry == 0x60410010
    assert pdo.parse_map_entry(0x606C0020) == (0x606C, 0, 32)
    data = pdo.encode_pdo((position, velocity), (-2, 5689))
    assert data == bytes.fromhex("FEFFFFFF39160000")
    assert pdo.decode_pdo((position, velocity), data) == (-2, 5689)
    assert pdo.encode_pdo((status,), (0x0637,)) == bytes.fromhex("3706")


def test_pdo_rejects_wrong_lengths() -> None:
    position = pdo.MappedObject(0x6064, 0, "<i")
    with pytest.raises(ValueError, match="mapping expects 4"):
        pdo.decode_pdo((position,), b"\x00\x00")
    with pytest.raises(ValueError, match="exceeds 8"):
        pdo.encode_pdo((position, position, position), (1, 2, 3))
    with pytest.raises(ValueError, match="2 values for 1"):
        pdo.encode_pdo((position,), (1, 2))


@given(st.integers(-(2**31), 2**31 - 1), st.integers(-(2**31), 2**31 - 1))
def test_pdo_round_trip(position: int, velocity: int) -> None:
    mapping = (pdo.MappedObject(0x6064, 0, "<i"), pdo.MappedObject(0x606C, 0, "<i"))
    assert pdo.decode_pdo(mapping, pdo.encode_pdo(mapping, (position, velocity))) == (position, velocity)


# ---------------------------------------------------------------------- NMT, heartbeat, EMCY


def test_nmt_transcript() -> None:
    assert nmt.nmt_frame(nmt.NmtCommand.START, 5) == b"\x01\x05"
    assert nmt.nmt_frame(nmt.NmtCommand.RESET_COMMUNICATION, 5) == b"\x82\x05"
    assert nmt.nmt_frame(nmt.NmtCommand.ENTER_PRE_OPERATIONAL, 0) == b"\x80\x00"
    assert nmt.parse_nmt(b"\x81\x05") == (nmt.NmtCommand.RESET_NODE, 5)
    with pytest.raises(nmt.NmtFrameError, match="unknown NMT command"):
        nmt.parse_nmt(b"\x03\x05")
    with pytest.raises(nmt.NmtFrameError, match="expected 2"):
        nmt.parse_nmt(b"\x01")
    with pytest.raises(ValueError, match="outside 0..127"):
        nmt.nmt_frame(nmt.NmtCommand.START, 128)


def test_cob_ids() -> None:
    assert [nmt.tpdo_cob_id(k, 5) for k in (1, 2, 3, 4)] == [0x185, 0x285, 0x385, 0x485]
    assert [nmt.rpdo_cob_id(k, 5) for k in (1, 2, 3, 4)] == [0x205, 0x305, 0x405, 0x505]
    assert (
        nmt.emcy_cob_id(5),
        nmt.sdo_response_cob_id(5),
        nmt.sdo_request_cob_id(5),
        nmt.heartbeat_cob_id(5),
    ) == (0x85, 0x585, 0x605, 0x705)


def test_heartbeat_transcript() -> None:
    assert nmt.heartbeat_frame(nmt.NmtState.OPERATIONAL) == b"\x05"
    assert nmt.heartbeat_frame(nmt.NmtState.BOOT_UP) == b"\x00"
    assert nmt.parse_heartbeat(b"\x7f") is nmt.NmtState.PRE_OPERATIONAL
    assert nmt.parse_heartbeat(b"\x85") is nmt.NmtState.OPERATIONAL  # node-guarding toggle bit
    with pytest.raises(nmt.NmtFrameError, match="unknown heartbeat state"):
        nmt.parse_heartbeat(b"\x06")
    with pytest.raises(nmt.NmtFrameError, match="expected 1"):
        nmt.parse_heartbeat(b"")
    assert nmt.consumer_heartbeat_value(0x7F, 300) == 0x007F012C
    assert nmt.parse_consumer_heartbeat(0x007F012C) == (0x7F, 300)
    with pytest.raises(ValueError):
        nmt.consumer_heartbeat_value(0, 300)


def test_emcy_transcript() -> None:
    frame = emcy.emcy_frame(emcy.Emcy(0x8611, 0x21, b"\x01\x02"))
    assert frame == bytes.fromhex("1186210102000000")
    parsed = emcy.parse_emcy(frame)
    assert (parsed.code, parsed.register, parsed.vendor) == (0x8611, 0x21, bytes.fromhex("0102000000"))
    assert parsed.meaning == "following error"
    assert emcy.emcy_meaning(0x2311) == "current, device output side (0x2311)"
    assert emcy.emcy_meaning(0xFF42) == "device specific (0xFF42)"
    assert emcy.emcy_meaning(0xA000) == "unknown error code 0xA000"
    with pytest.raises(emcy.EmcyFrameError, match="expected 8"):
        emcy.parse_emcy(b"\x00\x10\x01")


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.binary(min_size=5, max_size=5))
def test_emcy_round_trip(code: int, register: int, vendor: bytes) -> None:
    assert emcy.parse_emcy(emcy.emcy_frame(emcy.Emcy(code, register, vendor))) == emcy.Emcy(
        code, register, vendor
    )


# ---------------------------------------------------------------------- CiA 402 tables


@pytest.mark.parametrize(
    ("statusword", "state"),
    [
        (0x0000, S.NOT_READY_TO_SWITCH_ON),
        (0x0250, S.SWITCH_ON_DISABLED),
        (0x0231, S.READY_TO_SWITCH_ON),
        (0x0233, S.SWITCHED_ON),
        (0x0637, S.OPERATION_ENABLED),
        (0x0617, S.QUICK_STOP_ACTIVE),
        (0x021F, S.FAULT_REACTION_ACTIVE),
        (0x0208, S.FAULT),
        (0x0228, S.FAULT),
    ],
)
def test_statusword_decoding(statusword: int, state: S) -> None:
    assert cia402.state_from_statusword(statusword) is state


def test_undefined_statusword_is_refused() -> None:
    with pytest.raises(ValueError, match="0x0041 matches no CiA 402 state"):
        cia402.state_from_statusword(0x0041)


@given(st.integers(0, 0xFFFF))
def test_statusword_patterns_are_exclusive(statusword: int) -> None:
    matches = [s for s, (mask, value) in cia402.STATUSWORD_PATTERNS.items() if statusword & mask == value]
    assert len(matches) <= 1


def test_paths_through_the_state_machine() -> None:
    assert cia402.path(S.SWITCH_ON_DISABLED, S.OPERATION_ENABLED) == [
        (S.READY_TO_SWITCH_ON, 0x06),
        (S.SWITCHED_ON, 0x07),
        (S.OPERATION_ENABLED, 0x0F),
    ]
    assert cia402.path(S.FAULT, S.OPERATION_ENABLED)[0] == (S.SWITCH_ON_DISABLED, 0x80)
    assert cia402.path(S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED) == [(S.OPERATION_ENABLED, 0x0F)]
    assert cia402.path(S.OPERATION_ENABLED, S.OPERATION_ENABLED) == []
    with pytest.raises(ValueError, match="no host transition"):
        cia402.path(S.SWITCH_ON_DISABLED, S.FAULT)


@pytest.mark.parametrize(
    "goal", [s for s in S if s not in (S.FAULT, S.FAULT_REACTION_ACTIVE, S.NOT_READY_TO_SWITCH_ON)]
)
@pytest.mark.parametrize("start", list(S))
def test_every_commandable_state_is_reachable(start: S, goal: S) -> None:
    if start in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE):
        with pytest.raises(ValueError):
            cia402.path(start, goal)
        return
    steps = cia402.path(start, goal)
    state = start
    for next_state, controlword in steps:
        assert CIA402_CONTROLWORDS[(state, next_state)] == controlword
        state = next_state
    assert state is goal


CIA402_CONTROLWORDS = {
    (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON): 0x06,  # 2 shutdown
    (S.READY_TO_SWITCH_ON, S.SWITCHED_ON): 0x07,  # 3 switch on
    (S.SWITCHED_ON, S.OPERATION_ENABLED): 0x0F,  # 4 enable operation
    (S.OPERATION_ENABLED, S.SWITCHED_ON): 0x07,  # 5 disable operation
    (S.SWITCHED_ON, S.READY_TO_SWITCH_ON): 0x06,  # 6 shutdown
    (S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED): 0x00,  # 7 disable voltage
    (S.OPERATION_ENABLED, S.READY_TO_SWITCH_ON): 0x06,  # 8 shutdown
    (S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED): 0x00,  # 9 disable voltage
    (S.SWITCHED_ON, S.SWITCH_ON_DISABLED): 0x00,  # 10 disable voltage
    (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE): 0x02,  # 11 quick stop
    (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED): 0x00,  # 12 disable voltage
    (S.FAULT, S.SWITCH_ON_DISABLED): 0x80,  # 15 fault reset
    (S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED): 0x0F,  # 16 enable operation
}
"""CiA 402's host-commanded transitions and their controlwords, written out from the profile
(not read back from the table under test)."""


def test_the_transition_table_is_the_profiles() -> None:
    assert cia402.TRANSITIONS == CIA402_CONTROLWORDS
