"""The web application: pages, static assets (three.js from npm), viewer, marks and console APIs."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import structlog
from aiohttp import web

from daemon.records.store import ScanStore
from web import keys, login, marks, patients, rig, scans
from web.access import Access

STATIC = Path(__file__).with_name("static")
THREE = Path(__file__).with_name("node_modules") / "three"
MAX_REQUEST_BYTES = 64 * 1024
READ_TIMEOUT_S = 10.0

log = structlog.get_logger("web.app")


class AssetsMissing(RuntimeError):
    """three.js is not installed beside the web package (./dev installs it with npm)."""


@web.middleware
async def guard(request: web.Request, handler: Any) -> web.StreamResponse:
    """Host check, JSON errors for the API, a deadline for the body, and headers that keep pages
    to themselves."""
    access = request.app[keys.ACCESS]
    access.check_host(request)
    try:
        access.check_read(request)
        response = await _body_in_time(request, handler)
    except web.HTTPException as exc:
        if request.path.startswith("/api/") and exc.content_type != "application/json" and exc.status >= 400:
            return web.json_response({"error": {"type": type(exc).__name__, "message": exc.text or exc.reason}},
                                     status=exc.status)
        raise
    response.headers.setdefault("X-Content-Type-Options", "nosniff")
    response.headers.setdefault("Referrer-Policy", "no-referrer")
    response.headers.setdefault("X-Frame-Options", "DENY")
    return response


async def _body_in_time(request: web.Request, handler: Any) -> web.StreamResponse:
    """Run the handler; a body that has not arrived READ_TIMEOUT_S after the header closes the
    connection (a client trickling its body would hold it, and a descriptor, for ever)."""
    if not request.body_exists:
        return await handler(request)
    cut = False

    def deadline() -> None:
        nonlocal cut
        if not request.content.is_eof() and request.transport is not None:
            cut = True
            log.warning("web_slow_body_closed", peer=request.remote, path=request.path,
                        timeout_s=READ_TIMEOUT_S)
            request.transport.close()

    timer = asyncio.get_running_loop().call_later(READ_TIMEOUT_S, deadline)
    try:
        return await handler(request)
    except ConnectionError:
        if cut:  # the answer has no connection to go to; aiohttp drops it quietly
            raise web.HTTPRequestTimeout(text=f"the request body did not arrive within {READ_TIMEOUT_S:g} s") from None
        raise
    finally:
        timer.cancel()


def _page(name: str) -> Any:
    async def serve(request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC / name, headers={"Cache-Control": "no-cache"})

    return serve


async def _config(request: web.Request) -> web.Response:
    access: Access = request.app[keys.ACCESS]
    service = request.app[keys.SERVICE]
    return web.json_response({"rig": service is not None, "writes": access.writes_enabled,
                              "token_required": access.token is not None,
                              "login_required": access.login_required,
                              "poses": service.controller.rig.n_poses if service is not None else None,
                              "worklist": bool(service is not None and service.site is not None
                                               and service.site.worklist is not None)})


def make_app(store: Path | ScanStore, access: Access, *, service: Any | None = None,
             rig_path: Path | None = None, archive_url: str | None = None) -> web.Application:
    """The application for a scan store; service: the daemon's RigService (None: viewer only);
    archive_url: a DICOMweb archive whose studies the viewer lists and retrieves into the store."""
    if not (THREE / "build" / "three.module.js").is_file():
        raise AssetsMissing(f"{THREE}: three.js is not installed; run ./dev (npm ci in web/)")
    app = web.Application(middlewares=[guard], client_max_size=MAX_REQUEST_BYTES)
    app[keys.ACCESS] = access
    app[keys.SERVICE] = service
    app[keys.LIBRARY] = scans.ScanLibrary(store if isinstance(store, ScanStore) else ScanStore(store), rig_path)
    app[keys.CLOSING] = asyncio.Event()

    async def closing(app: web.Application) -> None:
        app[keys.CLOSING].set()  # event streams end so the server can close

    app.on_shutdown.append(closing)
    app.router.add_get("/", _page("console.html"))
    app.router.add_get("/scans", _page("scans.html"))
    app.router.add_get("/scans/{folder}", _page("viewer.html"))
    app.router.add_get("/api/config", _config)
    login.routes(app)
    scans.routes(app)
    marks.routes(app)
    patients.routes(app)
    rig.routes(app)
    if archive_url is not None:
        from planner.rig import DEFAULT_RIG_PATH, load_rig
        from web import archive

        archive.routes(app, archive_url, load_rig(rig_path or DEFAULT_RIG_PATH))
    app.router.add_static("/static/", STATIC, follow_symlinks=False)
    app.router.add_static("/vendor/three/", THREE, follow_symlinks=False)
    return app
