"""A careless or hostile control client (issue 14): deep JSON gets an error reply on a connection that
stays open; connections are limited in number and idle time, so clients cannot exhaust the daemon's
file descriptors."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from daemon.control import CommandFailed, ControlClient, ControlServer
from sim.clock import run_virtual
from tests.memory import within_rss
from tests.test_control import FakeDaemon


async def _request(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, raw: bytes) -> dict:
    writer.write(raw)
    return json.loads(await asyncio.wait_for(reader.readline(), 5.0))


async def test_thirty_thousand_deep_json_gets_an_error_and_the_connection_stays(tmp_path: Path) -> None:
    sock = tmp_path / "c.sock"
    async with ControlServer(sock, FakeDaemon()):
        reader, writer = await asyncio.open_unix_connection(str(sock))
        for deep in (b"[" * 30_000 + b"]" * 30_000, b'{"a":' * 10_000 + b"1" + b"}" * 10_000):
            reply, _ = await within_rss(_request(reader, writer, deep + b"\n"))
            assert reply == {"id": None, "ok": False,
                             "error": {"type": "ProtocolError", "message": "JSON nested too deeply"}}
        assert (await _request(reader, writer, b'{"id": 2, "cmd": "status"}\n'))["ok"] is True
        writer.close()
        await writer.wait_closed()


async def test_connections_beyond_the_limit_are_told_why_and_closed(tmp_path: Path) -> None:
    sock = tmp_path / "c.sock"
    limit = ControlServer.MAX_CONNECTIONS
    async with ControlServer(sock, FakeDaemon()) as server:
        held = [await asyncio.open_unix_connection(str(sock)) for _ in range(limit)]
        while len(server._connections) < limit:
            await asyncio.sleep(0.01)
        extra_reader, extra_writer = await asyncio.open_unix_connection(str(sock))
        refused = json.loads(await asyncio.wait_for(extra_reader.readline(), 5.0))
        assert refused["error"]["type"] == "TooManyConnections" and str(limit) in refused["error"]["message"]
        assert await extra_reader.read() == b""  # hung up
        extra_writer.close()
        reader, writer = held[0]
        assert (await _request(reader, writer, b'{"id": 1, "cmd": "status"}\n'))["ok"] is True
        for _, w in held:
            w.close()
        while server._connections:
            await asyncio.sleep(0.01)
        assert (await ControlClient(sock).status())["state"] == "IDLE"  # slots are given back


async def test_a_client_over_the_limit_reads_why_instead_of_a_broken_pipe(tmp_path: Path) -> None:
    """`tbp status` against a crowded daemon says the daemon is busy; the refusal used to be sent
    before the client wrote, so its write failed and it reported 'connection lost'."""
    sock = tmp_path / "c.sock"
    async with ControlServer(sock, FakeDaemon()) as server:
        held = [await asyncio.open_unix_connection(str(sock)) for _ in range(ControlServer.MAX_CONNECTIONS)]
        while len(server._connections) < ControlServer.MAX_CONNECTIONS:
            await asyncio.sleep(0.01)
        reader, writer = await asyncio.open_unix_connection(str(sock))
        await asyncio.sleep(0.2)  # a slow client: the server has had time to answer before it writes
        reply = await _request(reader, writer, b'{"id": 1, "cmd": "status"}\n')
        assert reply["error"]["type"] == "TooManyConnections"
        writer.close()
        with pytest.raises(CommandFailed) as refused:
            await ControlClient(sock).status()
        assert refused.value.error_type == "TooManyConnections"
        for _, w in held:
            w.close()


def test_an_idle_connection_is_closed_after_the_idle_timeout(tmp_path: Path) -> None:
    sock = tmp_path / "c.sock"

    async def main() -> float:
        async with ControlServer(sock, FakeDaemon()) as server:
            reader, writer = await asyncio.open_unix_connection(str(sock))
            started = asyncio.get_running_loop().time()
            async with asyncio.timeout(3 * ControlServer.IDLE_TIMEOUT_S):
                assert await reader.read() == b""  # the daemon hung up
            waited = asyncio.get_running_loop().time() - started
            writer.close()
            while server._connections:
                await asyncio.sleep(0.01)
            return waited

    waited = run_virtual(main())
    assert ControlServer.IDLE_TIMEOUT_S <= waited < ControlServer.IDLE_TIMEOUT_S + 1.0
