"""Slow and crowding web clients (issue 28, item 7): 200 clients that never finish their request
header held the server for as long as they liked (aiohttp's keep-alive timer: an hour), each a
descriptor the daemon shares with its devices. The server closes a header that has not arrived in
HEADER_TIMEOUT_S and a body that has not arrived in READ_TIMEOUT_S, keeps at most MAX_CONNECTIONS
open by closing the longest-waiting idle one for a newcomer, and answers 503 only when every
connection is serving a request. In virtual time, on loopback sockets."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from sim.clock import run_virtual
from web.access import Access
from web.app import READ_TIMEOUT_S, make_app
from web.server import WebServer

SLOW_CLIENTS = 200


def _server(tmp_path: Path) -> WebServer:
    return WebServer(make_app(tmp_path, Access("127.0.0.1", 0)), "127.0.0.1", 0)


async def _connect(port: int, sent: bytes) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(sent)
    for _ in range(3):  # the server accepts before the next client connects (its backlog stays short)
        await asyncio.sleep(0)
    return reader, writer


async def _get(port: int, path: str) -> bytes:
    reader, writer = await _connect(port, f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n".encode())
    try:
        return await reader.read()
    finally:
        writer.close()


async def _closed(reader: asyncio.StreamReader) -> bool:
    """The server has closed this connection (EOF or reset); False while it is open."""
    try:
        async with asyncio.timeout(0.5):
            return await reader.read() == b""
    except ConnectionError:
        return True
    except TimeoutError:
        return False


def test_slow_header_clients_leave_room_for_a_request_and_are_closed(tmp_path: Path) -> None:
    async def main() -> None:
        async with _server(tmp_path) as server:
            slow = [await _connect(server.port, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
                    for _ in range(SLOW_CLIENTS)]
            assert server.open_connections() <= WebServer.MAX_CONNECTIONS
            answer = await _get(server.port, "/api/config")
            assert answer.startswith(b"HTTP/1.1 200 ") and b'"writes": true' in answer
            await asyncio.sleep(WebServer.HEADER_TIMEOUT_S)
            assert server.open_connections() == 0
            assert all([await _closed(reader) for reader, _ in slow])
            for _, writer in slow:
                writer.close()
            assert (await _get(server.port, "/api/config")).startswith(b"HTTP/1.1 200 ")

    run_virtual(main(), idle_real_timeout=10.0)


def test_slow_bodies_are_closed_and_a_full_server_answers_503(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    async def main() -> None:
        async with _server(tmp_path) as server:
            with capture_logs() as records:
                slow = [await _connect(server.port, b"POST /login HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                                                    b"Content-Type: application/x-www-form-urlencoded\r\n"
                                                    b"Content-Length: 100\r\n\r\ntoken=")
                        for _ in range(WebServer.MAX_CONNECTIONS)]
                busy = await _get(server.port, "/api/config")
                assert busy.startswith(b"HTTP/1.1 503 ") and b"Retry-After: 1" in busy
                await asyncio.sleep(READ_TIMEOUT_S)
                assert all([await _closed(reader) for reader, _ in slow])
                for _, writer in slow:
                    writer.close()
                assert (await _get(server.port, "/api/config")).startswith(b"HTTP/1.1 200 ")
            assert sum(r["event"] == "web_slow_body_closed" for r in records) == WebServer.MAX_CONNECTIONS
            assert [r for r in records if r["event"] == "web_connection_refused"][0]["count"] == 1

    with caplog.at_level(logging.ERROR):
        run_virtual(main(), idle_real_timeout=10.0)
    assert not [r for r in caplog.records if r.name.startswith("aiohttp")], caplog.text[-3000:]
