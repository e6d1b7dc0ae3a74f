"""Fuzzing the ADB client's parsers with hypothesis: whatever a device sends, the host raises only
the ADB area's typed errors and buffers only what flow control allows."""

from __future__ import annotations

import asyncio
import struct
from collections import deque
from pathlib import Path
from types import SimpleNamespace

from hypothesis import given
from hypothesis import strategies as st

from drivers.adb.auth import AdbKey
from drivers.adb.connection import AdbConnection
from drivers.adb.errors import AdbError, AdbProtocolError, ConnectionLost, StreamClosed
from drivers.adb.message import (
    A_AUTH,
    A_CLSE,
    A_CNXN,
    A_OKAY,
    A_OPEN,
    A_WRTE,
    COMMAND_NAMES,
    HEADER_SIZE,
    MAX_PAYLOAD,
    AdbMessage,
    decode,
    parse_banner,
)
from drivers.adb.streams import StreamMux
from drivers.adb.sync import SyncClient
from sim.clock import run_virtual
from tests.fuzz import FUZZ

KEY = AdbKey.generate("fuzz@host")


class ScriptedTransport:
    """A link whose device side is a fixed list of messages; records what the host sends."""

    name = "fuzz"

    def __init__(self, messages: list[AdbMessage]) -> None:
        self.incoming = deque(messages)
        self.sent: list[AdbMessage] = []

    async def send(self, message: AdbMessage, *, with_checksum: bool = True) -> None:
        self.sent.append(message)

    async def recv(self, max_payload: int = MAX_PAYLOAD) -> AdbMessage:
        await asyncio.sleep(0)
        if not self.incoming:
            raise ConnectionLost(self.name, "receiving", "script ended")
        return self.incoming.popleft()

    async def close(self) -> None:
        self.incoming.clear()


commands = st.sampled_from(sorted(COMMAND_NAMES))
small_ids = st.sampled_from([0, 1, 2, 77, 78, 2**32 - 1])
messages = st.builds(AdbMessage, commands, small_ids, small_ids, st.binary(max_size=64))


@FUZZ
@given(st.binary(max_size=HEADER_SIZE + 80))
def test_decode_raises_only_protocol_errors(raw: bytes) -> None:
    try:
        msg = decode(raw)
    except AdbProtocolError:
        return
    assert msg.command in COMMAND_NAMES and len(msg.payload) == len(raw) - HEADER_SIZE


@FUZZ
@given(st.binary(max_size=300))
def test_parse_banner_never_fails(payload: bytes) -> None:
    kind, props = parse_banner(payload)
    assert isinstance(kind, str) and all(isinstance(v, str) for v in props.values())


@FUZZ
@given(st.lists(messages, max_size=40))
def test_stream_mux_survives_any_message_sequence_and_never_buffers_past_its_window(
        script: list[AdbMessage]) -> None:
    """Stream 1 is opened by the device's first OKAY, then never read (the worst case for buffering)."""

    async def main() -> None:
        transport = ScriptedTransport([AdbMessage(A_OKAY, 77, 1), *script])
        mux = StreamMux(transport, name="fuzz")  # type: ignore[arg-type]
        opening = asyncio.ensure_future(mux.open("shell:x"))
        await mux.run()  # returns when the link is lost; raises anything that is not an AdbError
        stream = await opening
        assert isinstance(mux.lost, ConnectionLost)
        assert len(stream._payloads) <= mux.READ_WINDOW + 1

    run_virtual(main())


def _handshake_messages() -> st.SearchStrategy[AdbMessage]:
    return st.builds(
        AdbMessage, st.sampled_from([A_AUTH, A_CNXN, A_OKAY, A_WRTE, A_OPEN, A_CLSE]),
        st.sampled_from([0, 1, 2, 3, 0x01000000, 0x01000001, 2**32 - 1]), st.integers(0, 2**32 - 1),
        st.one_of(st.binary(min_size=20, max_size=20), st.binary(max_size=64)))


@FUZZ
@given(st.lists(_handshake_messages(), max_size=5))
def test_handshake_raises_only_adb_errors(script: list[AdbMessage]) -> None:
    async def main() -> None:
        conn = AdbConnection(ScriptedTransport(script), KEY)  # type: ignore[arg-type]
        try:
            banner = await conn.connect()
        except AdbError:
            assert conn.state == "lost"
        else:
            assert conn.state == "online" and banner.max_payload >= 4096
        await conn.close()

    run_virtual(main())


class ScriptedSyncStream:
    """The 'sync:' stream of a device whose answers are fixed bytes."""

    def __init__(self, answer: bytes) -> None:
        self.answer = answer
        self.pos = 0
        self.state = "open"
        self.mux = SimpleNamespace(max_payload=4096)

    async def write(self, data: bytes) -> None:
        if self.state != "open":
            raise StreamClosed("fuzz", self.state, "closed")

    async def readexactly(self, n: int) -> bytes:
        if self.state != "open" or self.pos + n > len(self.answer):
            raise StreamClosed("fuzz", self.state, f"ended after {len(self.answer) - self.pos} of {n} bytes")
        self.pos += n
        return self.answer[self.pos - n:self.pos]

    async def readview(self, n: int) -> memoryview:
        return memoryview(await self.readexactly(n))

    async def close(self) -> None:
        self.state = "closed"


_IDS = [b"DATA", b"DONE", b"FAIL", b"DENT", b"STAT", b"OKAY", b"QUIT", b"XXXX"]
sync_pieces = st.one_of(
    st.builds(lambda ident, n: struct.pack("<4sI", ident, n), st.sampled_from(_IDS),
              st.one_of(st.integers(0, 80), st.integers(0, 2**32 - 1))),
    st.builds(lambda n: struct.pack("<IIII", *n), st.tuples(*[st.integers(0, 2**32 - 1)] * 4)),
    st.binary(max_size=40),
)


@FUZZ
@given(st.lists(sync_pieces, max_size=12).map(b"".join), st.sampled_from(["stat", "list", "pull_bytes", "pull"]))
def test_sync_answers_raise_only_adb_errors(answer: bytes, op: str) -> None:
    async def main(dest: Path) -> None:
        sync = SyncClient(ScriptedSyncStream(answer), device="fuzz")  # type: ignore[arg-type]
        try:
            if op == "stat":
                await sync.stat("/sdcard/a")
            elif op == "list":
                entries = await sync.list("/sdcard")
                assert all(len(e.name.encode()) <= 4 * 1024 for e in entries)
            elif op == "pull_bytes":
                assert len(await sync.pull_bytes("/sdcard/a", max_bytes=100)) <= 100
            else:
                size, _ = await sync.pull("/sdcard/a", dest, max_bytes=100)
                assert size <= 100 and dest.stat().st_size == size
        except AdbError:
            assert not dest.with_name(dest.name + ".part").exists()

    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        run_virtual(main(Path(folder) / "a.jpg"))
