"""The viewer on a workstation, reading the clinic's archive by DICOMweb (``tbp viewer --dicomweb
URL``): the archive's studies (QIDO-RS) and, on Open, the study retrieved (WADO-RS) into the local
cache store, then shown by the ordinary viewer (archive/reader.py)."""

from __future__ import annotations

from typing import Any

from aiohttp import web

from web import keys
from web.marks import read_json
from web.scans import _off_loop, json_error

ARCHIVE: web.AppKey[Any] = web.AppKey("archive", object)


async def list_studies(request: web.Request) -> web.Response:
    from archive.reader import studies
    from daemon.clinic.dimse import DicomPeerError

    url = request.app[ARCHIVE]
    try:
        found = await _off_loop(studies, url)
    except (DicomPeerError, OSError, ValueError) as exc:
        raise json_error(web.HTTPBadGateway, f"{url}: {exc}") from exc
    except Exception as exc:  # dicomweb-client's HTTP errors (requests): the archive's answer, named
        raise json_error(web.HTTPBadGateway, f"{url}: {type(exc).__name__}: {exc}") from exc
    return web.json_response({"archive": url, "studies": found})


async def open_study(request: web.Request) -> web.Response:
    """Retrieve the study into the cache (once) and answer with its folder for /scans/<folder>."""
    from archive.reader import fetch
    from daemon.clinic.patient import UID

    await read_json(request)
    uid = request.match_info["uid"]
    if not UID.fullmatch(uid) or len(uid) > 64:
        raise json_error(web.HTTPBadRequest, "not a Study Instance UID")
    library = request.app[keys.LIBRARY]
    rig = request.app[RIG]
    try:
        path = await _off_loop(fetch, request.app[ARCHIVE], uid, library.store.root, rig)
    except Exception as exc:  # the archive's refusal or a study this viewer cannot show, named
        raise json_error(web.HTTPBadGateway, f"{type(exc).__name__}: {exc}") from exc
    return web.json_response({"folder": path.name})


RIG: web.AppKey[Any] = web.AppKey("archive_rig", object)


def routes(app: web.Application, url: str, rig: Any) -> None:
    from web.app import _page

    app[ARCHIVE] = url.rstrip("/")
    app[RIG] = rig
    app.router.add_get("/archive", _page("archive.html"))
    app.router.add_get("/api/archive/studies", list_studies)
    app.router.add_post("/api/archive/studies/{uid}/open", open_study)
