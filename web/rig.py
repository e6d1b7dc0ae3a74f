"""The operator console's server side: status, the event stream, START / ABORT / RESET.

Every action calls the daemon's control handler (daemon.server.service.RigService), the same object
that serves the control socket and the panel's buttons; refusals come back as 409 with the
handler's error type and message. Events are Server-Sent Events: the recent events first
(``history``: the daemon's bounded buffer, so a console opened mid-scan shows what happened), the
status, then each state change and progress event as the state machine publishes it (each with its
``seq``: the client drops those the history already held), and the status again every
STATUS_PERIOD_S (beam angle, elapsed and remaining time) while the stream is open.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Any

import structlog
from aiohttp import web

from daemon.clinic.patient import PatientError
from daemon.errors import ScanBusy
from daemon.server.control import to_jsonable
from web import keys
from web.marks import read_json
from web.scans import json_error

log = structlog.get_logger("web.rig")
STATUS_PERIOD_S = 0.5


def _service(request: web.Request) -> Any:
    service = request.app[keys.SERVICE]
    if service is None:
        raise json_error(web.HTTPServiceUnavailable, "no rig daemon in this server (viewer only)")
    return service


def _sse(kind: str, data: Any) -> bytes:
    return f"event: {kind}\ndata: {json.dumps(to_jsonable(data), separators=(',', ':'))}\n\n".encode()


async def status(request: web.Request) -> web.Response:
    return web.json_response(to_jsonable(_service(request).status()))


async def events(request: web.Request) -> web.StreamResponse:
    service = _service(request)
    stream = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache",
                                         "X-Accel-Buffering": "no"})
    await stream.prepare(request)
    iterator = aiter(service.subscribe())
    nxt: asyncio.Future[Any] = asyncio.ensure_future(anext(iterator))
    await asyncio.sleep(0)  # subscribed before the snapshot: nothing between the two is lost
    closing: asyncio.Event = request.app[keys.CLOSING]
    stop = asyncio.ensure_future(closing.wait())
    try:
        await stream.write(b"retry: 2000\n\n" + _sse("history", service.recent_events())
                           + _sse("status", service.status()))
        while True:
            done, _ = await asyncio.wait({nxt, stop}, timeout=STATUS_PERIOD_S, return_when=asyncio.FIRST_COMPLETED)
            if stop in done:
                break
            if nxt in done:
                try:
                    event = nxt.result()
                except StopAsyncIteration:
                    break
                await stream.write(_sse("rig", event))
                nxt = asyncio.ensure_future(anext(iterator))
            else:
                await stream.write(_sse("status", service.status()))
    except (ConnectionError, asyncio.CancelledError):
        pass
    finally:
        stop.cancel()
        nxt.cancel()
        with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration):
            await nxt
        await iterator.aclose()
    return stream


async def _act(request: web.Request, action: str) -> web.Response:
    body = await read_json(request)
    service = _service(request)
    try:
        if action == "scan":
            scan_id = body.get("scan_id")
            if scan_id is not None and not isinstance(scan_id, str):
                raise json_error(web.HTTPBadRequest, f"scan_id {str(scan_id)[:40]!r}: a string or absent")
            result = await service.scan(**{k: v for k, v in body.items() if v not in (None, "")})
        elif action == "abort":
            result = service.abort()
        else:
            result = await service.reset()
    except ScanBusy as exc:
        raise json_error(web.HTTPConflict, exc) from exc
    except PatientError as exc:  # names the field, never the value
        raise json_error(web.HTTPBadRequest, exc) from exc
    except web.HTTPException:
        raise
    except Exception as exc:  # the handler's typed refusal (a bad scan id, an illegal transition)
        log.warning("web_command_failed", action=action, error_type=type(exc).__name__, error=str(exc))
        raise json_error(web.HTTPConflict, exc) from exc
    log.info("web_command", action=action, peer=request.remote)
    return web.json_response(to_jsonable(result))


async def worklist(request: web.Request) -> web.Response:
    """Today's worklist (the console picks a patient from it); 404 without a provider, 502 when it
    cannot be asked (the message names the provider and the reason)."""
    from daemon.clinic.dimse import DicomPeerError
    from daemon.server.service import WorklistUnavailable

    service = _service(request)
    try:
        return web.json_response(await service.worklist())
    except WorklistUnavailable as exc:
        raise json_error(web.HTTPNotFound, exc) from exc
    except DicomPeerError as exc:
        log.warning("worklist_failed", error=str(exc))
        raise json_error(web.HTTPBadGateway, exc) from exc


async def start_scan(request: web.Request) -> web.Response:
    return await _act(request, "scan")


async def abort(request: web.Request) -> web.Response:
    return await _act(request, "abort")


async def reset(request: web.Request) -> web.Response:
    return await _act(request, "reset")


def routes(app: web.Application) -> None:
    app.router.add_get("/api/rig/status", status)
    app.router.add_get("/api/rig/events", events)
    app.router.add_get("/api/rig/worklist", worklist)
    app.router.add_post("/api/rig/scan", start_scan)
    app.router.add_post("/api/rig/abort", abort)
    app.router.add_post("/api/rig/reset", reset)
