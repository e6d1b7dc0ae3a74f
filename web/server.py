"""The web server's life in the daemon's event loop: start after the rig is up, close before it."""

from __future__ import annotations

import structlog
from aiohttp import web

log = structlog.get_logger("web.server")


class WebServer:
    """Serves ``app`` on host:port (port 0 picks a free one, see :attr:`url`)."""

    SHUTDOWN_TIMEOUT_S = 1.0

    def __init__(self, app: web.Application, host: str, port: int) -> None:
        self.app = app
        self.host = host
        self.port = port
        self._runner: web.AppRunner | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    async def start(self) -> None:
        self._runner = web.AppRunner(self.app, access_log=None, shutdown_timeout=self.SHUTDOWN_TIMEOUT_S)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port, reuse_address=True)
        await site.start()
        if self.port == 0:
            server = getattr(site, "_server", None)
            self.port = server.sockets[0].getsockname()[1]
        log.info("web_listening", url=self.url)

    async def close(self) -> None:
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def __aenter__(self) -> WebServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
