"""A careless or hostile control client (issue 14): deep JSON gets an error reply on a connection that
stays open; connections are limited in number and idle time, so clients cannot exhaust the daemon's
file descriptors."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from daemon.rig.states import ScanState
from daemon.server.control import CommandFailed, ControlClient, ControlServer
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
    """`tbp scan` against a crowded daemon says the daemon is busy; the refusal used to be sent
    before the client wrote, so its write failed and it reported 'connection lost'."""
    sock = tmp_path / "c.sock"
    async with ControlServer(sock, FakeDaemon()) as server:
        held = [await asyncio.open_unix_connection(str(sock)) for _ in range(ControlServer.MAX_CONNECTIONS)]
        while len(server._connections) < ControlServer.MAX_CONNECTIONS:
            await asyncio.sleep(0.01)
        reader, writer = await asyncio.open_unix_connection(str(sock))
        await asyncio.sleep(0.2)  # a slow client: the server has had time to answer before it writes
        reply = await _request(reader, writer, b'{"id": 1, "cmd": "scan"}\n')
        assert reply["error"]["type"] == "TooManyConnections" and reply["id"] == 1
        writer.close()
        with pytest.raises(CommandFailed) as refused:
            await ControlClient(sock).scan()
        assert refused.value.error_type == "TooManyConnections"
        for _, w in held:
            w.close()


async def _silent_subscriber(sock: Path) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Subscribes, reads the reply, then never reads again."""
    reader, writer = await asyncio.open_unix_connection(str(sock))
    assert (await _request(reader, writer, b'{"id": 1, "cmd": "subscribe"}\n'))["ok"] is True
    return reader, writer


async def test_status_abort_and_reset_always_have_a_slot(tmp_path: Path) -> None:
    """Issue 28: 16 subscribers that never read locked `tbp status` and `tbp abort` out. Subscribers
    now have their own pool, and beyond every pool the urgent commands are still served."""
    sock = tmp_path / "c.sock"
    daemon = FakeDaemon()
    async with ControlServer(sock, daemon) as server:
        subscribers = [await _silent_subscriber(sock) for _ in range(ControlServer.MAX_SUBSCRIBERS)]
        idle = [await asyncio.open_unix_connection(str(sock)) for _ in range(ControlServer.MAX_CONNECTIONS)]
        while len(server._connections) < ControlServer.MAX_CONNECTIONS:
            await asyncio.sleep(0.01)
        client = ControlClient(sock)
        assert (await client.status())["state"] == "IDLE"
        daemon.machine.transition(ScanState.PREPARING, "start pressed")
        assert (await client.abort())["state"] == "ABORTING"
        with pytest.raises(CommandFailed) as refused:  # served: the handler's own refusal
            await client.reset()
        assert refused.value.error_type == "IllegalTransition"
        with pytest.raises(CommandFailed) as full:
            await anext(client.subscribe())
        assert full.value.error_type == "TooManySubscribers"
        for _, w in subscribers + idle:
            w.close()


def test_a_subscriber_that_stops_reading_is_dropped_and_logged(tmp_path: Path) -> None:
    sock = tmp_path / "c.sock"
    daemon = FakeDaemon()

    async def main() -> None:
        async with ControlServer(sock, daemon) as server:
            reader, writer = await _silent_subscriber(sock)
            with capture_logs() as records:
                published = 0
                while published < 100_000 and not any(r["event"] == "control_subscriber_dropped" for r in records):
                    daemon.machine.progress("captured", note="x" * 200, index=published)
                    published += 1
                    await asyncio.sleep(0)  # the server's send task runs
            dropped = [r for r in records if r["event"] == "control_subscriber_dropped"]
            assert dropped, f"still subscribed after {published} events"
            assert dropped[0]["pending_events"] == ControlServer.MAX_PENDING_EVENTS
            assert dropped[0]["peer_pid"] == os.getpid() and dropped[0]["peer_uid"] == os.getuid()
            await asyncio.sleep(ControlServer.HANG_UP_GRACE_S)  # it had that long to read why
            assert not server._subscribers
            received = 0
            with contextlib.suppress(ConnectionError):
                while await reader.readline():  # what was sent before the drop, then the end
                    received += 1
            assert received < published
            assert not daemon.machine._subscribers  # the handler's stream is closed
            writer.close()

    run_virtual(main(), idle_real_timeout=5.0)


async def test_a_subscriber_that_keeps_sending_is_hung_up_on_and_costs_no_memory(tmp_path: Path) -> None:
    """Issue 28: bytes sent after `subscribe` were read without bound (600 MiB sent grew the daemon
    by 1 GB). A byte now ends the subscription; at most LINGER_MAX_BYTES more are read."""
    sock = tmp_path / "c.sock"
    async with ControlServer(sock, FakeDaemon()) as server:
        _reader, writer = await _silent_subscriber(sock)

        async def flood() -> int:
            sent = 0
            chunk = b"x" * (1 << 20)
            with contextlib.suppress(ConnectionError):
                while sent < 64 << 20:
                    writer.write(chunk)
                    await writer.drain()
                    sent += len(chunk)
            return sent

        sent, _growth = await within_rss(flood(), limit_bytes=32 << 20)
        assert sent < 64 << 20, "the daemon kept reading"
        while server._subscribers:
            await asyncio.sleep(0.01)
        writer.close()


def test_a_request_on_a_subscription_is_answered_with_a_protocol_error(tmp_path: Path) -> None:
    sock = tmp_path / "c.sock"

    async def main() -> None:
        async with ControlServer(sock, FakeDaemon()) as server:
            reader, writer = await _silent_subscriber(sock)
            writer.write(b'{"id": 2, "cmd": "status"}\n')
            reply = json.loads(await reader.readline())
            assert reply["error"]["type"] == "ProtocolError" and "only events" in reply["error"]["message"]
            assert await reader.read() == b""
            writer.close()
            while server._subscribers:
                await asyncio.sleep(0.01)

    run_virtual(main(), idle_real_timeout=5.0)


def test_a_client_that_does_not_read_its_replies_is_hung_up_on(tmp_path: Path) -> None:
    """Pipelined requests whose replies are never read held a request slot for ever (the reply's
    drain never returned)."""
    sock = tmp_path / "c.sock"

    async def main() -> None:
        async with ControlServer(sock, FakeDaemon()) as server:
            _reader, writer = await asyncio.open_unix_connection(str(sock))
            writer.write(b'{"id": 1, "cmd": "status"}\n' * 100_000)
            async with asyncio.timeout(3 * ControlServer.IDLE_TIMEOUT_S):
                while not server._connections:
                    await asyncio.sleep(0.01)
                while server._connections:
                    await asyncio.sleep(0.1)
            writer.transport.abort()

    run_virtual(main(), idle_real_timeout=5.0)


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
