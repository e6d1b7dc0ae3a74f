"""The web server's life in the daemon's event loop: start after the rig is up, close before it.

The server shares the daemon's file descriptors with the devices, so slow and crowding clients
are bounded:

* a connection that has not sent a whole request header HEADER_TIMEOUT_S after it opened (or
  after its previous answer) is closed: aiohttp's keep-alive timer closes a connection still
  waiting for a request, and it starts when the connection opens;
* a request body that has not arrived READ_TIMEOUT_S after its header closes its connection
  (``web.app.guard``);
* at most MAX_CONNECTIONS connections: when full, the connection waiting longest without a
  request in progress is closed to make room (a slow-header flood cannot keep a real request
  out); when every one is serving a request, the newcomer is answered 503.
"""

from __future__ import annotations

import asyncio
from typing import Any

import structlog
from aiohttp import web

from drivers.noise import NoiseLog

log = structlog.get_logger("web.server")

_BUSY_TEXT = b"every connection of this server is serving a request; try again\n"
BUSY_RESPONSE = (b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
                 b"Content-Length: %d\r\nRetry-After: 1\r\nConnection: close\r\n\r\n%s"
                 % (len(_BUSY_TEXT), _BUSY_TEXT))


class WebServer:
    """Serves ``app`` on host:port (port 0 picks a free one, see :attr:`url`)."""

    SHUTDOWN_TIMEOUT_S = 1.0
    HEADER_TIMEOUT_S = 10.0
    MAX_CONNECTIONS = 64
    BACKLOG = 64

    def __init__(self, app: web.Application, host: str, port: int) -> None:
        self.app = app
        self.host = host
        self.port = port
        self._runner: web.AppRunner | None = None
        self.gate: ConnectionGate | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    async def start(self) -> None:
        self._runner = web.AppRunner(self.app, access_log=None, shutdown_timeout=self.SHUTDOWN_TIMEOUT_S,
                                     keepalive_timeout=self.HEADER_TIMEOUT_S)
        await self._runner.setup()
        assert self._runner.server is not None
        self.gate = ConnectionGate(self._runner.server, self.MAX_CONNECTIONS)
        site = _GatedSite(self._runner, self.host, self.port, self.gate, backlog=self.BACKLOG)
        await site.start()
        self.port = site.port
        log.info("web_listening", url=self.url, max_connections=self.MAX_CONNECTIONS,
                 header_timeout_s=self.HEADER_TIMEOUT_S)

    def open_connections(self) -> int:
        """Connections open now (0 before start)."""
        return len(self.gate.open_connections()) if self.gate is not None else 0

    async def close(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self.gate is not None:
            self.gate.flush()

    async def __aenter__(self) -> WebServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class ConnectionGate:
    """The protocol factory of the server's socket: aiohttp's handler for each new connection,
    at most ``limit`` of them open (see the module's docstring)."""

    def __init__(self, server: web.Server, limit: int) -> None:
        self.server = server
        self.limit = limit
        self._opened: dict[Any, float] = {}  # handler -> loop time its connection opened
        self._evicted = NoiseLog(log, "web_connection_evicted", period_s=10.0)
        self._refused = NoiseLog(log, "web_connection_refused", period_s=10.0)

    def open_connections(self) -> list[Any]:
        """aiohttp's handlers whose connection is open."""
        return [h for h in self.server.connections if h.transport is not None]

    def __call__(self) -> asyncio.BaseProtocol:
        now = asyncio.get_running_loop().time()
        live = self.open_connections()
        self._opened = {h: self._opened.get(h, now) for h in live}
        if len(live) >= self.limit:
            # aiohttp sets _request_in_progress from a request's header to the end of its answer
            waiting = [h for h in live if not h._request_in_progress]
            if not waiting:
                self._refused.report(limit=self.limit)
                return _Busy()
            oldest = min(waiting, key=self._opened.__getitem__)
            self._evicted.report(limit=self.limit, peer=str(oldest.peername),
                                 waited_s=round(now - self._opened.pop(oldest), 3))
            oldest.force_close()
        handler = self.server()
        self._opened[handler] = now
        return handler

    def flush(self) -> None:
        self._evicted.flush()
        self._refused.flush()


class _Busy(asyncio.Protocol):
    """A connection the server has no room for: answered 503 and closed."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        transport.write(BUSY_RESPONSE)
        transport.close()


class _GatedSite(web.BaseSite):
    """aiohttp's TCP site, its connections made by a :class:`ConnectionGate`."""

    def __init__(self, runner: web.AppRunner, host: str, port: int, gate: ConnectionGate, *,
                 backlog: int) -> None:
        super().__init__(runner, backlog=backlog)
        self.host = host
        self.port = port
        self.gate = gate

    @property
    def name(self) -> str:
        return f"http://{self.host}:{self.port}"

    async def start(self) -> None:
        await super().start()
        server = await asyncio.get_running_loop().create_server(
            self.gate, self.host, self.port, backlog=self._backlog, reuse_address=True)
        self._server = server
        self.port = server.sockets[0].getsockname()[1]
