"""The ADB client against a hostile device (issue 14, probe 3): every size the device sends is
bounded, every violation is a typed error, and the host's memory stays under 200 MiB of growth."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from drivers.adb.auth import AdbKey
from drivers.adb.connection import AdbConnection
from drivers.adb.errors import AdbLimitExceeded, AdbProtocolError, ConnectionLost
from drivers.adb.message import A_AUTH, A_CNXN, AUTH_TOKEN, AdbMessage
from drivers.adb.transport import StreamTransport
from sim.clock import run_virtual
from tests.adb_hostile import ENDLESS_DIR, HostileAdbd
from tests.adb_links import SimLink, stream_pair
from tests.memory import within_rss

KEY = AdbKey.generate("hostile@host")


def run(scenario: Callable[[AdbConnection, HostileAdbd], Awaitable[Any]]) -> int:
    """Run scenario(conn, device) on virtual time against a hostile adbd; the peak RSS growth."""

    async def main() -> int:
        device = HostileAdbd("EVIL0001", known_keys=[KEY.public_blob()])
        link = SimLink(device)
        conn = AdbConnection(await link.transport(), KEY)
        try:
            await conn.connect()
            _, peak = await within_rss(scenario(conn, device))
            return peak
        finally:
            await conn.close()
            await link.finish()

    return run_virtual(main())


def test_endless_shell_output_stops_at_the_limit_and_the_link_stays_up() -> None:
    async def scenario(conn: AdbConnection, device: HostileAdbd) -> None:
        with pytest.raises(AdbLimitExceeded, match="output of 'shell:yes'") as info:
            await conn.shell("yes")
        assert info.value.limit == AdbConnection.MAX_COMMAND_OUTPUT
        assert await conn.shell("echo still here") == b"still here\n"
        with pytest.raises(AdbLimitExceeded):
            await conn.exec("yes", max_bytes=1000)
        assert device.sent_bytes < 4 * AdbConnection.MAX_COMMAND_OUTPUT  # stopped, not drained

    run(scenario)


def test_wrte_beyond_the_flow_control_window_ends_the_link() -> None:
    """A stream nobody reads (like the capture agent's shell) while the device ignores OKAY."""

    async def scenario(conn: AdbConnection, device: HostileAdbd) -> None:
        stream = await conn.open("shell:flood")
        while conn.online:
            await asyncio.sleep(0.01)
        assert isinstance(conn.mux.lost, ConnectionLost)
        assert "beyond its flow-control window" in str(conn.mux.lost)
        assert device.sent_bytes < 16 * conn.mux.max_payload  # the host stopped reading at once
        with pytest.raises(ConnectionLost):
            await stream.read_all(10 * conn.mux.max_payload)

    run(scenario)


def test_endless_file_pull_stops_at_the_limit_and_leaves_nothing(tmp_path: Path) -> None:
    async def scenario(conn: AdbConnection, device: HostileAdbd) -> None:
        async with await conn.sync() as sync:
            with pytest.raises(AdbLimitExceeded, match="endless/a.jpg"):
                await sync.pull(f"{ENDLESS_DIR}/a.jpg", tmp_path / "a.jpg", max_bytes=3_000_000)
        assert list(tmp_path.iterdir()) == []
        async with await conn.sync() as sync:  # the default bound, into memory
            with pytest.raises(AdbLimitExceeded) as info:
                await sync.pull_bytes(f"{ENDLESS_DIR}/b.jpg")
        assert info.value.limit == 64 * 1024 * 1024
        assert await conn.shell("echo alive") == b"alive\n"

    peak = run(scenario)
    assert peak < 150 * 1024 * 1024  # the 64 MiB bound plus the host's own buffers


def test_endless_listing_long_names_and_long_fail_reasons_are_bounded() -> None:
    async def scenario(conn: AdbConnection, device: HostileAdbd) -> None:
        async with await conn.sync() as sync:
            with pytest.raises(AdbLimitExceeded, match="100000 entries"):
                await sync.list(ENDLESS_DIR)
        async with await conn.sync() as sync:
            with pytest.raises(AdbLimitExceeded, match="4294967295 bytes"):
                await sync.list("/sdcard/hugename")
        async with await conn.sync() as sync:
            with pytest.raises(AdbLimitExceeded, match="FAIL reason"):
                await sync.pull_bytes("/sdcard/longfail")
        assert await conn.shell("echo alive") == b"alive\n"

    run(scenario)


@pytest.mark.parametrize("size", [0, 19, 21, 4096])
def test_auth_token_of_the_wrong_length_is_a_protocol_error(size: int) -> None:
    async def main() -> None:
        (hr, hw), (dr, dw) = await stream_pair()
        device = StreamTransport(dr, dw, name="evil")
        conn = AdbConnection(StreamTransport(hr, hw, name="evil"), KEY)

        async def device_side() -> None:
            assert (await device.recv()).command == A_CNXN
            await device.send(AdbMessage(A_AUTH, AUTH_TOKEN, 0, bytes(size)))

        task = asyncio.create_task(device_side())
        with pytest.raises(AdbProtocolError, match=f"AUTH token of {size} bytes, expected 20"):
            await conn.connect()
        assert conn.state == "lost"
        await task
        dw.close()

    run_virtual(main())
